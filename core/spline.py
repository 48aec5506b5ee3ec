"""Spline initialisation and the Minimum Variation Spline problem, Eq. (8).

The spline S(u) = (S_x, S_y, S_z) lives in the space (x px, y px, z depth) of the left image.
Initialisation: H^i is H with every depth moved to the centre of its bounds; ``splprep`` fits
it with a clamped uniform knot vector and ``n_ctrl`` control points (paper: degree 4, m = 15).

MVS: with b_x, b_y fixed, minimise over b_z the integral over u in [0, l] of
(d kappa / du)^2 / sqrt(1 + (dS_z/du)^2), kappa the curvature of the graph of S_z, subject to
lower <= S_z <= upper and the endpoint value and slope of L_{k_1}, L_{k_n} (j = 0, 1).

Choices the paper leaves open (documented in docs/method.md):
- the parameter u runs over [0, l] with l the lateral arc length of the thread in calibration
  units (2D arc length in px times mean depth / f), so that S_z'(u) is a dimensionless slope and
  the objective does not depend on the length unit (cm or mm);
- Gauss-Legendre quadrature (``quad_per_span`` nodes per knot span) with analytic gradients;
- the bound constraints hold at every point of H and at the midpoints between them;
- the solver: the paper uses SLSQP; here a Gauss-Newton SQP (both terms of the objective are
  sums of squares) whose subproblems are dense QPs solved by DAQP (active set), with
  Levenberg-Marquardt damping, starting from b0 projected on the constraints along a unit
  gradient step (the first step SLSQP takes); objective normalised by its value at b0. The
  QP's exit flag is checked: an infeasible problem is reported as ``status="infeasible"``.
Deviation (``xy_knots="adaptive"``, default): S_x, S_y get extra knots where the uniform fit
cuts a bend of H by more than ``xy_tol_px``; S_z and the MVS problem keep the m uniform knots.
A solver failure, or a solution that leaves the bounds by more than ``bound_tol`` of the local
half-width, is reported (``status``) and the initial spline is returned as a visible fallback.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Final, Literal

import daqp
import numpy as np
from scipy.interpolate import BSpline, splprep

from threadrecon.core import spline_kernel
from threadrecon.core.bounds import Bounds
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.lru import LRU
from threadrecon.core.numeric import median
from threadrecon.core.params import Params, param

EQ_TOL = 1e-3  # endpoint equalities hold to 0.1 % of the median bound half-width
XY_ROUNDS = 3  # adaptive knots: a uniform span is split into at most 2^3 = 8 parts
XY_MIN_POINTS = 3  # a span with fewer points of H is not split: a half would hold <= 1
XY_PENALTY = 1e-3  # P-spline weight, relative to the mean diagonal of B^T B (1e-4..1e-2 alike)
Status = Literal["ok", "solver_failed", "infeasible", "out_of_bounds", "skipped"]


@dataclass(frozen=True)
class SplineParams(Params):
    n_ctrl: int = param(15, lo=3, hi=200, symbol="m", slider=(5, 40, 1), label="control points m")
    """Number of control points m."""
    degree: int = param(4, lo=2, hi=5, slider=(2, 5, 1), label="degree")
    """Spline degree (paper: 4)."""
    max_iter: int = param(100, lo=1, hi=100000, slider=(1, 500, 1), label="solver iterations")
    """Iteration limit of the MVS solver."""
    quad_per_span: int = param(4, lo=1, hi=20, slider=(1, 10, 1), label="quadrature nodes / span")
    """Gauss-Legendre nodes per knot span for the integral of Eq. (8)."""
    bound_tol: float = param(0.02, lo=0, hi=10, slider=(0.0, 0.5, 0.01), label="bound tolerance")
    """Allowed excursion outside the bounds, as a fraction of the local half-width."""
    optimise: bool = True
    """Solve the MVS problem; False keeps the initial spline (for comparison)."""
    relax_slopes: bool = True
    """When Eq. (8) is infeasible, retry once with only the endpoint values fixed (False: paper)."""
    relax_ends: bool = True
    """When Eq. (8) stays infeasible with only the endpoint values fixed (the lines' and the
    tips'), retry once with the bounds alone, no end constraint (False: report the failure and
    show the initial spline). Deviation 57, docs/method.md."""
    data_weight: float = param(
        10.0, lo=0, hi=1000000000.0, slider=(0.0, 100.0, 0.5), label="data weight"
    )
    """Weight of a data term added to Eq. (8) (0: the paper's pure MVS), see docs/method.md.

    The term is the mean over H of ((S_z(u_j) - c_j) / w_j)^2, c_j the bound centre and w_j the
    bound half-width, and Eq. (8) is normalised by its value at the initial spline."""
    xy_knots: Literal["uniform", "adaptive"] = "adaptive"
    """Knots of S_x, S_y. "uniform" (paper): the m uniform knots, shared with S_z. "adaptive":
    a knot span in which the 2D fit misses a point of H by more than ``xy_tol_px`` is halved,
    for S_x, S_y only (see ``_adaptive_xy``); S_z keeps its m control points (Eq. (8) is
    unchanged) and is re-expressed exactly on the refined knots: S stays one B-spline."""
    xy_tol_px: float = param(
        1.0,
        lo=0.01,
        hi=1000,
        unit="px",
        slider=(0.1, 5.0, 0.1),
        label="x,y knot split tolerance px",
    )
    """Largest 2D distance, px, from a point of H to S_x, S_y before its span is halved."""

    def _check(self) -> None:
        super()._check()
        if self.n_ctrl < self.degree + 1:
            raise ValueError("spline.n_ctrl must be at least spline.degree + 1")


@dataclass(frozen=True)
class SplineResult:
    """``knots``, ``ctrl`` (m', 3), ``degree``: the final spline in (x px, y px, z depth) over u
    in [0, ``length``], m' = m unless adaptive knots refined S_x, S_y; ``ctrl_init`` the
    initial one; ``u_H``: parameter of each point of H.
    ``status``: "ok", "solver_failed", "infeasible" or "out_of_bounds" (then ``ctrl`` = ``ctrl_init``, the
    fallback) or "skipped" (``optimise=False``). ``message``: the solver's message.
    ``objective``: Eq. (8) at the initial and final control points. ``iterations``: solver steps.
    """

    knots: np.ndarray
    ctrl: np.ndarray
    ctrl_init: np.ndarray
    degree: int
    length: float
    u_H: np.ndarray
    status: Status
    message: str
    objective: tuple[float, float]
    iterations: int
    max_violation: float
    """Largest excursion outside the bounds of the returned spline, fraction of half-width."""
    bounds_dropped: np.ndarray | None = None
    """(P,) bool over the points of H whose bounds of Eq. (7) the refine stage dropped (stereo
    matched a strand to its neighbour there, see core/refine.py); None: every bound holds."""

    @property
    def ok(self) -> bool:
        return self.status in ("ok", "skipped")

    def curve(self, n: int = 400, initial: bool = False) -> np.ndarray:
        """(n, 3) samples of S at uniform u, (x px, y px, z depth)."""
        c = self.ctrl_init if initial else self.ctrl
        return evaluate(np.linspace(0.0, self.length, n), self.knots, c, self.degree)


def fit_spline(
    bounds: Bounds, calib: StereoCalibration, p: SplineParams = SplineParams()
) -> SplineResult:
    """Initialise S from H^i and solve Eq. (8)."""
    if p.degree < 2 or p.degree > 5:
        raise ValueError(f"degree must be in 2..5, got {p.degree}")
    if p.n_ctrl < p.degree + 1:
        raise ValueError(f"n_ctrl must be >= degree + 1 = {p.degree + 1}, got {p.n_ctrl}")
    if p.max_iter < 1 or p.quad_per_span < 1:
        raise ValueError("max_iter and quad_per_span must be >= 1")
    if p.xy_knots not in ("uniform", "adaptive"):
        raise ValueError(f"xy_knots must be 'uniform' or 'adaptive', got {p.xy_knots!r}")
    if not p.xy_tol_px > 0:
        raise ValueError(f"xy_tol_px must be > 0, got {p.xy_tol_px}")
    st = _setup(bounds, calib, p)
    k, length, u, t_xy, ctrl_init = st.k, st.length, st.u.copy(), st.t_xy.copy(), st.ctrl_init
    lo_c, hi_c, half_c, mvs, b0, f0, A = st.lo_c, st.hi_c, st.half_c, st.mvs, st.b0, st.f0, st.A
    final = st.final
    if not p.optimise:
        viol = _violation(A @ b0, lo_c, hi_c, half_c)
        c0 = final(ctrl_init)
        return SplineResult(t_xy, c0, c0, k, length, u, "skipped", "", (f0, f0), 0, viol)

    E, e_rhs = st.E, st.e_rhs
    scale = 1.0 / f0 if f0 > 0 else 1.0
    Bd = A[: len(u)]  # basis at the points of H (the first constraint points)
    w_d = p.data_weight / (len(u) * np.maximum(0.5 * (bounds.upper - bounds.lower), 1e-12) ** 2)
    zs, (A_s, lo_s, hi_s, E_s, e_s) = st.zs, st.scaled
    problem = _Problem(mvs, scale, Bd, np.sqrt(w_d), bounds.centre, A_s, lo_s, hi_s)

    sol = problem.solve(b0, E_s, e_s, p.max_iter, st.qp_rows)
    untipped = sol.status == "infeasible" and bounds.line_ends is not None
    if untipped:  # a tip's end value (deviation 23) against tight bounds: the lines' (paper)
        e_rhs = np.asarray(bounds.line_ends) / np.array([1.0, st.du_ds, 1.0, st.du_ds])
        sol = problem.solve(b0, E / zs, e_rhs / zs, p.max_iter)
    relaxed = False
    if sol.status == "infeasible" and p.relax_slopes:
        # The endpoint slopes of L_{k_1}, L_{k_n} can contradict tight bounds next to the ends
        # (an infeasible problem): retry with only the endpoint values fixed.
        retry = problem.solve(b0, E[0:4:2] / zs, e_rhs[0:4:2] / zs, p.max_iter)
        if retry.status == "ok":
            sol, relaxed = retry, True
            E, e_rhs = E[0:4:2], e_rhs[0:4:2]
    if sol.status == "infeasible" and p.relax_slopes and untipped:
        # The lines' values were no better than the tips': the tips' values alone, the last
        # combination (real thread2_59: the tips' slopes and the lines' values both fail).
        retry = problem.solve(b0, st.E[0:4:2] / zs, st.e_rhs[0:4:2] / zs, p.max_iter)
        if retry.status == "ok":
            sol, relaxed, untipped = retry, True, False
            E, e_rhs = st.E[0:4:2], st.e_rhs[0:4:2]
    freed = False
    if sol.status == "infeasible" and p.relax_ends:
        # No end value either: the bounds alone (deviation 57). Every end constraint of Eq. (8)
        # is a line fitted through the measured depths near the end, or a tip's depth; when
        # none of them fits the bounds of the points beside it, the bounds (the measured
        # depths themselves) decide the ends, as they decide every other point.
        retry = problem.solve(b0, st.E[:0] / zs, st.e_rhs[:0] / zs, p.max_iter)
        if retry.status == "ok":
            sol, freed, relaxed, untipped = retry, True, False, False
    b = sol.x
    viol = _violation(A @ b, lo_c, hi_c, half_c) if np.all(np.isfinite(b)) else np.inf
    status: Status = sol.status
    if status == "ok" and viol > p.bound_tol:
        status = "out_of_bounds"
    if status != "ok":
        viol_init = _violation(A @ b0, lo_c, hi_c, half_c)
        msg = f"{sol.message} (bound excursion {viol:.3f} of the half-width)"
        c0 = final(ctrl_init)
        return SplineResult(
            t_xy, c0, c0, k, length, u, status, msg, (f0, f0), sol.iterations, viol_init
        )
    ctrl = ctrl_init.copy()
    ctrl[:, 2] = b
    msg = sol.message + (" (endpoint slope constraints relaxed)" if relaxed else "")
    msg += " (no end constraint: the bounds admit none of the end values)" if freed else ""
    msg += " (the window lines' end values: the tips' were infeasible)" if untipped else ""
    return SplineResult(
        t_xy,
        final(ctrl),
        final(ctrl_init),
        k,
        length,
        u,
        "ok",
        msg,
        (f0, mvs.value(b)),
        sol.iterations,
        viol,
    )


SETUP_CACHE: Final = 8  # set-ups kept: a few frames' spline stage in the debugger


@dataclass(frozen=True)
class _Setup:
    """What :func:`fit_spline` derives from H, its bounds and the knots alone, before the
    solve: the same for every value of the solver's parameters (``data_weight``,
    ``max_iter``, ``bound_tol``, ``relax_slopes``, ``relax_ends``, ``optimise``), so a slider
    of those re-runs the solve only. Read-only: results get copies (``final``, ``u``, ``t_xy``)."""

    k: int
    length: float
    u: np.ndarray
    t_xy: np.ndarray
    ctrl_init: np.ndarray
    xy: np.ndarray | None
    reexpress: np.ndarray | None
    lo_c: np.ndarray
    hi_c: np.ndarray
    half_c: np.ndarray
    mvs: _Mvs
    b0: np.ndarray
    f0: float
    A: np.ndarray
    E: np.ndarray
    e_rhs: np.ndarray
    du_ds: float  # u per unit of H's arc length s (the end slopes' scale)
    zs: float
    """The constraints' scale: the median half-width of the bounds (depths in half-widths)."""
    scaled: tuple[np.ndarray, ...]
    """A, lo_c, hi_c, E, e_rhs divided by ``zs``: the constraints of the first solve."""
    qp_rows: tuple[np.ndarray, ...]
    """Their QP rows, limits and kinds (:meth:`_Problem._constraints`). DAQP and the compiled
    kernels take writable arrays (neither writes them), so these and the scaled A are not
    flagged read-only: not to be written."""

    def final(self, c: np.ndarray) -> np.ndarray:
        """Control points on the knots of the result: S_x, S_y refined, S_z re-expressed."""
        if self.xy is None:
            return c.copy()
        return np.column_stack([self.xy, self.reexpress @ c[:, 2]])


_SETUPS: LRU[tuple, Any] = LRU(SETUP_CACHE)  # LRU.cached entries


def _setup(bounds: Bounds, calib: StereoCalibration, p: SplineParams) -> _Setup:
    """The (cached) set-up of Eq. (8) for ``bounds``: cached by the Bounds object (a weak
    reference, so that a freed one whose id is reused never hits), the focal length and the
    parameters the set-up reads."""
    key = (calib.focal, p.n_ctrl, p.degree, p.quad_per_span, p.xy_knots, p.xy_tol_px)
    return _SETUPS.cached((bounds,), key, lambda: _compute_setup(bounds, calib, p))


def _compute_setup(bounds: Bounds, calib: StereoCalibration, p: SplineParams) -> _Setup:
    k = p.degree
    P = len(bounds.H)
    s = bounds.s
    if P < 2 or s[-1] <= 0:
        raise ValueError("H spans no length: cannot fit a spline")
    c = bounds.centre  # np.nanmean's sum and count are np.mean's when no value is NaN
    z_mean = float(np.nanmean(c) if np.isnan(c).any() else np.add.reduce(c) / c.size)
    length = float(s[-1] * z_mean / calib.focal)  # l: lateral arc length, calib units
    u = np.clip(s * (length / s[-1]), 0.0, length)
    u[-1] = length
    m = min(p.n_ctrl, max(k + 1, P))  # no more control points than data points
    t = np.concatenate(
        [np.zeros(k + 1), np.linspace(0.0, length, m - k + 1)[1:-1], np.full(k + 1, length)]
    )

    Hi = np.column_stack([bounds.H[:, 0], bounds.H[:, 1], bounds.centre])  # H^i
    ctrl_init = _init_fit(Hi, u, t, k)
    t_xy, xy = t, None
    if p.xy_knots == "adaptive":
        t_xy, xy = _adaptive_xy(bounds.H[:, :2], u, t, k, p)

    reexpress = _reexpress_matrix(t, k, t_xy) if xy is not None else None
    du_ds = length / s[-1]
    lo_c, hi_c, u_c = _constraint_points(u, bounds.lower, bounds.upper)
    half_c = 0.5 * (hi_c - lo_c)
    mvs = _Mvs(t, k, length, p.quad_per_span)
    b0 = ctrl_init[:, 2].copy()
    f0 = mvs.value(b0)
    AV = basis_matrix(np.concatenate([u_c, [0.0, length]]), t, k)  # one call: rows apart
    A = AV[:-2]  # rows: u of H, then the midpoints
    E = _end_rows(t, k, length, mvs.end_slopes, AV[-2:])
    e_rhs = np.array(
        [
            bounds.end_values[0],
            bounds.end_slopes[0] / du_ds,
            bounds.end_values[1],
            bounds.end_slopes[1] / du_ds,
        ]
    )
    zs = max(median(half_c), 1e-12)  # constraint scaling: depths in half-widths
    scaled = (A / zs, lo_c / zs, hi_c / zs, E / zs, e_rhs / zs)
    qp_rows = _constraint_rows(scaled[0], scaled[3], scaled[4], scaled[1], scaled[2])
    arrays = (u, t_xy, ctrl_init, xy, reexpress, lo_c, hi_c, half_c, b0, A, E, e_rhs, *scaled[1:])
    for a in arrays:
        if a is not None:
            a.setflags(write=False)
    return _Setup(
        k,
        length,
        u,
        t_xy,
        ctrl_init,
        xy,
        reexpress,
        lo_c,
        hi_c,
        half_c,
        mvs,
        b0,
        f0,
        A,
        E,
        e_rhs,
        du_ds,
        zs,
        scaled,
        qp_rows,
    )


def _init_fit(Hi: np.ndarray, u: np.ndarray, t: np.ndarray, k: int) -> np.ndarray:
    """Least-squares spline through H^i with knots t: ``splprep(task=-1)``, ridge fallback."""
    m = len(t) - k - 1
    try:
        # FITPACK's status read from full_output, not turned into an exception by
        # warnings.catch_warnings: that swaps the process-wide filter list, and two sessions'
        # threads fitting at once could leave "error" installed for the whole server.
        (tck, _), _fp, ier, _msg = splprep(Hi.T, u=u, k=k, task=-1, t=t, full_output=1)
        ctrl = np.asarray(tck[1]).T[:m]
        if ier <= 0 and np.all(np.isfinite(ctrl)):
            return ctrl
    except (ValueError, TypeError):
        pass
    # Schoenberg-Whitney fails when H is sparse in some knot span: a tiny second-difference
    # ridge keeps the least-squares problem well posed and leaves well-covered spans unchanged.
    B = basis_matrix(u, t, k)
    D = np.diff(np.eye(m), 2, axis=0)
    lam = 1e-6 * np.trace(B.T @ B) / m
    return np.linalg.solve(B.T @ B + lam * D.T @ D, B.T @ Hi)


def _adaptive_xy(
    xy: np.ndarray, u: np.ndarray, t: np.ndarray, k: int, p: SplineParams
) -> tuple[np.ndarray, np.ndarray | None]:
    """Residual-driven knots for S_x, S_y: starting from the uniform knots t, every span holding
    a point of H farther than ``xy_tol_px`` from the fit is halved (at most ``XY_ROUNDS``
    times), so knots gather at tight bends and t stays a subset. Returns the knots and the
    (m', 2) control points, or (t, None) when no span needs splitting (the uniform fit)."""
    try:
        return _refine_xy(xy, u, t, k, p.xy_tol_px)
    except np.linalg.LinAlgError:  # a singular penalised system: keep the uniform fit
        return t, None


def _refine_xy(
    xy: np.ndarray, u: np.ndarray, t: np.ndarray, k: int, tol: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """Up to ``XY_ROUNDS`` rounds of a least-squares fit of S_x, S_y with a small
    third-difference penalty on the control points (a P-spline: halved spans may hold only a few
    points of H, where plain least squares oscillates; weight ``XY_PENALTY``) and of span
    splits, compiled (:func:`spline_kernel.refine_knots`: the basis banded, the normal equations
    by a banded Cholesky factorisation)."""
    t_xy, c, status = spline_kernel.refine_knots(
        np.ascontiguousarray(xy, dtype=np.float64),
        np.ascontiguousarray(u, dtype=np.float64),
        np.ascontiguousarray(t, dtype=np.float64),
        int(k),
        float(tol),
        XY_ROUNDS,
        XY_MIN_POINTS,
        XY_PENALTY,
    )
    if status == 2:
        raise np.linalg.LinAlgError("the penalised x, y fit's normal equations are singular")
    return (t_xy, c) if status == 0 else (t, None)


def _reexpress_matrix(t: np.ndarray, k: int, t_new: np.ndarray) -> np.ndarray:
    """(m', m) matrix taking coefficients on t to coefficients on t_new (a refinement of t) of
    the same spline: exact, as the spline lies in the refined space; the interpolation of the
    basis on t at the Greville abscissae of t_new (the collocation matrix there is square and
    nonsingular: Schoenberg-Whitney holds for a clamped knot vector of simple interior knots)."""
    m_new = len(t_new) - k - 1
    idx = np.arange(m_new)[:, None] + np.arange(1, k + 1)[None, :]
    # the Greville abscissae: np.mean's sum and division without its layers
    g = np.add.reduce(t_new[idx], axis=1) / k if k > 0 else 0.5 * (t_new[:-1] + t_new[1:])
    return np.linalg.solve(basis_matrix(g, t_new, k), basis_matrix(g, t, k))


def _distinct(t: np.ndarray) -> np.ndarray:
    """The distinct values of a sorted knot vector: ``np.unique(t)`` without its sort."""
    return t[np.concatenate(([True], t[1:] != t[:-1]))]


def basis_matrix(x: np.ndarray, t: np.ndarray, k: int, nu: int = 0) -> np.ndarray:
    """(len(x), m) dense matrix of the m B-spline basis functions on knots t (or their nu-th
    derivatives) at x in [t[k], t[-k-1]]: one evaluation of the spline with identity
    coefficients."""
    if not nu:
        return _basis_values(_as_points(x), t, k)
    return basis_derivatives(x, t, k, nu)[-1]


def _basis_values(x: np.ndarray, t: np.ndarray, k: int) -> np.ndarray:
    """``basis_matrix(x, t, k)``: compiled for points in a 1-D array
    (:func:`spline_kernel.basis_dense`, the same matrix to the last bit)."""
    m = len(t) - k - 1
    if x.ndim != 1 or m < 1 or k < 0:
        return BSpline.construct_fast(t, np.eye(m), k)(x)
    x, t = _writable(x), _writable(t)  # read-only: a copy
    return spline_kernel.basis_dense(x, t, int(k))


def _writable(a: np.ndarray) -> np.ndarray:
    """``np.require(a, np.float64, ("C", "W"))`` without its layers: ``a`` itself when it is
    a writable C-contiguous float64 array, else a copy that is."""
    if a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=np.float64, order="C")


def basis_derivatives(x: np.ndarray, t: np.ndarray, k: int, nu: int) -> list[np.ndarray]:
    """``[basis_matrix(x, t, k, j) for j in 1..nu]``, each derivative's coefficients computed
    from the previous one's (``_derivative_coefficients``, then :func:`evaluate`); compiled
    in one call for points in a 1-D array (:func:`spline_kernel.derivative_bases`, the same
    to the last bit): C-contiguous (len(x), m) arrays."""
    x = _as_points(x)
    if x.ndim != 1 or nu > k or k < 0 or len(t) < 2 * k + 2:
        return [evaluate(x, *tck) for tck in _derivative_coefficients(t, k, nu)]
    t = np.ascontiguousarray(t, dtype=np.float64)
    out, status = spline_kernel.derivative_bases(np.ascontiguousarray(x), t, int(k), int(nu))
    if status:
        raise ValueError(f"repeated inner knots: the spline is not {nu} times differentiable")
    return list(out)


def evaluate(x: np.ndarray, t: np.ndarray, c: np.ndarray, k: int) -> np.ndarray:
    """``BSpline.construct_fast(t, c, k)(x)``, the same values to the last bit, compiled for
    points x in a 1-D array and coefficients c (rows, d) (:func:`spline_kernel.evaluate`:
    ~2 us where scipy's call costs ~20 us); a C-contiguous (len(x), d) array."""
    x = _as_points(x)
    c = np.asarray(c)
    if x.ndim != 1 or c.ndim != 2 or c.dtype != np.float64 or len(c) < len(t) - k - 1 or k < 0:
        return np.ascontiguousarray(BSpline.construct_fast(t, c, k)(x))
    t, c = (np.ascontiguousarray(a, dtype=np.float64) for a in (t, c))
    return spline_kernel.evaluate(np.ascontiguousarray(x), t, c, int(k))


def _as_points(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _derivative_coefficients(
    t: np.ndarray, k: int, nu: int
) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Knots, (len(t) - 2 j, m) coefficients and degree of the j-th derivatives of the m basis
    functions on knots t, j = 1..nu: ``BSpline(t, eye(m), k).derivative(j)`` without its
    array-API layers (the same arithmetic as scipy's ``splder``, so the same values to the
    last bit)."""
    m = len(t) - k - 1
    if nu > k:
        raise ValueError(f"derivative order {nu} exceeds the degree {k}")
    c = np.zeros((len(t), m))
    c[:m] = np.eye(m)  # FITPACK convention: as many coefficient rows as knots
    out = []
    with np.errstate(invalid="raise", divide="raise"):
        try:
            for _ in range(nu):
                dt = (t[k + 1 : -1] - t[1 : -k - 1])[:, None]
                c = (c[1 : -1 - k] - c[: -2 - k]) * k / dt
                c = np.concatenate([c, np.zeros((k, m))])
                t = t[1:-1]
                k -= 1
                out.append((t, c, k))
        except FloatingPointError as exc:
            raise ValueError(
                f"repeated inner knots: the spline is not {nu} times differentiable"
            ) from exc
    return out


def _constraint_points(
    u: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mid = 0.5 * (u[1:] + u[:-1])
    uc = np.concatenate([u, mid])
    return np.interp(uc, u, lo), np.interp(uc, u, hi), uc


def _violation(z: np.ndarray, lo: np.ndarray, hi: np.ndarray, half: np.ndarray) -> float:
    out = np.maximum(lo - z, z - hi)
    return float(max(0.0, np.max(out / np.maximum(half, 1e-12))))


def _end_rows(
    t: np.ndarray,
    k: int,
    length: float,
    d1: np.ndarray | None = None,
    v: np.ndarray | None = None,
) -> np.ndarray:
    """Rows giving S_z(0), S_z'(0), S_z(l), S_z'(l) from b_z; ``d1``, ``v``: the basis' first
    derivatives and values at 0 and l, ``basis_matrix(ends, t, k, 1)`` and
    ``basis_matrix(ends, t, k)``, if the caller has them."""
    if v is None or d1 is None:
        ends = np.array([0.0, length])
        v = v if v is not None else basis_matrix(ends, t, k)
        d1 = d1 if d1 is not None else basis_derivatives(ends, t, k, 1)[0]
    return np.array([v[0], d1[0], v[1], d1[1]])  # np.stack's rows, without its layers


@functools.lru_cache(maxsize=16)
def _leggauss(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [-1, 1] (computed once per n)."""
    return np.polynomial.legendre.leggauss(n)


class _Mvs:
    """Eq. (8) by Gauss-Legendre quadrature, with its analytic gradient in b_z."""

    def __init__(
        self,
        t: np.ndarray,
        k: int,
        length: float,
        n_per_span: int,
    ) -> None:
        """The quadrature nodes uq and weights wq, the basis' first to third derivatives at the
        nodes (``B``, (nq, m) each) and its first derivatives at 0 and ``length``
        (``end_slopes``, (2, m), for Eq. (8)'s end rows): one compiled call."""
        xg, wg = _leggauss(n_per_span)
        edges = _distinct(t)
        a, b = edges[:-1], edges[1:]
        self.uq = (0.5 * (b - a)[:, None] * (xg[None, :] + 1.0) + a[:, None]).ravel()
        self.wq = (0.5 * (b - a)[:, None] * wg[None, :]).ravel()
        nq = len(self.uq)
        D = basis_derivatives(np.concatenate([self.uq, [0.0, length]]), t, k, 3)
        self.B = [d[:nq] for d in D]  # (nq, m) each, orders 1, 2, 3 (C-contiguous rows)
        self.end_slopes = D[0][nq:]
        self.sqrt_wq = np.sqrt(self.wq)

    def _terms(self, b: np.ndarray) -> tuple[np.ndarray, ...]:
        """The derivatives z1, z2, z3 of S_z at the nodes, g = 1 + z1^2, kp = d kappa / du, and
        g^-1.5, g^-2.5 (the Jacobian reuses them)."""
        z1, z2, z3 = (B @ b for B in self.B)
        g = 1.0 + z1 * z1
        g15, g25 = g**-1.5, g**-2.5
        kp = z3 * g15 - 3.0 * z1 * z2 * z2 * g25  # d kappa / du
        return z1, z2, z3, g, kp, g15, g25

    def value(self, b: np.ndarray) -> float:
        """Eq. (8) at b (compiled: :func:`spline_kernel.mvs_value`)."""
        return spline_kernel.mvs_value(*self.B, self.wq, np.ascontiguousarray(b, np.float64))

    def residual_jac(
        self,
        b: np.ndarray,
        scale: float,
        J_d: np.ndarray | None = None,
        c_d: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """rho, d rho / d b with scale * Eq. (8) = rho^T rho: rho_q = sqrt(w_q) kappa' g^-1/4
        (compiled: :func:`spline_kernel.mvs_residual`); with a linear data term's Jacobian
        ``J_d`` (P, m) and target ``c_d`` (P,), its residuals J_d b - c_d follow."""
        if J_d is None or c_d is None:
            J_d, c_d = np.zeros((0, len(b))), np.zeros(0)
        b = np.ascontiguousarray(b, dtype=np.float64)
        return spline_kernel.mvs_residual(*self.B, self.sqrt_wq, J_d, c_d, b, float(scale))

    def value_grad(self, b: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
        z1, z2, z3, g, kp = self._terms(b)[:5]
        r = g**-0.5
        f = float(np.sum(self.wq * kp * kp * r))
        dk1 = (
            -3.0 * z1 * z3 * g**-2.5 - 3.0 * z2 * z2 * g**-2.5 + 15.0 * z1 * z1 * z2 * z2 * g**-3.5
        )
        dk2 = -6.0 * z1 * z2 * g**-2.5
        dk3 = g**-1.5
        c = 2.0 * kp * r * self.wq
        g1 = c * dk1 - self.wq * kp * kp * z1 * g**-1.5
        grad = self.B[0].T @ g1 + self.B[1].T @ (c * dk2) + self.B[2].T @ (c * dk3)
        return f * scale, grad * scale


# --- the MVS solve: Gauss-Newton SQP with a dense active-set QP -----------------------------

# DAQP exit flags (https://darnstrom.github.io/daqp/parameters), in words for SplineResult.
_DAQP_FLAGS = {
    1: "optimal",
    2: "soft optimal",
    -1: "infeasible",
    -2: "cycling",
    -3: "unbounded",
    -4: "iteration limit",
    -5: "non-convex problem",
    -6: "initial active set overdetermined",
}
GN_FTOL = 1e-9  # stop when a step lowers the objective by less than this fraction (SLSQP ftol)
GN_STEP_TOL = 1e-9  # ... or moves b_z by less than this, in bound half-widths
LM_MU0 = 1e-3  # initial Levenberg-Marquardt damping, relative to the mean diagonal of J^T J


@dataclass(frozen=True)
class _Solution:
    x: np.ndarray
    status: Status
    message: str
    iterations: int


def _constraint_rows(
    A: np.ndarray, E: np.ndarray, e: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`_Problem._constraints` of the bound rows ``A`` (limits ``lo``, ``hi``) and the
    equality rows ``E`` (values ``e``)."""
    C = np.ascontiguousarray(np.vstack([A, E]))
    upper = np.concatenate([hi, e])
    lower = np.concatenate([lo, e])
    sense = np.concatenate([np.zeros(len(A), np.int32), np.full(len(E), 5, np.int32)])
    return C, upper, lower, sense


class _Problem:
    """min_b  scale * MVS(b) + sum_j w_j (B_d b - c)_j^2  s.t.  lo <= A b <= hi,  E b = e.

    Both terms are sums of squares, rho(b)^T rho(b), so each step solves the Gauss-Newton QP
    min_d |rho + J d|^2 under the linearised constraints (exact: they are linear) with DAQP,
    then backtracks along d for sufficient decrease. The constraints are linear, so every
    iterate after the first (a gradient step from b0 projected on the constraints) is feasible, and a
    line search between two feasible points stays feasible. The QP's exit flag is checked:
    an infeasible first QP means Eq. (8)'s constraints admit no spline."""

    def __init__(
        self,
        mvs: _Mvs,
        scale: float,
        Bd: np.ndarray,
        sqrt_wd: np.ndarray,
        centre: np.ndarray,
        A: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
    ) -> None:
        self.mvs, self.scale = mvs, scale
        self.A, self.lo, self.hi = A, lo, hi
        self.J_d = np.ascontiguousarray(sqrt_wd[:, None] * Bd)  # the data term's Jacobian
        self.c_d = np.ascontiguousarray(sqrt_wd * centre)  # ... and target: rho_d = J_d b - c_d

    def residual(self, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.mvs.residual_jac(b, self.scale, self.J_d, self.c_d)

    def value(self, b: np.ndarray) -> float:
        r, _ = self.residual(b)
        return float(r @ r)

    def _qp(
        self,
        H: np.ndarray,
        f: np.ndarray,
        b: np.ndarray,
        C: np.ndarray,
        upper: np.ndarray,
        lower: np.ndarray,
        sense: np.ndarray,
    ) -> tuple[np.ndarray, int]:
        """DAQP on the step d: min 0.5 d'Hd + f'd, lower <= C(b+d) <= upper; ``C``, ``upper``,
        ``lower``, ``sense``: the rows [A; E], their limits and kinds (:meth:`_constraints`,
        the same at every step)."""
        Cb = C @ b
        d, _, flag, _ = daqp.solve(H, f, C, upper - Cb, lower - Cb, sense)
        return np.asarray(d, dtype=np.float64), int(flag)

    def _constraints(
        self, E: np.ndarray, e: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The QP's constraint rows [A; E] (contiguous), their upper and lower limits and their
        DAQP kinds: bounds on A, equalities (5) on E."""
        return _constraint_rows(self.A, E, e, self.lo, self.hi)

    def solve(
        self,
        b0: np.ndarray,
        E: np.ndarray,
        e: np.ndarray,
        max_iter: int,
        rows: tuple[np.ndarray, ...] | None = None,
    ) -> _Solution:
        """Eq. (8) from b0 under E b = e; ``rows``: :meth:`_constraints` of (E, e) if the
        caller has them (the set-up keeps the first solve's)."""
        m = b0.size
        n_crossed = int(np.count_nonzero(self.lo > self.hi))
        if n_crossed:
            msg = f"infeasible: the lower depth bound lies above the upper at {n_crossed} points"
            return _Solution(b0, "infeasible", msg, 0)
        # Step 0: a unit gradient step from b0 projected on the constraints (SLSQP's first QP,
        # identity Hessian); it lands on the feasible set, where the Gauss-Newton steps start.
        C, upper, lower, sense = rows if rows is not None else self._constraints(E, e)
        r0, J0 = self.residual(b0)
        d, flag = self._qp(np.eye(m), 2.0 * (J0.T @ r0), b0, C, upper, lower, sense)
        if flag not in (1, 2):
            word = _DAQP_FLAGS.get(flag, f"exit flag {flag}")
            status: Status = "infeasible" if flag == -1 else "solver_failed"
            return _Solution(b0, status, f"QP (DAQP) {word} on the constraints of Eq. (8)", 0)
        b = b0 + d
        r, J = self.residual(b)
        F = float(r @ r)
        JtJ, g = J.T @ J, J.T @ r
        scale_h = np.trace(JtJ) / m + 1e-12
        mu, nu = LM_MU0 * scale_h, 2.0
        mvs = self.mvs
        for it in range(1, max_iter + 1):
            Hq = np.ascontiguousarray(2.0 * JtJ)  # 2 (J^T J + mu I)
            Hq.reshape(-1)[:: m + 1] += 2.0 * mu  # its diagonal (a view: C order)
            d, flag = self._qp(Hq, 2.0 * g, b, C, upper, lower, sense)
            if flag not in (1, 2):
                word = _DAQP_FLAGS.get(flag, f"exit flag {flag}")
                return _Solution(b, "solver_failed", f"QP (DAQP) {word} at step {it}", it)
            # the model decrease of F, the stop tests and the residuals at b + d (compiled)
            stop, pred, b_t, r_t, J_t, F_t, JtJ_t, g_t = spline_kernel.gn_trial(
                *mvs.B, mvs.sqrt_wq, self.J_d, self.c_d, float(self.scale), J, r, self.A, b, d,
                GN_FTOL * max(F, 1.0), GN_STEP_TOL,
            )  # fmt: skip
            if stop:
                return _Solution(b, "ok", f"converged in {it} Gauss-Newton steps", it)
            rho = (F - F_t) / pred
            if rho > 0:  # accept; Nielsen's damping update
                b, r, J, JtJ, g = b_t, r_t, J_t, JtJ_t, g_t
                done = F - F_t <= GN_FTOL * max(F, 1.0)
                F = F_t
                mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                if done:
                    return _Solution(b, "ok", f"converged in {it} Gauss-Newton steps", it)
            else:
                mu *= nu
                nu *= 2.0
        return _Solution(
            b, "solver_failed", f"iteration limit: {max_iter} Gauss-Newton steps", max_iter
        )
