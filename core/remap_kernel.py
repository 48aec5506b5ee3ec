"""Compiled kernel of the load step's rectification (core/rectify.py): a Lanczos-4 remap at
the maps' exact positions.

``cv2.remap`` rounds every sampling position to 1/32 px (its interpolation tables) before it
interpolates. Across a rectified view the maps' fractional parts drift slowly, so that
rounding is a position error of up to 1/64 px that stays put over tens of pixels, different in
the two views; where the thread runs near an image row a vertical error e moves the matched
disparity by about e / tan(theta) (core/stereo.py), and one pixel of disparity is metres of
depth at endoscope baselines. This kernel samples the same Lanczos-4 kernel (8 x 8 taps,
weights normalised to sum 1, the border replicated) at the float positions themselves.
"""

from __future__ import annotations

import math

import numpy as np

from threadrecon.core.compiled import helper, kernel


@helper(inline="always")
def _weights(f, wgt):  # noqa: ANN001
    """The 8 Lanczos-4 weights of taps -3..4 at fraction ``f`` in [0, 1), normalised to sum 1,
    into ``wgt``: L(t) = sin(pi t) sin(pi t / 4) / (pi^2 t^2 / 4), t = f - m, with
    sin(pi (f - m)) = (-1)^m sin(pi f) and sin(pi (f - m) / 4) by the angle difference (four
    sines and cosines a pixel instead of 32)."""
    s1 = math.sin(math.pi * f)
    s4 = math.sin(math.pi * f / 4.0)
    c4 = math.cos(math.pi * f / 4.0)
    total = 0.0
    for k in range(8):
        m = k - 3
        t = f - m
        if abs(t) < 1e-12:
            v = 1.0
        else:
            a = math.pi * m / 4.0
            sign = 1.0 if abs(m) % 2 == 0 else -1.0
            sin_t4 = s4 * math.cos(a) - c4 * math.sin(a)  # sin(pi (f - m) / 4)
            v = sign * s1 * sin_t4 / (math.pi * math.pi * t * t / 4.0)
        wgt[k] = v
        total += v
    for k in range(8):
        wgt[k] /= total


# Compiled ahead of time once per machine (core/compiled.py), so that numba is not loaded.
@kernel("float32[:, :, ::1](uint8[:, :, ::1], float32[:, ::1], float32[:, ::1])")
def lanczos4_remap(src, mx, my):  # noqa: ANN001
    """(h, w, C) float32: ``src`` (H, W, C) sampled at (``mx``, ``my``) (h, w) px (x = column,
    y = row) with the Lanczos-4 kernel; samples beyond the border repeat the edge pixel; a
    position that is not finite gives 0."""
    H, W, C = src.shape
    h, w = mx.shape
    out = np.zeros((h, w, C), dtype=np.float32)
    wx = np.empty(8)
    wy = np.empty(8)
    acc = np.empty(C)
    for r in range(h):
        for c in range(w):
            x = np.float64(mx[r, c])
            y = np.float64(my[r, c])
            if not (np.isfinite(x) and np.isfinite(y)) or abs(x) > 1e9 or abs(y) > 1e9:
                continue
            ix = math.floor(x)
            iy = math.floor(y)
            fx = x - ix
            fy = y - iy
            _weights(fx, wx)
            _weights(fy, wy)
            for ch in range(C):
                acc[ch] = 0.0
            for j in range(8):
                yy = min(max(int(iy) + j - 3, 0), H - 1)
                wj = wy[j]
                for i in range(8):
                    xx = min(max(int(ix) + i - 3, 0), W - 1)
                    wgt = wj * wx[i]
                    for ch in range(C):
                        acc[ch] += wgt * src[yy, xx, ch]
            for ch in range(C):
                out[r, c, ch] = acc[ch]
    return out
