"""Compiled kernels of the instrument's width test (core/instrument.py), exactly the numpy and
cv2 steps they replace (tests/core/test_instrument_kernel.py compares them):

- :func:`label_lookup`: ``table[labels]`` of a label image as uint8 (numpy's fancy index of an
  (H, W) int32 image builds an intp index first: ~1 ms at 640x480 against ~0.1 ms here);
- :func:`ridge_values`: the distances ``dist[ridge]`` of the medial-axis pixels, ``ridge =
  piece & (dist >= cv2.dilate(dist, 3x3))``, read on the piece's pixels only (no float
  dilation of the whole image, no (H, W) temporaries).

Its components touching a seed (``attached``) are :func:`ridge_kernel.attached`, beside the
union-find of the raw segmentation's other component kernels.
"""

from __future__ import annotations

import numpy as np

from threadrecon.core.compiled import helper, kernel


@kernel("uint8[:, ::1](int32[:, ::1], boolean[::1])")
def label_lookup(labels, table):  # noqa: ANN001
    """(H, W) uint8: 1 where ``table[labels]`` (``labels`` (H, W) int32 in 0..len(table) - 1),
    else 0."""
    h, w = labels.shape
    out = np.empty((h, w), np.uint8)
    for y in range(h):
        lab, o = labels[y], out[y]
        for x in range(w):
            o[x] = 1 if table[lab[x]] else 0
    return out


@kernel("float32[::1](float32[:, ::1], uint8[:, ::1])")
def ridge_values(dist, piece):  # noqa: ANN001
    """(K,) float32 ``dist[ridge]`` in row-major order, ``ridge`` the pixels of ``piece`` (H, W)
    uint8 (nonzero) whose ``dist`` (H, W) is at least that of each of their 8 neighbours in
    the image (cv2.dilate's 3x3 maximum: beyond the image's edge is no neighbour)."""
    h, w = dist.shape
    n = 0
    for y in range(h):
        for x in range(w):
            if piece[y, x] != 0 and _is_ridge(dist, y, x, h, w):
                n += 1
    out = np.empty(n, np.float32)
    i = 0
    for y in range(h):
        for x in range(w):
            if piece[y, x] != 0 and _is_ridge(dist, y, x, h, w):
                out[i] = dist[y, x]
                i += 1
    return out


@helper(inline="always")
def _is_ridge(dist, y, x, h, w):  # noqa: ANN001
    """Whether no pixel of the 3 x 3 window around (y, x) inside the (h, w) image has a
    larger ``dist`` than (y, x)."""
    d = dist[y, x]
    for yy in range(max(y - 1, 0), min(y + 2, h)):
        for xx in range(max(x - 1, 0), min(x + 2, w)):
            if dist[yy, xx] > d:
                return False
    return True
