"""Raw calibrated pairs vs rectified input: e_S of each, per generated frame.

    python scripts/measure_raw_rig.py [FIRST_SEED LAST_SEED] [--no-masks | --both] [--blur PX]
        [--views resample|rectified] [--control-noise SIGMA] [--set STAGE.NAME=VALUE ...] [--pixels]

Each seed's frame is seen by rotated, distorting cameras (tests/rig_support.py): the thread
rendered directly in each raw camera (default), or the rectified pair resampled into the raw
cameras (``--views resample``, two resamplings before the pipeline); ``--blur`` gives both rigs
the optics' blur (the generator's ``blur_sigma``, px). The raw pair is rectified in the load step
(core/rectify.py) and the curve mapped back to the left camera's frame; the rectified-input
result of the same frame is the reference. ``--views rectified`` renders the raw rig's rectified
views directly in its rectified cameras instead (no remap): the same rig and frames with a
rectification that loses nothing, the floor of the load step's.

``--control-noise SIGMA`` replaces the raw rig by the rectified input itself with i.i.d. pixel
noise of SIGMA grey levels (same thread, same masks, no rectification): how far the pipeline
moves under a perturbation of that size, the floor the raw rig is measured against.

``--set`` changes a parameter of both runs (e.g. ``--set stereo.epipolar_deg=0``: no continuity
along near-epipolar runs). ``--pixels`` adds, per frame, the stereo stage's disparity error
against the true centreline's (RMS, px) by the thread's angle to the image rows, for the
rectified input and the raw rig (or noisy input): where on the thread disparity moves.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from rig_support import RAW_MARGIN_PX, RawRig, raw_rig, rectified_views  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from threadrecon.app.bench import parse_overrides  # noqa: E402
from threadrecon.app.presets import validate  # noqa: E402
from threadrecon.core.calibration import StereoCalibration  # noqa: E402
from threadrecon.core.metrics import curve_errors  # noqa: E402
from threadrecon.core.pipeline import ReconParams, Reconstruction, reconstruct  # noqa: E402
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
        "--both", action="store_true", help="with masks and without, each frame rendered once"
    )
    parser.add_argument(
        "--views",
        choices=("render", "resample", "rectified"),
        default="render",
        help="raw views rendered in the raw cameras (default) or resampled from the rectified "
        "pair; 'rectified': the raw rig's rectified views rendered directly (no remap)",
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
    parser.add_argument(
        "--set", action="append", default=[], metavar="STAGE.NAME=VALUE", help="a parameter"
    )
    parser.add_argument(
        "--pixels", action="store_true", help="disparity error by thread angle, per frame"
    )
    args = parser.parse_args()
    data = ReconParams().to_dict()
    for stage, values in parse_overrides(args.set).items():
        data[stage].update(values)
    params = validate(data)
    modes = (False, True) if args.both else (args.no_masks,)
    diffs: dict[bool, list[float]] = {m: [] for m in modes}
    for seed in range(args.first, args.last + 1):
        views = "render" if args.views == "rectified" else args.views
        rig = raw_rig(seed, views=views, blur_sigma=args.blur)
        for no_masks in modes:
            diff = _measure(rig, seed, no_masks, args, params)
            if diff is not None:
                diffs[no_masks].append(diff)
    for no_masks in modes:
        d = np.array(diffs[no_masks])
        label = " (images only)" if no_masks else " (with masks)" if args.both else ""
        print(
            f"|difference|{label} median {np.median(d):.3f} mm, max {d.max():.3f} mm, "
            f"within 0.1 mm on {(d < 0.1).sum()} of {len(d)} frames"
        )


def _measure(
    rig: RawRig, seed: int, no_masks: bool, args: argparse.Namespace, params: ReconParams
) -> float | None:
    """One frame's |e_S(raw rig) - e_S(rectified input)|, mm, printed; None if a run failed."""
    tag = " images only" if args.both and no_masks else " with masks" if args.both else ""
    reference = rig.reference
    ref = reconstruct(_images_only(reference, no_masks), rig.reference_calib, params)
    if args.control_noise is None:
        rect = rectification(rig.calib)
        if args.views == "rectified":  # rendered in the rectified cameras: no remap
            pair = _images_only(rectified_views(rig, rect, args.blur), no_masks)
        else:
            pair = rectify_pair(_images_only(rig.pair, no_masks), rect)
        rec = reconstruct(pair, rect.calib, params)
        points = to_left_frame(rec["camera"].points, rect) if rec.status == "ok" else None
        truth = rig.truth_left
        rec_calib, rec_truth = rect.calib, truth @ rect.R1.T  # the rectified left frame
    else:
        render = RenderParams(blur_sigma=args.blur, noise_sigma=args.control_noise)
        thread = ThreadParams(margin_px=RAW_MARGIN_PX)
        noisy = generate_frame(SyntheticParams(thread=thread, render=render), rng=seed)
        pair = StereoPair(noisy.left, noisy.right, reference.mask_left, reference.mask_right)
        rec = reconstruct(_images_only(pair, no_masks), rig.reference_calib, params)
        points = rec["camera"].points if rec.status == "ok" else None
        truth = rig.frame.truth.centerline
        rec_calib, rec_truth = rig.reference_calib, truth
    if ref.status != "ok" or points is None:
        print(f"seed {seed}{tag}: failed ({ref.message or rec.message})")
        return None
    e_ref = curve_errors(ref["camera"].points, rig.frame.truth.centerline).e_S
    e_raw = curve_errors(points, truth).e_S
    what = "raw rig" if args.control_noise is None else "noisy input"
    print(
        f"seed {seed}{tag}: e_S rectified input {e_ref:.3f} mm, {what} {e_raw:.3f} mm, "
        f"|difference| {abs(e_raw - e_ref):.3f} mm"
    )
    if args.pixels:
        for name, run, calib, centreline in (
            ("rectified input", ref, rig.reference_calib, rig.frame.truth.centerline),
            (what, rec, rec_calib, rec_truth),
        ):
            print(f"    {name:15s} disparity RMS error, px, " + _by_angle(run, calib, centreline))
    return abs(e_raw - e_ref)


