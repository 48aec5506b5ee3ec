"""A raw (unrectified, distorted) stereo rig looking at a generated frame's thread.

The generator renders a rectified pair (camera matrix K, baseline B). A raw rig looks at the
same scene with its cameras rotated (p_raw_i = Ra_i p_rect_i) and with lens distortion D_i.
Its views are made in one of two ways:

- ``"render"`` (default): the thread is rendered directly in each raw camera: the 3D
  centreline projected with K, D (``cv2.projectPoints``) and drawn by the generator's own tube
  renderer, so the raw pair is as crisp as the rectified one and the load step's remap is the
  only resampling, as with a real rig;
- ``"resample"``: each raw pixel is undistorted and rotated into the rectified view
  (``cv2.undistortPoints`` with R and P), and the rendered rectified image is sampled there
  (Lanczos; beyond the rendered view: the background colour). The raw pair is then resampled
  twice before the pipeline sees it (here and in the load step).

The rig's OpenCV calibration is R = Ra_2 Ra_1^T, T = Ra_2 (-B, 0, 0); the true curve in the
raw left frame is Ra_1 p_rect.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from scipy.interpolate import BSpline

from threadrecon.core.calibration import StereoCalibration, make_calibration
from threadrecon.core.rectify import Rectification
from threadrecon.core.segmentation import StereoPair
from threadrecon.core.synthetic import (
    RenderParams,
    StereoCamera,
    SyntheticFrame,
    SyntheticParams,
    ThreadParams,
    generate_frame,
)

# the generator's tube renderer, reused so that the raw and the rectified views of a thread are
# drawn alike (the same coverage profile, shading and highlight)
from threadrecon.core.synthetic import _render_tube as render_tube

RAW_MARGIN_PX = 40.0  # px: the thread's distance to the rendered view's border
RENDER_STEP_PX = 0.4  # px: max image step of the rendered polyline (the generator's own)
THREAD_GREY = (120.0, 120.0, 120.0)  # the generator's thread colour on a flat background
Views = Literal["render", "resample"]


@dataclass(frozen=True)
class RawRig:
    frame: SyntheticFrame
    reference: StereoPair  # the rectified pair at working resolution, with masks
    reference_calib: StereoCalibration  # its calibration (K, B, mm)
    pair: StereoPair  # raw images and masks
    calib: StereoCalibration  # raw calibration: K_raw, D, R, T (mm)
    K: np.ndarray
    D1: np.ndarray
    D2: np.ndarray
    Ra1: np.ndarray  # p_raw_left = Ra1 p_rect_left
    Ra2: np.ndarray
    truth_left: np.ndarray  # (M, 3) true centerline in the raw left camera frame, mm


def rotation(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    rvec = np.deg2rad([rx_deg, ry_deg, rz_deg]).reshape(3, 1)
    return cv2.Rodrigues(rvec)[0]


def _rendered_views(
    frame: SyntheticFrame,
    diameter: float,
    render: RenderParams,
    K: np.ndarray,
    D: np.ndarray,
    Ra: np.ndarray,
    centre: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The raw camera's image and mask, rendered directly: the thread seen by a camera at
    ``centre`` (rectified left frame, mm), rotated by ``Ra`` and distorting by ``D``."""
    cam = frame.camera
    if render != RenderParams(blur_sigma=render.blur_sigma):
        raise ValueError("the raw rig renders the default flat-background frame (and blur) only")
    if not np.isclose(K[0, 0], cam.fx) or not np.isclose(K[1, 1], cam.fx):
        raise ValueError(f"the tube renderer's widths assume fx = fy = {cam.fx}, got K = {K}")
    truth = frame.truth
    spl = BSpline(truth.knots, truth.control_points, truth.degree)
    m = 2000
    for _ in range(4):  # refine until the image step is below RENDER_STEP_PX
        p_raw = (spl(np.linspace(0.0, 1.0, m)) - centre) @ Ra.T
        uv = _project(p_raw, K, D)
        step = float(np.linalg.norm(np.diff(uv, axis=0), axis=1).max())
        if step <= RENDER_STEP_PX:
            break
        m = int(math.ceil(m * step / RENDER_STEP_PX * 1.05))
    # the renderer draws a tube fx d / z px wide: the lens magnifies it locally by
    # sqrt|det J| (J: the distortion's Jacobian), i.e. it looks as wide as at depth z / that
    z_eff = p_raw[:, 2] / np.sqrt(np.abs(_distortion_det(p_raw, D)))
    background = np.full((cam.height, cam.width, 3), render.background_level, np.float32)
    grey = np.asarray(THREAD_GREY, np.float32)
    img, cov = render_tube(uv, z_eff, cam, diameter, grey, render.specular, background)
    if render.blur_sigma > 0:  # the optics' blur, in the raw camera's pixels, as the generator
        img = cv2.GaussianBlur(img, (0, 0), render.blur_sigma)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), cov >= 0.5


