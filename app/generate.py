"""``threadrecon generate``: write synthetic stereo thread frames in the paper dataset's layout.

::

    OUT_DIR/README.md                            settings and command of every group
    OUT_DIR/simulated/<group>/calibration.yaml   OpenCV FileStorage: K1 D1 K2 D2 R T ImageSize Units
    OUT_DIR/simulated/<group>/<group>_<k>.png    side-by-side pair, left = cols 0..W-1
    OUT_DIR/simulated/<group>/<group>_<k>.npy    (n, 3) float64 control points, left frame, mm
    OUT_DIR/simulated/<group>/<group>_<k>_mask.png   side-by-side binary mask, 0 / 255

Frame k (from 1) is drawn with ``np.random.default_rng([seed, k])``, so a frame does not depend
on ``--count``. Unlike the paper's ground truth (cm), ours is in mm (``Units`` in the YAML).

Use ``add_parser(subparsers)`` from the main CLI, or run ``python -m app.generate OUT_DIR ...``.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from core.synthetic import (
    THREAD_COLOURS,
    RenderParams,
    StereoCamera,
    SyntheticFrame,
    SyntheticParams,
    ThreadParams,
    generate_frame,
)

README_TITLE = "# Synthetic suture-thread stereo dataset"
DESCRIPTION = "Write synthetic stereo thread frames with exact 3D ground truth."
_GROUP_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")  # a plain folder name
_SECTION_RE = re.compile(r"<!-- group: (\S+) -->\n.*?<!-- end group -->\n", re.DOTALL)
# Core setting names -> the flags that set them, so errors name what the user typed.
_FLAG_NAMES = {
    "thread.length_mm": "--length-mm",
    "thread.depth_mm": "--depth-mm",
    "thread.diameter_mm": "--diameter-mm",
    "render.noise_sigma": "--noise",
    "render.blur_sigma": "--blur",
    "render.background": "--background",
    "render.thread_colour": "--thread-colour",
    "render.distractors": "--distractors",
    "render.lighting": "--lighting",
    "render.jpeg_quality": "--jpeg",
    "render.specular": "--specular",
}
_DEFAULT_THREAD = ThreadParams()
_DEFAULT_RENDER = RenderParams()


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


def run(args: argparse.Namespace) -> int:
    """Write ``args.count`` frames; raise ``ValueError`` naming the flag for bad settings."""
    count, seed = int(args.count), int(args.seed)
    if count < 1:
        raise ValueError(f"--count must be >= 1, got {count}")
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    params = _params(args)
    group = args.group or ("crossing" if args.crossing else args.background)
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
    """``python -m app.generate OUT_DIR ...``: the same command without the main CLI."""
    parser = argparse.ArgumentParser(prog="python -m app.generate", description=DESCRIPTION)
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
    return SyntheticParams(thread=thread, render=render)


def _flag_message(message: str) -> str:
    for name, flag in _FLAG_NAMES.items():
        message = message.replace(name, flag)
    return message


def _frame_paths(group_dir: Path, name: str, jpeg: bool = False) -> tuple[Path, Path, Path]:
    image = group_dir / f"{name}.{'jpg' if jpeg else 'png'}"
    return image, group_dir / f"{name}.npy", group_dir / f"{name}_mask.png"


def _write_frame(
    group_dir: Path, name: str, frame: SyntheticFrame, mask: bool = True, jpeg: int = 0
) -> None:
    image_path, truth_path, mask_path = _frame_paths(group_dir, name, jpeg=jpeg > 0)
    pair = cv2.cvtColor(np.hstack([frame.left, frame.right]), cv2.COLOR_RGB2BGR)
    png = [cv2.IMWRITE_PNG_COMPRESSION, 9]
    options = [cv2.IMWRITE_JPEG_QUALITY, jpeg] if jpeg > 0 else png
    if not cv2.imwrite(str(image_path), pair, options):
        raise OSError(f"could not write {image_path}")
    for other in _frame_paths(group_dir, name, jpeg=jpeg <= 0)[:1]:
        other.unlink(missing_ok=True)  # a stale pair in the other format would be read too
    if mask:
        binary = np.hstack([frame.mask_left, frame.mask_right]).astype(np.uint8) * 255
        if not cv2.imwrite(str(mask_path), binary, png):
            raise OSError(f"could not write {mask_path}")
    elif mask_path.exists():  # a stale mask would be read as this frame's
        mask_path.unlink()
    np.save(truth_path, frame.truth.control_points.astype(np.float64))


def _calibration(camera: StereoCamera) -> dict[str, np.ndarray]:
    return {
        "K1": camera.K,
        "D1": np.zeros((1, 5)),
        "K2": camera.K,
        "D2": np.zeros((1, 5)),
        "R": np.eye(3),
        "T": np.array([[-camera.baseline], [0.0], [0.0]]),  # mm, right camera at +baseline
        "ImageSize": np.array([[float(camera.height), float(camera.width)]]),  # [rows, cols]
    }


def _write_calibration(path: Path, camera: StereoCamera) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        for key, value in _calibration(camera).items():
            fs.write(key, value)
        fs.write("Units", "mm")
    finally:
        fs.release()


def _check_calibration(path: Path, camera: StereoCamera) -> None:
    """An existing calibration must be the one we would write."""
    if not path.exists():
        return
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        for key, value in _calibration(camera).items():
            node = fs.getNode(key)
            stored = None if node.empty() else node.mat()
            if stored is None or stored.shape != value.shape or not np.allclose(stored, value):
                raise ValueError(f"{path} holds a different calibration; use --force to overwrite")
    finally:
        fs.release()


def _check_readme(path: Path) -> None:
    if path.exists() and not path.read_text(encoding="utf-8").startswith(README_TITLE):
        raise ValueError(f"{path} exists and was not written by generate; use --force")


def _command(args: argparse.Namespace, group: str) -> str:
    parts = [
        f"threadrecon generate {args.out_dir}",
        f"--count {int(args.count)}",
        f"--seed {int(args.seed)}",
        f"--background {args.background}",
        f"--noise {float(args.noise):g}",
        f"--blur {float(args.blur):g}",
    ]
    parts += [
        flag
        for flag, on in (
            ("--crossing", args.crossing),
            ("--occlusion", args.occlusion),
            ("--leaves-image", getattr(args, "leaves_image", False)),
            ("--instrument", getattr(args, "instrument", False)),
            ("--no-mask", getattr(args, "no_mask", False)),
        )
        if on
    ]
    if getattr(args, "thread_colour", None):
        parts.append(f"--thread-colour {args.thread_colour}")
    for flag, attr, default in (
        ("--distractors", "distractors", 0),
        ("--lighting", "lighting", 0.0),
        ("--jpeg", "jpeg", 0),
        ("--specular", "specular", _DEFAULT_RENDER.specular),
    ):
        value = getattr(args, attr, default)
        if value != default:
            parts.append(f"{flag} {value:g}")
    length = getattr(args, "length_mm", _DEFAULT_THREAD.length_mm)
    depth = getattr(args, "depth_mm", _DEFAULT_THREAD.depth_mm)
    diameter = getattr(args, "diameter_mm", _DEFAULT_THREAD.diameter_mm)
    parts += [
        f"--length-mm {length[0]:g} {length[1]:g}",
        f"--depth-mm {depth[0]:g} {depth[1]:g}",
        f"--diameter-mm {diameter:g}",
        f"--group {group}",
    ]
    return " ".join(parts)


def _section(args: argparse.Namespace, params: SyntheticParams, group: str, rows: list[str]) -> str:
    cam, tp, rp = params.camera, params.thread, params.render
    lines = [
        f"<!-- group: {group} -->",
        f"## simulated/{group}",
        "",
        "Command (equivalently `python -m app.generate ...` with the same arguments):",
        "",
        "```",
        _command(args, group),
        "```",
        "",
        f"- Frame k is drawn with `numpy.random.default_rng([{int(args.seed)}, k])`.",
        f"- Camera: fx = fy = {cam.fx:g} px, (cx, cy) = ({cam.cx:g}, {cam.cy:g}) px, "
        f"baseline {cam.baseline:g} mm, {cam.width}x{cam.height} px per view.",
        f"- Thread: length {tp.length_mm[0]:g}-{tp.length_mm[1]:g} mm, depth "
        f"{tp.depth_mm[0]:g}-{tp.depth_mm[1]:g} mm, {tp.n_control[0]}-{tp.n_control[1]} control "
        f"points, curliness {tp.curliness:g} rad, diameter {tp.diameter_mm:g} mm, crossing "
        f"{tp.crossing}, leaves image {tp.leaves_image}, margin {tp.margin_px:g} px.",
        f"- Render: background {rp.background}, noise sigma {rp.noise_sigma:g}, blur sigma "
        f"{rp.blur_sigma:g} px, specular {rp.specular:g}, occlusion {rp.occlusion}, thread "
        f"colour {rp.thread_colour or 'default'}, distractors {rp.distractors}, instrument "
        f"{rp.instrument}, lighting {rp.lighting:g}, stored as JPEG quality "
        f"{getattr(args, 'jpeg', 0) or 'none (PNG)'}.",
        "",
        "| frame | control points | length (mm) | Z range (mm) | mask px left | mask px right |",
        "|---|---|---|---|---|---|",
        *rows,
        "<!-- end group -->",
        "",
    ]
    return "\n".join(lines)


_README_HEAD = f"""{README_TITLE}

