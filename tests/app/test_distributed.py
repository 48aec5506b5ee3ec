"""Frames on Dask (app/distributed.py): the chunks of a map cover every frame once, a worker's
frame cache hands out read-only frames and reloads a rewritten file, and a stop asked from
the progress callback ends a tune with its finished trials kept."""

from __future__ import annotations

import os
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from threadrecon.app import distributed
from threadrecon.app.dataset import discover
from threadrecon.app.distributed import _chunks, cached_frame, evaluate_rows
from threadrecon.app.evaluation import evaluate_frame
from threadrecon.app.tune import TuneConfig, parse_space, tune
from threadrecon.core.corrections import Correction

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"


@pytest.mark.parametrize("workers", [1, 2, 3, 8])
def test_chunks_cover_every_frame_exactly_once(workers: int) -> None:
    for n in (0, 1, 2, 7, 30, 121):
        chunks = _chunks(n, workers)
        flat = sorted(i for c in chunks for i in c)
        assert flat == list(range(n))
        assert len(chunks) <= max(1, distributed.TASKS_PER_WORKER * workers)
        sizes = [len(c) for c in chunks if c]
        assert not sizes or max(sizes) - min(sizes) <= 1  # balanced


def test_cached_frames_are_read_only_and_follow_a_rewritten_file(tmp_path: Path) -> None:
    shutil.copytree(SAMPLE / "simulated" / "flat", tmp_path / "simulated" / "flat")
    frame = next(f for f in discover(tmp_path) if f.id.endswith("flat_1"))
    pair, _, gt = cached_frame(frame)
    assert cached_frame(frame)[0] is pair  # a hit: the same object
    corrected = replace(frame, corrections=(Correction("erase", "left", ((5, 5),)),))
    assert cached_frame(corrected)[0] is pair  # corrections apply after loading: a hit too
    with pytest.raises(ValueError, match="read-only"):
        pair.left[0, 0] = 0
    assert gt is not None and not gt.flags.writeable
    # a rewritten image (new modification time) is loaded again
    path = frame.stereo or frame.left
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), 255 - img)
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    again, _, _ = cached_frame(frame)
    assert again is not pair
    assert not np.array_equal(again.left, pair.left)


def test_cached_rows_equal_uncached_rows() -> None:
    frames = discover(SAMPLE)[:6]
    params = TuneConfig(dataset=str(SAMPLE), space=parse_space({"stereo": {"window": [7]}})).base
    for _ in range(2):  # the second pass reads every frame from the cache
        rows = evaluate_rows(None, frames, params)
        plain = [evaluate_frame(f, params)[0] for f in frames]
        strip = lambda rs: [  # noqa: E731
            {k: str(v) for k, v in r.items() if not k.startswith("ms_")} for r in rs
        ]
        assert strip(rows) == strip(plain)


def test_a_stopped_tune_keeps_its_finished_trials_and_resumes(tmp_path: Path) -> None:
    data = tmp_path / "data"
    shutil.copytree(SAMPLE / "simulated" / "flat", data / "simulated" / "flat")
    cfg = TuneConfig(
        dataset=str(data),
        space=parse_space({"spline": {"n_ctrl": [10, 12, 14, 16]}}),
        mode="grid",
        prune=False,
    )
    finished: list[int] = []
    got = tune(
        cfg,
        tmp_path / "store",
        log=lambda _: None,
        on_trial=lambda t: finished.append(t.number),
        stop=lambda: len(finished) >= 2,
    )
    assert got.stopped and [t.number for t in got.trials] == [0, 1]
    again = tune(cfg, tmp_path / "store", log=lambda _: None)
    assert not again.stopped
    values = sorted(t.values["spline.n_ctrl"] for t in again.trials if t.state == "COMPLETE")
    assert values == [10, 12, 14, 16]


def test_a_tune_stopped_inside_a_trial_runs_that_trial_again_on_resume(tmp_path: Path) -> None:
    data = tmp_path / "data"
    shutil.copytree(SAMPLE / "simulated" / "flat", data / "simulated" / "flat")
    cfg = TuneConfig(
        dataset=str(data),
        space=parse_space({"spline": {"n_ctrl": [10, 12, 14]}}),
        mode="grid",
        prune=False,
    )
    frames: list[str] = []

    def stop() -> bool:  # asked before each frame: stop at the 2nd frame of the 2nd trial
        return len(frames) >= 6

    got = tune(
        cfg,
        tmp_path / "store",
        log=lambda _: None,
        progress=lambda done, n, fid: frames.append(fid),
        stop=stop,
    )
    assert got.stopped and [t.number for t in got.trials] == [0]
    again = tune(cfg, tmp_path / "store", log=lambda _: None)
    done = [t for t in again.trials if t.state == "COMPLETE"]
    assert sorted(t.values["spline.n_ctrl"] for t in done) == [10, 12, 14]
    assert all(len(t.rows) == 4 for t in done)
