"""Stereo calibration: OpenCV FileStorage YAML in, rectified projection matrices out.

The paper's pairs are already rectified; like the paper we still call
``cv2.stereoRectify(..., flags=cv2.CALIB_ZERO_DISPARITY)`` to obtain ``P1``, ``P2`` and the
disparity-to-depth matrix ``Q`` of Eq. (4).

Frame convention (used throughout ``core``): the left rectified camera frame of OpenCV,
x right, y down, z forward, in the calibration's length unit. Pixels are ``(x, y)`` =
``(col, row)`` with integer values at pixel centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

REQUIRED_KEYS = ("K1", "D1", "K2", "D2", "R", "T", "ImageSize")


class CalibrationError(ValueError):
    """A calibration file is missing, unreadable, or has a missing or malformed key, or its
    geometry is not a usable stereo rig (see :func:`make_calibration`)."""


ROTATION_TOL = 1e-3  # |R^T R - I| and |det R - 1| above this: not a rotation (6-digit files pass)
ROW_ALIGN_TOL = 1e-3  # vertical offset of the rectified right camera, fraction of the baseline


@dataclass(frozen=True)
class StereoCalibration:
    """Rectified stereo geometry.

    ``P1``, ``P2``: (3, 4) projection matrices of the rectified left and right cameras.
    ``Q``: (4, 4) disparity-to-depth matrix, Eq. (4).
    ``image_size``: (rows, cols) in px.
    ``unit``: length unit of ``T`` and of every reconstructed point ("mm" or "cm").
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: tuple[int, int]
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    unit: str = "mm"

    @property
    def G(self) -> np.ndarray:
        """(3, 3) camera matrix of the rectified left camera (the paper's G in Eq. (9))."""
        return self.P1[:, :3]

    @property
    def focal(self) -> float:
        """Rectified focal length f in px."""
        return float(self.P1[0, 0])

    @property
    def baseline(self) -> float:
        """Baseline B in calibration units (> 0)."""
        return float(abs(self.P2[0, 3] / self.P2[0, 0]))

    @property
    def mm_per_unit(self) -> float:
        return {"mm": 1.0, "cm": 10.0, "m": 1000.0}[self.unit]

    def disparity_to_depth(self, d: np.ndarray | float) -> np.ndarray:
        """Depth Z = f B / d for disparity ``d`` in px (Eqs. (4)-(5) with rectified Q)."""
        return self.focal * self.baseline / np.asarray(d, dtype=float)

    def depth_to_disparity(self, z: np.ndarray | float) -> np.ndarray:
        return self.focal * self.baseline / np.asarray(z, dtype=float)


def make_calibration(
    K1: np.ndarray,
    D1: np.ndarray,
    K2: np.ndarray,
    D2: np.ndarray,
    R: np.ndarray,
    T: np.ndarray,
    image_size: tuple[float, float],
    unit: str = "mm",
    source: str = "calibration",
) -> StereoCalibration:
    """Build a :class:`StereoCalibration`; ``image_size`` is (rows, cols).

    Sanity checks, each a :class:`CalibrationError` naming the problem: finite values, positive
    focal lengths in K1 and K2 (last row [0 0 1]), R a proper rotation (orthonormal, det +1), a
    finite positive whole-number ImageSize, and after rectification a baseline along x with the
    right camera to the right of the left one (the disparity search of Eq. (3) looks left).
    """
    shapes = {"K1": (3, 3), "K2": (3, 3), "R": (3, 3)}
    arrays = {"K1": K1, "D1": D1, "K2": K2, "D2": D2, "R": R, "T": T}
    clean: dict[str, np.ndarray] = {}
    for key, value in arrays.items():
        a = np.asarray(value, dtype=np.float64)
        if key in shapes and a.shape != shapes[key]:
            raise CalibrationError(f"{source}: key {key} must be 3x3, got shape {a.shape}")
        if key == "T" and a.size != 3:
            raise CalibrationError(f"{source}: key T must have 3 values, got shape {a.shape}")
        if key in ("D1", "D2") and a.size not in (4, 5, 8, 12, 14):
            raise CalibrationError(f"{source}: key {key} must have 4, 5, 8, 12 or 14 values")
        if not np.all(np.isfinite(a)):
            raise CalibrationError(f"{source}: key {key} has non-finite values")
        clean[key] = a
    for key in ("K1", "K2"):
        K = clean[key]
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise CalibrationError(
                f"{source}: key {key} must have positive focal lengths, got fx = {K[0, 0]:g}, "
                f"fy = {K[1, 1]:g}"
            )
        if not np.allclose(K[2], [0.0, 0.0, 1.0]):
            raise CalibrationError(f"{source}: key {key} must have last row [0 0 1], got {K[2]}")
    R = clean["R"]
    orth = float(np.max(np.abs(R.T @ R - np.eye(3))))
    det = float(np.linalg.det(R))
    if orth > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
        raise CalibrationError(
            f"{source}: key R is not a proper rotation (|R^T R - I| = {orth:.3g}, "
            f"det R = {det:.3g}; expected 0 and 1)"
        )
    size = np.asarray(image_size, dtype=np.float64).ravel()
    if size.size != 2 or not np.all(np.isfinite(size)) or np.any(size != np.round(size)):
        raise CalibrationError(
            f"{source}: key ImageSize must be two finite whole numbers [rows, cols], got "
            f"{size.tolist()}"
        )
    rows, cols = (int(v) for v in size)
    if rows <= 0 or cols <= 0:
        raise CalibrationError(f"{source}: key ImageSize must be positive [rows, cols]")
    if unit not in ("mm", "cm", "m"):
        raise CalibrationError(f"{source}: key Units must be mm, cm or m, got {unit!r}")
    T3 = clean["T"].reshape(3, 1)
    if abs(T3[0, 0]) <= 0:
        raise CalibrationError(f"{source}: key T has zero baseline")
    _, _, P1, P2, Q, _, _ = cv2.stereoRectify(
        clean["K1"],
        clean["D1"].reshape(1, -1),
        clean["K2"],
        clean["D2"].reshape(1, -1),
        (cols, rows),
        clean["R"],
        T3,
        flags=cv2.CALIB_ZERO_DISPARITY,
    )
    _check_rectified(P1, P2, source)
    return StereoCalibration(
        K1=clean["K1"],
        D1=clean["D1"],
        K2=clean["K2"],
        D2=clean["D2"],
        R=clean["R"],
        T=T3.ravel(),
        image_size=(rows, cols),
        P1=P1,
        P2=P2,
        Q=Q,
        unit=unit,
    )


