"""The threadrecon CLI: outputs, exit codes and one-line errors on bad input."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from threadrecon.app.cli import main
from threadrecon.app.presets import load_preset, save_preset, validate
from threadrecon.core.pipeline import ReconParams

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_data"
FLAT = SAMPLE / "simulated" / "flat"


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_reconstruct_writes_curve_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "curve.json"
    code, _, _ = run(
        capsys,
        "reconstruct",
        "--stereo",
        FLAT / "flat_1.png",
        "--mask",
        FLAT / "flat_1_mask.png",
        "--calib",
        FLAT / "calibration.yaml",
        "--out",
        out,
    )
    data = json.loads(out.read_text())
    assert code == 0
    assert data["status"] == "ok" and data["error"] is None
    pts = np.array(data["points"])
    assert pts.shape[0] >= 200 and pts.shape[1] == 3
    assert len(data["knots"]) == len(data["control_points"]) + data["degree"] + 1
    assert set(data["timings_ms"]) >= {"stereo", "spline", "camera"}


def test_reconstruct_missing_image_is_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = run(
        capsys,
        "reconstruct",
        "--left",
        tmp_path / "nope.png",
        "--right",
        tmp_path / "nope.png",
        "--calib",
        FLAT / "calibration.yaml",
        "--out",
        tmp_path / "o.json",
    )
    assert code == 2
    assert "nope.png" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_reconstruct_unreadable_image(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    code, _, err = run(
        capsys,
        "reconstruct",
        "--stereo",
        bad,
        "--calib",
        FLAT / "calibration.yaml",
        "--out",
        tmp_path / "o.json",
    )
    assert code == 2 and "not a readable image" in err


def test_calibration_missing_key_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (FLAT / "calibration.yaml").read_text()
    start = text.index("T:")
    end = text.index("data", start)
    end = text.index("]", end) + 1
    calib = tmp_path / "calib.yaml"
    calib.write_text(text[:start] + text[end:])
    code, _, err = run(
        capsys,
        "reconstruct",
        "--stereo",
        FLAT / "flat_1.png",
        "--calib",
        calib,
        "--out",
        tmp_path / "o.json",
    )
    assert code == 2 and "missing key T" in err and str(calib) in err


def test_left_right_size_mismatch(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    img = cv2.imread(str(FLAT / "flat_1.png"))
    cv2.imwrite(str(tmp_path / "l.png"), img[:, :640])
    cv2.imwrite(str(tmp_path / "r.png"), img[:400, 640:])
    code, _, err = run(
        capsys,
        "reconstruct",
        "--left",
        tmp_path / "l.png",
        "--right",
        tmp_path / "r.png",
        "--calib",
        FLAT / "calibration.yaml",
        "--out",
        tmp_path / "o.json",
    )
    assert code == 2 and "differ in size" in err


def test_empty_segmentation_fails_with_status(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blank = np.full((480, 1280, 3), 255, np.uint8)
    cv2.imwrite(str(tmp_path / "blank.png"), blank)
    out = tmp_path / "o.json"
    code, _, err = run(
        capsys,
        "reconstruct",
        "--stereo",
        tmp_path / "blank.png",
        "--calib",
        FLAT / "calibration.yaml",
        "--out",
        out,
    )
    data = json.loads(out.read_text())
    assert code == 1
    assert data["status"] == "failed" and "empty segmentation" in data["error"]
    assert data["points"] is None and "empty segmentation" in err


def test_evaluate_sample_data_writes_one_row_per_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "data"
    shutil.copytree(FLAT, data / "simulated" / "flat")
    out = tmp_path / "res.csv"
    code, stdout, _ = run(
        capsys, "evaluate", data, "--out", out, "--save-predictions", tmp_path / "pred"
    )
    rows = list(csv.DictReader(out.open()))
    assert code == 0 and len(rows) == 4
    assert all(r["status"] == "ok" for r in rows)
    assert max(float(r["e_S_mm"]) for r in rows) < 1.0
    assert "e_S_mm" in stdout and "mean" in stdout
    assert (tmp_path / "pred" / "simulated" / "flat" / "flat_1.json").exists()


def test_bench_prints_stage_medians(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "data" / "simulated" / "flat"
    data.mkdir(parents=True)
    for name in ("calibration.yaml", "flat_1.png", "flat_1.npy", "flat_1_mask.png"):
        shutil.copy(FLAT / name, data / name)
    code, stdout, _ = run(capsys, "bench", tmp_path / "data", "--repeat", "1")
    assert code == 0
    for stage in ("stereo", "spline", "total", "spline rerun", "solver rerun"):
        assert stage in stdout


def test_evaluate_missing_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(capsys, "evaluate", tmp_path / "nothing")
    assert code == 2 and "not found" in err


def test_presets_round_trip_and_reject_bad_keys(tmp_path: Path) -> None:
    params = validate({"spline": {"n_ctrl": 12}, "reliability": {"threshold": 0.8}})
    path = save_preset(params, "mine", tmp_path)
    assert load_preset(path) == params
    with pytest.raises(FileExistsError):
        save_preset(ReconParams(), "mine", tmp_path)
    assert load_preset(path) == params  # not overwritten
    with pytest.raises(ValueError, match="stereo.nope"):
        validate({"stereo": {"nope": 1}})
    with pytest.raises(ValueError, match="reliability.threshold"):
        validate({"reliability": {"threshold": 1.5}})
    with pytest.raises(ValueError, match="invalid preset name"):
        save_preset(params, "../evil", tmp_path)


def test_bundled_presets_are_valid() -> None:
    for path in sorted((ROOT / "configs").glob("*.toml")):
        load_preset(path)
    assert load_preset(ROOT / "configs" / "default.toml") == ReconParams()


def test_xy_knots_preset_keys_are_checked_and_paper_strict_keeps_uniform_knots() -> None:
    assert load_preset(ROOT / "configs" / "paper-strict.toml").spline.xy_knots == "uniform"
    assert validate({"spline": {"xy_knots": "uniform"}}).spline.xy_knots == "uniform"
    with pytest.raises(ValueError, match="spline.xy_knots"):
        validate({"spline": {"xy_knots": "curvature"}})
    with pytest.raises(ValueError, match="spline.xy_tol_px"):
        validate({"spline": {"xy_tol_px": 0.0}})


def test_bench_runs_on_a_plain_folder_with_overrides(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for name in ("calibration.yaml", "flat_1.png", "flat_1_mask.png"):
        shutil.copy(FLAT / name, tmp_path / name)
    code, stdout, _ = run(
        capsys, "bench", tmp_path, "--repeat", "2", "--set", "stereo.z_near_mm=40"
    )
    assert code == 0
    assert "1 frames (640x480)" in stdout
    assert "p90" in stdout and "peak RSS" in stdout
    code, _, err = run(capsys, "bench", tmp_path, "--set", "stereo.nothing=1")
    assert code == 2 and "stereo.nothing" in err
    code, _, err = run(capsys, "bench", tmp_path, "--set", "stereo.z_near_mm=-5")
    assert code == 2 and "z_near_mm" in err


def test_reconstruct_suspect_frame_exits_3_with_reasons_in_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 11: tissue_2 without its mask came back "ok", 879 m long, exit code 0 (with the
    grey threshold, the segmentation of the time; the raw-frame default now finds the thread)."""
    tissue = SAMPLE / "simulated" / "tissue"
    out = tmp_path / "t.json"
    grey = tmp_path / "grey.toml"
    grey.write_text('[segment]\nmethod = "threshold"\n')
    code, _, err = run(
        capsys,
        "reconstruct",
        "--stereo",
        tissue / "tissue_2.png",
        "--calib",
        tissue / "calibration.yaml",
        "--config",
        grey,
        "--out",
        out,
    )
    data = json.loads(out.read_text())
    assert data["status"] in ("suspect", "failed")
    assert code == {"suspect": 3, "failed": 1}[data["status"]]
    assert data["reasons"] and data["reasons"][0] in err


