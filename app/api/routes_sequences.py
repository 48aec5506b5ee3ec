"""Sequences of the data folder: the list, and each one's timeline (per-frame figures computed
in the background with tracking, and the curves of a computed frame).

A sequence's frame k is an ordinary frame of the frames API with the id ``<sequence id>@k``:
selecting it runs every stage in the session, so every layer follows the page's slider.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response

from threadrecon.app.api import schemas
from threadrecon.app.api.deps import State, answer
from threadrecon.app.api.routes_exports import content_disposition
from threadrecon.app.errors import Conflict, Invalid, NotFound
from threadrecon.app.recording import recording_html
from threadrecon.app.timeline import Timeline, Timelines

router = APIRouter(prefix="/api/sequences", tags=["sequences"])


def timelines(request: Request) -> Timelines:
    """The server's timelines (created with the app, see ``app.api.create_app``)."""
    return request.app.state.timelines


def sequence_entries(state: State) -> list[schemas.Frame]:
    """The sequences as entries of the frame list (``kind`` "sequence")."""
    out = []
    status = state.sessions.frame_status
    for e in state.library.sequences.values():
        try:
            count = state.library.sequence(e.id).count
        except Invalid:
            count = None  # unreadable: selecting it says why
        out.append(
            schemas.Frame(
                id=e.id,
                name=e.name,
                kind="sequence",
                has_ground_truth=e.kind == "images",
                status=status.get(e.frame_id(0)),
                rating=None,
                count=count,
                source=e.kind,
            )  # fmt: skip
        )
    return out


@router.get("")
def sequences(state: State) -> list[schemas.Frame]:
    """Every sequence of the data folder (image folders, videos, ROS bags)."""
    return sequence_entries(state)


def _timeline(
    state: State, request: Request, sequence_id: str, session: str | None, tracking: bool
) -> Timeline:
    if sequence_id not in state.library.sequences:
        raise NotFound(f"unknown sequence {sequence_id!r}")
    params = state.session(session).params
    return timelines(request).get(sequence_id, params, tracking)


@router.get("/{sequence_id:path}/timeline")
def timeline(
    state: State,
    request: Request,
    sequence_id: str,
    session: str | None = None,
    tracking: bool = True,
    since: Annotated[int, Query(ge=0)] = 0,
):
    """The sequence's per-frame rows from frame ``since`` on (status, length, confidence,
    timings, tracking flags and, with ground truth, errors), computed in the background with
    the session's parameters; ``done`` once every frame is in. Ask again for more."""
    return answer(_timeline(state, request, sequence_id, session, tracking).snapshot(since))


@router.get("/{sequence_id:path}/curves/{k}")
def curves(
    state: State,
    request: Request,
    sequence_id: str,
    k: int,
    session: str | None = None,
    tracking: bool = True,
):
    """Frame ``k``'s tracked, single-frame and true curves in the left image (px); 404 while
    the timeline has not reached the frame."""
    tl = _timeline(state, request, sequence_id, session, tracking)
    found = tl.curves(k)
    if found is None:
        raise NotFound(f"frame {k} of {sequence_id} is not computed yet ({len(tl.rows)} are)")
    return answer({"frame": k, "curves": found})


@router.get("/{sequence_id:path}/recording.html")
def recording(
    state: State,
    request: Request,
    sequence_id: str,
    session: str | None = None,
    tracking: bool = True,
    frame: Annotated[int | None, Query(ge=0)] = None,
) -> Response:
    """The 3D curves (tracked, single-frame, truth) of every computed frame, or of ``frame``,
    as one self-contained HTML file that opens in a browser with no server."""
    tl = _timeline(state, request, sequence_id, session, tracking)
    frames = tl.recorded(frame)
    if not frames:
        what = "no frame" if frame is None else f"frame {frame} is not"
        raise Conflict(f"nothing to record yet: {what} computed ({len(tl.rows)} are)")
    html, _ = recording_html(frames, baseline=tl.baseline)
    part = "sequence" if frame is None else f"frame{frame}"
    return Response(
        html, media_type="text/html",
        headers={"Content-Disposition": content_disposition(f"{tl.entry.name}_{part}.html")},
    )  # fmt: skip
