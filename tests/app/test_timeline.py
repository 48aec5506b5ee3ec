"""Sequences in the debugger: one entry of the frame list per sequence (app/sequence_library.py,
FrameLibrary), the background timeline (app/timeline.py) and its API (routes_sequences)."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from threadrecon.app import timeline as timeline_mod
from threadrecon.app import track_report
from threadrecon.app.cli import main
from threadrecon.app.dataset import discover
from threadrecon.app.errors import NotFound
from threadrecon.app.library import FrameLibrary
from threadrecon.app.sequence import write_video
from threadrecon.app.sequence_library import find_sequences, split_frame_id
from threadrecon.app.server import ServerConfig, create_app
from threadrecon.app.timeline import Timeline, Timelines
from threadrecon.core.pipeline import ReconParams
from threadrecon.core.tracking import TrackParams

N_FRAMES = 4


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """A still frame, a generated sequence (with its video inside its folder) and a video."""
    root = tmp_path_factory.mktemp("data")
    assert main(["generate", str(root), "--count", "1", "--seed", "3"]) == 0
    assert main(["generate", str(root), "--sequence", str(N_FRAMES), "--seed", "31",
                 "--speed-mm", "2.0"]) == 0  # fmt: skip
    clips = root / "clips"
    clips.mkdir()
    frames = (np.full((48, 64, 3), 40 * k, np.uint8) for k in range(3))
    assert write_video(clips / "take.mp4", frames) == 3
    return root


def wait_done(tl: Timeline, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not tl.done:
        assert time.monotonic() < deadline, "timeline did not finish"
        time.sleep(0.05)


def test_a_sequence_is_one_entry_and_its_frames_are_not_still_frames(data):
    entries = find_sequences(data)
    assert [(e.id, e.kind) for e in entries] == [
        ("clips/take.mp4", "video"),
        ("sequences/drag", "images"),  # its own drag.mp4 is not a second entry
    ]
    assert entries[1].calibration == data / "sequences/drag/calibration.yaml"
    assert entries[0].calibration is None  # no calibration.yaml above the video
    stills = [f.id for f in discover(data, skip=[entries[1].path])]
    assert stills == ["simulated/flat/flat_1"]
    assert len(discover(data)) == 1 + N_FRAMES  # evaluate still sees every pair


def test_frame_ids_of_a_sequence_resolve_and_load_lazily(data):
    lib = FrameLibrary(data)
    assert list(lib.frames) == ["simulated/flat/flat_1"]
    assert set(lib.sequences) == {"clips/take.mp4", "sequences/drag"}
    assert split_frame_id("sequences/drag@2") == ("sequences/drag", 2)
    assert split_frame_id("sequences/drag") is None
    frame = lib.get("sequences/drag@2")
    assert frame.kind == "simulated" and frame.stereo is not None
    loaded = lib.load("sequences/drag@2")
    assert loaded.pair.left.shape == (480, 640, 3) and loaded.pair.mask_left is not None
    assert loaded.ground_truth is not None and loaded.ground_truth.shape[1] == 3
    assert lib.load("sequences/drag@2") is loaded  # cached
    for bad in ("sequences/drag@4", "sequences/nope@0", "sequences/drag@x"):
        with pytest.raises(NotFound):
            lib.get(bad)
    with pytest.raises(ValueError, match="no calibration"):
        lib.load("clips/take.mp4@1")  # a video needs calibration.yaml beside it


def test_timeline_rows_and_bounded_curves(data, monkeypatch):
    monkeypatch.setattr(timeline_mod, "CURVE_FRAMES", 2)
    lib = FrameLibrary(data)
    tl = Timeline(lib, "sequences/drag", ReconParams(), tracking=True)
    wait_done(tl)
    snap = tl.snapshot()
    assert snap["error"] is None and snap["count"] == N_FRAMES
    assert [r["frame"] for r in snap["rows"]] == list(range(N_FRAMES))
    assert [r["frame_id"] for r in snap["rows"]][-1] == f"sequences/drag@{N_FRAMES - 1}"
    for r in snap["rows"]:
        assert r["track_status"] == "ok" and r["track_good"]
        assert 0 < r["confidence"] <= 1 and r["ms"] > 0 and "spline" in r["stage_ms"]
        assert r["curve_length"] == r["track_length"]
    assert [r["frame"] for r in tl.snapshot(since=2)["rows"]] == [2, 3]
    assert tl.curves(0) is None  # only the newest CURVE_FRAMES are kept
    c = tl.curves(N_FRAMES - 1)
    assert c is not None and set(c) == {"single", "tracked", "truth"}
    assert np.asarray(c["tracked"]).shape == (timeline_mod.CURVE_SAMPLES, 2)


def test_timelines_keep_the_newest_and_cancel_the_evicted(data, monkeypatch):
    monkeypatch.setattr(timeline_mod, "TIMELINES", 1)
    tls = Timelines(FrameLibrary(data))
    a = tls.get("sequences/drag", ReconParams(), tracking=True)
    assert tls.get("sequences/drag", ReconParams(), tracking=True) is a
    b = tls.get("sequences/drag", ReconParams(), tracking=False)
    assert b is not a and a._cancel.is_set()
    wait_done(b)
    assert all(r["track_status"] == "off" for r in b.snapshot()["rows"])
    with pytest.raises(NotFound):
        tls.get("sequences/none", ReconParams(), tracking=True)
    tls.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_sequences_api(data):
    config = ServerConfig(data_dir=data, viser_port=_free_port(), open_first=False)
    with TestClient(create_app(config), base_url="http://127.0.0.1") as c:
        frames = c.get("/api/frames").json()
        seq = [f for f in frames if f["kind"] == "sequence"]
        assert [(f["id"], f["count"], f["source"]) for f in seq] == [
            ("clips/take.mp4", 3, "video"),
            ("sequences/drag", N_FRAMES, "images"),
        ]
        r = c.post("/api/frames/sequences/drag@1/run", json={})
        assert r.status_code == 200 and r.json()["frame_id"] == "sequences/drag@1"
        assert c.get("/api/frames/sequences/drag@1/images/left").status_code == 200
        assert c.get("/api/frames/sequences/drag@9/images/left").status_code == 404
        url = "/api/sequences/sequences/drag"
        assert c.get(f"{url}/timeline", params={"since": -1}).status_code == 422
        deadline = time.monotonic() + 120
        while not (tl := c.get(f"{url}/timeline").json())["done"]:
            assert time.monotonic() < deadline
            time.sleep(0.1)
        assert tl["computed"] == N_FRAMES and tl["tracking"] is True
        got = c.get(f"{url}/curves/2").json()
        assert got["frame"] == 2 and len(got["curves"]["tracked"]) > 10
        assert c.get(f"{url}/curves/{N_FRAMES}").status_code == 404
        assert c.get("/api/sequences/nope/timeline").status_code == 404
        rec = c.get(f"{url}/recording.html", params={"frame": 1})
        assert rec.status_code == 200 and "__VISER_EMBED_DATA__" in rec.text
        assert "drag_frame1.html" in rec.headers["content-disposition"]
        assert c.get(f"{url}/recording.html", params={"frame": 99}).status_code == 409


class _Rec(SimpleNamespace):
    def __getitem__(self, key):
        return self.runs[key]


class _FakePipeline:
    """A pipeline whose first frame's curve is "ok" and every later one "suspect" (the check
    doubted it); it records the tracker's corrections of each run."""

    runs: list = []

    def __init__(self, pair, calib) -> None:
        self.pair, self.calib = pair, calib

    def run(self, params, corrections=None):
        _FakePipeline.runs.append(tuple(corrections or ()))
        x = np.linspace(0, 50, 30)
        pts = np.column_stack([x, np.zeros_like(x), np.full_like(x, 100.0)])
        status = "ok" if len(_FakePipeline.runs) == 1 else "suspect"
        return _Rec(status=status, runs={"camera": SimpleNamespace(points=pts)}, message="")


