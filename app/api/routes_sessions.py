"""Sessions (one per browser tab): state (long poll), parameters, stepper, overlays, pixels."""

from __future__ import annotations

from typing import Annotated, Any

import msgspec
from fastapi import APIRouter, Body, Query
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response

from threadrecon.app.api import schemas
from threadrecon.app.api.deps import State, session_answer, stage_answer
from threadrecon.app.api.state import AppState
from threadrecon.app.errors import Conflict, Invalid, NotFound, TimedOut
from threadrecon.app.library import merge_params
from threadrecon.app.session import Session
from threadrecon.app.views import pixel_info, stage_json
from threadrecon.core.pipeline import ReconParams

router = APIRouter(prefix="/api/sessions", tags=["sessions"])
MAX_POLL_S = 25.0  # a long poll answers after this long even without news
SETTLE_S = 0.15  # a long poll that finds a run going on waits this long for it to end


async def _reply(state: AppState, s: Session, seq: int, wait: bool) -> schemas.SessionState:
    if wait and not await s.finished(seq, state.config.run_timeout_s):
        raise TimedOut("the run did not finish in time")
    return session_answer(await run_in_threadpool(s.state))


@router.post("")
def new_session(state: State, frame_id: str | None = None) -> schemas.NewSession:
    """A session for one browser tab; its viser client connects to ``viser_path``."""
    if frame_id is not None:
        state.frame(frame_id)
    s = state.sessions.create()
    s.submit(frame_id=frame_id)
    return schemas.NewSession(
        session=s.id, viser_port=state.viser_port, viser_path=f"/session/{s.id}"
    )


@router.delete("/{sid}", status_code=204)
def close_session(state: State, sid: str) -> Response:
    """Close the session now (a tab that goes away); idle sessions also expire by themselves."""
    state.sessions.delete(sid)
    return Response(status_code=204)


@router.get("/{sid}", response_model=schemas.SessionState)
async def session_state(
    state: State,
    sid: str,
    since: int | None = None,
    timeout: float = Query(0.0, ge=0.0, le=MAX_POLL_S),
    overlay: str | None = None,
    keys: str | None = None,
) -> JSONResponse:
    """The session's stepper, metrics and errors; with ``since``, waits up to ``timeout`` s
    for a version newer than ``since`` (a long poll: no thread is held while waiting). A run
    in progress is answered when it ends or ``SETTLE_S`` after the change, whichever is
    first: a slider's run is one answer, not one per stage. With ``overlay`` (the tags the page
    holds, as for ``/overlay``), the answer of a finished run carries its 2D overlays too
    (``"overlay"``), saving the page the round trip; ``keys`` as for ``/overlay``. A long
    poll's answer comes before the run's last 3D layers are drawn (``Session.polling``)."""
    s = state.session(sid)
    tags = None if overlay is None else _tags(overlay)
    shown = _keys(keys)
    if since is None or timeout <= 0:
        body, _ = await run_in_threadpool(_state_and_overlay, s, tags, shown)
        return Response(body, media_type="application/json")
    with s.polling() as answered:  # a run's last 3D layers wait for this answer
        if await s.changed(since, timeout) and s.busy:
            await s.finished(s.seq, SETTLE_S)
        body, version = await run_in_threadpool(_state_and_overlay, s, tags, shown)
        answered(version)
    return Response(body, media_type="application/json")


def _state_and_overlay(
    s: Session, tags: frozenset[int] | None, keys: frozenset[str] | None
) -> tuple[bytes, int]:
    """The state as JSON, and with ``tags`` the overlays (``keys`` of them) once the run has
    finished, and the state's version; encoded here, in one thread hop off the event loop
    (a spline move's answer is ~40 kB: msgspec's encoder, ~10x the standard library's)."""
    data = s.state()
    answer = session_answer(data).model_dump(mode="json")
    if tags is not None and not data["busy"]:
        answer["overlay"] = s.overlay(tags, keys)
    return msgspec.json.encode(answer), data["version"]


def _keys(keys: str | None) -> frozenset[str] | None:
    """The overlays a page shows (comma-separated keys; None: every overlay)."""
    return None if keys is None else frozenset(k for k in keys.split(",") if k)


def _tags(known: str) -> frozenset[int]:
    try:
        return frozenset(int(t) for t in known.split(",") if t)
    except ValueError:
        raise Invalid(f"known must be comma-separated integer tags, got {known[:80]!r}") from None


@router.patch("/{sid}/params")
async def patch_params(
    state: State, sid: str, patch: Annotated[dict[str, Any], Body()], wait: bool = False
) -> schemas.SessionState:
    """Change parameters (``{stage: {name: value}}``); 422 names a refused parameter."""
    s = state.session(sid)
    seq = s.submit(params=merge_params(s.params, patch))
    return await _reply(state, s, seq, wait)


@router.post("/{sid}/params/reset")
async def reset_params(state: State, sid: str, wait: bool = False) -> schemas.SessionState:
    s = state.session(sid)
    seq = s.submit(params=ReconParams(), preset="default")
    return await _reply(state, s, seq, wait)


@router.post("/{sid}/step")
async def step(
    state: State, sid: str, body: schemas.StepBody, wait: bool = False
) -> schemas.SessionState:
    """The stage stepper: run (streamed), next (reveal one more stage) or all."""
    s = state.session(sid)
    seq = s.step(body.action, pause_s=body.pause_ms / 1000.0)
    return await _reply(state, s, seq, wait)


@router.post("/{sid}/preset")
async def use_preset(state: State, sid: str, body: schemas.UsePresetBody) -> schemas.SessionState:
    """Load a preset into the session: every slider takes its value, then it runs."""
    s = state.session(sid)
    seq = s.submit(params=state.preset(body.name), preset=body.name)
    return await _reply(state, s, seq, body.wait)


@router.get("/{sid}/overlay")
def session_overlay(
    state: State, sid: str, known: str = "", keys: str | None = None
) -> JSONResponse:
    """The 2D overlays of the session's current reconstruction. ``known``: comma-separated
    tags (``_tags`` of an earlier answer) of payloads the page holds; those are left out.
    ``keys``: the comma-separated keys of the overlays the page shows; the others are not
    built (``_later`` names them). Without it, every overlay."""
    return JSONResponse(state.session(sid).overlay(_tags(known), _keys(keys)))


@router.get("/{sid}/pixel")
def session_pixel(state: State, sid: str, x: int, y: int) -> JSONResponse:
    """Pixel inspector: the energy curve E(d) of a left-image pixel, d_min, d_next, R, depth.
    The pixel becomes the session's inspected pixel (marked in 3D)."""
    s = state.session(sid)
    rec = s.rec
    if rec is None:
        raise Conflict("no reconstruction yet")
    try:
        info = pixel_info(rec, x, y)
    except LookupError as exc:
        raise Conflict(str(exc.args[0])) from None
    except (ValueError, OverflowError) as exc:
        raise Invalid(str(exc)) from None
    s.set_inspect(info)
    return JSONResponse(info)


@router.get("/{sid}/stages/{stage}")
def session_stage(state: State, sid: str, stage: str) -> schemas.StageAnswer:
    s = state.session(sid)
    rec = s.rec
    if rec is None:
        raise Conflict(s.load_error or "no reconstruction yet")
    try:
        return stage_answer(stage_json(rec, stage))
    except KeyError as exc:
        raise NotFound(str(exc.args[0])) from None
    except LookupError as exc:
        raise Conflict(str(exc.args[0])) from None
