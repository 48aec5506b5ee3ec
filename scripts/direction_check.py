"""Direction harness (issue 12): every frame reconstructed twice, once as the ordering walked
it and once with that ordering reversed (core/reversal.py) before the stages after it (depth
bounds, spline, refinement, camera, check), and the two curves compared.

    python scripts/direction_check.py --seed 8130 [--count 20] [--suite spiral ...]
        [--mode output|walk] [--dev /work/shared/data/paper-dataset] [--set stage.name=value]
        [--csv out.csv]

Mode "walk" reverses the walk inside the ordering stage instead (its end extension, the gap
pixels' links and the tips' disparities are then computed for the reversed walk too). Mode
"start" walks from the other end of the chosen walk (the greedy walk's own dependence on its
start: another path, not the same one reversed).

Per frame: the distance between the two curves (mm; each curve's points to the other curve's
polyline, max and mean over both ways), e_S, e_S^max, length error and status both ways. Per
suite: the median and max of the max difference, the frames with a difference over 0.1 mm,
and the right/good counts both ways (as scripts/hard_suites.py scores them).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from threadrecon.app.bench import with_overrides  # noqa: E402
from threadrecon.app.dataset import discover, evaluate_reconstruction, load_frame  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402
from threadrecon.core import ordering  # noqa: E402
from threadrecon.core.pipeline import (  # noqa: E402
    STAGE_TABLE,
    STAGES,
    Pipeline,
    Reconstruction,
    StageError,
    StageRun,
    _describe,
)
from threadrecon.core.reversal import reversed_ordering  # noqa: E402
from threadrecon.core.segmentation import StereoPair  # noqa: E402
from threadrecon.core.synthetic import SyntheticParams, generate_frame  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from hard_suites import GOOD_MM, SUITES  # noqa: E402

DIFF_MM = 0.1  # a frame whose two curves lie further apart than this counts as asymmetric


@contextlib.contextmanager
def _walks_reversed():
    """The ordering stage with its walk (the keypoint order the walk chose) reversed before
    everything the stage does after the walk: end extension, gap pixels' links, tips."""
    saved = ordering._bending_walk, ordering._best_walk, ordering._explain

    def explain(*a, **k):  # the walk's replay of its decisions does not hold reversed
        try:
            return saved[2](*a, **k)
        except ValueError:
            return ()

    ordering._bending_walk = lambda *a, **k: saved[0](*a, **k)[::-1]
    ordering._best_walk = lambda *a, **k: saved[1](*a, **k)[::-1]
    ordering._explain = explain
    try:
        yield
    finally:
        ordering._bending_walk, ordering._best_walk, ordering._explain = saved


@contextlib.contextmanager
def _walks_from_other_end():
    """The ordering stage with its bending walk started at the chosen walk's last keypoint
    (no runner-up branches): where the greedy walk itself depends on its start."""
    saved = ordering._bending_walk

    def other(g, p):
        w = saved(g, p)
        if len(w) < 2:
            return w
        return ordering._walk_from([w[-1]], [], None, g, p)[0]

    ordering._bending_walk = other
    try:
        yield
    finally:
        ordering._bending_walk = saved


def reversed_walk_run(pipe: Pipeline, rec: Reconstruction, params, start: bool = False):
    """The whole pipeline once more with the ordering's walk reversed (mode "walk") or walked
    from the other end (mode "start")."""
    with _walks_from_other_end() if start else _walks_reversed():
        return Pipeline(pipe.pair, pipe.calib).run(params)


def reversed_run(pipe: Pipeline, rec: Reconstruction, params) -> Reconstruction:
    """The stages after the ordering once more, on the reversed ordering of ``rec``."""
    if "ordering" not in rec.runs:
        return rec
    results = {s: rec[s] for s in STAGES[: STAGES.index("ordering")]}
    results["ordering"] = reversed_ordering(rec["ordering"])
    runs = {s: StageRun(s, results[s], 0.0, True) for s in results}
    sources = {"pair": pipe.pair, "calib": pipe.calib}
    for st in STAGE_TABLE[STAGES.index("ordering") + 1 :]:
        try:
            out = st.run(*({**sources, **results}[i] for i in st.inputs), getattr(params, st.name))
        except Exception as exc:  # as the pipeline reports it
            err = exc if isinstance(exc, StageError) else StageError(st.name, _describe(exc))
            return Reconstruction(runs, err.stage, err.reason, params)
        results[st.name] = out
        runs[st.name] = StageRun(st.name, out, 0.0, False)
    return Reconstruction(runs, None, None, params)


def _dense(points: np.ndarray, step: float) -> np.ndarray:
    """The polyline through ``points`` resampled every ``step`` (at most) of its arc length."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(np.ceil(s[-1] / step)) + 1)
    u = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(u, s, points[:, j]) for j in range(3)])


def curve_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(max, mean) distance between two curves (N, 3), both ways, in their unit."""
    # each polyline resampled every 1e-5 of its length: distances to it within 5e-6 of that
    da = cKDTree(_dense(b, 1e-5 * _length(b) + 1e-12)).query(a)[0]
    db = cKDTree(_dense(a, 1e-5 * _length(a) + 1e-12)).query(b)[0]
    both = np.concatenate([da, db])
    return float(both.max()), float(both.mean())


