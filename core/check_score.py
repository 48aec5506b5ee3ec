"""The check stage's per-point confidence, grasp point and automatic quality score.

Per-point confidence (core/check.py's module docstring gives the formula): each point i of the
dense curve gets an expected 3D error e_i from the evidence near it, and the confidence
exp(-e_i / ``conf_mm``). The grasp point is the most confident point near ``grasp_mm`` from the
free end; the score rates the curve on the paper's 1-5 scale (Sec. IV-B) from the typical e_i
(their geometric mean, or the error of the curve's mean confidence: ``score_average``), capped
by the check's status: a continuous rating, and the integer class it rounds to (for a person's
1-5 ratings).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from threadrecon.core.bounds import Bounds
from threadrecon.core.numeric import arc_px, row_norms
from threadrecon.core.spline import SplineResult

if TYPE_CHECKING:
    from threadrecon.core.check import CheckParams, Status

# A curve point inside a thread pixel's cell reads up to half its diagonal from the pixel's
# centre (the distance field's value there): pixel quantisation, not a reprojection error.
PIXEL_HALF_DIAGONAL = math.sqrt(0.5)


@dataclass(frozen=True)
class GraspPoint:
    """``point``: (3,) left camera frame, calib units; ``tangent``: (3,) unit vector along the
    curve (start -> end); ``index`` into ``CameraCurve.points``; ``confidence`` in [0, 1];
    ``from_end``: "start" or "end", the end taken as free; ``distance``: arc length to it."""

    point: np.ndarray
    confidence: float
    tangent: np.ndarray
    index: int
    from_end: str
    distance: float


@dataclass(frozen=True)
class PointErrors:
    """Per point of the dense curve, (N,) each: ``e_mm`` the expected error e_i (mm, inf
    behind a camera), ``lateral_mm`` its lateral part (reprojection distance and bridges, mm)
    and ``confidence`` exp(-e_i / conf_mm) in [0, 1]."""

    e_mm: np.ndarray
    lateral_mm: np.ndarray
    confidence: np.ndarray


def point_errors(
    z_pos: np.ndarray,
    behind: np.ndarray,
    r: np.ndarray,
    rho: np.ndarray,
    bridge_gap: np.ndarray,
    step: np.ndarray,
    s3: np.ndarray,
    spline: SplineResult,
    f: float,
    fB: float,
    mm: float,
    p: CheckParams,
    s2: np.ndarray | None = None,
    supported: np.ndarray | None = None,
) -> PointErrors:
    """The expected error e_i and confidence of each curve point (core/check.py's docstring).

    ``z_pos``: (N,) depths (calib units, clipped above 0); ``behind``: (N,) bool, behind a
    camera; ``r``: (N,) disparity residuals (px); ``rho``: (N,) reprojection distance (px, 0
    where the view does not count); ``bridge_gap``: (N,) mm into a bridge; ``step``: (N-1,) px
    steps of the left projection; ``s3``: (N,) arc length (mm); ``f``, ``fB`` in px and
    px * calib units; ``mm``: mm per calib unit; ``s2``: ``arc_px(step)`` and ``supported``:
    ``r <= p.support_tol_px`` when the caller has them.
    """
    rho = np.maximum(rho - PIXEL_HALF_DIAGONAL, 0.0)  # inside a thread pixel's cell: on it
    lateral = z_pos / f * rho * mm + p.bridge_error * bridge_gap  # bridges: interpolated
    e_mm = _expected_error(z_pos, r, step, s3, spline, fB, p, s2)
    # unsupported stretches are interpolated like a bridge: drift from the nearest supported point
    if supported is None:
        supported = r <= p.support_tol_px
    drift = p.bridge_error * np.maximum(bridge_gap, _unsupported_gap(s3, supported))
    e_mm = e_mm * mm + z_pos / f * rho * mm + drift
    e_mm[behind] = np.inf
    conf = np.exp(-e_mm / p.conf_mm)
    return PointErrors(e_mm=e_mm, lateral_mm=lateral, confidence=conf)


def _expected_error(
    z: np.ndarray,
    r: np.ndarray,
    step: np.ndarray,
    s3: np.ndarray,
    spline: SplineResult,
    fB: float,
    p: CheckParams,
    s2: np.ndarray | None = None,
) -> np.ndarray:
    """Depth part of the expected error e_i (calib units): the depth size of a pixel of
    disparity z^2 / (f B) times the local disparity error sqrt(sigma_d^2 + rbar_i^2), rbar_i
    the mean residual r of the reliable matches over one knot span of the spline around the
    point (the stretch whose matches the spline averages); doubled at an end of the curve
    (fitted from one side only), falling back over ``end_mm``.

    r counts at most ``support_tol_px``: beyond it no reliable match agrees with the curve and
    the residual says nothing about the curve's error (the nearest match may be another
    strand's, e.g. a spiral's next turn on the same rows, whose depth the spline rightly
    ignored); the depth there is interpolated from the supported points around it, and
    ``point_errors`` adds the drift of that interpolation."""
    n_spans = max(len(spline.ctrl) - int(spline.degree), 1)
    s2 = arc_px(step) if s2 is None else s2
    r_local = _local_mean(np.minimum(r, p.support_tol_px), s2, s2[-1] / n_spans)
    d = np.sqrt(p.sigma_disparity_px**2 + r_local**2)
    end = np.minimum(s3, s3[-1] - s3)  # mm to the nearer end
    return z**2 / fB * d * (1.0 + np.exp(-end / p.end_mm))


def _unsupported_gap(s3: np.ndarray, supported: np.ndarray) -> np.ndarray:
    """Arc length (mm) from each point to the nearest supported point (0 on one; the curve's
    whole length when none is supported)."""
    n = len(s3)
    idx = np.flatnonzero(supported)
    if idx.size == 0:
        return np.full(n, float(s3[-1]) if np.isfinite(s3[-1]) else np.inf)
    k = np.searchsorted(idx, np.arange(n))
    before = np.where(k > 0, s3 - s3[idx[np.maximum(k - 1, 0)]], np.inf)
    after = np.where(k < idx.size, s3[idx[np.minimum(k, idx.size - 1)]] - s3, np.inf)
    return np.minimum(before, after)


def _local_mean(x: np.ndarray, s: np.ndarray, width: float) -> np.ndarray:
    """Mean of x over the samples within width / 2 of each sample along the arc length s."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    lo = np.searchsorted(s, s - 0.5 * width)
    hi = np.searchsorted(s, s + 0.5 * width, side="right")
    return (c[hi] - c[lo]) / np.maximum(hi - lo, 1)


