"""``threadrecon generate``: write synthetic stereo thread frames in the paper dataset's layout.

::

    OUT_DIR/README.md                            settings and command of every group
    OUT_DIR/simulated/<group>/calibration.yaml   OpenCV FileStorage: K1 D1 K2 D2 R T ImageSize Units
    OUT_DIR/simulated/<group>/<group>_<k>.png    side-by-side pair, left = cols 0..W-1
    OUT_DIR/simulated/<group>/<group>_<k>.npy    (n, 3) float64 control points, left frame, mm
    OUT_DIR/simulated/<group>/<group>_<k>_mask.png   side-by-side binary mask, 0 / 255

Frame k (from 1) is drawn with ``np.random.default_rng([seed, k])``, so a frame does not depend
on ``--count``. Unlike the paper's ground truth (cm), ours is in mm (``Units`` in the YAML).

Use ``add_parser(subparsers)`` from the main CLI, or run ``python -m threadrecon.app.generate OUT_DIR ...``.
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app.generate_files import (
    _DEFAULT_RENDER,
    _DEFAULT_THREAD,
    _GROUP_RE,
    DESCRIPTION,
    _check_calibration,
    _check_readme,
    _flag_message,
    _frame_paths,
    _section,
    _write_calibration,
    _write_frame,
    _write_readme,
)
from threadrecon.core.synthetic import (
    THREAD_COLOURS,
    RenderParams,
    StereoCamera,
    SyntheticParams,
    ThreadParams,
    generate_frame,
)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``generate`` on the main CLI's ``parser.add_subparsers()`` object."""
    parser = subparsers.add_parser(
        "generate",
        help="write synthetic stereo thread frames with exact 3D ground truth",
        description=DESCRIPTION,
    )
    _add_arguments(parser)
    parser.set_defaults(func=run)
    return parser


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out_dir", type=Path, help="dataset folder (created if missing)")
    parser.add_argument("--count", type=int, default=4, help="number of frames (default 4)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--background", choices=("flat", "tissue"), default="flat", help="default: flat"
    )
    parser.add_argument("--noise", type=float, default=0.0, help="pixel noise std, grey levels")
    parser.add_argument("--blur", type=float, default=0.0, help="Gaussian blur std, px")
    parser.add_argument("--crossing", action="store_true", help="thread crosses itself")
    parser.add_argument("--occlusion", action="store_true", help="an instrument hides part")
    parser.add_argument(
        "--hairpin", action="store_true", help="a tight U-turn: two strands side by side"
    )
    parser.add_argument(
        "--spiral",
        action="store_true",
        help="a coil of 1.5-3 turns 2-6 mm apart, axis near the view direction",
    )
    parser.add_argument(
        "--leaves-image", action="store_true", help="one end of the thread leaves the image"
    )
    parser.add_argument(
        "--length-mm",
        type=float,
        nargs=2,
        metavar=("MIN", "MAX"),
        default=_DEFAULT_THREAD.length_mm,
        help="3D thread length range, mm (default %(default)s)",
    )
    parser.add_argument(
        "--depth-mm",
        type=float,
        nargs=2,
        metavar=("MIN", "MAX"),
        default=_DEFAULT_THREAD.depth_mm,
        help="depth range of the thread, mm (default %(default)s)",
    )
    parser.add_argument(
        "--diameter-mm",
        type=float,
        default=_DEFAULT_THREAD.diameter_mm,
        help="thread diameter, mm (default %(default)s)",
    )
    parser.add_argument(
        "--thread-colour",
        choices=(*THREAD_COLOURS, "random"),
        default=None,
        help="thread dye; random: one per frame (default: violet on tissue, grey on flat)",
    )
    parser.add_argument(
        "--distractors",
        type=int,
        default=0,
        help="thread-wide vessels and fibres on the tissue (needs --background tissue)",
    )
    parser.add_argument(
        "--instrument", action="store_true", help="a grasper (shaft and open jaws) in view"
    )
    parser.add_argument(
        "--lighting", type=float, default=0.0, help="uneven light: darkest loss, 0-0.8"
    )
    parser.add_argument(
        "--jpeg",
        type=int,
        default=0,
        help="write each pair as <frame>.jpg at this quality 1-100, compressed once (0: PNG)",
    )
    parser.add_argument(
        "--specular",
        type=float,
        default=_DEFAULT_RENDER.specular,
        help="highlight on the thread, fraction of 255 (default %(default)s)",
    )
    parser.add_argument("--no-mask", action="store_true", help="write no *_mask.png (raw frames)")
    parser.add_argument(
        "--group", default=None, help="folder under simulated/ (default: background or crossing)"
    )
    parser.add_argument("--force", action="store_true", help="overwrite existing frame files")
    parser.add_argument(
        "--size",
        type=_size,
        default=None,
        metavar="WxH",
        help="image size per view, e.g. 1920x1080 (default 640x480); intrinsics scaled",
    )
    parser.add_argument(
        "--sequence",
        type=int,
        metavar="N",
        help="write a moving thread of N frames (and a video) under sequences/ instead",
    )
    parser.add_argument(
        "--motion",
        choices=("drag", "pull", "instrument"),
        default="drag",
        help="with --sequence: how the thread moves (default drag)",
    )
    parser.add_argument(
        "--speed-mm", type=float, default=0.6, help="with --sequence: mm per frame (default 0.6)"
    )