def _length(p: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def compare(pair: StereoPair, calib, truth, params, mode: str = "output") -> dict:
    pipe = Pipeline(pair, calib)
    fwd = pipe.run(params)
    if mode == "output":
        bwd = reversed_run(pipe, fwd, params)
    else:
        bwd = reversed_walk_run(pipe, fwd, params, start=mode == "start")
    row: dict = {}
    for tag, rec in (("fwd", fwd), ("bwd", bwd)):
        m = evaluate_reconstruction(rec, calib, truth)
        right = (
            rec.status != "failed"
            and abs(m["e_length_mm"]) <= GOOD_MM
            and m["e_S_max_mm"] <= GOOD_MM
        )
        row.update(
            {
                f"status_{tag}": rec.status,
                f"good_{tag}": bool(right and rec.status == "ok"),
                f"e_S_{tag}": m["e_S_mm"],
                f"e_max_{tag}": m["e_S_max_mm"],
                f"e_len_{tag}": m["e_length_mm"],
                f"reason_{tag}": rec.message or "",
            }
        )
    if "camera" in fwd.runs and "camera" in bwd.runs:
        mm = calib.mm_per_unit
        dmax, dmean = curve_difference(fwd["camera"].points * mm, bwd["camera"].points * mm)
    else:
        dmax = dmean = float("nan")
    row.update(diff_max=dmax, diff_mean=dmean)
    return row


def suite_rows(name: str, seed: int, count: int, params, mode: str) -> list[dict]:
    _, thread, render = SUITES[name]
    syn = SyntheticParams(thread=thread, render=render)
    calib = syn.camera.calibration()
    rows = []
    for k in range(1, count + 1):
        frame = generate_frame(syn, np.random.default_rng([seed, k]))
        pair = StereoPair(frame.left, frame.right, frame.mask_left, frame.mask_right)
        rows.append(
            dict(suite=name, seed=seed, frame=k)
            | compare(pair, calib, frame.truth.centerline, params, mode)
        )
    return rows


def dev_rows(root: str, params, mode: str) -> list[dict]:
    rows = []
    for fr in discover(root):
        pair, calib, gt = load_frame(fr)
        rows.append(
            dict(suite=fr.kind, seed=0, frame=fr.name) | compare(pair, calib, gt, params, mode)
        )
    return rows


def summary(name: str, rows: list[dict]) -> str:
    d = np.array([r["diff_max"] for r in rows])
    asym = [r for r in rows if not (r["diff_max"] <= DIFF_MM)]
    flips = [
        r for r in rows if r["good_fwd"] != r["good_bwd"] or r["status_fwd"] != r["status_bwd"]
    ]
    gf = sum(r["good_fwd"] for r in rows)
    gb = sum(r["good_bwd"] for r in rows)
    return (
        f"{name:16s} n={len(rows):3d} diff median {np.nanmedian(d):7.3f} max {np.nanmax(d):7.3f} mm"
        f"  >{DIFF_MM}: {len(asym):2d}  good fwd/bwd {gf}/{gb}  status flips: "
        + ", ".join(
            f"{r['frame']}({r['status_fwd']}/{r['status_bwd']}, {r['diff_max']:.2f})" for r in flips
        )
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, action="append", default=[])
    ap.add_argument("--count", type=int, default=20)
    ap.add_argument("--suite", action="append", choices=sorted(SUITES), default=None)
    ap.add_argument("--dev", default=None, help="also the paper dataset's frames at this root")
    ap.add_argument(
        "--mode",
        choices=("output", "walk", "start"),
        default="output",
        help="output: the ordering's result reversed (the stages after it); walk: the walk "
        "reversed inside the ordering (its end extension and gap links too); start: the "
        "bending walk started at the other end of the chosen walk",
    )
    ap.add_argument("--config", default=None)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--csv", default=None)
    args = ap.parse_args()
    params = with_overrides(resolve_preset(args.config), args.set)
    all_rows: list[dict] = []
    with threadpool_limits(1):
        for seed in args.seed:
            for name in args.suite or list(SUITES):
                rows = suite_rows(name, seed, args.count, params, args.mode)
                all_rows += rows
                print(summary(f"{seed} {name}", rows), flush=True)
        if args.dev:
            rows = dev_rows(args.dev, params, args.mode)
            all_rows += rows
            for kind in ("simulated", "real"):
                sel = [r for r in rows if r["suite"] == kind]
                if sel:
                    print(summary(f"dev {kind}", sel), flush=True)
    if all_rows:
        d = np.array([r["diff_max"] for r in all_rows])
        print(
            f"all: n={len(all_rows)} diff median {np.nanmedian(d):.3f} mean {np.nanmean(d):.3f}"
            f" max {np.nanmax(d):.3f} mm, > {DIFF_MM} mm: {int(np.sum(~(d <= DIFF_MM)))}"
        )
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(all_rows[0]))
            w.writeheader()
            w.writerows(all_rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
