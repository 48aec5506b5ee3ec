"""The views of the check stage: the curve coloured by its per-point confidence and the grasp
point with its tangent, in 3D (``@layer_view``) and over both stereo images (``@overlay_view``),
and the check's verdict as plain data for the page's status panel (:func:`check_json`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from threadrecon.app.dataset import reprojections
from threadrecon.app.views import stages  # noqa: F401  (its views register first: stage order)
from threadrecon.app.views.registry import Label, Layer, Points, Segments, layer_view, overlay_view
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.pipeline import Reconstruction

TANGENT_MM = 8.0  # half-length of the drawn grasp tangent, mm (a jaw's width)
_LOW, _MID, _HIGH = (
    np.array(c, np.float64) for c in ((230, 40, 40), (240, 200, 40), (40, 200, 80))
)


def confidence_colors(confidence: np.ndarray) -> np.ndarray:
    """Red (0) -> yellow (0.5) -> green (1), (N, 3) uint8; non-finite counts as 0."""
    c = np.clip(np.nan_to_num(np.asarray(confidence, np.float64), nan=0.0), 0.0, 1.0)[:, None]
    lo = _LOW + (_MID - _LOW) * np.clip(2 * c, 0, 1)
    rgb = np.where(c < 0.5, lo, _MID + (_HIGH - _MID) * np.clip(2 * c - 1, 0, 1))
    return np.rint(rgb).astype(np.uint8)


def _css(rgb: np.ndarray) -> list[str]:
    return [f"#{r:02x}{g:02x}{b:02x}" for r, g, b in rgb.tolist()]


def check_json(rec: Reconstruction | None) -> dict[str, Any] | None:
    """The check's verdict for the status panel: status, every reason, score (the integer class
    and the continuous rating it rounds) and grasp point
    (None before the check stage has run)."""
    if rec is None or "check" not in rec.runs:
        return None
    chk = rec["check"]
    g = chk.grasp
    conf = np.asarray(chk.confidence, np.float64)
    return {
        "status": chk.status,
        "reasons": list(chk.reasons),
        "score": chk.score,
        "rating": chk.rating,
        "confidence_min": float(conf.min()) if conf.size else None,
        "confidence_mean": float(conf.mean()) if conf.size else None,
        "grasp": None
        if g is None
        else {
            "confidence": g.confidence,
            "from_end": g.from_end,
            "distance": g.distance,
            "index": g.index,
        },
    }


def _finite_curve(rec: Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """The camera-stage points that are finite and their confidences."""
    pts = np.asarray(rec["camera"].points, np.float64)
    conf = np.asarray(rec["check"].confidence, np.float64)
    keep = np.isfinite(pts).all(axis=1)
    return pts[keep], conf[keep]


def _tangent_ends(rec: Reconstruction, calib: StereoCalibration) -> np.ndarray | None:
    """(3, 3) points: the grasp point's tangent from -TANGENT_MM to +TANGENT_MM through it."""
    g = rec["check"].grasp
    if g is None or not np.all(np.isfinite(g.point)) or not np.any(g.tangent):
        return None
    half = TANGENT_MM / calib.mm_per_unit
    return np.stack([g.point - half * g.tangent, g.point, g.point + half * g.tangent])


@layer_view("check", needs=("camera", "check"), shows_at="check")
def _check_layer(rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None) -> Layer:
    pts, conf = _finite_curve(rec)
    nodes: Layer = {}
    if len(pts) > 1:
        seg_conf = np.minimum(conf[:-1], conf[1:])  # a segment is as sure as its weaker end
        segs = np.stack([pts[:-1], pts[1:]], axis=1).astype(np.float32)
        # one scene node, a colour per segment: a slider move re-sends one node, not a few
        nodes["confidence"] = Segments(segs, confidence_colors(seg_conf), 5.0)
        nodes["points"] = Points(pts.astype(np.float32), confidence_colors(conf), 1.5)
    g = rec["check"].grasp
    ends = _tangent_ends(rec, calib)
    if g is not None and ends is not None:
        nodes["grasp/point"] = Points(
            g.point[None, :].astype(np.float32), np.array((0, 220, 255), np.uint8), 7.0
        )
        nodes["grasp/tangent"] = Segments(
            np.stack([ends[:-1], ends[1:]], axis=1).astype(np.float32), (0, 220, 255), 3.0
        )
        nodes["grasp/label"] = Label(f"grasp {g.confidence:.2f}", g.point)
    return nodes


@overlay_view("confidence", "confidence", "polyline", ("camera", "check"), "#28c850")
def _confidence_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    """The final curve projected into both views, each segment coloured by its confidence."""
    pts, conf = _finite_curve(rec)
    colors = np.array(_css(confidence_colors(conf)))
    out: dict[str, Any] = {}
    for side, (uv, _) in reprojections(pts, calib, rec["segment"], errors=False).items():
        ok = np.isfinite(uv).all(axis=1)
        out[side] = {
            "points": np.round(uv[ok], 2),
            "colors": colors[ok],  # a string array: one tolist(), no walk of its items
        }
    return out


def _grasp_projected(rec: Reconstruction, calib: StereoCalibration) -> dict[str, np.ndarray]:
    """Per side the (3, 2) projected tangent ends and grasp point (middle), when finite."""
    ends = _tangent_ends(rec, calib)
    if ends is None:
        return {}
    sides = reprojections(ends, calib, rec["segment"], errors=False).items()
    return {side: uv for side, (uv, _) in sides if np.isfinite(uv).all()}


@overlay_view("grasp", "grasp point", "circles", ("camera", "check"), "#00dcff")
def _grasp_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    """The grasp point projected into both views."""
    return {side: np.round(uv[1:2], 2) for side, uv in _grasp_projected(rec, calib).items()}


@overlay_view("grasp_tangent", "grasp tangent", "polyline", ("camera", "check"), "#00dcff")
def _grasp_tangent_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    """The curve's tangent at the grasp point, TANGENT_MM either side, in both views."""
    return {side: {"points": np.round(uv, 2)} for side, uv in _grasp_projected(rec, calib).items()}
