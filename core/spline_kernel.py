"""Compiled kernels of the spline stages (core/spline.py, core/camera.py): the dense B-spline
basis matrix, the residuals of Eq. (8)'s Gauss-Newton solve and the adaptive x, y knots.

``basis_dense(x, t, k)`` is ``BSpline(t, eye(m), k)(x)``, the matrix of the m basis functions
at the points x, as scipy computes it: the k + 1 non-zero functions at x by the de Boor - Cox
recursion (scipy's ``_deBoor_D``), then each column as the sum ``0 + sum_a c[a] b_a`` with the
identity's coefficients. Here the recursion's floating-point operations are the same, in the
same order, and the sum's products by 0 are left out (``0 + 1 * b`` is ``b + 0``, which only
turns a -0.0 into +0.0), so the matrix is the same to the last bit (tests/core/test_bounds_spline.py
checks it) at O(len(x) k^2) instead of O(len(x) m k): 5-10x at the m' = 60-80 control points of
a 1920x1080 frame's x, y spline.

``evaluate(x, t, c, k)`` is ``BSpline(t, c, k)(x)`` for any coefficients, the same way and to
the same bits, and ``derivative_bases(x, t, k, nu)`` the basis' first to nu-th derivatives as
``spline.basis_derivatives`` computes them (scipy's ``splder`` coefficients, then that
evaluation), in one call: a call into scipy costs ~20 us, these ~2 us.

``mvs_residual`` is ``spline._Mvs.residual_jac`` and ``mvs_value`` its ``value``: the same
formulas node by node (a few hundred flops on a 14-column problem, where numpy spent ~45 us in
its calls); ``gn_trial`` is the part of a Gauss-Newton step of ``spline._Problem.solve`` after
its QP (model decrease, stop tests, residuals, J^T J and J^T r at the trial point, each
row's sums over its non-zero span);
``refine_knots`` is ``spline._refine_xy``'s rounds of penalised fits and span splits on the
basis in banded form (k + 1 non-zeros a row), the normal equations by a banded Cholesky
factorisation; ``camera_refit`` is ``camera.to_camera``'s least-squares refit the same way.
They sum in another order than numpy and LAPACK: equal to rounding.
"""

from __future__ import annotations

import math

import numpy as np

from threadrecon.core.compiled import helper, kernel


@helper()
def _nonzero(xi, t, k, m, h, hh):  # noqa: ANN001
    """The k + 1 B-splines of degree k on knots t that may be non-zero at the finite point xi
    into h (de Boor - Cox, scipy's ``_deBoor_D`` operation for operation); returns the column
    of h[0], ell - k, with ell the last index in [k, m - 1] with t[ell] <= xi (scipy's
    find_interval)."""
    lo, hi = 0, t.size  # np.searchsorted(t, xi, side="right")
    while lo < hi:
        mid = (lo + hi) // 2
        if t[mid] <= xi:
            lo = mid + 1
        else:
            hi = mid
    ell = min(max(lo - 1, k), m - 1)
    h[0] = 1.0
    for j in range(1, k + 1):
        for a in range(j):
            hh[a] = h[a]
        h[0] = 0.0
        for a in range(1, j + 1):
            xb = t[ell + a]
            xa = t[ell + a - j]
            if xb == xa:
                h[a] = 0.0
                continue
            w = hh[a - 1] / (xb - xa)
            h[a - 1] += w * (xb - xi)
            h[a] = w * (xi - xa)
    return ell - k


# Compiled ahead of time once per machine (core/compiled.py), so that numba is not loaded.
@kernel("float64[:, ::1](float64[::1], float64[::1], int64)")
def basis_dense(x, t, k):  # noqa: ANN001
    """(len(x), m) basis matrix of the m = len(t) - k - 1 B-splines of degree k on knots t at
    x, extrapolating outside [t[k], t[m]] as scipy does (the first or last polynomial piece);
    a row of NaN for a non-finite x."""
    n = x.size
    m = t.size - k - 1
    out = np.zeros((n, m))
    h = np.empty(k + 1)
    hh = np.empty(k + 1)
    for i in range(n):
        xi = x[i]
        if not math.isfinite(xi):
            out[i, :] = np.nan
            continue
        first = _nonzero(xi, t, k, m, h, hh)
        for a in range(k + 1):
            out[i, first + a] = h[a] + 0.0
    return out


