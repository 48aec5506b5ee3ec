"""Frames of the data folder: list, images, runs and stage results."""

from __future__ import annotations

from typing import Annotated

import cv2
import numpy as np
from fastapi import APIRouter, Body
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from threadrecon.app.api import schemas
from threadrecon.app.api.deps import State, session_answer, stage_answer
from threadrecon.app.api.routes_sequences import sequence_entries
from threadrecon.app.errors import Conflict, Invalid, NotFound, TimedOut
from threadrecon.app.library import merge_params
from threadrecon.app.views import stage_json
from threadrecon.core.pipeline import STAGES

router = APIRouter(prefix="/api/frames", tags=["frames"])


@router.get("")
def frames(state: State) -> list[schemas.Frame]:
    """Every frame of the data folder, with the status of its last run and its rating."""
    status = state.sessions.frame_status
    ratings = state.store.latest_all()
    stills = [
        schemas.Frame(
            id=f.id,
            name=f.name,
            kind=f.kind,
            has_ground_truth=f.has_ground_truth,
            status=status.get(f.id),
            rating=ratings[f.id].score if f.id in ratings else None,
        )  # fmt: skip
        for f in state.library.frames.values()
    ]
    return sorted(stills + sequence_entries(state), key=lambda f: f.id)


@router.get("/{frame_id:path}/images/{side}")
def frame_image(state: State, frame_id: str, side: str) -> Response:
    """The rectified left or right image as PNG."""
    state.frame(frame_id)
    if side not in ("left", "right"):
        raise NotFound(f"no image {side!r}: use left or right")
    try:
        loaded = state.library.load(frame_id)
    except (ValueError, OSError) as exc:
        raise Invalid(f"cannot load frame {frame_id}: {exc}") from None
    img = loaded.pair.left if side == "left" else loaded.pair.right
    ok, png = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return Response(
        png.tobytes(), media_type="image/png", headers={"Cache-Control": "max-age=3600"}
    )


@router.post("/{frame_id:path}/run")
async def run_frame(
    state: State, frame_id: str, body: Annotated[schemas.RunBody | None, Body()] = None
) -> schemas.SessionState:
    """Select the frame in a session (default: the API session) and run it with the given
    parameters; answers with the session state when done (waiting holds no thread)."""
    state.frame(frame_id)
    body = body or schemas.RunBody()
    session = state.session(body.session)
    base = state.preset(body.preset) if body.preset is not None else session.params
    params = merge_params(base, body.params or {})
    if body.until is not None and body.until not in STAGES:
        raise Invalid(f"until: unknown stage {body.until!r}")
    reveal = STAGES.index(body.until) + 1 if body.until else len(STAGES)
    seq = session.submit(
        frame_id=frame_id, params=params, reveal=reveal, pause_s=body.pause_ms / 1000.0,
        preset=body.preset,
    )  # fmt: skip
    if body.wait and not await session.finished(seq, state.config.run_timeout_s):
        raise TimedOut("the run did not finish in time")
    return session_answer(await run_in_threadpool(session.state))


@router.get("/{frame_id:path}/stages/{stage}")
async def frame_stage(
    state: State, frame_id: str, stage: str, session: str | None = None
) -> schemas.StageAnswer:
    """One stage's result of the frame as the session last computed it (the frame is run
    with the session's parameters first if the session shows another frame)."""
    state.frame(frame_id)
    if stage not in STAGES:
        raise NotFound(f"unknown stage {stage!r} (stages: {', '.join(STAGES)})")
    s = state.session(session)
    fresh = s.frame_id == frame_id and s.shows(frame_id)
    seq = s.seq if fresh else s.submit(frame_id=frame_id)
    if not await s.finished(seq, state.config.run_timeout_s):
        raise TimedOut("the run did not finish in time")
    rec = s.rec
    if rec is None:
        raise Conflict(s.load_error or "no reconstruction")
    try:
        return stage_answer(await run_in_threadpool(stage_json, rec, stage))
    except LookupError as exc:
        raise Conflict(str(exc.args[0])) from None
