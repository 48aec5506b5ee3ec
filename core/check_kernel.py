"""Compiled kernels of the check stage (core/check.py, core/check_field.py): loops over the
curve's samples that numpy would run as many small calls, with the same floating-point
operations (the check's results are bit-identical to the numpy forms they replace).

``overlap_length``: the length over the pairs of curve samples within a distance in the image
and far apart along the curve (``check._overlap``), by a sweep over the samples sorted by x. ``field_at``: the
distance field of a thread mask read at the curve's points (``MaskField.at``). ``band_d2``:
the thread pixels' distances to the projected curve for the coverage (``check._coverage``:
the geometric band, no longer drawn as a thick polyline, so not bit-identical to the drawing).
``cone_pixels``: the uncovered thread pixels in the fan beyond a curve's end
(``check_beyond._cone``: one pass over the fan's box instead of cv2.findNonZero and numpy
filters; its distance along the way equal to rounding, as numpy's matrix product sums).
"""

from __future__ import annotations

import math

import numpy as np

from threadrecon.core.compiled import helper, kernel


# Compiled ahead of time once per machine (core/compiled.py), so that numba is not loaded.
@kernel(
    "float64(float64[:, ::1], float64[::1], float64, float64, float64[::1], boolean[::1], float64)"
)
def overlap_length(uv, step, r2, gap, disp, strand, dtol):  # noqa: ANN001
    """``check._overlap``: half the 2D length of the steps (``step``, non-finite ones 0)
    between two samples that ``overlap_hits`` finds among the finite samples of ``uv`` (N, 2)
    (``s`` the arc length along the steps), as numpy summed it (pairwise). 0 with fewer than
    3 finite samples."""
    n = len(uv)
    ok = np.zeros(n, dtype=np.bool_)
    m = 0
    for i in range(n):
        if np.isfinite(uv[i, 0]) and np.isfinite(uv[i, 1]):
            ok[i] = True
            m += 1
    if m < 3:
        return 0.0
    seg = np.empty(n - 1)
    s = np.empty(n)
    s[0] = 0.0
    for k in range(n - 1):
        seg[k] = step[k] if np.isfinite(step[k]) else 0.0
        s[k + 1] = seg[k] if k == 0 else s[k] + seg[k]  # np.cumsum's running sum
    x, y, ss = np.empty(m), np.empty(m), np.empty(m)
    dd, st = np.empty(m), np.empty(m, dtype=np.bool_)
    j = 0
    for i in range(n):
        if ok[i]:
            x[j], y[j], ss[j], dd[j], st[j] = uv[i, 0], uv[i, 1], s[i], disp[i], strand[i]
            j += 1
    sub = _overlap_hits(x, y, ss, r2, gap, dd, st, dtol)
    hit = np.zeros(n, dtype=np.bool_)
    j = 0
    for i in range(n):
        if ok[i]:
            hit[i] = sub[j]
            j += 1
    both = np.empty(n - 1)
    for k in range(n - 1):
        both[k] = seg[k] if hit[k + 1] and hit[k] else 0.0
    return 0.5 * (0.0 + _pairwise_sum(both, 0, n - 1))


@helper()
def _overlap_hits(x, y, s, r2, gap, disp, strand, dtol):  # noqa: ANN001
    """(n,) bool: sample i lies within sqrt(r2) (squared distance <= r2) of a sample j with
    |s[i] - s[j]| > gap, unless both are ``strand`` samples whose disparities ``disp`` differ by
    ``dtol`` or more (two strands crossing at different depths). Samples must be finite; the
    sweep visits them sorted by x."""
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
                if strand[i] and strand[j] and abs(disp[i] - disp[j]) >= dtol:
                    continue
                hit[i] = True
                hit[j] = True
    return hit


@kernel("int64[:, ::1](float64, float64, int64, int64, float64[:, ::1])")
def field_pixels(x0, y0, w, h, uv):  # noqa: ANN001
    """The pixel (column, row) of the field's (h, w) box nearest to each (x, y) of ``uv``
    (rounded, clamped to the box); (-1, -1) where the point is not finite."""
    out = np.empty((len(uv), 2), dtype=np.int64)
    for k in range(len(uv)):
        x, y = uv[k, 0], uv[k, 1]
        if not (np.isfinite(x) and np.isfinite(y)):
            out[k, 0] = -1
            out[k, 1] = -1
            continue
        out[k, 0] = int(min(max(np.rint(x - x0), 0.0), w - 1.0))
        out[k, 1] = int(min(max(np.rint(y - y0), 0.0), h - 1.0))
    return out


