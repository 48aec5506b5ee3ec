"""SSD stereo matching on lifted images, Eqs. (2)-(3), and depth via Q, Eqs. (4)-(5).

For every segmented left pixel p the energy curve E(d, p), d = 0..alpha, is the sum over the
segmented pixels p' of a window around p (g_p, a subset of P_L) of the squared difference
between I_L^lift(p') and I_R^lift(p' - (d, 0)).

Computation (a compiled kernel, ``_energy_kernel``, that scales with the thread, not the image):
I_R^lift is the lift value off P_R (dilated by the lift), so (I_L(p') - I_R(p' - d))^2 is a constant c_0(p') except
where p' - d falls on a segmented right pixel of the same row. E(., p) is therefore the window
sum of c_0, plus, for each p' in g_p and each segmented right pixel q of its row within the
search range, the change at d = x' - q_x. Work: N * |g_p| * (right pixels per row): a run of
adjacent right pixels is a run of consecutive disparities (one indexed loop), and each side of
the sliding window steps its first right pixel in range along the row (no search). Eq. (3)
reads each pixel's curve while it is in cache, so the (N, alpha+1) energy volume is never
stored (``StereoResult.energy`` recomputes it on demand); no image-sized temporary either.

Search range: ``alpha`` px (the paper's), or, with ``z_near_mm`` / ``z_far_mm`` set, the
disparities f B / z of that working depth range (docs/method.md, "Disparity range from depth"),
so that a rig of another resolution or baseline needs no retuning.

Deviation (``subpixel=True``, default): the integer argmin d_min is refined to the exact
minimiser of the same energy with the right image linearly interpolated between integer
disparities (closed form on [d_min-1, d_min] and [d_min, d_min+1]). With a 1 mm baseline one
pixel of disparity is about 7-11 mm of depth, so integer disparities cannot reach millimetre
accuracy. ``subpixel=False`` gives the paper's integer disparities.

Deviation (``epipolar_deg > 0``, default 15 deg): continuity along near-epipolar runs. Where the
thread runs within ``epipolar_deg`` of the image rows, shifting the match along the row hardly
changes the SSD (the cost of Eq. (2) is flat along the epipolar line), and the sub-pixel minimum
is set by image noise or by resampling errors of a rectified pair: a vertical error of e px
moves it by about e / tan(theta). Each pixel's disparity has the least-squares variance
sigma_d^2 = s^2 / sum(dI_R/dx)^2 (s^2: the residual per window pixel at the minimum, at least
the two images' rounding noise). Pixels with sigma_d <= ``ANCHOR_PX`` or off near-epipolar runs
keep their own disparity; the others take the MAP estimate of a membrane along the thread:
minimise sum_p w_p (d_p - d_hat_p)^2 + sum_(p,q 8-neighbours) (d_p - d_q)^2 / tau^2 with
w_p = 1 / (n sigma_d^2) and tau = ``continuity_px``, the anchors fixed (Dirichlet). n, the
window side, counts the pixels along the thread that share one window's data (neighbouring
estimates are not independent); data and membrane then both scale with the thread's width,
so the smoothing length does not depend on it. A flat run then follows its
well-conditioned ends and its own data where that is precise. Both terms are robust, over a few
reweighted rounds started from the 3 x 3 median of d_hat: a pixel's own match is Cauchy-weighted
(a gross mismatch stops pulling) and a link between neighbours Welsch-weighted at ``STRAND_PX``
(another strand touching the run in the image, a few px of disparity away, is cut off). ``epipolar_deg=0`` (paper-strict: ``subpixel=false``) leaves Eq. (3)'s minimiser.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import sparse
from scipy.linalg.lapack import dpbsv, dptsv
from scipy.sparse.csgraph import reverse_cuthill_mckee

from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.compiled import helper, kernel
from threadrecon.core.params import Params, param
from threadrecon.core.segmentation import LIFT_VALUE, LiftedPair

NEXT_GAP = 2  # Eq. (6) text: |d_next - d_min| > 2, neighbours of d_min have similar energies
D_MAX = 4096  # largest disparity search range, px: a depth range that asks for more is an error
ANCHOR_PX = 0.05  # px: a pixel whose disparity s.d. is below this keeps its own match
ROUNDING_VAR = 1.0 / 6.0  # grey^2: two 8-bit roundings (1/12 each), the least residual per pixel
ROBUST_PX = 0.5  # px: Cauchy scale of a pixel's own match (a gross mismatch stops pulling)
STRAND_PX = 1.0  # px: Welsch scale of a neighbour's difference (another strand at a crossing)
ROUNDS = 3  # reweighted least-squares rounds of the robust membrane


@dataclass(frozen=True)
class StereoParams(Params):
    alpha: int = param(
        80, lo=4, hi=512, unit="px", symbol="alpha", slider=(8, 200, 1), label="α max disparity"
    )
    """Maximum disparity alpha of Eq. (3), px."""
    window: int = param(
        9, lo=1, hi=51, unit="px", symbol="g_p", slider=(3, 21, 2), label="window px"
    )
    """Side of the square window g_p, px (odd)."""
    subpixel: bool = True
    """Refine d_min to sub-pixel precision (deviation, see module docstring)."""
    epipolar_deg: float = param(
        15.0,
        lo=0.0,
        hi=45.0,
        unit="deg",
        label="near-epipolar angle",
        slider=(0.0, 45.0, 1.0),
        doc="Thread runs within this angle of the image rows take their sub-pixel disparity "
        "from continuity along the thread where their own match is imprecise "
        "(module docstring; 0: off, each pixel's own minimum).",
    )
    continuity_px: float = param(
        0.03,
        lo=1e-4,
        hi=10.0,
        unit="px",
        symbol="tau",
        label="continuity tau",
        slider=(0.005, 0.2, 0.005),
        doc="Expected change of disparity between neighbouring thread pixels (the membrane's "
        "tau), px: smaller smooths near-epipolar runs more.",
    )
    z_near_mm: float | None = param(
        None,
        lo=1.0,
        hi=1e5,
        unit="mm",
        label="nearest depth",
        doc="Nearest working depth: the largest disparity searched is ceil(f B / z_near) "
        "instead of alpha (empty: alpha).",
    )
    z_far_mm: float | None = param(
        None,
        lo=1.0,
        hi=1e6,
        unit="mm",
        label="farthest depth",
        doc="Farthest working depth: d_min and d_next are searched from floor(f B / z_far) "
        "up (empty: from 0).",
    )

    def search_range(self, calib: StereoCalibration) -> tuple[int, int]:
        """(d_lo, d_hi), px: the disparities searched for d_min and d_next."""
        near, far = self.z_near_mm, self.z_far_mm
        for name, z in (("z_near_mm", near), ("z_far_mm", far)):
            if z is not None and not (math.isfinite(z) and z > 0):
                raise ValueError(f"{name} must be a positive depth in mm, got {z!r}")
        fB = calib.focal * calib.baseline * calib.mm_per_unit  # px mm
        d_hi = self.alpha if near is None else math.ceil(fB / near)
        d_lo = 0 if far is None else math.floor(fB / far)
        if near is not None and far is not None and not near < far:
            raise ValueError(f"z_near_mm ({near:g}) must be below z_far_mm ({far:g})")
        if d_hi > D_MAX:
            raise ValueError(
                f"the search range reaches {d_hi} px of disparity (f B = {fB:.0f} px mm): "
                f"raise z_near_mm or lower alpha (at most {D_MAX} px)"
            )
        if d_hi - d_lo < NEXT_GAP + 2:
            raise ValueError(
                f"the disparity search range [{d_lo}, {d_hi}] px is narrower than "
                f"{NEXT_GAP + 2} px: widen the depth range (z_near_mm, z_far_mm) or raise alpha"
            )
        return d_lo, d_hi

    def _check(self) -> None:
        super()._check()
        if self.window % 2 == 0:
            raise ValueError("stereo.window must be odd")


@dataclass(frozen=True)
class StereoResult:
    """Per segmented left pixel (N of them, in row-major order of P_L).

    ``pixels``: (N, 2) int, (x, y) = (col, row) of p.
    ``d_min``, ``d_next``: (N,) int, best and second-best disparity (|d_next - d_min| > 2).
    ``E_min``, ``E_next``: (N,) float, their energies.
    ``disparity``: (N,) float, d_min refined to sub-pixel precision (or d_min), px.
    ``points``: (N, 3) float, Eq. (4)-(5) reprojection (X, Y, Z) in the left camera frame,
    calibration units; NaN where the disparity is not positive.
    ``depth``: (N,) float, D(p) = Z, Eq. (5).
    ``d_range``: (d_lo, d_hi), px, the disparities searched (d_hi = alpha without a depth range).

    The energy volume E(d, p) of Eq. (2), (N, d_hi + 1) float32, is not kept (39 MB on a
    1920x1080 thread): :attr:`energy` recomputes it on first use, bit-identical to the values
    d_min and d_next were taken from, and :meth:`energy_row` one pixel's curve.
    """

    pixels: np.ndarray
    d_min: np.ndarray
    d_next: np.ndarray
    E_min: np.ndarray
    E_next: np.ndarray
    disparity: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    shape: tuple[int, int]
    d_range: tuple[int, int]

    @property
    def index_image(self) -> np.ndarray:
        """(H, W) int image: index into the per-pixel arrays, -1 off P_L."""
        idx = np.full(self.shape, -1, dtype=np.int64)
        idx[self.pixels[:, 1], self.pixels[:, 0]] = np.arange(len(self.pixels))
        return idx

    @functools.cached_property
    def energy(self) -> np.ndarray:
        """(N, d_hi + 1) float32 E(d, p) of Eq. (2), computed once on first use."""
        return self._energy(None)

    def energy_row(self, i: int) -> np.ndarray:
        """(d_hi + 1,) float32 E(., p) of the i-th pixel alone (the pixel inspector's curve)."""
        if not 0 <= i < len(self.pixels):
            raise IndexError(f"pixel index {i} out of range for {len(self.pixels)} pixels")
        if "energy" in self.__dict__:
            return self.__dict__["energy"][i]
        return self._energy(np.array([i]))[0]

    def _energy(self, which: np.ndarray | None) -> np.ndarray:
        source = self.__dict__.get("_source")
        if source is None:
            raise ValueError("this stereo result has no energy source (built by hand or copied)")
        return source.energy(which)

    def _with_source(self, source: _EnergySource) -> StereoResult:
        # not a field: JSON views and exports walk the fields, and the source holds the images
        object.__setattr__(self, "_source", source)
        return self


@dataclass(frozen=True)
class _EnergySource:
    """The inputs of Eq. (2) kept by a :class:`StereoResult` to recompute its energy volume."""

    lifted: LiftedPair
    window: int
    d_lo: int
    d_hi: int

    def energy(self, which: np.ndarray | None) -> np.ndarray:
        box = _Box.of(self.lifted, self.d_hi)
        ty, tx = (box.ry, box.rx) if which is None else (box.ry[which], box.rx[which])
        out, *_ = _energy_kernel(
            ty, tx, box.I_L_p, box.index, self.window // 2, box.q_ptr, box.q_col, box.q_val, box.q_run,
            box.x0, self.d_lo, self.d_hi, LIFT_VALUE, True,
        )  # fmt: skip
        return out


@dataclass(frozen=True)
class _Box:
    """The bounding box of P_L (rows y0.., columns x0..): everything Eq. (2) reads."""

    y0: int
    x0: int
    ry: np.ndarray
    """(N,) int64 rows of P_L in the box, row-major order."""
    rx: np.ndarray
    """(N,) int64 columns of P_L in the box."""
    index: np.ndarray
    """(h, w) int32 box image of pixel indices, -1 off P_L."""
    I_L_p: np.ndarray
    """(N,) float64 I_L^lift at the pixels of P_L."""
    q_ptr: np.ndarray
    q_col: np.ndarray
    q_val: np.ndarray
    """Right pixels off the lift value, per box row (CSR by row: pointers, absolute columns
    ascending, I_R), in the columns a left pixel reaches with d in 0..d_hi."""
    q_run: np.ndarray
    """(Q,) int64: for each right pixel, one past the last of its run of adjacent columns in
    its row (where the energy kernel's inner loop runs over consecutive disparities)."""

    @staticmethod
    def of(lifted: LiftedPair, d_hi: int) -> _Box:
        """The box of P_L and its arrays (:func:`_box_kernel`: one pass over the box of P_L and
        one over the right view's rows there, where some twenty numpy calls were)."""
        P_L = np.ascontiguousarray(lifted.P_L, dtype=bool)
        x0, y0, bw, bh = cv2.boundingRect(P_L.view(np.uint8))
        if bw == 0:
            raise ValueError("empty segmentation: no thread pixel in the left image")
        xr0 = max(0, x0 - d_hi)
        ry, rx, index, I_L_p, q_ptr, q_col, q_val, q_run = _box_kernel(
            P_L, np.asarray(lifted.I_L, dtype=np.float32), np.asarray(lifted.I_R, dtype=np.float32),
            y0, x0, y0 + bh, x0 + bw, xr0, LIFT_VALUE,
        )  # fmt: skip
        return _Box(y0, x0, ry, rx, index, I_L_p, q_ptr, q_col, q_val, q_run)


def match_stereo(
    lifted: LiftedPair, calib: StereoCalibration, p: StereoParams = StereoParams()
) -> StereoResult:
    """Eqs. (2)-(5) for every pixel of P_L."""
    if p.alpha < NEXT_GAP + 2:
        raise ValueError(f"alpha must be >= {NEXT_GAP + 2}, got {p.alpha}")
    if p.window < 1 or p.window % 2 == 0:
        raise ValueError(f"window must be a positive odd number of px, got {p.window}")
    H, W = lifted.P_L.shape
    if calib.image_size != (H, W):
        raise ValueError(f"images are {(H, W)} px but the calibration is for {calib.image_size}")
    if lifted.P_R.shape != (H, W) or lifted.I_L.shape != (H, W) or lifted.I_R.shape != (H, W):
        raise ValueError("lifted images and masks must all be (H, W)")
    d_lo, d_hi = p.search_range(calib)
    r = p.window // 2

    # Everything below works on the bounding box of P_L: the thread, not the image.
    box = _Box.of(lifted, d_hi)
    rows, cols = box.ry + box.y0, box.rx + box.x0
    _, d_min, d_next, E_min, E_next = _energy_kernel(
        box.ry, box.rx, box.I_L_p, box.index, r, box.q_ptr, box.q_col, box.q_val, box.q_run, box.x0,
        d_lo, d_hi, LIFT_VALUE, False,
    )  # Eqs. (2)-(3), fused: the energy volume is never stored  # fmt: skip

    disparity = d_min.astype(np.float64)
    if p.subpixel:
        I_R = np.ascontiguousarray(lifted.I_R)  # C order: indexed without strides (18 % faster)
        step, ee, resid, count, tan2 = _subpixel_kernel(
            box.ry, box.rx, box.I_L_p, box.index, r, I_R, box.y0, box.x0, d_min, d_hi, LIFT_VALUE,
        )  # fmt: skip
        disparity = disparity + step
        if p.epipolar_deg > 0:
            var = np.maximum(resid, count * ROUNDING_VAR) / np.maximum(count - 1, 1)
            with np.errstate(divide="ignore"):
                var = var / ee  # sigma_d^2, px^2 (inf where the cost has no slope)
            free = (tan2 < math.tan(math.radians(p.epipolar_deg)) ** 2) & (var > ANCHOR_PX**2)
            if free.any():
                w = 1.0 / (p.window * var)
                at = box.ry * box.index.shape[1] + box.rx  # = _positions(box.index)
                disparity = _continuity(box.index, disparity, w, free, p.continuity_px, at)

    points = _reproject(cols, rows, disparity, calib.Q)
    return StereoResult(
        pixels=np.stack([cols, rows], axis=1),
        d_min=d_min,
        d_next=d_next,
        E_min=E_min,
        E_next=E_next,
        disparity=disparity,
        points=points,
        depth=points[:, 2],
        shape=(H, W),
        d_range=(d_lo, d_hi),
    )._with_source(_EnergySource(lifted, p.window, d_lo, d_hi))


def _continuity(
    index: np.ndarray,
    d_hat: np.ndarray,
    w: np.ndarray,
    free: np.ndarray,
    tau: float,
    at: np.ndarray | None = None,
) -> np.ndarray:
    """Robust membrane MAP of the disparity on the ``free`` pixels (module docstring).

    ``index``: (h, w) box image of pixel indices (-1 off P_L, row-major); ``d_hat``: (N,)
    sub-pixel disparities, px; ``w``: (N,) data weights, 1/px^2; ``free``: (N,) bool, the pixels
    solved for (the others are fixed at ``d_hat``); ``at``: (N,) int64 flat box positions of
    the pixels (:func:`_positions`, computed when None). Returns the (N,) disparities."""
    at = _positions(index) if at is None else at
    # the neighbour pairs that touch a free pixel, in their order (one compiled pass:
    # not every pair of P_L, then a selection of them)
    a, b = _free_pairs_kernel(index, at, np.ascontiguousarray(free, dtype=bool))
    fi = np.flatnonzero(free)
    m = fi.size
    pos = np.full(d_hat.size, -1, dtype=np.int64)
    pos[fi] = np.arange(m)
    fa, fb = free[a], free[b]
    both, a_only, b_only = fa & fb, fa & ~fb, fb & ~fa
    pa, pb = pos[a], pos[b]
    # The matrix is a thin band once its pixels are in reverse Cuthill-McKee order (the thread
    # is a few px wide): a banded Cholesky per round, the order and band layout computed once.
    ia, ib = pa[both], pb[both]
    indptr, indices = _free_pattern_kernel(index, at[fi], pos)
    perm = _rcm(indices, indptr, m)
    rank = np.empty(m, dtype=np.int64)
    rank[perm] = np.arange(m)
    ra, rb = rank[ia], rank[ib]
    lo, hi = np.minimum(ra, rb), np.maximum(ra, rb)
    band = int((hi - lo).max()) if hi.size else 0
    d = d_hat.copy()
    d[fi] = _local_median_kernel(
        index, d_hat, at[fi]
    )  # a start that neither a mismatch nor noise moves
    # What the rounds share: the gathers that do not depend on d (the same values each round).
    w_f, d_hat_f = w[fi], d_hat[fi]
    pa_fa, pb_fb, pa_a, pb_b = pa[fa], pb[fb], pa[a_only], pb[b_only]
    d_hat_ba, d_hat_ab = d_hat[b[a_only]], d_hat[a[b_only]]
    off_row = band + lo - hi
    for _ in range(ROUNDS):
        rho = w_f / (1.0 + ((d_hat_f - d[fi]) / ROBUST_PX) ** 2)  # Cauchy IRLS weights
        e = np.exp(-(((d[a] - d[b]) / STRAND_PX) ** 2)) / tau**2  # Welsch: strands part
        diag = rho + 1e-9  # ridge: a run with no data and no anchor keeps a solution
        diag += np.bincount(pa_fa, e[fa], m) + np.bincount(pb_fb, e[fb], m)
        rhs = rho * d_hat_f
        rhs += np.bincount(pa_a, e[a_only] * d_hat_ba, m)
        rhs += np.bincount(pb_b, e[b_only] * d_hat_ab, m)
        ab = np.zeros((band + 1, m))  # upper band form of solveh_banded, permuted order
        ab[band, rank] = diag
        ab[off_row, hi] = -e[both]  # each pair once, off the diagonal row: no sums
        x = _solveh_banded_upper(ab, rhs[perm])
        d[fi] = x[rank]
    return d


def _rcm(indices: np.ndarray, indptr: np.ndarray, m: int) -> np.ndarray:
    """scipy's reverse Cuthill-McKee order of the symmetric (m, m) pattern (CSR ``indices``,
    ``indptr``), through its public function on an int32 ``csr_array`` (the private routine
    behind it saved ~0.1 ms a frame; the public API is kept)."""
    idx = np.int32 if m < 2**31 and indices.size < 2**31 else np.int64
    pattern = sparse.csr_array(
        (np.ones(indices.size), indices.astype(idx), indptr.astype(idx)), shape=(m, m)
    )
    return reverse_cuthill_mckee(pattern, symmetric_mode=True)


def _solveh_banded_upper(ab: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``scipy.linalg.solveh_banded(ab, b)`` (upper form, float64, m >= 1) calling its LAPACK
    routine directly (``?ptsv`` for one off-diagonal, else ``?pbsv``, as it does): the same
    solution bit for bit, without its wrappers' 20-30 us a call (3 calls a frame)."""
    if not (np.isfinite(ab).all() and np.isfinite(b).all()):
        raise ValueError("array must not contain infs or NaNs")
    if ab.shape[0] == 2:
        _, _, x, info = dptsv(ab[1, :], ab[0, 1:].copy(), b, False, False, False)
    else:
        _, x, info = dpbsv(ab, b, lower=0, overwrite_ab=False, overwrite_b=False)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}th leading minor not positive definite")
    if info < 0:
        raise ValueError(f"illegal value in {-info}th argument of internal pbsv")
    return x


def _local_median(index: np.ndarray, values: np.ndarray, which: np.ndarray) -> np.ndarray:
    """(len(which),) median of ``values`` over the pixels ``which`` of P_L and their
    8-neighbours in P_L (``index``: the box image of row-major pixel indices); NaN values do
    not count."""
    return _local_median_kernel(
        index, np.ascontiguousarray(values, dtype=np.float64), _positions(index)[which]
    )


def _positions(index: np.ndarray) -> np.ndarray:
    """(N,) flat box position of each pixel of the box image ``index`` (row-major order)."""
    return np.flatnonzero(index >= 0)


def reproject(x: np.ndarray, y: np.ndarray, disparity: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Eqs. (4)-(5): (x, y, d) in px -> (N, 3) points (X, Y, Z)/W; NaN where d <= 0."""
    return _reproject(np.asarray(x), np.asarray(y), np.asarray(disparity), Q)


def _reproject(x: np.ndarray, y: np.ndarray, disparity: np.ndarray, Q: np.ndarray) -> np.ndarray:
    h = np.stack([x, y, disparity, np.ones_like(disparity)], axis=0).astype(np.float64)
    XYZW = Q @ h
    with np.errstate(divide="ignore", invalid="ignore"):
        pts = (XYZW[:3] / XYZW[3]).T
    pts[~(disparity > 0)] = np.nan
    return pts


# --- compiled kernels ------------------------------------------------------------------------
# Compiled ahead of time once per machine, loaded without numba (core/compiled.py).


@kernel(
    "Tuple((float32[:, ::1], int64[::1], int64[::1], float64[::1], float64[::1]))(int64[::1], "
    "int64[::1], float64[::1], int32[:, ::1], int64, int64[::1], int64[::1], float64[::1], "
    "int64[::1], int64, int64, int64, float64, boolean)"
)
def _energy_kernel(
    ty, tx, I_L_p, index, r, q_ptr, q_col, q_val, q_run, x0, d_lo, d_hi, lift, store
):  # noqa: ANN001
    """Eqs. (2)-(3) at the pixels (ty, tx) of P_L: d_min, d_next, E_min, E_next, and with
            ``store`` the (T, d_hi+1) float32 energy E(d, p) (else a (0, d_hi+1) array, and only
            d >= d_lo is accumulated). Sums in float64, rounded to float32 per d as stored.

            ``ty``, ``tx``: rows and columns in the bounding box (origin row 0, column ``x0``), in
            row-major order; ``I_L_p``: I_L at every pixel of P_L; ``index``: box image of indices into
            ``I_L_p``, -1 off P_L; ``q_ptr``, ``q_col``, ``q_val``: the right pixels off the lift value
    in each box row (CSR by row, columns ascending, absolute), and their I_R; ``q_run``: the end
        of each one's run of adjacent columns (:attr:`_Box.q_run`). The window slides along a row: moving p one pixel right removes the window's left column and adds a new
            right column. Each pixel's curve lives in a (d_hi+1) buffer while Eq. (3) reads it."""
    n = I_L_p.size
    t = ty.size
    h, w = index.shape
    c0 = np.empty(n)  # (I_L(p') - lift)^2: the cost against the lifted background
    for j in range(n):
        c0[j] = (I_L_p[j] - lift) ** 2
    q_rev = q_val[::-1].copy()  # a run of right pixels meets the disparities in reverse
    d_from = 0 if store else d_lo
    out = np.empty((t if store else 0, d_hi + 1), dtype=np.float32)
    row = np.empty(d_hi + 1, dtype=np.float32)
    d_min = np.empty(t, dtype=np.int64)
    d_next = np.empty(t, dtype=np.int64)
    E_min = np.empty(t)
    E_next = np.empty(t)
    acc = np.zeros(d_hi + 1)
    base = np.zeros(1)
    # Per box row and side (0 adds the right column, 1 removes the left one): the first right
    # pixel with d <= d_hi for the column last visited, valid where its stamp is the current
    # window's. Columns only grow while a window slides, so that pixel only moves right.
    cursor = np.zeros((2, h), dtype=np.int64)
    stamp = np.full((2, h), -1, dtype=np.int64)
    gen = -1
    prev_y, prev_x = -1, -1
    for i in range(t):
        yi, xi = ty[i], tx[i]
        if yi == prev_y and xi - prev_x <= 2 * r:
            for x in range(prev_x + 1, xi + 1):  # slide the window one column at a time
                _add_column(x - 1 - r, yi, -1.0, r, index, h, w, c0, I_L_p, q_ptr, q_col, q_rev, q_run, x0, d_from, d_hi, acc, base, cursor[1], stamp[1], gen)  # fmt: skip
                _add_column(x + r, yi, 1.0, r, index, h, w, c0, I_L_p, q_ptr, q_col, q_rev, q_run, x0, d_from, d_hi, acc, base, cursor[0], stamp[0], gen)  # fmt: skip
        else:
            acc[:] = 0.0
            base[0] = 0.0
            gen += 1  # a new window: every cursor is stale
            for xx in range(xi - r, xi + r + 1):
                _add_column(xx, yi, 1.0, r, index, h, w, c0, I_L_p, q_ptr, q_col, q_rev, q_run, x0, d_from, d_hi, acc, base, cursor[0], stamp[0], gen)  # fmt: skip
        d_min[i], d_next[i], E_min[i], E_next[i] = _fill_best_two(
            row, base[0], acc, d_from, d_lo, NEXT_GAP
        )
        if store:
            out[i, :] = row
        prev_y, prev_x = yi, xi
    return out, d_min, d_next, E_min, E_next


@helper(inline="always")
def _add_column(
    xx,
    yi,
    sign,
    r,
    index,
    h,
    w,
    c0,
    I_L_p,
    q_ptr,
    q_col,
    q_rev,
    q_run,
    x0,
    d_from,
    d_hi,
    acc,
    base,
    cursor,
    stamp,
    gen,
):  # noqa: ANN001
    """Add (sign 1) or remove (-1) the window column xx of the pixel in row yi. ``q_rev``:
    the right pixels' I_R in reverse order (``q_val[::-1]``). ``cursor``, ``stamp``: this
    side's per-row first right pixel with d <= d_hi, and the window (``gen``) it was found for
    (else a binary search finds it)."""
    nq = q_rev.size
    if xx < 0 or xx >= w:
        return
    xa = xx + x0
    for yy in range(max(0, yi - r), min(h, yi + r + 1)):
        j = index[yy, xx]
        if j < 0:
            continue
        base[0] += sign * c0[j]
        vl, cj = I_L_p[j], c0[j]
        q_a, q_b = q_ptr[yy], q_ptr[yy + 1]
        if stamp[yy] == gen:  # the same window, one column further right: step on
            k = cursor[yy]
            while k < q_b and q_col[k] < xa - d_hi:
                k += 1
        else:
            k = q_a + np.searchsorted(q_col[q_a:q_b], xa - d_hi)  # first q with d <= d_hi
            stamp[yy] = gen
        cursor[yy] = k
        while k < q_b and q_col[k] <= xa - d_from:  # d >= d_from
            dk = xa - q_col[k]  # a run of adjacent columns: consecutive disparities from dk down
            e = min(q_run[k], k + dk - d_from + 1)
            # d = dk - i takes q_val[k + i] = q_rev[nq - 1 - k - i]: both read forwards on
            # slices (indices from 0, no wraparound test), so the loop vectorises; each d once,
            # the same sum in the same order per d
            a = acc[dk - (e - k) + 1 : dk + 1]
            b = q_rev[nq - e : nq - k]
            for i in range(e - k):
                a[i] += sign * ((vl - b[i]) ** 2 - cj)
            k = e


@helper(inline="always")
def _fill_best_two(row, base, acc, d_from, d_lo, gap):  # noqa: ANN001
    """Write one pixel's curve row[d] = base + acc[d] (float32, d = d_from..d_hi) and apply
    Eq. (3) to it: d_min = argmin over [d_lo, d_hi]; d_next = argmin over |d - d_min| > gap
    (first index on ties, as np.argmin); E_next = inf when no such d exists."""
    m = row.size
    r_s, a_s = row[d_from:], acc[d_from:]
    for t in range(m - d_from):  # one vectorised pass
        r_s[t] = base + a_s[t]
    best, vb = _first_min(row, d_lo, m)
    if best < 0 or row[d_lo] != row[d_lo]:  # nothing below inf, or a NaN first: a scan from
        best, vb = d_lo, row[d_lo]  # row[d_lo] keeps it
    nxt, vn = _first_min(row, d_lo, max(d_lo, best - gap))
    n2, v2 = _first_min(row, best + gap + 1, m)
    if n2 >= 0 and (nxt < 0 or v2 < vn):  # the lower range wins ties: the first index
        nxt, vn = n2, v2
    if nxt < 0:
        return best, (d_lo if best - d_lo > gap else m - 1), float(vb), np.inf
    return best, nxt, float(vb), float(vn)


@helper(inline="always")
def _first_min(v, lo, hi):  # noqa: ANN001
    """What the scan ``i, x = -1, inf; for t in lo..hi-1: if v[t] < x: i, x = t, v[t]`` finds:
    the first index of the least value below inf, NaN skipped (-1, inf when none). Eight
    running minima over interleaved elements (they vectorise; one running minimum with its
    index does not), then the first element equal to their least (-0.0 == 0.0: the first of
    either, as the scan)."""
    n = hi - lo
    inf = np.float32(np.inf)
    if n <= 0:
        return -1, inf
    s = v[lo:hi]
    m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = inf
    for b in range(n >> 3):
        o = b << 3
        x0, x1, x2, x3 = s[o], s[o + 1], s[o + 2], s[o + 3]
        x4, x5, x6, x7 = s[o + 4], s[o + 5], s[o + 6], s[o + 7]
        m0 = x0 if x0 < m0 else m0
        m1 = x1 if x1 < m1 else m1
        m2 = x2 if x2 < m2 else m2
        m3 = x3 if x3 < m3 else m3
        m4 = x4 if x4 < m4 else m4
        m5 = x5 if x5 < m5 else m5
        m6 = x6 if x6 < m6 else m6
        m7 = x7 if x7 < m7 else m7
    for t in range((n >> 3) << 3, n):
        m0 = s[t] if s[t] < m0 else m0
    for x in (m1, m2, m3, m4, m5, m6, m7):
        m0 = x if x < m0 else m0
    if not m0 < inf:
        return -1, inf
    for t in range(n):
        if s[t] == m0:
            return lo + t, s[t]
    return -1, inf  # not reached: m0 is one of s


@kernel(
    "Tuple((float64[::1], float64[::1], float64[::1], float64[::1], float64[::1]))"
    "(int64[::1], int64[::1], float64[::1], int32[:, ::1], int64, float32[:, ::1], "
    "int64, int64, int64[::1], int64, float64)"
)
def _subpixel_kernel(ry, rx, I_L_p, index, r, I_R, y0, x0, d_min, d_hi, lift):  # noqa: ANN001
    """Exact minimiser of Eq. (2) on [d_min - 1, d_min + 1], I_R linearly interpolated.

    Returns, per pixel: the step from d_min, px; the cost's curvature sum(dI_R/dd)^2 (the mean
    of the two one-sided ones), grey^2/px^2; the energy at the minimum, grey^2; the number of
    window pixels |g_p|; and tan^2 of the thread's angle to the rows, sum(I_x^2) / sum(I_y^2)
    of I_R's central differences at the match (inf without vertical structure)."""
    n = ry.size
    h, w = index.shape
    H, W = I_R.shape
    out = np.zeros(n)
    curv = np.zeros(n)
    resid = np.zeros(n)
    count = np.zeros(n)
    tan2 = np.zeros(n)
    for i in range(n):
        yi, xi, di = ry[i], rx[i], d_min[i]
        E0 = 0.0
        cnt = 0
        gxx = gyy = 0.0
        ce_p = ee_p = ce_m = ee_m = 0.0
        for yy in range(max(0, yi - r), min(h, yi + r + 1)):
            for xx in range(max(0, xi - r), min(w, xi + r + 1)):
                j = index[yy, xx]
                if j < 0:
                    continue
                xb = xx + x0 - di
                row = yy + y0
                a = float(I_R[row, xb]) if 0 <= xb < W else lift
                c = I_L_p[j] - a
                E0 += c * c
                cnt += 1
                ap = float(I_R[row, xb - 1]) if 0 <= xb - 1 < W else lift  # d_min + 1
                am = float(I_R[row, xb + 1]) if 0 <= xb + 1 < W else lift  # d_min - 1
                up = float(I_R[row - 1, xb]) if 0 <= xb < W and row >= 1 else lift
                dn = float(I_R[row + 1, xb]) if 0 <= xb < W and row + 1 < H else lift
                gxx += 0.25 * (ap - am) ** 2
                gyy += 0.25 * (dn - up) ** 2
                ep, em = ap - a, am - a
                ce_p += c * ep
                ee_p += ep * ep
                ce_m += c * em
                ee_m += em * em
        best_t, best_E = 0.0, E0
        for sign in (1, -1):  # towards d_min + 1 and d_min - 1
            ce, ee = (ce_p, ee_p) if sign == 1 else (ce_m, ee_m)
            t = min(max(ce / ee, 0.0), 1.0) if ee > 0 else 0.0
            if not (0 <= di + sign <= d_hi):
                t = 0.0
            E_t = E0 - 2 * t * ce + t * t * ee
            if E_t < best_E - 1e-9:
                best_t, best_E = sign * t, E_t
            best_E = min(E_t, best_E)
        out[i] = best_t
        curv[i] = 0.5 * (ee_p + ee_m)
        resid[i] = best_E
        count[i] = cnt
        tan2[i] = gxx / gyy if gyy > 0 else np.inf
    return out, curv, resid, count, tan2


@kernel(
    "Tuple((int64[::1], int64[::1], int32[:, ::1], float64[::1], int64[::1], int64[::1], "
    "float64[::1], int64[::1]))(boolean[:, ::1], float32[:, :], float32[:, :], int64, int64, "
    "int64, int64, int64, float64)"
)
def _box_kernel(P_L, I_L, I_R, y0, x0, y1, x1, xr0, lift):  # noqa: ANN001
    """The arrays of :class:`_Box` for the box rows ``y0..y1``, columns ``x0..x1`` of P_L:
    its pixels in row-major order (``ry``, ``rx`` in the box; ``index``; I_L there as float64)
    and the right pixels off ``lift`` in columns ``xr0..x1`` of those rows (CSR by row,
    absolute columns ascending, I_R as float64; each one's end of its run of adjacent
    columns). The same arrays as the numpy form (nonzero, searchsorted, a diff of columns)."""
    h, w = y1 - y0, x1 - x0
    index = np.full((h, w), -1, dtype=np.int32)
    n = 0
    for y in range(h):  # counts without branches (vectorised), on row slices
        row = P_L[y0 + y, x0:x1]
        for x in range(w):
            n += row[x]
    ry = np.empty(n, dtype=np.int64)
    rx = np.empty(n, dtype=np.int64)
    I_L_p = np.empty(n)
    k = 0
    for y in range(h):
        row = P_L[y0 + y, x0:x1]
        for x in range(w):
            if row[x]:
                ry[k] = y
                rx[k] = x
                index[y, x] = k
                I_L_p[k] = I_L[y0 + y, x0 + x]
                k += 1
    lift32 = np.float32(lift)  # the float32 comparison of the numpy form
    q_ptr = np.zeros(h + 1, dtype=np.int64)
    for y in range(h):
        c = 0
        row_r = I_R[y0 + y, xr0:x1]
        for x in range(x1 - xr0):
            c += row_r[x] != lift32
        q_ptr[y + 1] = q_ptr[y] + c
    m = q_ptr[h]
    q_col = np.empty(m, dtype=np.int64)
    q_val = np.empty(m)
    q_run = np.empty(m, dtype=np.int64)
    k = 0
    for y in range(h):
        row_r = I_R[y0 + y, xr0:x1]
        for x in range(x1 - xr0):
            v = row_r[x]
            if v != lift32:
                q_col[k] = x + xr0
                q_val[k] = v
                k += 1
    for y in range(h):  # runs never cross rows: each row's last pixel ends its run
        end = q_ptr[y + 1]
        for j in range(q_ptr[y + 1] - 1, q_ptr[y] - 1, -1):
            if j + 1 < q_ptr[y + 1] and q_col[j + 1] != q_col[j] + 1:
                end = j + 1
            q_run[j] = end
    return ry, rx, index, I_L_p, q_ptr, q_col, q_val, q_run


@kernel("Tuple((int64[::1], int64[::1]))(int32[:, ::1], int64[::1], boolean[::1])")
def _free_pairs_kernel(index, at, free):  # noqa: ANN001
    """The index pairs (a, b) of 8-connected pixels of P_L in the box image ``index`` (each
    once: the right, lower-left, lower and lower-right neighbour of each pixel; ``at``: their
    flat box positions) of which ``free[a]`` or ``free[b]`` holds, per direction in that order
    and row-major within each."""
    h, w = index.shape
    dirs = ((0, 1), (1, -1), (1, 0), (1, 1))
    n = at.size
    a = np.empty(4 * n, dtype=np.int64)
    b = np.empty(4 * n, dtype=np.int64)
    m = 0
    for dy, dx in dirs:
        for i in range(n):
            y, x = at[i] // w + dy, at[i] % w + dx
            if y < h and 0 <= x < w:
                j = index[y, x]
                if j >= 0 and (free[i] or free[j]):
                    a[m], b[m] = i, j
                    m += 1
    return a[:m].copy(), b[:m].copy()


@kernel("Tuple((int64[::1], int64[::1]))(int32[:, ::1], int64[::1], int64[::1])")
def _free_pattern_kernel(index, at, pos):  # noqa: ANN001
    """CSR (indptr, indices) of the symmetric 8-neighbour pattern among the free pixels, in
    their order (``at``: their flat box positions, row-major; ``pos``: each pixel's place among
    them, -1 if not free), columns ascending in each row: the canonical form that
    ``(P + P.T).tocsr()`` of the pairs gives, whose column order reverse Cuthill-McKee's ties
    follow. Neighbours visited in row-major order come in ascending order."""
    h, w = index.shape
    m = at.size
    indptr = np.zeros(m + 1, dtype=np.int64)
    indices = np.empty(8 * m, dtype=np.int64)
    k = 0
    for r in range(m):
        y, x = at[r] // w, at[r] % w
        for yy in range(y - 1, y + 2):
            for xx in range(x - 1, x + 2):
                if (yy != y or xx != x) and 0 <= yy < h and 0 <= xx < w:
                    j = index[yy, xx]
                    if j >= 0 and pos[j] >= 0:
                        indices[k] = pos[j]
                        k += 1
        indptr[r + 1] = k
    return indptr, indices[:k].copy()


@kernel("float64[::1](int32[:, ::1], float64[::1], int64[::1])")
def _local_median_kernel(index, values, pos):  # noqa: ANN001
    """Median of ``values`` over the 3 x 3 neighbourhood in P_L of each box position ``pos``
    (flat, row-major), NaN values left out (NaN when none is left): the mean of the two middle
    order statistics, 0.5 (a + b), as np.median takes them."""
    h, w = index.shape
    out = np.empty(pos.size)
    buf = np.empty(9)
    for i in range(pos.size):
        y, x = pos[i] // w, pos[i] % w
        n = 0
        for yy in range(y - 1, y + 2):
            for xx in range(x - 1, x + 2):
                if 0 <= yy < h and 0 <= xx < w and index[yy, xx] >= 0:
                    v = values[index[yy, xx]]
                    if not math.isnan(v):
                        k = n  # insertion sort as the values come
                        while k > 0 and buf[k - 1] > v:
                            buf[k] = buf[k - 1]
                            k -= 1
                        buf[k] = v
                        n += 1
        out[i] = 0.5 * (buf[(n - 1) // 2] + buf[n // 2]) if n > 0 else np.nan
    return out
