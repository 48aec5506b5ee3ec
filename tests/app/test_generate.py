"""Tests of ``threadrecon generate`` (app/generate.py): layout, README, overwrite rules."""

import argparse
from pathlib import Path

import cv2
import numpy as np
import pytest

from threadrecon.app import generate
from threadrecon.core.synthetic import RenderParams, SyntheticParams, ThreadParams, generate_frame


def _parse(*argv: str) -> argparse.Namespace:
    """Parse through a main-CLI-like parser, as app/cli.py registers the subcommand."""
    parser = argparse.ArgumentParser(prog="threadrecon")
    generate.add_parser(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(["generate", *argv])


def _run(*argv: str) -> int:
    args = _parse(*argv)
    return args.func(args)


def test_generate_writes_the_paper_dataset_layout(tmp_path: Path) -> None:
    assert _run(str(tmp_path), "--count", "2", "--seed", "5") == 0
    group = tmp_path / "simulated" / "flat"
    assert sorted(p.name for p in group.iterdir()) == [
        "calibration.yaml",
        "flat_1.npy",
        "flat_1.png",
        "flat_1_mask.png",
        "flat_2.npy",
        "flat_2.png",
        "flat_2_mask.png",
    ]
    expected = generate_frame(SyntheticParams(), np.random.default_rng([5, 1]))
    pair = cv2.imread(str(group / "flat_1.png"), cv2.IMREAD_COLOR)
    assert pair.shape == (480, 1280, 3)
    rgb = cv2.cvtColor(pair, cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(rgb[:, :640], expected.left)
    np.testing.assert_array_equal(rgb[:, 640:], expected.right)
    mask = cv2.imread(str(group / "flat_1_mask.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (480, 1280) and set(np.unique(mask).tolist()) == {0, 255}
    np.testing.assert_array_equal(mask[:, :640] > 0, expected.mask_left)
    np.testing.assert_array_equal(mask[:, 640:] > 0, expected.mask_right)
    ctrl = np.load(group / "flat_1.npy")
    assert ctrl.dtype == np.float64 and ctrl.ndim == 2 and ctrl.shape[1] == 3
    np.testing.assert_array_equal(ctrl, expected.truth.control_points)


def test_calibration_yaml_reads_back_with_opencv(tmp_path: Path) -> None:
    _run(str(tmp_path), "--count", "1")
    fs = cv2.FileStorage(str(tmp_path / "simulated" / "flat" / "calibration.yaml"), 0)
    k1 = fs.getNode("K1").mat()
    np.testing.assert_allclose(k1, [[890, 0, 320], [0, 890, 240], [0, 0, 1]])
    np.testing.assert_allclose(fs.getNode("K2").mat(), k1)
    np.testing.assert_allclose(fs.getNode("D1").mat(), np.zeros((1, 5)))
    np.testing.assert_allclose(fs.getNode("D2").mat(), np.zeros((1, 5)))
    np.testing.assert_allclose(fs.getNode("R").mat(), np.eye(3))
    np.testing.assert_allclose(fs.getNode("T").mat().ravel(), [-5.0, 0.0, 0.0])
    np.testing.assert_allclose(fs.getNode("ImageSize").mat(), [[480, 640]])
    assert fs.getNode("Units").string() == "mm"
    fs.release()


def test_readme_records_the_command_of_every_group(tmp_path: Path) -> None:
    _run(str(tmp_path), "--count", "1", "--seed", "3", "--background", "tissue", "--noise", "2")
    _run(str(tmp_path), "--count", "1", "--seed", "4", "--crossing")
    text = (tmp_path / "README.md").read_text()
    assert "--count 1 --seed 3 --background tissue --noise 2" in text
    assert "--seed 4 --background flat" in text and "--crossing" in text
    assert "## simulated/tissue" in text and "## simulated/crossing" in text
    assert "| tissue_1 |" in text and "| crossing_1 |" in text
    assert "millimetres" in text
    # Regenerating one group replaces its section and keeps the other.
    _run(str(tmp_path), "--count", "1", "--seed", "9", "--crossing", "--force")
    text = (tmp_path / "README.md").read_text()
    assert (
        text.count("## simulated/crossing") == 1 and "--seed 9" in text and "--seed 4" not in text
    )
    assert "## simulated/tissue" in text


def test_default_group_follows_background_and_crossing(tmp_path: Path) -> None:
    _run(str(tmp_path), "--count", "1", "--background", "tissue")
    _run(str(tmp_path), "--count", "1", "--crossing")
    _run(str(tmp_path), "--count", "1", "--group", "mine", "--occlusion")
    for name in ("tissue/tissue_1.png", "crossing/crossing_1.png", "mine/mine_1_mask.png"):
        assert (tmp_path / "simulated" / name).is_file()


def test_spiral_flag_writes_a_spiral_group_and_records_the_flag(tmp_path: Path) -> None:
    _run(str(tmp_path), "--count", "1", "--seed", "3", "--spiral")
    truth = np.load(tmp_path / "simulated" / "spiral" / "spiral_1.npy")
    assert truth.shape[1] == 3 and len(truth) >= 8 * 1.5  # 8 control points per turn
    text = (tmp_path / "README.md").read_text(encoding="utf-8")
    assert "--spiral" in text and "spiral True" in text


def test_refuses_to_overwrite_existing_frames_unless_forced(tmp_path: Path) -> None:
    _run(str(tmp_path), "--count", "1")
    image = tmp_path / "simulated" / "flat" / "flat_1.png"
    before = image.read_bytes()
    with pytest.raises(ValueError, match="flat_1.png"):
        _run(str(tmp_path), "--count", "1", "--seed", "1")
    assert image.read_bytes() == before
    assert _run(str(tmp_path), "--count", "1", "--seed", "1", "--force") == 0
    assert image.read_bytes() != before


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (("--count", "0"), "--count"),
        (("--seed", "-1"), "--seed"),
        (("--noise", "-1"), "--noise"),
        (("--blur", "-2"), "--blur"),
        (("--diameter-mm", "0"), "--diameter-mm"),
        (("--length-mm", "80", "40"), "--length-mm"),
        (("--length-mm", "500", "600", "--depth-mm", "20", "30"), "--length-mm"),
        (("--group", "../escape"), "--group"),
        (("--spiral", "--hairpin"), "--spiral"),
    ],
)
def test_bad_settings_raise_value_error_naming_the_flag(
    tmp_path: Path, argv: tuple[str, ...], flag: str
) -> None:
    with pytest.raises(ValueError, match=flag):
        _run(str(tmp_path / "out"), *argv)
    assert not (tmp_path / "out" / "simulated").exists()


def test_module_main_reports_errors_in_one_line_with_exit_code_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert generate.main([str(tmp_path), "--count", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "--count" in err and "\n" not in err


def test_written_settings_match_the_core_parameters(tmp_path: Path) -> None:
    _run(str(tmp_path), "--count", "1", "--seed", "2", "--leaves-image", "--blur", "0.8")
    params = SyntheticParams(
        thread=ThreadParams(leaves_image=True), render=RenderParams(blur_sigma=0.8)
    )
    expected = generate_frame(params, np.random.default_rng([2, 1]))
    ctrl = np.load(tmp_path / "simulated" / "flat" / "flat_1.npy")
    np.testing.assert_array_equal(ctrl, expected.truth.control_points)


def test_generate_size_scales_the_intrinsics(tmp_path: Path) -> None:
    assert _run(str(tmp_path), "--count", "1", "--size", "1280x960") == 0
    group = tmp_path / "simulated" / "flat"
    pair = cv2.imread(str(group / "flat_1.png"), cv2.IMREAD_COLOR)
    assert pair.shape == (960, 2560, 3)
    fs = cv2.FileStorage(str(group / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    K = fs.getNode("K1").mat()
    fs.release()
    base = generate.StereoCamera()
    assert_k = np.array([[2 * base.fx, 0, 2 * base.cx], [0, 2 * base.fx, 2 * base.cy], [0, 0, 1]])
    assert np.allclose(K, assert_k)
    assert "--size 1280x960" in (tmp_path / "README.md").read_text()
    with pytest.raises(SystemExit):
        _parse(str(tmp_path), "--size", "1280by960")


def test_realism_flags_reach_the_renderer_and_no_mask_writes_none(tmp_path: Path) -> None:
    argv = [str(tmp_path), "--count", "1", "--seed", "3", "--background", "tissue"]
    flags = ["--thread-colour", "blue", "--distractors", "4", "--instrument", "--lighting", "0.4"]
    assert _run(*argv, *flags, "--specular", "0.3", "--no-mask", "--group", "raw") == 0
    group = tmp_path / "simulated" / "raw"
    assert sorted(p.name for p in group.iterdir()) == ["calibration.yaml", "raw_1.npy", "raw_1.png"]
    render = RenderParams(
        background="tissue",
        thread_colour="blue",
        distractors=4,
        instrument=True,
        lighting=0.4,
        specular=0.3,
    )
    expected = generate_frame(SyntheticParams(render=render), np.random.default_rng([3, 1]))
    pair = cv2.cvtColor(cv2.imread(str(group / "raw_1.png"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(pair, np.hstack([expected.left, expected.right]))
    readme = (tmp_path / "README.md").read_text()
    assert "--thread-colour blue" in readme and "--no-mask" in readme


def test_jpeg_flag_writes_the_pair_as_jpeg_once(tmp_path: Path) -> None:
    assert _run(str(tmp_path), "--count", "1", "--seed", "2", "--jpeg", "80") == 0
    group = tmp_path / "simulated" / "flat"
    assert (group / "flat_1.jpg").exists() and not (group / "flat_1.png").exists()
    expected = generate_frame(SyntheticParams(), np.random.default_rng([2, 1]))
    pair = cv2.cvtColor(cv2.imread(str(group / "flat_1.jpg"), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    err = np.abs(pair.astype(int) - np.hstack([expected.left, expected.right]).astype(int))
    assert 0 < err.mean() < 3


@pytest.mark.parametrize(
    ("flags", "flag"),
    [
        (["--background", "flat", "--distractors", "2"], "--distractors"),
        (["--jpeg", "101"], "--jpeg"),
    ],
)
def test_bad_realism_flags_are_named(tmp_path: Path, flags: list[str], flag: str) -> None:
    with pytest.raises(ValueError, match=flag):
        _run(str(tmp_path), *flags)