def _check_rectified(P1: np.ndarray, P2: np.ndarray, source: str) -> None:
    """The rectified rig must have a positive focal length and a baseline along +x."""
    if not (np.all(np.isfinite(P1)) and np.all(np.isfinite(P2))):
        raise CalibrationError(f"{source}: rectification gave non-finite projection matrices")
    f = P1[0, 0]
    if not (f > 0 and P2[0, 0] > 0):
        raise CalibrationError(f"{source}: rectified focal length must be positive, got {f:g}")
    tx, ty = P2[0, 3] / P2[0, 0], P2[1, 3] / P2[0, 0]
    if abs(ty) > ROW_ALIGN_TOL * abs(tx) or P2[2, 3] != 0 or tx == 0:
        raise CalibrationError(
            f"{source}: after rectification the baseline is not along x (offset x {-tx:.4g}, "
            f"y {-ty:.4g}); key T must hold a mostly horizontal baseline"
        )
    if tx > 0:
        raise CalibrationError(
            f"{source}: after rectification the right camera lies left of the left camera "
            f"(baseline {-tx:.4g}): swap the images or the sign of key T"
        )


def parse_calibration(
    text: str, source: str = "calibration", unit: str | None = None
) -> StereoCalibration:
    """Parse OpenCV FileStorage YAML text (keys K1, D1, K2, D2, R, T, ImageSize [rows, cols]).

    The optional string key ``Units`` gives the length unit; without it ``unit`` (default "mm").
    """
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):  # OpenCV's parser raises on text that is not YAML/XML
        raise CalibrationError(f"{source}: not an OpenCV FileStorage YAML file") from None
    try:
        if not fs.isOpened():
            raise CalibrationError(f"{source}: not an OpenCV FileStorage YAML file")
        values: dict[str, np.ndarray] = {}
        for key in REQUIRED_KEYS:
            node = fs.getNode(key)
            if node.empty() or node.isNone():
                raise CalibrationError(f"{source}: missing key {key}")
            mat = node.mat() if node.isMap() else None
            if mat is None and node.isSeq():
                mat = np.array([node.at(i).real() for i in range(node.size())])
            if mat is None:
                raise CalibrationError(f"{source}: key {key} is not a matrix")
            values[key] = np.asarray(mat, dtype=np.float64)
        size = values["ImageSize"].ravel()
        if size.size != 2:
            raise CalibrationError(
                f"{source}: key ImageSize must hold [rows, cols], got {size.size} values"
            )
        units_node = fs.getNode("Units")
        file_unit = (
            units_node.string() if not units_node.empty() and units_node.isString() else None
        )
    finally:
        fs.release()
    return make_calibration(
        values["K1"],
        values["D1"],
        values["K2"],
        values["D2"],
        values["R"],
        values["T"],
        (size[0], size[1]),
        unit=file_unit or unit or "mm",
        source=source,
    )
