"""Whole-dataset evaluations: a background job, saved results, comparison of two."""

from __future__ import annotations

from fastapi import APIRouter, Query
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from threadrecon.app.api import schemas
from threadrecon.app.api.deps import State, answer
from threadrecon.app.errors import NotFound
from threadrecon.app.jobs import compare

router = APIRouter(prefix="/api/evaluations", tags=["evaluations"])
HEAD = ("id", "preset", "params_hash", "created_at")


@router.post("")
def start_evaluation(state: State, body: schemas.EvaluateBody) -> JSONResponse:
    """Evaluate every frame of the data folder in the background with the session's
    current parameters (or a named preset); poll ``/api/evaluations/current``."""
    if body.preset is not None:
        params, name = state.preset(body.preset), body.preset
    else:
        s = state.session(body.session)
        params, name = s.params, s.preset
    return answer(state.start_job(params, name).snapshot())


@router.get("/current")
def current_evaluation(state: State, since: int = Query(0, ge=0, le=10**9)) -> JSONResponse:
    """Progress and rows (from row ``since`` on) of the running or last evaluation (null
    when none was started since the server started)."""
    job = state.job
    if job is None:
        return JSONResponse(None)
    snap = job.snapshot(since)
    snap["saved_id"] = state.job_saved
    return answer(snap)


@router.post("/current/cancel")
async def cancel_evaluation(state: State) -> JSONResponse:
    """Stop the running evaluation after its current frame."""
    job = state.current_job()
    job.cancel()
    await run_in_threadpool(job.wait, state.config.run_timeout_s)
    return answer(job.snapshot())


@router.get("")
def evaluations(state: State) -> JSONResponse:
    """Saved evaluations, newest first."""
    return answer(state.store.evaluations())


@router.get("/compare")
def compare_evaluations(
    state: State, a: int = Query(ge=0, le=2**62), b: int = Query(ge=0, le=2**62)
) -> JSONResponse:
    """Two saved evaluations side by side, frame by frame (b - a), with a mean row."""
    ea, eb = state.store.evaluation(a), state.store.evaluation(b)
    for i, e in ((a, ea), (b, eb)):
        if e is None:
            raise NotFound(f"no saved evaluation {i}")
    return answer(
        {
            "a": {k: ea[k] for k in HEAD},
            "b": {k: eb[k] for k in HEAD},
            "rows": compare(ea["rows"], eb["rows"]),
        }
    )


@router.get("/{eid}")
def evaluation(state: State, eid: str) -> JSONResponse:
    """One saved evaluation (``last`` for the newest): rows, summary, parameters."""
    if eid == "last":  # the newest, or null when none was saved yet
        return answer(state.store.last_evaluation())
    e = state.store.evaluation(int(eid)) if eid.isdigit() and len(eid) < 19 else None
    if e is None:
        raise NotFound(f"no saved evaluation {eid!r}")
    return answer(e)