@kernel("float64[::1](float32[::1], float64, float64, float64, float64[:, ::1], int64[:, ::1])")
def field_at(d, x0, y0, reach, uv, pix):  # noqa: ANN001
    """``MaskField.at`` over (N, 2) points: ``d`` (the field at each point's pixel ``pix`` of
    the box, ``field_pixels``) plus the point's distance to that pixel, saturated at
    ``reach``; ``reach`` where not finite."""
    out = np.empty(len(uv))
    for k in range(len(uv)):
        if pix[k, 0] < 0:
            out[k] = reach
            continue
        qx, qy = uv[k, 0] - x0, uv[k, 1] - y0
        cx, cy = float(pix[k, 0]), float(pix[k, 1])
        v = np.float64(d[k]) + math.hypot(qx - cx, qy - cy)
        out[k] = v if v < reach else reach
    return out


@kernel(
    "float64[::1](int64[::1], int64[::1], int64, float64[::1], float64[::1], float64[::1], "
    "float64[::1], float64)"
)
def nearest_residual(xs, row_ptr, y0, disp, qx, qy, qdisp, support_px):  # noqa: ANN001
    """``check._disparity_residual`` over the curve's points: per point (qx, qy) with disparity
    qdisp, |qdisp - disp[j]| + dist / support_px for its nearest pixel j (Euclidean) of a set
    given by rows (CSR: the pixels of row y0 + k are xs[row_ptr[k]:row_ptr[k + 1]], x
    ascending); 1e3 where the point is not finite or the set is empty. The search visits the
    rows outwards from the point's and stops when a row lies farther than the best pixel."""
    n = len(qx)
    n_rows = len(row_ptr) - 1
    out = np.empty(n)
    for k in range(n):
        x, y = qx[k], qy[k]
        if not (np.isfinite(x) and np.isfinite(y)) or n_rows <= 0:
            out[k] = 1e3
            continue
        r0 = min(max(int(np.rint(y)) - y0, 0), n_rows - 1)
        best = np.inf
        bj = -1
        step = 0
        while True:
            active = False
            for sgn in range(2):
                if step == 0 and sgn == 1:
                    continue
                r = r0 - step if sgn == 0 else r0 + step
                if r < 0 or r >= n_rows:
                    continue
                dy = (y0 + r) - y
                dy2 = dy * dy
                if dy2 > best:
                    continue
                active = True
                lo, hi = row_ptr[r], row_ptr[r + 1]
                if lo == hi:
                    continue
                a, b = lo, hi  # first pixel with x >= the point's
                while a < b:
                    m = (a + b) // 2
                    if xs[m] < x:
                        a = m + 1
                    else:
                        b = m
                for j in (a - 1, a):
                    if lo <= j < hi:
                        dx = xs[j] - x
                        d2 = dx * dx + dy2
                        if d2 < best:
                            best = d2
                            bj = j
            if not active and step > 0:
                break
            step += 1
            if step > n_rows:
                break
        if bj < 0:
            out[k] = 1e3
        else:
            out[k] = abs(qdisp[k] - disp[bj]) + math.sqrt(best) / support_px
    return out


@kernel("float32[::1](uint8[:, ::1], int64, int64, int64[:, ::1])")
def near_values(mask, x0, y0, pix):  # noqa: ANN001
    """The distance transform's value (3x3 L2 mask, steps a = 0.955 and b = 1.3693) at each
    box pixel ``pix`` (column, row; box origin x0, y0 in the (H, W) image ``mask``) whose
    nearest thread pixel lies within two steps: 0 on one; a or b for one in the 3x3
    neighbourhood; else 2a, a + b or 2b for one two columns/rows away (straight, a knight's
    move, diagonal; every path of three steps is at least 3a = 2.865 > 2b); -1 farther (or no
    pixel). Each value is one float32 sum, whatever the order of its steps."""
    h, w = mask.shape
    a = np.float32(0.955)
    b = np.float32(1.3693)
    out = np.empty(len(pix), dtype=np.float32)
    for k in range(len(pix)):
        out[k] = -1.0
        if pix[k, 0] < 0:
            continue
        x, y = pix[k, 0] + x0, pix[k, 1] + y0
        best = np.float32(np.inf)
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                yy, xx = y + dy, x + dx
                if not (0 <= yy < h and 0 <= xx < w and mask[yy, xx]):
                    continue
                m, n = max(abs(dx), abs(dy)), min(abs(dx), abs(dy))
                if m == 0:
                    v = np.float32(0.0)
                elif m == 1:
                    v = a if n == 0 else b
                elif n == 0:
                    v = a + a
                elif n == 1:
                    v = a + b
                else:
                    v = b + b
                if v < best:
                    best = v
        if best < np.inf:
            out[k] = best
    return out


