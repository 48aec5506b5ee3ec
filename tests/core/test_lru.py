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
