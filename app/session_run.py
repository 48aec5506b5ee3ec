"""A session's worker running one request (``Session`` inherits it): the stages, streamed or
shown once; the run's final state, which the page's long poll answers before the 3D views draw
the last layers; a failed stage's state. The session holds the state, locks and views."""

from __future__ import annotations

import contextlib
import time
from typing import TYPE_CHECKING, Any

from threadrecon.app import heap
from threadrecon.app.dataset import evaluate_reconstruction
from threadrecon.app.errors import DomainError
from threadrecon.app.session_state import TIMING_KEYS, Request, timed
from threadrecon.core.pipeline import STAGES, Reconstruction, StageError

if TYPE_CHECKING:
    from threadrecon.app.session import Session

    _Base = Session
else:
    _Base = object


class RunWorker(_Base):
    def _fail(self, req: Request, exc: Exception) -> None:
        stage = self.running or STAGES[0]
        rec = self.rec
        runs = dict(rec.runs) if rec is not None and rec.params == req.params else {}
        runs.pop(stage, None)
        message = f"{stage}: internal error: {type(exc).__name__}: {exc}"
        with self.draw_lock:
            with self._state_lock:
                self.rec, self.metrics = Reconstruction(runs, stage, message, req.params), {}
            for view in list(self.views.values()):
                with contextlib.suppress(Exception):
                    view.show(self.rec, self.loaded)
        self._status(req.frame_id, "failed")
        self._bump()

    def _execute(self, req: Request) -> None:
        self.latency_ms = {}
        try:
            loaded = self.library.load(req.frame_id)
            pipe = self._pipeline(req.frame_id, loaded)
            pipe.corrections = self.library.corrections(req.frame_id)  # the worker's alone
        except (ValueError, OSError, DomainError) as exc:  # DomainError: the correction store
            with self.draw_lock:
                with self._state_lock:
                    self.loaded, self.rec, self.metrics = None, None, {}
                    self.load_error = f"cannot load frame {req.frame_id}: {exc}"
                for view in list(self.views.values()):
                    view.show_frame(None)
                    view.show(None, None)
            self._status(req.frame_id, "failed")
            self._bump()
            return
        new_frame = self.loaded is not loaded
        if new_frame:
            with self.draw_lock:
                with self._state_lock:
                    self.loaded, self.rec, self.load_error, self.metrics = loaded, None, None, {}
                for view in list(self.views.values()):
                    view.show_frame(loaded)
                    view.show(None, loaded)
        self.load_error = None
        until = STAGES[req.reveal - 1]
        runs: dict[str, Any] = {}
        rec: Reconstruction | None = None
        shown: Reconstruction | None = None
        stages = pipe.stages(req.params, until)
        self.running = STAGES[0]
        progress_at = req.t0  # the request, then when the run last showed a stage
        timing = self.timing = dict.fromkeys(TIMING_KEYS, 0.0)
        while True:
            with timed(timing, "compute"):
                try:
                    run = next(stages)
                except StopIteration:
                    break
                except StageError as exc:
                    rec = Reconstruction(dict(runs), exc.stage, exc.reason, req.params)
                    break
            runs[run.stage] = run
            rec = Reconstruction(dict(runs), None, None, req.params)
            nxt = STAGES.index(run.stage) + 1
            self.running = STAGES[nxt] if run.stage != until and nxt < len(STAGES) else None
            self.latency_ms[run.stage] = 1000.0 * (time.perf_counter() - req.t0)
            # a cached stage changes no view: it is shown with the next computed one; the last
            # stage's layers come after the run's final state (below), unless a newer request
            # supersedes the run now: it is then shown as it is (a dragged slider's steps)
            superseded = self._superseded(req)
            if run.stage == until and not superseded:
                break
            if req.pause_s or superseded or (not run.cached and self._due(progress_at)):
                with timed(timing, "publish"):
                    self._publish(rec, loaded)
                self._bump()
                shown, progress_at = rec, time.perf_counter()
                self.latency_ms["shown"] = 1000.0 * (time.perf_counter() - req.t0)
            if superseded:
                return
            if req.pause_s and run.stage != until:
                with self._cond:
                    self._cond.wait_for(lambda: self._superseded(req), req.pause_s)
                if self._superseded(req):
                    return
        if rec is None:
            return
        with timed(timing, "metrics"):
            try:
                metrics, self.metrics_error = (
                    evaluate_reconstruction(rec, loaded.calib, loaded.ground_truth),
                    None,
                )
            except Exception as exc:  # e.g. a ground truth holding NaN: the figures say why
                metrics, self.metrics_error = {}, f"metrics: {type(exc).__name__}: {exc}"
        # the frame list's status first: the run's answer below may reach the page (or a
        # client's next request for the frame list) before this thread goes on
        if rec.failed_stage is not None or "camera" in rec.runs:
            self._status(req.frame_id, rec.status)
        with self._state_lock, self._cond:  # the run's final state
            self.rec, self.metrics = rec, metrics
            self._answered_seq = max(self._answered_seq, req.seq)
        self.latency_ms["final"] = 1000.0 * (time.perf_counter() - req.t0)
        self._bump()
        self._answer_first(req)
        self.latency_ms["answered"] = 1000.0 * (time.perf_counter() - req.t0)
        if rec is not shown:
            with timed(timing, "publish"):
                self._publish(rec, loaded)
            self.latency_ms["shown"] = 1000.0 * (time.perf_counter() - req.t0)
        if new_frame:  # a new frame's run may have compiled kernels: a slider move's may not
            heap.settle_if_grown()