@kernel("boolean[::1](float64[:, ::1], float64[:, ::1], float64)")
def covered_by(px, curve, r2):  # noqa: ANN001
    """(k,) bool: pixel i of ``px`` (k, 2) lies within sqrt(r2) of a point of ``curve`` (m, 2)
    (squared distance <= r2, the same sums as numpy's (a - b) ** 2 + (c - d) ** 2)."""
    out = np.zeros(len(px), dtype=np.bool_)
    for i in range(len(px)):
        x, y = px[i, 0], px[i, 1]
        for j in range(len(curve)):
            dx = x - curve[j, 0]
            dy = y - curve[j, 1]
            if dx * dx + dy * dy <= r2:
                out[i] = True
                break
    return out


@kernel("float64[::1](int64[::1], int64[::1], float64, float64, float64[:, ::1], float64, float64)")
def band_d2(cols, row_ptr, ox, oy, xy, r, done):  # noqa: ANN001
    """Squared distances to the polyline ``xy`` (m, 2) of the thread pixels within ``r`` of it.
    The thread pixels by rows: row i holds the columns ``cols[row_ptr[i]:row_ptr[i + 1]]``
    (ascending); pixel (i, j) is the point (j + ox, i + oy). Per run of 8 consecutive segments,
    only the thread pixels of the run's bounding box grown by ``r`` are measured (the geometric
    band that a polyline drawn 2 r wide approximates). A pixel is not measured further once a
    segment lies within sqrt(``done``) of it: its value is then at most ``done`` but not
    necessarily the least (exact with ``done`` = 0; counts of values <= any T >= ``done``
    are exact either way). With ``done`` > 0 a first pass over the runs' boxes grown by
    sqrt(``done``) only settles the pixels near their own run (most of a thread's: else a run
    measures the pixels of its neighbours' segments first, against all its 8); the pass over
    the ``r`` boxes then measures the rest as before: the same values where above ``done``."""
    best = _band_best(cols, row_ptr, ox, oy, xy, r, done)
    r2 = r * r
    n = 0
    for q in range(len(best)):
        if best[q] <= r2:
            n += 1
    out = np.empty(n, np.float64)
    n = 0
    for q in range(len(best)):
        if best[q] <= r2:
            out[n] = best[q]
            n += 1
    return out


