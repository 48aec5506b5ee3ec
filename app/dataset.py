"""Dataset folders: where the stereo pairs, masks, ground truth and calibrations are, and
per-frame evaluation.

A dataset is any folder. Every folder under it (hidden ones skipped) is searched for pairs by
these rules, in this order; an image belongs to the first rule that claims it:

1. ``left/`` and ``right/`` sub-folders: images with the same name in both are a pair
   (frame id ``<folder>/<stem>``).
2. Names with ``left`` / ``right`` (any case; ``img_left_3.png`` + ``img_right_3.png``) or
   ending in ``_L`` / ``_R`` (``003_L.png`` + ``003_R.png``): the matching names are a pair
   (id: the name without the token, ``__`` collapsed to ``_``).
3. Any other image: a side-by-side composite (left half | right half).

Masks: ``<image stem>_mask.png`` beside each image (one composite mask for rule 3, one per
view otherwise; both views or neither). Ground truth: ``<id stem>.npy`` (clamped cubic B-spline
control points, left camera frame, calibration units) beside the (left) image or in the
frame's folder; a frame with ground truth is "simulated", else "real".
Calibration: per frame ``<id stem>.calib.yaml`` beside the image; otherwise per folder, in the
frame's folder or the nearest one above it (up to the dataset root): ``calibration.yaml``,
``camera_calibration.yaml``, ``camchain.yaml`` (Kalibr), or ``left.yaml`` + ``right.yaml``
(ROS camera_info); the paper's ``simulated/blend_calibration*.yaml`` as before. Frame ids are
the paths relative to the root without suffix, sorted; two frames with the same id are an
error naming both files.

Units: a calibration's ``Units`` key; without it the paper's Blender calibrations
(``blend_calibration*.yaml``) are centimetres (its README), OpenCV files millimetres, Kalibr
and ROS files metres.

Pixel origin: the paper's Blender calibrations put the principal point at the image's
geometric centre, (W / 2, H / 2), measured from the first pixel's outer corner (Blender's
convention); OpenCV and this pipeline measure from the first pixel's centre, so it is moved
by ``BLENDER_PIXEL_ORIGIN`` to (W / 2 - 0.5, H / 2 - 0.5) on load (docs/method.md, "The
Blender frames' pixel origin").
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from threadrecon.app.export import InputFile
from threadrecon.app.io import load_calibration, load_ground_truth, load_pair, prepare_pair
from threadrecon.core.calibration import StereoCalibration, make_calibration
from threadrecon.core.corrections import Correction
from threadrecon.core.lru import LRU, MISSING
from threadrecon.core.metrics import (
    ReprojectionErrors,
    frame_errors,
    project,
    reprojection_errors,
)
from threadrecon.core.pipeline import Reconstruction
from threadrecon.core.rectify import Rectification, from_left_frame, rectification
from threadrecon.core.segmentation import LiftedPair, StereoPair

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
PAPER_OLD_GROUPS = 4  # the paper's blend1..4 use blend_calibration.yaml (1 mm baseline)
BLENDER_PIXEL_ORIGIN = 0.5  # px: a pixel's centre lies half a pixel from its outer corner
FOLDER_CALIBRATIONS = ("calibration.yaml", "camera_calibration.yaml", "camchain.yaml")
ROS_PAIR = ("left.yaml", "right.yaml")
_LR_TOKEN = re.compile(r"(left|right)", re.IGNORECASE)
_LR_SUFFIX = re.compile(r"_(L|R)$")


@dataclass(frozen=True)
class Frame:
    id: str
    """Path relative to the dataset root, no suffix (e.g. simulated/blend1/blend1_1)."""
    kind: str
    """"simulated" (has 3D ground truth) or "real"."""
    calibration: Path
    stereo: Path | None = None
    left: Path | None = None
    right: Path | None = None
    ground_truth: Path | None = None
    mask: Path | None = None
    """Side-by-side mask of a composite."""
    mask_left: Path | None = None
    mask_right: Path | None = None
    calibration_right: Path | None = None
    """The right camera's ROS camera_info when ``calibration`` is the left one's."""
    corrections: tuple[Correction, ...] = ()
    """The user's mask corrections that every run of this frame applies (from the rating
    store, :func:`app.corrections.with_corrections`); none on disk."""

    @property
    def has_ground_truth(self) -> bool:
        return self.ground_truth is not None

    @property
    def name(self) -> str:
        return self.id.rsplit("/", 1)[-1]


def discover(root: str | Path, skip: Collection[Path] = ()) -> list[Frame]:
    """All frames under a dataset root, sorted by id; a clear error for a wrong folder.
    Folders in ``skip`` (and below them) are left out: the debugger shows a sequence's
    folder as one entry (:mod:`app.sequence_library`)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: dataset folder not found")
    found: dict[str, tuple[Frame, Path]] = {}
    skipped = {Path(p) for p in skip}
    for folder in _folders(root):
        if folder in skipped or skipped.intersection(folder.parents):
            continue
        for frame in _frames_in(root, folder):
            first = frame.left or frame.stereo
            assert first is not None
            if frame.id in found:
                raise ValueError(
                    f"{root}: two frames have the id {frame.id!r}: {found[frame.id][1]} and {first}"
                )
            found[frame.id] = (frame, first)
    if not found:
        raise FileNotFoundError(
            f"{root}: no frames found (expected side-by-side images, left/ + right/ folders, "
            "or *left*/*right* or *_L/*_R image pairs)"
        )
    return [found[k][0] for k in sorted(found)]


