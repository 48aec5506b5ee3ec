"""Exports of the current frame: the final spline (JSON, CSV) and point clouds (PLY)."""

from __future__ import annotations

import json
from urllib.parse import quote

from fastapi import APIRouter
from fastapi.responses import Response

from threadrecon.app.api.deps import State
from threadrecon.app.dataset import frame_inputs, frame_rectification
from threadrecon.app.errors import Conflict, NotFound
from threadrecon.app.export import LAYERS, cloud_ply, spline_csv, spline_json

router = APIRouter(tags=["exports"])
EXPORTS = {  # export name -> media type
    "spline.json": "application/json",
    "spline.csv": "text/csv",
    **{f"{layer}.ply": "application/octet-stream" for layer in LAYERS},
}


def content_disposition(filename: str) -> str:
    """``attachment`` with an ASCII fallback name and the exact name in RFC 5987 form, so
    that any frame name (Unicode, quotes, backslashes) gives a valid header."""
    ascii_name = "".join(
        c if c.isascii() and c.isprintable() and c not in '"\\;' else "_" for c in filename
    )
    return f"attachment; filename=\"{ascii_name}\"; filename*=UTF-8''{quote(filename, safe='')}"


@router.get("/api/sessions/{sid}/export/{name}")
def export(state: State, sid: str, name: str) -> Response:
    """The current frame's final spline (JSON: control points, knots, degree, dense
    points, keypoint reliability; CSV: dense points) or a point cloud as PLY."""
    if name not in EXPORTS:
        raise NotFound(f"no export {name!r} (exports: {', '.join(EXPORTS)})")
    s = state.session(sid)
    rec, loaded = s.rec, s.loaded
    if rec is None or loaded is None:
        raise Conflict(s.load_error or "no reconstruction yet")
    try:
        if name == "spline.json":
            frame = loaded.frame
            result = spline_json(
                rec, frame_rectification(frame), "left", s.preset, frame_inputs(frame)
            )
            data = json.dumps(result, indent=1, allow_nan=False).encode()
        elif name == "spline.csv":
            data = spline_csv(rec).encode()
        else:
            data = cloud_ply(rec, name.removesuffix(".ply"))
    except ValueError as exc:
        raise Conflict(str(exc)) from None
    return Response(
        data, media_type=EXPORTS[name],
        headers={"Content-Disposition": content_disposition(f"{loaded.frame.name}_{name}")},
    )  # fmt: skip
