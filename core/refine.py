"""Two-view depth refinement: the final curve's projection lies on the thread in both views.

The MVS spline of Eq. (8) takes its depth from the keypoints' stereo depths and the bounds of
Eq. (7) only; nothing checks that its projection into the right image lies on the thread. This
stage (a deviation, ``mode="two_view"``, the default; ``mode="repair"`` only on frames where
stereo matched a strand to its neighbour; ``mode="off"`` is the paper) refits S_z with S_x, S_y
fixed so that, row by row along the epipolar lines, the curve's disparity d(u) = f B / S_z(u)
matches the disparity of the thread itself:

- on image row y(u) the thread crosses the left mask in a run of pixels and the right mask in
  another; their sub-pixel centres c_L, c_R (the centroid of the thread's contrast against the
  local background, over the run and the pixels beside it that hold its edges' partial
  coverage) give the observed disparity t = c_L - c_R. The run nearest the curve's prediction
  (x(u), x(u) - d(u)) is taken; each run is one observation, shared by the samples on it.
- its variance: each centre's, from the image noise and how well the flanks beside the run
  fit a line of background (an occluder or another strand beside it: large), plus
  ``MODEL_PX``^2 each; Cauchy weights on the residuals after the first solve.
- the MVS curve itself is a measurement of the disparity at the points of H, with the
  stereo's own spread about it (the robust s.d. of H's stereo disparities about the curve),
  scaled by the half-width of Eq. (7)'s bounds there (wide bounds: the MVS is in doubt).
  Where the thread is seen cleanly the runs refine it; where they are doubtful it stays.
- smoothness: the integral of (d^3 S_z / ds^3)^2 over the image arc length s, the small-slope
  form of Eq. (8)'s Minimum Variation term, weighted by ``smooth_px``^5 (a length in px: depth
  features shorter than it are smoothed);
- the depth bounds of Eq. (7) hold at the points of H (exact: a least-squares problem with
  linear inequalities, solved by Lawson and Hanson's reduction to NNLS).

Gauss-Newton over the control values of S_z with re-association of the runs, ``iterations``
rounds; the result is the spline of the previous stage with its S_z replaced. The runs and
the rounds are compiled kernels (core/refine_kernel.py); the rounds work on the B-spline basis
in banded form (k + 1 nonzeros a row), so a solve costs O(samples k^2), not a dense QR.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Final, Literal

import cv2
import numpy as np

from threadrecon.core.bounds import Bounds
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.lru import LRU
from threadrecon.core.numeric import median
from threadrecon.core.params import Params, param
from threadrecon.core.refine_kernel import (
    GN_CONSTANTS,
    band_dot,
    basis_bands,
    edge_centres,
    gauss_newton,
    lsi,
    mask_runs,
    nearest_runs,
)
from threadrecon.core.segmentation import LiftedPair
from threadrecon.core.shift_information import scale as information_scale
from threadrecon.core.shift_information import shift_information
from threadrecon.core.spline import SplineResult

QUAD_PER_SPAN = 4  # Gauss-Legendre nodes per knot span: exact for the squared 3rd derivative
RIDGE = 1e-9  # relative ridge that keeps the least-squares matrix of full column rank
GATE_PX = 2.0  # a run is associated when the prediction lies within its half-length + 2 px
MISMATCH_PX = 4.0  # stereo off by more than this from the same-rank runs: another strand
MISMATCH_SIGMA = 2.0  # ... and by more than this many of the runs' sigma: 2 L / sqrt(6) < L + 1
MISMATCH_RUN = 3  # consecutive points of H that make a mismatched section
OFF_THREAD_PX = 10  # samples (~px of image arc) off the right thread that make a section
BACKGROUND_TOL = 12.0  # grey levels from B that look like bare background (2 x seg_delta)
ROW_LIMIT = 2.0**31  # px: an ordinate beyond any image (and safe to cast to int64)
MIN_DISPARITY_PX = 0.5  # the solve linear in depth needs a positive target disparity
EDGE_PX = 2  # pixels beyond a run's ends that hold its edges' partial coverage and blur
FLANK_PX = 2  # pixels beyond those whose mean is the background level on that side
MODEL_PX = 0.05  # s.d. of a centre beyond its noise: a sampled profile's centroid locks to pixels
CAUCHY = 2.385  # Cauchy scale of the run residuals, in their s.d. (95 % efficiency)
MIN_SD_PX = 0.01  # floor of the stereo's spread about the MVS curve (noise-free input), px
MIN_PRIOR_POINTS = 5  # points of H that estimate that spread (a robust scale needs a few)
NNLS_ITER = 50  # NNLS steps per column of the LDP problem before it gives up (scipy's 3)
GN_NOT_FINITE = 5  # status of refine_kernel.gauss_newton / lsi: a value is not finite
_GN_CONSTANTS = np.array(
    [
        {
            "gate_px": GATE_PX,
            "min_disparity_px": MIN_DISPARITY_PX,
            "model_px": MODEL_PX,
            "cauchy": CAUCHY,
            "ridge": RIDGE,
            "nnls_iter": NNLS_ITER,
        }[name]
        for name in GN_CONSTANTS
    ],
    dtype=np.float64,
)


@dataclass(frozen=True)
class RefineParams(Params):
    mode: Literal["repair", "two_view", "off"] = param(
        "two_view",  # with run centres from the edges and the MVS curve as a measurement it
        # wins on held-out generated, raw-rig and raw frames (docs/method.md, "Two-view
        # refinement, second round"); paper-strict turns it off
        label="two-view refinement",
        doc='"two_view": refit S_z so that the curve lies on the thread in both views; '
        '"repair": the same, only on a frame where stereo matched a section of one strand to '
        "its neighbour (a hairpin), the MVS spline unchanged on every other frame; "
        '"off": the MVS spline as it is (paper).',
    )
    smooth_px: float = param(
        20.0,
        lo=1.0,
        hi=1000.0,
        unit="px",
        label="smoothness length",
        doc="Depth features shorter than this along the image curve are smoothed, px.",
        slider=(5.0, 200.0, 1.0),
    )
    iterations: int = param(
        3, lo=1, hi=20, label="rounds", doc="Gauss-Newton rounds with re-association."
    )
    shift_information: bool = param(
        False,  # opt-in: the development split's e_S 0.343 -> 0.305 mm, held-out generated
        # suites unchanged within +-0.004 mm but occlusion frames slightly worse (docs/method.md,
        # "The Blender frames' pixel origin ...")
        label="stereo window information",
        doc="Doubt the MVS curve where the SSD window could not fix the disparity (its sum of "
        "squared horizontal gradients is low: a uniform thread along the rows); off: the "
        "bounds' half-width alone.",
    )


def refine_depth(
    spline: SplineResult,
    bounds: Bounds,
    lifted: LiftedPair,
    calib: StereoCalibration,
    p: RefineParams = RefineParams(),
) -> SplineResult:
    """S with S_z refitted to the disparity of the thread along the epipolar lines."""
    if p.mode == "off":
        return spline
    k = spline.degree
    fB = calib.focal * calib.baseline
    c0 = np.ascontiguousarray(spline.ctrl, dtype=np.float64)
    runs_L = _runs(lifted.P_L, lifted.grey_L, lifted.background[0])
    runs_R = _runs(lifted.P_R, lifted.grey_R, lifted.background[1])
    sm = _samples(spline, c0, runs_L)  # what S_x, S_y and the knots decide, kept
    t, xy_len, Bm, rows, iL, cL, okL = sm.t, sm.xy_len, sm.Bm, sm.rows, sm.iL, sm.cL, sm.okL
    xyz = Bm.dot(c0)
    xy, z_c0 = xyz[:, :2], np.ascontiguousarray(xyz[:, 2])

    d_run = functools.partial(_run_disparity, z_c0, iL, okL, runs_L.centre.size, fB)
    mismatched, shared = _mismatched(bounds, runs_L, runs_R, fB, d_run)  # d_run: when read
    keep = ~mismatched
    # Stereo matched another strand somewhere: pair runs by rank on rows where the two views
    # hold two runs (or equally many, on the rows of a coil's mismatched turn), and start
    # with one solve linear in depth (Gauss-Newton in disparity cannot cross from one
    # strand's depth to the other's).
    remedy = bool(mismatched.any())
    if not spline.ok and not remedy:
        return spline  # a failed MVS is repaired only where its bounds matched the wrong strand
    if (
        p.mode == "repair"
        and not remedy
        and not _off_thread(xy, z_c0, rows, okL, runs_R, lifted, fB)
    ):
        return spline  # the MVS curve lies on the thread in both views: nothing to repair
    # Smoothness: third derivative over image arc length s = u * xy_len / length.
    wq, D3 = sm.wq, sm.D3  # the quadrature weights, d^3 S_z / du^3 per control value
    ds_du = xy_len / spline.length
    z_mean = float(np.add.reduce(z_c0) / z_c0.size)  # np.mean's operations
    to_px = fB / z_mean**2  # depth -> disparity px at the mean depth
    S = D3.scaled(to_px / ds_du**3 * np.sqrt(p.smooth_px**5 * wq * ds_du))

    BH = sm.BH
    if remedy:
        iR_rank = runs_L.same_rank(runs_R, rows, np.where(okL, iL, -1), shared)
    else:
        iR_rank = np.full(len(iL), -1)
    if remedy:
        BK, lo, hi = BH[keep], bounds.lower[keep], bounds.upper[keep]
    else:  # every bound holds: the rows themselves, not a copy of each
        BK, lo, hi = BH, bounds.lower, bounds.upper
    G = BK.stack(BK.scaled(-1.0))  # Eq. (7): lower <= S_z(u_H) <= upper
    h = np.concatenate([lo, -hi])
    b0 = np.ascontiguousarray(c0[:, 2])
    # The MVS curve at the points of H as a measurement of the disparity there, with the
    # stereo's own noise: the robust spread of H's stereo disparities about it.
    z0_H = BH.dot(b0)
    with np.errstate(divide="ignore", invalid="ignore"):
        d0_H = fB / z0_H
        res_H = fB / bounds.H[:, 2] - d0_H
        hw_H = 0.5 * (fB / bounds.lower - fB / bounds.upper)  # Eq. (7)'s half-width, px
    use_H = keep & np.isfinite(res_H) & (z0_H > 0) & np.isfinite(hw_H) & (hw_H > 0)
    if spline.ok and use_H.sum() >= MIN_PRIOR_POINTS:  # a failed MVS measures nothing
        sd_0 = max(1.4826 * median(np.abs(res_H[use_H])), MIN_SD_PX)
        # the MVS is doubted where its bounds are wide: sd in proportion to the half-width
        sd_H = sd_0 * hw_H / median(hw_H[use_H])
        if p.shift_information:  # and where the SSD window could not fix the disparity
            sd_H = sd_H * _information_scale(lifted, bounds.H, use_H)
        # and its ends where Eq. (8) fixed them to a tip matched in both views (deviation 23:
        # L_{k_1}, L_{k_n} moved off the window lines), at the stereo's typical spread
        ends = _tip_ends(bounds) & keep[[0, -1]]
        BP = BH[use_H]
        if ends.any():
            BP = BP.stack(_basis(t, k, np.array([0.0, spline.length])[ends]))
        zP0 = BP.dot(b0)
        dP0 = fB / zP0
        sdP = np.concatenate([sd_H[use_H], np.full(int(ends.sum()), sd_0)])
    else:
        BP = BH[np.zeros(len(BH.first), dtype=bool)]
        zP0 = dP0 = sdP = np.zeros(0)
    b, status = gauss_newton(
        Bm.vals,
        Bm.first,
        np.ascontiguousarray(xy[:, 0]),
        rows,
        iL,
        cL,
        okL,
        runs_L.var,
        iR_rank,
        runs_R.key,
        runs_R.centre,
        runs_R.length,
        runs_R.var,
        runs_R.row_start,
        runs_R.key_scale,
        BP.vals,
        BP.first,
        zP0,
        dP0,
        sdP,
        S.vals,
        S.first,
        G.vals,
        G.first,
        np.ascontiguousarray(h, dtype=np.float64),
        np.ascontiguousarray(b0),
        float(fB),
        int(not remedy),  # rounds 1..: Gauss-Newton in disparity; round 0: linear in depth
        p.iterations,
        _GN_CONSTANTS,
    )
    if status == GN_NOT_FINITE:
        raise ValueError(
            "two-view refinement: a depth bound of Eq. (7) or the MVS curve is not finite"
        )
    if status:
        return spline  # a depth <= 0, too few samples on the thread in both views, or the
        # bounds cannot be met with this spline: keep the MVS depth
    ctrl = c0.copy()
    ctrl[:, 2] = b
    dropped = mismatched if remedy else None  # for the check: these bounds no longer hold
    if not spline.ok:  # the MVS failed on bounds built on the wrong strand's depth
        message = (
            f"the MVS result was rejected ({spline.status}: {spline.message}); the two-view "
            "repair met the bounds of Eq. (7) outside the strand matched to its neighbour"
        )
        return replace(spline, ctrl=ctrl, status="ok", message=message, bounds_dropped=dropped)
    return replace(spline, ctrl=ctrl, bounds_dropped=dropped)


SAMPLES_CACHE: Final = 4  # the samples of a few splines: a solver slider's re-runs
_SAMPLES: LRU[tuple, Any] = LRU(SAMPLES_CACHE)  # LRU.cached entries


@dataclass(frozen=True)
class _Samples:
    """What :func:`refine_depth` derives from the knots, S_x, S_y and the points of H alone
    (not S_z): the curve's image length, its samples' basis rows and left runs, the
    smoothness term's quadrature and H's basis rows. A solver parameter (``data_weight``,
    ``max_iter``, ...) changes S_z only, so its re-run finds them here. Shared: not to be
    written (the kernels read them; flagged read-only they would be another JIT type)."""

    t: np.ndarray
    xy_len: float
    Bm: _Basis
    rows: np.ndarray
    iL: np.ndarray
    cL: np.ndarray
    okL: np.ndarray
    wq: np.ndarray
    D3: _Basis
    BH: _Basis


def _samples(spline: SplineResult, c0: np.ndarray, runs_L: _Runs) -> _Samples:
    """The (cached) :class:`_Samples` of ``spline`` (control points ``c0``, C order) on the
    left runs ``runs_L``: kept by value (the knots, S_x, S_y, l and u_H: a re-run's spline
    is a new object with the same values) while ``runs_L`` lives."""
    key = (
        "samples",
        int(spline.degree),
        float(spline.length),
        np.ascontiguousarray(spline.knots, dtype=np.float64).tobytes(),
        c0[:, :2].tobytes(),
        np.ascontiguousarray(spline.u_H, dtype=np.float64).tobytes(),
    )
    return _SAMPLES.cached((runs_L,), key, lambda: _compute_samples(spline, c0, runs_L))


def _compute_samples(spline: SplineResult, c0: np.ndarray, runs_L: _Runs) -> _Samples:
    t, k = np.ascontiguousarray(spline.knots, dtype=np.float64), spline.degree
    c200 = spline.curve(200)[:, :2]
    step = c200[1:] - c200[:-1]  # np.linalg.norm(np.diff(...), axis=1)'s own operations
    sq = step * step
    xy_len = float(np.sqrt(sq[:, 0] + sq[:, 1]).sum())
    n = int(min(max(xy_len, 50), 3000))  # about one sample per px of image arc length
    u = np.linspace(0.0, spline.length, n)
    Bm = _basis(t, k, u)  # the samples' basis rows, banded
    xy = Bm.dot(c0)[:, :2]  # each column its own sums: S_z's are not read
    rows = _rows(xy[:, 1])
    iL = runs_L.nearest_index(rows, xy[:, 0])
    cL, lL = runs_L.at(iL)
    okL = np.isfinite(cL) & (np.abs(cL - xy[:, 0]) <= 0.5 * lL + GATE_PX)
    uq, wq = _gauss_nodes(t, k, QUAD_PER_SPAN)
    D3 = _basis(t, k, uq, 3)  # d^3 S_z / du^3 per control value
    BH = _basis(t, k, np.clip(spline.u_H, 0, spline.length))
    return _Samples(t, xy_len, Bm, rows, iL, cL, okL, wq, D3, BH)


def _information_scale(lifted: LiftedPair, H: np.ndarray, use: np.ndarray) -> np.ndarray:
    """(P,) factors of the MVS measurement's s.d. at the points ``H`` (P, 3) from the SSD
    window's information about a horizontal shift there (core/shift_information.py)."""
    return information_scale(shift_information(lifted.I_L, lifted.P_L, H[:, :2]), use)


