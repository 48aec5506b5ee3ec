"""Who may talk to the debugger: Host and Origin checks, and a request body limit.

The debugger has no accounts: anyone who reaches it can change parameters, cancel a running
evaluation or write presets. So it answers only requests addressed to it by a loopback name
(the Host header: stops DNS rebinding) and sent by a page of a loopback origin (the Origin
header: stops a foreign site's cross-site request). ``--allow-origin`` widens both. The same
check guards the viser websocket (:func:`guard_viser`).
"""

from __future__ import annotations

import gc
import json
import logging
from collections.abc import Awaitable, Callable, Iterable
from typing import Any
from urllib.parse import urlsplit

log = logging.getLogger("threadrecon.guard")
LOOPBACK = frozenset({"localhost", "127.0.0.1", "::1", "[::1]"})

Scope = dict[str, Any]
Message = dict[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


class Policy:
    """The allowed hosts and origins."""

    def __init__(self, allow_origins: Iterable[str] = (), bind_host: str | None = None) -> None:
        self.any = False
        self.origins: set[str] = set()
        self.hosts: set[str] = set(LOOPBACK)
        for origin in allow_origins:
            if origin == "*":
                self.any = True
                continue
            parts = urlsplit(origin)
            if parts.scheme not in ("http", "https") or not parts.hostname:
                raise ValueError(f"--allow-origin must look like http://host:port, got {origin!r}")
            self.origins.add(f"{parts.scheme}://{parts.netloc}".lower())
            self.hosts.add(parts.hostname.lower())
        if bind_host and bind_host not in ("0.0.0.0", "::", ""):
            self.hosts.add(bind_host.lower())

    def host_ok(self, host: str | None) -> bool:
        if self.any:
            return True
        if not host:
            return False
        name = urlsplit(f"//{host}").hostname
        return name is not None and (name.lower() in self.hosts or f"[{name}]" in self.hosts)

    def origin_ok(self, origin: str | None) -> bool:
        """No Origin (curl, the CLI, a same-origin GET) is fine; "null" or a foreign one not."""
        if origin is None or self.any:
            return True
        parts = urlsplit(origin)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            return False
        if parts.hostname.lower() in LOOPBACK:
            return True
        return f"{parts.scheme}://{parts.netloc}".lower() in self.origins

    def refusal(self, host: str | None, origin: str | None) -> str | None:
        """Why a request with these headers is refused, or None."""
        if not self.host_ok(host):
            return f"forbidden host {host!r}: the debugger answers to loopback names (see --allow-origin)"
        if not self.origin_ok(origin):
            return (
                f"forbidden origin {origin!r}: cross-site requests are refused (see --allow-origin)"
            )
        return None


class Guard:
    """ASGI middleware: Host/Origin policy on every HTTP and websocket request, and a body
    limit (413) checked on Content-Length first and then counted as the body streams in, so a
    huge body is never held in memory."""

    def __init__(self, app: ASGIApp, policy: Policy, max_body: int) -> None:
        self.app, self.policy, self.max_body = app, policy, max_body

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        why = self.policy.refusal(headers.get("host"), headers.get("origin"))
        if why is not None:
            if scope["type"] == "websocket":
                return await send({"type": "websocket.close", "code": 1008})
            return await _answer(send, 403, why)
        if scope["type"] == "websocket":
            return await self.app(scope, receive, send)
        length = headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > self.max_body):
            return await _answer(send, 413, self._too_large())
        seen = 0
        started = refused = False

        async def counted() -> Message:
            nonlocal seen, started, refused
            message = await receive()
            if message["type"] == "http.request" and not refused:
                seen += len(message.get("body", b""))
                if seen > self.max_body:  # answer now; the app sees a client that left
                    refused = True
                    if not started:
                        started = True
                        await _answer(send, 413, self._too_large())
                    return {"type": "http.disconnect"}
            return message

        async def tracked(message: Message) -> None:
            nonlocal started
            if refused:
                return
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counted, tracked)
        except Exception:
            if not refused:
                raise

    def _too_large(self) -> str:
        return f"request body too large: at most {self.max_body} bytes"


async def _answer(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


def guard_viser(port: int, policy: Policy) -> bool:
    """Put the Host/Origin check in front of the viser server listening on ``port``.

    viser 1.1 gives no hook for the websocket handshake, so the ``websockets`` server object
    it created is found and its ``process_request`` (which websockets calls for every
    handshake) wrapped: a refused handshake gets 403 and never reaches viser. False when the
    server was not found (the caller refuses to start rather than run unguarded)."""
    import http

    from websockets.asyncio.server import Server
    from websockets.datastructures import Headers
    from websockets.http11 import Response

    for obj in gc.get_objects():
        try:
            if not isinstance(obj, Server) or obj.server is None:
                continue
        except ReferenceError:  # a weakref.proxy on the heap whose object is gone
            continue
        if not any(s.getsockname()[1] == port for s in obj.server.sockets):
            continue
        inner = obj.process_request

        def checked(connection: Any, request: Any, inner: Any = inner) -> Any:
            why = policy.refusal(request.headers.get("Host"), request.headers.get("Origin"))
            if why is not None:
                log.warning("viser: %s", why)
                return Response(http.HTTPStatus.FORBIDDEN, "Forbidden", Headers(), why.encode())
            return inner(connection, request) if inner is not None else None

        obj.process_request = checked
        return True
    return False
