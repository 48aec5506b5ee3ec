"""What the debugger shows, as plain data: stage results as JSON, the 2D overlays of the
stereo images, the pixel inspector, and the 3D layers (numpy arrays in the left camera frame,
calibration units) that ``app.scene`` hands to viser.

Nothing here talks to viser or FastAPI, so every view is testable on its own.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.dataset import reprojections
from app.export import json_safe, reliability_colors
from core.calibration import StereoCalibration
from core.camera import image_to_camera
from core.pipeline import STAGES, Reconstruction

# Fields left out of a stage's JSON: per-pixel images and the (N, alpha+1) energy volume are
# megabytes; the inspector serves one pixel's energy curve instead.
_HEAVY_FIELDS = {
    "segment": {"I_L", "I_R", "grey_L", "grey_R", "P_L", "P_R"},
    "stereo": {"energy"},
    "ordering": {"node_image", "pixel_node", "pixel_t", "pixel_link"},
}
SPLINE_SAMPLES = 300  # points per drawn curve: smooth on screen, small on the wire


def stage_json(rec: Reconstruction, stage: str) -> dict[str, Any]:
    """One stage's result as JSON (without the per-pixel images), plus its time."""
    if stage not in STAGES:
        raise KeyError(f"unknown stage {stage!r} (stages: {', '.join(STAGES)})")
    if stage not in rec.runs:
        raise LookupError(_missing(rec, stage))
    run = rec.runs[stage]
    result = run.result
    skip = _HEAVY_FIELDS.get(stage, set())
    data = {
        f.name: json_safe(getattr(result, f.name))
        for f in dataclasses.fields(result)
        if f.name not in skip
    }
    if stage == "segment":
        data["n_left"] = int(result.P_L.sum())
        data["n_right"] = int(result.P_R.sum())
    if hasattr(result, "count"):
        data["count"] = result.count
    return {"stage": stage, "ms": run.ms, "cached": run.cached, "result": data}


def _missing(rec: Reconstruction, stage: str) -> str:
    if rec.failed_stage is not None and STAGES.index(stage) >= STAGES.index(rec.failed_stage):
        return f"stage {stage!r} has no result: the run failed at {rec.failed_stage}: {rec.error}"
    return f"stage {stage!r} has not been run yet"


# --- 2D overlays ---------------------------------------------------------------------------


def overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    """What is drawn over the stereo images: segmented, reliable and keypoint pixels of the
    left image, the ordered path, and the final (and initial) spline projected into both images
    with its reprojection errors. Pixel lists are flat [x0, y0, x1, y1, ...] integer lists."""
    out: dict[str, Any] = {"shape": list(calib.image_size)}
    if "stereo" in rec.runs:
        st = rec["stereo"]
        out["segmented"] = st.pixels.ravel().tolist()
        if "reliability" in rec.runs:
            out["reliable"] = st.pixels[rec["reliability"].reliable].ravel().tolist()
    if "clustering" in rec.runs:
        out["keypoints"] = np.round(rec["clustering"].keypoints_px[:, :2], 2).tolist()
    if "ordering" in rec.runs:
        out["path"] = np.round(rec["ordering"].path_px[:, :2], 2).tolist()
    if "bounds" in rec.runs:
        b = rec["bounds"]
        out["H"] = [
            [round(float(x), 2), round(float(y), 2), bool(k)]
            for (x, y, _), k in zip(b.H, b.is_key, strict=True)
        ]
    if "spline" in rec.runs:
        sp = rec["spline"]
        for name, initial in (("spline", False), ("spline_initial", True)):
            pts = image_to_camera(sp.curve(SPLINE_SAMPLES, initial=initial), calib.G)
            sides = {}
            for side, (uv, r) in reprojections(pts, calib, rec["segment"], not initial).items():
                entry: dict[str, Any] = {"points": np.round(uv, 2).tolist()}
                if r is not None:
                    entry.update(mean_px=r.mean, max_px=r.max, coverage=r.coverage)
                sides[side] = entry
            out[name] = sides
    return json_safe(out)


# --- pixel inspector -----------------------------------------------------------------------


