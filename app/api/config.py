"""Options of ``threadrecon serve``."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from threadrecon.app.presets import user_configs_dir
from threadrecon.app.resources import default_db
from threadrecon.app.sessions import IDLE_TIMEOUT_S

MAX_BODY_BYTES = 4 * 1024 * 1024  # a request body is a few parameters or a note, never more


@dataclass
class ServerConfig:
    data_dir: Path
    host: str = "127.0.0.1"
    port: int = 8000
    viser_port: int = 8080
    open_first: bool = True
    """Run the first frame at start-up, so the page shows a reconstruction without a click."""
    db_path: Path | None = None
    """Ratings and evaluations (SQLite); default ``<data_dir>/threadrecon.sqlite3``, or the user
    data folder's ``sample_data.sqlite3`` for the bundled sample (never inside the package)."""
    configs_dir: Path | None = None
    """User presets; default the platform's data folder (built-in presets are read-only)."""
    allow_origins: tuple[str, ...] = ()
    """Origins (``http://host:port``) allowed besides the loopback ones; their host names
    are accepted in the Host header too. ``*`` allows every origin and host."""
    idle_timeout_s: float = IDLE_TIMEOUT_S
    """A session without a 3D view and unused for this long is closed."""
    max_body_bytes: int = MAX_BODY_BYTES
    run_timeout_s: float = 120.0
    """A REST run waits this long for its result before answering 504."""
    extra: dict[str, object] = field(default_factory=dict)

    @property
    def db(self) -> Path:
        if self.db_path is not None:
            return self.db_path
        path = default_db(self.data_dir)
        path.parent.mkdir(parents=True, exist_ok=True)  # the user data folder on first use
        return path

    @property
    def configs(self) -> Path:
        return self.configs_dir or user_configs_dir()