Written by `threadrecon generate` (generator: `core/synthetic.py`). The layout matches the
paper dataset's `simulated/` folder, so the same evaluator reads both:

- `simulated/<group>/<frame>.png`: rectified stereo pair side by side (left view = columns
  0..639, right view = columns 640..1279).
- `simulated/<group>/<frame>.npy`: ground truth, (n, 3) float64 control points of a clamped
  cubic B-spline (knots `[0, 0, 0] + linspace(0, 1, n - 2) + [1, 1, 1]`) in the left camera
  frame (OpenCV: x right, y down, z forward), in **millimetres** (the paper's are in cm).
- `simulated/<group>/<frame>_mask.png`: exact thread mask (255 where the visible thread covers
  at least half of the pixel), same side-by-side layout.
- `simulated/<group>/calibration.yaml`: OpenCV FileStorage with K1, D1, K2, D2, R, T (mm),
  ImageSize ([rows, cols]) and `Units: "mm"`. The views are already rectified.

"""


def _write_readme(path: Path, group: str, section: str) -> None:
    """Rewrite the README, replacing this group's section and keeping the others."""
    sections = {}
    if path.exists():
        text = path.read_text(encoding="utf-8")
        if text.startswith(README_TITLE):
            sections = {m.group(1): m.group(0) for m in _SECTION_RE.finditer(text)}
    sections[group] = section
    body = "\n".join(sections[name] for name in sorted(sections))
    path.write_text(_README_HEAD + body, encoding="utf-8")


if __name__ == "__main__":
    sys.exit(main())
