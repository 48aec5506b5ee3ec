"""Compiled kernels of the raw segmentation's pieces (core/segment_raw.py, :func:`_pieces`).

The candidate pixels of a view are a few % of it (~10^4 at 640x480) and come as row-major
lists of rows and columns. Labelling them as an image (cv2.connectedComponents) passed over
all 3 * 10^5 pixels and wrote a fresh (H, W) int32 image, ~1 ms a call and four calls a frame;
:func:`label_pixels` joins the pixels' row runs instead (union-find, as
``ridge_kernel.small_components``), and :func:`piece_boxes` and :func:`half_widths` measure
the pieces from the same lists. The labels are cv2's, numbering included, and the boxes are
exact. The half-width is cv2's 3x3 chamfer distance (DIST_L2, mask 3) with its float32 steps;
cv2 (IPP) reaches some pixels along another path of the same steps, so its float32 sum can
differ in the last bit: on the 36,470 pieces of >= 10 px of 105 raw frames of 15 suites, 2
differed, by one ulp (6e-8 relative), and the masks were identical.
"""

from __future__ import annotations

import numpy as np

from threadrecon.core.compiled import helper, kernel


@kernel("int64(int64[::1], int64[::1], int64[::1])")
def label_pixels(rows, cols, lab):  # noqa: ANN001
    """8-connected components of the pixels (rows, cols) (M,), given in row-major order: the
    label of each pixel into ``lab`` (M,), 1, 2, ... numbered as cv2.connectedComponents
    numbers them; returns the number of labels + 1 (as cv2 counts its 0)."""
    m = len(rows)
    if m == 0:
        return 1
    # Row runs: first pixel index, row, first and last column.
    first = np.empty(m + 1, np.int64)
    n = 0
    for i in range(m):
        if i == 0 or rows[i] != rows[i - 1] or cols[i] != cols[i - 1] + 1:
            first[n] = i
            n += 1
    first[n] = m
    parent = np.arange(n)
    above0 = 0  # the runs of the row above: above0 .. above1 - 1
    above1 = 0
    r = 0
    while r < n:
        y = rows[first[r]]
        start = r
        if above1 > above0 and rows[first[above0]] != y - 1:
            above0 = above1  # the previous runs' row is not the row above
        j = above0
        while r < n and rows[first[r]] == y:
            a, b = cols[first[r]], cols[first[r + 1] - 1]
            while j < above1 and cols[first[j + 1] - 1] < a - 1:  # ends before column a - 1
                j += 1
            k = j
            while k < above1 and cols[first[k]] <= b + 1:  # starts by column b + 1
                _union(parent, r, k)
                k += 1
            r += 1
        above0, above1 = start, r
    # Components are numbered as cv2 numbers them: in the raster order of the 2 x 2 blocks
    # (rows 2i, 2i + 1) holding their first pixel (two components never share a block).
    root = np.empty(n, np.int64)
    key = np.full(n, np.iinfo(np.int64).max, np.int64)
    for r in range(n):
        root[r] = _root(parent, r)
        block = ((rows[first[r]] >> 1) << 32) | (cols[first[r]] >> 1)
        key[root[r]] = min(key[root[r]], block)
    roots = np.flatnonzero(root == np.arange(n))
    label = np.zeros(n, np.int64)
    order = np.argsort(key[roots])
    for j in range(len(roots)):
        label[roots[order[j]]] = j + 1
    for r in range(n):
        lr = label[root[r]]
        for i in range(first[r], first[r + 1]):
            lab[i] = lr
    return len(roots) + 1


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


@kernel("int64[:, ::1](int64[::1], int64[::1], int64[::1], int64)")
def piece_boxes(lab, rows, cols, n):  # noqa: ANN001
    """(4, n): first and last row, first and last column of the pixels of each label
    (``lab`` (M,) in 0..n-1 of the pixels (rows, cols)), 0 for labels without pixels."""
    out = np.zeros((4, n), np.int64)
    seen = np.zeros(n, np.bool_)
    for i in range(len(lab)):
        k = lab[i]
        r, c = rows[i], cols[i]
        if not seen[k]:
            seen[k] = True
            out[0, k], out[1, k], out[2, k], out[3, k] = r, r, c, c
        else:
            out[0, k] = min(out[0, k], r)
            out[1, k] = max(out[1, k], r)
            out[2, k] = min(out[2, k], c)
            out[3, k] = max(out[3, k], c)
    return out


