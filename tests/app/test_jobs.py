"""The background evaluation job agrees with ``evaluate_frame``; cancel, failure, compare."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import pytest

from threadrecon.app import jobs as app_jobs
from threadrecon.app.dataset import Frame, discover
from threadrecon.app.evaluation import evaluate_frame, summarise
from threadrecon.app.jobs import COMPARE_COLUMNS, EvaluationJob, compare
from threadrecon.core.pipeline import ReconParams

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"
TIMEOUT_S = 60.0  # generous: the machine is shared; a few frames take well under a second


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    all_frames = discover(SAMPLE)
    by_group = {f.id.rsplit("/", 1)[0]: f for f in reversed(all_frames)}  # first of each
    return sorted(by_group.values(), key=lambda f: f.id)


def _same_value(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    return type(a) is type(b) and a == b


def _assert_rows_equal(got: list[dict[str, Any]], expected: list[dict[str, Any]]) -> None:
    """Equal keys and values, timings (``ms_*``: wall time) excepted."""
    assert len(got) == len(expected)
    for g, e in zip(got, expected, strict=True):
        assert list(g) == list(e)
        for k in e:
            if not k.startswith("ms_"):
                assert _same_value(g[k], e[k]), f"{e['frame']} {k}: {g[k]!r} != {e[k]!r}"


def test_job_rows_equal_evaluate_frame_rows(frames: list[Frame]) -> None:
    assert len(frames) == 4  # one per sample group: crossing, flat, raw, tissue
    params = ReconParams()
    calls: list[EvaluationJob] = []
    job = EvaluationJob(frames, params, "default", on_done=calls.append)
    assert job.state == "pending" and job.done == 0 and job.total == 4
    job.start()
    assert job.wait(TIMEOUT_S)
    expected = [evaluate_frame(f, params)[0] for f in frames]
    assert job.state == "done" and job.done == job.total == 4 and job.error is None
    _assert_rows_equal(job.rows, expected)
    assert job.summary == summarise(expected)
    assert any(not math.isnan(r["e_S_mm"]) for r in job.rows)
    assert calls == [job]
    assert job.started_at is not None and job.finished_at is not None
    assert job.current is None
    with pytest.raises(RuntimeError, match="already started"):
        job.start()


def test_snapshot_is_strict_json_and_pages_rows(frames: list[Frame]) -> None:
    job = EvaluationJob(frames[:2], ReconParams(), "default").start()
    assert job.wait(TIMEOUT_S)
    snap = job.snapshot()
    json.dumps(snap, allow_nan=False)
    assert snap["state"] == "done" and snap["done"] == snap["total"] == 2
    assert [r["frame"] for r in snap["rows"]] == [f.id for f in frames[:2]]
    assert snap["summary"] == job.summary and snap["elapsed_s"] > 0
    assert [r["frame"] for r in job.snapshot(since=1)["rows"]] == [frames[1].id]
    assert job.snapshot(since=5)["rows"] == []


def test_unreadable_frame_gives_failed_row_and_null_metrics(
    frames: list[Frame], tmp_path: Path
) -> None:
    missing = Frame(
        id="simulated/flat/missing",
        kind="simulated",
        calibration=frames[0].calibration,
        stereo=tmp_path / "missing.png",
    )
    job = EvaluationJob([missing, frames[0]], ReconParams(), "p").start()
    assert job.wait(TIMEOUT_S)
    _assert_rows_equal(job.rows, [evaluate_frame(f, ReconParams())[0] for f in job.frames])
    bad = job.rows[0]
    assert job.state == "done" and bad["status"] == "failed" and "missing.png" in bad["error"]
    assert math.isnan(bad["e_S_mm"])
    snap = job.snapshot()
    json.dumps(snap, allow_nan=False)
    assert snap["rows"][0]["e_S_mm"] is None and snap["rows"][1]["e_S_mm"] is not None
    assert any(line.startswith("FAILED simulated/flat/missing") for line in snap["summary"])


def test_cancel_after_first_frame_stops_early(frames: list[Frame]) -> None:
    done_calls: list[str] = []
    job = EvaluationJob(
        frames,
        ReconParams(),
        "default",
        on_done=lambda j: done_calls.append(j.state),
        on_frame=lambda j, row: j.cancel(),
    ).start()
    assert job.wait(TIMEOUT_S)
    assert job.state == "cancelled" and job.done == 1 and job.total == len(frames)
    assert [r["frame"] for r in job.rows] == [frames[0].id]
    assert job.summary == summarise(job.rows)
    assert done_calls == ["cancelled"]


def test_cancel_before_start_evaluates_nothing(frames: list[Frame]) -> None:
    calls: list[EvaluationJob] = []
    job = EvaluationJob(frames, ReconParams(), "default", on_done=calls.append)
    job.cancel()
    job.start()
    assert job.wait(TIMEOUT_S)
    assert job.state == "cancelled" and job.rows == [] and calls == [job]


def test_unexpected_error_fails_the_job_and_keeps_rows(
    frames: list[Frame], monkeypatch: pytest.MonkeyPatch
) -> None:
    real = app_jobs.evaluate_frame

    def flaky(frame: Frame, params: ReconParams) -> Any:
        if frame.id == frames[1].id:
            raise RuntimeError("disk on fire")
        return real(frame, params)

    monkeypatch.setattr(app_jobs, "evaluate_frame", flaky)
    states: list[str] = []
    job = EvaluationJob(frames, ReconParams(), "p", on_done=lambda j: states.append(j.state))
    job.start()
    assert job.wait(TIMEOUT_S)
    assert job.state == "failed" and states == ["failed"]
    assert job.error == f"{frames[1].id}: RuntimeError: disk on fire"
    assert [r["frame"] for r in job.rows] == [frames[0].id]


def test_failing_on_done_is_recorded_not_raised(frames: list[Frame]) -> None:
    def boom(job: EvaluationJob) -> None:
        raise OSError("database gone")

    job = EvaluationJob([], ReconParams(), "p", on_done=boom).start()
    assert job.wait(TIMEOUT_S)
    assert job.state == "done" and job.on_done_error == "OSError: database gone"


def _row(frame: str, status: str = "ok", **metrics: float) -> dict[str, Any]:
    return {"frame": frame, "kind": "simulated", "status": status, **metrics}


def test_compare_pairs_frames_and_means_where_both_are_finite() -> None:
    a = [
        _row("f1", e_S_mm=1.0, length_mm=10.0),
        _row("f2", e_S_mm=2.0, length_mm=math.nan),
        _row("only_a", e_S_mm=9.0),
    ]
    b = [
        _row("f2", "failed", e_S_mm=5.0, length_mm=12.0),
        _row("f1", e_S_mm=1.5, length_mm=11.0),
        _row("only_b", e_S_mm=0.0),
    ]
    out = compare(a, b)
    assert [r["frame"] for r in out] == ["f1", "f2", "mean"]
    f1, f2, mean = out
    assert (f1["e_S_mm_a"], f1["e_S_mm_b"], f1["e_S_mm_diff"]) == (1.0, 1.5, 0.5)
    assert f2["status_b"] == "failed" and math.isnan(f2["length_mm_diff"])
    assert (mean["e_S_mm_a"], mean["e_S_mm_b"], mean["e_S_mm_diff"]) == (1.5, 3.25, 1.75)
    assert (mean["length_mm_a"], mean["length_mm_b"]) == (10.0, 11.0)  # f2 has no a value
    assert math.isnan(mean["right_max_px_a"]) and math.isnan(mean["right_max_px_diff"])
    assert (mean["status_a"], mean["status_b"]) == ("2/2 ok", "1/2 ok")
    assert all(set(r) == set(out[0]) for r in out)
    assert {f"{c}_diff" for c in COMPARE_COLUMNS} <= set(mean)


def test_compare_of_a_run_with_itself_has_zero_differences(frames: list[Frame]) -> None:
    rows = [evaluate_frame(f, ReconParams())[0] for f in frames[:2]]
    out = compare(rows, rows)
    assert len(out) == 3
    for r in out:
        for c in COMPARE_COLUMNS:
            if math.isfinite(r[f"{c}_a"]):
                assert r[f"{c}_diff"] == 0.0
    assert out[-1]["e_S_mm_a"] == pytest.approx(sum(r["e_S_mm"] for r in rows) / 2)


def test_a_poll_that_sees_a_final_state_sees_what_on_done_stored() -> None:
    stored: list[str] = []

    def slow_store(job: EvaluationJob) -> None:
        time.sleep(0.2)  # a slow database write
        stored.append(job.state)

    job = EvaluationJob([], ReconParams(), "p", on_done=slow_store).start()
    deadline = time.monotonic() + TIMEOUT_S
    while job.snapshot()["state"] == "running" and time.monotonic() < deadline:
        time.sleep(0.001)
    assert job.snapshot()["state"] == "done"
    assert stored == ["done"]
