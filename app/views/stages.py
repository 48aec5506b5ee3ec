"""The views of the paper's stages (segment .. spline): their 2D overlays over the stereo
images (``@overlay_view``) and their 3D layers (``@layer_view``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from threadrecon.app.dataset import reprojections
from threadrecon.app.export import reliability_colors
from threadrecon.app.views.data import SPLINE_SAMPLES
from threadrecon.app.views.registry import (
    GREY,
    Label,
    Layer,
    Points,
    Segments,
    layer_view,
    overlay_view,
    palette,
    polyline,
)
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.camera import image_to_camera
from threadrecon.core.pipeline import Reconstruction

# --- 2D overlays (drawn in this order) -----------------------------------------------------


@overlay_view(
    "segmented",
    "segmented",
    "pixels",
    ("stereo",),
    "rgba(90,160,255,0.75)",
    on=False,
    reveal="segment",
)
def _segmented_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    return {"left": rec["stereo"].pixels.ravel().tolist()}


@overlay_view("reliable", "reliable", "pixels", ("stereo", "reliability"), "#00e5ff", count=True)
def _reliable_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    return {"left": rec["stereo"].pixels[rec["reliability"].reliable].ravel().tolist()}


@overlay_view("path", "ordering", "polyline", ("ordering",), "#ff8c00")
def _path_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    return {"left": {"points": np.round(rec["ordering"].path_px[:, :2], 2)}}


@overlay_view("keypoints", "keypoints", "circles", ("clustering",), "#ffe14d", count=True)
def _keypoints_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    return {"left": np.round(rec["clustering"].keypoints_px[:, :2], 2)}


@overlay_view("H", "points H", "squares", ("bounds",), "#ffffff", color2="#ffc83c")
def _h_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    b = rec["bounds"]
    return {
        "left": [
            [round(float(x), 2), round(float(y), 2), bool(k)]
            for (x, y, _), k in zip(b.H, b.is_key, strict=True)
        ]
    }


def _projected(
    points: np.ndarray, calib: StereoCalibration, rec: Reconstruction, errors: bool
) -> dict[str, Any]:
    sides: dict[str, Any] = {}
    for side, (uv, r) in reprojections(points, calib, rec["segment"], errors).items():
        entry: dict[str, Any] = {"points": np.round(uv, 2)}
        if r is not None:
            entry.update(mean_px=r.mean, max_px=r.max, coverage=r.coverage)
        sides[side] = entry
    return sides


@overlay_view(
    "spline_initial", "initial spline", "polyline", ("spline",), "#6e82ff", on=False, dash=True
)
def _initial_spline_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    initial = image_to_camera(rec["spline"].curve(SPLINE_SAMPLES, initial=True), calib.G)
    return _projected(initial, calib, rec, errors=False)


@overlay_view("spline", "final spline", "polyline", ("spline",), "#ff3ecf")
def _spline_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    """The final curve with its reprojection errors: the camera stage's points, so the errors
    are the metrics' own (one number everywhere)."""
    if "camera" in rec.runs:
        return _projected(rec["camera"].points, calib, rec, errors=True)
    return _projected(
        image_to_camera(rec["spline"].curve(SPLINE_SAMPLES), calib.G), calib, rec, errors=False
    )


# --- 3D layers -----------------------------------------------------------------------------


def _finite_points(rec: Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    st = rec["stereo"]
    return st.points, np.isfinite(st.points).all(axis=1)


@layer_view("stereo", needs=("stereo", "reliability"), shows_at="stereo")  # coloured by R
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
        "path": Segments(polyline(path), (255, 140, 0), 3.0),
    }
    if len(path):
        nodes["start"] = Points(path[:1], np.array((0, 220, 0), np.uint8), 6.0)
        nodes["end"] = Points(path[-1:], np.array((230, 0, 0), np.uint8), 6.0)
        step = max(1, len(path) // 12)  # at most ~12 index labels, readable
        at = [*range(0, len(path) - step // 2, step), len(path) - 1]
        for k, i in enumerate(at):  # named by slot: a redraw updates the labels in place
            nodes[f"labels/{k}"] = Label(str(i), path[i])
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
        "lower": Segments(polyline(lo), (80, 160, 255), 2.0),
        "upper": Segments(polyline(hi), (255, 90, 90), 2.0),
        "spans": Segments(np.stack([lo, hi], axis=1), (160, 160, 160), 1.0),
    }


@layer_view("spline", needs=("spline", "camera"), shows_at="spline")  # + control points
def _spline_layer(rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None) -> Layer:
    sp, G = rec["spline"], calib.G
    nodes: Layer = {
        "initial": Segments(
            polyline(image_to_camera(sp.curve(SPLINE_SAMPLES, initial=True), G)),
            (110, 130, 255),
            2.0,
        ),
        "final": Segments(
            polyline(image_to_camera(sp.curve(SPLINE_SAMPLES), G)), (255, 0, 200), 4.0
        ),
    }
    if "camera" in rec.runs:
        nodes["control_points"] = Points(
            rec["camera"].ctrl.astype(np.float32), np.array((255, 0, 200), np.uint8), 3.0
        )
    return nodes


@layer_view("ground_truth", needs=(), shows_at="segment")
def _ground_truth_layer(
    rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None
) -> Layer:
    """The frame's true curve, when it has one: drawn once per frame (it needs no stage result,
    so no slider redraws it)."""
    return {} if gt is None else {"curve": Segments(polyline(gt), (0, 200, 90), 2.0)}
