"""What the server holds: the frame library, the sessions, the rating store, the evaluation job
and the viser server whose clients are the sessions' 3D views."""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
import threading

import viser

from threadrecon.app.api.config import ServerConfig
from threadrecon.app.api.guard import Policy, guard_viser
from threadrecon.app.corrections import CorrectionStore, with_corrections
from threadrecon.app.errors import Conflict, Invalid, NotFound
from threadrecon.app.jobs import EvaluationJob
from threadrecon.app.library import FrameLibrary
from threadrecon.app.presets import find_preset, load_preset
from threadrecon.app.ratings import RatingStore
from threadrecon.app.scene import SceneView
from threadrecon.app.session import Session
from threadrecon.app.sessions import SessionManager
from threadrecon.core.pipeline import ReconParams

log = logging.getLogger("threadrecon.server")
API_SESSION = "api"  # the session used by REST calls that name none


class AppState:
    def __init__(self, config: ServerConfig) -> None:
        self.config = config
        self.policy = Policy(config.allow_origins, config.host)
        self.store = RatingStore(config.db)  # StoreError now, not at the first rating
        self.corrections = CorrectionStore(self.store)  # the same file, its own table
        self.library = FrameLibrary(config.data_dir, corrections=self.corrections.active)
        self.job: EvaluationJob | None = None
        self.job_saved: int | None = None
        self._job_lock = threading.Lock()
        self.sessions = SessionManager(self.library, idle_timeout_s=config.idle_timeout_s)
        self.viser: viser.ViserServer | None = None
        self._views: dict[int, Session] = {}
        self._lock = threading.Lock()

    # --- viser ------------------------------------------------------------------------------

    def start_viser(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: we print one URL
            server = viser.ViserServer(
                host=self.config.host, port=self.config.viser_port, verbose=False
            )
        if not guard_viser(server.get_port(), self.policy):
            server.stop()
            raise RuntimeError("cannot guard the viser websocket (unexpected viser version)")
        server.scene.set_up_direction("-y")
        server.scene.configure_environment_map(hdri=None)
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        self.viser = server

    @property
    def viser_port(self) -> int:
        assert self.viser is not None
        return self.viser.get_port()

    def _session_of(self, client: viser.ClientHandle) -> Session:
        """The session named in the client's websocket path (``/session/<id>``), or a new one
        for a viser client opened on its own."""
        sid = None
        with contextlib.suppress(AttributeError, KeyError):  # viser internals: best effort
            conn = self.viser._websock_server._live_connections[client.client_id]  # type: ignore[union-attr]
            path = conn.request.path.partition("?")[0]
            parts = [p for p in path.split("/") if p]
            if len(parts) == 2 and parts[0] == "session":
                sid = parts[1]
        session = self.sessions.find(sid) if sid else None
        if session is None:
            session = self.sessions.create(sid)
            session.submit()
        return session

    def _on_connect(self, client: viser.ClientHandle) -> None:
        session = self._session_of(client)
        view = SceneView(client, session)
        with self._lock:
            self._views[client.client_id] = session
        session.attach(client.client_id, view)

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            session = self._views.pop(client.client_id, None)
        if session is not None:
            session.detach(client.client_id)

    async def expire_sessions(self) -> None:
        """Close idle sessions, checking a few times per timeout (a lifespan task)."""
        period = max(0.05, min(30.0, self.config.idle_timeout_s / 4))
        while True:
            await asyncio.sleep(period)
            closed = await asyncio.to_thread(self.sessions.expire)
            if closed:
                log.info("closed %d idle session(s)", len(closed))

    def stop(self) -> None:
        if self.job is not None:
            self.job.cancel()
        self.sessions.close()
        self.store.close()
        if self.viser is not None:
            with contextlib.redirect_stdout(io.StringIO()):
                self.viser.stop()
            self.viser = None

    # --- helpers ----------------------------------------------------------------------------

    def session(self, sid: str | None) -> Session:
        """The session ``sid``; the shared API session for None or "api" (created on use)."""
        if sid is None or sid == API_SESSION:
            found = self.sessions.find(API_SESSION)
            if found is not None:
                found.touch()
                return found
            return self.sessions.create(API_SESSION)
        return self.sessions.get(sid)

    def preset(self, name: str) -> ReconParams:
        """A preset by name (built-in or the user's); NotFound / Invalid otherwise."""
        path = find_preset(name, self.config.configs)
        try:
            return load_preset(path)
        except ValueError as exc:  # a broken preset file: its problem, named
            raise Invalid(str(exc)) from None

    def frame(self, frame_id: str) -> None:
        self.library.get(frame_id)

    def start_job(self, params: ReconParams, preset: str) -> EvaluationJob:
        with self._job_lock:
            if self.job is not None and self.job.state in ("pending", "running"):
                raise Conflict("an evaluation is already running: cancel it first")
            # every frame with the user's corrections, as the debugger runs it
            frames = with_corrections(self.library.frames.values(), self.corrections.active)
            self.job = EvaluationJob(frames, params, preset, on_done=self._job_done)
            self.job_saved = None
            return self.job.start()

    def current_job(self) -> EvaluationJob:
        if self.job is None:
            raise NotFound("no evaluation was started since the server started")
        return self.job

    def _job_done(self, job: EvaluationJob) -> None:
        if job.state == "done":
            self.job_saved = self.store.save_evaluation(
                job.preset, job.params_hash, job.params.to_dict(), job.rows, job.summary
            )
