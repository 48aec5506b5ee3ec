"""Where along the thread a reconstruction's errors lie, frame by frame (issue 12, dev split).

    python scripts/where_errors.py [DATA_DIR] [--config PRESET] [--ends]

For every frame with 3D ground truth: e_S, e_S^max and where the largest error lies along the
true curve (arc fraction 0..1), the signed length error, and how the ends compare with the
truth: the 2D gap in px between each reconstructed end and the true end in the left image
(does the curve reach the thread's end?) and the depth error there, mm (is the end at the
right depth?). Also the mean 2D distance, px, of the curve to the truth in the left image,
which separates a wrong image curve from a wrong depth. Frames are scored against the part of
the true curve visible in both views, as ``threadrecon evaluate`` does.

Frames without ground truth (the real ones) get one line per view: mean and max reprojection
error, px, where the max lies along the curve (arc fraction: 0 and 1 are its ends) and its
pixel, the coverage, and where the uncovered skeleton pixels lie: how many are nearest to the
curve's first or last point (beyond an end: thread the curve does not reach) and how many
nearest to its inside. Both kinds of frame also show the disparity of each end of the curve
against the tip matched in both views (``Ordering.end_disparity``, core/ends.py).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from threadrecon.app.dataset import discover, load_frame, reprojections  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402
from threadrecon.core.metrics import (  # noqa: E402
    COVERAGE_PX,
    project,
    resample,
    skeleton,
    visible_part,
)
from threadrecon.core.pipeline import Pipeline  # noqa: E402

DEFAULT_DATA = "/work/shared/data/paper-dataset"


def frame_row(points: np.ndarray, gt: np.ndarray, calib) -> dict[str, float]:
    """Error location figures of one reconstruction (N, 3) against its truth (M, 3), both in
    calibration units, in the left camera frame."""
    s = calib.mm_per_unit
    gt = visible_part(gt, calib.P1, calib.P2, calib.image_size)
    a, b = resample(points * s), resample(gt * s)
    d_ab, i_ab = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    arc = lambda p: float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())  # noqa: E731
    worst = int(np.argmax(d_ba)) if d_ba.max() >= d_ab.max() else int(i_ab[np.argmax(d_ab)])
    uv_a, uv_b = project(a / s, calib.P1), project(b / s, calib.P1)
    if np.linalg.norm(uv_a[0] - uv_b[0]) > np.linalg.norm(uv_a[0] - uv_b[-1]):
        a, uv_a = a[::-1], uv_a[::-1]  # the reconstruction in the truth's direction
    d2, k2 = cKDTree(uv_b).query(uv_a)
    row = dict(
        e_S=0.5 * (d_ab.mean() + d_ba.mean()),
        e_S_max=max(d_ab.max(), d_ba.max()),
        at=worst / (len(b) - 1),
        e_len=arc(a) - arc(b),
        mean_2d_px=float(d2.mean()),
    )
    for name, e in (("start", 0), ("end", -1)):
        row[f"{name}_gap_px"] = float(np.linalg.norm(uv_a[e] - uv_b[e]))
        row[f"{name}_dz_mm"] = float(a[e, 2] - b[k2[e], 2])
    return row


def view_rows(rec, calib) -> list[str]:
    """Per view of a frame: where its reprojection error and its uncovered thread lie."""
    pts = rec["camera"].points
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    arc /= max(arc[-1], 1e-12)
    lifted = rec["segment"]
    out = []
    for side, (uv, r) in reprojections(pts, calib, lifted).items():
        mask = lifted.P_L if side == "left" else lifted.P_R
        ys, xs = np.nonzero(mask)
        d = cKDTree(np.column_stack([xs, ys])).query(uv)[0]
        i = int(np.argmax(d))
        sy, sx = np.nonzero(skeleton(mask))
        sk = np.column_stack([sx, sy])
        dense = resample(uv, max(2000, 4 * len(uv)))
        uncovered = sk[cKDTree(dense).query(sk)[0] > COVERAGE_PX]
        near = cKDTree(uv).query(uncovered)[1] if len(uncovered) else np.zeros(0, int)
        beyond = int(np.sum((near == 0) | (near == len(uv) - 1)))
        out.append(
            f"  {side:5s} mean {r.mean:.3f} max {r.max:5.2f} px at arc {arc[i]:.2f} "
            f"({uv[i, 0]:.0f}, {uv[i, 1]:.0f}) | coverage {r.coverage:.3f}: {len(uncovered)} "
            f"skeleton px uncovered, {beyond} beyond an end, {len(uncovered) - beyond} inside"
        )
    return out


def end_rows(rec, calib) -> str:
    """The disparity of each end of the curve against the tip matched in both views."""
    pts = rec["camera"].points
    uv_l, uv_r = project(pts, calib.P1), project(pts, calib.P2)
    o = rec["ordering"]
    parts = []
    for name, row in (("start", 0), ("end", 1)):
        tip = o.path_px[0 if row == 0 else -1, :2]
        k = 0 if np.linalg.norm(uv_l[0] - tip) <= np.linalg.norm(uv_l[-1] - tip) else -1
        d_tip, var = o.end_disparity[row]
        parts.append(
            f"{name}: curve d {uv_l[k, 0] - uv_r[k, 0]:6.2f} px, tip d {d_tip:6.2f} "
            f"+- {np.sqrt(var):.2f} px"
        )
    return "  ends " + " | ".join(parts)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=DEFAULT_DATA)
    ap.add_argument("--config", default=None, help="preset name or TOML path (default: default)")
    ap.add_argument("--ends", action="store_true", help="also the ends' tip disparities")
    args = ap.parse_args()
    params = resolve_preset(args.config)
    print(
        "frame                 e_S   max    at  len err  2D px | start gap px  dz mm "
        "| end gap px  dz mm"
    )
    for frame in discover(args.data):
        pair, calib, gt = load_frame(frame)
        rec = Pipeline(pair, calib).run(params)
        if "camera" not in rec.runs:
            print(f"{frame.name:20s} failed: {rec.message}")
            continue
        if gt is None:
            print(f"{frame.name:20s} (no ground truth: reprojection, {rec.status})")
            print("\n".join([*view_rows(rec, calib), end_rows(rec, calib)]), flush=True)
            continue
        r = frame_row(rec["camera"].points, gt, calib)
        print(
            f"{frame.name:20s} {r['e_S']:5.2f} {r['e_S_max']:5.2f} {r['at']:5.2f} "
            f"{r['e_len']:+8.2f} {r['mean_2d_px']:6.2f} | {r['start_gap_px']:12.1f} "
            f"{r['start_dz_mm']:+6.2f} | {r['end_gap_px']:10.1f} {r['end_dz_mm']:+6.2f}",
            flush=True,
        )
        if args.ends:
            print(end_rows(rec, calib), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
