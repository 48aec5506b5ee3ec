"""Session logic without HTTP: the worker, waiting, closing, expiry."""

from __future__ import annotations

import asyncio
import math
import threading
import time
from pathlib import Path

import pytest

from threadrecon.app.errors import Invalid, NotFound
from threadrecon.app.library import FrameLibrary, merge_params
from threadrecon.app.sessions import SessionManager
from threadrecon.core import pipeline
from threadrecon.core.pipeline import ReconParams

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"
FLAT = "simulated/flat/flat_1"


@pytest.fixture(scope="module")
def library() -> FrameLibrary:
    return FrameLibrary(SAMPLE)


def test_an_exception_in_a_stage_fails_that_stage_and_the_worker_goes_on(library, monkeypatch):
    original = pipeline.Pipeline.stages

    def broken(self, params, until=None):
        for run in original(self, params, until):
            yield run
            if run.stage == "stereo":
                raise MemoryError("no room")

    manager = SessionManager(library)
    s = manager.create()
    monkeypatch.setattr(pipeline.Pipeline, "stages", broken)
    assert s.wait(s.submit(frame_id=FLAT), 120)
    st = s.state()
    assert st["failed_stage"] == "reliability" and "MemoryError: no room" in st["error"]
    assert not st["busy"]
    monkeypatch.setattr(pipeline.Pipeline, "stages", original)
    assert s.wait(s.submit(params=ReconParams()), 120)
    assert s.state()["status"] == "ok"
    manager.close()


@pytest.mark.parametrize("pause", [1e10, -1.0, math.nan, math.inf])
def test_a_pause_outside_its_range_is_refused(library, pause):
    s = SessionManager(library).create()
    with pytest.raises(Invalid, match="pause"):
        s.submit(frame_id=FLAT, pause_s=pause)


def test_huge_or_non_finite_parameters_are_invalid_not_overflow():
    for patch in ({"spline.n_ctrl": 10**400}, {"stereo": {"alpha": math.inf}}, {"nope.x": 1}):
        with pytest.raises(Invalid):
            merge_params(ReconParams(), patch)


def test_waiting_in_the_event_loop_holds_no_thread_and_wakes_on_a_change(library):
    s = SessionManager(library).create()
    assert s.wait(s.submit(frame_id=FLAT), 120)

    async def scenario() -> tuple[bool, bool, int, float]:
        threads = threading.active_count()
        v = s.version
        waits = [asyncio.create_task(s.changed(v, 30)) for _ in range(50)]
        await asyncio.sleep(0.2)
        during = threading.active_count() - threads  # no thread per waiter
        t0 = time.perf_counter()
        s.set_inspect(None)  # any change wakes every waiter
        woke = all(await asyncio.gather(*waits))
        elapsed = time.perf_counter() - t0
        timed_out = await s.changed(s.version, 0.05)
        return woke, timed_out, during, elapsed

    woke, timed_out, during, elapsed = asyncio.run(scenario())
    assert woke and not timed_out and during == 0 and elapsed < 1.0


def test_closing_a_session_frees_its_results_and_stops_its_worker(library):
    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=FLAT), 120)
    worker = s._worker
    assert s.rec is not None and worker is not None and worker.is_alive()
    manager.delete(s.id)
    worker.join(5)
    assert not worker.is_alive() and s.rec is None and s.loaded is None
    with pytest.raises(NotFound):
        manager.get(s.id)


def test_idle_sessions_expire_but_ones_with_a_view_stay(library):
    manager = SessionManager(library, idle_timeout_s=0.1)
    idle, viewed = manager.create(), manager.create()
    viewed.views[1] = object()  # a 3D view attached
    time.sleep(0.2)
    assert manager.expire() == [idle.id]
    assert manager.find(viewed.id) is viewed and manager.find(idle.id) is None


def test_a_session_whose_run_outlasts_the_idle_timeout_is_not_expired(library):
    """A run longer than the idle timeout (a first run that compiles the kernels, a slow
    machine) keeps its session: the request waiting for it gets its answer, and the idle time
    counts from the run's end."""
    manager = SessionManager(library, idle_timeout_s=0.2)
    s = manager.create()
    seq = s.submit(frame_id=FLAT, pause_s=0.1)  # ten stages, 0.1 s apart: ~1 s of run
    t0 = time.monotonic()
    while s.busy and time.monotonic() - t0 < 60:
        assert manager.expire() == []
        time.sleep(0.05)
    assert time.monotonic() - t0 > 0.4 and s.wait(seq, 5) and s.rec is not None
    assert manager.expire() == [] and manager.find(s.id) is s  # idle from the run's end
    time.sleep(0.3)
    assert manager.expire() == [s.id]


