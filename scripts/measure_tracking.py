"""Tracking vs single-frame on generated sequences (issue 15's "Must show").

    python scripts/measure_tracking.py OUT_DIR --seeds 101 102 103 --frames 60

For every seed and motion (drag, pull, instrument) it writes a sequence with
``generate --sequence``, runs ``track`` with and without tracking (masks given,
or withheld with ``--no-masks``) and prints the
share of good frames and the jitter of each, the jitter over the frame steps where both runs are
good on both frames, and the throughput (frames/s) of each run.

``--reuse MODE`` reads that mode's runs from an earlier call (their ``summary.csv`` in
``OUT_DIR/runs``) instead of running them again, e.g. the single-frame runs when only tracking
changed; their throughput is then not measured. ``--tag`` names this call's runs apart.
"""

from __future__ import annotations

import argparse
import csv
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

MOTIONS = ("drag", "pull", "instrument")


def _run(cmd: list[str]) -> tuple[float, float]:
    """Run ``cmd``; its wall time and CPU time (user + system of the child), s."""
    t0, r0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=False, stdout=subprocess.DEVNULL)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return time.perf_counter() - t0, cpu


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[101])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--motions", nargs="+", default=list(MOTIONS))
    ap.add_argument("--no-masks", action="store_true", help="raw frames: masks withheld")
    ap.add_argument("--reuse", choices=("single", "tracked"), nargs="*", default=[])
    ap.add_argument("--tag", default="", help="suffix of this call's run folders")
    args = ap.parse_args()
    raw = ["--no-masks"] if args.no_masks else []
    py = [sys.executable, "-m", "threadrecon.app.cli"]
    total = {"single": [0, 0], "single_within": [0, 0], "tracked": [0, 0]}
    jit_all: dict[str, list[float]] = {"single": [], "tracked": []}
    jit_own: dict[str, list[float]] = {"single": [], "tracked": []}  # steps good in that run
    rates: dict[str, list[float]] = {"single": [], "tracked": []}
    cpu_rates: dict[str, list[float]] = {"single": [], "tracked": []}  # frames per CPU second
    for seed in args.seeds:
        for motion in args.motions:
            group = f"{motion}_{seed}"
            folder = args.out / "sequences" / group
            if not folder.exists():
                _run(
                    [
                        *py,
                        "generate",
                        str(args.out),
                        "--sequence",
                        str(args.frames),
                        "--motion",
                        motion,
                        "--seed",
                        str(seed),
                        "--group",
                        group,
                    ]
                )
            res = {}
            speed: dict[str, str] = {}
            for mode, extra in (("single", ["--no-tracking"]), ("tracked", [])):
                name = f"{group}_{mode}{'_raw' if raw else ''}"
                if mode in args.reuse:  # this call's tagged run, else the untagged one
                    found = args.out / "runs" / f"{name}{args.tag}" / "summary.csv"
                    if not found.is_file():
                        found = args.out / "runs" / name / "summary.csv"
                    res[mode] = _rows(found)
                    continue
                out = args.out / "runs" / f"{name}{args.tag}"
                dt, cpu = _run([*py, "track", str(folder), "--out", str(out), *extra, *raw])
                rows = _rows(out / "summary.csv")
                rates[mode].append(len(rows) / dt)
                cpu_rates[mode].append(len(rows) / cpu)
                speed[mode] = f"{mode} {len(rows) / cpu:.2f}"
                res[mode] = rows
            s, t = res["single"], res["tracked"]
            gs = [r["good"] == "True" for r in s]
            ws = [r.get("within") == "True" for r in s]  # close enough, "suspect" or not
            total["single_within"][0] += sum(ws)
            total["single_within"][1] += len(ws)
            gt = [r["track_good"] == "True" for r in t]
            total["single"][0] += sum(gs)
            total["single"][1] += len(gs)
            total["tracked"][0] += sum(gt)
            total["tracked"][1] += len(gt)
            both = [k for k in range(1, len(s)) if gs[k] and gs[k - 1] and gt[k] and gt[k - 1]]
            js = [float(s[k]["jitter_mm"]) for k in both]
            jt = [float(t[k]["track_jitter_mm"]) for k in both]
            jit_all["single"] += js
            jit_all["tracked"] += jt
            for mode, g, rows, key in (
                ("single", gs, s, "jitter_mm"),
                ("tracked", gt, t, "track_jitter_mm"),
            ):
                jit_own[mode] += [
                    float(rows[k][key]) for k in range(1, len(rows)) if g[k] and g[k - 1]
                ]
            flagged = sum(r["flagged"] == "True" for r in t)
            print(
                f"{group:>16}: good single {sum(gs)}/{len(gs)} (within {sum(ws)}), "
                f"tracked {sum(gt)}/{len(gt)}; "
                f"jitter (both good, {len(both)} steps) single {np.mean(js):.3f} mm, "
                f"tracked {np.mean(jt):.3f} mm; flagged {flagged}"
                + (f"; frames per CPU s: {', '.join(speed.values())}" if speed else ""),
                flush=True,
            )
    g, n = total["single_within"]
    print(f"single-frame curves within the limits whatever their status: {g}/{n}")
    for mode in ("single", "tracked"):
        g, n = total[mode]
        j = np.array(jit_all[mode])
        o = np.array(jit_own[mode])
        print(
            f"{mode:>8}: good {g}/{n} = {100 * g / n:.1f}%; jitter mean {j.mean():.3f} mm, "
            f"median {np.median(j):.3f} mm over {j.size} steps good in both runs "
            f"(over its own good steps: mean {o.mean():.3f} mm, median {np.median(o):.3f} mm, "
            f"{o.size} steps); "
            + (
                f"median {np.median(rates[mode]):.2f} frames/s wall, "
                f"{np.median(cpu_rates[mode]):.2f} frames per CPU second (incl. start-up)"
                if rates[mode]
                else "rate not measured (runs reused)"
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