def _tip_ends(bounds: Bounds) -> np.ndarray:
    """(2,) bool: whether the start / end value of Eq. (8) came from a tip matched in both
    views (it differs from the window line's, ``Bounds.line_ends``)."""
    if bounds.line_ends is None:
        return np.zeros(2, dtype=bool)
    line = np.array([bounds.line_ends[0], bounds.line_ends[2]])
    return np.asarray(bounds.end_values, dtype=np.float64) != line


def _off_thread(
    xy: np.ndarray,
    z: np.ndarray,
    rows: np.ndarray,
    okL: np.ndarray,
    runs_R: _Runs,
    lifted: LiftedPair,
    fB: float,
) -> bool:
    """Whether the curve (samples ``xy``, depth ``z``, about one per px), on the thread in the
    left view (``okL``), misses the thread in the right view by more than ``MISMATCH_PX`` beyond
    the nearest run's half-length over a stretch of at least ``OFF_THREAD_PX`` samples, where
    the right image shows bare background (within ``BACKGROUND_TOL`` of its level B, or 3 robust
    standard deviations of the image's grey levels on a textured background): its depth
    there belongs to no strand the right view shows. Where the prediction falls outside the
    right image or on something else (an occluder hiding the thread from the right camera
    only), a miss proves nothing."""
    H, W = lifted.grey_R.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        x_R = xy[:, 0] - np.where(z > 0, fB / z, np.nan)
    inside = np.isfinite(x_R) & (x_R >= 0) & (x_R <= W - 1) & (rows >= 0) & (rows < H)
    xi = np.clip(np.nan_to_num(np.rint(x_R), nan=0.0), 0, W - 1).astype(np.int64)
    cR, lR = runs_R.at(runs_R.nearest_index(rows, np.where(inside, x_R, -1e9)))
    with np.errstate(invalid="ignore"):
        miss = okL & inside & np.isfinite(cR) & ~(np.abs(cR - x_R) <= 0.5 * lR + MISMATCH_PX)
    if not _long_stretch(miss):
        return False  # not even counting every miss as bare background (the usual case)
    tol = max(BACKGROUND_TOL, 3.0 * _derived("spread", (lifted.grey_R,), (), _spread))
    miss &= np.abs(lifted.grey_R[np.clip(rows, 0, H - 1), xi] - lifted.background[1]) <= tol
    return _long_stretch(miss)


