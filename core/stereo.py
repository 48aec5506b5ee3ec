"""SSD stereo matching on lifted images, Eqs. (2)-(3), and depth via Q, Eqs. (4)-(5).

For every segmented left pixel p the energy curve E(d, p), d = 0..alpha, is the sum over the
segmented pixels p' of a window around p (g_p, a subset of P_L) of the squared difference
between I_L^lift(p') and I_R^lift(p' - (d, 0)). Vectorised: the per-pixel squared differences
C(p', d) form an (N, alpha+1) array, and the window sum is one sparse (N, N) matrix product.

Deviation (``subpixel=True``, default): the integer argmin d_min is refined to the exact
minimiser of the same energy with the right image linearly interpolated between integer
disparities (closed form on [d_min-1, d_min] and [d_min, d_min+1]). With a 1 mm baseline one
pixel of disparity is about 7-11 mm of depth, so integer disparities cannot reach millimetre
accuracy. ``subpixel=False`` gives the paper's integer disparities.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from core.calibration import StereoCalibration
from core.params import Params, param
from core.segmentation import LIFT_VALUE, LiftedPair

NEXT_GAP = 2  # Eq. (6) text: |d_next - d_min| > 2, neighbours of d_min have similar energies


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

    def _check(self) -> None:
        super()._check()
        if self.window % 2 == 0:
            raise ValueError("stereo.window must be odd")


@dataclass(frozen=True)
class StereoResult:
    """Per segmented left pixel (N of them, in row-major order of P_L).

    ``pixels``: (N, 2) int, (x, y) = (col, row) of p.
    ``energy``: (N, alpha+1) float32, E(d, p) of Eq. (2).
    ``d_min``, ``d_next``: (N,) int, best and second-best disparity (|d_next - d_min| > 2).
    ``E_min``, ``E_next``: (N,) float, their energies.
    ``disparity``: (N,) float, d_min refined to sub-pixel precision (or d_min), px.
    ``points``: (N, 3) float, Eq. (4)-(5) reprojection (X, Y, Z) in the left camera frame,
    calibration units; NaN where the disparity is not positive.
    ``depth``: (N,) float, D(p) = Z, Eq. (5).
    """

    pixels: np.ndarray
    energy: np.ndarray
    d_min: np.ndarray
    d_next: np.ndarray
    E_min: np.ndarray
    E_next: np.ndarray
    disparity: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    shape: tuple[int, int]

    @property
    def index_image(self) -> np.ndarray:
        """(H, W) int image: index into the per-pixel arrays, -1 off P_L."""
        idx = np.full(self.shape, -1, dtype=np.int64)
        idx[self.pixels[:, 1], self.pixels[:, 0]] = np.arange(len(self.pixels))
        return idx


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
    rows, cols = np.nonzero(lifted.P_L)
    n = rows.size
    if n == 0:
        raise ValueError("empty segmentation: no thread pixel in the left image")
    d = np.arange(p.alpha + 1)

    # Right image padded with the lift value so that p'_x - d < 0 reads background.
    pad = p.alpha + 1
    I_R = np.full((H, W + pad + 1), LIFT_VALUE, dtype=np.float32)
    I_R[:, pad : pad + W] = lifted.I_R
    I_L_p = lifted.I_L[rows, cols]
    right = I_R[rows[:, None], cols[:, None] + pad - d[None, :]]  # (N, alpha+1)
    C = (I_L_p[:, None] - right) ** 2

    A = _window_matrix(rows, cols, (H, W), p.window)
    energy = np.asarray(A @ C, dtype=np.float32)  # Eq. (2)

    d_min = np.argmin(energy, axis=1)  # Eq. (3)
    E_min = energy[np.arange(n), d_min].astype(np.float64)
    far = np.abs(d[None, :] - d_min[:, None]) > NEXT_GAP
    masked = np.where(far, energy, np.inf)
    d_next = np.argmin(masked, axis=1)
    E_next = masked[np.arange(n), d_next].astype(np.float64)

    disparity = d_min.astype(np.float64)
    if p.subpixel:
        disparity = disparity + _subpixel_offset(A, rows, cols, I_L_p, I_R, pad, d_min, p.alpha)

    points = _reproject(cols, rows, disparity, calib.Q)
    return StereoResult(
        pixels=np.stack([cols, rows], axis=1),
        energy=energy,
        d_min=d_min,
        d_next=d_next,
        E_min=E_min,
        E_next=E_next,
        disparity=disparity,
        points=points,
        depth=points[:, 2],
        shape=(H, W),
    )


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


def _window_matrix(
    rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int], window: int
) -> sp.csr_matrix:
    """(N, N) 0/1 matrix: A[i, j] = 1 when segmented pixel j lies in the window g_i of pixel i."""
    H, W = shape
    r = window // 2
    idx = np.full((H + 2 * r, W + 2 * r), -1, dtype=np.int64)
    n = rows.size
    idx[rows + r, cols + r] = np.arange(n)
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    nb = idx[rows[:, None] + r + dy.ravel()[None, :], cols[:, None] + r + dx.ravel()[None, :]]
    i = np.repeat(np.arange(n), nb.shape[1])
    j = nb.ravel()
    ok = j >= 0
    return sp.csr_matrix((np.ones(ok.sum(), dtype=np.float32), (i[ok], j[ok])), shape=(n, n))


def _subpixel_offset(
    A: sp.csr_matrix,
    rows: np.ndarray,
    cols: np.ndarray,
    I_L_p: np.ndarray,
    I_R: np.ndarray,
    pad: int,
    d_min: np.ndarray,
    alpha: int,
) -> np.ndarray:
    """Exact minimiser of Eq. (2) on [d_min - 1, d_min + 1], I_R linearly interpolated."""
    coo = A.tocoo()
    i, j = coo.row, coo.col
    n = d_min.size
    di = d_min[i]
    base = cols[j] + pad - di
    a = I_R[rows[j], base]  # I_R at disparity d_min
    c = (I_L_p[j] - a).astype(np.float64)
    best_t = np.zeros(n)
    E0 = np.bincount(i, weights=c * c, minlength=n)
    best_E = E0.copy()
    for sign in (1, -1):  # towards d_min + 1 and d_min - 1
        e = (I_R[rows[j], base - sign] - a).astype(np.float64)
        ce = np.bincount(i, weights=c * e, minlength=n)
        ee = np.bincount(i, weights=e * e, minlength=n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip(np.where(ee > 0, ce / ee, 0.0), 0.0, 1.0)
        ok = (d_min + sign >= 0) & (d_min + sign <= alpha)
        t = np.where(ok, t, 0.0)
        E_t = E0 - 2 * t * ce + t * t * ee
        better = E_t < best_E - 1e-9
        best_t = np.where(better, sign * t, best_t)
        best_E = np.minimum(E_t, best_E)
    return best_t
