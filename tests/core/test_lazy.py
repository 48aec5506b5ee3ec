"""core/lazy.py: result fields computed on their first read."""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest
from support import synthetic_case

from threadrecon.core.lazy import Deferred, LazyField
from threadrecon.core.ordering import OrderingGraph
from threadrecon.core.pipeline import reconstruct


@dataclasses.dataclass(frozen=True)
class _Result:
    a: int
    b: np.ndarray = LazyField()  # type: ignore[assignment]  # no default
    c: np.ndarray | None = LazyField(None)  # type: ignore[assignment]


def test_a_deferred_field_is_computed_once_on_first_read() -> None:
    calls = []

    def make(n: int) -> np.ndarray:
        calls.append(n)
        return np.arange(n)

    r = _Result(1, Deferred(make, 3))
    assert calls == [] and r.c is None
    assert np.array_equal(r.b, [0, 1, 2]) and r.b is r.b and calls == [3]
    assert [f.name for f in dataclasses.fields(_Result)] == ["a", "b", "c"]
    copied = dataclasses.replace(r, a=2)
    assert copied.b is r.b and calls == [3]
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.b = np.zeros(2)  # type: ignore[misc]
    with pytest.raises(TypeError, match="'b'"):
        _Result(1)  # type: ignore[call-arg]  # a LazyField without a default is required
    assert _Result(1, np.ones(2), c=np.zeros(1)).c.tolist() == [0.0]  # plain values too


def test_threads_reading_a_deferred_field_at_once_compute_it_once() -> None:
    calls = []

    def slow(n: int) -> np.ndarray:
        calls.append(n)
        time.sleep(0.05)  # long enough for every reader to arrive while it computes
        return np.arange(n)

    r = _Result(1, Deferred(slow, 4))
    start = threading.Barrier(4)
    got: list[np.ndarray] = []

    def read() -> None:
        start.wait()
        got.append(r.b)

    threads = [threading.Thread(target=read) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert calls == [4] and len(got) == 4 and all(g is got[0] for g in got)


def test_the_ordering_graph_is_built_when_read_and_is_the_walks() -> None:
    pair, calib, _ = synthetic_case(0)
    rec = reconstruct(pair, calib)
    od = rec["ordering"]
    assert type(od.__dict__["_lazy_graph"]).__name__ == "Deferred"  # the pipeline did not read it
    graph = od.graph
    assert isinstance(graph, OrderingGraph) and graph is od.graph
    assert sorted(k for piece in graph.pieces for k in piece) == list(range(od.n_clusters))
    assert isinstance(graph.decisions, tuple) and graph.junctions.dtype == np.int64


def test_results_with_deferred_fields_pickle_before_and_after_the_read() -> None:
    import pickle

    pair, calib, _ = synthetic_case(0)
    rec = reconstruct(pair, calib)
    for name, field in (("segment", "score_L"), ("ordering", "graph")):
        result = rec[name]
        assert type(result.__dict__["_lazy_" + field]).__name__ == "Deferred"
        before = pickle.loads(pickle.dumps(result))  # still deferred: its inputs travel
        value = getattr(result, field)
        after = pickle.loads(pickle.dumps(result))
        for copy in (before, after):
            got = getattr(copy, field)
            if isinstance(value, np.ndarray):
                assert np.array_equal(got, value)
            else:
                assert got.pieces == value.pieces and got.decisions == value.decisions
