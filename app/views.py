"""What the debugger shows, as plain data: stage results as JSON, the 2D overlays of the
stereo images, the pixel inspector, and the 3D layers (numpy arrays in the left camera frame,
calibration units) that ``app.scene`` hands to viser.

Nothing here talks to viser or FastAPI, so every view is testable on its own.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.dataset import reprojections
from app.export import json_safe, reliability_colors
from core.calibration import StereoCalibration
from core.camera import image_to_camera
from core.pipeline import STAGES, Reconstruction

HEAVY_VALUES = 20_000  # arrays larger than this (per-pixel images, the energy volume) are
# left out of a stage's JSON: megabytes on the wire; the inspector serves one pixel instead
SPLINE_SAMPLES = 300  # points per drawn curve: smooth on screen, small on the wire


def stage_json(rec: Reconstruction, stage: str) -> dict[str, Any]:
    """One stage's result as JSON (without the per-pixel images), plus its time."""
    if stage not in STAGES:
        raise KeyError(f"unknown stage {stage!r} (stages: {', '.join(STAGES)})")
    if stage not in rec.runs:
        raise LookupError(_missing(rec, stage))
    run = rec.runs[stage]
    result = run.result
    data: dict[str, Any] = {}
    omitted: dict[str, Any] = {}
    for f in dataclasses.fields(result):
        value = getattr(result, f.name)
        if isinstance(value, np.ndarray) and value.size > HEAVY_VALUES:
            entry: dict[str, Any] = {"shape": list(value.shape), "dtype": str(value.dtype)}
            if value.dtype == bool:
                entry["count"] = int(value.sum())
            omitted[f.name] = entry
        else:
            data[f.name] = json_safe(value)
    if omitted:
        data["omitted"] = omitted
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
        initial = image_to_camera(sp.curve(SPLINE_SAMPLES, initial=True), calib.G)
        # the final curve's errors are the metrics' own (the camera stage's points), one number
        have_final = "camera" in rec.runs
        final = (
            rec["camera"].points
            if have_final
            else image_to_camera(sp.curve(SPLINE_SAMPLES), calib.G)
        )
        for name, pts, errors in (
            ("spline", final, have_final),
            ("spline_initial", initial, False),
        ):
            sides = {}
            for side, (uv, r) in reprojections(pts, calib, rec["segment"], errors).items():
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


@dataclass(frozen=True)
class LayerView:
    """One 3D layer of the scene: drawn from the results of ``needs``, first shown once the
    stage ``shows_at`` has run."""

    name: str
    needs: tuple[str, ...]
    shows_at: str
    draw: Callable[[Reconstruction, StereoCalibration, np.ndarray | None], Layer]


LAYER_VIEWS: dict[str, LayerView] = {}
"""The scene's layers in stage order: the one place a stage's 3D view is registered."""


def layer_view(
    name: str, needs: tuple[str, ...], shows_at: str | None = None
) -> Callable[[Callable[..., Layer]], Callable[..., Layer]]:
    """Register ``draw(rec, calib, ground_truth) -> Layer`` as the layer ``name``."""

    def register(draw: Callable[..., Layer]) -> Callable[..., Layer]:
        unknown = set(needs) - set(STAGES)
        if unknown:
            raise ValueError(f"layer {name!r} needs unknown stages {sorted(unknown)}")
        LAYER_VIEWS[name] = LayerView(name, needs, shows_at or needs[0], draw)
        return draw

    return register


def layer(
    name: str, rec: Reconstruction, calib: StereoCalibration, ground_truth: np.ndarray | None
) -> Layer:
    """The nodes of one layer from the stage results available in ``rec``."""
    view = LAYER_VIEWS.get(name)
    if view is None:
        raise KeyError(f"unknown layer {name!r} (layers: {', '.join(LAYER_VIEWS)})")
    return view.draw(rec, calib, ground_truth)


def _finite_points(rec: Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    st = rec["stereo"]
    return st.points, np.isfinite(st.points).all(axis=1)


@layer_view("stereo", needs=("stereo",))
def _stereo_layer(rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None) -> Layer:
    points, finite = _finite_points(rec)
    colors = (
        reliability_colors(rec["reliability"].R[finite])
        if "reliability" in rec.runs
        else np.array(GREY, np.uint8)
    )
    return {"depth": Points(points[finite].astype(np.float32), colors, 1.0)}


@layer_view("reliability", needs=("stereo", "reliability"), shows_at="reliability")
def _reliability_layer(
    rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None
) -> Layer:
    points, finite = _finite_points(rec)
    keep = finite & rec["reliability"].reliable
    return {
        "reliable": Points(points[keep].astype(np.float32), np.array((40, 200, 255), np.uint8), 1.6)
    }


@layer_view("clusters", needs=("stereo", "clustering"), shows_at="clustering")
def _clusters_layer(rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None) -> Layer:
    points, finite = _finite_points(rec)
    cl = rec["clustering"]
    keep = finite & (cl.labels >= 0)
    colors = palette(max(cl.count, 1))
    return {
        "members": Points(points[keep].astype(np.float32), colors[cl.labels[keep]], 1.6),
        "keypoints": Points(cl.keypoints.astype(np.float32), colors[: cl.count], 3.0),
    }


@layer_view("ordering", needs=("clustering", "ordering"), shows_at="ordering")
def _ordering_layer(rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None) -> Layer:
    cl, od = rec["clustering"], rec["ordering"]
    path = image_to_camera(od.path_px, calib.G).astype(np.float32)
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


@layer_view("bounds", needs=("bounds",))
def _bounds_layer(rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None) -> Layer:
    b, G = rec["bounds"], calib.G
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


@layer_view("spline", needs=("spline",))
def _spline_layer(rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None) -> Layer:
    sp, G = rec["spline"], calib.G
    nodes: Layer = {
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
    if gt is not None:
        nodes["ground_truth"] = Segments(_polyline(gt), (0, 200, 90), 2.0)
    return nodes


# Derived views of the registry, for the scene and the API.
LAYERS: dict[str, tuple[str, ...]] = {v.name: v.needs for v in LAYER_VIEWS.values()}
LAYER_STAGE: dict[str, str] = {v.name: v.shows_at for v in LAYER_VIEWS.values()}
