"""Before/after identity and CPU time of the check stage (issue 13: a speed-up of the check
changes nothing).

    # once per code version (PYTHONPATH selects the package), then compare:
    python scripts/check_identity.py write before.json DATA_DIR [DATA_DIR ...]
    python scripts/check_identity.py compare before.json after.json
    python scripts/check_identity.py profile DATA_DIR [DATA_DIR ...] [--top 30]

Per frame, for the default preset and for a spline re-run (n_ctrl - 1, the debugger's spline
slider): the check's status, reasons, score, every evidence figure (exact repr), the grasp
point and sha1 hashes of the per-point confidence and expected-error arrays (exact bytes).
``write`` also prints the check's CPU time (best of 3, median over frames) on a new
segmentation (per-segmentation caches cleared) and on a spline re-run (caches warm).
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import pstats
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stage_fingerprint import compare  # noqa: E402  (scripts/, this folder)

from threadrecon.app.dataset import discover, load_frame  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402
from threadrecon.core.check import check_curve  # noqa: E402
from threadrecon.core.check_field import clear_fields  # noqa: E402
from threadrecon.core.pipeline import Pipeline  # noqa: E402

STAGES_IN = ("segment", "stereo", "reliability", "ordering", "bounds", "refine", "camera")


def _h(a: Any) -> str:
    a = np.ascontiguousarray(np.asarray(a))
    return hashlib.sha1(a.tobytes() + f"{a.dtype}{a.shape}".encode()).hexdigest()[:16]


def _fingerprint(chk: Any) -> dict[str, Any]:
    g = chk.grasp
    return {
        "status": chk.status,
        "reasons": list(chk.reasons),
        "score": chk.score,
        "confidence": _h(chk.confidence),
        "expected_error_mm": _h(chk.expected_error_mm),
        "evidence": repr(chk.evidence()),
        "grasp": None
        if g is None
        else [
            _h(g.point),
            repr(g.confidence),
            _h(g.tangent),
            g.index,
            g.from_end,
            repr(g.distance),
        ],
    }


def _frames(roots: list[str]):
    for root in roots:
        for frame in discover(root):
            yield f"{root}:{frame.id}", frame


def _cpu(args: list, calib: Any, params: Any, clear: bool = False, repeat: int = 3) -> float:
    """CPU ms of the check on ``args`` (best of ``repeat``), caches cleared first or not."""
    best = float("inf")
    for _ in range(repeat):
        if clear:
            clear_fields()
        t0 = time.thread_time()
        check_curve(*args, calib, params.check)
        best = min(best, time.thread_time() - t0)
    return 1000.0 * best


def _runs(roots: list[str], params):
    changed = replace(params, spline=replace(params.spline, n_ctrl=params.spline.n_ctrl - 1))
    for key, frame in _frames(roots):
        pair, calib, _ = load_frame(frame)
        pipe = Pipeline(pair, calib)
        rec = pipe.run(params)
        if "check" not in rec.runs:
            yield key, None, None, None
            continue
        args = [rec[s] for s in STAGES_IN]
        rec2 = pipe.run(changed)
        args2 = [rec2[s] for s in STAGES_IN] if "check" in rec2.runs else None
        yield key, (rec, args, calib), (rec2, args2), params


def _write(args: argparse.Namespace) -> None:
    params = resolve_preset(args.config)
    out: dict[str, Any] = {}
    t_new, t_re = [], []
    with threadpool_limits(1):
        for key, first, second, _ in _runs(args.data, params):
            if first is None:
                out[key] = None
                continue
            rec, a1, calib = first
            rec2, a2 = second
            out[key] = {
                "run": _fingerprint(rec["check"]),
                "rerun": _fingerprint(rec2["check"]) if a2 is not None else None,
            }
            t_new.append(_cpu(a1, calib, params, clear=True))
            if a2 is not None:
                check_curve(*a1, calib, params.check)  # caches warm, as in the debugger
                t_re.append(_cpu(a2, calib, params))
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True))
    print(
        f"{len(out)} frames -> {args.out}; check CPU ms (best of 3): new segmentation median "
        f"{np.median(t_new):.2f} p90 {np.percentile(t_new, 90):.2f}; spline re-run median "
        f"{np.median(t_re):.2f} p90 {np.percentile(t_re, 90):.2f}"
    )


def _profile(args: argparse.Namespace) -> None:
    params = resolve_preset(args.config)
    calls = []
    with threadpool_limits(1):
        for _, first, second, _ in _runs(args.data, params):
            if first is not None:
                calls.append((first[1], first[2], second[1]))
    prof = cProfile.Profile()
    for a1, calib, a2 in calls:
        for _ in range(args.repeat):
            if args.rerun:  # the spline re-run's check, caches warm
                check_curve(*a1, calib, params.check)
            else:
                clear_fields()
            prof.enable()
            check_curve(*(a2 if args.rerun and a2 is not None else a1), calib, params.check)
            prof.disable()
    st = pstats.Stats(prof)
    st.sort_stats(args.sort).print_stats(args.top)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write")
    w.add_argument("out")
    w.add_argument("data", nargs="+")
    w.add_argument("--config", default=None)
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    c.add_argument("-v", "--verbose", action="store_true")
    p = sub.add_parser("profile")
    p.add_argument("data", nargs="+")
    p.add_argument("--config", default=None)
    p.add_argument("--top", type=int, default=40)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--sort", default="tottime")
    p.add_argument("--rerun", action="store_true", help="the spline re-run's check")
    args = ap.parse_args()
    if args.cmd == "write":
        _write(args)
        return 0
    if args.cmd == "profile":
        _profile(args)
        return 0
    return compare(args)


if __name__ == "__main__":
    sys.exit(main())
