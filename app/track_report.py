"""Per-frame rows, JSON and summary of ``threadrecon track`` (one place for each figure).

A frame is **good** when its curve's status is "ok" (for the tracked curve: this frame's
observation was used, not the motion prior alone) and, against the ground truth, the length
error and the largest curve error (e_S^max) are both <= ``GOOD_MM``. **Jitter** is
:func:`core.tracking.motion_error` between a frame and the one before it.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from threadrecon.app.errors import UserError
from threadrecon.app.evaluation import write_csv
from threadrecon.app.export import result_json, write_json
from threadrecon.app.io import load_calibration
from threadrecon.app.presets import resolve_preset
from threadrecon.app.recording import RecordedFrame
from threadrecon.app.sequence import Sequence, SequenceFrame
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.corrections import CorrectedPair
from threadrecon.core.metrics import frame_errors
from threadrecon.core.pipeline import Pipeline, ReconParams, Reconstruction
from threadrecon.core.tracking import (
    TrackParams,
    TrackResult,
    TrackState,
    gate_corrections,
    motion_error,
    search_alpha,
    start_corrections,
    track_step,
)

GOOD_MM = 20.0  # a frame's length error and largest curve error must both be within 2 cm


@dataclass(frozen=True)
class TrackedFrame:
    """One frame's results: the single-frame reconstruction (``single``; with tracking, run
    with the tracked search range), the tracked curve beside it (None when tracking is off),
    the search range used and the wall time of the frame (pipeline and tracking), ms.

    ``observed``: when the tracker did not observe ``single`` itself, the run it observed: the
    same pipeline with the tracker's mask corrections (``observed_by`` "gate": the masks cut to
    the band around the prediction; "start": a piece removed to start a track), whose segment
    result (a ``CorrectedPair``) shows what they removed."""

    frame: SequenceFrame
    single: Reconstruction
    tracked: TrackResult | None
    alpha: int
    ms: float
    observed: Reconstruction | None = None
    observed_by: str = ""


def track_sequence(
    frames: Iterator[SequenceFrame] | Sequence,
    calib: StereoCalibration,
    params: ReconParams | None = None,
    track: TrackParams | None = None,
) -> Iterator[TrackedFrame]:
    """Reconstruct every frame and, when ``track.enabled``, track the curve across them.

    A frame whose single-frame curve the check doubts is run again with the tracker's mask
    corrections: with a track, the gate around the predicted thread
    (:func:`core.tracking.gate_corrections`), whose run is the observation; without one, the
    removal of one of the largest pieces (:func:`core.tracking.start_corrections`), the first
    whose curve the check calls "ok" starting the track."""
    params = ReconParams() if params is None else params
    track = TrackParams() if track is None else track
    state: TrackState | None = None
    for frame in frames:
        t0 = time.perf_counter()
        alpha = search_alpha(state, calib.P1, calib.P2, track) if track.enabled else None
        p = params if alpha is None else replace(params, stereo=replace(params.stereo, alpha=alpha))
        pipeline = Pipeline(frame.pair, calib)
        rec = pipeline.run(p)
        if rec.status == "failed" and alpha is not None and alpha < params.stereo.alpha:
            p = params  # the prior's search range may be what failed: the configured one
            rec = pipeline.run(p)
        result, observed, by = None, None, ""
        if track.enabled:
            if rec.status != "ok":
                observed, by = _tracker_run(pipeline, rec, p, state, track)
            single, cloud, check = _observation(observed or rec)
            beside = "same" if observed is None else _curve(rec)  # flagged against the single
            result, state = track_step(single, state, track, cloud, check, beside)
        ms = 1000.0 * (time.perf_counter() - t0)
        yield TrackedFrame(frame, rec, result, p.stereo.alpha, ms, observed, by)


def _tracker_run(
    pipeline: Pipeline,
    rec: Reconstruction,
    p: ReconParams,
    state: TrackState | None,
    track: TrackParams,
) -> tuple[Reconstruction | None, str]:
    """The run with the tracker's mask corrections for a doubted frame (see track_sequence)."""
    if state is not None:
        calib = pipeline.calib
        seg = rec["segment"] if "segment" in rec.runs else None
        masks = None if seg is None else (seg.P_L, seg.P_R)
        gate = gate_corrections(state, calib.P1, calib.P2, pipeline.pair.shape, track, masks)
        return (pipeline.run(p, corrections=gate), "gate") if gate else (None, "")
    if "segment" not in rec.runs:
        return None, ""
    seg = rec["segment"]
    for corrections in start_corrections(seg.P_L, seg.P_R, track.thick_px):
        run = pipeline.run(p, corrections=corrections)
        if run.status == "ok":
            return run, "start"
    return None, ""


