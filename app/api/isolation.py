"""The page in a process of its own: ``Origin-Agent-Cluster: ?1`` on every answer.

The page embeds the viser viewer in an iframe of the same host on another port: the same site,
so by default the browser runs both in one renderer process, on one main thread. Without a
GPU, the viewer's WebGL frames are software-rendered there (about 100 ms each on a loaded
2-core machine) and the page's answers and redraws wait behind them after every slider move.
An origin-keyed agent cluster lets the browser give the page's origin its own process (the
viewer keeps rendering in the other). The page and the viewer only talk through the server,
never through ``document.domain`` (which an origin-keyed page gives up).
"""

from __future__ import annotations

from typing import Any

HEADER = (b"origin-agent-cluster", b"?1")


class OriginIsolation:
    """ASGI middleware: adds :data:`HEADER` to every HTTP response."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_header(message: dict) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", []), HEADER]}
            await send(message)

        await self.app(scope, receive, send_with_header)
