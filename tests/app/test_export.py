"""Exports of a reconstruction: spline JSON/CSV and PLY clouds read back equal what was stored;
the result JSON validates against docs/result.schema.json; the curve PLY is a line set."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import trimesh
from plyfile import PlyData
from rig_support import raw_rig
from support import assert_close, synthetic_case

from threadrecon.app.export import (
    LAYERS,
    SPLINE_END_RGB,
    SPLINE_START_RGB,
    InputFile,
    cloud_ply,
    json_safe,
    ply_bytes,
    polyline_ply,
    reliability_colors,
    result_json,
    software_version,
    spline_csv,
    spline_json,
)
from threadrecon.app.presets import params_hash
from threadrecon.core.pipeline import Pipeline, Reconstruction, reconstruct
from threadrecon.core.rectify import rectification, rectify_pair
from threadrecon.core.segmentation import StereoPair


@pytest.fixture(scope="module")
def rec() -> Reconstruction:
    pair, calib, _ = synthetic_case(0)
    out = reconstruct(pair, calib)
    assert out.status == "ok", out.message
    return out


@pytest.fixture(scope="module")
def failed() -> Reconstruction:
    pair, calib, _ = synthetic_case(0)
    blank = np.full_like(pair.left, 128)
    out = reconstruct(StereoPair(blank, blank.copy()), calib)
    assert out.failed_stage is not None
    return out


def read_ply(data: bytes) -> tuple[list[str], np.ndarray]:
    """Header lines and vertices of a PLY, read by plyfile (an independent reader)."""
    ply = PlyData.read(io.BytesIO(data))
    assert ply.header.splitlines()[:2] == ["ply", "format binary_little_endian 1.0"]
    return ply.header.splitlines(), ply["vertex"].data


def xyz(v: np.ndarray) -> np.ndarray:
    return np.stack([v["x"], v["y"], v["z"]], axis=1)


def rgb(v: np.ndarray) -> np.ndarray:
    return np.stack([v["red"], v["green"], v["blue"]], axis=1)


def test_ply_bytes_reads_back_points_and_colors() -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(57, 3)) * 40
    colors = rng.integers(0, 256, size=(57, 3)).astype(np.uint8)
    header, v = read_ply(ply_bytes(pts, colors, comments=["unit mm"]))
    assert "comment unit mm" in header
    assert_close(xyz(v), pts.astype(np.float32))
    np.testing.assert_array_equal(rgb(v), colors)
    _, empty = read_ply(ply_bytes(np.zeros((0, 3))))
    assert empty.size == 0


@pytest.mark.parametrize(
    ("points", "colors", "match"),
    [
        (np.zeros((4, 2)), None, r"\(N, 3\), got \(4, 2\)"),
        (np.zeros(3), None, r"\(N, 3\), got \(3,\)"),
        (np.array([[0.0, np.nan, 1.0]]), None, "finite"),
        (np.zeros((4, 3)), np.zeros((3, 3), np.uint8), r"colors must have shape \(4, 3\)"),
        (np.zeros((4, 3)), np.zeros((4, 3)), "uint8, got float64"),
    ],
)
def test_ply_bytes_rejects_bad_input(
    points: np.ndarray, colors: np.ndarray | None, match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        ply_bytes(points, colors)


def test_spline_json_matches_the_camera_curve(rec: Reconstruction) -> None:
    data = spline_json(rec)
    text = json.dumps(data, allow_nan=False)  # strict JSON
    data = json.loads(text)
    cam = rec["camera"]
    assert data["status"] == "ok" and data["fallback"] is False and data["unit"] == "mm"
    assert_close(np.array(data["points"]), cam.points)
    assert_close(np.array(data["control_points"]), cam.ctrl)
    assert_close(np.array(data["knots"]), cam.knots)
    assert data["degree"] == cam.degree and data["length"] == cam.length
    assert len(data["knots"]) == len(data["control_points"]) + data["degree"] + 1


def test_spline_json_keypoints_lie_on_the_curve_with_cluster_reliability(
    rec: Reconstruction,
) -> None:
    kp = spline_json(rec)["keypoints"]
    clusters, R = rec["clustering"], rec["reliability"].R
    pts = np.array(kp["points"])
    assert_close(pts, clusters.keypoints)
    assert kp["size"] == clusters.sizes.tolist()
    for k in (0, clusters.count // 2, clusters.count - 1):
        assert kp["reliability"][k] == pytest.approx(R[clusters.labels == k].mean(), rel=1e-12)
    assert all(0.0 <= r <= 1.0 for r in kp["reliability"])
    # Same frame as the spline: every keypoint is within 0.5 mm of the dense curve.
    d = np.linalg.norm(pts[:, None, :] - rec["camera"].points[None, :, :], axis=2).min(axis=1)
    assert d.max() < 0.5
    ranks = [r for r in kp["rank"] if r is not None]
    assert len(set(ranks)) == len(ranks) and len(ranks) >= 0.9 * clusters.count


def test_spline_csv_parses_back_to_the_camera_points(rec: Reconstruction) -> None:
    rows = list(csv.reader(io.StringIO(spline_csv(rec))))
    assert rows[0] == ["i", "x_mm", "y_mm", "z_mm", "confidence"]
    body = np.array(rows[1:], dtype=float)
    np.testing.assert_array_equal(body[:, 0], np.arange(len(rec["camera"].points)))
    np.testing.assert_array_equal(body[:, 1:4], rec["camera"].points)  # exact round trip
    np.testing.assert_array_equal(body[:, 4], rec["check"].confidence)


def test_cloud_layers_read_back_their_points(rec: Reconstruction) -> None:
    stereo, rel = rec["stereo"], rec["reliability"]
    finite = np.isfinite(stereo.points).all(axis=1)
    expected = {
        "stereo": stereo.points[finite],
        "reliable": stereo.points[finite & rel.reliable],
        "keypoints": rec["clustering"].keypoints,
        "spline": rec["camera"].points,
    }
    for layer in LAYERS:
        header, v = read_ply(cloud_ply(rec, layer))
        assert f"comment threadrecon layer {layer}" in header and "comment unit mm" in header
        assert_close(xyz(v), expected[layer].astype(np.float32))
    _, v = read_ply(cloud_ply(rec, "stereo"))
    np.testing.assert_array_equal(rgb(v), reliability_colors(rel.R[finite]))
    _, v = read_ply(cloud_ply(rec, "spline"))
    np.testing.assert_array_equal(rgb(v)[[0, -1]], [SPLINE_START_RGB, SPLINE_END_RGB])


def test_reliability_colors_run_from_red_through_yellow_to_green() -> None:
    got = reliability_colors(np.array([0.0, 0.25, 0.5, 1.0, np.nan, 2.0]))
    expected = [[255, 0, 0], [255, 128, 0], [255, 255, 0], [0, 255, 0], [255, 0, 0], [0, 255, 0]]
    np.testing.assert_array_equal(got, expected)
    assert got.dtype == np.uint8


def test_unknown_layer_is_named(rec: Reconstruction) -> None:
    with pytest.raises(ValueError, match="unknown layer 'depth'"):
        cloud_ply(rec, "depth")


def test_failed_reconstruction_gives_clear_errors(failed: Reconstruction) -> None:
    reason = f"failed at {failed.failed_stage}"
    with pytest.raises(ValueError, match=f"no final spline: the reconstruction {reason}"):
        spline_json(failed)
    with pytest.raises(ValueError, match="no final spline"):
        spline_csv(failed)
    with pytest.raises(ValueError, match=f"needs the camera stage: the reconstruction {reason}"):
        cloud_ply(failed, "spline")


def test_stopped_pipeline_names_the_missing_stage() -> None:
    pair, calib, _ = synthetic_case(0)
    partial = Pipeline(pair, calib).run(until="reliability")
    _, v = read_ply(cloud_ply(partial, "reliable"))
    assert len(v) == partial["reliability"].count
    with pytest.raises(ValueError, match="'keypoints' needs the clustering stage"):
        cloud_ply(partial, "keypoints")
    with pytest.raises(ValueError, match="stopped before the camera stage"):
        spline_json(partial)


def test_json_safe_replaces_non_finite_and_numpy() -> None:
    got = json_safe({"a": np.array([1.0, np.nan]), "b": (np.int64(3), np.float32(np.inf))})
    assert got == {"a": [1.0, None], "b": [3, None]}
    assert type(got["b"][0]) is int


def test_json_safe_converts_whole_arrays_like_their_elements() -> None:
    a = np.array([[1.25, np.nan], [-np.inf, 2.0]])
    assert json_safe(a) == [[1.25, None], [None, 2.0]]
    assert json_safe(a.astype(np.float32)[1:, 1:]) == [[2.0]]
    assert json_safe(np.array([[1, 2]], np.int16)) == [[1, 2]]
    assert json_safe(np.array([True, False])) == [True, False]
    assert all(type(v) is float for v in json_safe(np.array([0.5, 1.5], np.float32)))


# --- the one result schema and the PLY polyline ------------------------------------------


@pytest.fixture(scope="module")
def schema() -> dict:
    path = Path(__file__).resolve().parents[2] / "docs" / "result.schema.json"
    data = json.loads(path.read_text())
    jsonschema.Draft202012Validator.check_schema(data)
    return data


def test_result_json_of_ok_and_failed_reconstructions_validates(
    rec: Reconstruction, failed: Reconstruction, schema: dict
) -> None:
    inputs = [InputFile.of_array("left", np.zeros((4, 4), np.uint8))]
    for r in (rec, failed):
        data = json.loads(
            json.dumps(result_json(r, preset="default", inputs=inputs), allow_nan=False)
        )
        jsonschema.validate(data, schema)
    ok = result_json(rec, preset="default", inputs=inputs)
    assert ok["status"] == "ok" and ok["reasons"] == [] and ok["frame"] == "left"
    assert ok["params_hash"] == params_hash(rec.params) and ok["params"] == json_safe(
        rec.params.to_dict()
    )
    assert ok["software"]["version"] == software_version() != "unknown"
    assert (
        ok["inputs"][0]["sha256"] == InputFile.of_array("left", np.zeros((4, 4), np.uint8)).sha256
    )
    bad = result_json(failed)
    assert (
        bad["status"] == "failed" and bad["points"] is None and bad["reasons"] == [failed.message]
    )


def test_schema_rejects_a_result_with_a_missing_or_wrong_field(
    rec: Reconstruction, schema: dict
) -> None:
    data = result_json(rec)
    for broken in (
        {k: v for k, v in data.items() if k != "params_hash"},
        {**data, "frame": "right"},
        {**data, "points": [[1.0, 2.0]]},
        {**data, "surprise": 1},
    ):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(broken, schema)


def test_result_json_reports_the_left_frame_through_R1_or_the_rectified_one() -> None:
    rig = raw_rig(0)
    rect = rectification(rig.calib)
    r = reconstruct(rectify_pair(rig.pair, rect), rect.calib)
    left = result_json(r, rect, "left")
    rectified = result_json(r, rect, "left_rectified")
    assert_close(np.array(rectified["points"]), r["camera"].points)
    assert_close(np.array(left["points"]), r["camera"].points @ rect.R1)
    assert_close(np.array(left["control_points"]), r["camera"].ctrl @ rect.R1)
    assert left["rectification"]["applied"] is True
    assert_close(np.array(left["rectification"]["R1"]), rect.R1)
    assert left["length"] == pytest.approx(rectified["length"])
    with pytest.raises(ValueError, match="frame must be one of"):
        result_json(r, rect, "world")  # type: ignore[arg-type]


def test_curve_ply_is_a_polyline_line_set(rec: Reconstruction) -> None:
    pts = rec["camera"].points
    data = polyline_ply(pts, "mm", "left")
    ply = PlyData.read(io.BytesIO(data))
    assert_close(xyz(ply["vertex"].data), pts.astype(np.float32))
    edges = np.stack([ply["edge"].data["vertex1"], ply["edge"].data["vertex2"]], axis=1)
    np.testing.assert_array_equal(
        edges, np.stack([np.arange(len(pts) - 1), np.arange(1, len(pts))], 1)
    )
    assert "frame left" in ply.comments and "unit mm" in ply.comments
    path = trimesh.load(io.BytesIO(data), file_type="ply")
    assert isinstance(path, trimesh.path.Path3D)  # a line set, not a point cloud
    assert len(path.vertices) == len(pts)
    assert path.length == pytest.approx(rec["camera"].length, rel=1e-5)
    # the page's spline.ply is the same polyline
    page = PlyData.read(io.BytesIO(cloud_ply(rec, "spline")))
    assert page["edge"].count == len(pts) - 1


def test_ply_edges_are_checked() -> None:
    with pytest.raises(ValueError, match="index the 3 vertices"):
        ply_bytes(np.zeros((3, 3)), edges=np.array([[0, 3]]))
    with pytest.raises(ValueError, match=r"\(E, 2\) integers"):
        ply_bytes(np.zeros((3, 3)), edges=np.array([[0.0, 1.0]]))


def test_page_spline_json_is_the_cli_schema_with_preset_and_inputs(
    tmp_path: Path, schema: dict
) -> None:
    import shutil

    from test_server import FLAT, SAMPLE, url
    from test_server_workflows import CONFIGS, client_for

    data = tmp_path / "data"
    shutil.copytree(SAMPLE / "simulated" / "flat", data / "simulated" / "flat")
    with client_for(data, CONFIGS) as c:
        sid = c.post(url(FLAT, "run"), json={}).json()["session"]
        js = c.get(f"/api/sessions/{sid}/export/spline.json").json()
    jsonschema.validate(js, schema)
    assert js["preset"] == "default" and js["frame"] == "left"
    roles = {i["role"]: i["name"] for i in js["inputs"]}
    assert roles["stereo"] == "flat_1.png" and roles["calibration"] == "calibration.yaml"


def test_json_safe_converts_a_string_array_in_one_pass(monkeypatch) -> None:
    # an overlay's per-point CSS colours (~1,000 a slider move): no walk of the items
    from threadrecon.app import export

    calls: list[object] = []
    original = export.json_safe
    monkeypatch.setattr(export, "json_safe", lambda o: (calls.append(o), original(o))[1])
    colors = np.array(["#28c850", "#e62828", "#f0c828"])
    assert export.json_safe({"colors": colors}) == {"colors": ["#28c850", "#e62828", "#f0c828"]}
    assert len(calls) == 2  # the dict and the array, not each string
