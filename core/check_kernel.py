"""Compiled kernels of the check stage (core/check.py, core/check_field.py).

``chamfer_at``: the distance field of a thread mask read at a few pixels, without the
distance transform of the whole mask box. ``cv2.distanceTransform(.., DIST_L2, DIST_MASK_3)``
is the 3x3 chamfer distance with the fixed-point weights ``HV`` (a step along a row or column)
and ``DIAG`` (a diagonal step), 16 fractional bits: its two raster passes give, at each pixel,
the smallest weight of a staircase path to a thread pixel, i.e. ``m DIAG + (M - m) HV`` over the
thread pixels at offset (dx, dy), m = min(|dx|, |dy|), M = max(|dx|, |dy|); the float it writes
is that integer times 2^-16 (exact below 2^24, i.e. 256 px). The kernel takes the same minimum
ring by ring around each pixel (a thread pixel on the Chebyshev ring r weighs at least r HV),
so it returns the very integer the transform would.

``overlap_hits``: the pairs of curve samples within a distance in the image and far apart along
the curve (``check._overlap``), by a sweep over the samples sorted by x.
"""

from __future__ import annotations

import math

import numba
import numpy as np

DIST_SHIFT = 16  # fractional bits of OpenCV's chamfer distances
HV = 62587  # round(float32(0.955) * 2^16): OpenCV's 3x3 L2 weight of a row or column step
DIAG = 89738  # round(float32(1.3693) * 2^16): its weight of a diagonal step


# cache=True: compiled once per machine (numba's cache beside this file), not once per process.
@numba.njit(cache=True, nogil=True)
def chamfer_at(mask, xs, ys, cap, budget):  # noqa: ANN001
    """Chamfer distance (fixed point, ``HV``/``DIAG`` weights) of the pixels (xs[k], ys[k]) of
    the (H, W) bool ``mask`` to its nearest True pixel; ``cap`` where it is ``cap`` or more.
    Returns (distances int64, done): done False when more than ``budget`` pixels would have to
    be visited (the caller then takes the distance transform of the whole box)."""
    h, w = mask.shape
    out = np.empty(len(xs), dtype=np.int64)
    visited = 0
    for k in range(len(xs)):
        x, y = xs[k], ys[k]
        if mask[y, x]:
            out[k] = 0
            continue
        best = cap
        r = 1
        while r * HV < best:
            visited += 8 * r
            if visited > budget:
                return out, False
            r0, r1 = max(y - r, 0), min(y + r, h - 1)
            c0, c1 = max(x - r, 0), min(x + r, w - 1)
            for yy in (y - r, y + r):  # the ring's top and bottom rows
                if 0 <= yy < h:
                    for xx in range(c0, c1 + 1):
                        if mask[yy, xx]:
                            m = min(abs(xx - x), r)
                            c = m * DIAG + (r - m) * HV
                            if c < best:
                                best = c
            for xx in (x - r, x + r):  # its left and right columns, corners excluded
                if 0 <= xx < w:
                    for yy in range(max(r0, y - r + 1), min(r1, y + r - 1) + 1):
                        if mask[yy, xx]:
                            m = abs(yy - y)
                            c = m * DIAG + (r - m) * HV
                            if c < best:
                                best = c
            r += 1
        out[k] = best
    return out, True


@numba.njit(cache=True, nogil=True)
def overlap_hits(x, y, s, r2, gap):  # noqa: ANN001
    """(n,) bool: sample i lies within sqrt(r2) (squared distance <= r2) of a sample j with
    |s[i] - s[j]| > gap. Samples must be finite; the sweep visits them sorted by x."""
    n = len(x)
    hit = np.zeros(n, dtype=np.bool_)
    order = np.argsort(x, kind="mergesort")
    r = np.sqrt(r2)
    for a in range(n):
        i = order[a]
        for b in range(a + 1, n):
            j = order[b]
            if x[j] - x[i] > r * (1.0 + 1e-9):  # beyond r, whatever sqrt's rounding
                break
            dx = x[i] - x[j]
            dy = y[i] - y[j]
            if dx * dx + dy * dy <= r2 and abs(s[i] - s[j]) > gap:
                hit[i] = True
                hit[j] = True
    return hit


@numba.njit(cache=True, nogil=True)
def field_at(dist, x0, y0, reach, uv):  # noqa: ANN001
    """``MaskField.at`` over (N, 2) points: the field at each point's nearest pixel of the box
    plus the point's distance to that pixel, saturated at ``reach``; ``reach`` where not
    finite."""
    h, w = dist.shape
    out = np.empty(len(uv))
    for k in range(len(uv)):
        x, y = uv[k, 0], uv[k, 1]
        if not (np.isfinite(x) and np.isfinite(y)):
            out[k] = reach
            continue
        qx, qy = x - x0, y - y0
        cx = min(max(np.rint(qx), 0.0), w - 1.0)
        cy = min(max(np.rint(qy), 0.0), h - 1.0)
        v = np.float64(dist[int(cy), int(cx)]) + math.hypot(qx - cx, qy - cy)
        out[k] = v if v < reach else reach
    return out
