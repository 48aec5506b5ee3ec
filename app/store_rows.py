"""Rows of the rating store as strict JSON: NaN is stored as null and read back as NaN."""

from __future__ import annotations

import json
import math
from typing import Any


def nan_to_null(obj: Any) -> Any:
    """Non-finite floats -> None, numpy scalars -> Python, tuples -> lists, recursively."""
    if isinstance(obj, dict):
        return {k: nan_to_null(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [nan_to_null(v) for v in obj]
    if hasattr(obj, "dtype") and hasattr(obj, "item") and getattr(obj, "ndim", None) == 0:
        obj = obj.item()  # numpy scalar
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps(name: str, obj: Any) -> str:
    try:
        return json.dumps(nan_to_null(obj), allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} cannot be stored as JSON: {exc}") from None


def evaluation_from_row(r: tuple[Any, ...]) -> dict[str, Any]:
    eid, created_at, preset, params_hash, n_frames, params, rows, summary = r
    frames = [{k: math.nan if v is None else v for k, v in row.items()} for row in json.loads(rows)]
    return {
        "id": eid,
        "created_at": created_at,
        "preset": preset,
        "params_hash": params_hash,
        "n_frames": n_frames,
        "params": json.loads(params),
        "rows": frames,
        "summary": json.loads(summary),
    }
