"""``threadrecon generate --sequence N``: write a moving thread, frame by frame, with ground
truth per frame, and the same frames as a side-by-side video.

::

    OUT_DIR/sequences/<group>/calibration.yaml        as for still frames
    OUT_DIR/sequences/<group>/<group>_<k>.png         side-by-side pair of frame k (from 1)
    OUT_DIR/sequences/<group>/<group>_<k>_mask.png    side-by-side visible-thread mask
    OUT_DIR/sequences/<group>/<group>_<k>.npy         (n, 3) control points, left frame, mm
    OUT_DIR/sequences/<group>/<group>.mp4             the pairs as an H.264 video (side by side)

The folder is an image sequence that ``threadrecon track`` reads (masks and truth included);
the video is what a recording would give (no masks, no truth).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from threadrecon.app.sequence import write_video
from threadrecon.core.sequence_synth import MotionParams, SequenceParams, generate_sequence
from threadrecon.core.synthetic import SyntheticParams

VIDEO_FPS = 15.0  # frame rate written into the video, frames/s


def write_sequence(
    out_dir: Path,
    group: str,
    params: SyntheticParams,
    motion: MotionParams,
    seed: int,
    force: bool = False,
    write_calibration=None,
) -> Path:
    """Write one sequence (see the module docstring); returns its folder."""
    folder = Path(out_dir) / "sequences" / group
    video = folder / f"{group}.mp4"
    if folder.exists() and any(folder.iterdir()) and not force:
        raise ValueError(f"{folder} exists and is not empty; use --force to overwrite")
    folder.mkdir(parents=True, exist_ok=True)
    if write_calibration is not None:
        write_calibration(folder / "calibration.yaml", params.camera)
    width = len(str(motion.n_frames))
    png = [cv2.IMWRITE_PNG_COMPRESSION, 3]

    def frames() -> Iterator[np.ndarray]:
        seq = generate_sequence(SequenceParams(params, motion), seed)
        for k, f in enumerate(seq, start=1):
            name = f"{group}_{k:0{width}d}"
            pair = np.hstack([f.left, f.right])
            mask = np.hstack([f.mask_left, f.mask_right]).astype(np.uint8) * 255
            ok = cv2.imwrite(
                str(folder / f"{name}.png"), cv2.cvtColor(pair, cv2.COLOR_RGB2BGR), png
            )
            ok &= cv2.imwrite(str(folder / f"{name}_mask.png"), mask, png)
            if not ok:
                raise OSError(f"could not write {folder / name}.png")
            np.save(folder / f"{name}.npy", f.truth.control_points)
            print(
                f"[{k}/{motion.n_frames}] {folder / name}.png  length {f.truth.length_mm:.1f} mm",
                flush=True,
            )
            yield pair

    write_video(video, frames(), VIDEO_FPS)
    return folder


def run(args: argparse.Namespace, params: SyntheticParams, write_calibration) -> int:
    """The ``--sequence N`` branch of ``generate``."""
    if params.render.occlusion:
        raise ValueError("--occlusion draws a still instrument; use --motion instrument instead")
    try:
        motion = MotionParams(
            kind=args.motion, n_frames=int(args.sequence), speed_mm=float(args.speed_mm)
        )
    except ValueError as err:
        raise ValueError(
            str(err)
            .replace("motion.n_frames", "--sequence")
            .replace("motion.speed_mm", "--speed-mm")
        ) from None
    group = args.group or args.motion
    folder = write_sequence(
        Path(args.out_dir),
        group,
        params,
        motion,
        int(args.seed),
        bool(args.force),
        write_calibration,
    )
    print(f"sequence of {motion.n_frames} frames ({motion.kind}) -> {folder}")
    return 0
