"""Compiled kernel of the raw segmentation's last step: the thread mask grown from its core
(:func:`threadrecon.core.segment_raw._grow_mask`).

As numpy and cv2 calls the growth was ~20 passes over the band pixels and the core's bounding
box, most of them fancy-index gathers of a few thousand pixels from strided images (the RGB
view of a BGR file) and fresh box-sized buffers; :func:`grow_mask` is one pass over the box's
core pixels and a few over its band pixels.

Exactness: every step is the numpy/cv2 code's own arithmetic in its own order, so the mask is
the same bit for bit (tests/core/test_grow_kernel.py compares it with the plain computation):
the per-block sums of the core's contrast in float64 in pixel order (np.bincount), cast to
float32; their 3 x 3 box sum in float64 with constant zero border (cv2.boxFilter of float32
sums in float64); dot products and channel sums left to right in float32 (np.einsum and
``sum(axis=1)`` over three channels); dilations by their structuring elements (exact: maxima
and ORs); the closing's erosion takes the outside of the box as set (cv2's default border) and
the coverage test's neighbours are clamped to the box (BORDER_REPLICATE).
"""

from __future__ import annotations

import numpy as np

from threadrecon.core.compiled import helper, kernel

_SIG = (
    "uint8[:, ::1]({img}, float32[:, :, ::1], uint8[:, :], uint8[:, ::1], int64, int64, "
    "int64, int64, float32, float32)"
)


@kernel(_SIG.format(img="uint8[:, :, :]"))
def grow_mask_u8(a, bg, core, disc, r0, c0, q, band_px, glint_sin2, shared_px):  # noqa: ANN001
    """:func:`_grow` of a uint8 image box ``a``."""
    return _grow(a, bg, core, disc, r0, c0, q, band_px, glint_sin2, shared_px)


@kernel(_SIG.format(img="float32[:, :, :]"))
def grow_mask_f32(a, bg, core, disc, r0, c0, q, band_px, glint_sin2, shared_px):  # noqa: ANN001
    """:func:`_grow` of a float32 image box ``a``."""
    return _grow(a, bg, core, disc, r0, c0, q, band_px, glint_sin2, shared_px)


