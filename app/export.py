"""Downloads of one frame's reconstruction: the final spline (JSON, CSV) and point clouds (PLY).

Every 3D point is in the left rectified camera frame (OpenCV: x right, y down, z forward), in
the calibration's unit: the stereo points and keypoints come from Q, Eqs. (4)-(5), the spline
from G, Eq. (9), both of the same rectified left camera.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from core.pipeline import Reconstruction

LAYERS = ("stereo", "reliable", "keypoints", "spline")
"""Point-cloud layers of :func:`cloud_ply`."""

_LAYER_STAGES = {
    "stereo": ("stereo", "reliability"),
    "reliable": ("stereo", "reliability"),
    "keypoints": ("reliability", "clustering"),
    "spline": ("camera",),
}
_PLY_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
)
SPLINE_START_RGB = (0, 200, 255)  # cyan at u = 0: the colour ramp shows the curve's direction
SPLINE_END_RGB = (255, 0, 200)  # magenta at u = 1


def json_safe(obj: Any) -> Any:
    """``obj`` with NaN/inf -> None, numpy arrays and scalars -> lists and Python numbers,
    tuples -> lists, recursively: ready for ``json.dumps(..., allow_nan=False)``."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):  # e.g. the grasp point
        return {f.name: json_safe(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def spline_json(rec: Reconstruction) -> dict[str, Any]:
    """The final spline and the keypoints it was fitted to, JSON-safe.

    ``points``: (n, 3) dense centerline; ``control_points``, ``knots``, ``degree``: the
    B-spline over u in [0, 1]; ``length`` in ``unit``. ``keypoints``: ``points`` (K, 3)
    cluster centroids (the set K), ``reliability`` (K,) mean R of Eq. (6) over each cluster,
    ``size`` (K,) px, ``rank`` (K,) position along the ordered curve (None: dropped branch).
    ``fallback`` is True when the MVS fit was rejected and the curve is the initial spline.
    Raises ValueError when there is no final spline.
    """
    _require(rec, "camera", "no final spline")
    cam = rec["camera"]
    spline = rec["spline"]
    out: dict[str, Any] = {
        "status": rec.status,
        "error": rec.message,
        "fallback": not spline.ok,
        "spline_status": spline.status,
        "unit": cam.unit,
        "degree": cam.degree,
        "knots": cam.knots,
        "control_points": cam.ctrl,
        "points": cam.points,
        "length": cam.length,
        "keypoints": _keypoints(rec),
    }
    return json_safe(out)


def _keypoints(rec: Reconstruction) -> dict[str, Any]:
    clusters = rec["clustering"]
    R = rec["reliability"].R
    sel = clusters.labels >= 0
    k = clusters.count
    mean_R = np.bincount(clusters.labels[sel], weights=R[sel], minlength=k) / clusters.sizes
    rank: list[int | None] = [None] * k
    if "ordering" in rec.runs:
        for pos, kid in enumerate(rec["ordering"].order.tolist()):
            if kid >= 0 and rank[kid] is None:  # -1: an extension keypoint, not a cluster
                rank[kid] = pos
    return {
        "points": clusters.keypoints,
        "reliability": mean_R,
        "size": clusters.sizes,
        "rank": rank,
    }


def spline_csv(rec: Reconstruction) -> str:
    """The dense centerline as CSV: ``i,x_<unit>,y_<unit>,z_<unit>``, one row per point,
    floats written to round-trip exactly."""
    _require(rec, "camera", "no final spline")
    cam = rec["camera"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["i", *(f"{a}_{cam.unit}" for a in "xyz")])
    for i, (x, y, z) in enumerate(cam.points.tolist()):
        w.writerow([i, repr(x), repr(y), repr(z)])
    return buf.getvalue()


def ply_bytes(
    points: np.ndarray, colors: np.ndarray | None = None, comments: Sequence[str] = ()
) -> bytes:
    """Binary little-endian PLY of ``points`` (N, 3) finite, as float32 x y z, and ``colors``
    (N, 3) uint8 as uchar red green blue (grey when None); ``comments`` go in the header."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if not np.issubdtype(pts.dtype, np.number) or not np.isfinite(pts).all():
        raise ValueError("points must be finite numbers (drop NaN rows first)")
    if colors is None:
        colors = np.full((len(pts), 3), 200, dtype=np.uint8)
    colors = np.asarray(colors)
    if colors.shape != pts.shape:
        raise ValueError(f"colors must have shape {pts.shape} like points, got {colors.shape}")
    if colors.dtype != np.uint8:
        raise ValueError(f"colors must be uint8, got {colors.dtype}")
    for c in comments:
        if "\n" in c or "\r" in c:
            raise ValueError(f"a PLY comment must be one line, got {c!r}")
    vertices = np.empty(len(pts), dtype=_PLY_DTYPE)
    for a, name in enumerate("xyz"):
        vertices[name] = pts[:, a]
    for a, name in enumerate(("red", "green", "blue")):
        vertices[name] = colors[:, a]
    header = [
        "ply",
        "format binary_little_endian 1.0",
        *(f"comment {c}" for c in comments),
        f"element vertex {len(pts)}",
        *(f"property float {a}" for a in "xyz"),
        *(f"property uchar {c}" for c in ("red", "green", "blue")),
        "end_header",
    ]
    return ("\n".join(header) + "\n").encode("ascii") + vertices.tobytes()


def cloud_ply(rec: Reconstruction, layer: str) -> bytes:
    """One layer of the reconstruction as a PLY point cloud.

    ``stereo``: every segmented left pixel's 3D point (Eqs. (4)-(5); pixels without a positive
    disparity are left out), coloured by reliability R (red 0 .. yellow .. green 1);
    ``reliable``: the reliable pixels P_L^R only, same colours; ``keypoints``: the cluster
    centroids K, coloured by their mean R; ``spline``: the dense final centerline, coloured
    from cyan (u = 0) to magenta (u = 1).
    """
    if layer not in LAYERS:
        raise ValueError(f"unknown layer {layer!r} (known: {', '.join(LAYERS)})")
    for stage in _LAYER_STAGES[layer]:
        _require(rec, stage, f"layer {layer!r} needs the {stage} stage")
    if layer in ("stereo", "reliable"):
        stereo, rel = rec["stereo"], rec["reliability"]
        keep = np.isfinite(stereo.points).all(axis=1)
        if layer == "reliable":
            keep &= rel.reliable
        pts, colors = stereo.points[keep], reliability_colors(rel.R[keep])
    elif layer == "keypoints":
        kp = _keypoints(rec)
        pts, colors = kp["points"], reliability_colors(kp["reliability"])
    else:
        pts = rec["camera"].points
        u = np.linspace(0.0, 1.0, len(pts))[:, None]
        ramp = (1 - u) * np.array(SPLINE_START_RGB) + u * np.array(SPLINE_END_RGB)
        colors = np.round(ramp).astype(np.uint8)
    unit = rec["camera"].unit if "camera" in rec.runs else "calibration units"
    comments = (f"threadrecon layer {layer}", f"unit {unit}", "frame left rectified camera")
    return ply_bytes(pts, colors, comments)


def reliability_colors(R: np.ndarray) -> np.ndarray:
    """(N,) reliability R in [0, 1] -> (N, 3) uint8: red (0), yellow (0.5), green (1)."""
    R = np.clip(np.nan_to_num(np.asarray(R, dtype=np.float64), nan=0.0), 0.0, 1.0)
    rgb = np.stack([np.clip(2 * (1 - R), 0, 1), np.clip(2 * R, 0, 1), np.zeros_like(R)], axis=1)
    return np.round(255 * rgb).astype(np.uint8)


def _require(rec: Reconstruction, stage: str, what: str) -> None:
    if stage in rec.runs:
        return
    if rec.failed_stage is not None:
        raise ValueError(f"{what}: the reconstruction failed at {rec.failed_stage}: {rec.error}")
    raise ValueError(f"{what}: the pipeline stopped before the {stage} stage")
