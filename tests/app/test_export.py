"""Exports of a reconstruction: spline JSON/CSV and PLY clouds read back equal what was stored."""

from __future__ import annotations

import csv
import io
import json

import numpy as np
import pytest
from support import assert_close, synthetic_case

from app.export import (
    LAYERS,
    SPLINE_END_RGB,
    SPLINE_START_RGB,
    cloud_ply,
    json_safe,
    ply_bytes,
    reliability_colors,
    spline_csv,
    spline_json,
)
from core.pipeline import Pipeline, Reconstruction, reconstruct
from core.segmentation import StereoPair


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
    """A minimal reader of the binary PLY that ply_bytes writes: header lines and vertices."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    n = int(next(line for line in header if line.startswith("element vertex")).split()[-1])
    types = {"float": "<f4", "uchar": "u1"}
    props = [line.split() for line in header if line.startswith("property")]
    dtype = np.dtype([(name, types[t]) for _, t, name in props])
    assert len(data) - end == n * dtype.itemsize
    return header, np.frombuffer(data, dtype=dtype, offset=end)


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
    assert rows[0] == ["i", "x_mm", "y_mm", "z_mm"]
    body = np.array(rows[1:], dtype=float)
    np.testing.assert_array_equal(body[:, 0], np.arange(len(rec["camera"].points)))
    np.testing.assert_array_equal(body[:, 1:], rec["camera"].points)  # exact round trip


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
