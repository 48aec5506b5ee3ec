"""Tuning from the page: start a tune from a session's current setting, follow it trial by
trial, cancel it, read its results, and load a trial into the sliders or save it as a preset."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from threadrecon.app.api.deps import State, answer
from threadrecon.app.errors import Unavailable
from threadrecon.app.tune.job import MAX_TRIALS, Tuner
from threadrecon.app.tune.space import DEFAULT_CONSTRAINTS, OBJECTIVES

router = APIRouter(prefix="/api/tune", tags=["tune"])
CANCEL_WAIT_S = 30.0  # a cancel takes effect before the next frame: seconds at most


def _tuner(request: Request) -> Tuner:
    return request.app.state.tuner


TunerDep = Annotated[Tuner, Depends(_tuner)]


class TuneBody(BaseModel):
    space: dict[str, dict[str, Any]]
    """The parameters that vary: ``{stage: {name: [choices] | {low, high[, step][, log]}}}``,
    each inside the parameter's declared range."""
    session: str | None = None
    """The session whose current setting the others keep (default: the API session)."""
    objective: str = "e_S"
    constraints: list[str] = Field(default_factory=lambda: list(DEFAULT_CONSTRAINTS))
    mode: Literal["search", "grid"] = "search"
    trials: int | None = Field(None, ge=1, le=MAX_TRIALS)
    max_frames: int | None = Field(None, ge=1, le=10**6)
    seed: int = Field(0, ge=0, le=2**31)


class TrialTarget(BaseModel):
    session: str | None = None


class TrialPreset(BaseModel):
    name: str


@router.get("/objectives")
def objectives() -> list[dict[str, str]]:
    """The objectives a tune can optimise, with their direction."""
    return [{"name": o.name, "direction": o.direction, "doc": o.doc} for o in OBJECTIVES.values()]


@router.post("")
def start_tune(state: State, tuner: TunerDep, body: TuneBody) -> JSONResponse:
    """Start a tune on the data folder (one at a time: 409 while one runs); 422 names a bad
    parameter, range, objective or constraint."""
    base = state.session(body.session).params
    cfg = tuner.config(
        body.space,
        base,
        objective=body.objective,
        constraints=body.constraints,
        mode=body.mode,
        trials=body.trials,
        max_frames=body.max_frames,
        seed=body.seed,
    )
    return answer(tuner.start(cfg).snapshot())


@router.get("/current")
def current_tune(tuner: TunerDep, since: int = Query(0, ge=0, le=10**9)) -> JSONResponse:
    """Progress of the running or last tune, with its finished trials from ``since`` on (null
    when none was started since the server started)."""
    if tuner.job is None:
        return JSONResponse(None)
    return answer(tuner.job.snapshot(since))


@router.post("/current/cancel")
async def cancel_tune(tuner: TunerDep) -> JSONResponse:
    """Stop the tune before its next frame; the finished trials stay in its store."""
    job = tuner.current()
    job.cancel()
    await run_in_threadpool(job.wait, CANCEL_WAIT_S)
    return answer(job.snapshot())


@router.get("/current/results")
async def tune_results(tuner: TunerDep) -> JSONResponse:
    """Best trials, parameter importance, the trials' points and the Pareto front."""
    job = tuner.current()
    return JSONResponse(await run_in_threadpool(job.results))


@router.post("/current/trials/{number}/load")
async def load_trial(state: State, tuner: TunerDep, number: int, body: TrialTarget) -> JSONResponse:
    """Put a trial's setting into the session: every slider takes its value, then it runs."""
    job = tuner.current()
    s = state.session(body.session)
    s.submit(params=job.params(number), preset=f"tune-trial-{number}")
    return answer(await run_in_threadpool(s.state))


@router.post("/current/trials/{number}/preset")
def save_trial(tuner: TunerDep, number: int, body: TrialPreset) -> dict[str, str]:
    """Save a trial's setting as a new user preset: a built-in name is refused (403), an
    existing user preset too (409)."""
    try:
        path = tuner.save_trial(number, body.name)
    except OSError as exc:
        if isinstance(exc, FileExistsError):
            raise
        raise Unavailable(f"cannot write preset {body.name!r}: {exc}") from None
    return {"name": body.name, "path": str(path)}
