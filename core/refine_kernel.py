"""Compiled kernels of the two-view refinement (core/refine.py).

``mask_runs``: the horizontal runs of a thread mask, one pass over the image that skips eight
empty pixels at a time. ``edge_centres``: each run's sub-pixel centre and its variance, with
the same floating-point operations in the same order as the numpy form it replaced (bit-identical
centres; tests/core/test_refine_runs.py keeps that form as the reference). ``nearest_runs``: the
run nearest a column on a row. ``gauss_newton``: the refinement's rounds (association, weights,
one constrained least-squares solve each) on the B-spline basis in banded form (degree + 1
nonzeros a row): a QR factor by Givens rotations in O(rows (k + 1)^2) instead of a dense QR,
the bounds by Lawson and Hanson's LSI -> LDP -> NNLS (``lsi``). Its results agree with the
dense numpy form to rounding (~1e-11 px of disparity on the paper's frames), not to the bit.
"""

from __future__ import annotations

import numpy as np

from threadrecon.core.compiled import helper, kernel

NORMAL_MIN_ANGLE = 1e-3  # sine: the normal equations lose ~(1 / this)^2 eps, ~1e-10


# Compiled ahead of time once per machine (core/compiled.py), so that numba is not loaded.
@kernel(
    "Tuple((int64[::1], int64[::1], int64[::1]))"
    "(uint8[:, ::1], int64[:, ::1], int64, int64, int64, int64)"
)
def mask_runs(mask, words, y0, y1, x0, x1):  # noqa: ANN001
    """Row, first and last column (inclusive) of every maximal run of nonzero pixels of
    ``mask`` (H, W) inside rows y0..y1-1 and columns x0..x1-1, in row-major order. ``words``
    is the same mask seen as (H, W / 8) int64 (W a multiple of 8) to skip empty stretches
    eight pixels at a time, or a (0, 0) array (pixel by pixel)."""
    if words.shape[0] > 0:  # whole words: x0 = 0, x1 = W
        w0, w1, step = 0, words.shape[1], 8
    else:
        w0, w1, step = x0, x1, 1
    n = 0
    for y in range(y0, y1):  # pass 1: count the runs
        prev = False
        for wi in range(w0, w1):
            if step == 8 and words[y, wi] == 0:
                prev = False
                continue
            for x in range(step * wi, step * wi + step):
                on = mask[y, x] != 0
                if on and not prev:
                    n += 1
                prev = on
    row = np.empty(n, np.int64)
    first = np.empty(n, np.int64)
    last = np.empty(n, np.int64)
    k = 0
    for y in range(y0, y1):  # pass 2: record them
        prev = False
        for wi in range(w0, w1):
            if step == 8 and words[y, wi] == 0:
                if prev:
                    last[k - 1] = step * wi - 1
                prev = False
                continue
            for x in range(step * wi, step * wi + step):
                on = mask[y, x] != 0
                if on and not prev:
                    row[k] = y
                    first[k] = x
                    k += 1
                elif prev and not on:
                    last[k - 1] = x - 1
                prev = on
        if prev:
            last[k - 1] = step * w1 - 1
    return row, first, last