def _observation(
    rec: Reconstruction,
) -> tuple[np.ndarray | None, np.ndarray | None, Literal["ok", "suspect", "failed"]]:
    """What the tracker observes of a run: its curve, its reliable stereo points and the check's
    verdict. A "suspect" curve is an observation (e.g. bridged across an instrument): the
    tracker keeps its supported part and takes what no stereo point shows from the prior; a
    rejected ("failed") one's stereo-supported part may still serve (core.tracking.track_step)."""
    single = _curve(rec)
    rejected = single is None and rec.status == "failed" and "camera" in rec.runs
    if rejected:
        single = rec["camera"].points
    cloud = None
    if "reliability" in rec.runs:
        cloud = rec["stereo"].points[rec["reliability"].reliable]
    check = "failed" if rejected else ("suspect" if rec.status == "suspect" else "ok")
    return single, cloud, check


def _curve(rec: Reconstruction) -> np.ndarray | None:
    """The run's curve when the pipeline gave one ("ok" or "suspect"), else None."""
    return rec["camera"].points if rec.status != "failed" and "camera" in rec.runs else None


def _single_points(tf: TrackedFrame) -> np.ndarray | None:
    """The single-frame curve when the pipeline gave one ("ok" or "suspect"), else None."""
    return _curve(tf.single)


def _removed_px(rec: Reconstruction | None) -> int:
    """Mask pixels (both views) the tracker's corrections removed in the run it observed."""
    seg = None if rec is None or "segment" not in rec.runs else rec["segment"]
    if not isinstance(seg, CorrectedPair):
        return 0
    return int(np.count_nonzero(seg.removed_L) + np.count_nonzero(seg.removed_R))


def _tracked_points(tf: TrackedFrame) -> np.ndarray | None:
    return None if tf.tracked is None else tf.tracked.points


def frame_row(
    tf: TrackedFrame, calib: StereoCalibration, previous: TrackedFrame | None
) -> dict[str, Any]:
    """One summary-CSV row: single-frame and tracked results, and against the ground truth
    (when the source has it) their errors, goodness and jitter, in mm."""
    f, rec, tr = tf.frame, tf.single, tf.tracked
    single = _single_points(tf)
    row: dict[str, Any] = {
        "frame": f.index,
        "name": f.name,
        "stamp": math.nan if f.stamp is None else f.stamp,
        "status": rec.status,
        "error": rec.message or "",
        "length": rec["camera"].length if "camera" in rec.runs else math.nan,
        "track_status": "off" if tr is None else tr.status,
        "track_length": math.nan if tr is None else tr.length,
        "flagged": bool(tr is not None and tr.flagged),
        "track_reason": "" if tr is None else tr.reason,
        "disagreement": math.nan if tr is None else tr.disagreement,
        "filled": math.nan if tr is None else tr.filled,
        "alpha": tf.alpha,
        "ms": tf.ms,
        "observed_by": tf.observed_by or ("single" if tr is not None else ""),
        "observed_status": "" if tf.observed is None else tf.observed.status,
        "tracker_removed_px": _removed_px(tf.observed),
    }
    curve = _tracked_points(tf) if tr is not None else single
    row["curve"] = "none" if curve is None else ("tracked" if tr is not None else "single")
    if f.truth is None:
        return row
    mm = calib.mm_per_unit
    for prefix, pts, ok in (
        ("", single, rec.status == "ok"),
        ("track_", _tracked_points(tf), tr is not None and tr.status == "ok"),
    ):
        if tr is None and prefix:
            continue
        if pts is None:
            row.update({f"{prefix}e_S_mm": math.nan, f"{prefix}e_S_max_mm": math.nan})
            row.update({f"{prefix}e_length_mm": math.nan, f"{prefix}good": False})
            row[f"{prefix}within"] = False
        else:
            e = frame_errors(pts, f.truth, calib)  # on the part both views see
            row[f"{prefix}e_S_mm"] = e.e_S
            row[f"{prefix}e_S_max_mm"] = e.e_S_max
            row[f"{prefix}e_length_mm"] = e.e_length
            within = bool(e.e_length <= GOOD_MM and e.e_S_max <= GOOD_MM)
            row[f"{prefix}within"] = within  # the curve is close enough, whatever its status
            row[f"{prefix}good"] = bool(ok and within)
        row[f"{prefix}jitter_mm"] = math.nan
        if previous is not None and previous.frame.truth is not None and pts is not None:
            before = _tracked_points(previous) if prefix else _single_points(previous)
            if before is not None:
                row[f"{prefix}jitter_mm"] = mm * motion_error(
                    before, pts, previous.frame.truth, f.truth
                )
    return row


def tracked_json(tf: TrackedFrame, row: dict[str, Any]) -> dict[str, Any]:
    """What a frame's JSON adds to the single-frame reconstruction: the frame, the search
    range, the tracked curve and its flags, and the ground-truth figures when known."""
    tr = tf.tracked
    out: dict[str, Any] = {
        "frame": tf.frame.index,
        "name": tf.frame.name,
        "stamp": tf.frame.stamp,
        "alpha": tf.alpha,
        "ms": round(tf.ms, 3),
        "tracked": None,
    }
    if tr is not None:
        out["tracked"] = {
            "status": tr.status,
            "points": None if tr.points is None else tr.points.tolist(),
            "length": None if tr.points is None else tr.length,
            "flagged": tr.flagged,
            "reason": tr.reason,
            "disagreement": None if math.isnan(tr.disagreement) else tr.disagreement,
            "filled": tr.filled,
            "reversed": tr.reversed,
            "restarted": tr.restarted,
            "observed_by": row["observed_by"],
            "observed_status": row["observed_status"] or None,
            "tracker_removed_px": row["tracker_removed_px"],
        }
    truth = {k: row[k] for k in row if k.endswith(("_mm", "good")) and k not in ("ms",)}
    out["truth_metrics"] = {
        k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in truth.items()
    } or None
    return out


