"""The spline's compiled kernels (core/spline_kernel.py) against numpy written out from the
formulas: the adaptive x, y knots' rounds of penalised fits and span splits, and Eq. (8)'s
value and Gauss-Newton residuals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline

from threadrecon.core import spline_kernel
from threadrecon.core.spline import XY_MIN_POINTS, XY_PENALTY, XY_ROUNDS, _Mvs


def _rounds(xy: np.ndarray, u: np.ndarray, t: np.ndarray, k: int, tol: float):
    """The adaptive knots in numpy: dense basis, np.linalg.solve of the penalised normal
    equations, np.maximum.at per span (what core/spline.py ran before the kernel)."""

    def fit(tx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = len(tx) - k - 1
        B = BSpline.construct_fast(tx, np.eye(m), k)(u)
        BtB = B.T @ B
        D = np.diff(np.eye(m), 3, axis=0)
        c = np.linalg.solve(BtB + XY_PENALTY * np.trace(BtB) / m * (D.T @ D), B.T @ xy)
        return c, np.linalg.norm(B @ c - xy, axis=1)

    tx, fitted = t, None
    for _ in range(XY_ROUNDS):
        c, miss = fit(tx)
        edges = np.unique(tx)
        span = np.clip(np.searchsorted(edges, u, side="right") - 1, 0, len(edges) - 2)
        worst = np.zeros(len(edges) - 1)
        np.maximum.at(worst, span, miss)
        count = np.bincount(span, minlength=len(edges) - 1)
        split = (worst > tol) & (count >= XY_MIN_POINTS)
        if not split.any():
            fitted = c
            break
        tx = np.sort(np.concatenate([tx, 0.5 * (edges[:-1] + edges[1:])[split]]))
    if len(tx) == len(t):
        return t, None
    return tx, fitted if fitted is not None else fit(tx)[0]


def _wiggly(rng: np.random.Generator, P: int) -> tuple[np.ndarray, np.ndarray]:
    """A 2D path of P points with a few tight bends, and its arc-length parameter."""
    s = np.sort(rng.uniform(0.0, 1.0, P))
    s[0], s[-1] = 0.0, 1.0
    f = rng.uniform(1.0, 12.0, 2)
    xy = np.column_stack(
        [300.0 * s + 20.0 * np.sin(f[0] * 6.3 * s), 80.0 * np.cos(f[1] * 6.3 * s) + 5.0 * s]
    )
    return xy, s * float(rng.uniform(10.0, 200.0))


@pytest.mark.parametrize("seed", range(6))
def test_compiled_adaptive_knots_equal_the_numpy_rounds(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(10):
        k = int(rng.integers(2, 6))
        P = int(rng.integers(20, 300))
        xy, u = _wiggly(rng, P)
        m = int(rng.integers(k + 1, min(P, 40)))
        t = np.concatenate(
            [np.zeros(k + 1), np.linspace(0.0, u[-1], m - k + 1)[1:-1], np.full(k + 1, u[-1])]
        )
        tol = float(rng.choice([0.05, 0.5, 2.0, 50.0]))
        want_t, want_c = _rounds(xy, u, t, k, tol)
        got_t, got_c, status = spline_kernel.refine_knots(
            xy, u, t, k, tol, XY_ROUNDS, XY_MIN_POINTS, XY_PENALTY
        )
        if want_c is None:
            assert status == 1 and np.array_equal(got_t, t)
            continue
        assert status == 0
        assert np.array_equal(got_t, want_t)
        np.testing.assert_allclose(got_c, want_c, rtol=1e-9, atol=1e-9 * np.abs(want_c).max())


def test_compiled_adaptive_knots_refuse_a_singular_system() -> None:
    """Points that do not fix the fit (all at one u, NaN) give status 2: the caller keeps the
    uniform knots, as np.linalg.LinAlgError did."""
    k, t = 3, np.concatenate([np.zeros(4), [0.5], np.ones(4)])
    xy = np.column_stack([np.linspace(0, 5, 8), np.zeros(8)])
    for u in (np.full(8, 0.3), np.full(8, np.nan)):
        _, _, status = spline_kernel.refine_knots(xy, u, t, k, 0.1, 3, 3, XY_PENALTY)
        assert status == 2


def test_compiled_mvs_value_and_residuals_follow_the_formulas() -> None:
    """Eq. (8)'s quadrature and its Gauss-Newton residuals and Jacobian (the curvature
    derivative's chain rule written out in numpy), with a data term's rows after them."""
    rng = np.random.default_rng(5)
    for k in (3, 4, 5):
        t = np.concatenate([np.zeros(k + 1), np.linspace(0, 40.0, 14)[1:-1], np.full(k + 1, 40.0)])
        mvs = _Mvs(t, k, 40.0, 4)
        m = len(t) - k - 1
        b = rng.normal(90.0, 4.0, m)
        z1, z2, z3 = (B @ b for B in mvs.B)
        g = 1.0 + z1**2
        kp = z3 * g**-1.5 - 3.0 * z1 * z2**2 * g**-2.5
        np.testing.assert_allclose(mvs.value(b), np.sum(mvs.wq * kp**2 / np.sqrt(g)), rtol=1e-12)
        dk1 = -3.0 * z1 * z3 * g**-2.5 - 3.0 * z2**2 * g**-2.5 + 15.0 * z1**2 * z2**2 * g**-3.5
        dk2, dk3 = -6.0 * z1 * z2 * g**-2.5, g**-1.5
        sw = np.sqrt(0.3 * mvs.wq)
        r_want = sw * kp * g**-0.25
        dq = -0.25 * g**-1.25 * 2.0 * z1  # d g^-1/4 / d z1
        J_want = (sw * (dk1 * g**-0.25 + kp * dq))[:, None] * mvs.B[0]
        J_want += (sw * dk2 * g**-0.25)[:, None] * mvs.B[1]
        J_want += (sw * dk3 * g**-0.25)[:, None] * mvs.B[2]
        J_d = rng.normal(0.0, 1.0, (7, m))
        c_d = rng.normal(0.0, 1.0, 7)
        r, J = mvs.residual_jac(b, 0.3, J_d, c_d)
        scale = np.abs(J_want).max()
        np.testing.assert_allclose(r[: len(r_want)], r_want, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(J[: len(r_want)], J_want, rtol=1e-9, atol=1e-12 * scale)
        np.testing.assert_allclose(r[len(r_want) :], J_d @ b - c_d, rtol=1e-12, atol=1e-12)
        assert np.array_equal(J[len(r_want) :], J_d)


@pytest.mark.parametrize("seed", range(4))
def test_compiled_evaluation_equals_scipys_bit_for_bit(seed: int) -> None:
    """spline.evaluate (spline_kernel.evaluate) against BSpline(t, c, k)(x) byte for byte:
    splines and the derivative bases of Eq. (8), uniform and random knots, points outside the
    knots (extrapolated), on knots and NaN."""
    from threadrecon.core.spline import _derivative_coefficients, evaluate

    rng = np.random.default_rng(seed)
    for trial in range(40):
        k = int(rng.integers(2, 6))
        m = int(rng.integers(k + 1, 40))
        length = float(rng.uniform(0.1, 300.0))
        if trial % 2:
            inner = np.sort(rng.uniform(0.0, length, m - k - 1))
        else:
            inner = np.linspace(0.0, length, m - k + 1)[1:-1]
        t = np.concatenate([np.zeros(k + 1), inner, np.full(k + 1, length)])
        x = np.concatenate([rng.uniform(-0.1, 1.1, 100) * length, [0.0, length, np.nan], inner])
        cases = [(t, rng.normal(0.0, 100.0, (m, 3)), k)]
        cases += _derivative_coefficients(t, k, min(3, k))
        for tt, c, kk in cases:
            want = BSpline.construct_fast(tt, c, kk)(x)
            got = evaluate(x, tt, c, kk)
            assert got.tobytes() == want.tobytes()
            assert got.flags.c_contiguous


def _trial_full(B1, B2, B3, sqrt_wq, J_d, c_d, scale, J, r, A, b, d, f_stop, step_tol):  # noqa: ANN001, ANN202
    """gn_trial's sums over every column, one product at a time in the kernel's order (what
    the kernel computed before it skipped the rows' zeros)."""
    n, m = J.shape
    rJd = JdJd = 0.0
    for i in range(n):
        v = 0.0
        for j in range(m):
            v += J[i, j] * d[j]
        rJd += r[i] * v
        JdJd += v * v
    pred = -(2.0 * rJd + JdJd)
    step = 0.0
    for i in range(A.shape[0]):
        v = 0.0
        for j in range(m):
            v += A[i, j] * d[j]
        step = max(step, abs(v))
    if pred <= f_stop or step < step_tol:
        return 1, pred
    bt = b + d
    rt, Jt = spline_kernel.mvs_residual(B1, B2, B3, sqrt_wq, J_d, c_d, bt, scale)
    JtJ, g = np.zeros((m, m)), np.zeros(m)
    for i in range(len(rt)):
        for a in range(m):
            g[a] += Jt[i, a] * rt[i]
            for e in range(a, m):
                JtJ[a, e] += Jt[i, a] * Jt[i, e]
    JtJ = np.triu(JtJ) + np.triu(JtJ, 1).T
    F = 0.0
    for v in rt:
        F += v * v
    return 0, pred, bt, rt, Jt, F, JtJ, g


def test_gauss_newton_trial_on_banded_rows_equals_the_full_sums_bit_for_bit() -> None:
    """gn_trial sums each B-spline row over its non-zero span: the same numbers, to the bit,
    as the sums over every column (the products it leaves out are zeros), also with a
    non-finite step."""
    from threadrecon.core.spline import basis_matrix

    rng = np.random.default_rng(11)
    trials = 0
    for k in (3, 4, 5):
        length = 40.0
        t = np.concatenate(
            [np.zeros(k + 1), np.linspace(0, length, 14)[1:-1], np.full(k + 1, length)]
        )
        mvs = _Mvs(t, k, length, 4)
        m = len(t) - k - 1
        u = np.sort(rng.uniform(0.0, length, 30))
        Bd = basis_matrix(u, t, k)
        J_d = np.ascontiguousarray(0.2 * Bd)
        c_d = rng.normal(90.0, 1.0, 30)
        A = np.ascontiguousarray(basis_matrix(np.sort(rng.uniform(0.0, length, 50)), t, k))
        b = rng.normal(90.0, 4.0, m)
        r, J = mvs.residual_jac(b, 0.3, J_d, c_d)
        gn_step = -0.5 * np.linalg.lstsq(J, r, rcond=None)[0]  # a descent step: no stop
        for d in (
            gn_step,
            rng.normal(0.0, 0.5, m),
            np.full(m, 1e-12),
            np.where(np.arange(m) == 2, np.nan, 0.1),
        ):
            args = (*mvs.B, mvs.sqrt_wq, J_d, c_d, 0.3, J, r, A, b, d, 1e-12, 1e-9)
            got = spline_kernel.gn_trial(*args)
            want = _trial_full(*args)
            assert got[0] == want[0]
            assert np.array_equal(got[1], want[1], equal_nan=True)
            trials += want[0] == 0
            if want[0] == 0:
                for g_, w_ in zip(got[2:], want[2:], strict=True):
                    assert np.asarray(g_).tobytes() == np.asarray(w_).tobytes()
    assert trials >= 3  # the trial point's residuals were compared


def test_compiled_derivative_bases_equal_scipys_derivative_splines_byte_for_byte() -> None:
    """spline.basis_derivatives (spline_kernel.derivative_bases, one call for every order)
    against BSpline(t, eye(m), k).derivative(j)(x), byte for byte (signed zeros, NaN rows);
    a knot span of zero length is an error that says so."""
    from threadrecon.core.spline import basis_derivatives

    rng = np.random.default_rng(21)
    for _ in range(60):
        k = int(rng.integers(2, 6))
        m = int(rng.integers(k + 1, 40))
        length = float(rng.uniform(0.1, 300.0))
        inner = np.sort(rng.uniform(0.0, length, m - k - 1))
        t = np.concatenate([np.zeros(k + 1), inner, np.full(k + 1, length)])
        x = np.concatenate([rng.uniform(-0.1, 1.1, 50) * length, [0.0, length, np.nan], inner])
        nu = int(rng.integers(1, k + 1))
        got = basis_derivatives(x, t, k, nu)
        basis = BSpline.construct_fast(t, np.eye(m), k)
        assert len(got) == nu
        for j in range(1, nu + 1):
            assert got[j - 1].tobytes() == basis.derivative(j)(x).tobytes()
    t = np.array([0.0, 0, 0, 0, 1, 1, 1, 2, 2, 2, 2])  # a triple knot: C^0 there
    assert len(basis_derivatives(np.array([0.5]), t, 3, 1)) == 1
    with pytest.raises(ValueError, match="not 2 times differentiable"):
        basis_derivatives(np.array([0.5]), t, 3, 2)