@kernel(
    "int64(float64[:, ::1], boolean[::1], float64, float64, int64[::1], int64[::1], float64, "
    "float64, float64, float64, float64)"
)
def coverage_count(uv, inside, x0, y0, cols, row_ptr, ox, oy, cover_px, band_px, done):  # noqa: ANN001
    """``check._coverage``'s count: the thread pixels (by rows, as for ``band_d2``) within
    reach + 1.5 px of the polyline of the ``inside`` points of ``uv`` (N, 2), taken relative
    to (x0, y0) and rounded to 1/4 px, where reach = ceil(``cover_px`` + half) and half the
    thread's half-width: the thread pixels within ``band_px`` + 1.5 px over twice the
    polyline's length (at least 1 px; half at most ``band_px``). The band is measured out to
    ceil(``cover_px`` + ``band_px``) + 1.5 px, ``done`` as for ``band_d2``; the length is
    numpy's sum (pairwise) of the unrounded steps. At least 2 points must be inside."""
    m = 0
    for k in range(len(uv)):
        if inside[k]:
            m += 1
    xy = np.empty((m, 2))
    m = 0
    for k in range(len(uv)):
        if inside[k]:
            xy[m, 0] = uv[k, 0] - x0
            xy[m, 1] = uv[k, 1] - y0
            m += 1
    steps = np.empty(m - 1)
    for k in range(m - 1):
        dx = xy[k + 1, 0] - xy[k, 0]
        dy = xy[k + 1, 1] - xy[k, 1]
        steps[k] = math.sqrt(dx * dx + dy * dy)
    length = 0.0 + _pairwise_sum(steps, 0, m - 1)  # np.sum's order: identity, then pairwise
    poly = np.empty((m, 2))
    for k in range(m):
        poly[k, 0] = np.rint(xy[k, 0] * 4.0) / 4.0  # as drawn with 2 fractional bits
        poly[k, 1] = np.rint(xy[k, 1] * 4.0) / 4.0
    widest = math.ceil(cover_px + band_px) + 1.5
    best = _band_best(cols, row_ptr, ox, oy, poly, widest, done)
    band_r2 = (band_px + 1.5) * (band_px + 1.5)
    band = 0
    for q in range(len(best)):
        if best[q] <= band_r2:
            band += 1
    half = min(0.5 * band / max(length, 1.0), band_px)
    reach = math.ceil(cover_px + half)
    r2 = (reach + 1.5) * (reach + 1.5)
    n = 0
    for q in range(len(best)):
        if best[q] <= r2:
            n += 1
    return n


@kernel("float64(float64[::1], float64[::1], float64[::1], boolean[::1], float64)")
def unmeasured_length(step3, step, z, supported, half_per_f):  # noqa: ANN001
    """``check._unmeasured_length``: over each step with an unsupported end sample, ``step3``
    less ``step * half_per_f * (z[k + 1] + z[k])`` (the 2D step at the mean depth), summed
    where finite and positive as numpy sums with ``where`` (each run of counted values of the
    free steps' array added pairwise in turn)."""
    n = len(step)
    extra = np.empty(n)
    m = 0
    for k in range(n):
        if not (supported[k + 1] and supported[k]):
            extra[m] = step3[k] - step[k] * half_per_f * (z[k + 1] + z[k])
            m += 1
    acc = 0.0
    i = 0
    while i < m:
        if np.isfinite(extra[i]) and extra[i] > 0.0:
            j = i
            while j < m and np.isfinite(extra[j]) and extra[j] > 0.0:
                j += 1
            acc += _pairwise_sum(extra, i, j - i)
            i = j
        else:
            i += 1
    return acc


@kernel("float64(float64[::1], boolean[::1])")
def unsupported_travel(z, supported):  # noqa: ANN001
    """``check._unsupported_travel``: the depth's total variation over each stretch between
    two supported samples less its net change there, over each unsupported end the whole
    variation, summed as numpy sums (pairwise); the whole variation (numpy's sum of |dz|)
    when no sample is supported."""
    n = len(z)
    tv = np.empty(max(n - 1, 0))
    for k in range(n - 1):
        tv[k] = abs(z[k + 1] - z[k])
    m = 0
    for k in range(n):
        if supported[k]:
            m += 1
    if m == 0:
        return 0.0 + _pairwise_sum(tv, 0, n - 1)
    csum = np.empty(n)  # np.cumsum's running sums after a leading 0
    csum[0] = 0.0
    for k in range(n - 1):
        csum[k + 1] = tv[k] if k == 0 else csum[k] + tv[k]
    edges = np.empty(m + 2, np.int64)
    edges[0] = 0
    edges[m + 1] = n - 1
    m = 1
    for k in range(n):
        if supported[k]:
            edges[m] = k
            m += 1
    extra = np.empty(m)
    for k in range(m):
        travel = csum[edges[k + 1]] - csum[edges[k]]
        net = 0.0 if k == 0 or k == m - 1 else abs(z[edges[k + 1]] - z[edges[k]])
        extra[k] = travel - net
    return 0.0 + _pairwise_sum(extra, 0, m)


