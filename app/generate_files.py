"""The files ``threadrecon generate`` writes: frames, masks, ground truth, calibration and the
dataset's README (one section per group, with the command that made it)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import cv2
import numpy as np

from threadrecon.core.synthetic import (
    RenderParams,
    StereoCamera,
    SyntheticFrame,
    SyntheticParams,
    ThreadParams,
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
    "thread.spiral": "--spiral",
    "thread.hairpin": "--hairpin",
    "thread.crossing": "--crossing",
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
            ("--hairpin", getattr(args, "hairpin", False)),
            ("--spiral", getattr(args, "spiral", False)),
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
    size = getattr(args, "size", None)
    if size is not None:
        parts.append(f"--size {size[0]}x{size[1]}")
    return " ".join(parts)


def _section(args: argparse.Namespace, params: SyntheticParams, group: str, rows: list[str]) -> str:
    cam, tp, rp = params.camera, params.thread, params.render
    lines = [
        f"<!-- group: {group} -->",
        f"## simulated/{group}",
        "",
        "Command (equivalently `python -m threadrecon.app.generate ...` with the same arguments):",
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
        f"{tp.crossing}, hairpin {tp.hairpin}, spiral {tp.spiral}, leaves image "
        f"{tp.leaves_image}, margin {tp.margin_px:g} px.",
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
