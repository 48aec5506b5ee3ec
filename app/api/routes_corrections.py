"""The user's corrections of a frame's thread masks: list, add, undo, redo, clear, and the
corrected masks as PNG.

A correction is refused (422, nothing stored) when it names a pixel outside the image, a
brush beyond ``MAX_RADIUS_PX``, when it would change nothing (no piece near a "remove" click,
no thread contrast at an "add" click, a stroke over no thread pixel) or when it would leave a
view without thread pixels; an unknown frame is 404. Every accepted correction is stored
before the frame is run again, so that no error of the run can lose it.
"""

from __future__ import annotations

import contextlib
from typing import Annotated, Literal

import cv2
import numpy as np
from fastapi import APIRouter, Body
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field

from threadrecon.app.api.deps import State, answer
from threadrecon.app.api.state import AppState
from threadrecon.app.errors import Conflict, Invalid, TimedOut
from threadrecon.app.session import Session
from threadrecon.core.corrections import (
    MAX_RADIUS_PX,
    MAX_STROKE_POINTS,
    CorrectedPair,
    Correction,
    apply_corrections,
)

router = APIRouter(prefix="/api/frames", tags=["corrections"])
_NOTHING = {
    "remove": "no segmented piece within {r:g} px of ({x}, {y}) in the {view} view",
    "add": "no thread contrast within {r:g} px of ({x}, {y}) in the {view} view",
    "erase": "the stroke crosses no thread pixel of the {view} view",
    "paint": "the stroke adds no pixel to the {view} view",
}


class CorrectionBody(BaseModel):
    op: Literal["remove", "add", "erase", "paint"]
    view: Literal["left", "right"]
    points: list[tuple[int, int]] = Field(min_length=1, max_length=MAX_STROKE_POINTS)
    """(x, y) pixels of the rectified image: one click (remove, add) or a brush stroke."""
    radius: float = Field(8.0, gt=0.0, allow_inf_nan=False)
    """px: brush radius (erase, paint) or how far from the click a piece is looked for."""
    stereo: bool = False
    """remove: the piece's stereo partner in the other view goes too."""
    session: str | None = None
    """The session that shows the result (others showing the frame run again too)."""
    wait: bool = True


class ActionBody(BaseModel):
    session: str | None = None
    wait: bool = True


@router.get("/{frame_id:path}/corrections")
def list_corrections(state: State, frame_id: str) -> JSONResponse:
    """The frame's active corrections, oldest first, and whether undo / redo can act."""
    state.frame(frame_id)
    return answer(state.corrections.summary(frame_id))


@router.post("/{frame_id:path}/corrections")
async def add_correction(state: State, frame_id: str, body: CorrectionBody) -> JSONResponse:
    """Store a correction of the frame's mask and run the frame again with it."""
    state.frame(frame_id)
    if body.radius > MAX_RADIUS_PX:
        raise Invalid(f"radius must be at most {MAX_RADIUS_PX:g} px, got {body.radius:g}")
    try:
        points = tuple(tuple(p) for p in body.points)
        c = Correction(body.op, body.view, points, body.radius, body.stereo)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    s = state.session(body.session)
    await run_in_threadpool(_check, state, s, frame_id, c)
    stored = await run_in_threadpool(state.corrections.add, frame_id, c)
    out = await _rerun(state, s, frame_id, body.wait)
    return answer({"correction": stored.to_dict(), **out})


async def _history(
    state: AppState, frame_id: str, body: ActionBody | None, op: str
) -> JSONResponse:
    """Undo or redo one correction of the frame, then run it again."""
    state.frame(frame_id)
    body = body or ActionBody()
    s = state.session(body.session)
    changed = await run_in_threadpool(getattr(state.corrections, op), frame_id)
    key = {"undo": "undone", "redo": "redone"}[op]
    return answer({key: changed.to_dict(), **await _rerun(state, s, frame_id, body.wait)})


@router.post("/{frame_id:path}/corrections/undo")
async def undo(
    state: State, frame_id: str, body: Annotated[ActionBody | None, Body()] = None
) -> JSONResponse:
    """Undo the frame's newest correction (409 when there is none)."""
    return await _history(state, frame_id, body, "undo")


@router.post("/{frame_id:path}/corrections/redo")
async def redo(
    state: State, frame_id: str, body: Annotated[ActionBody | None, Body()] = None
) -> JSONResponse:
    """Apply again the correction undone last (409 when there is none)."""
    return await _history(state, frame_id, body, "redo")


