"""Stage results as plain data: a stage's JSON, the 2D overlays of the stereo images and the
pixel inspector. Nothing here talks to viser or FastAPI."""

from __future__ import annotations

import dataclasses
import itertools
import threading
from typing import Any

import numpy as np

from threadrecon.app.export import json_safe
from threadrecon.app.views.registry import OVERLAY_VIEWS, OverlayView
from threadrecon.core.calibration import StereoCalibration
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
    """What is drawn over the stereo images: every registered overlay whose stages have run,
    as ``{key: {side: payload}}`` (see ``registry.OverlayKind``), plus the image shape.

    For display only (the computation is untouched), a ``pixels`` payload longer than
    ``OVERLAY_PIXELS`` is decimated to the top-left corners of ``step`` x ``step`` blocks that
    cover every pixel (:func:`decimate_pixels`); ``"_pixels": {key: {side: {"step", "count"}}}``
    says so, with the full pixel count. Pixel lists are plain ints and skip ``json_safe``'s
    walk (100 ms at 1920x1080)."""
    out: dict[str, Any] = {"shape": list(calib.image_size), "_pixels": {}}
    for view in OVERLAY_VIEWS.values():
        if all(stage in rec.runs for stage in view.needs):
            out[view.key], meta = _overlay_entry(view, rec, calib)
            if meta is not None:
                out["_pixels"][view.key] = meta
    return out


def _overlay_entry(
    view: OverlayView, rec: Reconstruction, calib: StereoCalibration
) -> tuple[dict[str, Any], dict[str, dict[str, int]] | None]:
    """One overlay's JSON payload ``{side: payload}``, and for a ``pixels`` overlay its
    decimation ``{side: {"step", "count"}}`` (else None)."""
    payload = view.make(rec, calib)
    if view.kind != "pixels":
        return json_safe(payload), None
    sides, meta = {}, {}
    for side, flat in payload.items():
        pixels = np.asarray(flat, dtype=np.int64).reshape(-1, 2)
        blocks, step = decimate_pixels(pixels, OVERLAY_PIXELS)
        sides[side] = blocks.ravel().tolist()
        meta[side] = {"step": step, "count": len(pixels)}
    return sides, meta


class OverlayCache:
    """The 2D overlays of one session, each rebuilt only when one of the stage results it is
    drawn from changed (the pipeline cache hands back the same result object otherwise): a
    spline slider rebuilds the spline's overlays, not the masks'. Each payload carries a tag,
    unique in this process, that changes exactly when the payload does; :meth:`answer` leaves
    out the payloads whose tags the page already holds."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._entries: dict[str, tuple[tuple, int, dict[str, Any], Any]] = {}

    def answer(
        self,
        rec: Reconstruction,
        calib: StereoCalibration,
        known: frozenset[int] = frozenset(),
        keys: frozenset[str] | None = None,
    ) -> dict[str, Any]:
        """``{"shape", key: payload ..., "_pixels", "_tags": {key: tag}, "_later": [key ...]}``
        of every overlay whose stages ran in ``rec``; a payload whose tag is in ``known`` is
        left out (listed in ``_tags`` all the same: the page keeps its copy). With ``keys``
        (the overlays the page shows), the others are neither built nor sent: ``_later``
        names them, for the page to ask once it shows one (a hidden overlay costs nothing:
        at 1920x1080 the ordering graph's is ~180 kB and reads a graph that takes ~90 ms)."""
        out: dict[str, Any] = {
            "shape": list(calib.image_size), "_pixels": {}, "_tags": {}, "_later": []
        }  # fmt: skip
        with self._lock:  # two requests of one page never build the same overlay twice
            for view in OVERLAY_VIEWS.values():
                if not all(stage in rec.runs for stage in view.needs):
                    continue
                if keys is not None and view.key not in keys:
                    out["_later"].append(view.key)
                    continue
                key = tuple(id(rec.runs[s].result) for s in view.needs)
                hit = self._entries.get(view.key)
                if hit is None or hit[0] != key:
                    payload, meta = _overlay_entry(view, rec, calib)
                    # the results are kept with the key: their ids cannot be reused meanwhile
                    results = tuple(rec.runs[s].result for s in view.needs)
                    hit = (key, next(_TAGS), {"payload": payload, "meta": meta}, results)
                    self._entries[view.key] = hit
                tag, entry = hit[1], hit[2]
                out["_tags"][view.key] = tag
                if entry["meta"] is not None:
                    out["_pixels"][view.key] = entry["meta"]
                if tag not in known:
                    out[view.key] = entry["payload"]
        return out

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


_TAGS = itertools.count(1)  # overlay payload tags, unique in the process


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