@helper()
def _pairwise_sum(a, lo, n):  # noqa: ANN001
    """numpy's pairwise sum of the float64 values a[lo:lo + n] (its reduction's order: blocks
    of up to 128 in 8 running sums; above that the two halves, split at a multiple of 8,
    summed first and added), without recursion (an explicit stack of tasks)."""
    if n <= 128:
        return _block_sum(a, lo, n)
    t_lo = np.empty(256, np.int64)  # tasks: (start, count, combine?); depth < 64 halvings
    t_n = np.empty(256, np.int64)
    t_add = np.empty(256, np.bool_)
    vals = np.empty(256)
    nt, nv = 1, 0
    t_lo[0], t_n[0], t_add[0] = lo, n, False
    while nt > 0:
        nt -= 1
        if t_add[nt]:  # both halves done: left + right
            nv -= 1
            vals[nv - 1] = vals[nv - 1] + vals[nv]
        elif t_n[nt] <= 128:
            vals[nv] = _block_sum(a, t_lo[nt], t_n[nt])
            nv += 1
        else:
            s, m = t_lo[nt], t_n[nt]
            m2 = m // 2
            m2 -= m2 % 8
            t_add[nt] = True  # after the right half (pushed next) and the left (on top)
            t_lo[nt + 1], t_n[nt + 1], t_add[nt + 1] = s + m2, m - m2, False
            t_lo[nt + 2], t_n[nt + 2], t_add[nt + 2] = s, m2, False
            nt += 3
    return vals[0]


@helper()
def _block_sum(a, lo, n):  # noqa: ANN001
    """numpy's pairwise sum of at most 128 values: sequential below 8, else 8 running sums."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@helper()
def _band_best(cols, row_ptr, ox, oy, xy, r, done):  # noqa: ANN001
    """``band_d2``'s least squared distance of each thread pixel (inf: none measured)."""
    h = len(row_ptr) - 1
    m = len(xy)
    if m == 0 or h <= 0 or len(cols) == 0:
        return np.full(len(cols), np.inf)
    nseg = max(m - 1, 1)
    seg = np.empty((nseg, 5))  # per segment: start, direction, 1 / squared length (0: a point)
    for k in range(nseg):
        k1 = min(k + 1, m - 1)
        dx, dy = xy[k1, 0] - xy[k, 0], xy[k1, 1] - xy[k, 1]
        ll = dx * dx + dy * dy
        seg[k, 0], seg[k, 1], seg[k, 2], seg[k, 3] = xy[k, 0], xy[k, 1], dx, dy
        seg[k, 4] = 1.0 / ll if ll > 0.0 else 0.0
    best = np.full(len(cols), np.inf)
    if done <= 0.0:
        _band_pass(cols, row_ptr, ox, oy, xy, seg, best, r, done)
        return best
    _band_pass(cols, row_ptr, ox, oy, xy, seg, best, min(math.sqrt(done), r), done)
    # The pass over the r boxes leaves a pixel at most ``done`` as it is (its first test) and
    # measures each other one alone: run over those pixels only, by rows as they lie (a
    # subsequence of each row's ascending columns), it gives them the same values in the same
    # order of segments, without scanning the settled ones (most of a thread's, ~half of the
    # coverage's time)
    left = 0
    for q in range(len(best)):
        if best[q] > done:
            left += 1
    if left == 0:
        return best
    idx = np.empty(left, np.int64)
    cols2 = np.empty(left, np.int64)
    ptr2 = np.empty(h + 1, np.int64)
    k = 0
    for i in range(h):
        ptr2[i] = k
        for q in range(row_ptr[i], row_ptr[i + 1]):
            if best[q] > done:
                idx[k] = q
                cols2[k] = cols[q]
                k += 1
    ptr2[h] = k
    best2 = np.empty(left)
    for k in range(left):
        best2[k] = best[idx[k]]
    _band_pass(cols2, ptr2, ox, oy, xy, seg, best2, r, done)
    for k in range(left):
        best[idx[k]] = best2[k]
    return best