def _long_stretch(flags: np.ndarray) -> bool:
    """Whether ``flags`` (n,) bool holds a run of at least ``OFF_THREAD_PX`` consecutive True."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(np.int8), [0]])))
    return bool(np.any(edges[1::2] - edges[::2] >= OFF_THREAD_PX))


def _run_disparity(
    z: np.ndarray, iL: np.ndarray, okL: np.ndarray, n_runs: int, fB: float
) -> np.ndarray:
    """(n_runs,) mean disparity, px, of the curve samples (depth ``z``) on each left run
    (``iL`` where ``okL``); NaN on runs the curve does not visit."""
    use = okL & (z > 0)
    n = np.bincount(iL[use], minlength=n_runs)
    total = np.bincount(iL[use], weights=fB / z[use], minlength=n_runs)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(n > 0, total / n, np.nan)


def _mismatched(
    bounds: Bounds,
    runs_L: _Runs,
    runs_R: _Runs,
    fB: float,
    d_run: np.ndarray | Callable[[], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(P,) points of H whose stereo depth matched the wrong strand, and (H,) the image rows
    of such sections found on rows of three or more runs.

    On a row where both views hold two runs, the run of the same rank (runs keep their
    left-to-right order between the views) gives a disparity more than :func:`_tolerance`
    away: ``MISMATCH_PX``, or ``MISMATCH_SIGMA`` standard deviations of the run-centre
    disparity where the runs are long (a thread along the rows pins its runs' centres only to
    +- L / sqrt(12); on a 57 px run a correct match was 6 px off them).
    On a row where both views hold equally many runs, three or more (the turns of a coil),
    the same, and the right run that the point's stereo depth predicts is taken: it is the
    same-rank partner of another left run, on which the curve's own disparity ``d_run``
    (:func:`_run_disparity`) agrees with that pairing (uniqueness: one right run cannot show
    two strands; where strands cross and swap their order, the other strand's depth does
    not agree with the rank pairing, and nothing is flagged). Over at least ``MISMATCH_RUN``
    consecutive points. Their bounds of Eq. (7), built on that depth, are dropped.
    ``d_run`` may be a function that computes it: called only when a row holds three runs."""
    pre = _DERIVED.cached(
        (bounds, runs_L, runs_R),
        ("mismatch", float(fB)),
        lambda: _Stereo(bounds, runs_L, runs_R, fB),
    )
    if pre.result is not None:  # no row of three runs: d_run is not read (a spline re-run)
        return pre.result[0].copy(), pre.result[1].copy()
    return _sections(pre, runs_L, runs_R, d_run() if callable(d_run) else d_run)


