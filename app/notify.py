"""A version counter that threads bump and the event loop awaits, without holding a thread.

A session's worker thread calls :meth:`Changes.bump` whenever something visible changed; a
long poll in the server's event loop awaits :meth:`Changes.until` and is woken through
``loop.call_soon_threadsafe``: no thread is parked per waiting request.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable


class Changes:
    def __init__(self) -> None:
        self.version = 0
        self._lock = threading.Lock()
        self._waiters: set[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = set()
        self.closed = False

    def bump(self) -> None:
        """Something changed: a new version, and every waiter re-checks its condition."""
        with self._lock:
            self.version += 1
        self.notify()

    def notify(self) -> None:
        for loop, event in list(self._waiters):
            with contextlib.suppress(RuntimeError):  # that loop has closed
                loop.call_soon_threadsafe(event.set)

    def close(self) -> None:
        self.closed = True
        self.notify()

    async def until(self, done: Callable[[], bool], timeout: float) -> bool:
        """Wait until ``done()`` (re-checked at every change) or :meth:`close`; False when
        ``timeout`` s passed first or the counter closed with ``done()`` still false."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not done():
            left = deadline - loop.time()
            if left <= 0 or self.closed:
                return done()
            entry = (loop, asyncio.Event())
            self._waiters.add(entry)
            try:
                if done():
                    break
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(entry[1].wait(), left)
            finally:
                self._waiters.discard(entry)
        return True
