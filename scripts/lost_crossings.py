"""Crossing frames whose masks lost the crossing's pixels: the generator's crossing frames with
their exact masks, a disk erased at the self-crossing in both views (as a raw mask that misses
where the strands cross), reconstructed in memory.

    python scripts/lost_crossings.py --seed 777 --count 20 [--radius 4] [--background tissue]

Frame k (from 0) is ``generate_frame(params, default_rng([seed, k]))``. The crossing is the
closest approach, in each view, of two samples of the true centreline at least ``SEPARATION``
samples apart along it. Good: status ok, |length error| <= 20 mm, e_S^max <= 20 mm.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from threadrecon.core.metrics import frame_errors  # noqa: E402
from threadrecon.core.pipeline import Pipeline, ReconParams  # noqa: E402
from threadrecon.core.segmentation import StereoPair  # noqa: E402
from threadrecon.core.synthetic import (  # noqa: E402
    RenderParams,
    SyntheticParams,
    ThreadParams,
    generate_frame,
)

GOOD_MM = 20.0  # |length error| and max error limits of a good frame, mm (issue 10)
SEPARATION = 40  # samples (0.25 mm each): two samples nearer along the curve are no crossing


def crossing_px(uv: np.ndarray) -> np.ndarray:
    """(x, y) px midway between the two samples of ``uv`` ((M, 2) px) at least
    ``SEPARATION`` apart along the curve that lie closest in the image."""
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    i, j = np.indices(d.shape)
    d[np.abs(i - j) < SEPARATION] = np.inf
    a, b = np.unravel_index(np.argmin(d), d.shape)
    return (uv[a] + uv[b]) / 2


def lose_crossing(frame, radius: float) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """The frame's exact masks without the pixels within ``radius`` px of the crossing."""
    uv_left, uv_right = frame.camera.project(frame.truth.centerline)
    out = []
    for mask, uv in ((frame.mask_left, uv_left), (frame.mask_right, uv_right)):
        cx, cy = crossing_px(uv)
        yy, xx = np.indices(mask.shape)
        out.append(mask & ((xx - cx) ** 2 + (yy - cy) ** 2 > radius**2))
    return out[0], out[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--count", type=int, default=20)
    ap.add_argument("--radius", type=float, default=4.0, help="erased disk, px")
    ap.add_argument("--background", choices=("flat", "tissue"), default="flat")
    args = ap.parse_args(argv)
    params = SyntheticParams(
        thread=ThreadParams(crossing=True), render=RenderParams(background=args.background)
    )
    good, rows = 0, []
    for k in range(args.count):
        frame = generate_frame(params, np.random.default_rng([args.seed, k]))
        mask_left, mask_right = lose_crossing(frame, args.radius)
        calib = frame.camera.calibration()
        rec = Pipeline(StereoPair(frame.left, frame.right, mask_left, mask_right), calib).run(
            ReconParams()
        )
        if "camera" in rec.runs:
            e = frame_errors(rec["camera"].points, frame.truth.centerline, calib)
            ok = rec.status == "ok" and e.e_length <= GOOD_MM and e.e_S_max <= GOOD_MM
            rows.append(f"{k}:{rec.status}:{e.e_S_max:.1f}")
        else:
            ok = False
            rows.append(f"{k}:{rec.status}")
        good += ok
    print(f"radius {args.radius:g} px, {args.background}: good {good}/{args.count}")
    print(" ".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