@helper()
def _node(B1, B2, B3, b, q):  # noqa: ANN001
    """At quadrature node q: the first to third derivatives z1, z2, z3 of the curve's depth
    profile, g = 1 + z1^2 and kappa' = z3 g^-3/2 - 3 z1 z2^2 g^-5/2 (d kappa / du)."""
    z1 = 0.0
    z2 = 0.0
    z3 = 0.0
    for j in range(B1.shape[1]):
        z1 += B1[q, j] * b[j]
        z2 += B2[q, j] * b[j]
        z3 += B3[q, j] * b[j]
    g = 1.0 + z1 * z1
    return z1, z2, z3, g, z3 * g**-1.5 - 3.0 * z1 * z2 * z2 * g**-2.5


@kernel(
    "Tuple((float64[::1], float64[:, ::1]))(float64[:, ::1], float64[:, ::1], float64[:, ::1], "
    "float64[::1], float64[:, ::1], float64[::1], float64[::1], float64)"
)
def mvs_residual(B1, B2, B3, sqrt_wq, J_d, c_d, b, scale):  # noqa: ANN001
    """Residuals rho (nq + P,) and Jacobian (nq + P, m) of the Gauss-Newton form of Eq. (8) at
    b: first rho_q = sqrt(scale w_q) kappa'_q g_q^-1/4 at the quadrature nodes (``B1``..``B3``
    the basis' first to third derivatives there, (nq, m)), then the data term's rows
    ``J_d`` b - ``c_d`` (linear: ``J_d`` is its Jacobian)."""
    nq, m = B1.shape
    P = J_d.shape[0]
    r = np.empty(nq + P)
    J = np.empty((nq + P, m))
    s = math.sqrt(scale)
    for q in range(nq):
        z1, z2, z3, g, kp = _node(B1, B2, B3, b, q)
        g15 = g**-1.5
        g25 = g**-2.5
        g35 = g**-3.5
        sw = s * sqrt_wq[q]
        qq = g**-0.25
        dk1 = -3.0 * z1 * z3 * g25 - 3.0 * z2 * z2 * g25 + 15.0 * z1 * z1 * z2 * z2 * g35
        dk2 = -6.0 * z1 * z2 * g25
        j1 = sw * (dk1 * qq - 0.5 * kp * z1 * qq / g)
        j2 = sw * dk2 * qq
        j3 = sw * g15 * qq
        r[q] = sw * kp * qq
        for j in range(m):
            J[q, j] = j1 * B1[q, j] + j2 * B2[q, j] + j3 * B3[q, j]
    for i in range(P):
        acc = 0.0
        for j in range(m):
            v = J_d[i, j]
            J[nq + i, j] = v
            acc += v * b[j]
        r[nq + i] = acc - c_d[i]
    return r, J


@kernel("float64(float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[::1], float64[::1])")
def mvs_value(B1, B2, B3, wq, b):  # noqa: ANN001
    """Eq. (8) by quadrature: sum_q w_q kappa'_q^2 / sqrt(g_q) (``_Mvs.value``)."""
    nq = B1.shape[0]
    out = 0.0
    for q in range(nq):
        _, _, _, g, kp = _node(B1, B2, B3, b, q)
        out += wq[q] * kp * kp / math.sqrt(g)
    return out


@helper()
def _band_cholesky(M, m, bw):  # noqa: ANN001
    """M = L L^T inside the band of half-width ``bw`` (L overwrites M's lower triangle); the
    smallest and largest diagonal of L, or (0, 0) when M is not positive definite."""
    dmin = np.inf
    dmax = 0.0
    for j in range(m):
        s = M[j, j]
        for q in range(max(0, j - bw), j):
            s -= M[j, q] * M[j, q]
        if not s > 0.0:
            return 0.0, 0.0
        s = math.sqrt(s)
        dmin, dmax = min(dmin, s), max(dmax, s)
        M[j, j] = s
        for i in range(j + 1, min(m, j + bw + 1)):
            v = M[i, j]
            for q in range(max(0, i - bw), j):
                v -= M[i, q] * M[j, q]
            M[i, j] = v / s
    return dmin, dmax


@helper()
def _band_solve(M, rhs, c, m, bw):  # noqa: ANN001
    """c = (L L^T)^-1 rhs column by column, L from :func:`_band_cholesky`."""
    for col in range(rhs.shape[1]):
        for i in range(m):  # L y = rhs
            v = rhs[i, col]
            for q in range(max(0, i - bw), i):
                v -= M[i, q] * c[q, col]
            c[i, col] = v / M[i, i]
        for i in range(m - 1, -1, -1):  # L^T c = y
            v = c[i, col]
            for q in range(i + 1, min(m, i + bw + 1)):
                v -= M[q, i] * c[q, col]
            c[i, col] = v / M[i, i]


