"""Undistortion and rectification of a raw calibrated pair, before the pipeline.

The pipeline (Section III of the paper) assumes a rectified pair: the same row in both
images, disparity along x, Eq. (4). A raw pair (lens distortion D != 0, or cameras rotated
by R != I) is remapped once with ``cv2.stereoRectify`` + ``cv2.initUndistortRectifyMap``;
the pipeline then runs on the rectified pair with :attr:`Rectification.calib` (D = 0, R = I),
and its 3D results are in the left *rectified* camera frame. The left camera's own frame
differs by the rectifying rotation R_1 (p_rect = R_1 p_left); :func:`to_left_frame` maps
points back.

Frames: "left" is the left camera's own (unrectified) OpenCV frame, "left_rectified" the
frame of the rectified left camera; both share the left camera centre and the unit of T.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from threadrecon.core.calibration import StereoCalibration, make_calibration
from threadrecon.core.lru import LRU, MISSING
from threadrecon.core.remap_kernel import lanczos4_remap
from threadrecon.core.segmentation import StereoPair

Frame = Literal["left", "left_rectified"]
FRAMES: tuple[Frame, ...] = ("left", "left_rectified")

ROTATION_TOL = 1e-9  # |R_i - I| below this: no rotation (float64 round-off of an identity)
PIXEL_TOL = 1e-3  # px: camera matrices closer than this need no remap (OpenCV rounds cy to f32)
MAP_CACHE_SIZE = 8  # calibrations whose maps stay cached (4 float32 maps, ~5 MB at 640x480)


@dataclass(frozen=True)
class Rectification:
    """How a raw pair becomes the rectified pair the pipeline expects.

    ``raw``: the calibration as read; ``calib``: the calibration of the rectified pair
    (K_i = P_i[:, :3], D = 0, R = I, T = (-B, 0, 0)), what the pipeline gets.
    ``R1``, ``R2``: (3, 3) rectifying rotations, p_rect_i = R_i p_i.
    ``maps``: per side (map_x, map_y), (H, W) float32: the raw pixel (x, y) sampled for each
    rectified pixel; ``None`` when the pair is already rectified (identity).
    """

    raw: StereoCalibration
    calib: StereoCalibration
    R1: np.ndarray
    R2: np.ndarray
    maps: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None

    @property
    def identity(self) -> bool:
        """True when the raw pair is already rectified (no remap, R1 = I)."""
        return self.maps is None


def needs_rectification(calib: StereoCalibration) -> bool:
    """Whether images of ``calib`` must be undistorted/rectified before the pipeline.

    ``calib.rectified`` decides when set; otherwise the pair is taken as rectified iff
    D1 = D2 = 0 and ``cv2.stereoRectify`` would neither rotate the cameras (R_1 = R_2 = I) nor
    change their camera matrices (P_i[:, :3] = K_i within :data:`PIXEL_TOL`).
    """
    if calib.rectified is not None:
        return not calib.rectified
    if np.any(calib.D1 != 0) or np.any(calib.D2 != 0):
        return True
    R1, R2 = _rectifying_rotations(calib)
    eye = np.eye(3)
    if np.abs(R1 - eye).max() > ROTATION_TOL or np.abs(R2 - eye).max() > ROTATION_TOL:
        return True
    return bool(
        np.abs(calib.P1[:, :3] - calib.K1).max() > PIXEL_TOL
        or np.abs(calib.P2[:, :3] - calib.K2).max() > PIXEL_TOL
    )


_cache: LRU[bytes, Rectification] = LRU(MAP_CACHE_SIZE)


def rectification(calib: StereoCalibration) -> Rectification:
    """The :class:`Rectification` of ``calib``: the identity (``calib`` itself) for a rectified
    pair; otherwise the maps, computed once per calibration (cached by its numbers: K, D, R,
    T, size, unit, flag)."""
    if not needs_rectification(calib):  # identity: nothing worth caching, and raw is calib
        eye = np.eye(3)
        return Rectification(raw=calib, calib=calib, R1=eye, R2=eye, maps=None)
    key = _calibration_key(calib)
    hit = _cache.get(key)
    if hit is not MISSING:
        return hit  # type: ignore[return-value]
    out = _compute(calib)
    _cache.put(key, out)
    return out


def rectify_pair(pair: StereoPair, rect: Rectification) -> StereoPair:
    """The rectified pair: images resampled with Lanczos-4, masks by :func:`rectify_mask`.
    Rectified pixels that see outside the raw image get the image's median colour (the
    background of a thread image), so that neither an empty black frame nor a thread cut by
    the raw border and smeared outwards looks like thread; masks are 0 there. An identity
    ``rect`` returns ``pair`` itself (no resampling)."""
    if pair.shape != rect.raw.image_size:
        raise ValueError(
            f"images are {pair.shape} px but the calibration is for {rect.raw.image_size}"
        )
    if rect.maps is None:
        return pair
    views, masks = [], []
    for img, mask, (mx, my) in (
        (pair.left, pair.mask_left, rect.maps[0]),
        (pair.right, pair.mask_right, rect.maps[1]),
    ):
        out = _remap_image(img, mx, my)
        outside = _outside(mx, my, img.shape[:2])
        if outside.any():
            out[outside] = np.median(img.reshape(-1, *img.shape[2:]), axis=0).astype(img.dtype)
        views.append(out)
        if mask is None:
            masks.append(None)
            continue
        m = rectify_mask(mask, img, out, mx, my)
        m[outside] = False  # nothing of the raw mask is seen there
        masks.append(m)
    return StereoPair(views[0], views[1], masks[0], masks[1])


def _remap_image(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """``img`` sampled at the maps with Lanczos-4 at their exact positions (core/remap_kernel.py:
    cv2.remap rounds positions to 1/32 px), the border replicated.

    Lanczos: the least interpolation error of cv2's kernels on a 3-6 px thread (against the
    same thread rendered in the rectified camera, seeds 54 and 61: 5.5 and 4.3 grey levels RMS
    near the thread against 6.0 and 4.9 cubic; with 0.7 px optics blur 1.6 against 1.8).
    Images other than 8-bit go through cv2.remap's Lanczos-4."""
    if img.dtype != np.uint8:
        return cv2.remap(img, mx, my, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)
    src = np.ascontiguousarray(img.reshape(img.shape[0], img.shape[1], -1))
    fx = np.ascontiguousarray(mx, dtype=np.float32)
    fy = np.ascontiguousarray(my, dtype=np.float32)
    out = lanczos4_remap(src, fx, fy)
    np.rint(out, out=out)
    np.clip(out, 0, 255, out=out)
    return out.astype(np.uint8).reshape(mx.shape + img.shape[2:])