@helper()
def _band_pass(cols, row_ptr, ox, oy, xy, seg, best, r, done):  # noqa: ANN001
    """``band_d2``'s pass over the runs of 8 segments, their boxes grown by ``r``: ``best``
    lowered to each measured segment's squared distance (a pixel at most ``done`` is left)."""
    h = len(row_ptr) - 1
    m = len(xy)
    nseg = len(seg)
    inf = np.inf
    for c0 in range(0, nseg, 8):  # runs of 8 segments: a pixel is visited once per run
        c1 = min(c0 + 8, nseg)
        cx0, cx1, cy0, cy1 = inf, -inf, inf, -inf
        for k in range(c0, min(c1 + 1, m)):
            cx0 = min(cx0, xy[k, 0])
            cx1 = max(cx1, xy[k, 0])
            cy0 = min(cy0, xy[k, 1])
            cy1 = max(cy1, xy[k, 1])
        jlo = cx0 - r - ox
        jhi = cx1 + r - ox
        si0 = max(0, int(math.floor(cy0 - r - oy)))
        si1 = min(h, int(math.ceil(cy1 + r - oy)) + 1)
        for i in range(si0, si1):
            y = i + oy
            lo, hi = row_ptr[i], row_ptr[i + 1]
            while lo < hi:  # the row's first column >= jlo (binary search)
                mid = (lo + hi) >> 1
                if cols[mid] < jlo:
                    lo = mid + 1
                else:
                    hi = mid
            for q in range(lo, row_ptr[i + 1]):
                if cols[q] > jhi:
                    break
                b = best[q]
                if b <= done:
                    continue
                x = cols[q] + ox
                for k in range(c0, c1):
                    px, py = x - seg[k, 0], y - seg[k, 1]
                    dx, dy = seg[k, 2], seg[k, 3]
                    t = min(max((px * dx + py * dy) * seg[k, 4], 0.0), 1.0)
                    ex = px - t * dx
                    ey = py - t * dy
                    d2 = ex * ex + ey * ey
                    if d2 < b:
                        b = d2
                        if b <= done:
                            break
                best[q] = b


@kernel(
    "Tuple((float64[:, ::1], float64[::1]))(float64[:, ::1], float64, float64, float64, float64, "
    "uint8[:, ::1], float64, float64, float64, int64)"
)
def cone_pixels(curve, tx, ty, wx, wy, mask, radius, cos, cover_px, margin):  # noqa: ANN001
    """``check_beyond._cone``: the thread pixels (x, y) of ``mask`` within ``radius`` of the
    tip (tx, ty), within acos(cos) of the unit way (wx, wy) and more than ``cover_px`` along
    it, farther than ``cover_px`` from every sample of ``curve`` (m, 2), with their distance
    along the way; searched in the box of the fan's outline (the tip and 9 points on its arc)
    grown by ``margin`` px, row by row (cv2.findNonZero's order), with numpy's arithmetic."""
    h, w = mask.shape
    half = math.acos(min(max(cos, -1.0), 1.0))
    a0 = math.atan2(wy, wx)
    xmin, xmax, ymin, ymax = tx, tx, ty, ty
    for k in range(9):  # the fan's outline
        a = a0 + half * (k / 4.0 - 1.0)
        x = tx + radius * math.cos(a)
        y = ty + radius * math.sin(a)
        xmin, xmax = min(xmin, x), max(xmax, x)
        ymin, ymax = min(ymin, y), max(ymax, y)
    x0 = max(int(math.floor(xmin)) - margin, 0)
    y0 = max(int(math.floor(ymin)) - margin, 0)
    x1 = min(int(math.ceil(xmax)) + margin + 1, w)
    y1 = min(int(math.ceil(ymax)) + margin + 1, h)
    reach = radius + cover_px
    r2 = cover_px * cover_px
    near = np.empty(len(curve), np.int64)  # the samples that may cover a pixel of the fan
    n_near = 0
    for j in range(len(curve)):
        if math.hypot(curve[j, 0] - tx, curve[j, 1] - ty) <= reach:
            near[n_near] = j
            n_near += 1
    px = np.empty((max((x1 - x0) * (y1 - y0), 0), 2))
    along = np.empty(px.shape[0])
    n = 0
    for y in range(y0, y1):
        for x in range(x0, x1):
            if mask[y, x] == 0:
                continue
            rx = float(x) - tx
            ry = float(y) - ty
            dist = math.hypot(rx, ry)
            al = rx * wx + ry * wy
            if not (dist <= radius and al >= cos * dist and al > cover_px):
                continue
            covered = False
            for q in range(n_near):
                j = near[q]
                dx = float(x) - curve[j, 0]
                dy = float(y) - curve[j, 1]
                if dx * dx + dy * dy <= r2:
                    covered = True
                    break
            if covered:
                continue
            px[n, 0] = x
            px[n, 1] = y
            along[n] = al
            n += 1
    return px[:n].copy(), along[:n].copy()
