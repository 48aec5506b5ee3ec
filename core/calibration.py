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
    ``unit``: length unit of ``T`` and of every reconstructed point ("mm", "cm" or "m").
    ``rectified``: whether the images this calibration describes are already undistorted and
    rectified. ``None`` (default): decided from the numbers by
    :func:`core.rectify.needs_rectification` (D1 = D2 = 0, R = I, K1 = K2 up to the rectified
    cameras); ``False`` forces the load step to undistort and rectify; ``True`` forbids it.
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
    rectified: bool | None = None

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
    rectified: bool | None = None,
) -> StereoCalibration:
    """Build a :class:`StereoCalibration`; ``image_size`` is (rows, cols).

    OpenCV's stereo convention: a point p_left in the left camera frame is
    p_right = R p_left + T in the right camera frame; ``T`` in ``unit``.

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
        rectified=rectified,
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
    The optional key ``Rectified`` (0 or 1) sets :attr:`StereoCalibration.rectified`.
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
        rect_node = fs.getNode("Rectified")
        rectified = None if rect_node.empty() or rect_node.isNone() else bool(rect_node.real())
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
        rectified=rectified,
    )


# --- ROS camera_info and Kalibr camchain (already parsed from YAML by the app) ---------------

ROS_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")  # OpenCV's own D layout
KALIBR_LENGTH_UNIT = "m"  # Kalibr writes T_cn_cnm1 in metres
ROS_LENGTH_UNIT = "m"  # REP 103: ROS lengths are metres unless the file's author says otherwise


def from_ros_camera_info(
    left: dict, right: dict, unit: str | None = None, source: str = "camera_info"
) -> StereoCalibration:
    """A stereo calibration from the two ``sensor_msgs/CameraInfo`` of a ROS stereo rig.

    ``left``, ``right``: the YAML of ``camera_calibration`` (``image_width``, ``image_height``,
    ``camera_matrix``, ``distortion_model``, ``distortion_coefficients``,
    ``rectification_matrix``, ``projection_matrix``; each matrix a ``{rows, cols, data}`` map)
    or the message's own fields (``width``, ``height``, ``K``, ``D``, ``R``, ``P``). ROS gives
    each camera's rectifying rotation R_i (p_rect_i = R_i p_i) and the rectified right
    projection P_2 = K' [I | t], t = (T_x, 0, 0); then R = R_2^T R_1 and T = R_2^T t.
    ``unit``: the unit of T_x (the files do not say; default metres, ROS's convention).
    The images they describe are the raw ones: ``rectified`` is left to the numbers.
    """
    cams = []
    for side, info in (("left", left), ("right", right)):
        where = f"{source} ({side})"
        if not isinstance(info, dict):
            raise CalibrationError(f"{where}: not a camera_info mapping")
        size = (_ros_field(info, where, "image_height", "height"),
                _ros_field(info, where, "image_width", "width"))  # fmt: skip
        K = _ros_matrix(info, where, ("camera_matrix", "K", "k"), (3, 3))
        D = _ros_matrix(info, where, ("distortion_coefficients", "D", "d"), None).ravel()
        Rr = _ros_matrix(info, where, ("rectification_matrix", "R", "r"), (3, 3))
        P = _ros_matrix(info, where, ("projection_matrix", "P", "p"), (3, 4))
        model = info.get("distortion_model", "plumb_bob")
        if model not in ROS_DISTORTION_MODELS:
            raise CalibrationError(
                f"{where}: distortion_model {model!r} is not supported "
                f"(supported: {', '.join(ROS_DISTORTION_MODELS)})"
            )
        if D.size == 0:
            D = np.zeros(5)
        cams.append((tuple(int(v) for v in size), K, D, Rr, P))
    (size1, K1, D1, R1, P1), (size2, K2, D2, R2, P2) = cams
    if size1 != size2:
        raise CalibrationError(f"{source}: left image is {size1} px but right is {size2} px")
    if abs(P1[0, 3]) > 1e-9 * abs(P1[0, 0]) or abs(P1[1, 3]) > 1e-9 * abs(P1[1, 1]):
        raise CalibrationError(f"{source}: the left projection_matrix must have P[0:2, 3] = 0")
    if abs(P2[1, 3]) > 1e-9 * abs(P2[1, 1]) or abs(P2[2, 3]) > 1e-12:
        raise CalibrationError(
            f"{source}: only horizontal stereo is supported (right P[1, 3] and P[2, 3] must be 0)"
        )
    if P2[0, 3] == 0:
        raise CalibrationError(
            f"{source}: the right projection_matrix has P[0, 3] = 0 (no baseline): "
            "give the right camera's camera_info, not the left's twice"
        )
    t = np.array([P2[0, 3] / P2[0, 0], 0.0, 0.0])
    for name, Ri in (("left", R1), ("right", R2)):
        if not np.allclose(Ri @ Ri.T, np.eye(3), atol=1e-6) or np.linalg.det(Ri) <= 0:
            raise CalibrationError(f"{source} ({name}): rectification_matrix is not a rotation")
    return make_calibration(
        K1, D1, K2, D2, R2.T @ R1, R2.T @ t, size1,
        unit=unit or ROS_LENGTH_UNIT, source=source,
    )  # fmt: skip


def from_kalibr_camchain(
    chain: dict, unit: str | None = None, source: str = "camchain"
) -> StereoCalibration:
    """A stereo calibration from a Kalibr ``camchain.yaml`` (``cam0`` left, ``cam1`` right).

    Each camera: ``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``,
    ``distortion_model`` ``radtan`` (D = [k1, k2, p1, p2]) or ``none``, ``resolution:
    [width, height]``; ``cam1.T_cn_cnm1`` (4x4) maps cam0 points into cam1, which is OpenCV's
    [R | T]. ``unit``: the unit of its translation (default metres, Kalibr's unit).
    """
    if not isinstance(chain, dict):
        raise CalibrationError(f"{source}: not a Kalibr camchain mapping")
    cams = []
    for name in ("cam0", "cam1"):
        cam = chain.get(name)
        where = f"{source} ({name})"
        if not isinstance(cam, dict):
            raise CalibrationError(f"{source}: missing key {name}")
        if cam.get("camera_model", "pinhole") != "pinhole":
            raise CalibrationError(
                f"{where}: camera_model {cam.get('camera_model')!r} is not supported (pinhole)"
            )
        intr = _as_array(cam.get("intrinsics"), where, "intrinsics")
        if intr.size != 4:
            raise CalibrationError(f"{where}: intrinsics must be [fu, fv, pu, pv]")
        model = cam.get("distortion_model", "none")
        if model == "radtan":
            D = _as_array(cam.get("distortion_coeffs"), where, "distortion_coeffs")
            if D.size != 4:
                raise CalibrationError(f"{where}: radtan distortion_coeffs must have 4 values")
        elif model == "none":
            D = np.zeros(4)
        else:
            raise CalibrationError(
                f"{where}: distortion_model {model!r} is not supported (radtan or none)"
            )
        res = _as_array(cam.get("resolution"), where, "resolution")
        if res.size != 2:
            raise CalibrationError(f"{where}: resolution must be [width, height]")
        K = np.array([[intr[0], 0.0, intr[2]], [0.0, intr[1], intr[3]], [0.0, 0.0, 1.0]])
        cams.append((K, D, (int(res[1]), int(res[0]))))
    T_cn = _as_array(chain["cam1"].get("T_cn_cnm1"), f"{source} (cam1)", "T_cn_cnm1")
    if T_cn.shape != (4, 4):
        raise CalibrationError(f"{source} (cam1): T_cn_cnm1 must be 4x4, got {T_cn.shape}")
    (K1, D1, size1), (K2, D2, size2) = cams
    if size1 != size2:
        raise CalibrationError(f"{source}: cam0 is {size1} px but cam1 is {size2} px")
    return make_calibration(
        K1, D1, K2, D2, T_cn[:3, :3], T_cn[:3, 3], size1,
        unit=unit or KALIBR_LENGTH_UNIT, source=source,
    )  # fmt: skip


def _as_array(value: object, where: str, key: str) -> np.ndarray:
    if value is None:
        raise CalibrationError(f"{where}: missing key {key}")
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: key {key} is not numeric") from None
    return a


def _ros_field(info: dict, where: str, *keys: str) -> int:
    for key in keys:
        if key in info:
            try:
                return int(info[key])
            except (TypeError, ValueError):
                raise CalibrationError(f"{where}: key {key} is not an integer") from None
    raise CalibrationError(f"{where}: missing key {keys[0]}")


def _ros_matrix(
    info: dict, where: str, keys: tuple[str, ...], shape: tuple[int, int] | None
) -> np.ndarray:
    key = next((k for k in keys if k in info), None)
    if key is None:
        raise CalibrationError(f"{where}: missing key {keys[0]}")
    value = info[key]
    data = value.get("data") if isinstance(value, dict) else value
    a = _as_array(data, where, key)
    if shape is not None:
        if a.size != shape[0] * shape[1]:
            raise CalibrationError(
                f"{where}: key {key} must have {shape[0]}x{shape[1]} values, got {a.size}"
            )
        a = a.reshape(shape)
    return a