EDGE_EPS = 1e-3  # resampled mask values within this of 0 or 1 are sure (float32 weights)
LEVEL_RADIUS = 2  # px: the thread and background levels are means within this (5 x 5)
MIN_CONTRAST = 10.0  # grey levels: a band pixel is decided by its grey only above this contrast
# share of the raw mask's edge pixels the half-coverage rule must explain: ~0.9 for generated
# thread masks (the rule ignores shading and blur), ~0.5 for the same masks a pixel wider/narrower
FOLLOWS_COVERAGE = 0.75


def rectify_mask(
    mask: np.ndarray, raw: np.ndarray, rectified: np.ndarray, mx: np.ndarray, my: np.ndarray
) -> np.ndarray:
    """(H, W) bool: the raw view's mask in the rectified view (``mx``, ``my``: the maps).

    A binary mask says only which raw pixels are in; resampled to another grid its edges are
    uncertain by up to a pixel (bilinear and thresholded at one half: a staircase of the
    staircase, different in each view, where the pipeline's lifted images and run centres
    want the edge where the thread covers half a pixel). Where the resampled mask is strictly
    between 0 and 1 (the band along its edges) a rectified pixel is decided by its own grey
    level in the resampled image: in when its contrast to the local background is at least
    half the local thread's (the levels: the mean grey of the sure-out and sure-in pixels
    within ``LEVEL_RADIUS``), the rule by which the mask follows the thread's half coverage.
    This is used only when the raw mask follows that rule in the raw view (at least
    ``FOLLOWS_COVERAGE`` of its edge pixels, :func:`_follows_coverage`: a mask drawn wider or
    narrower than the thread is resampled as it is), and only where the band pixel sees both
    levels with ``MIN_CONTRAST`` between them; elsewhere the bilinear value >= 0.5."""
    inside = np.asarray(mask).astype(bool)
    m = cv2.remap(inside.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderValue=0.0)
    plain = m >= 0.5
    if not _follows_coverage(inside, _grey(raw)):
        return plain
    band = (m > EDGE_EPS) & (m < 1.0 - EDGE_EPS)
    half = _half_coverage(_grey(rectified), m >= 1.0 - EDGE_EPS, m <= EDGE_EPS, band)
    return np.where(half >= 0, half > 0, plain)


def _grey(img: np.ndarray) -> np.ndarray:
    """(H, W) float32 mean of the channels (the rule compares levels: any channel order)."""
    g = img.astype(np.float32)
    return g.mean(axis=2) if g.ndim == 3 else g