def test_the_number_of_sessions_is_bounded(library):
    manager = SessionManager(library, max_sessions=5)
    for _ in range(12):
        manager.create()
    assert len(manager) == 5


def _record_publishes(monkeypatch) -> list[tuple[str, ...]]:
    """The stages of each result a session publishes to its views, in order."""
    from threadrecon.app.session import Session

    shown: list[tuple[str, ...]] = []
    original = Session._publish
    monkeypatch.setattr(
        Session,
        "_publish",
        lambda self, rec, loaded: (shown.append(tuple(rec.runs)), original(self, rec, loaded)),
    )
    return shown


@pytest.mark.parametrize("progress_after_s", [1e9, 0.0])
def test_a_slider_publishes_only_the_stages_it_recomputes(library, monkeypatch, progress_after_s):
    """A quick run shows its result once; a slow one each computed stage as it comes (the
    cached stages before the first computed one are shown with it)."""
    from threadrecon.app import session as session_module

    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=FLAT), 120)
    shown = _record_publishes(monkeypatch)
    monkeypatch.setattr(session_module, "PROGRESS_AFTER_S", progress_after_s)
    params = merge_params(s.params, {"spline": {"n_ctrl": s.params.spline.n_ctrl + 1}})
    assert s.wait(s.submit(params=params), 120)
    assert shown[-1] == pipeline.STAGES
    latency = s.state()["latency_ms"]  # request -> each stage done, and -> the last one shown
    assert latency["check"] <= latency["shown"]
    if progress_after_s:
        assert len(shown) == 1
    else:
        first = shown[0]
        assert first[-1] == "spline" and len(first) == pipeline.STAGES.index("spline") + 1
        assert [r[-1] for r in shown] == ["spline", "refine", "camera", "check"]
    timing = s.state()["timing"]
    assert timing["compute_ms"] > 0 and timing["publish_ms"] > 0
    assert timing["compute_cpu_ms"] <= timing["compute_ms"] * 1.5 + 5
    manager.close()


def test_a_run_that_fails_at_a_stage_is_shown_up_to_that_stage(library, monkeypatch):

    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=FLAT), 120)
    shown = _record_publishes(monkeypatch)
    original_stages = pipeline.Pipeline.stages

    def failing(self, params, until=None):
        for run in original_stages(self, params, until):
            if run.stage == "spline":
                raise pipeline.StageError("spline", "no curve through these bounds")
            yield run

    monkeypatch.setattr(pipeline.Pipeline, "stages", failing)
    params = merge_params(s.params, {"spline": {"n_ctrl": s.params.spline.n_ctrl + 1}})
    assert s.wait(s.submit(params=params), 120)
    st = s.state()
    assert st["failed_stage"] == "spline" and "no curve" in st["error"]
    assert shown == [pipeline.STAGES[: pipeline.STAGES.index("spline")]]
    manager.close()


def test_a_dragged_slider_shows_its_values_in_order_and_ends_on_the_last(library, monkeypatch):
    """Latest wins: moves that come faster than the runs are dropped, never queued, and an
    older value is never shown after a newer one."""
    from threadrecon.app.session import Session

    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=FLAT), 120)
    shown: list[int] = []
    original = Session._publish
    monkeypatch.setattr(
        Session,
        "_publish",
        lambda self, rec, loaded: (
            shown.append(rec.params.spline.n_ctrl),
            original(self, rec, loaded),
        ),
    )
    values = list(range(8, 20))
    for n in values:
        seq = s.submit(params=merge_params(s.params, {"spline": {"n_ctrl": n}}))
    assert s.wait(seq, 120)
    assert shown[-1] == values[-1] and shown == sorted(shown)
    assert len(shown) <= len(values)
    assert s.state()["params"]["spline"]["n_ctrl"] == values[-1] and not s.busy
    manager.close()


def test_the_end_of_a_run_is_a_new_version(library, monkeypatch):
    """A long poll answers a version; the state of a run that has ended (not busy) must be a
    newer version than any state seen while it was running, or a page that saw the last one
    busy would wait for news forever."""
    from threadrecon.app.session import Session

    manager = SessionManager(library)
    s = manager.create()
    seen: list[tuple[int, bool]] = []
    original = Session._bump
    monkeypatch.setattr(
        Session, "_bump", lambda self: (original(self), seen.append((self.version, self.busy)))
    )
    assert s.wait(s.submit(frame_id=FLAT), 120)
    params = merge_params(s.params, {"spline": {"n_ctrl": s.params.spline.n_ctrl + 1}})
    assert s.wait(s.submit(params=params), 120)
    final = s.state()
    assert not final["busy"] and seen
    assert all(version < final["version"] for version, busy in seen if busy)
    manager.close()