@helper()
def _grow(a, bg, core, disc, r0, c0, q, band_px, glint_sin2, shared_px):  # noqa: ANN001, C901
    """(bh, bw) uint8, 1 on the thread pixels grown from ``core`` (bh, bw) (nonzero: core
    pixels) in the box ``a`` (bh, bw, C) of the image whose top-left pixel is (r0, c0) of the
    view; ``bg`` (h, w, C) the view's local background per ``q`` x ``q`` block; ``disc``
    (2 band_px + 1,) ^ 2 the band's structuring element. The steps and constants are those of
    segment_raw._grow_mask and _body_contrast (their docstrings say why)."""
    bh, bw, c = a.shape
    hq_all, wq_all = bg.shape[0], bg.shape[1]
    zero = np.float32(0.0)
    quarter = np.float32(0.25)
    half = np.float32(0.5)
    one = np.float32(1.0)
    inv_sqrt3 = np.float32(3**-0.5)
    tiny = np.float32(1e-12)
    k = disc.shape[0] // 2
    # The band: the core dilated by ``disc`` (its pixels in row-major order, as findNonZero).
    # Each row of ``disc`` is one span (an ellipse): a core pixel right of another one adds
    # only the spans' right ends to what its left neighbour set.
    left = np.empty(2 * k + 1, np.int64)
    right = np.empty(2 * k + 1, np.int64)
    for dy in range(2 * k + 1):
        left[dy], right[dy] = k + 1, -k - 1  # empty until an element is met
        for dx in range(2 * k + 1):
            if disc[dy, dx] != 0:
                left[dy] = min(left[dy], dx - k)
                right[dy] = max(right[dy], dx - k)
    band = np.zeros((bh, bw), np.uint8)
    n_core = 0
    for y in range(bh):
        run = False
        for x in range(bw):
            if core[y, x] == 0:
                run = False
                continue
            n_core += 1
            for dy in range(-k, k + 1):
                yy = y - dy
                lo, hi = left[dy + k], right[dy + k]
                if yy < 0 or yy >= bh or lo > hi:
                    continue
                # band[yy, x - hi .. x - lo] (the element reflected, as cv2.dilate applies it)
                start = x - lo if run else x - hi
                for xx in range(max(start, 0), min(x - lo + 1, bw)):
                    band[yy, xx] = 1
            run = True
    out = np.zeros((bh, bw), np.uint8)
    if n_core == 0:
        return out
    m = 0
    for y in range(bh):
        for x in range(bw):
            m += band[y, x]
    rows = np.empty(m, np.int64)
    cols = np.empty(m, np.int64)
    i = 0
    for y in range(bh):
        for x in range(bw):
            if band[y, x]:
                rows[i] = y
                cols[i] = x
                i += 1
    # I - B per band pixel, the block of each, and the blocks' span.
    diff = np.empty((m, c), np.float32)
    qr = np.empty(m, np.int64)
    qc = np.empty(m, np.int64)
    # (the block of each row and column of the box: a division per row and column of the
    # box, not two per band pixel)
    q_row = np.empty(bh, np.int64)
    for y in range(bh):
        q_row[y] = min((y + r0) // q, hq_all - 1)
    q_col = np.empty(bw, np.int64)
    for x in range(bw):
        q_col[x] = min((x + c0) // q, wq_all - 1)
    for i in range(m):
        qr[i] = q_row[rows[i]]
        qc[i] = q_col[cols[i]]
        for j in range(c):
            diff[i, j] = np.float32(a[rows[i], cols[i], j]) - bg[qr[i], qc[i], j]
    qr0, qr1, qc0, qc1 = qr.min(), qr.max(), qc.min(), qc.max()
    hq, wq = qr1 - qr0 + 1, qc1 - qc0 + 1
    # The thread's contrast direction per block: the core's summed contrast over the block and
    # the 8 around it, normalised (bincount in float64, cv2.boxFilter in float64); only the
    # blocks that hold band pixels need it.
    acc = np.zeros((hq, wq, c), np.float64)
    used = np.zeros((hq, wq), np.bool_)
    for i in range(m):
        used[qr[i] - qr0, qc[i] - qc0] = True
        if core[rows[i], cols[i]] != 0:
            for j in range(c):
                acc[qr[i] - qr0, qc[i] - qc0, j] += np.float64(diff[i, j])
    u = np.empty((hq, wq, c), np.float32)
    for y in range(hq):
        for x in range(wq):
            if not used[y, x]:
                continue
            for j in range(c):
                t = 0.0
                for yy in range(max(y - 1, 0), min(y + 2, hq)):
                    r = 0.0
                    for xx in range(max(x - 1, 0), min(x + 2, wq)):
                        r += np.float64(np.float32(acc[yy, xx, j]))
                    t += r
                u[y, x, j] = np.float32(t)
            n2 = u[y, x, 0] * u[y, x, 0]
            for j in range(1, c):
                n2 = n2 + u[y, x, j] * u[y, x, j]
            inv = one / np.sqrt(max(n2, tiny))
            for j in range(c):
                u[y, x, j] = u[y, x, j] * inv
    # Contrast along u (proj), net of a highlight where that fit applies (glint).
    c2 = np.empty(m, np.float32)
    net2 = np.zeros(m, np.float32)
    glint = np.zeros(m, np.bool_)
    for i in range(m):
        by, bx = qr[i] - qr0, qc[i] - qc0
        proj = diff[i, 0] * u[by, bx, 0]
        for j in range(1, c):
            proj = proj + diff[i, j] * u[by, bx, j]
        c2[i] = max(proj, zero) * max(proj, zero)
        if c == 3:
            uw = (u[by, bx, 0] + u[by, bx, 1] + u[by, bx, 2]) * inv_sqrt3
            den = one - uw * uw
            dw = (diff[i, 0] + diff[i, 1] + diff[i, 2]) * inv_sqrt3
            glint[i] = den >= glint_sin2 and dw > proj * uw
            net = (proj - dw * uw) / max(den, glint_sin2)
            net2[i] = max(net, zero) * max(net, zero)
    # |T - B|^2: the largest core value within the band's box around each pixel (dilation by
    # a square: a row maximum, then a column maximum; a core pixel's value is read where it
    # is computed, no (bh, bw) image of them).
    rowmax = np.zeros((bh, bw), np.float32)
    for i in range(m):
        y, x = rows[i], cols[i]
        if core[y, x] == 0:
            continue
        v = max(net2[i], c2[i]) if glint[i] else c2[i]
        if v > zero:
            for xx in range(max(x - band_px, 0), min(x + band_px + 1, bw)):
                rowmax[y, xx] = max(rowmax[y, xx], v)
    peak = np.empty(m, np.float32)
    keep = np.zeros(m, np.bool_)
    for i in range(m):
        y, x = rows[i], cols[i]
        p = zero
        for yy in range(max(y - band_px, 0), min(y + band_px + 1, bh)):
            p = max(p, rowmax[yy, x])
        peak[i] = p
        keep[i] = c2[i] >= quarter * p and p > zero
    # Pixels whose coverage net of a highlight passes, where enclosed by thread pixels (a
    # 3 x 3 closing of the mask).
    n_add = 0
    add = np.zeros(m, np.bool_)
    for i in range(m):
        if glint[i] and not keep[i] and net2[i] >= quarter * peak[i] and peak[i] > zero:
            add[i] = True
            n_add += 1
    if n_add > 0:
        mask = np.zeros((bh, bw), np.uint8)
        for i in range(m):
            if keep[i]:
                mask[rows[i], cols[i]] = 1
        for i in range(m):
            if add[i] and _closed(mask, rows[i], cols[i], bh, bw):
                keep[i] = True
                c2[i] = net2[i]
    # Coverage conservation across 1-2 px thin sections.
    cov = np.zeros((bh, bw), np.float32)
    for i in range(m):
        if keep[i]:
            cov[rows[i], cols[i]] = np.sqrt(c2[i] / peak[i])
    for i in range(m):
        if not keep[i]:
            continue
        y, x = rows[i], cols[i]
        cv = cov[y, x]
        for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nb = _at(cov, y + dy, x + dx, bh, bw)
            far = _at(cov, y + 2 * dy, x + 2 * dx, bh, bw)
            back = _at(cov, y - dy, x - dx, bh, bw)
            if nb > cv and nb + cv < shared_px and far < half and back < half:
                keep[i] = False
                break
        if keep[i]:
            out[y, x] = 1
    return out


@helper(inline="always")
def _at(a, y, x, h, w):  # noqa: ANN001
    """``a[y, x]`` with the indices clamped to (h, w) (BORDER_REPLICATE)."""
    return a[min(max(y, 0), h - 1), min(max(x, 0), w - 1)]


@helper(inline="always")
def _closed(mask, y, x, h, w):  # noqa: ANN001
    """Whether pixel (y, x) is set in the 3 x 3 closing of ``mask`` (h, w) (cv2's borders:
    outside the image the dilation sees nothing set, the erosion everything set)."""
    for yy in range(y - 1, y + 2):
        for xx in range(x - 1, x + 2):
            if yy < 0 or yy >= h or xx < 0 or xx >= w:
                continue  # the erosion's border: set
            dil = False
            for y2 in range(max(yy - 1, 0), min(yy + 2, h)):
                for x2 in range(max(xx - 1, 0), min(xx + 2, w)):
                    if mask[y2, x2] != 0:
                        dil = True
            if not dil:
                return False
    return True
