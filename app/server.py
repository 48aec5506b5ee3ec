"""``threadrecon serve``: the FastAPI app of the debugger (:mod:`app.api`) run by uvicorn,
with a viser server in its lifespan.

The page (``static/``) creates a session, embeds the viser client with the session id in its
websocket path (``ws://host:port/session/<id>``) so that the 3D view, the sliders and the page
all belong to the same session, and long-polls the session's state. The REST API (``/docs``)
is what the page and the tests use.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
from pathlib import Path
from typing import Any

from threadrecon.app import heap
from threadrecon.app.api import AppState, ServerConfig, create_app
from threadrecon.app.dataset import discover
from threadrecon.app.errors import UserError

__all__ = ["ServerConfig", "create_app", "serve"]
SHUTDOWN_GRACE_S = 1.0  # open long polls are cut after this long on Ctrl-C


def serve(config: ServerConfig, sock: socket.socket | None = None) -> None:
    """Run the debugger until Ctrl-C. ``sock`` is an already bound listening socket (the CLI
    binds it first, with SO_REUSEADDR, so that a taken port is a one-line error)."""
    import uvicorn

    from threadrecon.core.compiled import set_default_mode

    set_default_mode("jit")  # numba's kernels release the GIL: pipelines in worker threads
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
            heap.settle()  # full garbage collections skip what the start made
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


def cmd_serve(args: argparse.Namespace) -> int:
    from threadrecon.app.ratings import StoreError
    from threadrecon.app.server import ServerConfig, serve

    root = Path(args.dataset)
    discover(root)  # a wrong folder is a one-line error, before anything starts
    for name, port in (("--port", args.port), ("--viser-port", args.viser_port)):
        if port is not None and not 0 < port < 65536:
            raise UserError(f"{name} must be in 1..65535, got {port}")
    viser_port = args.viser_port if args.viser_port is not None else args.port + 1
    if not args.idle_timeout > 0:
        raise UserError(f"--idle-timeout must be > 0, got {args.idle_timeout}")
    if args.max_body < 1:
        raise UserError(f"--max-body must be >= 1, got {args.max_body}")
    family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    # SO_REUSEADDR: a restart right after Ctrl-C binds despite the old connections in
    # TIME_WAIT; the socket is handed to uvicorn, so a taken port is a one-line error here.
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.host, args.port))
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        raise UserError(
            f"cannot listen on {args.host}:{args.port} ({exc.strerror}): choose another --port"
        ) from None
    try:
        from threadrecon.app.api.guard import Policy

        Policy(args.allow_origin)
    except ValueError as exc:
        sock.close()
        raise UserError(str(exc)) from None
    config = ServerConfig(
        data_dir=root,
        host=args.host,
        port=args.port,
        viser_port=viser_port,
        db_path=Path(args.db) if args.db else None,
        configs_dir=Path(args.configs) if args.configs else None,
        allow_origins=tuple(args.allow_origin),
        idle_timeout_s=args.idle_timeout,
        max_body_bytes=args.max_body,
    )
    code = 0
    try:
        serve(config, sock)
    except StoreError as exc:  # an unusable database stops the start, and nothing is written
        raise UserError(str(exc)) from None
    except KeyboardInterrupt:  # uvicorn re-raises Ctrl-C once it has stopped cleanly
        print("threadrecon: interrupted", file=sys.stderr)
        code = 130
    # Stopped cleanly: the database is closed and viser stopped. Skip the interpreter's
    # teardown (seconds of freeing a large heap on a busy machine) so that Ctrl-C is quick.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
