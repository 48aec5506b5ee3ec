"""A session's state as the page polls it: stepper, metrics, errors (one serialiser)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from threadrecon.app.presets import diff, params_hash
from threadrecon.app.views.check import check_json
from threadrecon.core.pipeline import STAGES, ReconParams, Reconstruction

if TYPE_CHECKING:
    from threadrecon.app.library import LoadedFrame
    from threadrecon.app.session import Session

TIMING_KEYS = (
    "compute_ms", "compute_cpu_ms", "publish_ms", "publish_cpu_ms", "metrics_ms", "metrics_cpu_ms",
)  # fmt: skip


@contextlib.contextmanager
def timed(into: dict[str, float], part: str) -> Iterator[None]:
    """Add the wall and this thread's CPU ms of the block to ``into[part + "_ms"]`` and
    ``into[part + "_cpu_ms"]`` (the latency's breakdown: computing the stages, publishing
    their views, the metrics)."""
    t, c = time.perf_counter(), time.thread_time()
    try:
        yield
    finally:
        into[f"{part}_ms"] += 1000.0 * (time.perf_counter() - t)
        into[f"{part}_cpu_ms"] += 1000.0 * (time.thread_time() - c)


class View(Protocol):
    """A 3D view of a session (``app.scene.SceneView``)."""

    def show_frame(self, loaded: LoadedFrame | None) -> None: ...
    def show(self, rec: Reconstruction | None, loaded: LoadedFrame | None) -> None: ...
    def show_params(self, params: ReconParams) -> None: ...
    def show_inspect(self, info: dict[str, Any] | None) -> None: ...


@dataclass(frozen=True)
class Request:
    seq: int
    frame_id: str
    params: ReconParams
    reveal: int  # number of stages to compute and show (1..len(STAGES))
    pause_s: float  # pause after each stage, so that a streamed run can be watched
    t0: float  # perf_counter() when the request was made (for the latency figures)


def describe(s: Session) -> dict[str, Any]:
    """The state of session ``s`` (the caller holds ``s._state_lock``)."""
    rec = s.rec
    stages = []
    for i, stage in enumerate(STAGES):
        entry: dict[str, Any] = {"stage": stage, "revealed": i < s.reveal}
        if rec is not None and stage in rec.runs:
            run = rec.runs[stage]
            entry.update(status="cached" if run.cached else "done", ms=run.ms)
            if stage == "spline" and not run.result.ok:
                entry["status"] = "fallback"
        elif rec is not None and rec.failed_stage == stage:
            entry["status"] = "failed"
        elif s.running == stage:
            entry["status"] = "running"
        else:
            entry["status"] = "pending"
        stages.append(entry)
    error = s.load_error or (rec.message if rec is not None else None)
    if s.load_error:
        status, failed = "failed", "load"
    else:
        status = rec.status if rec is not None else "pending"
        failed = rec.failed_stage if rec is not None else None
    loaded = s.loaded
    return {
        "session": s.id,
        "version": s.version,
        "frame_id": s.frame_id,
        "shown_frame": loaded.frame.id if loaded is not None else None,
        "busy": s.busy,
        "preset": s.preset,
        "params": s.params.to_dict(),
        "params_hash": params_hash(s.params),
        "diff": diff(s.params),
        "reveal": s.reveal,
        "stages": stages,
        "status": status,
        "failed_stage": failed,
        "error": error or s.metrics_error,
        "reasons": list(rec.reasons) if rec is not None and not s.load_error else [],
        "check": check_json(rec),
        "metrics": dict(s.metrics),
        "latency_ms": dict(s.latency_ms),
        "timing": dict(s.timing),
        "inspect": s.inspect,
        "unit": loaded.calib.unit if loaded is not None else None,
    }
