"""Compiled kernels of the raw segmentation's filters (core/segment_raw.py).

The line response at one scale is five 3x3 derivative filters of the smoothed image (gradient
and Hessian) and a dozen per-pixel operations on them. As cv2 calls that was fifteen passes
over full-size float32 images, five of them into fresh buffers (their page faults cost more
than the arithmetic at 640x480); :func:`line_response` is one pass that reads three rows of
the smoothed image and writes the response, with the same formula. :func:`log_planes` gives
the log channels the response reads (full-resolution brightness, half-resolution pyrDown of
all channels) straight from the uint8 image, without the (H, W, 3) float image, and
:func:`upsample_max` merges the coarse scale into the fine one in place.

Exactness: these three compute cv2's formulas in float32 in another order, so the response
differs from the cv2 calls' in the last bits (~1e-5 relative); on 195 raw frames of 15 suites
(two seeds) the masks were the same but for one pixel of one frame, and the held-out suites'
figures were unchanged. :func:`kth_smallest`, :func:`at_least`, :func:`small_components`
and :func:`attached` (the instrument's components that hold a seed, core/instrument.py) give
exactly the values of the numpy/cv2 code they replace.

The raw segmentation's pieces (:func:`segment_raw._pieces`) come from the candidate pixels'
row-major lists (a few % of the view): :func:`label_pixels` joins their row runs (union-find,
as :func:`small_components`) instead of labelling an (H, W) image, numbered as
cv2.connectedComponents numbers them, and :func:`piece_stats` and :func:`half_widths` measure
the pieces from the same lists. The boxes, counts and sums are exact; the half-width is cv2's
3x3 chamfer distance (DIST_L2, mask 3) with its float32 steps; cv2 (IPP) reaches some pixels
along another path of the same steps, so its float32 sum can differ in the last bit: on the
36,470 pieces of >= 10 px of 105 raw frames of 15 suites, 2 differed, by one ulp, and the
masks were identical.

:func:`block_residuals` gives the surface test's grey residuals (core/segment_surface.py) at
a piece's pixels and a range of disparities and their mean per block: exactly numpy's clipped
fancy index and np.add.reduceat (its pairwise summation, in its order).
"""

from __future__ import annotations

import numpy as np

from threadrecon.core.compiled import helper, kernel


@kernel(
    "float32[:, ::1](float32[:, ::1], int64, float32, float32, float32, float32, float32[:, ::1])"
)
def line_response(g, c, k1, k2, w_line, w_grad, out):  # noqa: ANN001
    """Line strength of the smoothed channels ``g`` (c * H, W), ``c`` planes one below the
    other (channel j in rows j H .. (j + 1) H - 1), into ``out`` (H, W), returned; ``out``
    may be ``g`` itself (one channel). Per channel, with the 3x3 Sobel filters of cv2 (border:
    reflect-101) scaled to derivatives, gx = k1 Sobel_x, gy, hxx = k2 Sobel_xx, hyy, hxy:

        line = max(w_line min(|hxx + hyy| / 2, |(hxx - hyy, 2 hxy)| / 2) - w_grad |(gx, gy)|, 0)

    and the response is line (one channel) or the Euclidean norm of the channels' lines."""
    h = g.shape[0] // c
    w = g.shape[1]
    two = np.float32(2.0)
    # Rows filtered vertically, one per channel, padded by a reflect-101 column on each side:
    # s = [1 2 1], t = [-1 0 1], q = [1 -2 1] down the column.
    s = np.empty((c, w + 2), np.float32)
    t = np.empty((c, w + 2), np.float32)
    q = np.empty((c, w + 2), np.float32)
    line = np.empty(w, np.float32)
    prev = np.empty((c, w), np.float32)  # row y - 1 as it was (``out`` may overwrite it)
    lo = 1 if w > 1 else 0  # reflect-101 columns: -1 -> 1, W -> W - 2 (one column: itself)
    hi = w - 2 if w > 1 else 0
    for y in range(h):
        for j in range(c):
            base = j * h
            mid = g[base + y]
            up = prev[j] if y > 0 else g[base + min(1, h - 1)]
            dn = g[base + y + 1] if y < h - 1 else (prev[j] if h > 1 else mid)
            sj, tj, qj = s[j], t[j], q[j]
            for x in range(w):
                u, m, d = up[x], mid[x], dn[x]
                sj[x + 1] = u + two * m + d
                tj[x + 1] = d - u
                qj[x + 1] = u - two * m + d
            sj[0], tj[0], qj[0] = sj[lo + 1], tj[lo + 1], qj[lo + 1]
            sj[w + 1], tj[w + 1], qj[w + 1] = sj[hi + 1], tj[hi + 1], qj[hi + 1]
            pj = prev[j]
            for x in range(w):
                pj[x] = mid[x]
        row = out[y]
        for j in range(c):
            _row_line(s[j], t[j], q[j], w, k1, k2, w_line, w_grad, line)
            if c == 1:
                for x in range(w):
                    row[x] = line[x]
            elif j == 0:
                for x in range(w):
                    row[x] = line[x] * line[x]
            else:
                for x in range(w):
                    row[x] += line[x] * line[x]
        if c > 1:
            for x in range(w):
                row[x] = np.sqrt(row[x])
    return out