def test_reconstruct_ok_json_has_confidence_grasp_and_score(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "c.json"
    args = ["--stereo", FLAT / "flat_2.png", "--mask", FLAT / "flat_2_mask.png"]
    code, _, _ = run(
        capsys, "reconstruct", *args, "--calib", FLAT / "calibration.yaml", "--out", out
    )
    data = json.loads(out.read_text())
    assert code == 0 and data["status"] == "ok" and data["reasons"] == []
    assert len(data["confidence"]) == len(data["points"])
    assert data["grasp"]["point"] == data["points"][data["grasp"]["index"]]
    assert 1 <= data["score"] <= 5 and "coverage_left" in data["check"]
    assert 1.0 <= data["rating"] <= 5.0 and abs(data["rating"] - data["score"]) <= 0.5


def test_non_finite_values_are_written_as_null(tmp_path: Path) -> None:
    """A diverged curve still gets its JSON (status, reasons), non-finite numbers as null."""
    from threadrecon.app.export import write_json as _write_json

    path = tmp_path / "n.json"
    _write_json(path, {"status": "failed", "reasons": ["x"], "points": [[np.nan, np.inf, 1.0]]})
    assert json.loads(path.read_text())["points"] == [[None, None, 1.0]]


def test_evaluate_never_aborts_on_a_nan_ground_truth_or_n_ctrl_80(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 11: a NaN in a ground-truth file, or n_ctrl = 80, aborted the whole run."""
    data = tmp_path / "data" / "simulated" / "flat"
    shutil.copytree(FLAT, data)
    gt = np.load(data / "flat_1.npy")
    gt[2, 1] = np.nan
    np.save(data / "flat_1.npy", gt)
    out = tmp_path / "res.csv"
    code, _, err = run(capsys, "evaluate", tmp_path / "data", "--out", out)
    rows = {r["frame"]: r for r in csv.DictReader(out.open())}
    assert len(rows) == 4 and code == 1 and "1 of 4 frames failed" in err
    assert rows["simulated/flat/flat_1"]["status"] == "failed"
    assert rows["simulated/flat/flat_1"]["error"]
    preset = tmp_path / "p.toml"
    preset.write_text("[spline]\nn_ctrl = 80\n")
    code, _, _ = run(capsys, "evaluate", tmp_path / "data", "--out", out, "--config", preset)
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 4 and all(r["status"] in ("ok", "suspect", "failed") for r in rows)
