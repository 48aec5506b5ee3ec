"""Request and response bodies of the REST API."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from threadrecon.app.session import MAX_PAUSE_S
from threadrecon.app.views.registry import OverlayKind

PauseMs = Field(0.0, ge=0.0, le=1000.0 * MAX_PAUSE_S, allow_inf_nan=False)


class RunBody(BaseModel):
    params: dict[str, Any] | None = None
    """Partial parameters ``{stage: {name: value}}`` applied over the session's current ones."""
    preset: str | None = None
    """Start from this preset instead of the session's current parameters."""
    until: str | None = None
    """Compute and show the stages up to this one (default: all)."""
    session: str | None = None
    pause_ms: float = PauseMs
    wait: bool = True


class StepBody(BaseModel):
    action: Literal["run", "next", "all"]
    """"run" (all stages, streamed one by one), "next" (reveal one more stage), "all"."""
    pause_ms: float = Field(350.0, ge=0.0, le=1000.0 * MAX_PAUSE_S, allow_inf_nan=False)


class RatingBody(BaseModel):
    score: Any = None
    """1..5 (whole number)."""
    note: Any = ""
    session: str | None = None
    """The session whose reconstruction is rated (its preset and parameters are recorded)."""


class SavePresetBody(BaseModel):
    name: str
    session: str | None = None
    overwrite: bool = False


class UsePresetBody(BaseModel):
    name: str
    wait: bool = False


class EvaluateBody(BaseModel):
    session: str | None = None
    preset: str | None = None


class NewSession(BaseModel):
    session: str
    viser_port: int
    viser_path: str


class Frame(BaseModel):
    id: str
    name: str
    kind: str
    has_ground_truth: bool
    status: str | None
    rating: int | None


class OverlaySpec(BaseModel):
    key: str
    label: str
    kind: OverlayKind
    color: str
    color2: str | None
    on: bool
    dash: bool
    count: bool
    reveal: str | None


class Info(BaseModel):
    viser_port: int
    data_dir: str
    stages: list[str]
    controls: list[dict[str, Any]]
    defaults: dict[str, Any]
    metrics: list[dict[str, str]]
    """Metric keys with their label and unit, in display order (the page has no copy)."""
    layers: list[str]
    """Point-cloud layers that can be exported as PLY."""
    overlays: list[OverlaySpec]
    """The 2D overlays over the stereo images, in drawing order (the page's toggles)."""
    exports: list[str]


class SavedPreset(BaseModel):
    name: str
    path: str


class Preset(BaseModel):
    name: str
    builtin: bool
    params: dict[str, Any]
    diff: list[dict[str, Any]]