@helper(inline="always")
def _row_line(s, t, q, w, k1, k2, w_line, w_grad, line):  # noqa: ANN001
    """One row's line strength (``line``, (W,)) from its vertically filtered rows s, t, q
    (W + 2,): the horizontal halves of the five Sobel filters, then the formula."""
    two = np.float32(2.0)
    half = np.float32(0.5)
    zero = np.float32(0.0)
    for x in range(w):
        gx = k1 * (s[x + 2] - s[x])
        gy = k1 * (t[x] + two * t[x + 1] + t[x + 2])
        hxx = k2 * (s[x] - two * s[x + 1] + s[x + 2])
        hyy = k2 * (q[x] + two * q[x + 1] + q[x + 2])
        hxy = k2 * (t[x + 2] - t[x])
        a = abs(half * hxx + half * hyy)
        dd = half * hxx - half * hyy
        d = np.sqrt(dd * dd + hxy * hxy)
        v = w_line * min(a, d) - w_grad * np.sqrt(gx * gx + gy * gy)
        line[x] = max(v, zero)


@helper(inline="always")
def _reflect(i, n):  # noqa: ANN001
    """Index ``i`` in 0..n-1 with cv2's BORDER_REFLECT_101 (..., 2, 1, 0, 1, 2, ...)."""
    if n == 1:
        return 0
    period = 2 * n - 2
    i = abs(i) % period
    return period - i if i >= n else i


@helper(inline="always")
def _mixed_row(src, c, w, lut, mix, ratios, row, grey):  # noqa: ANN001
    """One image row ``src`` (W, c) uint8 as log channels into ``row`` (c, W + 4): channel j
    at row[j, x + 2] is ``mix[j]`` of lut[value] of (R, G, B) (lut[value] for one channel;
    m0 lr + m1 lg + m2 lb, added left to right), and two columns on each side are
    reflect-101 copies (for the 5-tap filter); the first channel also into ``grey`` (W,).
    ``ratios``: mix's last two rows are (1, -1, 0) and (0, -1, 1), whose sums are lr - lg and
    lb - lg exactly (products by 1 and -1 are exact, 0 lb is +0 for lut > 0 and x + 0 = x
    for x != -0, and x - y is never -0 for finite x, y): computed as such."""
    if c == 1:
        r0 = row[0]
        for x in range(w):
            r0[x + 2] = lut[src[x, 0]]
    elif ratios:
        y0, y1, y2 = row[0], row[1], row[2]
        a0, a1, a2 = mix[0, 0], mix[0, 1], mix[0, 2]
        for x in range(w):
            lr, lg, lb = lut[src[x, 0]], lut[src[x, 1]], lut[src[x, 2]]
            y0[x + 2] = a0 * lr + a1 * lg + a2 * lb
            y1[x + 2] = lr - lg
            y2[x + 2] = lb - lg
    else:
        y0, y1, y2 = row[0], row[1], row[2]
        a0, a1, a2 = mix[0, 0], mix[0, 1], mix[0, 2]
        b0, b1, b2 = mix[1, 0], mix[1, 1], mix[1, 2]
        c0, c1, c2 = mix[2, 0], mix[2, 1], mix[2, 2]
        for x in range(w):
            lr, lg, lb = lut[src[x, 0]], lut[src[x, 1]], lut[src[x, 2]]
            y0[x + 2] = a0 * lr + a1 * lg + a2 * lb
            y1[x + 2] = b0 * lr + b1 * lg + b2 * lb
            y2[x + 2] = c0 * lr + c1 * lg + c2 * lb
    for j in range(c):
        rj = row[j]
        for p in (0, 1, w + 2, w + 3):
            rj[p] = rj[_reflect(p - 2, w) + 2]
    r0 = row[0]
    for x in range(w):
        grey[x] = r0[x + 2]


