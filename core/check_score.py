"""The check stage's per-point confidence, grasp point and automatic quality score.

Per-point confidence (core/check.py's module docstring gives the formula): each point i of the
dense curve gets an expected 3D error e_i from the evidence near it, and the confidence
exp(-e_i / ``conf_mm``). The grasp point is the most confident point near ``grasp_mm`` from the
free end; the score rates the curve on the paper's 1-5 scale (Sec. IV-B) from the typical e_i,
capped by the check's status.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from threadrecon.core.bounds import Bounds
from threadrecon.core.spline import SplineResult

if TYPE_CHECKING:
    from threadrecon.core.check import CheckParams, Status

_SCORE_STEPS = (1.0, 2.0, 4.0, 8.0)  # score 5..1 edges, in multiples of score_mm
_R_CAP_PX = 10.0  # a residual counts at most this (px) in the local mean: no reliable match near


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
) -> PointErrors:
    """The expected error e_i and confidence of each curve point (core/check.py's docstring).

    ``z_pos``: (N,) depths (calib units, clipped above 0); ``behind``: (N,) bool, behind a
    camera; ``r``: (N,) disparity residuals (px); ``rho``: (N,) reprojection distance (px, 0
    where the view does not count); ``bridge_gap``: (N,) mm into a bridge; ``step``: (N-1,) px
    steps of the left projection; ``s3``: (N,) arc length (mm); ``f``, ``fB`` in px and
    px * calib units; ``mm``: mm per calib unit.
    """
    lateral = z_pos / f * rho * mm + p.bridge_error * bridge_gap  # bridges: interpolated
    e_mm = _expected_error(z_pos, r, step, s3, spline, fB, p)
    e_mm = e_mm * mm + lateral
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
) -> np.ndarray:
    """Depth part of the expected error e_i (calib units): the depth size of a pixel of
    disparity z^2 / (f B) times the local disparity error sqrt(sigma_d^2 + rbar_i^2), rbar_i
    the mean residual r of the reliable matches over one knot span of the spline around the
    point (the stretch whose matches the spline averages; r capped at _R_CAP_PX); doubled at
    an end of the curve (fitted from one side only), falling back over ``end_mm``."""
    n_spans = max(len(spline.ctrl) - int(spline.degree), 1)
    s2 = np.concatenate([[0.0], np.cumsum(np.where(np.isfinite(step), step, 0.0))])
    r_local = _local_mean(np.minimum(r, _R_CAP_PX), s2, s2[-1] / n_spans)
    d = np.sqrt(p.sigma_disparity_px**2 + r_local**2)
    end = np.minimum(s3, s3[-1] - s3)  # mm to the nearer end
    return z**2 / fB * d * (1.0 + np.exp(-end / p.end_mm))


def _local_mean(x: np.ndarray, s: np.ndarray, width: float) -> np.ndarray:
    """Mean of x over the samples within width / 2 of each sample along the arc length s."""
    c = np.concatenate([[0.0], np.cumsum(x)])
    lo = np.searchsorted(s, s - 0.5 * width)
    hi = np.searchsorted(s, s + 0.5 * width, side="right")
    return (c[hi] - c[lo]) / np.maximum(hi - lo, 1)


def bound_halfwidth_px(spline: SplineResult, bounds: Bounds, n: int, fB: float) -> np.ndarray:
    """Bound half-width of Eq. (7) at each curve point, in px of disparity (|dd/dz| = fB/z^2)."""
    u = np.linspace(0.0, 1.0, n)
    uh = spline.u_H / spline.length if spline.length > 0 else np.linspace(0, 1, len(spline.u_H))
    half = np.interp(u, uh, 0.5 * (bounds.upper - bounds.lower))
    centre = np.maximum(np.interp(u, uh, bounds.centre), 1e-12)
    return half * fB / centre**2


def _typical(e_mm: np.ndarray) -> float:
    """The typical expected error of a curve (mm): the geometric mean of e_i (a few points of
    large e_i, e.g. an interpolated stretch, do not swamp it; 1e6 for a non-finite one)."""
    with np.errstate(divide="ignore"):
        return float(np.exp(np.mean(np.log(np.clip(e_mm, 1e-9, 1e6)))))


def _score(error_mm: float, status: Status, score_mm: float) -> int:
    """The paper's 1-5 rating from the typical expected error, capped by the status."""
    score = 5 - int(np.searchsorted(np.array(_SCORE_STEPS) * score_mm, error_mm))
    if status == "failed":
        return 1
    if status == "suspect":
        return min(score, 2)
    return max(1, score)


def quality_score(e_mm: np.ndarray, status: Status, p: CheckParams) -> int:
    """The automatic quality score (1-5, the paper's rating scale) of a checked curve."""
    return _score(_typical(e_mm), status, p.score_mm)


def grasp_point(
    pts: np.ndarray,
    conf: np.ndarray,
    uv_l: np.ndarray,
    uv_r: np.ndarray,
    shape: tuple[int, int],
    mm: float,
    p: CheckParams,
) -> GraspPoint | None:
    """The most confident point within ``grasp_window_mm`` of ``grasp_mm`` from the free end."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]) * mm
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
            xs = np.array([uv_l[i, 0], uv_r[i, 0]])
            ys = np.array([uv_l[i, 1], uv_r[i, 1]])
            m = min(xs.min(), ys.min(), W - 1 - xs.max(), H - 1 - ys.max())
            at_border[end] = not (m >= p.border_px)
        ends = [e for e in ("start", "end") if not at_border[e]] or ["start", "end"]
        best = max(ends, key=lambda e: float(conf[near[e]].mean()) if near[e].any() else -1.0)
    else:
        best = p.free_end
    cand = np.flatnonzero(near[best])
    if cand.size == 0:  # a curve shorter than the grasp distance: its far end
        dist = from_start if best == "start" else from_end
        cand = np.array([int(np.argmin(np.abs(dist - p.grasp_mm)))])
    i = int(cand[np.argmax(conf[cand])])
    tangent = _gradient_at(pts, i)
    norm = np.linalg.norm(tangent)
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


def _gradient_at(pts: np.ndarray, i: int) -> np.ndarray:
    """Row i of ``np.gradient(pts, axis=0)`` (unit spacing, edge_order 1)."""
    if i == 0:
        return pts[1] - pts[0]
    if i == len(pts) - 1:
        return pts[-1] - pts[-2]
    return (pts[i + 1] - pts[i - 1]) / 2.0
