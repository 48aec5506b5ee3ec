"""Tests of app/dataset.py: every documented folder layout is a dataset, with its masks,
ground truth and calibration found by name; frame ids are unique and stable."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from rig_support import opencv_yaml, raw_rig, ros_camera_info
from support import assert_close, calibration_for, synthetic_frame, write_calibration, write_png

from threadrecon.app.dataset import discover, load_frame, reprojections
from threadrecon.core.metrics import project, reprojection_errors
from threadrecon.core.rectify import rectification, rectify_pair


def _write_pair(folder: Path, left: str, right: str, masks: bool = True, seed: int = 0) -> None:
    f = synthetic_frame(seed)
    lp, rp = write_png(folder / left, f.left), write_png(folder / right, f.right)
    if masks:
        write_png(lp.with_name(lp.stem + "_mask.png"), f.mask_left)
        write_png(rp.with_name(rp.stem + "_mask.png"), f.mask_right)


def _check_loaded(frame, with_masks: bool = True) -> None:  # type: ignore[no-untyped-def]
    pair, calib, gt = load_frame(frame)
    f = synthetic_frame(0)
    assert_close(pair.left, f.left)
    assert_close(pair.right, f.right)
    if with_masks:
        assert pair.mask_left is not None and pair.mask_right is not None
        assert_close(pair.mask_left, f.mask_left)
        assert_close(pair.mask_right, f.mask_right)
    else:
        assert pair.mask_left is None
    assert calib.image_size == (480, 640)


def test_side_by_side_with_mask_ground_truth_and_folder_calibration(tmp_path: Path) -> None:
    f = synthetic_frame(0)
    write_png(tmp_path / "run1" / "a.png", np.hstack([f.left, f.right]))
    write_png(tmp_path / "run1" / "a_mask.png", np.hstack([f.mask_left, f.mask_right]))
    np.save(tmp_path / "run1" / "a.npy", f.truth.control_points)
    write_calibration(tmp_path)  # in the root: found from run1/ by walking up
    (frame,) = discover(tmp_path)
    assert frame.id == "run1/a" and frame.kind == "simulated"
    assert frame.calibration == tmp_path / "calibration.yaml"
    _check_loaded(frame)


def test_left_right_folders_pair_by_name(tmp_path: Path) -> None:
    d = tmp_path / "seq"
    for name in ("0001.png", "0002.png"):
        f = synthetic_frame(0)
        write_png(d / "left" / name, f.left)
        write_png(d / "right" / name, f.right)
        write_png(d / "left" / name.replace(".png", "_mask.png"), f.mask_left)
        write_png(d / "right" / name.replace(".png", "_mask.png"), f.mask_right)
    write_png(d / "left" / "0003.png", synthetic_frame(0).left)  # no right view: not a frame
    np.save(d / "0001.npy", synthetic_frame(0).truth.control_points)
    write_calibration(d)
    frames = discover(tmp_path)
    assert [fr.id for fr in frames] == ["seq/0001", "seq/0002"]
    assert frames[0].kind == "simulated" and frames[1].kind == "real"
    _check_loaded(frames[0])


@pytest.mark.parametrize(
    ("left", "right", "fid"),
    [
        ("thread1_left_99_final.png", "thread1_right_99_final.png", "thread1_99_final"),
        ("Left_img.png", "Right_img.png", "_img"),
        ("003_L.png", "003_R.png", "003"),
        ("cam_left.jpg", "cam_right.jpg", "cam_"),
    ],
)
def test_left_right_names_in_a_flat_folder_with_masks(
    tmp_path: Path, left: str, right: str, fid: str
) -> None:
    _write_pair(tmp_path, left, right)
    write_calibration(tmp_path)
    (frame,) = discover(tmp_path)
    assert frame.id == fid and frame.left is not None and frame.left.name == left
    assert frame.mask_left is not None and frame.mask_right is not None
    if left.endswith(".png"):  # jpeg is lossy: pixels are not compared
        _check_loaded(frame)


def test_paper_style_real_folder_reads_masks_beside_each_view(tmp_path: Path) -> None:
    sub = tmp_path / "real" / "thread_1_seg"
    _write_pair(sub, "thread1_left_99_final.png", "thread1_right_99_final.png")
    write_calibration(tmp_path / "real", "camera_calibration.yaml")
    (frame,) = discover(tmp_path)
    assert frame.id == "real/thread_1_seg/thread1_99_final"  # the id the old reader gave
    _check_loaded(frame)


def test_mask_of_one_view_only_is_ignored(tmp_path: Path) -> None:
    _write_pair(tmp_path, "a_L.png", "a_R.png", masks=False)
    write_png(tmp_path / "a_L_mask.png", synthetic_frame(0).mask_left)
    write_calibration(tmp_path)
    (frame,) = discover(tmp_path)
    assert frame.mask_left is None and frame.mask_right is None
    _check_loaded(frame, with_masks=False)


def test_calibration_per_frame_wins_over_the_folder(tmp_path: Path) -> None:
    _write_pair(tmp_path, "a_L.png", "a_R.png")
    _write_pair(tmp_path, "b_L.png", "b_R.png")
    write_calibration(tmp_path)
    own = write_calibration(tmp_path, "b.calib.yaml")
    a, b = discover(tmp_path)
    assert a.calibration == tmp_path / "calibration.yaml" and b.calibration == own


def test_ros_camera_info_pair_as_folder_calibration(tmp_path: Path) -> None:
    _write_pair(tmp_path, "a_L.png", "a_R.png")
    left, right = ros_camera_info(calibration_for(synthetic_frame(0).camera))
    (tmp_path / "left.yaml").write_text(yaml.safe_dump(left))
    (tmp_path / "right.yaml").write_text(yaml.safe_dump(right))
    (frame,) = discover(tmp_path)
    assert frame.calibration.name == "left.yaml" and frame.calibration_right is not None
    _, calib, _ = load_frame(frame)
    ref = calibration_for(synthetic_frame(0).camera)
    assert calib.unit == "m"  # ROS lengths are metres unless told
    assert_close(calib.baseline, ref.baseline, rtol=1e-9)


def test_frame_ids_are_unique_or_an_error_names_both_files(tmp_path: Path) -> None:
    f = synthetic_frame(0)
    write_png(tmp_path / "a.png", np.hstack([f.left, f.right]))
    _write_pair(tmp_path, "a_L.png", "a_R.png", masks=False)  # id "a" again
    write_calibration(tmp_path)
    with pytest.raises(ValueError, match=r"two frames have the id 'a': .*a_L\.png and .*a\.png"):
        discover(tmp_path)


def test_ids_are_stable_and_sorted(tmp_path: Path) -> None:
    for name in ("z", "b", "m"):
        _write_pair(tmp_path / name, "x_L.png", "x_R.png", masks=False)
    write_calibration(tmp_path)
    first = [fr.id for fr in discover(tmp_path)]
    assert first == ["b/x", "m/x", "z/x"] == [fr.id for fr in discover(tmp_path)]


def test_empty_or_missing_folder_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("nothing here")
    with pytest.raises(FileNotFoundError, match="no frames found"):
        discover(tmp_path)
    with pytest.raises(FileNotFoundError, match="dataset folder not found"):
        discover(tmp_path / "nope")


def test_missing_calibration_is_named_when_the_frame_loads(tmp_path: Path) -> None:
    _write_pair(tmp_path, "a_L.png", "a_R.png", masks=False)
    (frame,) = discover(tmp_path)
    with pytest.raises(ValueError, match="calibration.yaml"):
        load_frame(frame)


def test_raw_frame_is_rectified_on_load_with_ground_truth_in_the_rectified_frame(
    tmp_path: Path,
) -> None:
    rig = raw_rig(0)
    write_png(tmp_path / "a_L.png", rig.pair.left)
    write_png(tmp_path / "a_R.png", rig.pair.right)
    np.save(tmp_path / "a.npy", rig.frame.truth.control_points @ rig.Ra1.T)  # left frame
    (tmp_path / "calibration.yaml").write_text(opencv_yaml(rig.calib))
    (frame,) = discover(tmp_path)
    pair, calib, gt = load_frame(frame)
    rect = rectification(rig.calib)
    assert calib.rectified is True
    assert not np.array_equal(pair.left, rig.pair.left)  # remapped
    assert gt is not None
    # ground truth in the rectified frame: the truth of the reference, rotated by R1 Ra1
    ref_truth = rig.frame.truth.centerline @ (rect.R1 @ rig.Ra1).T
    assert np.abs(gt[0] - ref_truth[0]).max() < 1e-6


def test_debugger_library_holds_the_rectified_pair_of_a_raw_frame(tmp_path: Path) -> None:
    from threadrecon.app.session import FrameLibrary

    rig = raw_rig(0)
    write_png(tmp_path / "a_L.png", rig.pair.left)
    write_png(tmp_path / "a_R.png", rig.pair.right)
    (tmp_path / "calibration.yaml").write_text(opencv_yaml(rig.calib))
    loaded = FrameLibrary(tmp_path).load("a")
    expected = rectify_pair(rig.pair, rectification(rig.calib))
    np.testing.assert_array_equal(loaded.pair.left, expected.left)  # what the page shows
    np.testing.assert_array_equal(loaded.pair.right, expected.right)
    assert loaded.calib.rectified is True


def test_reprojections_remember_errors_by_the_pixels_and_the_mask() -> None:
    """The metrics and the spline overlay share one computation of a curve's errors; a moved
    curve or another mask gets its own."""
    calib = calibration_for(synthetic_frame(3).camera)
    pts = np.column_stack([np.linspace(-5, 5, 40), np.zeros(40), np.full(40, 60.0)])
    h, w = calib.image_size
    masks = [np.zeros((h, w), bool) for _ in range(2)]
    masks[0][h // 2 - 1 : h // 2 + 2, :] = True
    masks[1][h // 2 + 5 : h // 2 + 8, :] = True

    class Lifted:
        P_L, P_R = masks

    first = reprojections(pts, calib, Lifted)
    assert reprojections(pts, calib, Lifted)["left"][1] is first["left"][1]
    for side, P, mask in (("left", calib.P1, masks[0]), ("right", calib.P2, masks[1])):
        assert first[side][1] == reprojection_errors(project(pts, P), mask)
    moved = pts + np.array([0.0, 1.0, 0.0])
    assert reprojections(moved, calib, Lifted)["left"][1] == reprojection_errors(
        project(moved, calib.P1), masks[0]
    )
    Lifted.P_L = masks[1].copy()
    assert reprojections(pts, calib, Lifted)["left"][1] == reprojection_errors(
        project(pts, calib.P1), masks[1]
    )


def test_blender_calibrations_are_pixel_centred_and_others_are_read_as_written(
    tmp_path: Path,
) -> None:
    """The paper's Blender calibration (``blend_calibration*.yaml``) measures its principal
    point from the first pixel's outer corner: on load both cameras' principal points move by
    half a pixel (OpenCV counts from the pixel's centre); focal length, baseline and every
    other calibration are untouched."""
    from dataclasses import replace

    from threadrecon.app.dataset import frame_calibration
    from threadrecon.app.io import load_calibration

    _write_pair(tmp_path, "a_L.png", "a_R.png")
    write_calibration(tmp_path)
    (frame,) = discover(tmp_path)
    for name in ("blend_calibration_new.yaml", "calibration.yaml"):
        written = write_calibration(tmp_path, name)
        loaded = frame_calibration(replace(frame, calibration=written))
        raw = load_calibration(written, unit=loaded.unit)
        shift = 0.5 if name.startswith("blend") else 0.0
        for P, P_raw in ((loaded.P1, raw.P1), (loaded.P2, raw.P2)):
            np.testing.assert_allclose(P[:2, 2], P_raw[:2, 2] - shift, atol=1e-4)
            assert P[0, 0] == P_raw[0, 0] and P[1, 1] == P_raw[1, 1]
        assert_close(loaded.baseline, raw.baseline)
        assert rectification(loaded).identity  # still a rectified pair: nothing resampled