def _project(p: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N, 3) points of a camera's frame -> (N, 2) distorted pixels (x, y)."""
    zero = np.zeros(3)
    uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), zero, zero, K, D)
    return uv.reshape(-1, 2)


def _distortion_det(p: np.ndarray, D: np.ndarray) -> np.ndarray:
    """(N,) det of the Jacobian of the distortion at the normalised image points of ``p``."""
    xn = p[:, :2] / p[:, 2:3]
    h = 1e-6  # normalised units: central differences exact to ~1e-10 for a polynomial model
    one = np.eye(3)

    def dist(q: np.ndarray) -> np.ndarray:
        return _project(np.column_stack([q, np.ones(len(q))]), one, D)

    jx = (dist(xn + [h, 0.0]) - dist(xn - [h, 0.0])) / (2 * h)
    jy = (dist(xn + [0.0, h]) - dist(xn - [0.0, h])) / (2 * h)
    return jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0]


def _resampled_views(
    img: np.ndarray, mask: np.ndarray, K: np.ndarray, D: np.ndarray, Ra: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The raw camera's image and mask of what the rectified camera ``K`` sees."""
    h, w = img.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    # raw pixel -> undistorted ray in the raw frame -> rotate to rectified (Ra^T) -> project K
    rect = cv2.undistortPoints(
        pts,
        K,
        D,
        R=Ra.T,
        P=K,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9),
    )
    mx = rect[:, 0, 0].reshape(h, w).astype(np.float32)
    my = rect[:, 0, 1].reshape(h, w).astype(np.float32)
    raw_mask = cv2.remap(mask.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderValue=0.0)
    out = cv2.remap(img, mx, my, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)
    outside = (mx < -0.5) | (mx > w - 0.5) | (my < -0.5) | (my > h - 0.5)
    out[outside] = np.median(img.reshape(-1, img.shape[2]), axis=0).astype(img.dtype)
    return out, raw_mask >= 0.5  # beyond the rendered view the raw camera sees background


def _calib(
    K: np.ndarray,
    D1: np.ndarray,
    D2: np.ndarray,
    R: np.ndarray,
    T: np.ndarray,
    size: tuple[int, int],
) -> StereoCalibration:
    return make_calibration(K1=K, D1=D1, K2=K, D2=D2, R=R, T=T, image_size=size, unit="mm")


@functools.lru_cache(maxsize=8)
def raw_rig(
    seed: int,
    angles1: tuple[float, float, float] = (1.5, -2.0, 1.0),
    angles2: tuple[float, float, float] = (-1.0, 1.5, -0.5),
    distortion: bool = True,
    views: Views = "render",
    blur_sigma: float = 0.0,
) -> RawRig:
    """A raw pair of the generated frame ``seed`` seen by rotated, distorting cameras, its
    views rendered directly or resampled from the rectified pair (``views``, module doc)."""
    cam = StereoCamera()
    # the raw cameras' views are rotated by ~2 deg (up to ~25 px at the borders): a wider margin
    # keeps the whole thread in both raw views, so both inputs see the same thread
    thread = ThreadParams(margin_px=RAW_MARGIN_PX)
    params = SyntheticParams(camera=cam, thread=thread, render=RenderParams(blur_sigma=blur_sigma))
    frame = generate_frame(params, rng=seed)
    K = np.asarray(cam.K, dtype=np.float64)
    size = (cam.height, cam.width)
    D1 = np.array([-0.08, 0.02, 0.0005, -0.0003, 0.0]) if distortion else np.zeros(5)
    D2 = np.array([-0.06, 0.015, -0.0004, 0.0002, 0.0]) if distortion else np.zeros(5)
    Ra1, Ra2 = rotation(*angles1), rotation(*angles2)
    t = np.array([-cam.baseline, 0.0, 0.0])
    if views == "render":
        d = thread.diameter_mm
        left, mask_left = _rendered_views(frame, d, params.render, K, D1, Ra1, np.zeros(3))
        right, mask_right = _rendered_views(frame, d, params.render, K, D2, Ra2, -t)
    elif views == "resample":
        left, mask_left = _resampled_views(frame.left, frame.mask_left, K, D1, Ra1)
        right, mask_right = _resampled_views(frame.right, frame.mask_right, K, D2, Ra2)
    else:
        raise ValueError(f"views must be 'render' or 'resample', got {views!r}")
    raw = StereoPair(left, right, mask_left, mask_right)
    zero = np.zeros(5)
    return RawRig(
        frame=frame,
        reference=StereoPair(frame.left, frame.right, frame.mask_left, frame.mask_right),
        reference_calib=_calib(K, zero, zero, np.eye(3), t, size),
        pair=raw,
        calib=_calib(K, D1, D2, Ra2 @ Ra1.T, Ra2 @ t, size),
        K=K,
        D1=D1,
        D2=D2,
        Ra1=Ra1,
        Ra2=Ra2,
        truth_left=frame.truth.centerline @ Ra1.T,
    )


