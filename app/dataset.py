"""Dataset layout of the paper (and of ``threadrecon generate``), and per-frame evaluation.

```
DATASET/simulated/<group>/<frame>.png|.jpg    side-by-side pair (left | right)
DATASET/simulated/<group>/<frame>.npy         ground-truth control points, left camera frame
DATASET/simulated/<group>/<frame>_mask.png    optional side-by-side mask
DATASET/simulated/<group>/calibration.yaml    or the paper's simulated/blend_calibration*.yaml
DATASET/real/<sub>/<name>left<rest>.png       with the matching ...right... image
DATASET/real/camera_calibration.yaml          or <sub>/calibration.yaml
```
Units: a calibration's ``Units`` key; without it the paper's Blender calibrations
(``blend_calibration*.yaml``) are centimetres (its README) and every other file millimetres.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.io import load_calibration, load_ground_truth, load_pair
from core.calibration import StereoCalibration
from core.metrics import (
    ReprojectionErrors,
    curve_errors,
    project,
    reprojection_errors,
    visible_part,
)
from core.pipeline import Reconstruction
from core.segmentation import LiftedPair, StereoPair

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
PAPER_OLD_GROUPS = 4  # the paper's blend1..4 use blend_calibration.yaml (1 mm baseline)


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

    @property
    def has_ground_truth(self) -> bool:
        return self.ground_truth is not None

    @property
    def name(self) -> str:
        return self.id.rsplit("/", 1)[-1]


def discover(root: str | Path) -> list[Frame]:
    """All frames under a dataset root, sorted by id; a clear error for a wrong folder."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: dataset folder not found")
    frames: list[Frame] = []
    sim = root / "simulated"
    if sim.is_dir():
        for group in sorted(p for p in sim.iterdir() if p.is_dir()):
            calib = _sim_calibration(sim, group)
            for img in sorted(group.iterdir()):
                if img.suffix.lower() not in IMAGE_SUFFIXES or img.stem.endswith("_mask"):
                    continue
                gt = img.with_suffix(".npy")
                mask = img.with_name(img.stem + "_mask.png")
                frames.append(
                    Frame(
                        id=str(img.relative_to(root).with_suffix("")),
                        kind="simulated" if gt.exists() else "real",
                        calibration=calib,
                        stereo=img,
                        ground_truth=gt if gt.exists() else None,
                        mask=mask if mask.exists() else None,
                    )
                )
    real = root / "real"
    if real.is_dir():
        for sub in sorted(p for p in real.iterdir() if p.is_dir()):
            calib = sub / "calibration.yaml"
            calib = calib if calib.exists() else real / "camera_calibration.yaml"
            for left in sorted(sub.glob("*left*")):
                if left.suffix.lower() not in IMAGE_SUFFIXES:
                    continue
                right = left.with_name(left.name.replace("left", "right", 1))
                if not right.exists():
                    continue
                fid = str(left.relative_to(root).with_suffix("")).replace("left", "", 1)
                fid = re.sub(r"__+", "_", fid)
                frames.append(Frame(id=fid, kind="real", calibration=calib, left=left, right=right))
    if not frames:
        raise FileNotFoundError(
            f"{root}: no frames found (expected simulated/<group>/*.png or real/<sub>/*left*.png)"
        )
    return frames


def _sim_calibration(sim: Path, group: Path) -> Path:
    own = group / "calibration.yaml"
    if own.exists():
        return own
    m = re.search(r"(\d+)$", group.name)
    n = int(m.group(1)) if m else 0
    name = "blend_calibration.yaml" if n <= PAPER_OLD_GROUPS else "blend_calibration_new.yaml"
    return sim / name


def frame_unit(calibration: Path) -> str | None:
    """Default unit when the file has no Units key: cm for the paper's Blender calibrations."""
    return "cm" if calibration.name.startswith("blend_calibration") else None


def load_frame(frame: Frame) -> tuple[StereoPair, StereoCalibration, np.ndarray | None]:
    """The pair, its calibration and the dense ground-truth curve (calib units) if any."""
    calib = load_calibration(frame.calibration, unit=frame_unit(frame.calibration))
    if frame.stereo is not None:
        pair = load_pair(stereo=frame.stereo, mask=frame.mask)
    else:
        pair = load_pair(left=frame.left, right=frame.right)
    gt = load_ground_truth(frame.ground_truth) if frame.ground_truth is not None else None
    return pair, calib, gt


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
        s = calib.mm_per_unit
        gt = visible_part(gt, calib.P1, calib.P2, calib.image_size)  # a thread may leave the view
        e = curve_errors(pts * s, gt * s)
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
        out[side] = (uv, reprojection_errors(uv, mask) if errors else None)
    return out
