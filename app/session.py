"""Debugger sessions: one per browser tab.

A session holds the frame being looked at, the parameters, how many stages are revealed, the
latest reconstruction, and the 3D views (viser clients) that show it. Controls only *submit*
what they want (frame, parameters, stages to reveal); one worker thread per session computes
the newest request (latest wins: an older request still running stops at its next stage) and
publishes each stage's layers as soon as the stage exists. Each session keeps its own pipelines,
so two tabs never disturb each other's cache or scene.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from app.dataset import Frame, discover, evaluate_reconstruction, load_frame
from app.presets import diff, params_hash, validate
from app.views import overlay
from core.calibration import StereoCalibration
from core.pipeline import STAGES, Pipeline, ReconParams, Reconstruction, StageError
from core.segmentation import StereoPair

PIPELINES_PER_SESSION = 3  # frames whose stage cache a session keeps (back-and-forth browsing)
LOADED_FRAMES = 16  # decoded frames kept by the library
MAX_SESSIONS = 64  # the oldest session without a viewer is dropped beyond this


@dataclass(frozen=True)
class LoadedFrame:
    frame: Frame
    pair: StereoPair
    calib: StereoCalibration
    ground_truth: np.ndarray | None


class FrameLibrary:
    """The frames of a data folder, decoded on demand and kept in a small LRU cache."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.frames: dict[str, Frame] = {f.id: f for f in discover(self.root)}
        self._cache: OrderedDict[str, LoadedFrame] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, frame_id: str) -> Frame:
        try:
            return self.frames[frame_id]
        except KeyError:
            raise KeyError(f"unknown frame {frame_id!r}") from None

    def load(self, frame_id: str) -> LoadedFrame:
        """Raises KeyError for an unknown id, ValueError/OSError for an unreadable frame."""
        frame = self.get(frame_id)
        with self._lock:
            hit = self._cache.get(frame_id)
            if hit is not None:
                self._cache.move_to_end(frame_id)
                return hit
        pair, calib, gt = load_frame(frame)
        loaded = LoadedFrame(frame, pair, calib, gt)
        with self._lock:
            self._cache[frame_id] = loaded
            while len(self._cache) > LOADED_FRAMES:
                self._cache.popitem(last=False)
        return loaded


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
    reveal: int
    """Number of stages to compute and show (1..len(STAGES))."""
    pause_s: float
    """Pause after each stage, so that a streamed run can be watched."""
    t0: float
    """perf_counter() when the request was made (for the latency figures)."""


def merge_params(params: ReconParams, patch: dict[str, Any]) -> ReconParams:
    """``params`` with the values of ``{stage: {name: value}}`` (or ``{"stage.name": value}``)
    applied; raises ValueError naming the parameter when a value is invalid."""
    data = params.to_dict()
    for key, value in patch.items():
        if isinstance(value, dict):
            if key not in data:
                raise ValueError(f"unknown parameter group {key!r} (known: {', '.join(STAGES)})")
            data[key].update(value)
        else:
            stage, _, name = key.partition(".")
            if stage not in data or not name:
                raise ValueError(f"unknown parameter {key}")
            data[stage][name] = value
    return validate(data)


