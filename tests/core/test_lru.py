"""The core's small LRU map: a hit makes its entry the newest, a put past the size drops the
oldest, a cached None is a hit, a size under 1 is refused."""

from __future__ import annotations

import pytest

from threadrecon.core.lru import LRU, MISSING


def test_the_oldest_unused_entry_goes_first() -> None:
    lru: LRU[str, int] = LRU(2)
    lru.put("a", 1)
    lru.put("b", 2)
    assert lru.get("a") == 1  # "a" is now the newest
    lru.put("c", 3)
    assert lru.get("b") is MISSING and lru.get("a") == 1 and lru.get("c") == 3
    assert len(lru) == 2


def test_a_cached_none_is_a_hit_and_clear_forgets() -> None:
    lru: LRU[str, None] = LRU(1)
    assert lru.get("x") is MISSING
    lru.put("x", None)
    assert lru.get("x") is None
    lru.clear()
    assert lru.get("x") is MISSING and len(lru) == 0


def test_a_size_under_one_is_refused() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        LRU(0)


def test_cached_values_live_with_their_owners_and_a_reused_id_never_hits() -> None:
    import gc

    import numpy as np

    cache: LRU[tuple, object] = LRU(4)
    calls: list[int] = []
    a = np.zeros(3)
    first = cache.cached((a,), ("k",), lambda: calls.append(1) or "value of a")
    assert cache.cached((a,), ("k",), lambda: calls.append(1) or "again") == first
    assert calls == [1]  # the second call hit
    assert cache.cached((a,), ("other",), lambda: "other key") == "other key"
    a_id = id(a)
    del a
    gc.collect()
    b = None
    for _ in range(1000):  # an array at the freed id: the weak reference tells it apart
        b = np.zeros(3)
        if id(b) == a_id:
            break
    if b is not None and id(b) == a_id:
        assert cache.cached((b,), ("k",), lambda: "value of b") == "value of b"


def test_a_cached_value_hits_only_when_every_owner_is_the_same_object() -> None:
    import weakref

    import numpy as np

    cache: LRU[tuple, object] = LRU(4)
    a, b, c = np.zeros(1), np.zeros(1), np.zeros(1)
    # an entry under a and b's ids whose second owner is another object (an id reused)
    cache.put(("k", id(a), id(b)), ((weakref.ref(a), weakref.ref(c)), "stale"))
    assert cache.cached((a, b), ("k",), lambda: "fresh") == "fresh"
    assert cache.cached((a, b), ("k",), lambda: "again") == "fresh"  # now a hit
    cache.put(("j", id(a), id(b)), ((weakref.ref(c), weakref.ref(b)), "stale"))
    assert cache.cached((a, b), ("j",), lambda: "fresh j") == "fresh j"
