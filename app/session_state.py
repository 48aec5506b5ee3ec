"""A session's state as the page polls it: stepper, metrics, errors (one serialiser)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from threadrecon.app.presets import diff, params_hash
from threadrecon.app.views.check import check_json
from threadrecon.core.pipeline import STAGES

if TYPE_CHECKING:
    from threadrecon.app.session import Session


def describe(s: Session) -> dict[str, Any]:
    """The state of session ``s`` (the caller holds ``s.draw_lock``)."""
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
        "inspect": s.inspect,
        "unit": loaded.calib.unit if loaded is not None else None,
    }
