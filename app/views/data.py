"""Stage results as plain data: a stage's JSON, the 2D overlays of the stereo images and the
pixel inspector. Nothing here talks to viser or FastAPI."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from threadrecon.app.dataset import reprojections
from threadrecon.app.export import json_safe
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.camera import image_to_camera
from threadrecon.core.pipeline import STAGES, Reconstruction

HEAVY_VALUES = 20_000  # arrays larger than this (per-pixel images, the energy volume) are
# left out of a stage's JSON: megabytes on the wire; the inspector serves one pixel instead
SPLINE_SAMPLES = 300  # points per drawn curve: smooth on screen, small on the wire
OVERLAY_PIXELS = 16_000  # display budget of a pixel list: a 640x480 thread (3-10k px) is sent
# whole; a 1920x1080 one (20-40k px, shown at about half size) as blocks of 2x2 px


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
    with its reprojection errors. Pixel lists are flat [x0, y0, x1, y1, ...] integer lists of
    the top-left corners of ``<name>_step`` px square blocks (1: the pixels themselves; more
    when the list exceeds the display budget, see :func:`decimate_pixels`), and
    ``<name>_count`` is the number of pixels. For display only: the computation is untouched."""
    out: dict[str, Any] = {"shape": list(calib.image_size)}
    plain: dict[str, Any] = {}  # long lists already JSON-safe: kept out of json_safe's walk
    if "stereo" in rec.runs:
        st = rec["stereo"]
        lists = {"segmented": st.pixels}
        if "reliability" in rec.runs:
            lists["reliable"] = st.pixels[rec["reliability"].reliable]
        for name, pixels in lists.items():
            blocks, step = decimate_pixels(pixels, OVERLAY_PIXELS)
            plain[name] = blocks.ravel().tolist()  # Python ints: JSON as they are
            out[f"{name}_step"] = step
            out[f"{name}_count"] = len(pixels)
    if "clustering" in rec.runs:
        plain["keypoints"] = _rounded(rec["clustering"].keypoints_px[:, :2])
    if "ordering" in rec.runs:
        plain["path"] = _rounded(rec["ordering"].path_px[:, :2])
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
                entry: dict[str, Any] = {"points": _rounded(uv)}
                if r is not None:
                    entry.update(
                        json_safe({"mean_px": r.mean, "max_px": r.max, "coverage": r.coverage})
                    )
                sides[side] = entry
            plain[name] = sides
    return {**json_safe(out), **plain}


def _rounded(a: np.ndarray) -> list:
    """(N, 2) floats as nested lists rounded to 0.01 px; NaN/inf become None."""
    a = np.round(np.asarray(a, dtype=np.float64), 2)
    return a.tolist() if np.isfinite(a).all() else json_safe(a)


def decimate_pixels(pixels: np.ndarray, budget: int) -> tuple[np.ndarray, int]:
    """A pixel list for display: the (M, 2) int top-left corners (x, y) of the step x step blocks
    that hold at least one of ``pixels`` ((N, 2) int, x, y), with the smallest step for which
    M <= ``budget`` (step 1: the pixels unchanged, in their order). Drawn as squares, the blocks
    cover every pixel: a thin thread stays connected."""
    pixels = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
    if budget < 1:
        raise ValueError(f"budget must be >= 1, got {budget}")
    step, blocks = 1, pixels
    while len(blocks) > budget:
        step += 1
        cells = pixels // step
        width = int(cells[:, 0].max()) + 1
        keys = np.unique(cells[:, 1] * width + cells[:, 0])  # one per occupied block
        blocks = np.column_stack([keys % width, keys // width]) * step
    return blocks, step


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
        "energy": st.energy_row(i),
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
