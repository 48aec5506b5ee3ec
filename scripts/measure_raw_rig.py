"""Raw calibrated pairs vs rectified input: e_S of each, per generated frame.

    python scripts/measure_raw_rig.py [FIRST_SEED LAST_SEED] [--no-masks] [--blur PX]
        [--views resample] [--control-noise SIGMA]

Each seed's frame is seen by rotated, distorting cameras (tests/rig_support.py): the thread
rendered directly in each raw camera (default), or the rectified pair resampled into the raw
cameras (``--views resample``, two resamplings before the pipeline); ``--blur`` gives both rigs
the optics' blur (the generator's ``blur_sigma``, px). The raw pair is rectified in the load step
(core/rectify.py) and the curve mapped back to the left camera's frame; the rectified-input
result of the same frame is the reference.

``--control-noise SIGMA`` replaces the raw rig by the rectified input itself with i.i.d. pixel
noise of SIGMA grey levels (same thread, same masks, no rectification): how far the pipeline
moves under a perturbation of that size, the floor the raw rig is measured against.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from rig_support import RAW_MARGIN_PX, raw_rig  # noqa: E402

from threadrecon.core.metrics import curve_errors  # noqa: E402
from threadrecon.core.pipeline import reconstruct  # noqa: E402
from threadrecon.core.rectify import rectification, rectify_pair, to_left_frame  # noqa: E402
from threadrecon.core.segmentation import StereoPair  # noqa: E402
from threadrecon.core.synthetic import (  # noqa: E402
    RenderParams,
    SyntheticParams,
    ThreadParams,
    generate_frame,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=int, nargs="?", default=50)
    parser.add_argument("last", type=int, nargs="?", default=61)
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
    parser.add_argument(
        "--control-noise",
        type=float,
        default=None,
        metavar="SIGMA",
        help="instead of the raw rig: the rectified input with i.i.d. noise, grey levels",
    )
    args = parser.parse_args()
    diffs = []
    for seed in range(args.first, args.last + 1):
        rig = raw_rig(seed, views=args.views, blur_sigma=args.blur)
        reference = rig.reference
        ref = reconstruct(_images_only(reference, args.no_masks), rig.reference_calib)
        if args.control_noise is None:
            rect = rectification(rig.calib)
            raw = _images_only(rig.pair, args.no_masks)
            rec = reconstruct(rectify_pair(raw, rect), rect.calib)
            points = to_left_frame(rec["camera"].points, rect) if rec.status == "ok" else None
            truth = rig.truth_left
        else:
            render = RenderParams(blur_sigma=args.blur, noise_sigma=args.control_noise)
            thread = ThreadParams(margin_px=RAW_MARGIN_PX)
            noisy = generate_frame(SyntheticParams(thread=thread, render=render), rng=seed)
            pair = StereoPair(noisy.left, noisy.right, reference.mask_left, reference.mask_right)
            rec = reconstruct(_images_only(pair, args.no_masks), rig.reference_calib)
            points = rec["camera"].points if rec.status == "ok" else None
            truth = rig.frame.truth.centerline
        if ref.status != "ok" or points is None:
            print(f"seed {seed}: failed ({ref.message or rec.message})")
            continue
        e_ref = curve_errors(ref["camera"].points, rig.frame.truth.centerline).e_S
        e_raw = curve_errors(points, truth).e_S
        diffs.append(abs(e_raw - e_ref))
        what = "raw rig" if args.control_noise is None else "noisy input"
        print(
            f"seed {seed}: e_S rectified input {e_ref:.3f} mm, {what} {e_raw:.3f} mm, "
            f"|difference| {abs(e_raw - e_ref):.3f} mm"
        )
    d = np.array(diffs)
    print(
        f"|difference| median {np.median(d):.3f} mm, max {d.max():.3f} mm, "
        f"within 0.1 mm on {(d < 0.1).sum()} of {len(d)} frames"
    )


def _images_only(pair: StereoPair, no_masks: bool) -> StereoPair:
    return StereoPair(pair.left, pair.right) if no_masks else pair


if __name__ == "__main__":
    main()