class Session:
    def __init__(
        self,
        sid: str,
        library: FrameLibrary,
        on_status: Callable[[str, str], None] | None = None,
    ) -> None:
        self.id = sid
        self.library = library
        self._on_status = on_status
        self._cond = threading.Condition()
        self._seq = 0
        self._done_seq = 0
        self._pending: Request | None = None
        self._closed = False
        self._worker: threading.Thread | None = None
        self.draw_lock = threading.RLock()
        # What the user asked for most recently (the controls show this).
        self.frame_id: str | None = None
        self.params = ReconParams()
        self.preset = "default"
        self.reveal = len(STAGES)
        # What the worker produced.
        self.loaded: LoadedFrame | None = None
        self.rec: Reconstruction | None = None
        self.load_error: str | None = None
        self.running: str | None = None
        self.metrics: dict[str, float] = {}
        self.latency_ms: dict[str, float] = {}
        self.inspect: dict[str, Any] | None = None
        self.version = 0
        self.views: dict[int, View] = {}
        self.last_used = time.time()
        self._pipelines: OrderedDict[str, Pipeline] = OrderedDict()
        self._overlay: tuple[tuple, dict[str, Any]] | None = None

    # --- requests ---------------------------------------------------------------------------

    def submit(
        self,
        frame_id: str | None = None,
        params: ReconParams | None = None,
        reveal: int | None = None,
        pause_s: float = 0.0,
        preset: str | None = None,
    ) -> int:
        """Ask for a run; returns its sequence number. A newer request supersedes it."""
        if frame_id is not None:
            self.library.get(frame_id)  # KeyError for an unknown frame
        changed = False
        with self._cond:
            if self._closed:
                raise RuntimeError(f"session {self.id} is closed")
            if frame_id is not None and frame_id != self.frame_id:
                self.frame_id = frame_id
                self.inspect = None
            if self.frame_id is None:
                self.frame_id = next(iter(self.library.frames))
            if params is not None:
                changed = params != self.params
                self.params = params
                if preset is not None:
                    self.preset = preset
                elif changed:
                    self.preset = "custom"
            if reveal is not None:
                if not 1 <= reveal <= len(STAGES):
                    raise ValueError(f"reveal must be in [1, {len(STAGES)}], got {reveal}")
                self.reveal = reveal
            self._seq += 1
            self._pending = Request(
                self._seq,
                self.frame_id,
                self.params,
                self.reveal,
                max(0.0, pause_s),
                time.perf_counter(),
            )
            self.last_used = time.time()
            if self._worker is None:
                self._worker = threading.Thread(
                    target=self._loop, name=f"session-{self.id[:8]}", daemon=True
                )
                self._worker.start()
            self._cond.notify_all()
            seq = self._seq
        if changed:  # every view's controls follow, whoever changed the parameters
            self.sync_params()
        return seq

    def step(self, action: str, pause_s: float = 0.0) -> int:
        """The stage stepper: "run" (every stage, streamed with ``pause_s`` between them),
        "next" (reveal one more stage, from the first after the last) or "all"."""
        n = len(STAGES)
        if action == "run":
            return self.submit(reveal=n, pause_s=pause_s)
        if action == "next":
            return self.submit(reveal=1 if self.reveal >= n else self.reveal + 1)
        if action == "all":
            return self.submit(reveal=n)
        raise ValueError(f"action must be run, next or all, got {action!r}")

    def wait(self, seq: int, timeout: float = 60.0) -> bool:
        """Block until request ``seq`` (or a newer one) has finished; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._done_seq < seq and not self._closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until every request made so far has finished."""
        with self._cond:
            seq = self._seq
        return self.wait(seq, timeout)

    @property
    def busy(self) -> bool:
        with self._cond:
            return self._done_seq < self._seq

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # --- views --------------------------------------------------------------------------------

    def attach(self, key: int, view: View) -> None:
        with self.draw_lock:
            self.views[key] = view
            view.show_params(self.params)
            view.show_frame(self.loaded)
            view.show(self.rec, self.loaded)
            view.show_inspect(self.inspect)

    def detach(self, key: int) -> None:
        with self.draw_lock:
            self.views.pop(key, None)

    def set_inspect(self, info: dict[str, Any] | None) -> None:
        with self.draw_lock:
            self.inspect = info
            for view in list(self.views.values()):
                view.show_inspect(info)
            self.version += 1

    def sync_params(self) -> None:
        """Show the current parameters in every view (after a preset load or a reset)."""
        with self.draw_lock:
            for view in list(self.views.values()):
                view.show_params(self.params)

    # --- the worker ---------------------------------------------------------------------------

    def _superseded(self, req: Request) -> bool:
        return self._seq != req.seq or self._closed

    def _loop(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                req, self._pending = self._pending, None
            try:
                self._execute(req)
            finally:
                with self._cond:
                    if self._pending is None:
                        self._done_seq = max(self._done_seq, req.seq)
                    self.running = None
                    self._cond.notify_all()

    def _execute(self, req: Request) -> None:
        self.latency_ms = {}
        try:
            loaded = self.library.load(req.frame_id)
            pipe = self._pipeline(req.frame_id, loaded)
        except (ValueError, OSError) as exc:
            with self.draw_lock:
                self.loaded, self.rec, self.metrics = None, None, {}
                self.load_error = f"cannot load frame {req.frame_id}: {exc}"
                for view in list(self.views.values()):
                    view.show_frame(None)
                    view.show(None, None)
                self.version += 1
            self._status(req.frame_id, "failed")
            return
        if self.loaded is not loaded:
            with self.draw_lock:
                self.loaded, self.rec, self.load_error, self.metrics = loaded, None, None, {}
                for view in list(self.views.values()):
                    view.show_frame(loaded)
                    view.show(None, loaded)
        self.load_error = None
        until = STAGES[req.reveal - 1]
        runs: dict[str, Any] = {}
        rec: Reconstruction | None = None
        stages = pipe.stages(req.params, until)
        self.running = STAGES[0]
        while True:
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
            self._publish(rec, loaded)
            self.latency_ms[run.stage] = 1000.0 * (time.perf_counter() - req.t0)
            if self._superseded(req):
                return
            if req.pause_s and run.stage != until:
                with self._cond:
                    self._cond.wait_for(lambda: self._superseded(req), req.pause_s)
                if self._superseded(req):
                    return
        if rec is None:
            return
        self._publish(rec, loaded)
        metrics = evaluate_reconstruction(rec, loaded.calib, loaded.ground_truth)
        with self.draw_lock:
            self.metrics = metrics
            self.version += 1
        if rec.failed_stage is not None or "camera" in rec.runs:
            self._status(req.frame_id, rec.status)

    def _publish(self, rec: Reconstruction, loaded: LoadedFrame) -> None:
        with self.draw_lock:
            self.rec = rec
            for view in list(self.views.values()):
                view.show(rec, loaded)
            self.version += 1

    def _status(self, frame_id: str, status: str) -> None:
        if self._on_status is not None:
            self._on_status(frame_id, status)

    def _pipeline(self, frame_id: str, loaded: LoadedFrame) -> Pipeline:
        pipe = self._pipelines.get(frame_id)
        if pipe is None or pipe.pair is not loaded.pair:
            pipe = Pipeline(loaded.pair, loaded.calib)
            self._pipelines[frame_id] = pipe
        self._pipelines.move_to_end(frame_id)
        while len(self._pipelines) > PIPELINES_PER_SESSION:
            self._pipelines.popitem(last=False)
        return pipe

    def overlay(self) -> dict[str, Any]:
        """The 2D overlays of the current reconstruction, computed once per set of stage
        results (the page asks after every stage; a cached stage costs nothing)."""
        with self.draw_lock:
            rec, loaded, version = self.rec, self.loaded, self.version
        if rec is None or loaded is None:
            return {"frame_id": self.frame_id, "version": version}
        key = (loaded.frame.id, *(id(run.result) for run in rec.runs.values()))
        cached = self._overlay
        if cached is None or cached[0] != key:
            cached = (key, overlay(rec, loaded.calib))
            self._overlay = cached
        return {**cached[1], "frame_id": loaded.frame.id, "version": version}

    # --- state for the page -------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """The stepper, metrics and errors, as the page polls them."""
        with self.draw_lock:
            rec, version = self.rec, self.version
            stages = []
            for i, stage in enumerate(STAGES):
                entry: dict[str, Any] = {"stage": stage, "revealed": i < self.reveal}
                if rec is not None and stage in rec.runs:
                    run = rec.runs[stage]
                    entry.update(status="cached" if run.cached else "done", ms=run.ms)
                    if stage == "spline" and not run.result.ok:
                        entry["status"] = "fallback"
                elif rec is not None and rec.failed_stage == stage:
                    entry["status"] = "failed"
                elif self.running == stage:
                    entry["status"] = "running"
                else:
                    entry["status"] = "pending"
                stages.append(entry)
            error = self.load_error or (rec.message if rec is not None else None)
            return {
                "session": self.id,
                "version": version,
                "frame_id": self.frame_id,
                "shown_frame": self.loaded.frame.id if self.loaded is not None else None,
                "busy": self.busy,
                "preset": self.preset,
                "params": self.params.to_dict(),
                "params_hash": params_hash(self.params),
                "diff": diff(self.params),
                "reveal": self.reveal,
                "stages": stages,
                "status": "failed" if self.load_error else (rec.status if rec else "pending"),
                "failed_stage": "load"
                if self.load_error
                else (rec.failed_stage if rec is not None else None),
                "error": error,
                "metrics": self.metrics,
                "latency_ms": dict(self.latency_ms),
                "inspect": self.inspect,
                "unit": self.loaded.calib.unit if self.loaded is not None else None,
            }


class SessionManager:
    """All sessions of the server, by id."""

    def __init__(self, library: FrameLibrary) -> None:
        self.library = library
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()
        self.frame_status: dict[str, str] = {}

    def _on_status(self, frame_id: str, status: str) -> None:
        self.frame_status[frame_id] = status

    def create(self, sid: str | None = None) -> Session:
        with self._lock:
            sid = sid or uuid.uuid4().hex
            if sid in self._sessions:
                return self._sessions[sid]
            if len(self._sessions) >= MAX_SESSIONS:
                idle = [s for s in self._sessions.values() if not s.views]
                if idle:
                    oldest = min(idle, key=lambda s: s.last_used)
                    oldest.close()
                    del self._sessions[oldest.id]
            session = Session(sid, self.library, self._on_status)
            self._sessions[sid] = session
            return session

    def get(self, sid: str) -> Session:
        with self._lock:
            try:
                return self._sessions[sid]
            except KeyError:
                raise KeyError(f"unknown session {sid!r}") from None

    def find(self, sid: str) -> Session | None:
        with self._lock:
            return self._sessions.get(sid)

    def close(self) -> None:
        with self._lock:
            for s in self._sessions.values():
                s.close()
            self._sessions.clear()