def _half_coverage(
    grey: np.ndarray, sure_in: np.ndarray, sure_out: np.ndarray, which: np.ndarray
) -> np.ndarray:
    """(H, W) int8 at the pixels ``which``: 1 where the grey is at least half-way from the
    local background level (mean of ``sure_out`` within ``LEVEL_RADIUS``) to the local thread
    level (of ``sure_in``), 0 where less, -1 where undecided (a level missing, contrast below
    ``MIN_CONTRAST``) and at every other pixel."""
    k = (2 * LEVEL_RADIUS + 1, 2 * LEVEL_RADIUS + 1)

    def box(a: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(a, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)

    fin, fout = sure_in.astype(np.float32), sure_out.astype(np.float32)
    n_in, n_out = box(fin), box(fout)
    fg = box(fin * grey) / np.maximum(n_in, 1.0)
    bg = box(fout * grey) / np.maximum(n_out, 1.0)
    contrast = bg - fg  # signed: a thread lighter than its background too
    ok = which & (n_in > 0) & (n_out > 0) & (np.abs(contrast) >= MIN_CONTRAST)
    out = np.full(grey.shape, -1, np.int8)
    # (bg - I) / (bg - fg) >= 1/2, written without the division
    out[ok] = ((bg - grey)[ok] * np.sign(contrast[ok]) >= 0.5 * np.abs(contrast[ok])).astype(
        np.int8
    )
    return out


def _follows_coverage(mask: np.ndarray, grey: np.ndarray) -> bool:
    """Whether the raw ``mask`` holds the pixels the thread covers at least half: on its edge
    pixels (in the mask with a 4-neighbour out, or out with one in) the half-coverage rule of
    :func:`_half_coverage` (levels from the pixels off the edge) agrees with the mask on at
    least ``FOLLOWS_COVERAGE`` of those it decides."""
    u = mask.astype(np.uint8)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    inner = mask & (cv2.erode(u, cross, borderType=cv2.BORDER_REPLICATE) == 0)
    outer = ~mask & (cv2.dilate(u, cross) > 0)
    edge = inner | outer
    half = _half_coverage(grey, mask & ~inner, ~mask & ~outer, edge)
    decided = half >= 0
    if not decided.any():
        return False
    agree = (half[decided] > 0) == mask[decided]
    return bool(agree.mean() >= FOLLOWS_COVERAGE)


def _outside(mx: np.ndarray, my: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """(H, W) bool: rectified pixels whose raw sample lies outside the raw image."""
    h, w = shape[:2]
    return (mx < -0.5) | (mx > w - 0.5) | (my < -0.5) | (my > h - 0.5)


def to_left_frame(points: np.ndarray, rect: Rectification) -> np.ndarray:
    """(N, 3) points of the left rectified frame -> the left camera's own frame: R_1^T p."""
    p = _check_points(points)
    return p @ rect.R1  # rows: (R1^T p)^T = p^T R1


def from_left_frame(points: np.ndarray, rect: Rectification) -> np.ndarray:
    """(N, 3) points of the left camera's own frame -> the left rectified frame: R_1 p."""
    p = _check_points(points)
    return p @ rect.R1.T


def in_frame(points: np.ndarray, rect: Rectification, frame: Frame) -> np.ndarray:
    """Points of the left rectified frame expressed in ``frame``."""
    if frame == "left_rectified":
        return _check_points(points)
    if frame == "left":
        return to_left_frame(points, rect)
    raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")


# --- helpers ------------------------------------------------------------------------------


def _rectifying_rotations(calib: StereoCalibration) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = calib.image_size
    R1, R2, *_ = cv2.stereoRectify(
        calib.K1,
        calib.D1.reshape(1, -1),
        calib.K2,
        calib.D2.reshape(1, -1),
        (cols, rows),
        calib.R,
        calib.T.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
    )
    return R1, R2


def _compute(calib: StereoCalibration) -> Rectification:
    R1, R2 = _rectifying_rotations(calib)
    rows, cols = calib.image_size
    maps = tuple(
        cv2.initUndistortRectifyMap(K, D.reshape(1, -1), Ri, P, (cols, rows), cv2.CV_32FC1)
        for K, D, Ri, P in (
            (calib.K1, calib.D1, R1, calib.P1),
            (calib.K2, calib.D2, R2, calib.P2),
        )
    )
    baseline = calib.P2[0, 3] / calib.P2[0, 0]  # -B: the rectified right camera's T_x
    rectified = make_calibration(
        K1=calib.P1[:, :3],
        D1=np.zeros(5),
        K2=calib.P2[:, :3],
        D2=np.zeros(5),
        R=np.eye(3),
        T=np.array([baseline, 0.0, 0.0]),
        image_size=calib.image_size,
        unit=calib.unit,
        source="rectified calibration",
        rectified=True,
    )
    return Rectification(raw=calib, calib=rectified, R1=R1, R2=R2, maps=maps)  # type: ignore[arg-type]


def _calibration_key(calib: StereoCalibration) -> bytes:
    parts = [np.ascontiguousarray(a, dtype=np.float64).tobytes()
             for a in (calib.K1, calib.D1, calib.K2, calib.D2, calib.R, calib.T)]  # fmt: skip
    meta = f"{calib.image_size}|{calib.unit}|{calib.rectified}|{calib.D1.size}|{calib.D2.size}"
    return b"|".join([*parts, meta.encode()])


def _check_points(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"expected (N, 3) points, got shape {p.shape}")
    return p
