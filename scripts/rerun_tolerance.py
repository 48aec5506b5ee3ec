"""Tolerance-level identity of two code versions (issue 13: a speed-up may change figures
below the third significant digit, never a status or a verdict).

    # once per code version (PYTHONPATH selects the package), then compare:
    python scripts/rerun_tolerance.py write before.json DATA_DIR[,DATA_DIR...] [--set S.N=V]
    python scripts/rerun_tolerance.py compare before.json after.json [--tol 1e-3]

Per frame: ``evaluate``'s CSV row (every column but the ms ones) of a full run, and the
check's status, reasons and evidence after the spline re-run (n_ctrl - 1) and the run back
on the same pipeline, as ``threadrecon bench`` and the debugger's sliders run them.
``compare`` requires identical strings (status, verdict, reasons) and numbers equal to the
third significant digit (or both below ``ZERO``: rounding residues of 0), or, for e_S and
the coverage, within ``--tol`` (absolute).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from threadpoolctl import threadpool_limits

from threadrecon.app.bench import with_overrides
from threadrecon.app.dataset import discover, load_frame
from threadrecon.app.evaluation import evaluate_frame
from threadrecon.app.presets import resolve_preset
from threadrecon.core.pipeline import Pipeline

CLOSE = ("e_S", "coverage")  # compared within --tol (absolute) besides to 3 digits
ZERO = 1e-9  # two values both below this are rounding residues of 0 (a bound excursion of
# 1e-14 half-widths at an active constraint): equal, whatever their digits


def _plain(v: Any) -> Any:
    if isinstance(v, float | int | str | bool) or v is None:
        return float(v) if isinstance(v, float) else v
    if isinstance(v, list | tuple):
        return {str(i): _plain(x) for i, x in enumerate(v)}
    try:
        return float(v)
    except (TypeError, ValueError):
        return repr(v)


def _check(rec: Any) -> dict[str, Any]:
    if rec is None or "check" not in rec.runs:
        return {"check": "none"}
    c = rec["check"]
    out = {"check": str(c.status), "reasons": repr(c.reasons)}
    out.update({k: _plain(v) for k, v in c.evidence().items()})
    return out


def write(out: Path, roots: list[str], config: str, overrides: list[str]) -> None:
    params = with_overrides(resolve_preset(config), overrides)
    rows: dict[str, Any] = {}
    changed = replace(params, spline=replace(params.spline, n_ctrl=params.spline.n_ctrl - 1))
    for root in roots:
        for frame in discover(Path(root)):
            key = f"{root}:{frame.id}"
            loaded = load_frame(frame)
            row, _ = evaluate_frame(frame, params, loaded)
            entry = {
                k: _plain(v)
                for k, v in row.items()
                if not (k.startswith("ms_") or k.endswith("_ms"))
            }
            pair, calib, _ = loaded
            pipe = Pipeline(pair, calib, frame.corrections)
            pipe.run(params)
            entry["rerun"] = _check(pipe.run(changed))
            entry["back"] = _check(pipe.run(params))
            rows[key] = entry
            print(key, entry.get("status"), entry.get("check"), file=sys.stderr)
            out.write_text(json.dumps(rows, indent=1, sort_keys=True))  # a frame at a time


def _same(k: str, a: Any, b: Any, tol: float) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        if math.isnan(a) or math.isnan(b):
            return math.isnan(a) and math.isnan(b)
        if a == b or max(abs(a), abs(b)) < ZERO:
            return True
        if any(c in k for c in CLOSE) and abs(a - b) <= tol:
            return True
        return f"{a:.3g}" == f"{b:.3g}"
    return a == b


def _diffs(prefix: str, a: dict[str, Any], b: dict[str, Any], tol: float) -> list[str]:
    out = []
    for k in sorted(set(a) | set(b)):
        if k.startswith("ms_") or k.endswith("_ms"):  # timings
            continue
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += _diffs(f"{prefix}{k}.", va, vb, tol)
        elif not _same(k, va, vb, tol):
            out.append(f"{prefix}{k}: {va!r} -> {vb!r}")
    return out


def compare(before: Path, after: Path, tol: float) -> int:
    a, b = json.loads(before.read_text()), json.loads(after.read_text())
    bad = 0
    for key in sorted(set(a) & set(b)):  # frames both have written
        d = _diffs("", a.get(key, {}), b.get(key, {}), tol)
        if d:
            bad += 1
            print(key, *d, sep="\n  ")
    print(f"{len(a)} / {len(b)} frames, {bad} differ beyond 3 digits (tol {tol:g})")
    return 1 if bad else 0


def main() -> int:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write")
    w.add_argument("out", type=Path)
    w.add_argument("roots")
    w.add_argument("--config", default=None)
    w.add_argument("--set", action="append", default=[], help="STAGE.NAME=VALUE (as bench)")
    c = sub.add_parser("compare")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    c.add_argument("--tol", type=float, default=1e-3)
    args = ap.parse_args()
    with threadpool_limits(1):
        if args.cmd == "write":
            write(args.out, args.roots.split(","), args.config, args.set)
            return 0
        return compare(args.before, args.after, args.tol)


if __name__ == "__main__":
    sys.exit(main())
