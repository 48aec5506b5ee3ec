"""Compiled kernels of the instrument's width test (core/instrument.py), exactly the numpy and
cv2 steps they replace (tests/core/test_instrument_kernel.py compares them):

- :func:`label_lookup`: ``table[labels]`` of a label image as uint8 (numpy's fancy index of an
  (H, W) int32 image builds an intp index first: ~1 ms at 640x480 against ~0.1 ms here);
- :func:`ridge_values`: the distances ``dist[ridge]`` of the medial-axis pixels, ``ridge =
  piece & (dist >= cv2.dilate(dist, 3x3))``, read on the piece's pixels only (no float
  dilation of the whole image, no (H, W) temporaries);
- :func:`attached`: the 8-connected components of a mask that hold a pixel of another
  (``touching[labels]`` of cv2.connectedComponents and the seeds' labels), from the mask's
  row runs (union-find): no int32 label image, no fancy index of it.
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


@kernel("uint8[:, ::1](uint8[:, ::1], uint8[:, ::1], uint8[:, ::1])")
def attached(mask, seeds, out):  # noqa: ANN001
    """``out`` (H, W) = 1 on the 8-connected components of ``mask | seeds`` (uint8, nonzero
    set) that hold a pixel of ``seeds``, else 0; returns ``out``. As cv2.connectedComponents
    (connectivity 8) of ``mask | seeds``, ``touching[labels[seeds > 0]] = True``, label 0
    cleared, and ``touching[labels]``: a component is a union of row runs (a run touches the
    runs of the row above that overlap it grown by one column)."""
    h, w = mask.shape
    n = 0
    for y in range(h):
        prev = False
        my, sy = mask[y], seeds[y]
        for x in range(w):
            on = my[x] != 0 or sy[x] != 0
            if on and not prev:
                n += 1
            prev = on
    start = np.empty(n, np.int64)
    stop = np.empty(n, np.int64)  # exclusive
    seeded = np.zeros(n, np.bool_)
    row_of = np.empty(h + 1, np.int64)  # the runs of row y: row_of[y] .. row_of[y + 1] - 1
    i = 0
    for y in range(h):
        row_of[y] = i
        my, sy = mask[y], seeds[y]
        x = 0
        while x < w:
            if my[x] == 0 and sy[x] == 0:
                x += 1
                continue
            a = x
            hit = False
            while x < w and (my[x] != 0 or sy[x] != 0):
                hit = hit or sy[x] != 0
                x += 1
            start[i], stop[i], seeded[i] = a, x, hit
            i += 1
    row_of[h] = i
    parent = np.arange(n)
    for y in range(1, h):
        j, above1 = row_of[y - 1], row_of[y]
        for r in range(row_of[y], row_of[y + 1]):
            a, b = start[r], stop[r]
            while j < above1 and stop[j] < a:  # ends before column a - 1
                j += 1
            k = j
            while k < above1 and start[k] <= b:  # starts by column b (the run's end + 1)
                _union(parent, r, k)
                k += 1
    for r in range(n):
        if seeded[r]:
            seeded[_root(parent, r)] = True
    for y in range(h):
        o = out[y]
        for x in range(w):
            o[x] = 0
        for r in range(row_of[y], row_of[y + 1]):
            if seeded[_root(parent, r)]:
                for x in range(start[r], stop[r]):
                    o[x] = 1
    return out


@helper()
def _root(parent, i):  # noqa: ANN001
    """Root of ``i`` in the union-find forest ``parent`` (paths halved on the way)."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@helper()
def _union(parent, a, b):  # noqa: ANN001
    """Join the trees of ``a`` and ``b`` (the smaller root becomes the root)."""
    ra = _root(parent, a)
    rb = _root(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb
