"""Whole-dataset evaluation in a background thread, and side-by-side comparison of two runs.

Each frame's row is :func:`app.evaluation.evaluate_frame`'s and the summary :func:`app.evaluation.summarise`'s,
so that the page agrees to the digit with ``threadrecon evaluate``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from typing import Any, Self

from threadrecon.app.dataset import METRIC_COLUMNS, Frame
from threadrecon.app.evaluation import evaluate_frame, summarise
from threadrecon.app.export import json_safe
from threadrecon.app.presets import params_hash
from threadrecon.core.pipeline import ReconParams

log = logging.getLogger(__name__)

STATES = ("pending", "running", "done", "cancelled", "failed")
FINAL_STATES = ("done", "cancelled", "failed")
COMPARE_COLUMNS = (*METRIC_COLUMNS, "n_reliable", "n_keypoints", "ms_total")


class BackgroundJob:
    """Work in a daemon thread, followed by polling: the common life of the page's dataset
    evaluation (:class:`EvaluationJob`) and its tunes (:class:`app.tune.job.TuneJob`).

    ``state`` is "pending" until :meth:`start`, then "running", then what :meth:`_work`
    returns ("done" or "cancelled": :meth:`cancel` sets an event the work reads between its
    steps), or "failed" when it raised (``error`` says why, :meth:`_error_text`). The
    subclass's :meth:`_finish` runs once at the end, in the job's thread with the lock held,
    before :meth:`wait` returns: a poll that sees a final state sees what it stored.
    """

    def __init__(self, name: str) -> None:
        self._name = name
        self._lock = threading.RLock()
        self._cancel = threading.Event()
        self._finished = threading.Event()
        self._thread: threading.Thread | None = None
        self._state = "pending"
        self._error: str | None = None
        self._started_at: str | None = None
        self._t0 = 0.0
        self._t1: float | None = None

    def start(self) -> Self:
        """Start the job's thread (once); returns the job."""
        with self._lock:
            if self._thread is not None:
                raise RuntimeError(f"job {self._name} was already started")
            self._state = "running"
            self._started_at = _now()
            self._t0 = time.monotonic()
            self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()
        return self

    def cancel(self) -> None:
        """Ask the job to stop at its next step."""
        self._cancel.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the job has finished (and :meth:`_finish` returned); False on timeout."""
        return self._finished.wait(timeout)

    def _run(self) -> None:
        final = "failed"
        try:
            final = self._work()
        except Exception as exc:
            with self._lock:
                self._error = self._error_text(exc)
            log.exception("job %s failed", self._name)
        finally:
            with self._lock:
                self._state = final
                self._t1 = time.monotonic()
                self._finish()
            self._finished.set()

    def _work(self) -> str:
        """The job's work; returns its final state, "done" or "cancelled"."""
        raise NotImplementedError

    def _error_text(self, exc: BaseException) -> str:
        return f"{type(exc).__name__}: {exc}"

    def _finish(self) -> None:
        """Called once at the end with the lock held (the state is final)."""

    def _elapsed(self) -> float:
        """Seconds since :meth:`start` (to the end once finished; 0 while pending)."""
        if self._state == "pending":
            return 0.0
        return (self._t1 if self._t1 is not None else time.monotonic()) - self._t0

    @property
    def state(self) -> str:
        with self._lock:
            return self._state

    @property
    def error(self) -> str | None:
        with self._lock:
            return self._error

    @property
    def started_at(self) -> str | None:
        """ISO-8601 UTC time of :meth:`start`."""
        with self._lock:
            return self._started_at