def pixel_info(rec: Reconstruction, x: int, y: int, snap_px: int = 3) -> dict[str, Any]:
    """Why a pixel was or was not trusted: its energy curve E(d) with d_min and d_next, E_min,
    E_next, reliability R and depth. A click off the thread snaps to the nearest segmented
    pixel within ``snap_px``."""
    if "stereo" not in rec.runs:
        raise LookupError(_missing(rec, "stereo"))
    st = rec["stereo"]
    h, w = st.shape
    if not (0 <= x < w and 0 <= y < h):
        raise ValueError(f"pixel ({x}, {y}) is outside the {w}x{h} image")
    d2 = (st.pixels[:, 0] - x) ** 2 + (st.pixels[:, 1] - y) ** 2
    if d2.size == 0 or d2.min() > snap_px**2:
        return {"x": x, "y": y, "segmented": False}
    i = int(np.argmin(d2))
    out: dict[str, Any] = {
        "x": int(st.pixels[i, 0]),
        "y": int(st.pixels[i, 1]),
        "clicked": [x, y],
        "segmented": True,
        "index": i,
        "energy": st.energy[i],
        "d_min": int(st.d_min[i]),
        "d_next": int(st.d_next[i]),
        "E_min": float(st.E_min[i]),
        "E_next": float(st.E_next[i]),
        "disparity": float(st.disparity[i]),
        "depth": float(st.depth[i]),
        "point": st.points[i],
    }
    if "reliability" in rec.runs:
        rel = rec["reliability"]
        out["R"] = float(rel.R[i])
        out["reliable"] = bool(rel.reliable[i])
        out["threshold"] = rec.params.reliability.threshold
    if "clustering" in rec.runs:
        out["cluster"] = int(rec["clustering"].labels[i])
    return json_safe(out)


def nearest_to_ray(
    points: np.ndarray, origin: np.ndarray, direction: np.ndarray, tol: float
) -> int | None:
    """Index of the point closest to a ray (among those within ``tol`` of it, the one nearest
    the ray's origin), or None. ``points`` (N, 3) in the ray's frame; NaN rows never match."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    rel = points - np.asarray(origin, dtype=float)
    t = rel @ d
    dist = np.linalg.norm(rel - t[:, None] * d, axis=1)
    ok = np.isfinite(dist) & (t > 0) & (dist <= tol)
    if not ok.any():
        return None
    idx = np.flatnonzero(ok)
    return int(idx[np.argmin(t[idx] + dist[idx])])


# --- 3D layers -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Points:
    points: np.ndarray
    """(N, 3) float32, left camera frame."""
    colors: np.ndarray
    """(N, 3) uint8 or (3,) uint8."""
    size: float
    """Point size as a multiple of the scene's base point size."""


@dataclass(frozen=True)
class Segments:
    points: np.ndarray
    """(M, 2, 3) float32 line segments."""
    color: tuple[int, int, int]
    width: float
    """Screen-space width, px."""


@dataclass(frozen=True)
class Label:
    text: str
    position: np.ndarray


Layer = dict[str, Points | Segments | Label]
"""Node name (relative to the layer root) -> what to draw there."""

# The layers of the scene, in stage order; each is drawn from the results of the named stages.
LAYERS: dict[str, tuple[str, ...]] = {
    "stereo": ("stereo", "reliability"),
    "reliability": ("stereo", "reliability"),
    "clusters": ("stereo", "clustering"),
    "ordering": ("clustering", "ordering"),
    "bounds": ("bounds",),
    "spline": ("spline", "camera"),
}
LAYER_STAGE = {  # the stage whose result first reveals the layer
    "stereo": "stereo",
    "reliability": "reliability",
    "clusters": "clustering",
    "ordering": "ordering",
    "bounds": "bounds",
    "spline": "spline",
}

GREY = (150, 150, 150)


def palette(n: int) -> np.ndarray:
    """n distinct colours (golden-ratio hues), (n, 3) uint8."""
    h = (np.arange(n) * 0.618033988749895) % 1.0
    k = (np.array([5.0, 3.0, 1.0])[None, :] + h[:, None] * 6.0) % 6.0
    rgb = 1.0 - 0.75 * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)  # HSV with s=0.75, v=1
    return (rgb * 255).astype(np.uint8)