def _folders(root: Path) -> list[Path]:
    out = []
    for d in sorted([root, *(p for p in root.rglob("*") if p.is_dir())]):
        rel = d.relative_to(root).parts
        if any(part.startswith((".", "__")) for part in rel):
            continue
        if (
            d.name in ("left", "right")
            and (d.parent / "left").is_dir()
            and (d.parent / "right").is_dir()
        ):
            continue  # rule 1 reads these from the parent
        out.append(d)
    return out


def _images(folder: Path) -> list[Path]:
    return sorted(
        p for p in folder.iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.stem.endswith("_mask")
    )  # fmt: skip


def _beside(img: Path, suffix: str) -> Path | None:
    p = img.with_name(img.stem + suffix)
    return p if p.exists() else None


def _frames_in(root: Path, folder: Path) -> list[Frame]:
    frames: list[Frame] = []
    if (folder / "left").is_dir() and (folder / "right").is_dir():
        rights = {p.stem: p for p in _images(folder / "right")}
        for left in _images(folder / "left"):
            right = rights.get(left.stem)
            if right is None:
                continue
            fid = (folder / left.stem).relative_to(root).as_posix()
            gt = _first(left.with_suffix(".npy"), folder / f"{left.stem}.npy")
            frames.append(_frame(root, fid, folder, left.stem, gt, left=left, right=right))
    claimed: set[Path] = set()
    images = _images(folder)
    names = {p.name: p for p in images}
    for img in images:
        if img in claimed:
            continue
        m = _LR_SUFFIX.search(img.stem)
        if m and m.group(1) == "L":
            partner = names.get(img.stem[:-1] + "R" + img.suffix)
            stem = img.stem[: m.start()]
        else:
            t = _LR_TOKEN.search(img.name)
            if t is None or t.group(1).lower() != "left":
                continue
            repl = {"left": "right", "Left": "Right", "LEFT": "RIGHT"}.get(t.group(1), "right")
            partner = names.get(img.name[: t.start()] + repl + img.name[t.end() :])
            stem = re.sub(r"__+", "_", img.stem[: t.start()] + img.stem[t.end() :])
        if partner is None:
            continue
        claimed |= {img, partner}
        fid = (folder / stem).relative_to(root).as_posix()
        gt = _first(folder / f"{stem}.npy", img.with_suffix(".npy"))
        frames.append(_frame(root, fid, folder, stem, gt, left=img, right=partner))
    for img in images:
        if img in claimed or _LR_TOKEN.search(img.name) or _LR_SUFFIX.search(img.stem):
            continue  # an unmatched left/right image is not a composite
        fid = img.relative_to(root).with_suffix("").as_posix()
        frames.append(
            _frame(root, fid, folder, img.stem, _beside(img, ".npy"), stereo=img,
                   mask=_beside(img, "_mask.png"))
        )  # fmt: skip
    return frames