def bound_halfwidth_px(spline: SplineResult, bounds: Bounds, n: int, fB: float) -> np.ndarray:
    """Bound half-width of Eq. (7) at each curve point, in px of disparity (|dd/dz| = fB/z^2)."""
    u = _unit_grid(n)
    uh = spline.u_H / spline.length if spline.length > 0 else np.linspace(0, 1, len(spline.u_H))
    half = np.interp(u, uh, 0.5 * (bounds.upper - bounds.lower))
    centre = np.maximum(np.interp(u, uh, bounds.centre), 1e-12)
    return half * fB / centre**2


@functools.lru_cache(maxsize=8)
def _unit_grid(n: int) -> np.ndarray:
    """``np.linspace(0.0, 1.0, n)``, read-only and kept (the curve's n is the same every run)."""
    u = np.linspace(0.0, 1.0, n)
    u.setflags(write=False)
    return u


def _typical(e_mm: np.ndarray, conf_mm: float, average: str) -> float:
    """The typical expected error of a curve (mm) behind its score.

    "confidence": the error whose confidence is the curve's mean confidence,
    e = -conf_mm ln(mean_i exp(-e_i / conf_mm)). Equal e_i give that e; a point counts by its
    confidence, so a stretch of large or infinite e_i raises e by at most -conf_mm ln(1 - q) for
    its share q of the curve (the score reads the share of the curve a gripper may trust, the
    page's mean confidence), while the small e_i of good stretches rank curves as a mean of e_i
    does (docs/method.md, score19). "geometric": the geometric mean of e_i (1e6 for a
    non-finite one), the default (``CheckParams.score_average``)."""
    if average == "geometric":
        # np.clip's values (NaN stays NaN) without its layers; the log never divides by zero
        return float(np.exp(np.log(np.minimum(np.maximum(e_mm, 1e-9), 1e6)).mean()))
    mean_conf = float(np.mean(np.exp(-np.asarray(e_mm, dtype=np.float64) / conf_mm)))
    return -conf_mm * math.log(mean_conf) if mean_conf > 0.0 else math.inf


def _rating(error_mm: float, status: Status, score_mm: float, step: float) -> float:
    """The continuous rating on the paper's 1-5 scale from the typical expected error:
    4.5 - log_step(error / score_mm), in [1, 5]; a suspect curve at most 2, a failed one 1.
    Rounded, it is the score: 5 below score_mm, each further class a factor ``step`` wider."""
    if status == "failed" or not error_mm < np.inf:
        return 1.0
    with np.errstate(divide="ignore"):
        x = math.log(max(error_mm, 1e-12) / score_mm) / math.log(step)
    rating = min(max(4.5 - x, 1.0), 5.0)
    return min(rating, 2.0) if status == "suspect" else rating


