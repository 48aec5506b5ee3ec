"""Masks of every folder layout (a complement to test_dataset.py): a mask of the wrong size,
an unreadable mask or one that is not an image is an error naming the file, never a crash or
a mask silently cropped; masks beside the images of a ``real/`` folder and of a flat folder
reach the pipeline as given."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from support import synthetic_frame, write_calibration, write_png

from threadrecon.app.dataset import discover, load_frame
from threadrecon.core.pipeline import reconstruct


def test_masks_of_a_real_folder_are_the_segmentation(tmp_path: Path) -> None:
    f = synthetic_frame(1)
    sub = tmp_path / "real" / "thread_2_seg"
    write_png(sub / "thread2_left_7_final.png", f.left)
    write_png(sub / "thread2_right_7_final.png", f.right)
    # a partial mask: the run must use it as given, not segment the image again
    half = f.mask_left.copy()
    half[:, : half.shape[1] // 2] = False
    write_png(sub / "thread2_left_7_final_mask.png", half)
    write_png(sub / "thread2_right_7_final_mask.png", f.mask_right)
    write_calibration(tmp_path / "real", "camera_calibration.yaml")
    (frame,) = discover(tmp_path)
    assert frame.kind == "real" and frame.mask_left is not None
    pair, calib, _ = load_frame(frame)
    rec = reconstruct(pair, calib)
    seg = rec["segment"]
    assert seg.method == "mask"
    assert np.array_equal(seg.P_L, half) and np.array_equal(seg.P_R, f.mask_right)


@pytest.mark.parametrize("layout", ["composite", "views"])
def test_a_mask_of_the_wrong_size_names_the_file(tmp_path: Path, layout: str) -> None:
    f = synthetic_frame(0)
    if layout == "composite":
        write_png(tmp_path / "a.png", np.hstack([f.left, f.right]))
        bad = write_png(tmp_path / "a_mask.png", np.zeros((480, 1278), bool))
        size = "1278x480"
    else:
        write_png(tmp_path / "a_L.png", f.left)
        write_png(tmp_path / "a_R.png", f.right)
        write_png(tmp_path / "a_L_mask.png", f.mask_left)
        bad = write_png(tmp_path / "a_R_mask.png", np.zeros((240, 320), bool))
        size = "320x240"
    write_calibration(tmp_path)
    (frame,) = discover(tmp_path)
    with pytest.raises(ValueError, match=rf"{bad.name}: the mask is {size} px but the .* is"):
        load_frame(frame)


def test_a_mask_that_is_not_an_image_names_the_file(tmp_path: Path) -> None:
    f = synthetic_frame(0)
    write_png(tmp_path / "a.png", np.hstack([f.left, f.right]))
    (tmp_path / "a_mask.png").write_bytes(b"not a png")
    write_calibration(tmp_path)
    (frame,) = discover(tmp_path)
    with pytest.raises(ValueError, match="a_mask.png: not a readable image"):
        load_frame(frame)