def _first(*paths: Path) -> Path | None:
    return next((p for p in paths if p.exists()), None)


def _frame(
    root: Path, fid: str, folder: Path, stem: str, gt: Path | None, **files: Path | None
) -> Frame:
    if "left" in files:
        ml, mr = (_beside(files[k], "_mask.png") for k in ("left", "right"))  # type: ignore[arg-type]
        if (ml is None) != (mr is None):
            ml = mr = None  # one view's mask only: a mask pair or none
        files.update(mask_left=ml, mask_right=mr)
    calib, calib_right = _calibration(root, folder, stem)
    return Frame(
        id=fid,
        kind="simulated" if gt is not None else "real",
        calibration=calib,
        calibration_right=calib_right,
        ground_truth=gt,
        **files,  # type: ignore[arg-type]
    )


def _calibration(root: Path, folder: Path, stem: str) -> tuple[Path, Path | None]:
    own = folder / f"{stem}.calib.yaml"
    if own.exists():
        return own, None
    d = folder
    while True:
        for name in FOLDER_CALIBRATIONS:
            if (d / name).exists():
                return d / name, None
        if all((d / n).exists() for n in ROS_PAIR):
            return d / ROS_PAIR[0], d / ROS_PAIR[1]
        if d.parent.name == "simulated" or d.name == "simulated":
            paper = _sim_calibration(d if d.name == "simulated" else d.parent, folder)
            if paper.exists():
                return paper, None
        if d == root or root not in d.parents:
            break
        d = d.parent
    return folder / FOLDER_CALIBRATIONS[0], None  # missing: load_frame names it


def _sim_calibration(sim: Path, group: Path) -> Path:
    m = re.search(r"(\d+)$", group.name)
    n = int(m.group(1)) if m else 0
    name = "blend_calibration.yaml" if n <= PAPER_OLD_GROUPS else "blend_calibration_new.yaml"
    return sim / name


def frame_unit(calibration: Path) -> str | None:
    """Default unit when the file has no Units key: cm for the paper's Blender calibrations."""
    return "cm" if _blender(calibration) else None


def _blender(calibration: Path) -> bool:
    """Whether ``calibration`` is one of the paper's Blender calibrations."""
    return calibration.name.startswith("blend_calibration")


def pixel_centred(
    calib: StereoCalibration, origin: float = BLENDER_PIXEL_ORIGIN
) -> StereoCalibration:
    """``calib`` with both cameras' principal points moved by ``-origin`` px in x and y: a
    principal point measured from the first pixel's outer corner (Blender) measured from its
    centre (OpenCV), the rectification recomputed."""
    K1, K2 = calib.K1.copy(), calib.K2.copy()
    for K in (K1, K2):
        K[:2, 2] -= origin
    return make_calibration(
        K1, calib.D1, K2, calib.D2, calib.R, calib.T, calib.image_size, unit=calib.unit,
        source="pixel-centred calibration", rectified=calib.rectified,
    )  # fmt: skip


def load_frame(frame: Frame) -> tuple[StereoPair, StereoCalibration, np.ndarray | None]:
    """The pair the pipeline runs on, its calibration and the dense ground-truth curve (calib
    units) if any. A raw pair is undistorted and rectified here (core/rectify.py): the pair and
    calibration returned are the rectified ones and the ground truth is moved from the left
    camera frame into the left rectified frame, where the pipeline's points are."""
    calib = frame_calibration(frame)
    if frame.stereo is not None:
        pair = load_pair(stereo=frame.stereo, mask=frame.mask)
    else:
        pair = load_pair(
            left=frame.left, right=frame.right, mask_left=frame.mask_left,
            mask_right=frame.mask_right,
        )  # fmt: skip
    pair, calib_rect, rect = prepare_pair(pair, calib)
    gt = load_ground_truth(frame.ground_truth) if frame.ground_truth is not None else None
    if gt is not None and not rect.identity:
        gt = from_left_frame(gt, rect)
    return pair, calib_rect, gt