def test_a_slow_run_shows_its_progress_at_a_pace_not_every_stage(library, monkeypatch):
    """A run that takes long shows the stages it has computed once ``PROGRESS_AFTER_S`` has
    passed, then at most once per ``PROGRESS_AFTER_S``: a move that is just slow does not
    draw each of its intermediate 3D layers before its final state."""
    from threadrecon.app import session as session_module
    from threadrecon.app.session import Session

    pace, stage_s = 0.15, 0.05
    original_stages = pipeline.Pipeline.stages

    def slow(self, params, until=None):
        for run in original_stages(self, params, until):
            time.sleep(stage_s)
            yield run

    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=FLAT), 120)
    monkeypatch.setattr(pipeline.Pipeline, "stages", slow)
    monkeypatch.setattr(session_module, "PROGRESS_AFTER_S", pace)
    shown: list[tuple[float, tuple[str, ...]]] = []
    original = Session._publish
    monkeypatch.setattr(
        Session,
        "_publish",
        lambda self, rec, loaded: (
            shown.append((time.perf_counter(), tuple(rec.runs))),
            original(self, rec, loaded),
        ),
    )
    params = merge_params(s.params, {"segment": {"min_component_px": 5}})  # every stage
    t0 = time.perf_counter()
    assert s.wait(s.submit(params=params), 120)
    assert shown[-1][1] == pipeline.STAGES  # the final layers, always
    progress = [t for t, runs in shown[:-1]]
    assert progress, "a run of ~0.4 s shows some progress"
    assert len(progress) < len(pipeline.STAGES) - 2
    starts = [t0, *progress]
    assert all(b - a >= pace * 0.99 for a, b in zip(starts, starts[1:], strict=False))
    manager.close()


def test_a_waiting_page_has_the_final_state_before_the_views_draw_the_last_layers(
    library, monkeypatch
):
    """With a page's long poll waiting, the run's final state (results, metrics, not busy) is
    answered before the views draw its last layers; drawing them makes no new version, and
    :meth:`Session.wait` returns once they are drawn."""
    from threadrecon.app import session as session_module
    from threadrecon.app.session import Session

    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=FLAT), 120)
    monkeypatch.setattr(session_module, "PROGRESS_AFTER_S", 1e9)  # one publish: the last
    events: list[tuple] = []
    original = Session._publish
    monkeypatch.setattr(
        Session,
        "_publish",
        lambda self, rec, loaded: (
            events.append(("drawn", self.version, tuple(rec.runs))),
            original(self, rec, loaded),
        ),
    )
    params = merge_params(s.params, {"spline": {"n_ctrl": s.params.spline.n_ctrl + 1}})
    with s.polling() as answered:  # what the page's long poll does
        seq = s.submit(params=params)
        deadline = time.monotonic() + 120
        while s.busy and time.monotonic() < deadline:
            time.sleep(0.002)
        st = s.state()
        time.sleep(0.1)  # building the answer takes a while: the views wait for it
        events.append(("answered", st["version"], st["busy"], bool(st["metrics"])))
        answered(st["version"])
    assert s.wait(seq, 120)
    assert [e[0] for e in events] == ["answered", "drawn"]
    _, version, busy, has_metrics = events[0]
    assert not busy and has_metrics and st["stages"][-1]["status"] == "done"
    assert events[1] == ("drawn", version, pipeline.STAGES) and s.version == version
    latency = s.state()["latency_ms"]  # final state, answered, last layers drawn: in order
    assert latency["check"] <= latency["final"] <= latency["answered"] <= latency["shown"]
    manager.close()


def test_the_views_draw_anyway_when_a_waiting_page_does_not_answer(library, monkeypatch):
    from threadrecon.app import session as session_module

    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=FLAT), 120)
    monkeypatch.setattr(session_module, "ANSWER_FIRST_S", 0.2)
    params = merge_params(s.params, {"spline": {"n_ctrl": s.params.spline.n_ctrl + 1}})
    with s.polling():  # a poll that never answers
        t0 = time.perf_counter()
        assert s.wait(s.submit(params=params), 120)
        waited = time.perf_counter() - t0
    assert 0.2 <= waited < 60 and not s.busy
    manager.close()


def test_the_state_is_read_while_the_views_draw(library):
    manager = SessionManager(library)
    s = manager.create()
    assert s.wait(s.submit(frame_id=FLAT), 120)
    got: list[dict] = []
    with s.draw_lock:  # a view drawing
        reader = threading.Thread(target=lambda: got.append(s.state()))
        reader.start()
        reader.join(10)
    assert got and got[0]["status"] == "ok"
    manager.close()
