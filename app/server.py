"""``threadrecon serve``: the FastAPI app of the debugger (:mod:`app.api`) run by uvicorn,
with a viser server in its lifespan.

The page (``static/``) creates a session, embeds the viser client with the session id in its
websocket path (``ws://host:port/session/<id>``) so that the 3D view, the sliders and the page
all belong to the same session, and long-polls the session's state. The REST API (``/docs``)
is what the page and the tests use.
"""

from __future__ import annotations

import socket
from typing import Any

from app.api import AppState, ServerConfig, create_app

__all__ = ["ServerConfig", "create_app", "serve"]
SHUTDOWN_GRACE_S = 1.0  # open long polls are cut after this long on Ctrl-C


def serve(config: ServerConfig, sock: socket.socket | None = None) -> None:
    """Run the debugger until Ctrl-C. ``sock`` is an already bound listening socket (the CLI
    binds it first, with SO_REUSEADDR, so that a taken port is a one-line error)."""
    import uvicorn

    app = create_app(config)
    state: AppState = app.state.core
    uv = uvicorn.Server(
        uvicorn.Config(
            app, host=config.host, port=config.port, log_level="warning",
            timeout_graceful_shutdown=SHUTDOWN_GRACE_S,
        )
    )  # fmt: skip
    original = uv.startup

    async def startup(sockets: Any = None) -> None:
        await original(sockets)
        if uv.started:
            print(
                f"threadrecon debugger: open http://{config.host}:{config.port}/  "
                f"({len(state.library.frames)} frames of {config.data_dir}; "
                f"3D view on port {state.viser_port})",
                flush=True,
            )

    original_shutdown = uv.shutdown

    async def shutdown(sockets: Any = None) -> None:
        state.sessions.stop_waiting()  # open long polls answer at once instead of at the grace
        await original_shutdown(sockets)

    uv.startup = startup  # type: ignore[method-assign]
    uv.shutdown = shutdown  # type: ignore[method-assign]
    uv.run(sockets=[sock] if sock is not None else None)
