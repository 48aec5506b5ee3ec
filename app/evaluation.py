"""Evaluation as a library: one row per frame, one summary, one CSV writer.

The CLI (``threadrecon evaluate``), the debugger's background job and the rated-frames table
all call these, so every view shows the same figures.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app.dataset import METRIC_COLUMNS, Frame, evaluate_reconstruction, load_frame
from threadrecon.core.pipeline import STAGES, Pipeline, ReconParams, Reconstruction

LENGTH_FAILURE_MM = 20.0  # a simulated frame whose length is off by more than 2 cm has failed


def evaluate_frame(
    frame: Frame, params: ReconParams, loaded: tuple[Any, Any, Any] | None = None
) -> tuple[dict[str, Any], Reconstruction | None]:
    """One CSV row for a frame (never raises for a bad frame: the row says what failed).
    ``loaded``: the frame's ``load_frame(frame)`` when the caller already has it (a cache)."""
    row: dict[str, Any] = {"frame": frame.id, "kind": frame.kind}
    row["corrections"] = len(frame.corrections)  # the user's mask corrections applied
    try:
        pair, calib, gt = loaded if loaded is not None else load_frame(frame)
        rec = Pipeline(pair, calib, frame.corrections).run(params)
    except Exception as exc:  # any frame's error is that frame's failed row, never the run's
        row.update(status="failed", error=_describe(exc), **{c: math.nan for c in METRIC_COLUMNS})
        row.update(check="failed", reasons=row["error"], auto_score=math.nan, auto_rating=math.nan)
        row["grasp_confidence"] = math.nan
        return row, None
    row.update(status=rec.status, error=rec.message or "")
    row.update(_check_columns(rec))
    try:
        row.update(evaluate_reconstruction(rec, calib, gt))
    except Exception as exc:  # e.g. a non-finite curve or ground truth: the row says so
        row.update(status="failed", error=f"metrics: {_describe(exc)}")
        row.update({c: math.nan for c in METRIC_COLUMNS})
    if (
        row["status"] == "ok"
        and frame.has_ground_truth
        and not (row["e_length_mm"] <= LENGTH_FAILURE_MM)
    ):
        row["status"] = "failed"
        row["error"] = f"length error {row['e_length_mm']:.1f} mm > {LENGTH_FAILURE_MM:g} mm"
    row["n_reliable"] = rec["reliability"].count if "reliability" in rec.runs else 0
    row["n_keypoints"] = rec["clustering"].count if "clustering" in rec.runs else 0
    for stage in STAGES:
        row[f"ms_{stage}"] = rec.timings_ms.get(stage, math.nan)
    row["ms_total"] = sum(rec.timings_ms.values())
    return row, rec


CHECK_COLUMNS = ("check", "reasons", "auto_score", "auto_rating", "grasp_confidence")
"""The check stage's verdict in every row: its status (before the ground-truth length test),
every reason (joined by "; "), the automatic score on the paper's 1-5 scale as its integer
class (``auto_score``, for the confusion table against a person's ratings) and continuous
(``auto_rating``, the value that ranks frames) and the grasp point's confidence."""


def _check_columns(rec: Reconstruction) -> dict[str, Any]:
    if "check" not in rec.runs:  # a stage before the check failed: that stage's reason
        return {"check": rec.status, "reasons": rec.message or "", "auto_score": math.nan,
                "auto_rating": math.nan, "grasp_confidence": math.nan}  # fmt: skip
    chk = rec["check"]
    return {
        "check": chk.status,
        "reasons": "; ".join(chk.reasons),
        "auto_score": chk.score,
        "auto_rating": chk.rating,
        "grasp_confidence": chk.grasp.confidence if chk.grasp is not None else math.nan,
    }


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return (
        text if isinstance(exc, ValueError | OSError) and text else f"{type(exc).__name__}: {text}"
    )


STATUSES = ("ok", "suspect", "failed")


def status_counts(rows: list[dict[str, Any]]) -> dict[str, int]:
    """Frames per status ("ok", "suspect", "failed")."""
    return {s: sum(r.get("status") == s for r in rows) for s in STATUSES}


def summarise(rows: list[dict[str, Any]]) -> list[str]:
    """Frames per status, mean and standard deviation per metric over the frames with a curve
    (ok and suspect: the paper's figures count every frame that did not fail), per kind; then
    every frame that is not ok with its reasons."""
    lines = []
    for kind, cols in (("simulated", METRIC_COLUMNS[:3]), ("real", METRIC_COLUMNS[5:])):
        sel = [r for r in rows if r["kind"] == kind]
        if not sel:
            continue
        n = status_counts(sel)
        lines.append(
            f"{kind}: {len(sel)} frames: {n['ok']} ok, {n['suspect']} suspect, {n['failed']} failed"
        )
        good = [r for r in sel if r["status"] != "failed"]
        for c in cols:
            v = np.array([r.get(c, np.nan) for r in good], dtype=float)
            v = v[np.isfinite(v)]
            if v.size:
                lines.append(f"  {c:<16} mean {v.mean():8.3f}  sd {v.std():8.3f}")
    for r in rows:
        if r["status"] != "ok":
            lines.append(f"{r['status'].upper()} {r['frame']}: {r['error']}")
    return lines


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    tmp = path.with_suffix(path.suffix + ".tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    tmp.replace(path)