@router.post("/{frame_id:path}/corrections/clear")
async def clear(
    state: State, frame_id: str, body: Annotated[ActionBody | None, Body()] = None
) -> JSONResponse:
    """Back to the segmenter's masks in both views; undoable like any correction."""
    state.frame(frame_id)
    body = body or ActionBody()
    if not await run_in_threadpool(state.corrections.active, frame_id):
        raise Conflict(f"frame {frame_id} has no corrections to clear")
    s = state.session(body.session)
    stored = await run_in_threadpool(state.corrections.add, frame_id, Correction("clear", "both"))
    out = await _rerun(state, s, frame_id, body.wait)
    return answer({"correction": stored.to_dict(), **out})


@router.get("/{frame_id:path}/mask.png")
async def mask_png(
    state: State,
    frame_id: str,
    view: Literal["both", "left", "right"] = "both",
    session: str | None = None,
) -> Response:
    """The frame's thread masks P as the run uses them (segmented, with the corrections), in
    the rectified images, white on black: ``both`` side by side (left | right, the
    ``<stem>_mask.png`` of a side-by-side frame), or one view."""
    state.frame(frame_id)
    s = state.session(session)
    seg = await _segment_of(state, s, frame_id)
    masks = {"left": seg.P_L, "right": seg.P_R}
    img = np.hstack([masks["left"], masks["right"]]) if view == "both" else masks[view]
    ok, png = cv2.imencode(".png", img.astype(np.uint8) * 255)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    name = frame_id.rsplit("/", 1)[-1] + ("" if view == "both" else f"_{view}") + "_mask.png"
    return Response(
        png.tobytes(), media_type="image/png",
        headers={"Content-Disposition": f'attachment; filename="{_safe(name)}"'},
    )  # fmt: skip


# --- helpers -----------------------------------------------------------------------------


def _check(state: AppState, s: Session, frame_id: str, c: Correction) -> None:
    """Refuse a correction outside the image, or one that changes nothing or empties a view
    (tried on the segmentation the session shows, when it is the frame's current one)."""
    try:
        loaded = state.library.load(frame_id)
    except (ValueError, OSError) as exc:
        raise Invalid(f"cannot load frame {frame_id}: {exc}") from None
    try:
        c.check_inside(loaded.pair.shape)
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    rec = s.rec
    if rec is None or not s.shows(frame_id) or "segment" not in rec.runs:
        return
    seg = rec["segment"]
    done = seg.corrections if isinstance(seg, CorrectedPair) else ()
    if done != state.corrections.active(frame_id):
        return  # a run with the newest corrections is under way: nothing to try on
    try:
        tried = apply_corrections(
            seg, (c,), rec.params.segment.lift_dilate_px, (loaded.pair.left, loaded.pair.right)
        )
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    if tried.changed_px[-1] == 0:
        x, y = c.points[0]
        raise Invalid(_NOTHING[c.op].format(r=c.radius, x=x, y=y, view=c.view))


async def _rerun(state: AppState, s: Session, frame_id: str, wait: bool) -> dict:
    """Run the frame again in ``s`` and in every other session showing it; with ``wait``,
    the state of ``s`` once done."""
    seq = s.submit(frame_id=frame_id)
    for other in state.sessions.all():
        if other is not s and other.frame_id == frame_id:
            with contextlib.suppress(Conflict):  # closed meanwhile
                other.submit()
    out = await run_in_threadpool(state.corrections.summary, frame_id)
    if wait:
        if not await s.finished(seq, state.config.run_timeout_s):
            raise TimedOut("the run did not finish in time (the correction is stored)")
        out["state"] = await run_in_threadpool(s.state)
    return out


async def _segment_of(state: AppState, s: Session, frame_id: str) -> CorrectedPair:
    """The segment stage's result of the frame with its current corrections."""
    rec = s.rec
    current = await run_in_threadpool(state.corrections.active, frame_id)
    fresh = rec is not None and s.shows(frame_id) and not s.busy and "segment" in rec.runs
    if fresh:
        seg = rec["segment"]  # type: ignore[index]
        fresh = (seg.corrections if isinstance(seg, CorrectedPair) else ()) == current
    if not fresh:
        seq = s.submit(frame_id=frame_id)
        if not await s.finished(seq, state.config.run_timeout_s):
            raise TimedOut("the run did not finish in time")
        rec = s.rec
    if rec is None or "segment" not in rec.runs:
        reason = s.load_error or (rec.message if rec is not None else None) or "no segmentation"
        raise Conflict(f"frame {frame_id} has no mask: {reason}")
    return rec["segment"]


def _safe(name: str) -> str:
    """A file name for a header: ASCII letters, digits, dot, dash and underscore only."""
    return "".join(ch if ch.isascii() and (ch.isalnum() or ch in "._-") else "_" for ch in name)
