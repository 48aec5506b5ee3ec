"""The check's look at the reliable matches right next to the curve: depth they contradict.

A curve point is *contradicted* when reliable pixels of P_L^R lie within ``near_px`` of its
left projection and none of them agrees with the curve's disparity within ``tol_px``: the
images measure another depth there (a wrong branch at a crossing runs at one strand's depth
over the other strand's pixels, or between them). The reliable pixels are kept by rows with
their disparities (``reliable_rows``), built once per stereo result (``check_field.derived``)
and shared with the check's disparity residual; each curve point reads the rows of the
(2 near_px + 1)^2 window around it.
"""

from __future__ import annotations

import numpy as np

from threadrecon.core.check_fast_kernel import contested_runs, rows_contradicted
from threadrecon.core.check_field import derived
from threadrecon.core.refine import row_runs
from threadrecon.core.reliability import ReliabilityResult
from threadrecon.core.stereo import StereoResult


def contradicted(
    stereo: StereoResult,
    rel: ReliabilityResult,
    uv_l: np.ndarray,
    disp_curve: np.ndarray,
    near_px: int,
    tol_px: float,
) -> np.ndarray:
    """(N,) bool: reliable pixels lie within ``near_px`` (a square window) of the curve point
    ``uv_l`` (N, 2) (x, y) left px, and none has a disparity within ``tol_px`` of
    ``disp_curve`` (N,) px."""
    uv_l = np.asarray(uv_l, dtype=np.float64)
    if uv_l.ndim != 2 or uv_l.shape[1] != 2 or len(disp_curve) != len(uv_l):
        raise ValueError(f"uv_l must be (N, 2) with N disparities, got {uv_l.shape}")
    xs, row_ptr, y0, disp_rel = reliable_rows(stereo, rel)
    n = len(uv_l)
    if xs.size == 0 or n == 0:
        return np.zeros(n, dtype=bool)
    ok = np.isfinite(uv_l).all(axis=1) & np.isfinite(disp_curve)
    q = np.rint(np.where(ok[:, None], uv_l, -1e6)).astype(np.int64)
    disp = np.ascontiguousarray(disp_curve, dtype=np.float64)
    # compiled: each point's window read from the rows (no image of the reliable pixels' box)
    return rows_contradicted(xs, row_ptr, y0, disp_rel, q, ok, disp, int(near_px), float(tol_px))


def reliable_rows(
    stereo: StereoResult, rel: ReliabilityResult
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """The reliable pixels P_L^R by rows (CSR: x ascending per row, ``row_ptr`` from row
    ``y0``) and their disparities, cached per stereo result."""
    return derived(
        (stereo.pixels, stereo.disparity, rel.reliable), "reliable_rows",
        lambda: _rows(stereo, rel),
    )  # fmt: skip


def _rows(
    stereo: StereoResult, rel: ReliabilityResult
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    sel = np.flatnonzero(rel.reliable)
    if sel.size == 0:
        return np.zeros(0, np.int64), np.zeros(1, np.int64), 0, np.zeros(0)
    xs = stereo.pixels[sel, 0].astype(np.int64)
    ys = stereo.pixels[sel, 1].astype(np.int64)
    disp = np.asarray(stereo.disparity, dtype=np.float64)[sel]
    key = ys * (int(xs.max()) + 1) + xs
    if np.any(np.diff(key) < 0):  # P_L comes in raster order; sort otherwise
        order = np.argsort(key, kind="stable")
        xs, ys, disp = xs[order], ys[order], disp[order]
    y0 = int(ys[0])
    row_ptr = np.searchsorted(ys, np.arange(y0, int(ys[-1]) + 2)).astype(np.int64)
    return xs, row_ptr, y0, np.ascontiguousarray(disp)


def contested(
    stereo: StereoResult, rel: ReliabilityResult, P_R: np.ndarray, slack_px: float
) -> np.ndarray:
    """(N,) bool over the pixels of P_L: reliable matches that share one strand of the right
    view with another reliable match of their row lying farther from them in the left view
    than that strand is wide plus ``slack_px``.

    A strand's row run in the right view holds the pixels of one strand (one right run is as
    wide as the left one, less the disparity change across it). Two left pixels of a row more
    than the right run's width apart, both matched into it, cannot both be seen there: the
    right view shows one strand where the left shows two side by side (a distractor's piece
    next to the thread matched the thread's right pixels at a larger disparity), or one of the
    two lies behind the other in the right view. Either way one of the two matches is not an
    observation, and the images do not tell which: neither measures the depth. The right run
    of a match is the one holding its right position x - d, or a pixel next to it (the run's
    sub-pixel edge)."""
    return derived(
        (stereo.pixels, stereo.disparity, rel.reliable, P_R),
        f"contested {slack_px:g}",
        lambda: _contested(stereo, rel, P_R, slack_px),
    )  # fmt: skip  (read-only: cached while the stereo result and P_R live)


def uncontested(
    stereo: StereoResult, rel: ReliabilityResult, P_R: np.ndarray, slack_px: float
) -> np.ndarray | None:
    """``rel.reliable`` less the ``contested`` matches (read-only), or None when no match is
    contested. Cached with the stereo result and P_R like ``contested``: every run of the
    check then passes one array on, and ``reliable_rows`` built from it is cached too (a new
    array per run was a cache miss each time, and an LRU entry that pushed others out)."""
    return derived(
        (stereo.pixels, stereo.disparity, rel.reliable, P_R),
        f"uncontested {slack_px:g}",
        lambda: _uncontested(stereo, rel, P_R, slack_px),
    )  # fmt: skip


def _uncontested(
    stereo: StereoResult, rel: ReliabilityResult, P_R: np.ndarray, slack_px: float
) -> np.ndarray | None:
    clash = _contested(stereo, rel, P_R, slack_px)
    if not clash.any():
        return None  # (not rel.reliable itself: the cache holds its owners weakly)
    kept = rel.reliable & ~clash
    kept.setflags(write=False)
    return kept


def _contested(
    stereo: StereoResult, rel: ReliabilityResult, P_R: np.ndarray, slack_px: float
) -> np.ndarray:
    out = np.zeros(len(stereo.pixels), dtype=bool)
    sel = np.flatnonzero(rel.reliable)
    if sel.size >= 2:
        H, W = P_R.shape
        x = stereo.pixels[sel, 0].astype(np.int64)
        y = stereo.pixels[sel, 1].astype(np.int64)
        xr = np.rint(x - np.asarray(stereo.disparity, dtype=np.float64)[sel])
        # P_R's runs (row, first and last column, row-major; cached with P_R, the refine
        # stage reads them too); compiled: each match's run and the matches' spread per run
        row, first, last = row_runs(P_R)
        out[sel] = contested_runs(x, y, xr, row, first, last, H, W, float(slack_px))
    out.setflags(write=False)  # the cached value is shared
    return out