@kernel(
    "float32[:, ::1](uint8[:, :, :], float32[::1], float32[:, ::1], float32[:, ::1], "
    "float32[:, ::1])"
)
def log_planes(img, lut, mix, grey, half):  # noqa: ANN001
    """Log channels of ``img`` (H, W, c) uint8 (any strides), c = 1 or 3 channels: their
    first channel at full resolution into ``grey`` (H, W), and all of them at half resolution
    into ``half`` (c * h, w), one plane below the other, h = (H + 1) // 2, w = (W + 1) // 2,
    as cv2.pyrDown takes them
    (5 x 5 binomial filter [1 4 6 4 1] / 16 each way, reflect-101, even pixels); returns
    ``half``. A channel is ``mix`` (c, c) of lut[value] of the pixel's values."""
    h_in, w, c = img.shape
    h2 = half.shape[0] // c
    w2 = half.shape[1]
    ratios = c == 3 and _is_ratios(mix) and lut.min() > 0
    # The mixed rows of the last five input rows (each row is mixed once): slot r % 5.
    cache = np.empty((5, c, w + 4), np.float32)
    cached = np.full(5, -1, np.int64)
    # The five rows' sums at the even and at the odd columns (the 5-tap filter along the row
    # then reads two contiguous arrays, not every second element of one)
    even = np.zeros((w + 5) // 2, np.float32)
    odd = np.zeros((w + 5) // 2, np.float32)
    four = np.float32(4.0)
    six = np.float32(6.0)
    scale = np.float32(1.0 / 256.0)
    for y2 in range(h2):
        for k in range(5):
            r = _reflect(2 * y2 + k - 2, h_in)
            slot = r % 5
            if cached[slot] != r:
                _mixed_row(img[r], c, w, lut, mix, ratios, cache[slot], grey[r])
                cached[slot] = r
        s0 = cache[_reflect(2 * y2 - 2, h_in) % 5]
        s1 = cache[_reflect(2 * y2 - 1, h_in) % 5]
        s2 = cache[_reflect(2 * y2, h_in) % 5]
        s3 = cache[_reflect(2 * y2 + 1, h_in) % 5]
        s4 = cache[_reflect(2 * y2 + 2, h_in) % 5]
        for j in range(c):
            # the five rows' taps [1 4 6 4 1] added in turn, one pass (the order of the sums
            # of one tap after another)
            a0, a1, a2, a3, a4 = s0[j], s1[j], s2[j], s3[j], s4[j]
            for i in range((w + 4) // 2):
                x = 2 * i
                even[i] = (((a0[x] + four * a1[x]) + six * a2[x]) + four * a3[x]) + a4[x]
                x += 1
                odd[i] = (((a0[x] + four * a1[x]) + six * a2[x]) + four * a3[x]) + a4[x]
            if w % 2 == 1:  # (w + 4 columns: the last one is even)
                x = w + 3
                even[x // 2] = (((a0[x] + four * a1[x]) + six * a2[x]) + four * a3[x]) + a4[x]
            out = half[j * h2 + y2]
            for x2 in range(w2):  # columns 2 x2 .. 2 x2 + 4 of the sums
                v = even[x2] + four * odd[x2] + six * even[x2 + 1] + four * odd[x2 + 1]
                out[x2] = (v + even[x2 + 2]) * scale
    return half


@helper(inline="always")
def _is_ratios(mix):  # noqa: ANN001
    """Whether the last two rows of ``mix`` (3, 3) are (1, -1, 0) and (0, -1, 1)."""
    return (
        mix[1, 0] == 1 and mix[1, 1] == -1 and mix[1, 2] == 0
        and mix[2, 0] == 0 and mix[2, 1] == -1 and mix[2, 2] == 1
    )  # fmt: skip


@kernel("uint8[:, ::1](uint8[:, :, :], float32[::1], float32, uint8[:, ::1])")
def achromatic(img, lut, limit, out):  # noqa: ANN001
    """1 into ``out`` (H, W) where ``img`` (H, W, 3) uint8 (any strides) is unsaturated, else 0;
    returns ``out``. Unsaturated: both log chroma channels of the pixel, lut[R] - lut[G] and
    lut[B] - lut[G] (float32, as cv2.transform mixes the looked-up channels), are below
    ``limit`` in magnitude. The instrument's jaws are grown into such pixels
    (segment_raw._View.build): one pass from the uint8 image, no (H, W, 3) float image."""
    h, w = out.shape
    for y in range(h):
        src, o = img[y], out[y]
        for x in range(w):
            g = lut[src[x, 1]]
            a = abs(lut[src[x, 0]] - g)
            b = abs(lut[src[x, 2]] - g)
            o[x] = 1 if max(a, b) < limit else 0
    return out


@kernel("float32[:, ::1](float32[:, ::1], float32[:, ::1])")
def upsample_max(coarse, out):  # noqa: ANN001
    """``out`` (H, W) = max(out, coarse (h, w) resized to (W, H) bilinearly as cv2.resize's
    INTER_LINEAR does: source coordinate (x + 0.5) h / H - 0.5, clamped to the edge);
    returns ``out``."""
    h, w = coarse.shape
    big_h, big_w = out.shape
    x0 = np.empty(big_w, np.int64)
    x1 = np.empty(big_w, np.int64)
    ax = np.empty(big_w, np.float32)
    for x in range(big_w):
        i, a = _linear_source(x, w, big_w)
        x0[x] = i
        x1[x] = min(i + 1, w - 1)
        ax[x] = a
    one = np.float32(1.0)
    # Twice as wide (the usual case): outputs 2 j + 1 and 2 j + 2 blend inputs j and j + 1
    # with the weights (3/4, 1/4) and (1/4, 3/4), the same products and sums as the general
    # formula, without its gathers; the first and last outputs repeat the edge.
    double = big_w == 2 * w and w > 1
    q1, q3 = np.float32(0.25), np.float32(0.75)
    # The coarse rows resized along x, the last two: slot i % 2 holds coarse row i.
    rows = np.empty((2, big_w), np.float32)
    held = np.full(2, -1, np.int64)
    for y in range(big_h):
        i, b = _linear_source(y, h, big_h)
        for k in (i, min(i + 1, h - 1)):
            if held[k % 2] != k:
                src, dst = coarse[k], rows[k % 2]
                if double:
                    for x in (0, big_w - 1):
                        dst[x] = (one - ax[x]) * src[x0[x]] + ax[x] * src[x1[x]]
                    for j in range(w - 1):
                        s0, s1 = src[j], src[j + 1]
                        dst[2 * j + 1] = q3 * s0 + q1 * s1
                        dst[2 * j + 2] = q1 * s0 + q3 * s1
                else:
                    for x in range(big_w):
                        dst[x] = (one - ax[x]) * src[x0[x]] + ax[x] * src[x1[x]]
                held[k % 2] = k
        lo, hi = rows[i % 2], rows[min(i + 1, h - 1) % 2]
        row = out[y]
        for x in range(big_w):
            row[x] = max(row[x], (one - b) * lo[x] + b * hi[x])
    return out


@helper(inline="always")
def _linear_source(x, n, big_n):  # noqa: ANN001
    """(index, weight of index + 1) of output pixel ``x`` of ``big_n`` resized from ``n``
    (cv2 INTER_LINEAR: centres aligned, the edge pixel repeated)."""
    f = (x + 0.5) * (n / big_n) - 0.5
    i = int(np.floor(f))
    a = f - i
    if i < 0:
        return 0, np.float32(0.0)
    if i >= n - 1:
        return n - 1, np.float32(0.0)
    return i, np.float32(a)


@kernel("float32(float32[:, :], int64)")
def kth_smallest(x, k):  # noqa: ANN001
    """The ``k``-th smallest (0-based) of the non-negative values ``x`` (any 2-D view), as
    ``np.partition(x.ravel(), k)[k]``: the bit patterns of non-negative floats sort like the
    floats (sign bit cleared: -0.0 is 0), so a histogram of their top 11 bits finds the bin
    holding the k-th; the values of that bin are gathered, a histogram of their next 12 bits
    finds the sub-bin, and only that (a handful of values) is sorted. Small histograms: no
    fresh pages to fault in.

    Speed: the values of a response or of pixel differences fall in a few bins (many are 0):
    one table's increments of one bin wait on each other, so the first histogram goes to
    four tables in turn; the bin's values are gathered once, without a branch (every value is
    written at the next free slot, which only a value of the bin advances), and the second
    histogram and the last selection read those only."""
    n = x.shape[0] * x.shape[1]
    vals = x.ravel() if x.flags.c_contiguous else np.empty(n, np.float32)
    if not x.flags.c_contiguous:
        i = 0
        for r in range(x.shape[0]):
            for c in range(x.shape[1]):
                vals[i] = x[r, c]
                i += 1
    raw = vals.view(np.uint32)
    sign_off = np.uint32(0x7FFFFFFF)
    part = np.zeros((4, 1 << 11), np.int64)  # bits 20-30, four tables
    m = n - n % 4
    for i in range(0, m, 4):
        part[0, (raw[i] & sign_off) >> 20] += 1
        part[1, (raw[i + 1] & sign_off) >> 20] += 1
        part[2, (raw[i + 2] & sign_off) >> 20] += 1
        part[3, (raw[i + 3] & sign_off) >> 20] += 1
    for i in range(m, n):
        part[0, (raw[i] & sign_off) >> 20] += 1
    top = part[0] + part[1] + part[2] + part[3]
    b1, k1 = _bin_of(top, k)
    nb = top[b1]
    held = np.empty(nb + 1, np.uint32)  # the bin's values (sign cleared); one slot spare
    j = 0
    for i in range(n):
        b = raw[i] & sign_off
        held[j] = b
        j += 1 if b >> 20 == b1 else 0
    sub = np.zeros(1 << 12, np.int64)  # bits 8-19 of the values in bin b1
    for i in range(nb):
        sub[(held[i] >> 8) & 0xFFF] += 1
    b2, k2 = _bin_of(sub, k1)
    rest = np.empty(sub[b2], np.uint32)
    m = 0
    key = (b1 << 12) | b2
    for i in range(nb):
        if held[i] >> 8 == key:
            rest[m] = held[i]
            m += 1
    rest.sort()  # as the floats sort (non-negative bit patterns)
    return rest.view(np.float32)[k2]


@helper(inline="always")
def _bin_of(counts, k):  # noqa: ANN001
    """(bin, rank within it) of the ``k``-th smallest (0-based) of values in ``counts``."""
    below = 0
    b = 0
    while below + counts[b] <= k:
        below += counts[b]
        b += 1
    return b, k - below


@kernel("int64(uint8[:, :], int64, boolean)")
def small_components(mask, min_px, clear):  # noqa: ANN001
    """Pixels of ``mask`` (H, W) uint8 (any strides) in 8-connected components of fewer than
    ``min_px`` pixels; with ``clear``, those pixels are set to 0 in ``mask``. Components are
    unions of row runs (a run touches the runs of the row above that overlap it grown by one
    column): a thin mask's few hundred runs, not a label image."""
    h, w = mask.shape
    n = 0
    for y in range(h):
        prev = 0
        for x in range(w):
            on = 1 if mask[y, x] != 0 else 0
            if on and not prev:
                n += 1
            prev = on
    row = np.empty(n, np.int64)
    start = np.empty(n, np.int64)
    stop = np.empty(n, np.int64)  # exclusive
    parent = np.arange(n)
    i = 0
    above0 = 0  # the runs of the row above: above0 .. above1 - 1
    above1 = 0
    for y in range(h):
        first = i
        x = 0
        j = above0
        while x < w:
            if mask[y, x] == 0:
                x += 1
                continue
            a = x
            while x < w and mask[y, x] != 0:
                x += 1
            row[i], start[i], stop[i] = y, a, x
            j = _join_above(parent, start, stop, i, j, above1)
            i += 1
        above0, above1 = first, i
    size = np.zeros(n, np.int64)
    for r in range(n):
        size[_root(parent, r)] += stop[r] - start[r]
    small = 0
    for r in range(n):
        if size[_root(parent, r)] < min_px:
            small += stop[r] - start[r]
            if clear:
                for x in range(start[r], stop[r]):
                    mask[row[r], x] = 0
    return small


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
            j = _join_above(parent, start, stop, r, j, above1)
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


@helper(inline="always")
def _join_above(parent, start, stop, r, j, above1):  # noqa: ANN001
    """Join run ``r`` to the runs ``j .. above1 - 1`` of the row above that touch it (8-connected:
    they overlap its columns grown by one); returns the first of them that can touch the next
    run of its row (runs are in column order)."""
    a, b = start[r], stop[r]
    while j < above1 and stop[j] < a:  # ends before column a - 1
        j += 1
    k = j
    while k < above1 and start[k] <= b:  # starts by column b (the run's end + 1)
        _union(parent, r, k)
        k += 1
    return j


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


@kernel("int64[:, ::1](float32[:, ::1], float32, uint8[:, ::1])")
def at_least(s, t, lo):  # noqa: ANN001
    """``lo`` (H, W) = 255 where ``s`` (H, W) >= ``t``, else 0 (cv2.compare's CMP_GE), and the
    rows and columns (2, M) of those pixels in row-major order (cv2.findNonZero's)."""
    h, w = s.shape
    n = 0
    for y in range(h):
        sy, ly = s[y], lo[y]
        for x in range(w):
            on = sy[x] >= t
            ly[x] = 255 if on else 0
            n += 1 if on else 0
    out = np.empty((2, n), np.int64)
    # Each row's set columns without a branch per pixel (a few % to ~20 % of the pixels are
    # set, scattered: the branch mispredicts): every column is written at the next free slot,
    # which only a set pixel advances.
    cols = np.empty(w + 1, np.int64)
    i = 0
    for y in range(h):
        ly = lo[y]
        k = 0
        for x in range(w):
            cols[k] = x
            k += ly[x] >> 7
        for j in range(k):
            out[0, i + j] = y
            out[1, i + j] = cols[j]
        i += k
    return out


@kernel("uint8[:, ::1](uint8[:, :, :], int64[::1], int64[::1])")
def pixels_at(img, rows, cols):  # noqa: ANN001
    """(M, c) values of ``img`` (H, W, c) uint8 (any strides) at the pixels (rows, cols) (M,):
    ``img[rows, cols]`` without numpy's fancy indexing of a strided image."""
    m = len(rows)
    c = img.shape[2]
    out = np.empty((m, c), np.uint8)
    for i in range(m):
        for j in range(c):
            out[i, j] = img[rows[i], cols[i], j]
    return out


@helper(inline="always")
def _shift_of(q):  # noqa: ANN001
    """log2 ``q`` when ``q`` >= 1 is a power of two, else -1."""
    sh = 0
    while (1 << sh) < q:
        sh += 1
    return sh if (1 << sh) == q else -1


@helper(inline="always")
def _block_of(i, q, sh, n):  # noqa: ANN001
    """min(i // q, n - 1) of a pixel index i >= 0; a shift when q = 2^sh (sh >= 0): the same
    integer without a division."""
    b = (i >> sh) if sh >= 0 else i // q
    return min(b, n - 1)


@kernel("float32[:, ::1](float32[:, :, ::1], int64[::1], int64[::1], int64)")
def blocks_at(a, rows, cols, q):  # noqa: ANN001
    """(M, c) values of the block image ``a`` (h, w, c) at the blocks of the full-resolution
    pixels (rows, cols) (M,), ``q`` pixels a block, the last block taking the rest:
    ``a[min(rows // q, h - 1), min(cols // q, w - 1)]``."""
    h, w, c = a.shape
    m = len(rows)
    out = np.empty((m, c), np.float32)
    sh = _shift_of(q)
    for i in range(m):
        r, k = _block_of(rows[i], q, sh, h), _block_of(cols[i], q, sh, w)
        for j in range(c):
            out[i, j] = a[r, k, j]
    return out


@kernel("float32[:, ::1](uint8[:, :], float32[:, ::1])")
def block_means(rows, out):  # noqa: ANN001
    """``out`` (H // 4, (W // 4) * 3) = the means of the 4 x 4 blocks of the three channels of
    an image (H, W, 3) uint8 given as its ``rows`` (H, 3 W) (each row's pixels one after the
    other, interleaved; any row stride; H and W multiples of 4), interleaved, rounded half to
    even as cv2.resize's INTER_AREA rounds them; returns ``out``. Integer sums (exact in any
    order): the four rows' column sums of each block row first (one contiguous pass, which
    vectorises), then the four columns of each block."""
    h2, wc = out.shape
    w2 = wc // 3
    col = np.empty(12 * w2, np.int32)
    for y2 in range(h2):
        r0, r1, r2, r3 = rows[4 * y2], rows[4 * y2 + 1], rows[4 * y2 + 2], rows[4 * y2 + 3]
        for i in range(12 * w2):
            col[i] = np.int32(r0[i]) + np.int32(r1[i]) + np.int32(r2[i]) + np.int32(r3[i])
        o = out[y2]
        for x in range(w2):
            b = 12 * x
            for j in range(3):
                a = col[b + j] + col[b + 3 + j] + col[b + 6 + j] + col[b + 9 + j]
                q = a >> 4
                r = a & 15
                if r > 8 or (r == 8 and (q & 1) == 1):  # exactly half: to the even neighbour
                    q += 1
                o[3 * x + j] = q
    return out


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


@kernel(
    "Tuple((float64[::1], float64[::1], boolean[::1], int64[:, ::1]))(int64[::1], int64[::1], "
    "int64[::1], float32[::1], float32, int64)"
)
def piece_stats(lab, rows, cols, s, seed, n):  # noqa: ANN001
    """Per label 0..n-1 of the pixels (rows, cols) (``lab`` (M,)) with values ``s`` (M,), in
    one pass: (n,) pixel counts as float64 (``np.bincount(lab).astype(float)``), (n,) sums of
    the values (``np.bincount(lab, weights=s)``: float64, added in pixel order), (n,) whether
    a value is >= ``seed`` (a seed of the hysteresis), and (4, n) the first and last row and
    first and last column of the pixels (0 for labels without pixels)."""
    area = np.zeros(n, np.float64)
    sums = np.zeros(n, np.float64)
    seeded = np.zeros(n, np.bool_)
    boxes = np.zeros((4, n), np.int64)
    for i in range(len(lab)):
        k = lab[i]
        r, c = rows[i], cols[i]
        if area[k] == 0.0:
            boxes[0, k], boxes[1, k], boxes[2, k], boxes[3, k] = r, r, c, c
        else:
            boxes[0, k] = min(boxes[0, k], r)
            boxes[1, k] = max(boxes[1, k], r)
            boxes[2, k] = min(boxes[2, k], c)
            boxes[3, k] = max(boxes[3, k], c)
        area[k] += 1.0
        sums[k] += np.float64(s[i])
        if s[i] >= seed:
            seeded[k] = True
    return area, sums, seeded, boxes


@kernel(
    "Tuple((float64[::1], boolean[::1], float64[::1]))(float64[::1], float64[::1], boolean[::1], "
    "int64[:, ::1], float64, float64, float64, int64, int64, int64)"
)
def piece_candidates(area, sums, seeded, boxes, min_len, sqrt2, two_a, h, w, border):  # noqa: ANN001
    """The per-piece steps of segment_raw._pieces before the half-widths, elementwise over the
    n pieces of :func:`piece_stats`' ``area``, ``sums``, ``seeded`` and ``boxes`` (4, n), in
    one pass and with numpy's float64 operations: (n,) mean values (``sums / max(area, 1)``,
    0 for label 0), (n,) whether a piece is a candidate (seeded, ``sqrt2 area >= min_len``, not
    label 0; its box kept, the others' set to 0 in place; then ``max(diag, area / two_a) >=
    min_len`` and its box not within ``border`` px of one side of the (h, w) image), and (n,)
    the boxes' diagonals ``hypot(c1 - c0 + 1, r1 - r0 + 1)`` (of the zeroed boxes too)."""
    n = len(area)
    means = np.empty(n, np.float64)
    cands = np.empty(n, np.bool_)
    diag = np.empty(n, np.float64)
    for k in range(n):
        means[k] = sums[k] / max(area[k], 1.0)
        c = seeded[k] and sqrt2 * area[k] >= min_len and k != 0
        if not c:
            boxes[0, k] = boxes[1, k] = boxes[2, k] = boxes[3, k] = 0
        r0, r1, c0, c1 = boxes[0, k], boxes[1, k], boxes[2, k], boxes[3, k]
        diag[k] = np.hypot(c1 - c0 + 1.0, r1 - r0 + 1.0)
        c = c and max(diag[k], area[k] / two_a) >= min_len
        near = r1 < border or r0 >= h - border or c1 < border or c0 >= w - border
        cands[k] = c and not near
    if n > 0:
        means[0] = 0.0
    return means, cands, diag


@kernel(
    "Tuple((float64[::1], boolean[::1], boolean[::1]))(float64[::1], float64[::1], "
    "float64[::1], boolean[::1], float64, float64)"
)
def piece_shapes(area, diag, half, cands, min_len, max_half):  # noqa: ANN001
    """The per-piece steps of segment_raw._pieces after the half-widths ``half`` (n,), with
    numpy's float64 operations: (n,) lengths ``max(diag, area / max(2 half, 1))``, (n,)
    shape-ok (a candidate at least ``min_len`` long and at most ``max_half`` half-wide) and
    (n,) too wide (a long candidate that is not shape-ok)."""
    n = len(area)
    length = np.empty(n, np.float64)
    ok = np.empty(n, np.bool_)
    wide = np.empty(n, np.bool_)
    for k in range(n):
        length[k] = max(diag[k], area[k] / max(2.0 * half[k], 1.0))
        long = cands[k] and length[k] >= min_len
        ok[k] = long and half[k] <= max_half
        wide[k] = long and not ok[k]
    return length, ok, wide


@kernel("float64[::1](int64[::1], int64[::1], int64[::1], int64[::1], int64[:, ::1], int64, int64)")
def half_widths(lab, rows, cols, ids, boxes, h, w):  # noqa: ANN001
    """(n,) largest 3x3 chamfer distance (cv2.distanceTransform, DIST_L2, mask 3) of the
    pixels of each piece ``ids`` to the outside of its own mask in the (h, w) image, 0 for the
    other labels; ``lab`` (M,) the label of each pixel (rows, cols), ``boxes`` (4, n) the
    labels' first and last rows and columns (:func:`piece_stats`). The outside of the image
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


@kernel(
    "Tuple((float32[:, ::1], boolean[:, ::1], int64[::1], float32[:, ::1]))(float32[:, ::1], "
    "float32[:, ::1], int64[::1], int64[::1], int64[::1], int64, int64, int64, boolean)"
)
def block_residuals(this, other, r, c, block, n_blocks, d0, nd, look_left):  # noqa: ANN001
    """Grey residuals |this[r, c] - other[r, c -+ d]| of the pixels (r, c) (N,) at the
    disparities d = d0 .. d0 + nd - 1 (minus: ``look_left``), grouped by their ``block`` (N,)
    in 0 .. n_blocks - 1 (a stable sort: np.argsort(block, kind="stable")): (N, nd) residuals
    and (N, nd) whether the partner column is inside the image (outside: the edge column's
    residual, as a clipped index gives it), (n_blocks,) pixels per block, and (n_blocks, nd)
    the mean residual over the inside pixels per block, inf where fewer than half of the
    block's pixels (or none) are inside. The sums are np.add.reduceat's, to the last bit: the
    block's first row plus numpy's pairwise sum of the others."""
    n = len(r)
    w = this.shape[1]
    size = np.zeros(n_blocks, np.int64)
    for i in range(n):
        size[block[i]] += 1
    fill = np.empty(n_blocks, np.int64)
    at = 0
    for b in range(n_blocks):
        fill[b] = at
        at += size[b]
    diff = np.empty((n, nd), np.float32)
    inside = np.empty((n, nd), np.bool_)
    masked = np.empty((n, nd), np.float32)  # diff * inside
    counted = np.empty((n, nd), np.float32)  # inside as 0.0 / 1.0
    for i in range(n):
        o = fill[block[i]]
        fill[block[i]] += 1
        a = this[r[i], c[i]]
        row = other[r[i]]
        for k in range(nd):
            cc = c[i] - (d0 + k) if look_left else c[i] + (d0 + k)
            ok = 0 <= cc < w
            v = abs(a - row[min(max(cc, 0), w - 1)])
            diff[o, k] = v
            inside[o, k] = ok
            masked[o, k] = v if ok else np.float32(0.0)
            counted[o, k] = np.float32(1.0) if ok else np.float32(0.0)
    mean = np.empty((n_blocks, nd), np.float32)
    inf = np.float32(np.inf)
    at = 0
    for b in range(n_blocks):
        m = size[b]
        for k in range(nd):
            if m == 0:
                mean[b, k] = inf
                continue
            total = masked[at, k] + _pairwise(masked, k, at + 1, m - 1)
            count = counted[at, k] + _pairwise(counted, k, at + 1, m - 1)
            if count >= max(0.5 * m, 1.0):
                mean[b, k] = total / max(count, np.float32(1.0))
            else:
                mean[b, k] = inf
        at += m
    return diff, inside, size, mean


@kernel(
    "UniTuple(float64, 3)(float32[:, ::1], boolean[:, ::1], int64, int64, int64, int64, float32)"
)
def excess_stats(diff, inside, start, size, at, own, cap):  # noqa: ANN001
    """(n, mean, standard deviation) of the excess residuals x = diff[i, at] - diff[i, own]
    of the rows i = start .. start + size - 1 where both columns are ``inside``, clipped to
    [-cap, cap]: np.mean(x) and np.std(x) of float32 x to the last bit (numpy's pairwise
    sums of the whole array, its float32 divisions by n)."""
    x = np.empty((size, 1), np.float32)
    n = 0
    for i in range(start, start + size):
        if inside[i, at] and inside[i, own]:
            x[n, 0] = min(max(diff[i, at] - diff[i, own], -cap), cap)
            n += 1
    if n == 0:
        return 0.0, 0.0, 0.0
    nf = np.float32(n)
    mean = _pairwise(x, 0, 0, n) / nf
    for i in range(n):
        d = x[i, 0] - mean
        x[i, 0] = d * d
    std = np.sqrt(_pairwise(x, 0, 0, n) / nf)
    return float(n), float(mean), float(std)


@kernel(
    "int64(float32[:, ::1], float32[:, ::1], int64[::1], int64[::1], int64, int64, int64, "
    "boolean, int64, int64, float64, float64, float64)"
)
def background_vote(this, other, r, c, d, dmax, window, look_left, resolve_px, min_samples,  # noqa: ANN001, ANN201
                    same_px, tail, t_same):  # fmt: skip
    """The surface test's vote of one block's background samples (r, c) (N,) on a piece of
    best disparity ``d`` (core/segment_surface.py, ``SurfaceTest.votes``): their residuals
    (:func:`block_residuals`, one block) at the disparities max(d - window, 0) ..
    min(d + window, dmax); -1 where the background does not resolve its own best disparity
    (fewer than ``min_samples`` samples, no finite residual, or a side ``resolve_px`` away
    that is not worse by ``t_same`` standard errors of the excess residuals clipped at
    ``tail`` times the least plus 1: :func:`excess_stats`), else 1 where it matches at ``d``
    (within ``same_px``) with an excess under half of the sides' least, 0 where not. The
    Python steps' own arithmetic (float64 from the float32 residuals, np.argmin's first
    minimum) in one call."""
    d0 = max(d - window, 0)
    nd = min(d + window, dmax) + 1 - d0
    block = np.zeros(len(r), np.int64)
    diff, inside, size, mean = block_residuals(this, other, r, c, block, 1, d0, nd, look_left)
    m = mean[0]
    own = 0
    for k in range(1, nd):
        if m[k] < m[own]:
            own = k
    least = m[own]
    if size[0] < min_samples or not np.isfinite(least):
        return -1
    n_sides = 0
    ref = np.inf
    for i in (own - resolve_px, own + resolve_px):
        if i < 0 or i >= nd:
            continue
        n_sides += 1
        cap = np.float32(tail * np.float64(least) + 1.0)
        n, mu, sd = excess_stats(diff, inside, 0, size[0], i, own, cap)
        if n < min_samples:
            return -1
        se = sd / np.sqrt(n) + 1e-6
        if not mu >= t_same * se:
            return -1
        ref = min(ref, np.float64(m[i]))
    if n_sides == 0:
        return -1
    lo = max(int(np.ceil(d - same_px)) - d0, 0)
    hi = min(int(np.floor(d + same_px)) - d0, nd - 1)
    if hi < lo:
        return 0
    low = m[lo]
    for k in range(lo + 1, hi + 1):
        low = min(low, m[k])
    excess = np.float64(low) - np.float64(least)
    return 1 if excess < 0.5 * (ref - np.float64(least)) else 0


@helper()
def _pairwise(x, j, lo, n):  # noqa: ANN001
    """Sum of x[lo : lo + n, j] in float32 as numpy's pairwise summation adds it: runs of at
    most 128 values (:func:`_pairwise_leaf`); a longer run is the sum of its halves, split at
    a multiple of 8 (numpy recurses; here a stack: the AOT compiler takes no recursion)."""
    if n <= 128:
        return _pairwise_leaf(x, j, lo, n)
    los = np.empty(64, np.int64)
    ns = np.empty(64, np.int64)
    state = np.empty(64, np.int64)  # 1: the left half is being summed, 2: the right half
    left = np.empty(64, np.float32)  # the left half's sum, in state 2
    top = 0
    los[0], ns[0] = lo, n
    while True:
        m = ns[top]
        if m > 128:  # split: sum the left half first
            half = m // 2
            half -= half % 8
            state[top] = 1
            los[top + 1], ns[top + 1] = los[top], half
            top += 1
            continue
        v = _pairwise_leaf(x, j, los[top], m)
        while True:  # return v to the parents
            if top == 0:
                return v
            top -= 1
            if state[top] == 1:  # the left half is done: sum the right half
                left[top] = v
                state[top] = 2
                half = ns[top] // 2
                half -= half % 8
                los[top + 1], ns[top + 1] = los[top] + half, ns[top] - half
                top += 1
                break
            v = left[top] + v


@helper(inline="always")
def _pairwise_leaf(x, j, lo, n):  # noqa: ANN001
    """numpy's pairwise sum of a run of at most 128 values x[lo : lo + n, j]: below 8 one by
    one, else 8 interleaved partial sums, combined as a tree, then the rest one by one."""
    if n < 8:
        res = np.float32(0.0)
        for i in range(lo, lo + n):
            res += x[i, j]
        return res
    r0, r1, r2, r3 = x[lo, j], x[lo + 1, j], x[lo + 2, j], x[lo + 3, j]
    r4, r5, r6, r7 = x[lo + 4, j], x[lo + 5, j], x[lo + 6, j], x[lo + 7, j]
    i = 8
    while i < n - n % 8:
        b = lo + i
        r0 += x[b, j]
        r1 += x[b + 1, j]
        r2 += x[b + 2, j]
        r3 += x[b + 3, j]
        r4 += x[b + 4, j]
        r5 += x[b + 5, j]
        r6 += x[b + 6, j]
        r7 += x[b + 7, j]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += x[lo + i, j]
        i += 1
    return res


@kernel("float32[::1](float32[:, ::1], int64[::1], int64[::1])")
def values_at(a, rows, cols):  # noqa: ANN001
    """(M,) values of ``a`` (H, W) at the pixels (rows, cols) (M,): ``a[rows, cols]``."""
    m = len(rows)
    out = np.empty(m, np.float32)
    for i in range(m):
        out[i] = a[rows[i], cols[i]]
    return out
