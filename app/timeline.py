"""The debugger's sequence timeline: every frame of a sequence reconstructed and tracked in the
background, its figures plotted along the timeline and its curves kept for the slider.

A :class:`Timeline` runs :func:`app.track_report.track_sequence` (the same code as
``threadrecon track``) over one sequence with one set of parameters, in its own thread, and
keeps per frame a small row (status, length, confidence, timings, tracking flags, the
ground-truth figures of :func:`app.track_report.frame_row`) and the curves projected into the
left image. Rows are a few hundred bytes a frame; curves are kept for the newest
``CURVE_FRAMES`` frames only, and :class:`Timelines` keeps ``TIMELINES`` timelines (the oldest
is cancelled), so memory stays bounded whatever the sequence's length.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import OrderedDict
from typing import Any, Final

import numpy as np

from threadrecon.app.library import FrameLibrary
from threadrecon.app.presets import params_hash
from threadrecon.app.recording import RecordedFrame
from threadrecon.app.track_report import TrackedFrame, frame_row, track_sequence
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.metrics import project
from threadrecon.core.pipeline import ReconParams
from threadrecon.core.tracking import TrackParams, resample

log = logging.getLogger("threadrecon.timeline")
CURVE_FRAMES: Final = 2000  # frames whose curves a timeline keeps (about 6 kB a frame)
CURVE_SAMPLES: Final = 100  # points per curve sent to the page (a 2D polyline)
TIMELINES: Final = 3  # timelines kept at once (sequence x parameters x tracking)
ROW_KEYS: Final = (
    "frame", "name", "status", "length", "track_status", "track_length", "flagged",
    "track_reason", "alpha", "ms", "e_S_max_mm", "track_e_S_max_mm", "good", "track_good",
    "jitter_mm", "track_jitter_mm", "observed_by", "observed_status", "tracker_removed_px",
)  # fmt: skip


class Timeline:
    """One sequence reconstructed frame by frame in a background thread (module docstring)."""

    def __init__(
        self,
        library: FrameLibrary,
        sequence_id: str,
        params: ReconParams,
        tracking: bool,
    ) -> None:
        self.sequence_id = sequence_id
        self.params = params
        self.tracking = tracking
        self.entry = library.sequences[sequence_id]
        self.seq = library.sequence(sequence_id)
        self.count: int | None = self.seq.count
        self.rows: list[dict[str, Any]] = []
        self.error: str | None = None
        self.done = False
        self._curves: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()
        self._curves3d: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()
        self.baseline: float | None = None
        self._lock = threading.Lock()
        self._cancel = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"timeline-{sequence_id[-20:]}", daemon=True
        )
        self._thread.start()

    def cancel(self) -> None:
        self._cancel.set()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def snapshot(self, since: int = 0) -> dict[str, Any]:
        """The rows from frame ``since`` on, and the progress."""
        with self._lock:
            rows = [dict(r) for r in self.rows[max(0, since) :]]
            computed = len(self.rows)
        return {
            "sequence": self.sequence_id,
            "tracking": self.tracking,
            "params_hash": params_hash(self.params),
            "count": self.count,
            "computed": computed,
            "done": self.done,
            "error": self.error,
            "rows": rows,
        }

    def curves(self, k: int) -> dict[str, Any] | None:
        """Frame ``k``'s curves in the left image, ``{name: [[x, y], ...]}`` (tracked,
        single-frame, truth; px); None when the frame is not computed (or no longer kept)."""
        with self._lock:
            c = self._curves.get(k)
        if c is None:
            return None
        return {name: np.round(uv, 2).tolist() for name, uv in c.items()}

    def recorded(self, k: int | None = None) -> list[RecordedFrame]:
        """The computed frames still kept (or frame ``k`` alone) as a recording's frames: the
        tracked, single-frame and true curves in the left camera frame."""
        with self._lock:
            keys = list(self._curves3d) if k is None else [k] if k in self._curves3d else []
            found = [(i, self._curves3d[i]) for i in keys]
        names = {r["frame"]: r["name"] for r in self.rows}
        return [RecordedFrame(dict(c), names.get(i, str(i))) for i, c in found]

    # --- the worker -----------------------------------------------------------------------

    def _run(self) -> None:
        try:
            calib = self.entry.calib(self.seq)
            self.baseline = calib.baseline
            track = TrackParams(enabled=self.tracking)
            previous: TrackedFrame | None = None
            for tf in track_sequence(self.seq, calib, self.params, track):
                row = _row(tf, calib, previous)
                row["frame_id"] = self.entry.frame_id(tf.frame.index)
                curves3d = _curves3d(tf)
                previous = tf
                with self._lock:
                    self.rows.append(row)
                    k = tf.frame.index
                    self._curves3d[k] = curves3d
                    self._curves[k] = {
                        name: project(x, calib.P1).astype(np.float32)
                        for name, x in curves3d.items()
                    }
                    while len(self._curves) > CURVE_FRAMES:
                        self._curves.popitem(last=False)
                        self._curves3d.popitem(last=False)
                if self._cancel.is_set():
                    return
            with self._lock:
                self.count = len(self.rows)
        except Exception as exc:  # a broken frame or source: the timeline says why and stops
            log.exception("timeline of %s failed", self.sequence_id)
            self.error = f"frame {len(self.rows)}: {type(exc).__name__}: {exc}"
        finally:
            self.done = True


def _row(tf: TrackedFrame, calib: StereoCalibration, previous: TrackedFrame | None) -> dict:
    full = frame_row(tf, calib, previous)
    row = {k: full[k] for k in ROW_KEYS if k in full}
    rec = tf.single
    conf = rec["check"].confidence if "check" in rec.runs else None
    row["confidence"] = float(np.mean(conf)) if conf is not None and len(conf) else math.nan
    row["stage_ms"] = {name: round(run.ms, 2) for name, run in rec.runs.items()}
    row["curve_length"] = row["track_length"] if tf.tracked is not None else row["length"]
    return row


def _curves3d(tf: TrackedFrame) -> dict[str, np.ndarray]:
    """The frame's curves, ``CURVE_SAMPLES`` points each (left camera frame, float32)."""
    rec, tr = tf.single, tf.tracked
    found = {
        "single": rec["camera"].points if "camera" in rec.runs else None,
        "tracked": None if tr is None else tr.points,
        "truth": tf.frame.truth,
    }
    out = {}
    for name, pts in found.items():
        if pts is None or len(pts) < 2 or not np.all(np.isfinite(pts)):
            continue
        out[name] = resample(pts, CURVE_SAMPLES).astype(np.float32)
    return out


class Timelines:
    """The timelines the pages asked for: one per (sequence, parameters, tracking), the
    ``TIMELINES`` most recently asked kept (an evicted one is cancelled)."""

    def __init__(self, library: FrameLibrary) -> None:
        self.library = library
        self._items: OrderedDict[tuple[str, str, bool], Timeline] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, sequence_id: str, params: ReconParams, tracking: bool) -> Timeline:
        """The timeline (started on first use); NotFound / Invalid from the library."""
        self.library.sequence(sequence_id)
        key = (sequence_id, params_hash(params), bool(tracking))
        with self._lock:
            tl = self._items.get(key)
            if tl is None:
                tl = Timeline(self.library, sequence_id, params, tracking)
                self._items[key] = tl
            self._items.move_to_end(key)
            while len(self._items) > TIMELINES:
                self._items.popitem(last=False)[1].cancel()
        return tl

    def close(self) -> None:
        with self._lock:
            for tl in self._items.values():
                tl.cancel()
            self._items.clear()