@helper()
def _penalised_fit(xy, u, t, k, penalty, c, miss):  # noqa: ANN001
    """``spline._penalised_fit``: c (m, 2) = argmin |B c - xy|^2 + lam |D3 c|^2, lam =
    ``penalty`` trace(B^T B) / m, with the basis B banded; ``miss`` (P,) the 2D distance of each
    point to the fit. Returns False when the normal equations are not positive definite."""
    P = u.size
    m = t.size - k - 1
    h = np.empty(k + 1)
    hh = np.empty(k + 1)
    first = np.empty(P, np.int64)
    vals = np.empty((P, k + 1))
    for i in range(P):
        first[i] = _nonzero(u[i], t, k, m, h, hh)
        for a in range(k + 1):
            vals[i, a] = h[a]
    bw = max(k, 3)  # half-bandwidth of B^T B (k) and of D3^T D3 (3)
    M = np.zeros((m, m))
    rhs = np.zeros((m, 2))
    for i in range(P):
        f = first[i]
        for a in range(k + 1):
            va = vals[i, a]
            rhs[f + a, 0] += va * xy[i, 0]
            rhs[f + a, 1] += va * xy[i, 1]
            for e in range(k + 1):
                M[f + a, f + e] += va * vals[i, e]
    trace = 0.0
    for j in range(m):
        trace += M[j, j]
    lam = penalty * trace / m
    d = (-1.0, 3.0, -3.0, 1.0)  # a row of the third-difference matrix D3 ((m - 3, m))
    for r in range(m - 3):
        for a in range(4):
            for e in range(4):
                M[r + a, r + e] += lam * d[a] * d[e]
    if _band_cholesky(M, m, bw)[0] <= 0.0:
        return False
    _band_solve(M, rhs, c, m, bw)
    for i in range(P):
        f = first[i]
        x = 0.0
        y = 0.0
        for a in range(k + 1):
            x += vals[i, a] * c[f + a, 0]
            y += vals[i, a] * c[f + a, 1]
        miss[i] = math.sqrt((x - xy[i, 0]) ** 2 + (y - xy[i, 1]) ** 2)
    return True


@kernel(
    "Tuple((float64[::1], float64[:, ::1], int64))(float64[:, ::1], float64[::1], float64[::1], "
    "int64, float64, int64, int64, float64)"
)
def refine_knots(xy, u, t, k, tol, rounds, min_points, penalty):  # noqa: ANN001
    """``spline._refine_xy``: up to ``rounds`` times, fit S_x, S_y (:func:`_penalised_fit`) on
    the knots and halve every knot span that holds at least ``min_points`` points u of H and
    one farther than ``tol`` from the fit. Returns the refined knots, the (m', 2) control
    points of the fit on them and 0; status 1 when no span was split or the fit is not
    finite, 2 when the normal equations were not positive definite (the caller keeps t)."""
    P = u.size
    tx = t.copy()
    miss = np.empty(P)
    c = np.empty((0, 2))
    fitted = False
    for _ in range(rounds):
        c = np.empty((tx.size - k - 1, 2))
        if not _penalised_fit(xy, u, tx, k, penalty, c, miss):
            return t.copy(), c, 2
        n_e = 1  # the distinct knots (edges) of the spans
        for i in range(1, tx.size):
            if tx[i] != tx[i - 1]:
                n_e += 1
        edges = np.empty(n_e)
        edges[0] = tx[0]
        j = 1
        for i in range(1, tx.size):
            if tx[i] != tx[i - 1]:
                edges[j] = tx[i]
                j += 1
        worst = np.zeros(n_e - 1)
        count = np.zeros(n_e - 1, np.int64)
        for i in range(P):
            s = np.searchsorted(edges, u[i], side="right") - 1
            s = min(max(s, 0), n_e - 2)
            worst[s] = max(worst[s], miss[i])
            count[s] += 1
        n_split = 0
        for s in range(n_e - 1):
            if worst[s] > tol and count[s] >= min_points:
                n_split += 1
        if n_split == 0:
            fitted = True
            break
        grown = np.empty(tx.size + n_split)
        grown[: tx.size] = tx
        j = tx.size
        for s in range(n_e - 1):
            if worst[s] > tol and count[s] >= min_points:
                grown[j] = 0.5 * (edges[s] + edges[s + 1])
                j += 1
        tx = np.sort(grown)
    if tx.size == t.size:
        return t.copy(), c, 1
    if not fitted:
        c = np.empty((tx.size - k - 1, 2))
        if not _penalised_fit(xy, u, tx, k, penalty, c, miss):
            return t.copy(), c, 2
    for i in range(c.shape[0]):
        if not (math.isfinite(c[i, 0]) and math.isfinite(c[i, 1])):
            return t.copy(), c, 1
    return tx, c, 0