def test_a_suspect_curve_is_observed_through_the_gate_and_not_rerun(monkeypatch):
    monkeypatch.setattr(track_report, "Pipeline", _FakePipeline)
    calib = SimpleNamespace(P1=np.hstack([np.eye(3) * [500, 500, 1], np.zeros((3, 1))]),
                            P2=np.hstack([np.eye(3) * [500, 500, 1], [[-500.0], [0], [0]]]))  # fmt: skip
    pair = SimpleNamespace(shape=(480, 640))
    frames = [SimpleNamespace(pair=pair, index=k, truth=None) for k in range(3)]
    _FakePipeline.runs = []
    out = list(track_report.track_sequence(frames, calib, ReconParams(), TrackParams()))
    assert [tf.tracked.status for tf in out] == ["ok", "ok", "ok"]
    assert [tf.observed_by for tf in out] == ["", "gate", "gate"]
    # one run a frame, and for a doubted frame one more with the gate (no configured-alpha rerun)
    ops = [tuple(c.op for c in run) for run in _FakePipeline.runs]
    assert ops == [(), (), ("keep", "keep"), (), ("keep", "keep")]


def test_a_suspect_first_curve_starts_no_track(monkeypatch):
    monkeypatch.setattr(track_report, "Pipeline", _FakePipeline)
    calib = SimpleNamespace(P1=None, P2=None)
    frames = [SimpleNamespace(pair=None, index=k, truth=None) for k in range(2)]
    _FakePipeline.runs = [()]  # the first run is already made: every run is "suspect"
    out = list(track_report.track_sequence(frames, calib, ReconParams(), TrackParams()))
    assert [tf.tracked.status for tf in out] == ["lost", "lost"]
    assert all("starts from an ok one" in tf.tracked.reason for tf in out)


def test_a_video_frame_is_reached_forward_from_a_cursor_and_backward_from_the_start(data):
    seq = FrameLibrary(data).sequence("clips/take.mp4")
    means = [float(seq.frame(k).pair.left.mean()) for k in (1, 2, 0, 2)]
    assert means == pytest.approx([40, 80, 0, 80], abs=3)  # frame k is grey 40 * k
    with pytest.raises(ValueError, match="no frame 3"):
        seq.frame(3)
