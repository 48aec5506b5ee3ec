"""A small thread-safe least-recently-used map: the caches of derived data in the core (mask
skeletons and indexes, rectification maps, distance fields) all keep a few entries this way.
The server's sessions run pipelines in several threads, so every access takes the lock."""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Generic, TypeVar

K = TypeVar("K")
V = TypeVar("V")
T = TypeVar("T")

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

    def cached(self, owners: tuple[Any, ...], key: tuple, compute: Callable[[], T]) -> T:
        """``compute()``, kept under ``key`` while the objects ``owners`` (arrays, a Bounds)
        live: the entry holds weak references to them, so that an object freed and another
        allocated at its id never hits. Values derived from one stage's result and re-read
        when a later stage re-runs (a slider move)."""
        full = (*key, *map(id, owners))
        hit: Any = self.get(full)  # type: ignore[arg-type]
        if hit is not MISSING:  # (a loop: all() over a generator costs as much as the lookup)
            for ref, owner in zip(hit[0], owners, strict=True):
                if ref() is not owner:
                    break
            else:
                return hit[1]
        value = compute()
        self.put(full, (tuple(weakref.ref(o) for o in owners), value))  # type: ignore[arg-type]
        return value

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
