"""Outputs of one frame's reconstruction: the result JSON (one schema for the CLI, the Python
API and the page: ``docs/result.schema.json``), the curve as CSV and as a PLY polyline, and
point clouds (PLY).

The pipeline's 3D points are in the left rectified camera frame (OpenCV: x right, y down,
z forward), in the calibration's unit: the stereo points and keypoints come from Q,
Eqs. (4)-(5), the spline from G, Eq. (9). The result JSON reports them in the left camera's
own frame by default (``frame="left"``: R_1^T p, core/rectify.py; the same as the rectified
frame when the input pair was already rectified) or in ``"left_rectified"``.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app.presets import params_hash
from threadrecon.core.pipeline import Reconstruction
from threadrecon.core.rectify import FRAMES, Frame, Rectification, in_frame

SCHEMA_ID = "threadrecon-result/1"
"""Value of the ``schema`` field; bumped when a field changes meaning."""
FRAME_DESCRIPTIONS = {
    "left": "left camera's own (unrectified) frame, OpenCV axes: x right, y down, z forward",
    "left_rectified": "left rectified camera frame, OpenCV axes: x right, y down, z forward",
}

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
        return _array_json(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):  # e.g. the grasp point
        return {f.name: json_safe(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _array_json(a: np.ndarray) -> Any:
    """A numeric array as nested lists in one vectorised pass (NaN/inf -> None); the overlays
    of every slider move go through here, and a per-element walk cost them milliseconds."""
    if a.dtype.kind in "biuU":  # strings too (e.g. an overlay's CSS colours, one a point)
        return a.tolist()
    if a.dtype.kind == "f":
        finite = np.isfinite(a)
        if finite.all():
            return a.tolist()
        out = a.astype(object)
        out[~finite] = None
        return out.tolist()
    return json_safe(a.tolist())


@dataclass(frozen=True)
class InputFile:
    """One input of a reconstruction: its role ("left", "right", "stereo", "mask", "mask_left",
    "mask_right", "calibration", "calibration_right"), file name (None for an array given in
    memory) and the SHA-256 of its bytes (of the array's bytes for an array)."""

    role: str
    name: str | None
    sha256: str

    @classmethod
    def of_file(cls, role: str, path: str | Path) -> InputFile:
        path = Path(path)
        h = hashlib.sha256()
        with path.open("rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        return cls(role, path.name, h.hexdigest())

    @classmethod
    def of_array(cls, role: str, array: np.ndarray) -> InputFile:
        a = np.ascontiguousarray(array)
        h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
        return cls(role, None, h.hexdigest())

    def to_json(self) -> dict[str, Any]:
        return {"role": self.role, "name": self.name, "sha256": self.sha256}


def software_version() -> str:
    """The installed ``threadrecon`` distribution's version."""
    import threadrecon

    return threadrecon.__version__


def result_json(
    rec: Reconstruction,
    rect: Rectification | None = None,
    frame: Frame = "left",
    preset: str | None = None,
    inputs: Sequence[InputFile] = (),
) -> dict[str, Any]:
    """The one JSON of a reconstruction (schema ``docs/result.schema.json``), JSON-safe.

    ``status`` "ok" or "failed" with ``reasons`` (one line each) and ``error`` (their join);
    ``frame`` and ``unit`` of every 3D value; ``points`` (n, 3) dense centerline,
    ``control_points``, ``knots``, ``degree`` (B-spline over u in [0, 1]), ``length``: None
    when there is no final spline; ``confidence`` (n,) per point when the pipeline gives one;
    ``keypoints`` as :func:`_keypoints`; ``timings_ms`` per stage; provenance: ``preset``,
    ``params_hash``, ``params`` (every parameter), ``inputs``, ``software``, and the
    ``rectification`` that was applied (``R1``: left -> left rectified, p_rect = R1 p_left).
    ``rect`` None means the pair was rectified already (identity).
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    R1 = np.eye(3) if rect is None else rect.R1

    def moved(points: np.ndarray) -> np.ndarray:
        if rect is None or frame == "left_rectified":
            return points
        return in_frame(points, rect, frame)

    message = rec.message
    out: dict[str, Any] = {
        "schema": SCHEMA_ID,
        "software": {"name": "threadrecon", "version": software_version()},
        "status": rec.status,
        "reasons": list(rec.reasons),
        "error": message,
        "failed_stage": rec.failed_stage,
        "frame": frame,
        "frame_description": FRAME_DESCRIPTIONS[frame],
        "unit": None,
        "points": None,
        "control_points": None,
        "knots": None,
        "degree": None,
        "length": None,
        "confidence": None,
        "fallback": None,
        "spline_status": None,
        "keypoints": None,
        "n_keypoints": rec["clustering"].count if "clustering" in rec.runs else None,
        "n_reliable": rec["reliability"].count if "reliability" in rec.runs else None,
        "timings_ms": {k: round(v, 3) for k, v in rec.timings_ms.items()},
        "preset": preset,
        "params_hash": params_hash(rec.params),
        "params": rec.params.to_dict(),
        "inputs": [i.to_json() for i in inputs],
        "rectification": {
            "applied": rect is not None and not rect.identity,
            "R1": R1,
        },
    }
    if "camera" in rec.runs:
        cam = rec["camera"]
        spline = rec["spline"]
        confidence = getattr(cam, "confidence", None)
        out.update(
            unit=cam.unit,
            points=moved(cam.points),
            control_points=moved(cam.ctrl),  # a rotation maps a B-spline's control points
            knots=cam.knots,
            degree=cam.degree,
            length=cam.length,
            confidence=None if confidence is None else np.asarray(confidence, dtype=float),
            fallback=not spline.ok,
            spline_status=spline.status,
        )
    if "check" in rec.runs:
        chk = rec["check"]
        g = chk.grasp
        out.update(
            score=chk.score,
            rating=chk.rating,
            confidence=chk.confidence,
            grasp=None
            if g is None
            else {
                "point": moved(g.point[None, :])[0],
                "confidence": g.confidence,
                "tangent": moved(g.tangent[None, :])[0],  # a rotation, no shift
                "index": g.index,
                "from_end": g.from_end,
                "distance": g.distance,
            },
            check=chk.evidence(),
        )
    if "clustering" in rec.runs and "reliability" in rec.runs:
        kp = _keypoints(rec)
        kp["points"] = moved(kp["points"]) if len(kp["points"]) else kp["points"]
        out["keypoints"] = kp
    return json_safe(out)


def spline_json(
    rec: Reconstruction,
    rect: Rectification | None = None,
    frame: Frame = "left",
    preset: str | None = None,
    inputs: Sequence[InputFile] = (),
) -> dict[str, Any]:
    """:func:`result_json` of a reconstruction that has a final spline (the page's download).
    Raises ValueError when there is no final spline."""
    _require(rec, "camera", "no final spline")
    return result_json(rec, rect, frame, preset, inputs)


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
    floats written to round-trip exactly; with a check run, a last column ``confidence``
    (the check's per-point confidence in [0, 1])."""
    _require(rec, "camera", "no final spline")
    cam = rec["camera"]
    conf = rec["check"].confidence.tolist() if "check" in rec.runs else None
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["i", *(f"{a}_{cam.unit}" for a in "xyz"), *(["confidence"] if conf else [])])
    for i, (x, y, z) in enumerate(cam.points.tolist()):
        w.writerow([i, repr(x), repr(y), repr(z), *([repr(conf[i])] if conf else [])])
    return buf.getvalue()


def ply_bytes(
    points: np.ndarray,
    colors: np.ndarray | None = None,
    comments: Sequence[str] = (),
    edges: np.ndarray | None = None,
) -> bytes:
    """Binary little-endian PLY of ``points`` (N, 3) finite, as float32 x y z, and ``colors``
    (N, 3) uint8 as uchar red green blue (grey when None); ``comments`` go in the header.
    ``edges`` (E, 2) vertex indices become an ``edge`` element (int vertex1, vertex2): a line
    set in Open3D, trimesh and plyfile."""
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
    edge_block = b""
    edge_header: list[str] = []
    if edges is not None:
        e = np.asarray(edges)
        if e.ndim != 2 or e.shape[1] != 2 or not np.issubdtype(e.dtype, np.integer):
            raise ValueError(f"edges must be (E, 2) integers, got {e.shape} {e.dtype}")
        if e.size and (e.min() < 0 or e.max() >= len(pts)):
            raise ValueError(f"edges must index the {len(pts)} vertices")
        edge_block = e.astype("<i4").tobytes()
        edge_header = [f"element edge {len(e)}", "property int vertex1", "property int vertex2"]
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
        *edge_header,
        "end_header",
    ]
    return ("\n".join(header) + "\n").encode("ascii") + vertices.tobytes() + edge_block


def polyline_ply(
    points: np.ndarray, unit: str, frame: str = "left", comments: Sequence[str] = ()
) -> bytes:
    """The curve ``points`` (n, 3) as a PLY polyline: n vertices coloured from cyan (u = 0) to
    magenta (u = 1) and n - 1 edges (i, i + 1)."""
    pts = np.asarray(points)
    u = np.linspace(0.0, 1.0, len(pts))[:, None]
    ramp = (1 - u) * np.array(SPLINE_START_RGB) + u * np.array(SPLINE_END_RGB)
    idx = np.arange(max(len(pts) - 1, 0))
    return ply_bytes(
        pts,
        np.round(ramp).astype(np.uint8),
        ("threadrecon curve", f"unit {unit}", f"frame {frame}", *comments),
        edges=np.stack([idx, idx + 1], axis=1),
    )


def cloud_ply(rec: Reconstruction, layer: str) -> bytes:
    """One layer of the reconstruction as a PLY point cloud.

    ``stereo``: every segmented left pixel's 3D point (Eqs. (4)-(5); pixels without a positive
    disparity are left out), coloured by reliability R (red 0 .. yellow .. green 1);
    ``reliable``: the reliable pixels P_L^R only, same colours; ``keypoints``: the cluster
    centroids K, coloured by their mean R; ``spline``: the dense final centerline as a
    polyline (:func:`polyline_ply`). All in the left rectified frame (the 3D view's).
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
        cam = rec["camera"]
        return polyline_ply(
            cam.points, cam.unit, "left_rectified", comments=(f"threadrecon layer {layer}",)
        )
    unit = rec["camera"].unit if "camera" in rec.runs else "calibration units"
    comments = (f"threadrecon layer {layer}", f"unit {unit}", "frame left_rectified")
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


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` as strict JSON (no NaN) through a temporary file: never half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(json_safe(data), indent=1, allow_nan=False, default=_json_default))
    tmp.replace(path)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
