"""Sequence inputs (app/sequence.py), ``threadrecon track`` and ``generate --sequence``."""

from __future__ import annotations

import csv
import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from threadrecon.app.cli import main
from threadrecon.app.sequence import (
    BagSequence,
    SequenceError,
    open_sequence,
    write_video,
)
from threadrecon.app.track_report import track_sequence
from threadrecon.core.metrics import curve_errors
from threadrecon.core.sequence_synth import MotionParams, SequenceParams, generate_sequence
from threadrecon.core.tracking import TrackParams

N_FRAMES = 4


@pytest.fixture(scope="module")
def frames():
    params = SequenceParams(motion=MotionParams(kind="drag", n_frames=N_FRAMES, speed_mm=1.0))
    return list(generate_sequence(params, seed=11))


def _stamp(ts, k: int):
    Time = ts.types["builtin_interfaces/msg/Time"]
    return Time(sec=100 + k // 10, nanosec=(k % 10) * 100_000_000)


def _header(ts, k: int, frame_id: str, ros1: bool):
    Header = ts.types["std_msgs/msg/Header"]
    if ros1:
        return Header(seq=k, stamp=_stamp(ts, k), frame_id=frame_id)
    return Header(stamp=_stamp(ts, k), frame_id=frame_id)


def _camera_info(ts, k, side, cam, ros1: bool):
    Info = ts.types["sensor_msgs/msg/CameraInfo"]
    RoI = ts.types["sensor_msgs/msg/RegionOfInterest"]
    P = np.hstack([cam.K, np.zeros((3, 1))])
    if side == "right":
        P[0, 3] = -cam.fx * cam.baseline / 1000.0  # ROS: metres
    mats = {
        "d": np.zeros(5),
        "k": cam.K.ravel(),
        "r": np.eye(3).ravel(),
        "p": P.ravel(),
    }
    if ros1:
        mats = {key.upper(): v for key, v in mats.items()}
    return Info(
        header=_header(ts, k, side, ros1),
        height=cam.height,
        width=cam.width,
        distortion_model="plumb_bob",
        binning_x=0,
        binning_y=0,
        roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        **mats,
    )


def write_bag(path: Path, frames, ros1: bool, compressed_right: bool = False) -> None:
    """A stereo bag of the frames: /stereo/{left,right}/image_rect (+ camera_info)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, ser = Writer(path, version=8), ts.serialize_cdr
    Image = ts.types["sensor_msgs/msg/Image"]
    Compressed = ts.types["sensor_msgs/msg/CompressedImage"]
    with writer:
        conns = {}
        for side in ("left", "right"):
            kind = Compressed if (side == "right" and compressed_right) else Image
            conns[side] = writer.add_connection(
                f"/stereo/{side}/image_rect", kind.__msgtype__, typestore=ts
            )
            conns[side + "_info"] = writer.add_connection(
                f"/stereo/{side}/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts
            )
        for k, f in enumerate(frames):
            t_ns = (100 + k // 10) * 10**9 + (k % 10) * 100_000_000
            for side, img in (("left", f.left), ("right", f.right)):
                if side == "right" and compressed_right:
                    import cv2

                    ok, png = cv2.imencode(".png", img[:, :, ::-1])
                    assert ok
                    msg = Compressed(
                        header=_header(ts, k, side, ros1), format="png", data=png.ravel()
                    )
                    msgtype = Compressed.__msgtype__
                else:
                    h, w = img.shape[:2]
                    msg = Image(
                        header=_header(ts, k, side, ros1),
                        height=h,
                        width=w,
                        encoding="bgr8" if side == "right" else "rgb8",
                        is_bigendian=0,
                        step=3 * w,
                        data=np.ascontiguousarray(
                            img[:, :, ::-1] if side == "right" else img
                        ).ravel(),
                    )
                    msgtype = Image.__msgtype__
                writer.write(conns[side], t_ns, ser(msg, msgtype))
                info = _camera_info(ts, k, side, f.camera, ros1)
                writer.write(conns[side + "_info"], t_ns, ser(info, info.__msgtype__))


def _check_tracked(seq, frames) -> None:
    cam = frames[0].camera
    calib = seq.calibration
    assert calib is not None and calib.unit == "mm"
    assert calib.baseline == pytest.approx(cam.baseline, rel=1e-6)
    assert calib.focal == pytest.approx(cam.fx)
    out = list(track_sequence(seq, calib, track=TrackParams()))
    assert len(out) == len(frames) == seq.count
    for tf, f in zip(out, frames, strict=True):
        assert np.array_equal(tf.frame.pair.left, f.left)
        assert np.array_equal(tf.frame.pair.right, f.right)
        assert tf.tracked is not None and tf.tracked.status == "ok"
        e = curve_errors(tf.tracked.points, f.truth.centerline)
        assert e.e_length < 5.0 and e.e_S_max < 5.0
    assert out[-1].alpha < 80  # the search range came from the previous frame


def test_a_ros1_bag_is_read_and_tracked(tmp_path, frames):
    path = tmp_path / "stereo.bag"
    write_bag(path, frames, ros1=True)
    seq = open_sequence(path)
    assert isinstance(seq, BagSequence) and seq.left_topic == "/stereo/left/image_rect"
    _check_tracked(seq, frames)


def test_a_ros2_bag_is_read_and_tracked(tmp_path, frames):
    path = tmp_path / "stereo_ros2"
    write_bag(path, frames, ros1=False, compressed_right=True)
    seq = open_sequence(path)
    assert isinstance(seq, BagSequence)
    _check_tracked(seq, frames)


def test_a_bag_with_unnamed_topics_asks_for_them(tmp_path, frames):
    path = tmp_path / "stereo.bag"
    write_bag(path, frames[:1], ros1=True)
    with pytest.raises(SequenceError, match="no image topic '/cam0'"):
        open_sequence(path, left_topic="/cam0")
    seq = open_sequence(
        path, left_topic="/stereo/left/image_rect", right_topic="/stereo/right/image_rect"
    )
    assert seq.count == 1


def test_a_video_is_read_one_frame_at_a_time(tmp_path, frames):
    sbs = [np.hstack([f.left, f.right]) for f in frames]
    n = 60  # repeat the frames: a video far larger than one frame
    path = tmp_path / "stereo.mp4"
    assert write_video(path, (sbs[k % len(sbs)] for k in range(n))) == n
    seq = open_sequence(path)
    assert seq.count == n
    frame_bytes = sbs[0].nbytes
    for k, fr in zip(range(len(frames)), seq, strict=False):  # near-lossless H.264
        assert np.mean(np.abs(fr.pair.left.astype(int) - frames[k].left.astype(int))) < 2.0
    tracemalloc.start()
    count = 0
    for fr in seq:
        assert fr.pair.left.shape == frames[0].left.shape
        count += 1
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert count == n
    print(f"video of {n} frames ({n * frame_bytes / 1e6:.1f} MB decoded): peak {peak / 1e6:.2f} MB")
    assert peak < 3 * frame_bytes  # a whole decoded video would be n = 60 frames


def test_left_and_right_videos_are_paired(tmp_path, frames):
    for side in ("left", "right"):
        write_video(tmp_path / f"{side}.mp4", (getattr(f, side) for f in frames))
    seq = open_sequence(tmp_path / "left.mp4", right=tmp_path / "right.mp4")
    pairs = list(seq)
    assert len(pairs) == len(frames)
    assert np.mean(np.abs(pairs[1].pair.right.astype(int) - frames[1].right.astype(int))) < 2.0


def test_unreadable_sources_are_named(tmp_path):
    with pytest.raises(SequenceError, match="no such file"):
        open_sequence(tmp_path / "missing.mp4")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(SequenceError, match="not a readable video"):
        open_sequence(bad)
    (tmp_path / "empty").mkdir()
    with pytest.raises(SequenceError, match="no images"):
        open_sequence(tmp_path / "empty")
    broken = tmp_path / "broken.bag"
    broken.write_bytes(b"#ROSBAG V2.0\n garbage")
    with pytest.raises(SequenceError, match="not a readable ROS bag"):
        open_sequence(broken)


def test_generate_sequence_then_track_writes_a_result_per_frame(tmp_path, capsys):
    assert (
        main(["generate", str(tmp_path), "--sequence", "3", "--motion", "pull", "--seed", "2"]) == 0
    )
    folder = tmp_path / "sequences" / "pull"
    assert (folder / "pull.mp4").is_file() and (folder / "pull_3_mask.png").is_file()
    assert len(list(folder.glob("pull_?.npy"))) == 3
    out = tmp_path / "run"
    assert main(["track", str(folder), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "frames/s" in text and "tracked good frames: 3/3" in text
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["name"] for r in rows] == ["pull_1", "pull_2", "pull_3"]
    assert all(r["track_good"] == "True" for r in rows)
    assert all(r["observed_by"] == "single" and r["tracker_removed_px"] == "0" for r in rows)
    data = json.loads((out / "frames" / "pull_2.json").read_text())
    assert data["tracked"]["status"] == "ok" and len(data["tracked"]["points"]) > 10
    assert data["tracked"]["observed_by"] == "single"  # an ok frame is observed as it is
    assert data["status"] == "ok" and data["truth_metrics"]["track_e_length_mm"] < 5
    # the video of the same sequence, with the folder's calibration, no masks
    out_v = tmp_path / "run_video"
    code = main(
        ["track", str(folder / "pull.mp4"), "--calib", str(folder / "calibration.yaml"),
         "--out", str(out_v), "--no-tracking"]
    )  # fmt: skip
    assert code in (0, 1)
    assert len(list((out_v / "frames").glob("*.json"))) == 3


def test_raw_frames_with_an_instrument_are_tracked_through_the_trackers_corrections(tmp_path):
    """The raw segmenter (forced: ``auto`` thresholds this flat scene and drops the grasper,
    its single-frame curves are right) takes the shaft's dark tip for thread on every frame of
    this sequence: their single-frame curves are wrong. The track starts from the first
    frame's start hypothesis the check calls ok (a piece removed), follows the thread through
    the gate around its prediction, and flags the frames where the single-frame curve
    differs."""
    args = ["generate", str(tmp_path), "--sequence", "4", "--motion", "instrument", "--seed", "10",
            "--size", "320x240", "--group", "inst"]  # fmt: skip
    assert main(args) == 0
    raw = tmp_path / "raw.toml"
    raw.write_text('[segment]\nmethod = "raw"\n')
    out = tmp_path / "run"
    main(["track", str(tmp_path / "sequences" / "inst"), "--out", str(out), "--no-masks",
          "--config", str(raw)])  # fmt: skip
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["good"] for r in rows] == ["False"] * 4
    assert [r["observed_by"] for r in rows] == ["start", "gate", "gate", "gate"]
    assert [r["track_good"] for r in rows] == ["True"] * 4
    assert [r["track_status"] for r in rows] == ["ok"] * 4
    assert all(int(r["tracker_removed_px"]) > 1000 for r in rows)  # the gate cut the shaft
    assert [r["flagged"] for r in rows] == ["True"] * 4


def test_track_without_a_calibration_is_a_one_line_error(tmp_path, frames, capsys):
    path = tmp_path / "v.mp4"
    write_video(path, (np.hstack([f.left, f.right]) for f in frames))
    assert main(["track", str(path), "--out", str(tmp_path / "o")]) == 2
    assert "carries no calibration: give --calib" in capsys.readouterr().err
