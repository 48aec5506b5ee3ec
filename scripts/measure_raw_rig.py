"""Raw calibrated pairs vs rectified input: e_S of each, per generated frame.

    python scripts/measure_raw_rig.py [FIRST_SEED LAST_SEED] [--no-masks] [--views resample]

Each seed's frame is re-imaged by rotated, distorting cameras (tests/rig_support.py: rendered
directly in the raw cameras, or resampled from the rectified pair with ``--views resample``); the raw
pair is rectified in the load step (core/rectify.py) and the curve mapped back to the left
camera's frame; the rectified-input result of the same frame is the reference.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from rig_support import raw_rig  # noqa: E402

from threadrecon.core.metrics import curve_errors  # noqa: E402
from threadrecon.core.pipeline import reconstruct  # noqa: E402
from threadrecon.core.rectify import rectification, rectify_pair, to_left_frame  # noqa: E402
from threadrecon.core.segmentation import StereoPair  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=int, nargs="?", default=10)
    parser.add_argument("last", type=int, nargs="?", default=21)
    parser.add_argument("--no-masks", action="store_true", help="segment the images instead")
    parser.add_argument(
        "--views",
        choices=("render", "resample"),
        default="render",
        help="raw views rendered in the raw cameras (default) or resampled from the rectified pair",
    )
    parser.add_argument(
        "--blur", type=float, default=0.0, help="the optics' blur of both rigs, px (generator)"
    )
    args = parser.parse_args()
    diffs = []
    for seed in range(args.first, args.last + 1):
        rig = raw_rig(seed, views=args.views, blur_sigma=args.blur)
        reference, raw = rig.reference, rig.pair
        if args.no_masks:
            reference, raw = (
                StereoPair(reference.left, reference.right),
                StereoPair(raw.left, raw.right),
            )
        ref = reconstruct(reference, rig.reference_calib)
        rect = rectification(rig.calib)
        rec = reconstruct(rectify_pair(raw, rect), rect.calib)
        if ref.status != "ok" or rec.status != "ok":
            print(f"seed {seed}: failed ({ref.message or rec.message})")
            continue
        e_ref = curve_errors(ref["camera"].points, rig.frame.truth.centerline).e_S
        e_raw = curve_errors(to_left_frame(rec["camera"].points, rect), rig.truth_left).e_S
        diffs.append(abs(e_raw - e_ref))
        print(f"seed {seed}: e_S rectified input {e_ref:.3f} mm, raw rig {e_raw:.3f} mm")
    d = np.array(diffs)
    print(
        f"|difference| median {np.median(d):.3f} mm, max {d.max():.3f} mm, "
        f"within 0.1 mm on {(d < 0.1).sum()} of {len(d)} frames"
    )


if __name__ == "__main__":
    main()
