"""Tests of app/io.py's calibration readers: OpenCV FileStorage, ROS camera_info pairs and
Kalibr camchains of the same rig give the same calibration; errors name the file and key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from rig_support import opencv_yaml, raw_rig, ros_camera_info
from support import assert_close

from threadrecon.app.io import load_calibration, prepare_pair
from threadrecon.core.calibration import CalibrationError, StereoCalibration


def _same_rig(a: StereoCalibration, b: StereoCalibration) -> None:
    for key in ("K1", "K2", "R", "P1", "P2", "Q"):
        assert_close(getattr(a, key), getattr(b, key), rtol=1e-9, atol=1e-9)
    assert_close(a.T, b.T, rtol=1e-9, atol=1e-12)
    for key in ("D1", "D2"):  # Kalibr's radtan has 4 terms: k3 = 0
        da, db = (np.pad(getattr(c, key).ravel(), (0, 5))[:5] for c in (a, b))
        assert_close(da, db, atol=1e-15)
    assert a.image_size == b.image_size and a.unit == b.unit


def _write_ros(tmp_path: Path, calib: StereoCalibration) -> tuple[Path, Path]:
    left, right = ros_camera_info(calib)
    lp, rp = tmp_path / "left.yaml", tmp_path / "right.yaml"
    lp.write_text(yaml.safe_dump(left))
    rp.write_text(yaml.safe_dump(right))
    return lp, rp


def _kalibr(calib: StereoCalibration, scale: float = 1.0) -> dict:
    rows, cols = calib.image_size
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = calib.R, calib.T * scale
    cams = {}
    for name, K, D in (("cam0", calib.K1, calib.D1), ("cam1", calib.K2, calib.D2)):
        cams[name] = {
            "camera_model": "pinhole",
            "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
            "distortion_model": "radtan",
            "distortion_coeffs": D[:4].tolist(),
            "resolution": [cols, rows],
            "rostopic": f"/{name}/image_raw",
        }
    cams["cam1"]["T_cn_cnm1"] = T.tolist()
    return cams


def test_ros_camera_info_pair_reads_as_the_opencv_file_of_the_same_rig(tmp_path: Path) -> None:
    calib = raw_rig(0).calib
    cv_path = tmp_path / "rig.yaml"
    cv_path.write_text(opencv_yaml(calib))
    lp, rp = _write_ros(tmp_path, calib)
    from_cv = load_calibration(cv_path)
    from_ros = load_calibration(lp, unit="mm", right=rp)
    _same_rig(from_cv, from_ros)
    assert load_calibration(lp, right=rp).unit == "m"  # ROS convention when not told


def test_ros_message_fields_read_as_the_calibration_files(tmp_path: Path) -> None:
    calib = raw_rig(0).calib
    msgs = []
    for info in ros_camera_info(calib):  # sensor_msgs/CameraInfo as `rostopic echo` prints it
        msgs.append({
            "height": info["image_height"], "width": info["image_width"],
            "distortion_model": info["distortion_model"],
            "D": info["distortion_coefficients"]["data"], "K": info["camera_matrix"]["data"],
            "R": info["rectification_matrix"]["data"], "P": info["projection_matrix"]["data"],
        })  # fmt: skip
    (tmp_path / "l.yaml").write_text(yaml.safe_dump(msgs[0]))
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(msgs[1]))
    _same_rig(load_calibration(tmp_path / "l.yaml", unit="mm", right=tmp_path / "r.yaml"), calib)


def test_kalibr_camchain_reads_as_the_same_rig_in_metres(tmp_path: Path) -> None:
    calib = raw_rig(0).calib
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(_kalibr(calib, scale=1e-3)))
    got = load_calibration(tmp_path / "camchain.yaml")
    assert got.unit == "m"
    assert_close(got.T * 1000, calib.T, rtol=1e-12)
    assert_close(got.R, calib.R, atol=1e-15)
    (tmp_path / "mm.yaml").write_text(yaml.safe_dump(_kalibr(calib)))
    _same_rig(load_calibration(tmp_path / "mm.yaml", unit="mm"), calib)


def test_opencv_rectified_flag_is_read(tmp_path: Path) -> None:
    text = opencv_yaml(raw_rig(0).reference_calib)
    p = tmp_path / "c.yaml"
    p.write_text(text)
    assert load_calibration(p).rectified is None
    p.write_text(text + "Rectified: 0\n")
    assert load_calibration(p).rectified is False


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda left, right: (left, left), r"P\[0, 3\] = 0 \(no baseline\)"),
        (lambda left, right: ({**left, "distortion_model": "equidistant"}, right), "equidistant"),
        (
            lambda left, right: ({k: v for k, v in left.items() if k != "camera_matrix"}, right),
            "missing key camera_matrix",
        ),
        (lambda left, right: (left, {**right, "image_width": 320}), "left image is"),
        (
            lambda left, right: ({**left, "rectification_matrix": {"data": [2.0] * 9}}, right),
            "not a rotation",
        ),
    ],
)
def test_bad_ros_pair_is_named(tmp_path: Path, edit, match: str) -> None:  # type: ignore[no-untyped-def]
    left, right = edit(*ros_camera_info(raw_rig(0).calib))
    (tmp_path / "l.yaml").write_text(yaml.safe_dump(left))
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(right))
    with pytest.raises(CalibrationError, match=match):
        load_calibration(tmp_path / "l.yaml", right=tmp_path / "r.yaml")


def test_single_camera_info_asks_for_the_right_one(tmp_path: Path) -> None:
    lp, _ = _write_ros(tmp_path, raw_rig(0).calib)
    with pytest.raises(CalibrationError, match="--calib-right"):
        load_calibration(lp)


def test_bad_kalibr_is_named(tmp_path: Path) -> None:
    chain = _kalibr(raw_rig(0).calib)
    chain["cam1"]["distortion_model"] = "equidistant"
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(chain))
    with pytest.raises(CalibrationError, match=r"cam1\): distortion_model 'equidistant'"):
        load_calibration(tmp_path / "c.yaml")
    del chain["cam1"]
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(chain))
    with pytest.raises(CalibrationError, match="missing key cam1"):
        load_calibration(tmp_path / "c.yaml")


def test_unreadable_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration(tmp_path / "none.yaml")
    (tmp_path / "bad.yaml").write_text("key: [unclosed\n")
    with pytest.raises(CalibrationError, match="bad.yaml"):
        load_calibration(tmp_path / "bad.yaml")
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(CalibrationError, match="bin.yaml"):
        load_calibration(tmp_path / "bin.yaml")


def test_prepare_pair_rectifies_only_a_raw_pair() -> None:
    rig = raw_rig(0)
    pair, calib, rect = prepare_pair(rig.reference, rig.reference_calib)
    assert pair is rig.reference and calib is rig.reference_calib and rect.identity
    pair, calib, rect = prepare_pair(rig.pair, rig.calib)
    assert not rect.identity and calib.rectified is True
    assert pair.mask_left is not None and pair.left.shape == rig.pair.left.shape