@kernel(
    "Tuple((float64[:, ::1], float64[:, ::1], int64))(float64[::1], int64, float64[:, ::1], "
    "int64, float64[:, ::1], float64)"
)
def camera_refit(t, k, ctrl, n, G_inv, cond_floor):  # noqa: ANN001
    """``camera.to_camera``'s refit: the spline (t, ``ctrl`` (m, 3) in (x px, y px, z)) at n
    uniform u in [0, 1] (as np.linspace), each sample mapped to the camera frame by Eq. (9)
    (z ``G_inv`` [x, y, 1]), and the control points (m, 3) of the least-squares fit of those
    points on the same knots: the normal equations B^T B c = B^T p with B banded, by a banded
    Cholesky factorisation. Returns (control points, points, 0), or status 1 when the factor's
    diagonal ratio is below ``cond_floor`` or not positive (the caller solves by SVD)."""
    m = t.size - k - 1
    h = np.empty(k + 1)
    hh = np.empty(k + 1)
    pts = np.empty((n, 3))
    M = np.zeros((m, m))
    rhs = np.zeros((m, 3))
    step = 1.0 / (n - 1) if n > 1 else 0.0
    for i in range(n):
        u = i * step + 0.0 if i < n - 1 else 1.0
        f = _nonzero(u, t, k, m, h, hh)
        x = 0.0
        y = 0.0
        z = 0.0
        for a in range(k + 1):
            x += h[a] * ctrl[f + a, 0]
            y += h[a] * ctrl[f + a, 1]
            z += h[a] * ctrl[f + a, 2]
        for d in range(3):
            pts[i, d] = (G_inv[d, 0] * x + G_inv[d, 1] * y + G_inv[d, 2]) * z
        for a in range(k + 1):
            va = h[a]
            for d in range(3):
                rhs[f + a, d] += va * pts[i, d]
            for e in range(k + 1):
                M[f + a, f + e] += va * h[e]
    c = np.empty((m, 3))
    dmin, dmax = _band_cholesky(M, m, k)
    if not dmin > 0.0 or not dmin > cond_floor * dmax:
        return c, pts, 1
    _band_solve(M, rhs, c, m, k)
    return c, pts, 0


@kernel("float64[:, ::1](float64[::1], float64[::1], float64[:, ::1], int64)")
def evaluate(x, t, c, k):  # noqa: ANN001
    """(len(x), d) values of the spline of degree k on knots t with coefficients c (rows: at
    least len(t) - k - 1, d columns) at x: ``BSpline.construct_fast(t, c, k)(x)`` (scipy's
    ``evaluate_spline``: the k + 1 non-zero B-splines by :func:`_nonzero`, then each column
    as 0 + sum_a c[ell - k + a] b_a in that order), the same to the last bit; a row of NaN
    for a non-finite x."""
    n = x.size
    m = t.size - k - 1
    d = c.shape[1]
    out = np.empty((n, d))
    h = np.empty(k + 1)
    hh = np.empty(k + 1)
    for i in range(n):
        xi = x[i]
        if not math.isfinite(xi):
            out[i, :] = np.nan
            continue
        first = _nonzero(xi, t, k, m, h, hh)
        for j in range(d):
            s = 0.0
            for a in range(k + 1):
                s += c[first + a, j] * h[a]
            out[i, j] = s
    return out