@kernel(
    "Tuple((float64[::1], float64[::1]))"
    "(int64[::1], int64[::1], int64[::1], float32[:, ::1], float64, int64, int64)"
)
def edge_centres(row, a, b, grey, background, edge_px, flank_px):  # noqa: ANN001
    """Sub-pixel centres (R,) px and their variances (R,) px^2 of the runs a..b (inclusive
    columns) on rows ``row`` of the (H, W) grey image, in row-major order.

    Model of a row's cut through the thread: the background is a line between the mean grey
    level of the ``flank_px`` pixels beyond each end of the window (the run and ``edge_px``
    pixels beyond each of its ends, half the gap where another run is nearer); the thread's
    contrast w(x) = background(x) - I(x) (its sign taken over the run) is symmetric about the
    axis, so the centre is its centroid sum w x / sum w. Its variance is that of the centroid
    under pixel noise sigma_n^2 (estimated from neighbouring flank pixels over the whole image:
    the median of their squared differences / 0.4549, the median of chi^2 with one degree of
    freedom, / 2 for a difference of two pixels; at least two roundings to 8 bits) and errors
    of the two flank levels: sigma_n^2 / flank_px each, plus a quarter of their squared
    difference (the flanks disagree where the background is not a line: an occluder or
    another strand beside the run, texture). Where a window lacks a flank (the image border),
    or its contrast is not significant (the centroid's noise not below the mask's own
    uncertainty), the centre is the run's midpoint with the variance of a uniform position
    over the run, (L^2 + 1) / 12 (the mask alone)."""
    n = len(a)
    W = grey.shape[1]
    centre = np.empty(n)
    var = np.empty(n)
    if n == 0:
        return centre, var
    lo = np.empty(n, np.int64)
    hi = np.empty(n, np.int64)
    fl_lo = np.empty(n, np.int64)
    fr_hi = np.empty(n, np.int64)
    # pass 1: windows, flanks and the differences of neighbouring flank pixels (the noise)
    n_diff = 0
    for i in range(n):
        prev_end = b[i - 1] if i > 0 and row[i - 1] == row[i] else -1
        next_start = a[i + 1] if i + 1 < n and row[i + 1] == row[i] else W
        lo[i] = a[i] - min(edge_px, (a[i] - prev_end - 1) // 2)
        hi[i] = b[i] + min(edge_px, (next_start - b[i] - 1) // 2)
        fl_lo[i] = max(lo[i] - flank_px, prev_end + 1)
        fr_hi[i] = min(hi[i] + flank_px, next_start - 1)
        n_diff += max(lo[i] - 1 - fl_lo[i], 0) + max(fr_hi[i] - hi[i] - 1, 0)
    diffs = np.empty(n_diff)
    k = 0
    for i in range(n):  # left flanks first, then right flanks (the order is immaterial)
        y = row[i]
        for x in range(fl_lo[i] + 1, lo[i]):
            d = np.float64(grey[y, x]) - np.float64(grey[y, x - 1])
            diffs[k] = d * d
            k += 1
    for i in range(n):
        y = row[i]
        for x in range(hi[i] + 2, fr_hi[i] + 1):
            d = np.float64(grey[y, x]) - np.float64(grey[y, x - 1])
            diffs[k] = d * d
            k += 1
    est = np.median(diffs) / 0.4549 / 2.0 if n_diff >= 20 else 0.0
    noise = max(est, 2.0 / 12.0)
    # pass 2: the centroid of the contrast over each window and its variance
    for i in range(n):
        y = row[i]
        ai, bi, li, hii = a[i], b[i], lo[i], hi[i]
        fl_hi, fr_lo = li - 1, hii + 1
        n_l = max(fl_hi - fl_lo[i] + 1, 0)
        n_r = max(fr_hi[i] - fr_lo + 1, 0)
        flanked = n_l > 0 and n_r > 0
        mid = 0.5 * (ai + bi)
        t = bi - ai + 1.0
        var_mask = (t * t + 1.0) / 12.0
        centre[i] = mid
        var[i] = var_mask
        if not flanked:
            continue  # the image border: the mask alone
        s_l = 0.0
        for x in range(fl_lo[i], fl_hi + 1):
            s_l += np.float64(grey[y, x])
        s_r = 0.0
        for x in range(fr_lo, fr_hi[i] + 1):
            s_r += np.float64(grey[y, x])
        b_l = s_l / n_l
        b_r = s_r / n_r
        x0 = 0.5 * (fl_lo[i] + fl_hi)
        x1 = 0.5 * (fr_lo + fr_hi[i])
        slope = (b_r - b_l) / (x1 - x0)
        s_on = 0.0
        sw = 0.0
        swx = 0.0
        for x in range(li, hii + 1):
            w = b_l + slope * (x - x0) - np.float64(grey[y, x])  # contrast, signed
            if ai <= x <= bi:
                s_on += w
            sw += w
            swx += w * x
        if s_on < 0:  # lighter than its background
            sw = -sw
            swx = -swx
        if not (sw > 0 and sw * sw > 0):  # no contrast (or beyond the square's range): the mask
            continue
        s0 = np.float64(hii - li + 1)
        s1 = 0.5 * s0 * (li + hii)
        s2 = (hii * (hii + 1.0) * (2 * hii + 1.0) - (li - 1.0) * li * (2 * li - 1.0)) / 6.0
        c = swx / sw
        sdx2 = s2 - 2.0 * c * s1 + s0 * c * c  # sum (x - c)^2
        sdx_tau = (s2 - (c + x0) * s1 + s0 * c * x0) / (x1 - x0)  # sum (x - c) tau
        sdx_1mtau = s1 - s0 * c - sdx_tau  # sum (x - c) (1 - tau)
        s_b = noise / flank_px + 0.25 * ((b_l - b_r) * (b_l - b_r))  # each flank level's
        v = (noise * sdx2 + s_b * (sdx_1mtau * sdx_1mtau + sdx_tau * sdx_tau)) / (sw * sw)
        if np.isfinite(c) and c >= li and c <= hii and v < var_mask:
            centre[i] = c
            var[i] = v
    return centre, var


@helper()
def _nearest(key, centre, row_start, key_scale, r, x):  # noqa: ANN001
    """Index of the run nearest column ``x`` on row ``r`` (``refine._Runs.nearest_index``:
    the two runs either side of ``x`` in the row-major key order); -1 where the row holds
    none or ``x`` is not finite."""
    if r < 0 or r >= len(row_start) - 1 or not np.isfinite(x):
        return -1
    lo = row_start[r]
    hi = row_start[r + 1]
    if hi <= lo:
        return -1
    q = key_scale * r + x
    a = 0
    b = len(key)
    while a < b:  # np.searchsorted(key, q, "left")
        mid = (a + b) >> 1
        if key[mid] < q:
            a = mid + 1
        else:
            b = mid
    best = -1
    best_d = np.inf
    for cand in (a - 1, a):
        if cand >= lo and cand < hi:
            dist = abs(centre[cand] - x)
            if dist < best_d:
                best = cand
                best_d = dist
    return best


@kernel("int64[::1](float64[::1], float64[::1], int64[::1], float64, int64[::1], float64[::1])")
def nearest_runs(key, centre, row_start, key_scale, rows, x):  # noqa: ANN001
    """:func:`_nearest` for every (row, x) pair: (n,) run indices, -1 for none."""
    out = np.empty(len(x), np.int64)
    for i in range(len(x)):
        out[i] = _nearest(key, centre, row_start, key_scale, rows[i], x[i])
    return out


@helper()
def _givens_row(R, qr, vals, f, rhs, w):  # noqa: ANN001
    """Rotate one row (``vals`` at columns f .. f + K - 1, right-hand side ``rhs``) into the
    banded triangular factor ``R`` (m, K) (R[j, c] is column j + c of row j) and ``qr``
    (Q^T r); ``w`` (K,) is scratch. Rows must come in nondecreasing order of ``f``: the
    factor's rows at and after ``f`` then end by column f + K - 1, and K rotations finish the
    row."""
    m, K = R.shape
    for t in range(K):
        w[t] = vals[t]
    rh = rhs
    for j in range(f, min(f + K, m)):
        x = w[0]
        if x != 0.0:
            rjj = R[j, 0]
            h = np.sqrt(rjj * rjj + x * x)  # no overflow: |entries| << 1e150
            c = rjj / h
            s = x / h
            R[j, 0] = h
            for t in range(1, K):
                rt = R[j, t]
                wt = w[t]
                R[j, t] = c * rt + s * wt
                w[t - 1] = c * wt - s * rt
            q = qr[j]
            qr[j] = c * q + s * rh
            rh = c * rh - s * q
        else:
            for t in range(1, K):
                w[t - 1] = w[t]
        w[K - 1] = 0.0


@helper()
def _ls_columns(Mt, cols, p, e_row):  # noqa: ANN001
    """Least-squares coefficients (p,) of the columns ``Mt[cols[:p]]`` (each of length r)
    fitted to the unit vector e_{e_row} (Householder QR), and the magnitude of the last
    column's diagonal relative to its norm (its independence of the others)."""
    r = Mt.shape[1]
    Q = np.empty((r, p))
    for k in range(p):
        for i in range(r):
            Q[i, k] = Mt[cols[k], i]
    y = np.zeros(r)
    y[e_row] = 1.0
    last_norm = 0.0
    for i in range(r):
        last_norm += Q[i, p - 1] * Q[i, p - 1]
    last_norm = np.sqrt(last_norm)
    for k in range(p):
        sig = 0.0
        for i in range(k, r):
            sig += Q[i, k] * Q[i, k]
        sig = np.sqrt(sig)
        if sig == 0.0:
            continue
        alpha = -sig if Q[k, k] >= 0 else sig
        # v = x - alpha e_k, stored in Q[k:, k]; H = I - 2 v v^T / v^T v
        Q[k, k] -= alpha
        vtv = 0.0
        for i in range(k, r):
            vtv += Q[i, k] * Q[i, k]
        for j in range(k + 1, p):
            s = 0.0
            for i in range(k, r):
                s += Q[i, k] * Q[i, j]
            s = 2.0 * s / vtv
            for i in range(k, r):
                Q[i, j] -= s * Q[i, k]
        s = 0.0
        for i in range(k, r):
            s += Q[i, k] * y[i]
        s = 2.0 * s / vtv
        for i in range(k, r):
            y[i] -= s * Q[i, k]
        Q[k, k] = alpha  # the diagonal of R (the rest of column k below it is v, unused)
    z = np.empty(p)
    for k in range(p - 1, -1, -1):
        s = y[k]
        for j in range(k + 1, p):
            s -= Q[k, j] * z[j]  # R[k, j]
        z[k] = s / Q[k, k] if Q[k, k] != 0.0 else 0.0
    rel = abs(Q[p - 1, p - 1]) / last_norm if last_norm > 0.0 else 0.0
    return z, rel


@helper()
def _nnls(Mt, maxiter, cols, n_warm):  # noqa: ANN001
    """min ||M u - e|| over u >= 0, M = Mt.T (r, N), e the last unit vector of length r
    (Lawson and Hanson's active-set algorithm, ch. 23: a column joins the passive set only if
    independent of it and with a positive coefficient). ``cols`` (>= r,) holds a passive set
    to start from in its first ``n_warm`` entries (the last solve's: the constraints active
    there; taken where its least-squares coefficients are all positive, else a cold start)
    and the final passive set on return. Returns u (N,), a status (0, or 4 when ``maxiter``
    inner steps did not suffice) and the size of the passive set."""
    N, r = Mt.shape
    u = np.zeros(N)
    passive = np.zeros(N, np.bool_)
    rejected = np.zeros(N, np.bool_)
    p = 0
    resid = np.zeros(r)
    resid[r - 1] = 1.0
    if 0 < n_warm <= r:  # warm start: the last passive set, if feasible here
        z, rel = _ls_columns(Mt, cols, n_warm, r - 1)
        feasible = True
        for k in range(n_warm):
            if not (z[k] > 0.0 and np.isfinite(z[k])):
                feasible = False
        if feasible:
            p = n_warm
            for k in range(p):
                passive[cols[k]] = True
                u[cols[k]] = z[k]
                for i in range(r):
                    resid[i] -= Mt[cols[k], i] * z[k]
    w = np.empty(N)
    scale = 0.0
    for j in range(N):
        for i in range(r):
            scale = max(scale, abs(Mt[j, i]))
    tol = 1e-14 * max(scale, 1e-300) * r
    steps = 0
    while True:
        for j in range(N):
            s = 0.0
            for i in range(r):
                s += Mt[j, i] * resid[i]
            w[j] = s
        while True:
            t = -1
            wmax = tol
            for j in range(N):
                if not passive[j] and not rejected[j] and w[j] > wmax:
                    wmax = w[j]
                    t = j
            if t < 0 or p == r:
                return u, 0, p
            cols[p] = t
            z, rel = _ls_columns(Mt, cols, p + 1, r - 1)
            if rel > 1e-10 and z[p] > 0.0:
                break
            rejected[t] = True  # dependent on the passive columns, or it would enter negative
        rejected[:] = False
        passive[t] = True
        p += 1
        while True:  # step back until every passive coefficient is positive
            neg = False
            for k in range(p):
                if z[k] <= 0.0:
                    neg = True
            if not neg:
                break
            steps += 1
            if steps > maxiter:
                return u, 4, p
            alpha = 1.0
            for k in range(p):
                if z[k] <= 0.0:
                    uk = u[cols[k]]
                    alpha = min(alpha, uk / (uk - z[k]))
            q = 0
            for k in range(p):
                j = cols[k]
                u[j] += alpha * (z[k] - u[j])
                if u[j] <= tol:
                    u[j] = 0.0
                    passive[j] = False
                else:
                    cols[q] = j
                    q += 1
            p = q
            if p == 0:
                break
            z, rel = _ls_columns(Mt, cols, p, r - 1)
        for k in range(p):
            u[cols[k]] = z[k]
        steps += 1
        if steps > maxiter:
            return u, 4, p
        for i in range(r):
            resid[i] = 0.0
        resid[r - 1] = 1.0
        for j in range(N):
            if u[j] != 0.0:
                for i in range(r):
                    resid[i] -= Mt[j, i] * u[j]


@helper()
def _normal_factor(vals, first, rhs, n_rows, ridge, R, qr):  # noqa: ANN001
    """R (m, K) banded upper triangular and Q^T r (m,) of the least-squares problem
    [A; ridge I] x ~ [r; 0] (rows ``vals[:n_rows]`` at columns ``first``) from the Cholesky
    factor of its normal matrix A^T A + ridge^2 I (the same R as a QR gives, up to the
    rows' signs). Its error grows with the square of A's condition: False (R unusable)
    where a column lies within ``NORMAL_MIN_ANGLE`` of the span of the columns before it
    (relative to its norm: a condition of 1 / that at least), then the caller rotates."""
    m, K = R.shape
    N = np.zeros((m, K))  # N[j, c] = (A^T A)[j, j + c]
    g = np.zeros(m)  # A^T r
    for i in range(n_rows):
        f = first[i]
        for a in range(K):
            va = vals[i, a]
            if va == 0.0:
                continue
            g[f + a] += va * rhs[i]
            for b in range(a, K):
                N[f + a, b - a] += va * vals[i, b]
    for j in range(m):
        N[j, 0] += ridge * ridge
    for j in range(m):  # banded Cholesky, R^T R = N
        s = N[j, 0]
        for i in range(max(0, j - K + 1), j):
            s -= R[i, j - i] * R[i, j - i]
        if not (s > 0.0 and s >= NORMAL_MIN_ANGLE * NORMAL_MIN_ANGLE * N[j, 0]):
            return False
        rjj = np.sqrt(s)
        R[j, 0] = rjj
        for c in range(1, K):
            if j + c >= m:
                break
            s2 = N[j, c]
            for i in range(max(0, j + c - K + 1), j):
                s2 -= R[i, j - i] * R[i, j + c - i]
            R[j, c] = s2 / rjj
    for j in range(m):  # Q^T r = R^-T A^T r
        s = g[j]
        for i in range(max(0, j - K + 1), j):
            s -= R[i, j - i] * qr[i]
        qr[j] = s / R[j, 0]
    return True


@helper()
def _givens_factor(vals, first, rhs, n_rows, ridge, R, qr):  # noqa: ANN001
    """R and Q^T r of [A; ridge I] x ~ [r; 0] by Givens rotations, rows in order of their
    first column (a counting sort; the ridge's row j after the rows that start at j)."""
    m, K = R.shape
    one = np.zeros(K)
    w = np.empty(K)
    start = np.zeros(m + 1, np.int64)
    for i in range(n_rows):
        start[first[i] + 1] += 1
    for j in range(m):
        start[j + 1] += start[j]
    order = np.empty(n_rows, np.int64)
    for i in range(n_rows):
        order[start[first[i]]] = i
        start[first[i]] += 1
    i = 0
    for j in range(m):
        while i < n_rows and first[order[i]] <= j:
            o = order[i]
            _givens_row(R, qr, vals[o], first[o], rhs[o], w)
            i += 1
        fj = min(j, m - K)
        one[:] = 0.0
        one[j - fj] = ridge
        _givens_row(R, qr, one, fj, 0.0, w)
    while i < n_rows:
        o = order[i]
        _givens_row(R, qr, vals[o], first[o], rhs[o], w)
        i += 1


@helper()
def _lsi(vals, first, rhs, n_rows, ridge, band_g, first_g, h, m, maxiter, warm, n_warm):  # noqa: ANN001, E501
    """min ||A x - r|| subject to G x >= h (Lawson and Hanson: LSI -> LDP -> NNLS) for the
    banded rows ``vals[:n_rows]`` at columns ``first`` (any order) with right-hand sides
    ``rhs``, plus ``ridge`` times the identity; the rows of G are banded too (``band_g`` at
    ``first_g``); ``warm``, ``n_warm``: the NNLS's passive set to start from (:func:`_nnls`).
    Returns x (m,), a status: 0, 3 (the constraints cannot be met), 4 (NNLS iteration limit)
    or 5 (a value of the system is not finite), and the size of the final passive set."""
    K = vals.shape[1]
    R = np.zeros((m, K))
    qr = np.zeros(m)
    x = np.zeros(m)
    # R and Q^T r of [A; ridge I]: from the normal equations where they are well
    # conditioned (O(rows K^2) multiply-adds), else by rotations
    if not _normal_factor(vals, first, rhs, n_rows, ridge, R, qr):
        R[:, :] = 0.0
        qr[:] = 0.0
        _givens_factor(vals, first, rhs, n_rows, ridge, R, qr)
    for j in range(m):
        if not (np.isfinite(R[j, 0]) and np.isfinite(qr[j]) and R[j, 0] != 0.0):
            return x, 5, 0
    # LDP: min ||y|| subject to E y >= f, E = G R^-1 (rows e with e R = g: forward
    # substitution), f = h - E Q^T r; by NNLS on M = [E^T; f^T]
    P = len(h)
    r = m + 1
    Mt = np.empty((P, r))
    for p in range(P):
        f = first_g[p]
        eq = 0.0
        for j in range(min(f, m)):  # ahead of the row's band: e = 0 / R[j, j] = +0.0 exactly
            Mt[p, j] = 0.0
        for j in range(min(f, m), m):
            s = band_g[p, j - f] if j < f + K else 0.0
            for i2 in range(max(0, j - K + 1), j):
                s -= Mt[p, i2] * R[i2, j - i2]
            e = s / R[j, 0]
            Mt[p, j] = e
            eq += e * qr[j]
        Mt[p, m] = h[p] - eq
        if not np.isfinite(Mt[p, m]):
            return x, 5, 0
    u, status, n_passive = _nnls(Mt, maxiter, warm, n_warm)
    if status:
        return x, status, 0
    res = np.zeros(r)  # M u - e
    res[m] = -1.0
    for j in range(P):
        if u[j] != 0.0:
            for i2 in range(r):
                res[i2] += Mt[j, i2] * u[j]
    if abs(res[m]) < 1e-12:
        return x, 3, 0
    for j in range(m - 1, -1, -1):  # x = R^-1 (y + Q^T r), y = -res[:m] / res[m]
        s = -res[j] / res[m] + qr[j]
        for t in range(1, K):
            if j + t < m:
                s -= R[j, t] * x[j + t]
        x[j] = s / R[j, 0]
    return x, 0, n_passive


@kernel(
    "Tuple((float64[::1], int64))(float64[:, ::1], int64[::1], float64[::1], float64, "
    "float64[:, ::1], int64[::1], float64[::1], int64, int64)"
)
def lsi(vals, first, rhs, ridge, band_g, first_g, h, m, maxiter):  # noqa: ANN001
    """:func:`_lsi` of every row."""
    warm = np.empty(m + 1, np.int64)
    x, status, _ = _lsi(vals, first, rhs, len(rhs), ridge, band_g, first_g, h, m, maxiter, warm, 0)
    return x, status


# float64 constants of gauss_newton, in this order
GN_CONSTANTS = ("gate_px", "min_disparity_px", "model_px", "cauchy", "ridge", "nnls_iter")


@kernel(
    "Tuple((float64[::1], int64))("
    "float64[:, ::1], int64[::1], float64[::1], int64[::1], int64[::1], float64[::1], "
    "boolean[::1], float64[::1], int64[::1], "
    "float64[::1], float64[::1], float64[::1], float64[::1], int64[::1], float64, "
    "float64[:, ::1], int64[::1], float64[::1], float64[::1], float64[::1], "
    "float64[:, ::1], int64[::1], float64[:, ::1], int64[::1], float64[::1], "
    "float64[::1], float64, int64, int64, float64[::1])"
)
def gauss_newton(  # noqa: ANN201
    band_m,  # noqa: ANN001
    first_m,  # noqa: ANN001
    x_L,  # noqa: ANN001
    rows,  # noqa: ANN001
    iL,  # noqa: ANN001
    cL,  # noqa: ANN001
    okL,  # noqa: ANN001
    var_L,  # noqa: ANN001
    iR_rank,  # noqa: ANN001
    key_R,  # noqa: ANN001
    centre_R,  # noqa: ANN001
    length_R,  # noqa: ANN001
    var_R,  # noqa: ANN001
    row_start_R,  # noqa: ANN001
    key_scale_R,  # noqa: ANN001
    band_p,  # noqa: ANN001
    first_p,  # noqa: ANN001
    zP0,  # noqa: ANN001
    dP0,  # noqa: ANN001
    sdP,  # noqa: ANN001
    band_s,  # noqa: ANN001
    first_s,  # noqa: ANN001
    band_g,  # noqa: ANN001
    first_g,  # noqa: ANN001
    h,  # noqa: ANN001
    b0,  # noqa: ANN001
    fB,  # noqa: ANN001
    first_it,  # noqa: ANN001
    iterations,  # noqa: ANN001
    consts,  # noqa: ANN001
):
    """The Gauss-Newton rounds of ``refine.refine_depth`` (its docstring gives the model) on
    banded basis rows: the samples' rows ``band_m``/``first_m`` with their left runs (``iL``,
    centres ``cL``, ``okL``) and rank-paired right runs ``iR_rank``, the right view's runs
    (key, centre, length, variance, row starts, key scale), the prior rows at the points of
    H (``band_p``, depth ``zP0``, disparity ``dP0``, s.d. ``sdP``), the smoothness rows
    ``band_s`` and the bounds G b >= h (rows ``band_g`` at ``first_g``); control values ``b0``; rounds ``first_it``
    .. ``iterations`` (round 0: linear in depth); ``consts`` as named in GN_CONSTANTS.
    Returns the control values and a status: 0, 1 (a depth <= 0), 2 (fewer than 10 samples
    on both views' thread), 3 (bounds infeasible), 4 (NNLS iteration limit), 5 (not
    finite)."""
    n, K = band_m.shape
    m = len(b0)
    gate_px = consts[0]
    min_disp = consts[1]
    model2 = 2.0 * consts[2] * consts[2]
    cauchy = consts[3]
    ridge_rel = consts[4]
    n_p = len(zP0)
    n_s = band_s.shape[0]
    b = b0.copy()
    z = np.empty(n)
    d = np.empty(n)
    iR = np.empty(n, np.int64)
    ok = np.zeros(n, np.bool_)
    share = np.zeros(len(var_L), np.int64)
    n_max = n + n_p + n_s
    vals = np.empty((n_max, K))
    first = np.empty(n_max, np.int64)
    rhs = np.empty(n_max)
    maxiter = int(consts[5] * len(h))
    warm = np.empty(m + 1, np.int64)
    n_warm = 0
    for it in range(first_it, iterations + 1):
        nonpos = False
        for i in range(n):
            f = first_m[i]
            s = 0.0
            for c in range(K):
                s += band_m[i, c] * b[f + c]
            z[i] = s
            if s <= 0.0:
                nonpos = True
            d[i] = fB / s if s > 0.0 else np.nan
        if nonpos and it > 0:
            return b0.copy(), 1
        n_ok = 0
        for i in range(n):
            x_R = x_L[i] - d[i]
            j = iR_rank[i]
            if j < 0:
                j = _nearest(key_R, centre_R, row_start_R, key_scale_R, rows[i], x_R)
            iR[i] = j
            o = okL[i] and j >= 0
            if o and iR_rank[i] < 0:
                o = abs(centre_R[j] - x_R) <= 0.5 * length_R[j] + gate_px
            if o and it == 0:
                o = cL[i] - centre_R[j] > min_disp
            ok[i] = o
            if o:
                n_ok += 1
        if n_ok < 10:
            return b0.copy(), 2
        share[:] = 0
        for i in range(n):
            if ok[i]:
                share[iL[i]] += 1
        q = 0
        amax = 0.0
        for i in range(n):  # the samples: one observation per left run, shared
            if not ok[i]:
                continue
            j = iR[i]
            target = cL[i] - centre_R[j]
            var = var_L[iL[i]] + var_R[j] + model2  # px^2
            w = 1.0 / np.sqrt(var * share[iL[i]])
            if it > first_it:  # Cauchy weights on the last solve's residuals
                rr = (target - d[i]) / np.sqrt(var) / cauchy
                w = w / np.sqrt(1.0 + rr * rr)
            f = first_m[i]
            first[q] = f
            if it == 0:  # linear in depth
                wz = w * target * target / fB
                for c in range(K):
                    vals[q, c] = band_m[i, c] * wz
                rhs[q] = fB / target * wz
            else:  # Gauss-Newton in disparity
                g = -fB / (z[i] * z[i])
                jb = 0.0
                for c in range(K):
                    v = g * band_m[i, c]
                    vals[q, c] = v * w
                    jb += v * b[f + c]
                rhs[q] = (target - d[i] + jb) * w
            for c in range(K):
                amax = max(amax, abs(vals[q, c]))
            q += 1
        for i in range(n_p):  # the MVS curve at the points of H
            f = first_p[i]
            first[q] = f
            if it == 0:
                wp = dP0[i] * dP0[i] / fB / sdP[i]
                for c in range(K):
                    vals[q, c] = band_p[i, c] * wp
                rhs[q] = zP0[i] * wp
            else:
                zp = 0.0
                for c in range(K):
                    zp += band_p[i, c] * b[f + c]
                g = -fB / (zp * zp)
                jb = 0.0
                for c in range(K):
                    v = g * band_p[i, c]
                    vals[q, c] = v / sdP[i]
                    jb += v * b[f + c]
                rhs[q] = (dP0[i] - fB / zp + jb) / sdP[i]
            for c in range(K):
                amax = max(amax, abs(vals[q, c]))
            q += 1
        for i in range(n_s):  # smoothness
            first[q] = first_s[i]
            for c in range(K):
                vals[q, c] = band_s[i, c]
                amax = max(amax, abs(band_s[i, c]))
            rhs[q] = 0.0
            q += 1
        ridge = ridge_rel * max(amax, 1e-300)
        x, status, n_warm = _lsi(
            vals, first, rhs, q, ridge, band_g, first_g, h, m, maxiter, warm, n_warm
        )  # NNLS from the last round's active bounds
        if status:
            return b0.copy(), status
        b = x
    return b, 0


@kernel("Tuple((float64[:, ::1], int64[::1]))(float64[::1], int64, float64[::1], int64)")
def basis_bands(t, k, x, nu):  # noqa: ANN001
    """The ``nu``-th derivatives (0: the values) of the k + 1 B-splines of degree ``k`` on
    knots ``t`` that are nonzero at each of ``x`` (n,): ``vals`` (n, k + 1) of the basis
    functions first .. first + k (``first`` (n,)). The knot span of x is the last nonempty
    one starting at or before it (x beyond the ends: the end spans, extrapolated), as
    scipy's BSpline takes it. Values by the triangular Cox-de Boor recursion on degree
    k - nu, then nu times d/dx N_{i,p} = p (N_{i,p-1} / (t_{i+p} - t_i) - N_{i+1,p-1} /
    (t_{i+p+1} - t_{i+1}))."""
    n = len(x)
    m = len(t) - k - 1  # basis functions
    K = k + 1
    vals = np.zeros((n, K))
    first = np.zeros(n, np.int64)
    N = np.zeros(K + 1)
    left = np.zeros(K + 1)
    right = np.zeros(K + 1)
    p0 = k - nu
    for q in range(n):
        xq = x[q]
        lo = k
        hi = m - 1
        while lo < hi:  # the largest span index ell in [k, m - 1] with t[ell] <= x
            mid = (lo + hi + 1) >> 1
            if t[mid] <= xq:
                lo = mid
            else:
                hi = mid - 1
        ell = lo
        while ell > k and t[ell] == t[ell + 1]:  # an empty span (repeated knot)
            ell -= 1
        # degree p0: N[0..p0] are N_{ell-p0+r, p0}
        N[0] = 1.0
        for j in range(1, p0 + 1):
            left[j] = xq - t[ell + 1 - j]
            right[j] = t[ell + j] - xq
            saved = 0.0
            for r in range(j):
                temp = N[r] / (right[r + 1] + left[j - r])
                N[r] = saved + right[r + 1] * temp
                saved = left[j - r] * temp
            N[j] = saved
        # raise to degree k through the derivative recurrence: N[r] is function ell - p + r
        for p in range(p0 + 1, k + 1):
            N[p] = 0.0
            for r in range(p, -1, -1):
                i = ell - p + r  # the function of degree p
                a = N[r - 1] if r >= 1 else 0.0  # N_{i, p-1} (index r - 1 at degree p - 1)
                b = N[r] if r <= p - 1 else 0.0  # N_{i+1, p-1}
                da = t[i + p] - t[i]
                db = t[i + p + 1] - t[i + 1]
                v = 0.0
                if da != 0.0:
                    v += a / da
                if db != 0.0:
                    v -= b / db
                N[r] = p * v
        first[q] = ell - k
        for r in range(K):
            vals[q, r] = N[r]
    return vals, first


@kernel("float64[:, ::1](float64[:, ::1], int64[::1], float64[:, ::1])")
def band_dot(vals, first, c):  # noqa: ANN001
    """(n, d) products of the banded rows (``vals`` (n, K) at columns ``first``) with ``c``
    (m, d)."""
    n, K = vals.shape
    d = c.shape[1]
    out = np.zeros((n, d))
    for i in range(n):
        f = first[i]
        for j in range(d):
            s = 0.0
            for r in range(K):
                s += vals[i, r] * c[f + r, j]
            out[i, j] = s
    return out