class _Stereo:
    """What :func:`_mismatched` reads of H's stereo depths and the runs of both views: the
    same for every spline on one segmentation and one set of bounds, so cached with them
    (:data:`_DERIVED`) while a spline slider re-runs the refinement. ``result``: the
    finished (out, shared) when no point can be a coil's (no row holds three runs, or none
    of H's stereo depths there names another left run's partner): ``d_run`` is then not
    read, and a re-run neither computes it nor finds the sections again."""

    def __init__(self, bounds: Bounds, runs_L: _Runs, runs_R: _Runs, fB: float) -> None:
        H = bounds.H
        self.rows = rows = np.rint(H[:, 1]).astype(np.int64)
        self.iL = iL = runs_L.nearest_index(rows, H[:, 0])
        iR = runs_L.same_rank(runs_R, rows, iL)
        self.cL, self.lL = cL, lL = runs_L.at(iL)
        cR, lR = runs_R.at(iR)
        with np.errstate(divide="ignore", invalid="ignore"):
            self.d_H = d_H = fB / bounds.centre
            # NaN depth: not bad
            self.bad = (iR >= 0) & (np.abs(cL - cR - d_H) > _tolerance(lL, lR))
        self.n_L = runs_L.count(rows)  # same_rank requires as many in the right view
        self.result: tuple[np.ndarray, np.ndarray] | None = None
        self.coil: tuple[np.ndarray, ...] | None = None  # the coil test's curve-free part
        if (self.n_L >= 3).any():
            self.coil = _coil_pairs(self, runs_L, runs_R)
        if self.coil is None or not self.coil[0].any():  # no coil point, whatever d_run
            out, shared = _sections(self, runs_L, runs_R, None)
            out.setflags(write=False)
            shared.setflags(write=False)
            self.result = (out, shared)