class EvaluationJob(BackgroundJob):
    """Evaluates ``frames`` with ``params`` one after the other in a daemon thread.

    ``state`` is "pending" until :meth:`start`, then "running", then "done" (every frame),
    "cancelled" (stopped early by :meth:`cancel`, which takes effect between frames) or
    "failed" (an unexpected exception; ``error`` names the frame; the rows so far are kept).

    ``on_frame(job, row)`` is called after each frame; ``on_done(job)`` once at the end, in
    the job's thread, with the job's lock held: a :meth:`snapshot` taken by another thread
    waits until ``on_done`` returns, so a poll that sees a final state also sees what
    ``on_done`` stored. Exceptions from ``on_done`` are logged and kept in ``on_done_error``.
    """

    def __init__(
        self,
        frames: Sequence[Frame],
        params: ReconParams,
        preset: str,
        on_done: Callable[[EvaluationJob], None] | None = None,
        on_frame: Callable[[EvaluationJob, dict[str, Any]], None] | None = None,
    ) -> None:
        super().__init__(f"evaluate-{preset}")
        self.frames: tuple[Frame, ...] = tuple(frames)
        self.params = params
        self.preset = preset
        self.params_hash = params_hash(params)
        self.total = len(self.frames)
        self._on_done = on_done
        self._on_frame = on_frame
        self._rows: list[dict[str, Any]] = []
        self._current: str | None = None
        self._summary: list[str] = []
        self._on_done_error: str | None = None
        self._finished_at: str | None = None

    def _work(self) -> str:
        for frame in self.frames:
            if self._cancel.is_set():
                return "cancelled"
            with self._lock:
                self._current = frame.id
            row, _ = evaluate_frame(frame, self.params)
            with self._lock:
                self._rows.append(row)
            if self._on_frame is not None:
                self._on_frame(self, row)
        return "done"

    def _error_text(self, exc: BaseException) -> str:
        return f"{self._current}: {type(exc).__name__}: {exc}"

    def _finish(self) -> None:
        self._summary = summarise(self._rows)
        self._current = None
        self._finished_at = _now()
        if self._on_done is not None:
            try:
                self._on_done(self)
            except Exception as exc:
                self._on_done_error = f"{type(exc).__name__}: {exc}"
                log.exception("on_done of evaluation job %s failed", self.preset)

    @property
    def done(self) -> int:
        """Frames finished."""
        with self._lock:
            return len(self._rows)

    @property
    def current(self) -> str | None:
        """Id of the frame being evaluated (None when not running)."""
        with self._lock:
            return self._current

    @property
    def rows(self) -> list[dict[str, Any]]:
        """A copy of the rows so far, in frame order (``evaluate_frame``'s dicts, NaN kept)."""
        with self._lock:
            return [dict(r) for r in self._rows]

    @property
    def summary(self) -> list[str]:
        """``summarise(rows)`` once finished; empty before."""
        with self._lock:
            return list(self._summary)

    @property
    def on_done_error(self) -> str | None:
        with self._lock:
            return self._on_done_error

    @property
    def finished_at(self) -> str | None:
        """ISO-8601 UTC time the last frame finished (None while running)."""
        with self._lock:
            return self._finished_at

    def snapshot(self, since: int = 0) -> dict[str, Any]:
        """JSON-safe state for polling (NaN -> None); ``rows`` holds the rows from index
        ``since`` on, so that a poller can fetch only the new ones."""
        if since < 0:
            raise ValueError(f"since must be >= 0, got {since}")
        with self._lock:
            elapsed = self._elapsed()
            return json_safe(
                {
                    "state": self._state,
                    "preset": self.preset,
                    "params_hash": self.params_hash,
                    "done": len(self._rows),
                    "total": self.total,
                    "current": self._current,
                    "error": self._error,
                    "on_done_error": self._on_done_error,
                    "started_at": self._started_at,
                    "finished_at": self._finished_at,
                    "elapsed_s": round(elapsed, 3),
                    "since": since,
                    "rows": self._rows[since:],
                    "summary": self._summary,
                }
            )


def compare(
    rows_a: Sequence[dict[str, Any]],
    rows_b: Sequence[dict[str, Any]],
    columns: Sequence[str] = COMPARE_COLUMNS,
) -> list[dict[str, Any]]:
    """Side-by-side rows of two evaluations (e.g. two presets) of the same frames.

    One row per frame present in both (in ``rows_a``'s order) with ``frame``, ``kind``,
    ``status_a``, ``status_b`` and, per column c, ``c_a``, ``c_b`` and ``c_diff`` = b - a
    (NaN where either is missing). Then one summary row, ``frame`` = ``kind`` = "mean",
    statuses "k/n ok", whose ``c_a``, ``c_b``, ``c_diff`` are means over the frames where both
    values are finite (so that ``c_diff`` = ``c_b`` - ``c_a``), NaN when there is none.
    """
    by_frame = {r["frame"]: r for r in rows_b}
    out: list[dict[str, Any]] = []
    for ra in rows_a:
        rb = by_frame.get(ra["frame"])
        if rb is None:
            continue
        row: dict[str, Any] = {
            "frame": ra["frame"],
            "kind": ra.get("kind", ""),
            "status_a": ra.get("status", ""),
            "status_b": rb.get("status", ""),
        }
        for c in columns:
            a, b = _number(ra.get(c)), _number(rb.get(c))
            row[f"{c}_a"], row[f"{c}_b"], row[f"{c}_diff"] = a, b, b - a
        out.append(row)
    n = len(out)
    mean: dict[str, Any] = {
        "frame": "mean",
        "kind": "mean",
        "status_a": f"{sum(r['status_a'] == 'ok' for r in out)}/{n} ok",
        "status_b": f"{sum(r['status_b'] == 'ok' for r in out)}/{n} ok",
    }
    for c in columns:
        pairs = [
            (r[f"{c}_a"], r[f"{c}_b"])
            for r in out
            if math.isfinite(r[f"{c}_a"]) and math.isfinite(r[f"{c}_b"])
        ]
        if pairs:
            ma = math.fsum(a for a, _ in pairs) / len(pairs)
            mb = math.fsum(b for _, b in pairs) / len(pairs)
        else:
            ma = mb = math.nan
        mean[f"{c}_a"], mean[f"{c}_b"], mean[f"{c}_diff"] = ma, mb, mb - ma
    out.append(mean)
    return out


def _number(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        return math.nan
    return float(v)


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="microseconds")
