"""Tests of app/api.py (``reconstruct``) and of ``threadrecon reconstruct`` on raw rigs: the
same rig described by OpenCV, ROS or Kalibr files gives the same curve; arrays and paths give
the same result; the JSON validates against the schema."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import jsonschema
import numpy as np
import pytest
import yaml
from plyfile import PlyData
from rig_support import opencv_yaml, raw_rig, ros_camera_info
from support import assert_close

from threadrecon.app.cli import main
from threadrecon.app.python_api import ThreadResult, reconstruct
from threadrecon.core.metrics import curve_errors

SCHEMA = json.loads(
    (Path(__file__).resolve().parents[2] / "docs" / "result.schema.json").read_text()
)


def _png(path: Path, img: np.ndarray) -> Path:
    img = img.astype(np.uint8) * 255 if img.dtype == bool else cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    assert cv2.imwrite(str(path), img)
    return path


@pytest.fixture(scope="module")
def rig_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("rig")
    rig = raw_rig(0)
    files = {
        "left": _png(d / "cam_left.png", rig.pair.left),
        "right": _png(d / "cam_right.png", rig.pair.right),
        "mask_left": _png(d / "cam_left_mask.png", rig.pair.mask_left),
        "mask_right": _png(d / "cam_right_mask.png", rig.pair.mask_right),
        "opencv": d / "rig.yaml",
        "ros_left": d / "left.yaml",
        "ros_right": d / "right.yaml",
    }
    files["opencv"].write_text(opencv_yaml(rig.calib))
    left, right = ros_camera_info(rig.calib)
    files["ros_left"].write_text(yaml.safe_dump(left))
    files["ros_right"].write_text(yaml.safe_dump(right))
    return files


@pytest.fixture(scope="module")
def from_opencv(rig_files: dict[str, Path]) -> ThreadResult:
    f = rig_files
    out = reconstruct(
        f["left"], f["right"], f["opencv"], mask_left=f["mask_left"], mask_right=f["mask_right"]
    )
    assert out.ok, out.reasons
    return out


def test_ros_and_opencv_files_of_the_same_rig_give_the_same_curve(
    rig_files: dict[str, Path], from_opencv: ThreadResult
) -> None:
    f = rig_files
    from_ros = reconstruct(
        f["left"], f["right"], f["ros_left"], calib_right=f["ros_right"], units="mm",
        mask_left=f["mask_left"], mask_right=f["mask_right"],
    )  # fmt: skip
    assert from_ros.ok and from_ros.unit == from_opencv.unit == "mm"
    assert from_opencv.points is not None and from_ros.points is not None
    gap = np.abs(from_ros.points - from_opencv.points).max()
    assert gap < 1e-6, gap
    assert_close(from_ros.control_points, from_opencv.control_points, atol=1e-6, rtol=0)


def test_raw_rig_through_files_is_close_to_the_truth_in_the_left_frame(
    from_opencv: ThreadResult,
) -> None:
    rig = raw_rig(0)
    assert from_opencv.frame == "left" and from_opencv.rectification.identity is False
    e = curve_errors(from_opencv.points, rig.truth_left)
    assert e.e_S < 0.3, e


def test_arrays_and_paths_give_the_same_result(
    rig_files: dict[str, Path], from_opencv: ThreadResult
) -> None:
    rig = raw_rig(0)
    from_arrays = reconstruct(
        rig.pair.left, rig.pair.right, rig.calib,
        mask_left=rig.pair.mask_left, mask_right=rig.pair.mask_right,
    )  # fmt: skip
    # the OpenCV file stores the same numbers; PNG is lossless
    assert_close(from_arrays.points, from_opencv.points, atol=1e-9, rtol=0)
    assert [i.name for i in from_arrays.inputs] == [None] * 4
    assert {i.role for i in from_opencv.inputs} == {
        "left",
        "right",
        "mask_left",
        "mask_right",
        "calibration",
    }


def test_frame_option_gives_the_rectified_frame(
    rig_files: dict[str, Path], from_opencv: ThreadResult
) -> None:
    f = rig_files
    rect = reconstruct(
        f["left"], f["right"], f["opencv"], mask_left=f["mask_left"], mask_right=f["mask_right"],
        frame="left_rectified",
    )  # fmt: skip
    R1 = from_opencv.rectification.R1
    assert_close(rect.points @ R1, from_opencv.points, atol=1e-9, rtol=0)
    assert rect.to_json()["frame"] == "left_rectified"
    # the grasp point and its tangent turn with the curve
    assert_close(rect.grasp.point @ R1, from_opencv.grasp.point, atol=1e-9, rtol=0)
    assert_close(rect.grasp.tangent @ R1, from_opencv.grasp.tangent, atol=1e-12, rtol=0)


def test_grasp_point_lies_on_the_curve_with_its_confidence(from_opencv: ThreadResult) -> None:
    r = from_opencv
    g = r.grasp
    i = int(np.argmin(np.linalg.norm(r.points - g.point, axis=1)))
    assert_close(r.points[i], g.point, atol=1e-9, rtol=0)
    assert g.confidence == pytest.approx(float(r.confidence[i]))
    assert np.linalg.norm(g.tangent) == pytest.approx(1.0)
    step = r.points[min(i + 1, len(r.points) - 1)] - r.points[max(i - 1, 0)]
    assert float(g.tangent @ step) > 0.9 * np.linalg.norm(step)  # along the curve, start -> end
    assert r.confidence.shape == (len(r.points),) and 1 <= r.score <= 5
    assert r.rating == r.reconstruction["check"].rating and abs(r.rating - r.score) <= 0.5
    assert r.reasons == r.reconstruction.reasons


def test_result_json_validates_and_names_its_inputs(
    from_opencv: ThreadResult, rig_files: dict[str, Path]
) -> None:
    data = json.loads(json.dumps(from_opencv.to_json(), allow_nan=False))
    jsonschema.validate(data, SCHEMA)
    names = {i["role"]: i["name"] for i in data["inputs"]}
    assert names["left"] == "cam_left.png" and names["calibration"] == "rig.yaml"
    assert data["preset"] == "default" and data["rectification"]["applied"] is True


def test_point_at_walks_the_curve(from_opencv: ThreadResult) -> None:
    pts = from_opencv.points
    assert_close(from_opencv.point_at(0.0), pts[0])
    assert_close(from_opencv.point_at(1.0), pts[-1])
    mid = from_opencv.point_at(0.5)
    assert np.linalg.norm(pts - mid, axis=1).min() < 0.5
    with pytest.raises(ValueError, match=r"s must be in \[0, 1\]"):
        from_opencv.point_at(1.5)


def test_bad_api_input_is_named(rig_files: dict[str, Path]) -> None:
    rig = raw_rig(0)
    with pytest.raises(ValueError, match="a calibration is needed"):
        reconstruct(rig.pair.left, rig.pair.right)
    with pytest.raises(ValueError, match="both masks or neither"):
        reconstruct(rig.pair.left, rig.pair.right, rig.calib, mask_left=rig.pair.mask_left)
    with pytest.raises(ValueError, match="must be uint8"):
        reconstruct(rig.pair.left.astype(float), rig.pair.right, rig.calib)
    with pytest.raises(FileNotFoundError, match="left image file not found"):
        reconstruct("nope.png", rig_files["right"], rig.calib)
    with pytest.raises(ValueError, match="calibration is for"):
        reconstruct(rig.pair.left[:200], rig.pair.right[:200], rig.calib)
    with pytest.raises(ValueError, match="frame must be one of"):
        reconstruct(rig.pair.left, rig.pair.right, rig.calib, frame="world")  # type: ignore[arg-type]


def test_cli_reconstructs_a_ros_rig_with_frame_and_ply(
    rig_files: dict[str, Path],
    from_opencv: ThreadResult,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    f = rig_files
    out, ply = tmp_path / "curve.json", tmp_path / "curve.ply"
    code = main([
        "reconstruct", "--left", str(f["left"]), "--right", str(f["right"]),
        "--mask-left", str(f["mask_left"]), "--mask-right", str(f["mask_right"]),
        "--calib", str(f["ros_left"]), "--calib-right", str(f["ros_right"]), "--units", "mm",
        "--config", "default", "--out", str(out), "--ply", str(ply),
    ])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    data = json.loads(out.read_text())
    jsonschema.validate(data, SCHEMA)
    assert data["frame"] == "left" and data["preset"] == "default"
    assert {i["role"] for i in data["inputs"]} >= {"calibration", "calibration_right"}
    assert np.abs(np.array(data["points"]) - from_opencv.points).max() < 1e-6
    curve = PlyData.read(str(ply))
    assert curve["edge"].count == len(data["points"]) - 1
    assert "frame left" in capsys.readouterr().out


def test_cli_single_camera_info_is_a_one_line_error(
    rig_files: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = rig_files
    code = main([
        "reconstruct", "--left", str(f["left"]), "--right", str(f["right"]),
        "--calib", str(f["ros_left"]), "--out", str(tmp_path / "o.json"),
    ])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "--calib-right" in err and len(err.strip().splitlines()) == 1


def test_example_script_prints_a_grasp_point() -> None:
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[2] / "examples" / "reconstruct_frame.py"
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "grasp point (mm):" in run.stdout and "frame left" in run.stdout
