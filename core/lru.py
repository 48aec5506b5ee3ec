"""A small thread-safe least-recently-used map: the caches of derived data in the core (mask
skeletons and indexes, rectification maps, distance fields) all keep a few entries this way.
The server's sessions run pipelines in several threads, so every access takes the lock."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Generic, TypeVar

K = TypeVar("K")
V = TypeVar("V")

MISSING: object = object()
"""What :meth:`LRU.get` returns for a key it does not hold (a cached value may be None)."""


class LRU(Generic[K, V]):
    """At most ``size`` entries; a hit makes its entry the newest, a put past ``size`` drops
    the oldest."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"an LRU holds at least 1 entry, got {size}")
        self.size = size
        self._entries: OrderedDict[K, V] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: K) -> V | object:
        """The value of ``key`` (now the newest entry), or :data:`MISSING`."""
        with self._lock:
            value = self._entries.get(key, MISSING)
            if value is not MISSING:
                self._entries.move_to_end(key)
            return value

    def put(self, key: K, value: V) -> None:
        with self._lock:
            self._entries[key] = value
            self._entries.move_to_end(key)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
