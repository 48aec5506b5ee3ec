"""Reading images, calibrations and ground truth from disk (the core itself does no I/O), and
the load step that undistorts and rectifies a raw pair before the pipeline (core/rectify.py).

Calibration files: OpenCV FileStorage YAML (K1 D1 K2 D2 R T ImageSize, optional Units and
Rectified), a Kalibr ``camchain.yaml`` (cam0 = left, cam1 = right), or the two ROS
``camera_info`` YAML files of a stereo pair (left file, and ``right=`` the right one).
Lengths: OpenCV files state ``Units`` or take ``unit`` (default mm); Kalibr and ROS files are
in metres unless ``unit`` says otherwise.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy.interpolate import BSpline

from threadrecon.core.calibration import (
    CalibrationError,
    StereoCalibration,
    from_kalibr_camchain,
    from_ros_camera_info,
    parse_calibration,
)
from threadrecon.core.rectify import Rectification, rectification, rectify_pair
from threadrecon.core.segmentation import StereoPair, split_side_by_side

GT_SAMPLES = 2000  # dense samples of a ground-truth spline for the curve metrics


def read_image(path: str | Path) -> np.ndarray:
    """RGB uint8 image; a clear error when the file is missing or not an image."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file not found")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_mask(path: str | Path) -> np.ndarray:
    """(H, W) bool mask: pixels brighter than 127 in a greyscale image."""
    img = read_image(path)
    return img[:, :, 0] > 127


def load_pair(
    left: str | Path | None = None,
    right: str | Path | None = None,
    stereo: str | Path | None = None,
    mask: str | Path | None = None,
    mask_left: str | Path | None = None,
    mask_right: str | Path | None = None,
) -> StereoPair:
    """A rectified pair from two images or one side-by-side composite, with optional masks."""
    if stereo is not None:
        if left is not None or right is not None:
            raise ValueError("give either --stereo or --left/--right, not both")
        L, R = split_side_by_side(read_image(stereo))
    elif left is not None and right is not None:
        L, R = read_image(left), read_image(right)
    else:
        raise ValueError("need --left and --right, or --stereo")
    mL = mR = None
    if mask is not None:
        whole = read_mask(mask)
        _same_size(mask, whole, (L.shape[0], 2 * L.shape[1]), "side-by-side image")
        mL, mR = whole[:, : L.shape[1]], whole[:, L.shape[1] :]
    elif mask_left is not None or mask_right is not None:
        if mask_left is None or mask_right is None:
            raise ValueError("give both masks or neither")
        mL, mR = read_mask(mask_left), read_mask(mask_right)
        _same_size(mask_left, mL, L.shape[:2], "left image")
        _same_size(mask_right, mR, R.shape[:2], "right image")
    return StereoPair(L, R, mL, mR)


def _same_size(path: str | Path, mask: np.ndarray, shape: tuple[int, ...], what: str) -> None:
    if mask.shape[:2] != tuple(shape[:2]):
        h, w = mask.shape[:2]
        raise ValueError(
            f"{path}: the mask is {w}x{h} px but the {what} is {shape[1]}x{shape[0]} px"
        )


def load_calibration(
    path: str | Path, unit: str | None = None, right: str | Path | None = None
) -> StereoCalibration:
    """Read a stereo calibration; errors name the file and the key.

    ``path``: OpenCV FileStorage YAML, a Kalibr camchain, or (with ``right``) the left ROS
    camera_info YAML. The format is told from the content.
    """
    path = Path(path)
    text = _read_text(path)
    if right is not None:
        right = Path(right)
        return from_ros_camera_info(
            _yaml(text, path), _yaml(_read_text(right), right), unit=unit,
            source=f"{path} + {right}",
        )  # fmt: skip
    if text.lstrip().startswith("%YAML:") or "!!opencv-matrix" in text:
        return _opencv(text, path, unit)
    data = _yaml(text, path) if text.strip() else None
    if isinstance(data, dict) and "cam0" in data:
        return from_kalibr_camchain(data, unit=unit, source=str(path))
    if isinstance(data, dict) and any(k in data for k in ("camera_matrix", "K", "k")):
        raise CalibrationError(
            f"{path}: a ROS camera_info describes one camera: give the right camera's file "
            "too (--calib-right)"
        )
    return _opencv(text, path, unit)


def _read_text(path: Path) -> str:
    try:
        return path.read_text()
    except OSError as exc:
        raise CalibrationError(
            f"{path}: cannot read calibration file ({exc.strerror or exc})"
        ) from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text calibration file") from None


def _opencv(text: str, path: Path, unit: str | None) -> StereoCalibration:
    try:
        return parse_calibration(text, source=str(path), unit=unit)
    except cv2.error as exc:
        raise CalibrationError(f"{path}: malformed calibration file ({exc.err})") from None


def _yaml(text: str, path: Path) -> object:
    import yaml  # PyYAML: ROS and Kalibr files are plain YAML, not OpenCV FileStorage

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path}: not a YAML file ({str(exc).splitlines()[0]})") from None


def prepare_pair(
    pair: StereoPair, calib: StereoCalibration
) -> tuple[StereoPair, StereoCalibration, Rectification]:
    """The load step: the pair the pipeline runs on (undistorted and rectified when the
    calibration says the images are raw), its calibration, and the rectification (identity
    for an already rectified pair) that maps results back to the left camera frame."""
    rect = rectification(calib)
    return rectify_pair(pair, rect), rect.calib, rect


def ground_truth_curve(ctrl: np.ndarray, n: int = GT_SAMPLES) -> np.ndarray:
    """Dense points of the dataset's ground truth: clamped cubic B-spline, knots
    [0, 0, 0, linspace(0, 1, n - 2), 1, 1, 1] (the paper's dataset convention)."""
    ctrl = np.asarray(ctrl, dtype=np.float64)
    if ctrl.ndim != 2 or ctrl.shape[1] != 3 or len(ctrl) < 4:
        raise ValueError(f"ground truth must be (n >= 4, 3) control points, got {ctrl.shape}")
    m = len(ctrl)
    t = np.concatenate([[0.0, 0.0, 0.0], np.linspace(0.0, 1.0, m - 2), [1.0, 1.0, 1.0]])
    return BSpline(t, ctrl, 3)(np.linspace(0.0, 1.0, n))


def load_ground_truth(path: str | Path) -> np.ndarray:
    path = Path(path)
    try:
        ctrl = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable ground truth ({exc})") from None
    return ground_truth_curve(ctrl)
