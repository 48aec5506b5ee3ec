"""Debugger sessions: one per browser tab.

A session holds the frame being looked at, the parameters, how many stages are revealed, the
latest reconstruction, and the 3D views (viser clients) that show it. Controls only *submit*
what they want (frame, parameters, stages to reveal); one worker thread per session computes
the newest request (latest wins: an older request still running stops at its next stage).
Once it is done, its final state (results and metrics) becomes the session's, the page's long
poll answers it with the 2D overlays, and only then do the 3D views draw its last layers (a run
that has taken longer than ``PROGRESS_AFTER_S`` shows the stages computed so far at that pace;
a streamed one shows each stage's as soon as it exists). The state is read under its own lock,
never behind the views' drawing. The worker survives any exception (the stage that raised shows
the error; the next request runs). Waiting is possible from a thread (:meth:`Session.wait`: the
views have drawn) or the event loop, holding no thread (:meth:`Session.finished`: the final
state is out).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any

from threadrecon.app.errors import Conflict, Invalid
from threadrecon.app.library import FrameLibrary, LoadedFrame, merge_params
from threadrecon.app.notify import Changes
from threadrecon.app.session_run import RunWorker
from threadrecon.app.session_state import Request, View, describe
from threadrecon.app.views import OverlayCache
from threadrecon.core.pipeline import STAGES, Pipeline, ReconParams, Reconstruction

__all__ = ["FrameLibrary", "LoadedFrame", "Session", "View", "merge_params"]

log = logging.getLogger("threadrecon.session")
PIPELINES_PER_SESSION = 3  # frames whose stage cache a session keeps (back-and-forth browsing)
MAX_PAUSE_S = 10.0  # longest pause between streamed stages (a watchable step, not a hang)
PROGRESS_AFTER_S = 0.4  # a run shows the stages it has computed this long after the request,
# then at most once per this long (the pace at which the page's 2D overlays follow a run,
# images.js OVERLAY_EVERY_MS); a quicker run (a slider move) shows its result once: one batch of
# scene updates, one redraw. Each stage of a run older than 0.1 s used to be shown: a move that
# crossed it (1920x1080, or any size on a loaded machine) drew its intermediate 3D layers
# before its final state, and the page waited for them
ANSWER_FIRST_S = 0.25  # with a page's long poll waiting, the views draw a run's last layers
# once it has answered the final state, or after this long: the answer (state, 2D overlays,
# JSON) and the 3D batch (Python here, software WebGL in the browser) no longer share the
# two cores; the bound keeps the views going if the page is slow to answer


class Session(RunWorker):
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
        self._done_seq = 0  # the last request finished: final state out, layers drawn
        self._answered_seq = 0  # the last request whose final state is the session's
        self._polls = 0  # page long polls waiting for, or building, an answer
        self._answered_version = 0  # the newest version a long poll has answered
        self._pending: Request | None = None
        self._closed = False
        self._worker: threading.Thread | None = None
        self.changes = Changes()
        self.draw_lock = threading.RLock()  # the views' drawing
        self._state_lock = threading.Lock()  # what state() and overlay() read together
        # What the user asked for most recently (the controls show this).
        self.frame_id: str | None = None
        self.params = ReconParams()
        self.preset = "default"
        self.reveal = len(STAGES)
        # What the worker produced.
        self.loaded: LoadedFrame | None = None
        self.rec: Reconstruction | None = None
        self.load_error: str | None = None
        self.metrics_error: str | None = None
        self.running: str | None = None
        self.metrics: dict[str, float] = {}
        self.latency_ms: dict[str, float] = {}
        self.inspect: dict[str, Any] | None = None
        self.views: dict[int, View] = {}
        self.last_used = time.monotonic()
        self._pipelines: OrderedDict[str, Pipeline] = OrderedDict()
        self._overlays = OverlayCache()
        self.timing: dict[str, float] = {}  # the last request's ms: compute, publish (+ _cpu)

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
            self.library.get(frame_id)  # NotFound for an unknown frame
        if reveal is not None and not 1 <= reveal <= len(STAGES):
            raise Invalid(f"reveal must be in [1, {len(STAGES)}], got {reveal}")
        if not 0.0 <= pause_s <= MAX_PAUSE_S:  # NaN fails too
            raise Invalid(f"pause must be in [0, {MAX_PAUSE_S:g}] s, got {pause_s!r}")
        if self.library.first_id() is None:
            raise Conflict(f"no frames in {self.library.root}")
        changed = False
        with self._cond:
            if self._closed:
                raise Conflict(f"session {self.id} is closed")
            if frame_id is not None and frame_id != self.frame_id:
                self.frame_id = frame_id
                self.inspect = None
            if self.frame_id is None:
                self.frame_id = self.library.first_id()
            if params is not None:
                changed = params != self.params
                self.params = params
                if preset is not None:
                    self.preset = preset
                elif changed:
                    self.preset = "custom"
            if reveal is not None:
                self.reveal = reveal
            self._seq += 1
            self._pending = Request(
                self._seq, self.frame_id, self.params, self.reveal, pause_s, time.perf_counter()
            )
            self.touch()
            if self._worker is None or not self._worker.is_alive():
                self._worker = threading.Thread(
                    target=self._loop, name=f"session-{self.id[:8]}", daemon=True
                )
                self._worker.start()
            self._cond.notify_all()
            seq = self._seq
        if changed:  # every view's controls follow, whoever changed the parameters
            self.sync_params()
        self._bump()  # the page's long poll learns of the request (preset, busy) at once
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
        raise Invalid(f"action must be run, next or all, got {action!r}")

    def rename_preset(self, name: str) -> None:
        """The session's parameters were saved as preset ``name``."""
        self.preset = name
        self._bump()

    def touch(self) -> None:
        self.last_used = time.monotonic()

    def idle_for(self) -> float:
        """Seconds since the session was last used or its last run ended (0 while a 3D view
        is attached or a run is pending: a first run that compiles the kernels may take longer
        than the idle timeout, and its request waits for it)."""
        if self.views or self.busy:
            return 0.0
        return time.monotonic() - self.last_used

    def wait(self, seq: int, timeout: float = 60.0) -> bool:
        """Block until request ``seq`` (or a newer one) has finished, its layers drawn in
        every view; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._done_seq < seq and not self._closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    async def finished(self, seq: int, timeout: float) -> bool:
        """Wait in the event loop, holding no thread, until request ``seq`` (or a newer one)
        has its final state (the views may still be drawing its last layers)."""
        return await self.changes.until(lambda: self._answered_seq >= seq, timeout)

    async def changed(self, since: int, timeout: float) -> bool:
        """Wait in the event loop until the session's version is newer than ``since``."""
        return await self.changes.until(lambda: self.version > since, timeout)

    @property
    def seq(self) -> int:
        return self._seq

    @property
    def busy(self) -> bool:
        """The state is not the latest request's final one yet."""
        return self._answered_seq < self._seq

    @contextlib.contextmanager
    def polling(self) -> Iterator[Callable[[int], None]]:
        """A page's long poll: while it waits and builds its answer, a run's last layers wait
        for it (up to ``ANSWER_FIRST_S``); call the function it gives with the version the
        answer carries once it is built."""
        with self._cond:
            self._polls += 1

        def answered(version: int) -> None:
            with self._cond:
                self._answered_version = max(self._answered_version, version)
                self._cond.notify_all()

        try:
            yield answered
        finally:
            with self._cond:
                self._polls -= 1
                self._cond.notify_all()

    def close(self) -> None:
        """Stop the worker and drop every result, so that the memory is freed."""
        with self._cond:
            self._closed = True
            self._pending = None
            self._cond.notify_all()
        with self.draw_lock:
            self.views.clear()
            self._release()
        self.changes.close()

    def _release(self) -> None:
        self._pipelines.clear()
        self.rec, self.loaded, self.inspect = None, None, None
        self._overlays.clear()

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
        self.touch()  # the idle time counts from the last view's departure

    def set_inspect(self, info: dict[str, Any] | None) -> None:
        with self.draw_lock:
            self.inspect = info
            for view in list(self.views.values()):
                view.show_inspect(info)
        self._bump()

    def sync_params(self) -> None:
        """Show the current parameters in every view (after a preset load or a reset)."""
        with self.draw_lock:
            for view in list(self.views.values()):
                view.show_params(self.params)

    def _bump(self) -> None:
        self.changes.bump()  # a new version; long polls wake up

    @property
    def version(self) -> int:
        return self.changes.version

    # --- the worker ---------------------------------------------------------------------------

    def _superseded(self, req: Request) -> bool:
        return self._seq != req.seq or self._closed

    def _loop(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._closed:
                    self._cond.wait()
                if self._closed:
                    break
                req, self._pending = self._pending, None
            try:
                self._execute(req)
            except Exception as exc:  # any error is this request's failed stage, never the worker's
                log.exception("session %s: request %d failed", self.id, req.seq)
                self._fail(req, exc)
            finally:
                with self._cond:
                    news = self._answered_seq < req.seq  # not announced by _execute
                    if self._pending is None:
                        self._done_seq = max(self._done_seq, req.seq)
                        self._answered_seq = max(self._answered_seq, req.seq)
                    self.running = None
                    self.last_used = time.monotonic()  # idle from the run's end
                    self._cond.notify_all()
                # "busy" changed: a new version, so that a long poll that answered the
                # last one while the run was ending still gets the idle state
                if news:
                    self._bump()
        with self.draw_lock:
            self._release()

    @staticmethod
    def _due(since: float) -> bool:
        """A run's progress is shown: ``PROGRESS_AFTER_S`` has passed since ``since`` (the
        request, or the run's last stage shown)."""
        return time.perf_counter() - since >= PROGRESS_AFTER_S

    def _answer_first(self, req: Request) -> None:
        """With a page's long poll waiting for news, wait (up to ``ANSWER_FIRST_S``) until it
        has answered the current version, unless a newer request or the session's end comes
        first."""
        version = self.version
        with self._cond:
            self._cond.wait_for(
                lambda: (
                    not self._polls or self._answered_version >= version or self._superseded(req)
                ),
                ANSWER_FIRST_S,
            )

    def _publish(self, rec: Reconstruction, loaded: LoadedFrame) -> None:
        """Make ``rec`` the session's reconstruction and draw it in every view (the caller
        makes the new version)."""
        with self.draw_lock:
            with self._state_lock:
                self.rec = rec
            for view in list(self.views.values()):
                view.show(rec, loaded)

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

    def overlay(
        self, known: frozenset[int] = frozenset(), keys: frozenset[str] | None = None
    ) -> dict[str, Any]:
        """The 2D overlays of the current reconstruction (``OverlayCache.answer``: each built
        once per set of its stage results; payloads tagged ``known`` are left out; with
        ``keys``, only those overlays)."""
        with self._state_lock:
            rec, loaded, version = self.rec, self.loaded, self.version
        if rec is None or loaded is None:
            return {"frame_id": self.frame_id, "version": version}
        out = self._overlays.answer(rec, loaded.calib, known, keys)
        return {**out, "frame_id": loaded.frame.id, "version": version}

    def shows(self, frame_id: str) -> bool:
        """True when the session's reconstruction is of ``frame_id``."""
        loaded = self.loaded
        return self.rec is not None and loaded is not None and loaded.frame.id == frame_id

    def state(self) -> dict[str, Any]:
        """The stepper, metrics and errors, as the page polls them (never waits for the views'
        drawing)."""
        with self._state_lock:
            return describe(self)