@kernel("Tuple((float64[:, :, ::1], int64))(float64[::1], float64[::1], int64, int64)")
def derivative_bases(x, t, k, nu):  # noqa: ANN001
    """(nu, len(x), m): the j-th derivatives, j = 1..nu, of the m = len(t) - k - 1 B-splines
    of degree k on knots t at x, and a status (1: a knot span of zero length, the spline is
    not nu times differentiable). As ``spline.basis_derivatives`` computed them: each
    derivative's coefficients from the previous one's as scipy's ``splder`` does (the
    identity's, with FITPACK's len(t) coefficient rows: (c[i + 1] - c[i]) * k / (t[i + k +
    1] - t[i + 1])), each evaluated as :func:`evaluate` does, so the same to the last bit."""
    n = x.size
    m = t.size - k - 1
    out = np.zeros((nu, n, m))
    c = np.zeros((t.size, m))
    for j in range(m):
        c[j, j] = 1.0
    tj = t.copy()
    kj = k
    h = np.empty(k + 1)
    hh = np.empty(k + 1)
    for d in range(nu):
        cn = np.zeros((tj.size - 2, m))
        for i in range(tj.size - kj - 2):
            dt = tj[i + kj + 1] - tj[i + 1]
            if dt == 0.0:
                return out, 1
            for col in range(m):
                cn[i, col] = (c[i + 1, col] - c[i, col]) * kj / dt
        c = cn
        tj = tj[1:-1].copy()
        kj -= 1
        mj = tj.size - kj - 1
        for i in range(n):
            xi = x[i]
            if not math.isfinite(xi):
                out[d, i, :] = np.nan
                continue
            first = _nonzero(xi, tj, kj, mj, h, hh)
            for col in range(m):
                s = 0.0
                for a in range(kj + 1):
                    s += c[first + a, col] * h[a]
                out[d, i, col] = s
    return out, 0


@helper()
def _span(row, m):  # noqa: ANN001
    """First and last index (exclusive) of the non-zero entries of ``row`` (m,); (0, m) when a
    value is not finite (then no product may be left out)."""
    lo = m
    hi = 0
    for j in range(m):
        v = row[j]
        if not math.isfinite(v):
            return 0, m
        if v != 0.0:
            lo = min(lo, j)
            hi = j + 1
    return lo, max(hi, lo)


@kernel(
    "Tuple((int64, float64, float64[::1], float64[::1], float64[:, ::1], float64, "
    "float64[:, ::1], float64[::1]))(float64[:, ::1], float64[:, ::1], float64[:, ::1], "
    "float64[::1], float64[:, ::1], float64[::1], float64, float64[:, ::1], float64[::1], "
    "float64[:, ::1], float64[::1], float64[::1], float64, float64)"
)
def gn_trial(B1, B2, B3, sqrt_wq, J_d, c_d, scale, J, r, A, b, d, f_stop, step_tol):  # noqa: ANN001
    """One Gauss-Newton trial step d from b of ``spline._Problem.solve``: the model decrease
    pred = -(2 r.Jd + |Jd|^2); stop (1) when pred <= ``f_stop`` or max |A d| < ``step_tol``;
    else (0) the residuals at b + d (:func:`mvs_residual`), their sum of squares, J^T J and
    J^T r there. Returns (stop, pred, b + d, r, J, F, J^T J, J^T r).

    The rows of J and A are B-spline rows, non-zero over k + 1 to 2 k + 1 columns: each sum
    runs over a row's non-zero span only (:func:`_span`). The products left out are exact
    zeros and every sum starts at +0.0, which adding a zero leaves unchanged, so the results
    are those of the sums over every column, bit for bit (a row or step with a value that
    is not finite is summed in full)."""
    n, m = J.shape
    d_finite = True
    for j in range(m):
        if not math.isfinite(d[j]):
            d_finite = False
    pred = 0.0
    rJd = 0.0
    JdJd = 0.0
    for i in range(n):
        lo, hi = _span(J[i], m) if d_finite else (0, m)
        v = 0.0
        for j in range(lo, hi):
            v += J[i, j] * d[j]
        rJd += r[i] * v
        JdJd += v * v
    pred = -(2.0 * rJd + JdJd)
    step = 0.0
    for i in range(A.shape[0]):
        lo, hi = _span(A[i], m) if d_finite else (0, m)
        v = 0.0
        for j in range(lo, hi):
            v += A[i, j] * d[j]
        step = max(step, abs(v))
    empty1 = np.empty(0)
    empty2 = np.empty((0, 0))
    if pred <= f_stop or step < step_tol:
        return 1, pred, empty1, empty1, empty2, 0.0, empty2, empty1
    bt = b + d
    rt, Jt = mvs_residual(B1, B2, B3, sqrt_wq, J_d, c_d, bt, scale)
    F = 0.0
    for i in range(rt.size):
        F += rt[i] * rt[i]
    JtJ = np.zeros((m, m))
    g = np.zeros(m)
    for i in range(rt.size):
        lo, hi = _span(Jt[i], m) if math.isfinite(rt[i]) else (0, m)
        for a in range(lo, hi):
            va = Jt[i, a]
            g[a] += va * rt[i]
            for e in range(a, hi):
                JtJ[a, e] += va * Jt[i, e]
    for a in range(m):
        for e in range(a):
            JtJ[a, e] = JtJ[e, a]
    return 0, pred, bt, rt, Jt, F, JtJ, g