def frame_calibration(frame: Frame) -> StereoCalibration:
    """The frame's calibration as its file(s) say (before any rectification), with the
    principal point of the paper's Blender calibrations measured from a pixel's centre."""
    calib = load_calibration(
        frame.calibration, unit=frame_unit(frame.calibration), right=frame.calibration_right
    )
    return pixel_centred(calib) if _blender(frame.calibration) else calib


def frame_rectification(frame: Frame) -> Rectification:
    """How the frame's pair is rectified on load (identity for a rectified pair); cached per
    calibration, so asking again costs a file read."""
    return rectification(frame_calibration(frame))


def frame_inputs(frame: Frame) -> list[InputFile]:
    """The frame's files with their roles and SHA-256, for the result JSON's provenance."""
    roles = ("stereo", "left", "right", "mask", "mask_left", "mask_right", "calibration",
             "calibration_right")  # fmt: skip
    return [
        InputFile.of_file(role, path)
        for role in roles
        if (path := getattr(frame, role)) is not None and path.exists()
    ]


METRIC_COLUMNS = (
    "e_S_mm", "e_S_max_mm", "e_length_mm", "length_mm", "length_gt_mm",
    "left_mean_px", "left_max_px", "right_mean_px", "right_max_px", "coverage_left", "coverage_right",
)  # fmt: skip


def evaluate_reconstruction(
    rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None
) -> dict[str, float]:
    """Table I columns (mm, when ``gt`` is given) and Table II columns (px) plus coverage."""
    out: dict[str, float] = {c: float("nan") for c in METRIC_COLUMNS}
    if "camera" not in rec.runs:
        return out
    pts = rec["camera"].points
    if gt is not None:
        e = frame_errors(pts, gt, calib)  # on the visible part: a thread may leave the view
        out.update(
            e_S_mm=e.e_S,
            e_S_max_mm=e.e_S_max,
            e_length_mm=e.e_length,
            length_mm=e.length,
            length_gt_mm=e.length_gt,
        )
    for side, (_, r) in reprojections(pts, calib, rec["segment"]).items():
        out[f"{side}_mean_px"], out[f"{side}_max_px"], out[f"coverage_{side}"] = (
            r.mean,
            r.max,
            r.coverage,
        )
    return out


def reprojections(
    points: np.ndarray, calib: StereoCalibration, lifted: LiftedPair, errors: bool = True
) -> dict[str, tuple[np.ndarray, ReprojectionErrors | None]]:
    """(N, 3) camera-frame points projected into the left and right images: per side the
    (N, 2) pixels and, with ``errors``, their Table II errors against the segmented thread."""
    out = {}
    for side, P, mask in (("left", calib.P1, lifted.P_L), ("right", calib.P2, lifted.P_R)):
        uv = project(points, P)
        out[side] = (uv, _errors(uv, mask) if errors else None)
    return out


_ERRORS: LRU[tuple, tuple[np.ndarray, ReprojectionErrors]] = LRU(8)  # a few frames' curves
# The metrics and the spline overlay ask for the same curve's errors after every run.


def _errors(uv: np.ndarray, mask: np.ndarray) -> ReprojectionErrors:
    """``reprojection_errors(uv, mask)``, remembered by the pixels' content and the mask
    (held, so that its id is not reused while the entry lives)."""
    uv = np.ascontiguousarray(uv)
    key = (uv.shape, hashlib.blake2b(uv.tobytes(), digest_size=16).digest(), id(mask))
    hit = _ERRORS.get(key)
    if hit is not MISSING and hit[0] is mask:  # type: ignore[index]
        return hit[1]  # type: ignore[index]
    errors = reprojection_errors(uv, mask)
    _ERRORS.put(key, (mask, errors))
    return errors
