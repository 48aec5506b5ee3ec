"""Quality ratings (the paper's 1-5 score) and the rated-frames table (Table II)."""

from __future__ import annotations

from typing import Any

import numpy as np
from fastapi import APIRouter
from fastapi.responses import JSONResponse, Response

from threadrecon.app.agreement import agreement, rated_pairs
from threadrecon.app.api import schemas
from threadrecon.app.api.deps import State, answer
from threadrecon.app.dataset import METRIC_COLUMNS
from threadrecon.app.errors import Invalid
from threadrecon.app.presets import params_hash

router = APIRouter(tags=["ratings"])
TABLE_METRICS = METRIC_COLUMNS[5:]  # the image-space figures every frame has (Table II)


@router.put("/api/frames/{frame_id:path}/rating")
def put_rating(state: State, frame_id: str, body: schemas.RatingBody) -> JSONResponse:
    """Rate the frame's reconstruction 1-5 (below 3 is a failure) with a note. The rating
    records the preset and the hash of the parameters of the reconstruction the session
    shows; earlier ratings stay in the history."""
    state.frame(frame_id)
    s = state.session(body.session)
    rec = s.rec
    params = rec.params if rec is not None and s.shows(frame_id) else s.params
    try:
        rating = state.store.add_rating(
            frame_id, body.score, body.note, s.preset, params_hash(params)
        )
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    history = state.store.history(frame_id)
    return JSONResponse(
        {
            "frame_id": frame_id,
            "latest": rating.to_dict(),
            "history": [r.to_dict() for r in history],
        }
    )


@router.get("/api/frames/{frame_id:path}/rating")
def get_rating(state: State, frame_id: str) -> JSONResponse:
    """The latest rating of the frame (null if none) and its history, newest first."""
    state.frame(frame_id)
    history = state.store.history(frame_id)
    return JSONResponse(
        {
            "frame_id": frame_id,
            "latest": history[0].to_dict() if history else None,
            "history": [r.to_dict() for r in history],
        }
    )


@router.get("/api/ratings.csv")
def ratings_csv(state: State, history: bool = True) -> Response:
    """Every rating (or only the latest per frame) as CSV."""
    return Response(
        state.store.ratings_csv(history), media_type="text/csv",
        headers={"Content-Disposition": 'attachment; filename="ratings.csv"'},
    )  # fmt: skip


@router.get("/api/ratings/summary")
def ratings_summary(state: State, session: str | None = None) -> JSONResponse:
    """The paper's Table II for the rated frames: the latest score, the failure rate
    (score < 3), and the reprojection errors and coverage *as stored* by the newest saved
    dataset evaluation with the session's current parameters (else the newest one): nothing
    is recomputed here. ``evaluation`` names the evaluation the figures come from."""
    s = state.session(session)
    current = params_hash(s.params)
    ev = state.store.last_evaluation(params_hash=current) or state.store.last_evaluation()
    by_frame = {r["frame"]: r for r in ev["rows"]} if ev is not None else {}
    rows = []
    for frame_id, rating in sorted(state.store.latest_all().items()):
        frame = state.library.frames.get(frame_id)
        if frame is None:
            continue
        stored = by_frame.get(frame_id, {})
        rows.append(
            {
                "frame": frame_id, "kind": frame.kind, "score": rating.score,
                "note": rating.note, "rated_at": rating.created_at, "preset": rating.preset,
                "params_hash": rating.params_hash, "same_params": rating.params_hash == current,
                "status": stored.get("status"), **{c: stored.get(c) for c in TABLE_METRICS},
            }
        )  # fmt: skip
    n = len(rows)
    summary: dict[str, Any] = {"rated": n, "failures": sum(r["score"] < 3 for r in rows)}
    summary["failure_rate"] = summary["failures"] / n if n else None
    summary["mean_score"] = float(np.mean([r["score"] for r in rows])) if n else None
    for c in TABLE_METRICS:
        v = np.array([np.nan if r[c] is None else r[c] for r in rows], dtype=float)
        v = v[np.isfinite(v)]
        summary[c] = float(v.mean()) if v.size else None
    source = None
    if ev is not None:
        source = {k: ev[k] for k in ("id", "preset", "params_hash", "created_at")}
        source["same_params"] = ev["params_hash"] == current
    return answer({"rows": rows, "summary": summary, "params_hash": current, "evaluation": source})


@router.get("/api/ratings/agreement")
def ratings_agreement(state: State, session: str | None = None) -> JSONResponse:
    """The automatic 1-5 score against the person's latest rating of each rated frame: a 5x5
    confusion table (rows: rating, columns: automatic score's class) and the Spearman rank
    correlation (of the continuous automatic score, where the evaluation stored it). The
    automatic scores are those stored by the saved evaluation that
    ``/api/ratings/summary`` uses (current parameters, else the newest); ``missing`` lists
    the rated frames that evaluation has no score for."""
    s = state.session(session)
    current = params_hash(s.params)
    ev = state.store.last_evaluation(params_hash=current) or state.store.last_evaluation()
    ratings = {f: r.score for f, r in state.store.latest_all().items() if f in state.library.frames}
    frames, missing = rated_pairs(ratings, ev["rows"] if ev is not None else [])
    continuous = [f["auto_rating"] for f in frames]  # None in an evaluation before session 19
    agree = agreement(
        [(f["auto"], f["human"]) for f in frames],
        continuous if all(v is not None for v in continuous) else None,
    )
    source = None
    if ev is not None:
        source = {k: ev[k] for k in ("id", "preset", "params_hash", "created_at")}
        source["same_params"] = ev["params_hash"] == current
    return answer(
        {**agree.to_dict(), "rated": len(ratings), "frames": frames, "missing": missing,
         "evaluation": source}
    )  # fmt: skip
