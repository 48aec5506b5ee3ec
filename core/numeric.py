"""Small numeric helpers whose results are exactly defined: what numpy returns, faster, and
the exact Euclidean distance transform (OpenCV's, without IPP).

``np.median`` of a short 1-D array costs ~20-40 us, most of it in its generic layers (axis
handling, ``np.mean`` of the middle values, a NaN check on the partitioned copy); a spline
re-run takes three of them.
"""

from __future__ import annotations

import cv2
import numpy as np


def median(a: np.ndarray) -> float:
    """``float(np.median(a))`` of a 1-D float array, bit for bit: the middle order statistic
    (``np.partition``), or the two middle ones' sum halved (``np.mean`` of two values); NaN
    when a value is NaN (numpy's NaN check) or the array is empty (numpy warns there)."""
    a = np.asarray(a)
    if a.ndim != 1 or a.dtype.kind != "f":
        return float(np.median(a))
    n = a.size
    if n == 0 or np.isnan(a).any():
        return float("nan")
    h = n // 2
    if n % 2:
        return float(np.partition(a, h)[h])
    part = np.partition(a, (h - 1, h))
    return float((part[h - 1] + part[h]) / 2.0)


def row_norms(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=1)`` of an (N, 2) or (N, 3) float64 array, bit for bit: numpy's
    own operations in its order (the squares, their sum over a row from its first column on,
    the square root) without its generic layers (a third to a half of its time)."""
    if v.ndim != 2 or v.shape[1] not in (2, 3) or v.dtype != np.float64:
        return np.linalg.norm(v, axis=1)
    sq = v * v
    total = sq[:, 0] + sq[:, 1]
    if v.shape[1] == 3:
        total += sq[:, 2]
    return np.sqrt(total)


def arc_px(step: np.ndarray) -> np.ndarray:
    """(N,) cumulative 2D length (px) of the steps ``step`` (N-1,) from 0, a non-finite step
    counted as 0 (the check reads it for the ends, the strands, the folds and the expected
    errors)."""
    return np.concatenate([[0.0], np.where(np.isfinite(step), step, 0.0).cumsum()])


def distance_to_zero(image: np.ndarray) -> np.ndarray:
    """(H, W) float32, the Euclidean distance (px) of each pixel of the (H, W) uint8 ``image``
    to its nearest zero pixel: ``cv2.distanceTransform(image, DIST_L2, DIST_MASK_PRECISE)`` as
    OpenCV computes it (Felzenszwalb's exact transform: the float32 square root of the integer
    squared distance), never through IPP.

    IPP's ``ippiTrueDistanceTransform``, which OpenCV calls first when it is built with IPP,
    is off by one float32 ulp on ~14 % of the pixels and WHICH pixels depends on the address
    of the output buffer modulo 32 bytes: what numpy's allocator returns, so on what the
    process allocated before. One ulp flipped the split of a crossing's gap between its
    links (``ordering._curve_distance``) and moved e_S of a frame by 3e-4 mm between two
    processes (generated crossing-tissue 13133 #18). The IPP switch is per thread (OpenCV's
    thread-local flag), restored after the call."""
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(
            f"a distance transform needs an (H, W) uint8 image, got {image.shape} {image.dtype}"
        )
    was = cv2.ipp.useIPP()
    cv2.ipp.setUseIPP(False)
    try:
        return cv2.distanceTransform(image, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    finally:
        cv2.ipp.setUseIPP(was)