def _sections(
    pre: _Stereo, runs_L: _Runs, runs_R: _Runs, d_run: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_mismatched` from its cached part ``pre``."""
    rows, bad = pre.rows, pre.bad
    coil = np.zeros_like(bad)
    if d_run is not None and d_run.size and pre.coil is not None:  # else no coil point (exact)
        taken, o, c_o, c_j = pre.coil
        with np.errstate(invalid="ignore"):
            coil = taken & (np.abs(c_o - c_j - d_run[o]) <= MISMATCH_PX)
    # A strand matched to its neighbour is a section of consecutive points, not one point.
    both = bad | coil
    edges = np.flatnonzero(np.diff(np.concatenate([[0], both.astype(np.int8), [0]])))
    out = np.zeros_like(bad)
    shared = np.zeros(runs_R.H, dtype=bool)
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if b - a >= MISMATCH_RUN:
            out[a:b] = True
            if coil[a:b].any():  # the rows this section spans: rank pairing there
                lo, hi = int(rows[a:b].min()), int(rows[a:b].max())
                shared[max(lo - 1, 0) : min(hi + 2, runs_R.H)] = True
    return out, shared


def _coil_pairs(
    pre: _Stereo, runs_L: _Runs, runs_R: _Runs
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What :func:`_sections` tests against the curve's own disparity ``d_run`` on rows of
    three or more runs, computed once per stereo match (it does not depend on the curve):
    the points whose stereo depth predicts the right run ``j`` that is the same-rank partner
    of another left run ``o``, and the two runs' centres (read-only)."""
    rows, iL, cL, lL, d_H, n_L = pre.rows, pre.iL, pre.cL, pre.lL, pre.d_H, pre.n_L
    many = np.ones(runs_R.H, dtype=bool)
    iR_n = runs_L.same_rank(runs_R, rows, iL, many)
    on = (iR_n >= 0) & (n_L >= 3)
    cR_n, lR_n = runs_R.at(np.where(on, iR_n, -1))
    with np.errstate(invalid="ignore"):
        x_R = np.where(np.isfinite(d_H), cL - d_H, -1e9)
        on &= np.abs(cL - cR_n - d_H) > _tolerance(lL, lR_n)
    j = runs_R.nearest_index(rows, np.where(on, x_R, -1e9))
    r = np.clip(rows, 0, runs_R.H - 1)
    other = np.where(on & (j >= 0), runs_L.row_start[r] + (j - runs_R.row_start[r]), -1)
    taken = on & (j >= 0) & (other != iL) & (other >= 0)
    o = np.clip(other, 0, max(runs_L.centre.size - 1, 0))
    c_o, _ = runs_L.at(np.where(taken, o, -1))
    c_j, _ = runs_R.at(np.where(taken, j, -1))
    for a in (taken, o, c_o, c_j):
        a.setflags(write=False)
    return taken, o, c_o, c_j


def _tolerance(l_L: np.ndarray, l_R: np.ndarray) -> np.ndarray:
    """How far, px, a stereo disparity may lie from the disparity of a left and a right run of
    lengths ``l_L``, ``l_R`` (px) and still be theirs: ``MISMATCH_PX``, or ``MISMATCH_SIGMA``
    times the run-centre disparity's standard deviation sqrt((l_L^2 + l_R^2) / 12) (the
    weight of the solve), whichever is larger. With ``MISMATCH_SIGMA`` = 2 a stereo depth from
    the neighbour strand still exceeds it on runs of equal length L: two disjoint runs' centres
    lie at least L + 1 apart, and 2 L / sqrt(6) < L + 1. Inf where a run is missing."""
    return np.maximum(MISMATCH_PX, MISMATCH_SIGMA * np.sqrt((l_L**2 + l_R**2) / 12.0))


def _rows(y: np.ndarray) -> np.ndarray:
    """Image rows (int64) of sample ordinates ``y``, px; -1 (outside the image) where y is not
    finite or beyond any image (an unoptimised spline's NaN or 1e40 control values)."""
    inside = np.abs(y) < ROW_LIMIT  # False for NaN
    return np.rint(np.where(inside, y, -1.0)).astype(np.int64)


@functools.cache
def _leggauss(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [-1, 1] (an eigenvalue problem: computed once)."""
    return np.polynomial.legendre.leggauss(n)


def _gauss_nodes(t: np.ndarray, k: int, per_span: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights, ``per_span`` per non-empty knot span of (t, k)."""
    x, w = _leggauss(per_span)
    brk = t[k : len(t) - k]
    if np.all(brk[1:] >= brk[:-1]):  # sorted (and no NaN): np.unique's values without a sort
        brk = brk[np.concatenate(([True], brk[1:] != brk[:-1]))]
    else:
        brk = np.unique(brk)
    a, b = brk[:-1, None], brk[1:, None]
    return (0.5 * (b - a) * x + 0.5 * (a + b)).ravel(), (0.5 * (b - a) * w).ravel()


def _lsi(A: np.ndarray, r: np.ndarray, G: np.ndarray, h: np.ndarray) -> np.ndarray | None:
    """min ||A x - r|| subject to G x >= h for dense A (N, n), G (P, n) (Lawson and Hanson,
    LSI -> LDP -> NNLS; the kernel's solve with a band as wide as the matrix, A kept of full
    column rank by a ridge of ``RIDGE`` times its largest entry). None when the constraints
    are infeasible."""
    A = np.ascontiguousarray(A, dtype=np.float64)
    G = np.ascontiguousarray(G, dtype=np.float64)
    n = A.shape[1]
    if A.ndim != 2 or G.ndim != 2 or G.shape[1] != n or len(r) != len(A) or len(h) != len(G):
        raise ValueError(f"A {A.shape}, r {np.shape(r)}, G {G.shape}, h {np.shape(h)} mismatch")
    ridge = RIDGE * max(float(np.abs(A).max(initial=0.0)), 1e-300)
    x, status = lsi(
        A,
        np.zeros(len(A), np.int64),
        np.ascontiguousarray(r, dtype=np.float64),
        ridge,
        G,
        np.zeros(len(G), np.int64),
        np.ascontiguousarray(h, dtype=np.float64),
        n,
        int(NNLS_ITER * len(G)),
    )
    if status == GN_NOT_FINITE:
        raise ValueError("least squares with inequalities: a value is not finite")
    return None if status else x


@dataclass(frozen=True)
class _Basis:
    """Rows of a B-spline basis matrix in banded form: row i is ``vals[i]`` (k + 1,) at
    columns first[i] .. first[i] + k (:func:`_basis`)."""

    vals: np.ndarray
    first: np.ndarray

    def __len__(self) -> int:
        return len(self.first)

    def __getitem__(self, rows: np.ndarray) -> _Basis:
        return _Basis(np.ascontiguousarray(self.vals[rows]), self.first[rows])

    def scaled(self, w: float | np.ndarray) -> _Basis:
        """Rows times ``w`` (a number, or one per row)."""
        w = np.asarray(w, dtype=np.float64)
        return _Basis(self.vals * (w[:, None] if w.ndim else w), self.first)

    def stack(self, other: _Basis) -> _Basis:
        return _Basis(
            np.concatenate([self.vals, other.vals]), np.concatenate([self.first, other.first])
        )

    def dot(self, c: np.ndarray) -> np.ndarray:
        """The rows times c (m,) or (m, d)."""
        c = np.asarray(c, dtype=np.float64)
        out = band_dot(self.vals, self.first, np.ascontiguousarray(c.reshape(len(c), -1)))
        return out[:, 0] if c.ndim == 1 else out


def _basis(t: np.ndarray, k: int, x: np.ndarray, nu: int = 0) -> _Basis:
    """The B-splines of degree k on knots t (float64, C order) at points x, or their nu-th
    derivatives, as banded rows."""
    if len(t) < 2 * k + 2:
        raise ValueError(f"a spline of degree {k} needs at least {k + 1} control points")
    inner = t[k + 1 : len(t) - k - 1]
    if nu and inner.size and (inner[1:] == inner[:-1]).any():
        raise ValueError(f"repeated inner knots: the spline is not {nu} times differentiable")
    return _Basis(*basis_bands(t, int(k), np.ascontiguousarray(x, dtype=np.float64), nu))


def _spread(grey: np.ndarray) -> float:
    """Robust standard deviation (1.4826 MAD) of an image's grey levels, on every 4th pixel of
    every 4th row: the background's own spread."""
    sample = grey[::4, ::4].astype(np.float64)
    return 1.4826 * float(np.median(np.abs(sample - np.median(sample))))


def _runs(mask: np.ndarray, grey: np.ndarray, background: float) -> _Runs:
    """The (cached) runs of one view's mask P and grey image."""
    return _derived("runs", (mask, grey), (float(background),), _Runs, background)


DERIVED_CACHE: Final = 24  # runs of both views (and their row runs), a spread, H's stereo
# match: a few frames
_DERIVED: LRU[tuple, Any] = LRU(DERIVED_CACHE)  # LRU.cached entries


def _derived(
    kind: str, arrays: tuple[np.ndarray, ...], extra: tuple, fn: Callable, *args: Any
) -> Any:
    """``fn(*arrays, *args)``: data that depend only on the segmentation (its masks and grey
    images), cached by the array objects (weak references, so that a freed array whose id is
    reused never hits) while the pipeline re-runs the stages after it (a spline slider)."""
    return _DERIVED.cached(arrays, (kind, *extra), lambda: fn(*arrays, *args))


class _Runs:
    """Horizontal runs of a mask (one per maximal row segment) with sub-pixel centres.

    A run's centre is the centroid of the thread's contrast against the local background over
    the run and ``EDGE_PX`` pixels beyond each of its ends: the thread's cross-section (its
    partial coverage at the edges, its shading, the optics' blur) is symmetric about its axis,
    and the pixels beside the mask hold the edge's partial coverage (below the mask's 0.5) that
    the mask alone cuts off (a bias of up to +-0.5 px; see ``refine_kernel.edge_centres``).
    ``var`` is the centre's variance, px^2, from the image noise and the uncertainty of the
    background.
    """

    def __init__(self, mask: np.ndarray, grey: np.ndarray, background: float) -> None:
        H, W = mask.shape
        if grey.shape != mask.shape:
            raise ValueError(f"grey image {grey.shape} and mask {mask.shape} differ in shape")
        self.row, a, b = row_runs(mask)
        self.length = (b - a + 1).astype(np.float64)
        self.centre, self.var = edge_centres(
            self.row,
            a,
            b,
            np.ascontiguousarray(grey, dtype=np.float32),
            float(background),
            EDGE_PX,
            FLANK_PX,
        )
        self.H = H
        self.key_scale = 4.0 * W
        self.key = self.row * self.key_scale + self.centre  # sorted: row-major, then by x
        self.row_start = np.searchsorted(self.row, np.arange(H + 1))

    def nearest(self, rows: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre and length of the run nearest ``x`` on each row; inf where the row has none."""
        return self.at(self.nearest_index(rows, x))

    def at(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre and length of runs ``idx``; inf where ``idx`` < 0."""
        found = idx >= 0
        c = np.full(len(idx), np.inf)
        ln = np.full(len(idx), np.inf)
        c[found] = self.centre[idx[found]]
        ln[found] = self.length[idx[found]]
        return c, ln

    def count(self, rows: np.ndarray) -> np.ndarray:
        """Runs on each row (0 outside the image)."""
        valid = (rows >= 0) & (rows < self.H)
        r = np.where(valid, rows, 0)
        return np.where(valid, self.row_start[r + 1] - self.row_start[r], 0)

    def nearest_index(self, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Index of the run nearest ``x`` on each row (of the two either side of it); -1 where
        the row has none or ``x`` is not finite."""
        return nearest_runs(
            self.key,
            self.centre,
            self.row_start,
            self.key_scale,
            np.ascontiguousarray(rows, dtype=np.int64),
            np.ascontiguousarray(x, dtype=np.float64),
        )

    def same_rank(
        self, other: _Runs, rows: np.ndarray, idx: np.ndarray, shared: np.ndarray | None = None
    ) -> np.ndarray:
        """Index of ``other``'s run with the same rank on the row as run ``idx`` of this view,
        where both views hold two runs on the row (two strands side by side; with more, near
        crossings and loops, the left-to-right order need not hold), or equally many on a row
        flagged in ``shared`` (H,) (a coil's turn matched to its neighbour, see
        :func:`_mismatched`); -1 elsewhere."""
        out = np.full(len(idx), -1)
        n_self, n_other = self.count(rows), other.count(rows)
        use = (idx >= 0) & (n_self == 2) & (n_other == 2)  # two strands side by side
        if shared is not None:
            inside = (rows >= 0) & (rows < self.H)
            on = inside & shared[np.clip(rows, 0, self.H - 1)]
            use |= (idx >= 0) & on & (n_self >= 2) & (n_self == n_other)
        r = rows[use]
        out[use] = other.row_start[r] + (idx[use] - self.row_start[r])
        return out


def row_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (cached) horizontal runs of a mask (:func:`_mask_runs`), kept while the mask
    object lives: the runs of P_R serve this stage and the check's contested matches
    (core/check_support), one scan of the mask per segmentation. Shared: not to be written."""
    return _derived("row_runs", (mask,), (), _mask_runs)


def _mask_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row, first and last column (inclusive) of the horizontal runs of an (H, W) mask, in
    row-major order (a run is a maximal stretch of mask pixels on one row)."""
    m = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    H, W = m.shape
    if W % 8 == 0 and W:  # eight pixels a word: empty stretches are skipped a word at a time
        return mask_runs(m, m.view(np.int64), 0, H, 0, W)
    x, y, w, h = cv2.boundingRect(m)  # else pixel by pixel, inside the mask's bounding box
    return mask_runs(m, np.zeros((0, 0), np.int64), y, y + h, x, x + w)