ANGLES = (0.0, 3.0, 6.0, 10.0, 15.0, 30.0, 90.1)  # deg: classes of the thread's angle to the rows


def _by_angle(run: Reconstruction, calib: StereoCalibration, centreline: np.ndarray) -> str:
    """The stereo stage's disparity error against the true centreline's (the nearest projected
    centreline point of each pixel, rectified left frame), RMS per class of the thread's angle
    to the image rows there; pixels more than 3 px off the projection are left out."""
    stereo = run["stereo"]
    K = calib.K1
    fB = calib.focal * calib.baseline
    z = centreline[:, 2]
    uv = np.stack(
        [K[0, 0] * centreline[:, 0] / z + K[0, 2], K[1, 1] * centreline[:, 1] / z + K[1, 2]], 1
    )
    dist, j = cKDTree(uv).query(stereo.pixels.astype(float))
    tangent = np.gradient(uv, axis=0)[j]
    angle = np.degrees(np.arctan2(np.abs(tangent[:, 1]), np.abs(tangent[:, 0])))
    err = stereo.disparity - fB / z[j]
    out = []
    for lo, hi in zip(ANGLES[:-1], ANGLES[1:], strict=True):
        m = (angle >= lo) & (angle < hi) & (dist <= 3.0)
        rms = f"{np.sqrt(np.mean(err[m] ** 2)):.3f}" if m.any() else "-"
        out.append(f"{lo:g}-{min(hi, 90):g} deg {rms} ({m.sum()})")
    return ", ".join(out)


def _images_only(pair: StereoPair, no_masks: bool) -> StereoPair:
    return StereoPair(pair.left, pair.right) if no_masks else pair


if __name__ == "__main__":
    main()
