"""The depth of the thread's ends from both views (issue 12, deviation 23).

The end of a thread is a point both cameras see: in the rectified pair it lies on the same row
in both images, and its column in each view fixes its disparity. Near the end the thread often
runs along the image rows, where the SSD of Eq. (2) on a window *inside* the thread is
ambiguous (every shift along the thread looks alike) and the paper's endpoint extension copies
the end keypoint's depth to the tip; a window that holds the tip itself is not ambiguous: only
one shift lays the left tip onto the right one.

:func:`tip_disparity` matches a square window centred on the end of the ordered path (the
extension's tip pixel, or the end keypoint) between the lifted images of Eq. (1) and returns the
sub-pixel disparity with its variance from the SSD curve's residual and curvature (the
Gauss-Newton variance of a least-squares shift). :func:`fuse_end` weighs it against Eq. (7)'s
window line extrapolated to the end (its own variance from the fit's residuals): the line wins
where the tip's match is poor (a tip the right view does not show), the tip where depth curves
inside the window (the line is then biased and its residuals large).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from threadrecon.core import walk_kernel

ROW_SLACK = 1  # px: rows of the two views may differ by this (a real rig's rectification)
QUANT_VAR = 1.0 / 12.0  # px^2: variance of a pixel-quantised position, the tip's floor


@dataclass(frozen=True)
class TipMatch:
    """Disparity of one end of the thread from a window on its tip, px."""

    disparity: float
    """Sub-pixel disparity of the tip, px (NaN when no match)."""
    var: float
    """Its variance, px^2 (inf when no match)."""


NO_MATCH = TipMatch(float("nan"), float("inf"))


def tip_disparity(
    I_L: np.ndarray,
    I_R: np.ndarray,
    tip_xy: np.ndarray,
    d_ref: float,
    radius: int,
    reach: float = 0.0,
) -> TipMatch:
    """Match the (2 radius + 1)^2 window of ``I_L`` centred on ``tip_xy`` (x, y px) along its
    row in ``I_R`` over disparities ``d_ref`` +- ``radius`` px (SSD, mean over the window), on
    the row itself or one above or below, whichever matches best (``ROW_SLACK``: on the
    development split's real frames the right view's thread lies a row higher than the left's,
    and a thread running along the rows then matches at a wrong shift).

    ``reach`` > 0 (deviation 55): the tip of a dead end along the rows lies at a disparity of
    its own, which the end keypoint's ``d_ref`` (copied along the dead end) may miss by more
    than ``radius``: the search is cut to the shifts whose right window lies inside the right
    image (a tip near the left border), and where its best shift lies on the edge of
    ``d_ref`` +- ``radius`` (the SSD still falling outwards), the SSD's descent is followed
    outwards to its minimum as long as that lies within ``radius`` + ``reach`` px of ``d_ref``
    (``reach``: how far the thread's disparity may change between the end keypoint and the
    tip). ``reach`` = 0 is deviation 23's search.

    ``I_L``, ``I_R``: (H, W) lifted images of Eq. (1). No match (:data:`NO_MATCH`) when the
    window leaves either image (a thread that leaves the view has no tip there), when the best
    shift lies on the edge of the search, or when the SSD curve is flat (nothing in the window
    fixes the shift)."""
    if I_L.shape != I_R.shape or I_L.ndim != 2:
        raise ValueError(f"tip_disparity needs two (H, W) images, got {I_L.shape}, {I_R.shape}")
    if radius < 1 or not np.isfinite(d_ref) or not reach >= 0:
        return NO_MATCH
    H, W = I_L.shape
    x, y = int(round(float(tip_xy[0]))), int(round(float(tip_xy[1])))
    d0 = int(round(d_ref))
    if (
        y - radius - ROW_SLACK < 0
        or y + radius + ROW_SLACK >= H
        or x - radius < 0
        or x + radius >= W
    ):
        return NO_MATCH
    extra = int(np.floor(reach))
    lo, hi = d0 - radius - extra, d0 + radius + extra  # shifts searched, inclusive
    if extra > 0:  # only shifts whose right window lies inside the right image
        lo, hi = max(lo, x + radius - W + 1), min(hi, x - radius)
        if hi - lo < 2:
            return NO_MATCH
    elif x - radius - d0 - radius < 0 or x + radius - d0 + radius >= W:
        return NO_MATCH
    A = I_L[y - radius : y + radius + 1, x - radius : x + radius + 1].astype(np.float64)
    # shift d = lo + k lays the window on right columns x - radius - d + (0..n-1), on the row
    # itself or ROW_SLACK above or below: every cost of the three rows at once
    rows = slice(y - ROW_SLACK - radius, y + ROW_SLACK + radius + 1)
    strip = I_R[rows, x - radius - hi : x + radius - lo + 1].astype(np.float64)
    costs = walk_kernel.tip_costs(np.ascontiguousarray(A), strip, radius, ROW_SLACK, hi - lo + 1)
    best: tuple[float, int, np.ndarray] | None = None
    inner = slice(max(d0 - radius, lo) - lo, min(d0 + radius, hi) - lo + 1)
    if inner.start >= inner.stop:
        return NO_MATCH
    for cost in costs:  # rows y - ROW_SLACK .. y + ROW_SLACK: a handful of items
        i = inner.start + int(np.argmin(cost[inner]))
        if extra > 0:  # follow the descent outwards from the inner search's edge
            while i > 0 and cost[i - 1] < cost[i]:
                i -= 1
            while i < len(cost) - 1 and cost[i + 1] < cost[i]:
                i += 1
        if best is None or cost[i] < best[0]:
            best = (float(cost[i]), i, cost)
    assert best is not None
    _, i, cost = best
    if i == 0 or i == len(cost) - 1:
        return NO_MATCH
    c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
    curv = c0 - 2.0 * c1 + c2  # = 2 G / N, G = sum of squared gradients (per-pixel mean)
    if not curv > 0:
        return NO_MATCH
    off = 0.5 * (c0 - c2) / curv
    # Least-squares shift: var = sigma^2 / G with sigma^2 the residual per pixel (c1), plus
    # the quantisation of the tip's pixels (a noise-free render still ends on a pixel).
    var = 2.0 * c1 / (A.size * curv) + QUANT_VAR
    return TipMatch(float(lo + i + off), float(var))


def seen_in_right(px: np.ndarray, P_R: np.ndarray, d_ref: float, tol: int) -> np.ndarray:
    """(N,) bool: left-view pixels ``px`` ((N, 2) int x, y) that the right view's thread mask
    ``P_R`` shows too: a thread pixel on the same row (+- ``ROW_SLACK``) within ``tol`` px of
    the column ``x - d_ref``. A tip pixel without one is a part of the thread only the left view
    sees (hidden or cut differently in the right): its depth has no second view."""
    px = np.asarray(px, dtype=np.int64).reshape(-1, 2)
    out = np.zeros(len(px), dtype=bool)
    if not len(px) or not np.isfinite(d_ref) or tol < 0:
        return out
    centre = np.rint(px[:, 0] - d_ref).astype(np.int64)
    return walk_kernel.row_hits(
        centre, np.ascontiguousarray(px[:, 1]), np.asarray(P_R, dtype=bool), tol, ROW_SLACK
    )


def fuse_end(z_line: float, var_line: float, z_tip: float, var_tip: float) -> tuple[float, float]:
    """Inverse-variance mean of the window line's end value and the tip's depth (both in the
    same depth unit, variances in that unit squared); the line alone when the tip has none."""
    if not (np.isfinite(z_tip) and np.isfinite(var_tip) and var_tip > 0):
        return z_line, var_line
    if not (np.isfinite(var_line) and var_line > 0):
        return (z_line, var_line) if np.isfinite(var_line) else (z_tip, var_tip)
    w_l, w_t = 1.0 / var_line, 1.0 / var_tip
    return (w_l * z_line + w_t * z_tip) / (w_l + w_t), 1.0 / (w_l + w_t)