def summary_lines(rows: list[dict[str, Any]], elapsed_s: float) -> list[str]:
    n = len(rows)
    lines = [f"{n} frames in {elapsed_s:.1f} s: {n / max(elapsed_s, 1e-9):.2f} frames/s"]
    lines.append(f"single-frame: {sum(r['status'] == 'ok' for r in rows)} ok")
    if rows[0]["track_status"] != "off":
        count = {s: sum(r["track_status"] == s for r in rows) for s in ("ok", "predicted", "lost")}
        flagged = sum(r["flagged"] for r in rows)
        lines.append(
            f"tracked: {count['ok']} ok, {count['predicted']} predicted, {count['lost']} lost, "
            f"{flagged} flagged (tracking and single-frame disagree)"
        )
    for prefix, label in (("", "single-frame"), ("track_", "tracked")):
        if f"{prefix}good" not in rows[0]:
            continue
        good = sum(bool(r[f"{prefix}good"]) for r in rows)
        jit = np.array([r[f"{prefix}jitter_mm"] for r in rows], dtype=float)
        jit = jit[np.isfinite(jit)]
        jtxt = f", jitter mean {jit.mean():.3f} mm over {jit.size} steps" if jit.size else ""
        lines.append(f"{label} good frames: {good}/{n} ({100 * good / n:.1f}%){jtxt}")
    return lines


def recorded_frame(tf: TrackedFrame) -> RecordedFrame:
    """The curves of a frame for a recording: tracked, single-frame and ground truth."""
    curves = {"single": _single_points(tf), "tracked": _tracked_points(tf), "truth": tf.frame.truth}
    return RecordedFrame({k: v for k, v in curves.items() if v is not None}, tf.frame.name)


def cmd_track(args: argparse.Namespace) -> int:
    from threadrecon.app.sequence import ImageFolderSequence, SequenceError, open_sequence
    from threadrecon.app.track_report import frame_row, recorded_frame, summary_lines, tracked_json

    params = resolve_preset(args.config)
    if args.limit is not None and args.limit < 1:
        raise UserError(f"--limit must be >= 1, got {args.limit}")
    try:
        seq = open_sequence(args.source, args.right, args.left_topic, args.right_topic)
    except SequenceError as exc:
        raise UserError(str(exc)) from None
    if getattr(args, "no_masks", False):
        if not isinstance(seq, ImageFolderSequence):
            raise UserError("--no-masks applies to an image folder (videos and bags have no masks)")
        seq.masks = False
    if args.calib is not None:
        calib = load_calibration(args.calib, unit=args.units)
    elif seq.calibration is not None:
        calib = seq.calibration
    else:
        raise UserError(f"{args.source} carries no calibration: give --calib")
    out = Path(args.out)
    track = TrackParams(enabled=not args.no_tracking)
    n = seq.count if args.limit is None else min(seq.count or args.limit, args.limit)
    rows: list[dict[str, Any]] = []
    recorded: list[Any] = []
    previous = None
    t0 = time.perf_counter()
    for k, tf in enumerate(track_sequence(seq, calib, params, track), start=1):
        row = frame_row(tf, calib, previous)
        rows.append(row)
        previous = tf
        data = result_json(tf.single)
        data.update(tracked_json(tf, row))
        write_json(out / "frames" / f"{tf.frame.name}.json", data)
        if args.record:
            recorded.append(recorded_frame(tf))
        rate = k / (time.perf_counter() - t0)
        _track_progress(k, n, tf.frame.name, rate)
        if args.limit is not None and k >= args.limit:
            break
    if not rows:
        raise UserError(f"{args.source}: no frames")
    elapsed = time.perf_counter() - t0
    write_csv(out / "summary.csv", rows)
    for line in summary_lines(rows, elapsed):
        print(line)
    if args.record:
        from threadrecon.app.recording import save_recording

        save_recording(recorded, args.record, baseline=calib.baseline)
        print(f"recording of {len(recorded)} frames -> {args.record} (opens without a server)")
    lost = sum(r["curve"] == "none" for r in rows)
    if lost:
        print(f"threadrecon: {lost} of {len(rows)} frames have no curve", file=sys.stderr)
        return 1
    return 0


def _track_progress(k: int, n: int | None, name: str, rate: float) -> None:
    total = f"/{n}" if n else ""
    if sys.stderr.isatty():
        sys.stderr.write(f"\r[{k}{total}] {name[:30]:<30} {rate:6.2f} frames/s")
        if n is not None and k == n:
            sys.stderr.write("\n")
    elif k == 1 or k % 10 == 0 or k == n:
        sys.stderr.write(f"[{k}{total}] {name} {rate:.2f} frames/s\n")
    sys.stderr.flush()