def run(args: argparse.Namespace) -> int:
    """Write ``args.count`` frames; raise ``ValueError`` naming the flag for bad settings."""
    count, seed = int(args.count), int(args.seed)
    if count < 1:
        raise ValueError(f"--count must be >= 1, got {count}")
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    params = _params(args)
    if getattr(args, "sequence", None) is not None:
        from threadrecon.app import sequence_gen  # video encoding only when a sequence is asked for

        return sequence_gen.run(args, params, _write_calibration)
    group = args.group or (
        "crossing"
        if args.crossing
        else "hairpin"
        if getattr(args, "hairpin", False)
        else "spiral"
        if getattr(args, "spiral", False)
        else args.background
    )
    if not _GROUP_RE.match(group):
        raise ValueError(f"--group must be a plain folder name, got {group!r}")
    out_dir = Path(args.out_dir)
    group_dir = out_dir / "simulated" / group
    names = [f"{group}_{k}" for k in range(1, count + 1)]
    force = bool(getattr(args, "force", False))
    if not force:
        for name in names:
            for path in _frame_paths(group_dir, name, jpeg=int(getattr(args, "jpeg", 0)) > 0):
                if path.exists():
                    raise ValueError(f"{path} exists; use --force to overwrite")
        _check_calibration(group_dir / "calibration.yaml", params.camera)
        _check_readme(out_dir / "README.md")
    rows = []
    for k, name in enumerate(names, start=1):
        try:
            frame = generate_frame(params, np.random.default_rng([seed, k]))
        except ValueError as err:  # e.g. a thread too long for the view: name the flags
            raise ValueError(_flag_message(str(err))) from None
        if k == 1:  # nothing is written before the first frame succeeds
            group_dir.mkdir(parents=True, exist_ok=True)
            _write_calibration(group_dir / "calibration.yaml", params.camera)
        _write_frame(
            group_dir,
            name,
            frame,
            mask=not getattr(args, "no_mask", False),
            jpeg=int(getattr(args, "jpeg", 0)),
        )
        z = frame.truth.centerline[:, 2]
        rows.append(
            f"| {name} | {len(frame.truth.control_points)} | {frame.truth.length_mm:.1f} "
            f"| {z.min():.1f}-{z.max():.1f} | {int(frame.mask_left.sum())} "
            f"| {int(frame.mask_right.sum())} |"
        )
        print(
            f"[{k}/{count}] {_frame_paths(group_dir, name, jpeg=int(getattr(args, 'jpeg', 0)) > 0)[0]}  length {frame.truth.length_mm:.1f} mm, "
            f"Z {z.min():.0f}-{z.max():.0f} mm",
            flush=True,
        )
    _write_readme(out_dir / "README.md", group, _section(args, params, group, rows))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m threadrecon.app.generate OUT_DIR ...``: the same command without the main CLI."""
    parser = argparse.ArgumentParser(
        prog="python -m threadrecon.app.generate", description=DESCRIPTION
    )
    _add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


# ----------------------------------------------------------------------------------------------


def _params(args: argparse.Namespace) -> SyntheticParams:
    """Build the generator settings from the flags, renaming core setting names to flags."""
    try:
        thread = ThreadParams(
            length_mm=tuple(getattr(args, "length_mm", _DEFAULT_THREAD.length_mm)),
            depth_mm=tuple(getattr(args, "depth_mm", _DEFAULT_THREAD.depth_mm)),
            diameter_mm=float(getattr(args, "diameter_mm", _DEFAULT_THREAD.diameter_mm)),
            crossing=bool(args.crossing),
            leaves_image=bool(getattr(args, "leaves_image", False)),
            hairpin=bool(getattr(args, "hairpin", False)),
            spiral=bool(getattr(args, "spiral", False)),
        )
        render = RenderParams(
            background=args.background,
            noise_sigma=float(args.noise),
            blur_sigma=float(args.blur),
            occlusion=bool(args.occlusion),
            thread_colour=getattr(args, "thread_colour", None),
            distractors=int(getattr(args, "distractors", 0)),
            instrument=bool(getattr(args, "instrument", False)),
            lighting=float(getattr(args, "lighting", 0.0)),
            # Compressed once, when the pair is written (see _write_frame); validated here.
            jpeg_quality=0 if 0 <= int(getattr(args, "jpeg", 0)) <= 100 else int(args.jpeg),
            specular=float(getattr(args, "specular", _DEFAULT_RENDER.specular)),
        )
    except ValueError as err:
        raise ValueError(_flag_message(str(err))) from None
    size = getattr(args, "size", None)
    camera = StereoCamera() if size is None else scaled_camera(StereoCamera(), *size)
    return SyntheticParams(camera=camera, thread=thread, render=render)


def _size(text: str) -> tuple[int, int]:
    """argparse type of ``--size``: "WxH" -> (W, H)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if m is None:
        raise argparse.ArgumentTypeError(f"--size must be WxH in px, e.g. 1920x1080, got {text!r}")
    w, h = int(m.group(1)), int(m.group(2))
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise argparse.ArgumentTypeError(f"--size must be 16..8192 px per side, got {w}x{h}")
    return w, h


def scaled_camera(camera: StereoCamera, width: int, height: int) -> StereoCamera:
    """``camera`` at another resolution: the focal length scales with the width (the horizontal
    field of view is kept), the principal point moves to the same relative position, the
    baseline is unchanged. A different aspect ratio crops or extends the vertical view."""
    s = width / camera.width
    return replace(
        camera,
        fx=camera.fx * s,
        cx=camera.cx * width / camera.width,
        cy=camera.cy * height / camera.height,
        width=int(width),
        height=int(height),
    )


if __name__ == "__main__":
    sys.exit(main())
