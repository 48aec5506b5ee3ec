"""One-pixel stability (issues 10-12): how far one pixel of a mask moves the curve.

    python scripts/pixel_check.py --seed 20253 [--count 12] [--suite distractors ...]
        [--flips 4] [--view 0|1] [--near] [--only K ...] [--csv out.csv]

Each raw frame of ``scripts/eval_suites.py`` (seed, suite, frame k) is segmented once and
reconstructed on its masks; then, ``--flips`` times, one pixel on the boundary of one view's
mask (inside or just outside it; the view at random unless ``--view``), at least 20 px from the
path's ends in that view, is flipped and the rest of the pipeline run again on the changed
masks. ``--near``: only pixels within 6 px of a point of the path (in that view). The pixels
are drawn from a generator seeded with [seed, suite, k, 7]: the same flips on every branch.

Per flip: the largest distance between the two curves (mm; each curve's points to the other's
polyline, both ways, as ``scripts/direction_check.py``), both statuses and e_S^max; at the end
the median and largest distance and the flips over 0.1 and 1 mm.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from threadrecon.core.metrics import frame_errors  # noqa: E402
from threadrecon.core.pipeline import Pipeline, ReconParams  # noqa: E402
from threadrecon.core.segmentation import StereoPair, segment  # noqa: E402
from threadrecon.core.synthetic import SyntheticParams, generate_frame  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from direction_check import curve_difference  # noqa: E402
from eval_suites import SUITES  # noqa: E402

END_PX = 20.0  # flips at least this far from the path's ends (in the flipped view)
NEAR_PX = 6.0  # --near: flips at most this far from a point of the path


def _run(frame, calib, params, P_L: np.ndarray, P_R: np.ndarray):
    rec = Pipeline(StereoPair(frame.left, frame.right, P_L, P_R), calib).run(params)
    if "camera" not in rec.runs:
        return rec, None, None
    pts = rec["camera"].points
    return rec, pts, frame_errors(pts, frame.truth.centerline, calib)


def boundary(P: np.ndarray) -> np.ndarray:
    """(n, 2) rows and columns of the mask's pixels with a 4-neighbour outside it and of the
    pixels outside it with a 4-neighbour inside."""
    inner = P.copy()
    inner[1:-1, 1:-1] &= P[:-2, 1:-1] & P[2:, 1:-1] & P[1:-1, :-2] & P[1:-1, 2:]
    grown = P.copy()
    grown[1:-1, 1:-1] |= P[:-2, 1:-1] | P[2:, 1:-1] | P[1:-1, :-2] | P[1:-1, 2:]
    return np.argwhere((P & ~inner) | (grown & ~P))


def frame_rows(name: str, seed: int, k: int, args, params) -> list[dict]:
    si = list(SUITES).index(name)
    tp, rp = SUITES[name]
    frame = generate_frame(
        SyntheticParams(thread=tp, render=rp), np.random.default_rng([seed, si, k])
    )
    calib = frame.camera.calibration()
    try:
        seg = segment(StereoPair(frame.left, frame.right), params.segment)
    except ValueError:  # no thread found: nothing to move
        return []
    rec0, p0, e0 = _run(frame, calib, params, seg.P_L, seg.P_R)
    if p0 is None:
        return []
    path = rec0["ordering"].path_px
    rng = np.random.default_rng([seed, si, k, 7])
    rows = []
    for f in range(args.flips):
        view = int(rng.integers(2)) if args.view is None else args.view
        cand = boundary((seg.P_L, seg.P_R)[view])
        x = path[:, 0] - (view == 1) * np.asarray(frame.camera.disparity(path[:, 2]))
        dx = cand[:, 1, None] - x[None, :]
        dy = cand[:, 0, None] - path[None, :, 1]
        dist = np.hypot(dx, dy)
        keep = np.minimum(dist[:, 0], dist[:, -1]) >= END_PX
        if args.near:
            keep &= dist.min(axis=1) <= NEAR_PX
        cand = cand[keep]
        if not len(cand):
            continue
        y, xx = cand[int(rng.integers(len(cand)))]
        masks = [seg.P_L.copy(), seg.P_R.copy()]
        masks[view][y, xx] = ~masks[view][y, xx]
        rec1, p1, e1 = _run(frame, calib, params, *masks)
        diff = curve_difference(p0, p1)[0] if p1 is not None else float("inf")
        rows.append(
            dict(suite=name, k=k, flip=f, view=view, row=int(y), col=int(xx), diff_mm=diff,
                 status=rec0.status, status_flipped=rec1.status, e_S_max=e0.e_S_max,
                 e_S_max_flipped=e1.e_S_max if e1 is not None else float("nan"))
        )  # fmt: skip
        print(
            f"  {name} #{k} flip {f}: view {view} ({y}, {xx}) {rec0.status} -> "
            f"{rec1.status}, {diff:.3f} mm, e_S^max {rows[-1]['e_S_max']:.2f} -> "
            f"{rows[-1]['e_S_max_flipped']:.2f} mm",
            flush=True,
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--count", type=int, default=12)
    ap.add_argument("--suite", action="append", choices=sorted(SUITES))
    ap.add_argument("--only", type=int, action="append", help="only frame K (from 1)")
    ap.add_argument("--flips", type=int, default=4)
    ap.add_argument("--view", type=int, choices=(0, 1))
    ap.add_argument("--near", action="store_true")
    ap.add_argument("--csv", type=Path)
    args = ap.parse_args(argv)
    threadpool_limits(limits=1, user_api="blas")
    params = ReconParams()
    names = args.suite or [n for n in SUITES if not n.startswith("empty")]
    rows = []
    for name in names:
        for k in args.only or range(1, args.count + 1):
            rows += frame_rows(name, args.seed, k, args, params)
    if not rows:
        print("no flips")
        return 1
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    d = np.array([r["diff_mm"] for r in rows])
    flips = sum(r["status"] != r["status_flipped"] for r in rows)
    print(
        f"{len(d)} flips: median {np.median(d):.4f} mm, max {d.max():.2f} mm, "
        f"> 0.1 mm {int((d > 0.1).sum())}, > 1 mm {int((d > 1).sum())}, status changed {flips}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
