"""All sessions of the server, by id, with an idle timeout and a bound on their number."""

from __future__ import annotations

import threading
import uuid

from threadrecon.app.errors import NotFound
from threadrecon.app.heap import release_memory
from threadrecon.app.library import FrameLibrary
from threadrecon.app.session import Session

MAX_SESSIONS = 64  # beyond this the longest-idle session without a 3D view is closed
IDLE_TIMEOUT_S = 600.0  # a session without a view and unused this long is closed


class SessionManager:
    def __init__(
        self,
        library: FrameLibrary,
        idle_timeout_s: float = IDLE_TIMEOUT_S,
        max_sessions: int = MAX_SESSIONS,
    ) -> None:
        self.library = library
        self.idle_timeout_s = idle_timeout_s
        self.max_sessions = max_sessions
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()
        self.frame_status: dict[str, str] = {}

    def _on_status(self, frame_id: str, status: str) -> None:
        self.frame_status[frame_id] = status

    def __len__(self) -> int:
        return len(self._sessions)

    def create(self, sid: str | None = None) -> Session:
        """A new session (or the open one named ``sid``)."""
        dropped = None
        with self._lock:
            sid = sid or uuid.uuid4().hex
            if sid in self._sessions:
                return self._sessions[sid]
            if len(self._sessions) >= self.max_sessions:
                idle = [s for s in self._sessions.values() if not s.views]
                if idle:
                    dropped = max(idle, key=lambda s: s.idle_for())
                    del self._sessions[dropped.id]
            session = Session(sid, self.library, self._on_status)
            self._sessions[sid] = session
        if dropped is not None:
            dropped.close()
        return session

    def get(self, sid: str) -> Session:
        """The open session ``sid`` (marked as used); :class:`NotFound` otherwise."""
        with self._lock:
            session = self._sessions.get(sid)
        if session is None:
            raise NotFound(f"unknown session {sid!r} (closed, or expired after being idle)")
        session.touch()
        return session

    def all(self) -> list[Session]:
        """The open sessions."""
        with self._lock:
            return list(self._sessions.values())

    def find(self, sid: str) -> Session | None:
        with self._lock:
            return self._sessions.get(sid)

    def delete(self, sid: str) -> None:
        with self._lock:
            session = self._sessions.pop(sid, None)
        if session is None:
            raise NotFound(f"unknown session {sid!r}")
        session.close()
        release_memory()

    def expire(self) -> list[str]:
        """Close the sessions idle for longer than the timeout; their ids."""
        with self._lock:
            old = [s for s in self._sessions.values() if s.idle_for() > self.idle_timeout_s]
            for s in old:
                del self._sessions[s.id]
        for s in old:
            s.close()
        if old:
            release_memory()
        return [s.id for s in old]

    def stop_waiting(self) -> None:
        """The server is stopping: every long poll answers now."""
        with self._lock:
            sessions = list(self._sessions.values())
        for s in sessions:
            s.changes.close()

    def close(self) -> None:
        with self._lock:
            sessions = list(self._sessions.values())
            self._sessions.clear()
        for s in sessions:
            s.close()
