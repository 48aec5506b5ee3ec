"""Raw-frame benchmark: each suite's frames reconstructed with the exact masks and with the masks
withheld (the segmentation finds the thread), in memory, from the generator.

    python scripts/eval_suites.py --seed 7 --count 20 [--suite tissue ...] [--csv out.csv]

Per suite: % good frames (status ok, |length error| <= 20 mm, max error <= 20 mm) without
masks, how many frames came back "ok" but not good (a wrong curve, or one where there is no
thread), mean e_S without / with masks over the frames good in both, mask IoU against the exact
mask (thread pixels, both views), median segmentation time and median pipeline time; 'seen':
good frames among those with no end of the true thread hidden under an occluder by more than
20 mm (``metrics.hidden_ends``), which no method can recover. The
``empty-*`` suites hold no thread (a sub-pixel one): good there is "no thread found". Frame k of
a suite is drawn with ``default_rng([seed, suite_index, k])``: use seeds you did not tune on.
The same frames on disk: ``threadrecon generate`` with the flags in SUITES, then
``threadrecon evaluate DIR --no-masks``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from threadrecon.core.calibration import StereoCalibration  # noqa: E402
from threadrecon.core.metrics import frame_errors, hidden_ends  # noqa: E402
from threadrecon.core.pipeline import Pipeline, ReconParams  # noqa: E402
from threadrecon.core.segmentation import StereoPair, segment  # noqa: E402
from threadrecon.core.synthetic import (  # noqa: E402
    RenderParams,
    StereoCamera,
    SyntheticParams,
    ThreadParams,
    generate_frame,
)

GOOD_MM = 20.0  # |length error| and max error limits of a good frame, mm (issue 10)
TISSUE = RenderParams(background="tissue", noise_sigma=2.0, blur_sigma=0.5)

SUITES: dict[str, tuple[ThreadParams, RenderParams]] = {
    "tissue": (ThreadParams(), TISSUE),
    "tissue+occlusion": (ThreadParams(), replace(TISSUE, occlusion=True)),
    "tissue+leaving": (ThreadParams(leaves_image=True), TISSUE),
    "tissue+crossing": (ThreadParams(crossing=True), TISSUE),
    "noisy-flat": (ThreadParams(), RenderParams(noise_sigma=6.0, blur_sigma=0.7)),
    "distractors": (ThreadParams(), replace(TISSUE, distractors=8)),
    "instrument": (ThreadParams(), replace(TISSUE, instrument=True)),
    "colours": (ThreadParams(), replace(TISSUE, thread_colour="random")),
    "thin-1-2px": (ThreadParams(diameter_mm=0.16), TISSUE),
    "lighting": (ThreadParams(), replace(TISSUE, lighting=0.6)),
    "jpeg": (ThreadParams(), replace(TISSUE, noise_sigma=3.0, jpeg_quality=60)),
    "specular": (ThreadParams(), replace(TISSUE, specular=0.4)),
    "all": (
        ThreadParams(),
        replace(
            TISSUE,
            thread_colour="random",
            distractors=6,
            instrument=True,
            lighting=0.5,
            jpeg_quality=75,
            specular=0.3,
            noise_sigma=3.0,
        ),
    ),
}
NO_THREAD = ThreadParams(diameter_mm=1e-6)  # covers no pixel: a thread-free frame
SUITES |= {
    "empty-tissue": (NO_THREAD, TISSUE),
    "empty-lighting": (NO_THREAD, replace(TISSUE, lighting=0.6)),
    "empty-jpeg": (NO_THREAD, replace(TISSUE, noise_sigma=3.0, jpeg_quality=60)),
    "empty-distractors": (NO_THREAD, replace(TISSUE, distractors=8)),
    "empty-instrument": (NO_THREAD, replace(TISSUE, instrument=True)),
}
# Appended last so that the suites above keep their index (and frames) of earlier runs.
SUITES |= {
    "flat+occlusion": (ThreadParams(), RenderParams(occlusion=True)),
    "flat+instrument": (ThreadParams(), RenderParams(instrument=True)),
}


def calibration_for(camera: StereoCamera) -> StereoCalibration:
    """The :class:`StereoCalibration` of a synthetic rectified camera (mm)."""
    return camera.calibration()


def run_frame(frame, params: ReconParams, masks: bool) -> dict:
    pair = (
        StereoPair(frame.left, frame.right, frame.mask_left, frame.mask_right)
        if masks
        else StereoPair(frame.left, frame.right)
    )
    calib = calibration_for(frame.camera)
    t0 = time.perf_counter()
    rec = Pipeline(pair, calib).run(params)
    ms = 1000 * (time.perf_counter() - t0)
    row = {"status": rec.status, "error": rec.message or "", "ms_total": ms}
    row["ms_segment"] = rec.timings_ms.get("segment", float("nan"))
    if "segment" in rec.runs:
        lifted = rec["segment"]
        ious = []
        for P, M in ((lifted.P_L, frame.mask_left), (lifted.P_R, frame.mask_right)):
            ious.append(float((P & M).sum()) / max(float((P | M).sum()), 1.0))
        row["iou"] = float(np.mean(ious))
    if not frame.mask_left.any():  # a thread-free frame: the right answer is no curve
        row["good"] = rec.status == "failed" and "no thread found" in (rec.message or "")
        return row
    # the true thread's length no view shows at an end (under an occluder): unobservable
    row["hidden_mm"] = max(
        hidden_ends(frame.truth.centerline, calib, frame.mask_left, frame.mask_right)
    )
    if "camera" in rec.runs:
        e = frame_errors(rec["camera"].points, frame.truth.centerline, calib)
        row.update(e_S=e.e_S, e_S_max=e.e_S_max, e_length=e.e_length)
        row["good"] = bool(rec.status == "ok" and e.e_length <= GOOD_MM and e.e_S_max <= GOOD_MM)
    else:
        row["good"] = False
    return row


def seg_time_ms(frame, params: ReconParams, repeat: int = 3) -> tuple[float, float]:
    """Fastest wall time and CPU time (this thread) of the segmentation of the raw pair, ms."""
    pair = StereoPair(frame.left, frame.right)
    best, best_cpu = float("inf"), float("inf")
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.thread_time()
        with contextlib.suppress(ValueError):  # "no thread found" is timed like any answer
            segment(pair, params.segment)
        best = min(best, 1000 * (time.perf_counter() - t0))
        best_cpu = min(best_cpu, 1000 * (time.thread_time() - c0))
    return best, best_cpu


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--count", type=int, default=20)
    ap.add_argument("--suite", action="append", choices=sorted(SUITES))
    ap.add_argument("--csv", type=Path)
    ap.add_argument("--no-masked", action="store_true", help="skip the masked reference runs")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args(argv)
    threadpool_limits(limits=1, user_api="blas")
    params = ReconParams()
    names = args.suite or list(SUITES)
    rows = []
    print(
        f"{'suite':<18} {'good raw':>9} {'seen':>5} {'ok wrong':>8} {'good mask':>9} {'e_S raw':>8} "
        f"{'e_S mask':>8} {'IoU':>5} {'IoU min':>7} {'seg ms':>7} {'seg cpu':>7} {'total ms':>8}"
    )
    for name in names:
        si = list(SUITES).index(name)
        tp, rp = SUITES[name]
        res = []
        for k in range(1, args.count + 1):
            frame = generate_frame(
                SyntheticParams(thread=tp, render=rp), np.random.default_rng([args.seed, si, k])
            )
            raw = run_frame(frame, params, masks=False)
            raw["ms_seg_best"], raw["ms_seg_cpu"] = seg_time_ms(frame, params)
            masked = not args.no_masked and frame.mask_left.any()
            ref = run_frame(frame, params, masks=True) if masked else {}
            res.append((raw, ref))
            rows.append(
                {"suite": name, "k": k}
                | {f"raw_{a}": b for a, b in raw.items()}
                | {f"mask_{a}": b for a, b in ref.items()}
            )
            if args.verbose:
                print(
                    f"  {name} {k}: raw {raw['status']} good={raw['good']} "
                    f"e_S={raw.get('e_S', float('nan')):.2f} iou={raw.get('iou', 0):.2f} "
                    f"{raw['error'][:90]}"
                )
        good = np.mean([r["good"] for r, _ in res]) * 100
        # good among the frames with no end hidden over GOOD_MM (``hidden_ends``: no method can
        # recover those; a curve stopping where the thread disappears is rightly suspect)
        seen = [r["good"] for r, _ in res if r.get("hidden_mm", 0.0) <= GOOD_MM]
        good_seen = f"{sum(seen)}/{len(seen)}"
        # A wrong answer given as "ok" (a curve where there is none, or a bad one): the worst.
        ok_wrong = sum(r["status"] == "ok" and not r["good"] for r, _ in res)
        good_m = np.mean([m.get("good", False) for _, m in res]) * 100
        both = [(r["e_S"], m["e_S"]) for r, m in res if r["good"] and m.get("good")]
        e_raw = np.mean([b[0] for b in both]) if both else float("nan")
        e_msk = np.mean([b[1] for b in both]) if both else float("nan")
        ious = [r.get("iou", 0.0) for r, _ in res]
        seg = np.median([r["ms_seg_best"] for r, _ in res])
        tot = np.median([r["ms_total"] for r, _ in res])
        cpu = np.median([r["ms_seg_cpu"] for r, _ in res])
        print(
            f"{name:<18} {good:8.0f}% {good_seen:>5} {ok_wrong:8d} {good_m:8.0f}% {e_raw:8.3f} {e_msk:8.3f} "
            f"{np.mean(ious):5.2f} {np.min(ious):7.2f} {seg:7.1f} {cpu:7.1f} {tot:8.1f}",
            flush=True,
        )
    if args.csv:
        keys: list[str] = []
        for r in rows:
            keys += [k for k in r if k not in keys]
        with args.csv.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