@kernel("float64[::1](int64[::1], int64[::1], int64[::1], int64[::1], int64[:, ::1], int64, int64)")
def half_widths(lab, rows, cols, ids, boxes, h, w):  # noqa: ANN001
    """(n,) largest 3x3 chamfer distance (cv2.distanceTransform, DIST_L2, mask 3) of the
    pixels of each piece ``ids`` to the outside of its own mask in the (h, w) image, 0 for the
    other labels; ``lab`` (M,) the label of each pixel (rows, cols), ``boxes`` (4, n) the
    labels' first and last rows and columns (:func:`piece_boxes`). The outside of the image
    is far, as in cv2. Per piece, on its box grown by one pixel where that stays inside the
    image: the two raster passes of the chamfer transform with cv2's float32 steps 0.955 and
    1.3693, visiting the piece's own pixels only (cv2's to the last bit or so: see above)."""
    n = boxes.shape[1]
    out = np.zeros(n, np.float64)
    if len(ids) == 0:
        return out
    # The pixels of the pieces ``ids``, grouped by piece (counting sort).
    slot = np.full(n, -1, np.int64)
    for j in range(len(ids)):
        slot[ids[j]] = j
    start = np.zeros(len(ids) + 1, np.int64)
    for i in range(len(lab)):
        j = slot[lab[i]]
        if j >= 0:
            start[j + 1] += 1
    for j in range(len(ids)):
        start[j + 1] += start[j]
    fill = start[:-1].copy()
    order = np.empty(start[len(ids)], np.int64)
    for i in range(len(lab)):
        j = slot[lab[i]]
        if j >= 0:
            order[fill[j]] = i
            fill[j] += 1
    hv = np.float32(0.955)  # cv2's DIST_L2 3x3 steps, summed in float32 as cv2 sums them
    diag = np.float32(1.3693)
    far = np.float32(3.4028234663852886e38)  # beyond the image: FLT_MAX, as cv2
    for j in range(len(ids)):
        k = ids[j]
        # The box grown by one pixel of zeros where it is not at the image's edge.
        y0 = boxes[0, k] - (1 if boxes[0, k] > 0 else 0)
        y1 = boxes[1, k] + (1 if boxes[1, k] < h - 1 else 0)
        x0 = boxes[2, k] - (1 if boxes[2, k] > 0 else 0)
        x1 = boxes[3, k] + (1 if boxes[3, k] < w - 1 else 0)
        bh, bw = y1 - y0 + 1, x1 - x0 + 1
        # The box in a one-pixel frame of ``far``.
        t = np.zeros((bh + 2, bw + 2), np.float32)
        for x in range(bw + 2):
            t[0, x] = far
            t[bh + 1, x] = far
        for y in range(bh + 2):
            t[y, 0] = far
            t[y, bw + 1] = far
        # cv2's forward and backward passes, on the piece's pixels only (the rest stays 0).
        for i in range(start[j], start[j + 1]):
            p = order[i]
            y, x = rows[p] - y0 + 1, cols[p] - x0 + 1
            up, row = t[y - 1], t[y]
            row[x] = min(up[x - 1] + diag, up[x] + hv, up[x + 1] + diag, row[x - 1] + hv)
        best = np.float32(0.0)
        for i in range(start[j + 1] - 1, start[j] - 1, -1):
            p = order[i]
            y, x = rows[p] - y0 + 1, cols[p] - x0 + 1
            dn, row = t[y + 1], t[y]
            d = row[x]
            if d > hv:
                d = min(d, dn[x + 1] + diag, dn[x] + hv, dn[x - 1] + diag, row[x + 1] + hv)
                row[x] = d
            best = max(best, d)
        out[k] = best
    return out