def rectified_views(rig: RawRig, rect: Rectification, blur_sigma: float = 0.0) -> StereoPair:
    """The raw rig's rectified pair rendered directly in its rectified cameras (K_i =
    P_i[:, :3], rotated by R_i Ra_i from the reference cameras, no distortion) with the raw
    rig's ``blur_sigma``: a rectification without resampling, the floor of the load step's
    (``rect`` is ``rectification(rig.calib)``)."""
    if rect.identity:
        raise ValueError("the rig needs no rectification: its raw views are the rectified ones")
    d = ThreadParams(margin_px=RAW_MARGIN_PX).diameter_mm
    render = RenderParams(blur_sigma=blur_sigma)
    t = np.array([-rig.frame.camera.baseline, 0.0, 0.0])
    zero = np.zeros(5)
    left, mask_left = _rendered_views(
        rig.frame, d, render, rect.calib.K1, zero, rect.R1 @ rig.Ra1, np.zeros(3)
    )
    right, mask_right = _rendered_views(
        rig.frame, d, render, rect.calib.K2, zero, rect.R2 @ rig.Ra2, -t
    )
    return StereoPair(left, right, mask_left, mask_right)


def opencv_yaml(calib: StereoCalibration) -> str:
    """``calib`` as OpenCV FileStorage YAML text (what the paper's files look like)."""
    fs = cv2.FileStorage("out.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    for key in ("K1", "D1", "K2", "D2", "R"):
        fs.write(
            key,
            np.asarray(getattr(calib, key), dtype=np.float64).reshape(-1, 3)
            if key[0] in "KR"
            else getattr(calib, key).reshape(1, -1),
        )
    fs.write("T", calib.T.reshape(3, 1))
    fs.write("ImageSize", np.array([calib.image_size], dtype=np.float64))
    fs.write("Units", calib.unit)
    return fs.releaseAndGetString()


def ros_camera_info(calib: StereoCalibration) -> tuple[dict, dict]:
    """The two camera_info YAML mappings that ROS's camera_calibration writes for ``calib``."""
    rows, cols = calib.image_size
    R1, R2, P1, P2, *_ = cv2.stereoRectify(
        calib.K1,
        calib.D1.reshape(1, -1),
        calib.K2,
        calib.D2.reshape(1, -1),
        (cols, rows),
        calib.R,
        calib.T.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
    )
    out = []
    for name, K, D, R, P in (
        ("left", calib.K1, calib.D1, R1, P1),
        ("right", calib.K2, calib.D2, R2, P2),
    ):
        out.append(
            {
                "image_width": cols,
                "image_height": rows,
                "camera_name": name,
                "camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()},
                "distortion_model": "plumb_bob",
                "distortion_coefficients": {"rows": 1, "cols": D.size, "data": D.ravel().tolist()},
                "rectification_matrix": {"rows": 3, "cols": 3, "data": R.ravel().tolist()},
                "projection_matrix": {"rows": 3, "cols": 4, "data": P.ravel().tolist()},
            }
        )
    return out[0], out[1]