def _polyline(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float32)
    return np.stack([p[:-1], p[1:]], axis=1) if len(p) > 1 else np.zeros((0, 2, 3), np.float32)


def layer(
    name: str, rec: Reconstruction, calib: StereoCalibration, ground_truth: np.ndarray | None
) -> Layer:
    """The nodes of one layer from the stage results available in ``rec``."""
    G = calib.G
    if name in ("stereo", "reliability", "clusters"):
        st = rec["stereo"]
        finite = np.isfinite(st.points).all(axis=1)
        if name == "stereo":
            colors = (
                reliability_colors(rec["reliability"].R[finite])
                if "reliability" in rec.runs
                else np.array(GREY, np.uint8)
            )
            return {"depth": Points(st.points[finite].astype(np.float32), colors, 1.0)}
        if name == "reliability":
            keep = finite & rec["reliability"].reliable
            pts = st.points[keep].astype(np.float32)
            return {"reliable": Points(pts, np.array((40, 200, 255), np.uint8), 1.6)}
        cl = rec["clustering"]
        keep = finite & (cl.labels >= 0)
        colors = palette(max(cl.count, 1))[cl.labels[keep]]
        return {
            "members": Points(st.points[keep].astype(np.float32), colors, 1.6),
            "keypoints": Points(
                cl.keypoints.astype(np.float32), palette(max(cl.count, 1))[: cl.count], 3.0
            ),
        }
    if name == "ordering":
        cl, od = rec["clustering"], rec["ordering"]
        path = image_to_camera(od.path_px, G).astype(np.float32)
        nodes: Layer = {
            "graph": Segments(cl.keypoints[od.edges].astype(np.float32), (120, 120, 140), 1.5),
            "path": Segments(_polyline(path), (255, 140, 0), 3.0),
        }
        if len(path):
            nodes["start"] = Points(path[:1], np.array((0, 220, 0), np.uint8), 6.0)
            nodes["end"] = Points(path[-1:], np.array((230, 0, 0), np.uint8), 6.0)
            step = max(1, len(path) // 12)  # at most ~12 index labels, readable
            for i in [*range(0, len(path) - step // 2, step), len(path) - 1]:
                nodes[f"labels/{i}"] = Label(str(i), path[i])
        return nodes
    if name == "bounds":
        b = rec["bounds"]
        xy = b.H[:, :2]
        lo = image_to_camera(np.column_stack([xy, b.lower]), G).astype(np.float32)
        hi = image_to_camera(np.column_stack([xy, b.upper]), G).astype(np.float32)
        H = image_to_camera(b.H, G).astype(np.float32)
        colors = np.where(b.is_key[:, None], [255, 255, 255], [255, 200, 60]).astype(np.uint8)
        return {
            "H": Points(H, colors, 2.5),
            "lower": Segments(_polyline(lo), (80, 160, 255), 2.0),
            "upper": Segments(_polyline(hi), (255, 90, 90), 2.0),
            "spans": Segments(np.stack([lo, hi], axis=1), (160, 160, 160), 1.0),
        }
    if name == "spline":
        sp = rec["spline"]
        nodes = {
            "initial": Segments(
                _polyline(image_to_camera(sp.curve(SPLINE_SAMPLES, initial=True), G)),
                (110, 130, 255),
                2.0,
            ),
            "final": Segments(
                _polyline(image_to_camera(sp.curve(SPLINE_SAMPLES), G)), (255, 0, 200), 4.0
            ),
        }
        if "camera" in rec.runs:
            nodes["control_points"] = Points(
                rec["camera"].ctrl.astype(np.float32), np.array((255, 0, 200), np.uint8), 3.0
            )
        if ground_truth is not None:
            nodes["ground_truth"] = Segments(_polyline(ground_truth), (0, 200, 90), 2.0)
        return nodes
    raise KeyError(f"unknown layer {name!r} (layers: {', '.join(LAYERS)})")
