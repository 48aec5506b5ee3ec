"""The process's heap: full garbage collections skip what is settled; freed pages go back."""

from __future__ import annotations

import gc
import weakref
from pathlib import Path

import pytest

from threadrecon.app import heap
from threadrecon.app.library import FrameLibrary, merge_params
from threadrecon.app.sessions import SessionManager

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"


@pytest.fixture
def unsettled(monkeypatch):
    monkeypatch.setattr(heap, "_settled", False)
    gc.unfreeze()
    yield
    gc.unfreeze()


def test_settling_freezes_what_is_alive_and_leaves_what_comes_after_to_the_collector(unsettled):
    heap.settle()
    frozen = gc.get_freeze_count()
    assert frozen > 1000  # at least the imports
    later = [[] for _ in range(20_000)]
    assert gc.get_freeze_count() == frozen
    assert len(gc.get_objects()) >= len(later)  # what a full collection still scans


def test_a_process_that_never_settled_is_left_as_it_is(unsettled):
    junk = [[] for _ in range(2000)]
    assert not heap.settle_if_grown(limit=100) and gc.get_freeze_count() == 0 and junk


def test_a_settled_process_settles_again_once_enough_is_left_to_scan(unsettled):
    heap.settle()
    assert not heap.settle_if_grown(limit=10**9)
    junk = [[] for _ in range(2000)]
    before = gc.get_freeze_count()
    assert heap.settle_if_grown(limit=100) and gc.get_freeze_count() >= before + 2000 and junk


def test_a_new_frames_run_may_settle_the_heap_a_slider_move_does_not(monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(heap, "settle_if_grown", lambda: calls.append(1))
    library = FrameLibrary(SAMPLE)
    frames = list(library.frames)[:2]
    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=frames[0]), 120)
    assert len(calls) == 1
    params = merge_params(s.params, {"spline": {"n_ctrl": s.params.spline.n_ctrl + 1}})
    assert s.wait(s.submit(params=params), 120)
    assert len(calls) == 1
    assert s.wait(s.submit(frame_id=frames[1]), 120)
    assert len(calls) == 2
    manager.close()


def _resident_mb() -> float:
    return int(Path("/proc/self/statm").read_text().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(heap._TRIM is None, reason="not glibc: no malloc_trim")
def test_trim_hands_freed_heap_pages_back():
    """Freed small blocks stay in glibc's heap (the RSS keeps them) until trimmed; one block
    kept at the top stops glibc's own trimming of the top of the heap."""
    blocks = [bytearray(8192) for _ in range(12_000)]  # ~96 MB below the mmap threshold
    keep = bytearray(8192)
    del blocks
    before = _resident_mb()
    heap.trim()
    assert _resident_mb() < before - 50
    assert len(keep) == 8192


def test_release_memory_collects_unreachable_cycles():
    class Node:
        pass

    a, b = Node(), Node()
    a.other, b.other = b, a
    ref = weakref.ref(a)
    del a, b
    heap.release_memory()
    assert ref() is None
