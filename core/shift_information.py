"""How much a stereo window can say about a horizontal shift: the doubt of the MVS measurement.

The two-view refinement (core/refine.py) takes the MVS curve at the points of H as a
measurement of the disparity there, its s.d. the stereo's robust spread about the curve times
the half-width of Eq. (7)'s bounds over their median. Neither says where the SSD of Eq. (2)
could not fix the disparity at all: a window on a stretch of thread that runs along the
image rows (the epipolar lines) and carries no shading along its length matches equally well
anywhere along the row. The SSD's disparity from a window W (the Cramer-Rao bound of a
shift between two noisy copies of one signal) has the variance

    var(d) = 2 sigma_n^2 / J,    J = sum over the pixels p' of W in P_L of (dI_L/dx (p'))^2,

the window's information about a horizontal shift (Lucas and Kanade's 1-D structure term).
A window across a steep thread holds its two edges (large J); one along a uniform thread
running along the rows holds almost no horizontal gradient (J near 0); one on a thread with
shading or texture along its length holds that texture (the SSD locks on it, J large again),
which the angle of the thread alone cannot tell. The refinement scales each point's s.d. by
sqrt(median J / J_i) (the typical point keeps the spread measured for it; ``scale``).
"""

from __future__ import annotations

from typing import Final

import numpy as np

WINDOW_HALF: Final = 4  # px: the stereo stage's default 9 x 9 SSD window of Eq. (2)
MIN_SHARE: Final = 1e-6  # J below this share of the median counts as this share: finite s.d.


def shift_information(
    image: np.ndarray, mask: np.ndarray, xy: np.ndarray, half: int = WINDOW_HALF
) -> np.ndarray:
    """J (P,) at the points ``xy`` (P, 2) float (x px, y px): the sum, over the pixels of the
    (2 half + 1)^2 window around each point's pixel that lie in ``mask`` (H, W) bool, of the
    squared central difference of ``image`` (H, W) along the rows (one-sided at the image's
    left and right border). Windows are cut at the image border; a point outside the image
    or not finite has J = 0."""
    if image.ndim != 2 or mask.shape != image.shape:
        raise ValueError(f"image {image.shape} and mask {mask.shape} must be one (H, W)")
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"points must be (P, 2) (x, y), got {xy.shape}")
    if half < 0:
        raise ValueError(f"window half-size must be >= 0, got {half}")
    H, W = image.shape
    finite = np.all(np.isfinite(xy), axis=1)
    c = np.rint(np.where(finite[:, None], xy, -1e9)).clip(-1, max(H, W) + 1).astype(np.int64)
    inside = finite & (c[:, 0] >= 0) & (c[:, 0] < W) & (c[:, 1] >= 0) & (c[:, 1] < H)
    d = np.arange(-half, half + 1)
    x = c[:, 0, None, None] + d[None, None, :]  # (P, 1, n): columns of each window
    y = c[:, 1, None, None] + d[None, :, None]  # (P, n, 1): rows
    on = inside[:, None, None] & (x >= 0) & (x < W) & (y >= 0) & (y < H)
    xs, ys = np.clip(x, 0, W - 1), np.clip(y, 0, H - 1)
    xs, ys = np.broadcast_arrays(xs, ys)
    img = np.asarray(image, dtype=np.float64)
    right = img[ys, np.minimum(xs + 1, W - 1)]
    left = img[ys, np.maximum(xs - 1, 0)]
    span = np.minimum(xs + 1, W - 1) - np.maximum(xs - 1, 0)  # 2 inside, 1 at the border
    gx = (right - left) / np.maximum(span, 1)
    on &= mask[ys, xs]
    return np.where(on, gx * gx, 0.0).sum(axis=(1, 2))


def scale(info: np.ndarray, use: np.ndarray) -> np.ndarray:
    """(P,) factors sqrt(median J / J_i) for the s.d. of the points of H, the median over the
    points ``use`` (P,) bool with J > 0; ones where no such point exists (nothing to compare)."""
    info = np.asarray(info, dtype=np.float64)
    if use.shape != info.shape:
        raise ValueError(f"use {use.shape} and information {info.shape} differ in shape")
    ref = info[use & (info > 0)]
    if ref.size == 0:
        return np.ones_like(info)
    med = float(np.median(ref))
    return np.sqrt(med / np.maximum(info, MIN_SHARE * med))
