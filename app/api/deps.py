"""What the routes share: the server state as a dependency, and JSON answers."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.responses import JSONResponse

from threadrecon.app.api import schemas
from threadrecon.app.api.state import AppState
from threadrecon.app.export import json_safe


def _state(request: Request) -> AppState:
    return request.app.state.core


State = Annotated[AppState, Depends(_state)]


def answer(data: Any) -> JSONResponse:
    """``data`` as strict JSON (NaN and infinities as null)."""
    return JSONResponse(json_safe(data))


def session_answer(data: dict[str, Any]) -> schemas.SessionState:
    """A session's state, checked against its response model."""
    return schemas.SessionState.model_validate(json_safe(data))


def stage_answer(data: dict[str, Any]) -> schemas.StageAnswer:
    return schemas.StageAnswer.model_validate(data)