def _score(error_mm: float, status: Status, score_mm: float, step: float) -> int:
    """The paper's 1-5 rating from the typical expected error, capped by the status: 5 below
    score_mm, 4 below step x score_mm, 3 below step^2 x, 2 below step^3 x, else 1."""
    edges = score_mm * step ** np.arange(4.0)
    score = 5 - int(np.searchsorted(edges, error_mm, side="right"))
    if status == "failed":
        return 1
    if status == "suspect":
        return min(score, 2)
    return max(1, score)


def quality_score(e_mm: np.ndarray, status: Status, p: CheckParams) -> tuple[int, float]:
    """The automatic quality score (1-5, the paper's rating scale) of a checked curve and the
    continuous rating behind it (module docstring)."""
    typical = _typical(e_mm, p.conf_mm, p.score_average)
    return (
        _score(typical, status, p.score_mm, p.score_step),
        _rating(typical, status, p.score_mm, p.score_step),
    )


def grasp_point(
    pts: np.ndarray,
    conf: np.ndarray,
    uv_l: np.ndarray,
    uv_r: np.ndarray,
    shape: tuple[int, int],
    mm: float,
    p: CheckParams,
    d3: np.ndarray | None = None,
) -> GraspPoint | None:
    """The most confident point within ``grasp_window_mm`` of ``grasp_mm`` from the free end.
    ``d3``: (N-1,) ``row_norms(pts[1:] - pts[:-1])`` (calib units) when the caller has it."""
    if d3 is None:
        d3 = row_norms(pts[1:] - pts[:-1])  # (np.diff's subtraction)
    s = np.concatenate([[0.0], d3.cumsum()]) * mm
    if not np.isfinite(s[-1]):
        return None
    from_start, from_end = s, s[-1] - s
    lo, hi = p.grasp_mm - p.grasp_window_mm, p.grasp_mm + p.grasp_window_mm
    near = {
        "start": (from_start >= lo) & (from_start <= hi),
        "end": (from_end >= lo) & (from_end <= hi),
    }
    if p.free_end == "auto":
        H, W = shape
        at_border = {}
        for end, i in (("start", 0), ("end", -1)):
            x0, x1, y0, y1 = uv_l[i, 0], uv_r[i, 0], uv_l[i, 1], uv_r[i, 1]
            if x0 == x0 and x1 == x1 and y0 == y0 and y1 == y1:  # no NaN: numpy's min and max
                m = min(min(x0, x1), min(y0, y1), W - 1 - max(x0, x1), H - 1 - max(y0, y1))
            else:  # (of two numbers, without two arrays and four reductions)
                xs, ys = np.array([x0, x1]), np.array([y0, y1])
                m = min(xs.min(), ys.min(), W - 1 - xs.max(), H - 1 - ys.max())
            at_border[end] = not (m >= p.border_px)
        ends = [e for e in ("start", "end") if not at_border[e]] or ["start", "end"]
        best = max(ends, key=lambda e: _mean(conf[near[e]]) if near[e].any() else -1.0)
    else:
        best = p.free_end
    cand = np.flatnonzero(near[best])
    if cand.size == 0:  # a curve shorter than the grasp distance: its far end
        dist = from_start if best == "start" else from_end
        cand = np.array([int(np.argmin(np.abs(dist - p.grasp_mm)))])
    i = int(cand[np.argmax(conf[cand])])
    tangent = _gradient_at(pts, i)
    norm = np.sqrt(tangent.dot(tangent))  # np.linalg.norm's own operations, without its layers
    tangent = tangent / norm if norm > 0 else np.zeros(3)
    dist = from_start if best == "start" else from_end
    return GraspPoint(
        point=pts[i].copy(),
        confidence=float(conf[i]),
        tangent=tangent,
        index=i,
        from_end=best,
        distance=float(dist[i] / mm),
    )


def _mean(x: np.ndarray) -> float:
    """``float(x.mean())`` of a non-empty 1-D float64 array: numpy's sum (the same pairwise
    reduction) over the count, without ``_methods._mean``'s layers."""
    return float(x.sum() / x.size)


def _gradient_at(pts: np.ndarray, i: int) -> np.ndarray:
    """Row i of ``np.gradient(pts, axis=0)`` (unit spacing, edge_order 1)."""
    if i == 0:
        return pts[1] - pts[0]
    if i == len(pts) - 1:
        return pts[-1] - pts[-2]
    return (pts[i + 1] - pts[i - 1]) / 2.0
