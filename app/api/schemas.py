"""Request and response bodies of the REST API."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

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


class StageState(BaseModel):
    stage: str
    revealed: bool
    status: Literal["pending", "running", "done", "cached", "fallback", "failed"]
    """"fallback": the spline stage returned its initial curve (the solver did not finish)."""
    ms: float | None = None


class ParamChange(BaseModel):
    key: str
    """``stage.name``."""
    value: Any
    base: Any


class GraspState(BaseModel):
    confidence: float
    from_end: str
    distance: float
    """Arc length from the free end, calibration units."""
    index: int
    """Index of the grasp point in the curve's points."""


class CheckState(BaseModel):
    status: Literal["ok", "suspect", "failed"]
    reasons: list[str]
    score: int
    """The automatic quality score's class, 1-5 (the paper's integer rating scale): the
    continuous ``rating`` rounded, for the confusion table against a person's ratings."""
    rating: float
    """The automatic quality score on the paper's 1-5 scale, continuous (core/check_score.py):
    what ranks frames by their expected error."""
    confidence_min: float | None
    confidence_mean: float | None
    grasp: GraspState | None


class SessionState(BaseModel):
    """What a session shows: its frame, parameters, stepper, status and metrics. Answers every
    session call and frame run (NaN and infinities become null)."""

    model_config = ConfigDict(extra="forbid")

    session: str
    version: int
    """Grows with every change; a long poll waits for a newer one."""
    frame_id: str | None
    shown_frame: str | None
    """The frame whose reconstruction is on screen (None while the first one loads)."""
    busy: bool
    preset: str | None
    params: dict[str, dict[str, Any]]
    params_hash: str
    diff: list[ParamChange]
    """The parameters that differ from the paper's defaults."""
    reveal: int
    stages: list[StageState]
    status: Literal["pending", "ok", "suspect", "failed"]
    failed_stage: str | None
    error: str | None
    reasons: list[str]
    """Every reason for a status other than "ok", in words (the check stage's findings)."""
    check: CheckState | None
    """The check stage's verdict (None before it has run)."""
    metrics: dict[str, float | int | str | None]
    latency_ms: dict[str, float]
    """ms from the request to each stage's result in the scene."""
    timing: dict[str, float] = {}
    """The last request's ms: computing the stages and publishing their views (wall, _cpu)."""
    inspect: dict[str, Any] | None
    """The inspected pixel (see ``/pixel``), or None."""
    unit: str | None


class StageAnswer(BaseModel):
    """One stage's result as JSON (per-pixel images are left out: see ``omitted``)."""

    stage: str
    ms: float
    cached: bool
    result: dict[str, Any]


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
    count: int | None = None
    """Frames of a sequence entry (``kind`` "sequence"; its frame k has the id ``<id>@k``)."""
    source: str | None = None
    """A sequence's source: "images", "video" or "bag"."""


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
