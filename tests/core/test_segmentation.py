"""Tests of core/segmentation.py: input pair checks, thresholding and lifting, Eq. (1)."""

import re

import numpy as np
import pytest
from support import assert_close

from core.segmentation import (
    LIFT_VALUE,
    SegmentationParams,
    StereoPair,
    segment,
    split_side_by_side,
)

BG, INK = 200, 60


def _line_pair(shift: int = 3) -> StereoPair:
    """Flat background BG with a dark 2-px line (rows 20-21) in both views, shifted by ``shift``."""
    left = np.full((48, 64), BG, np.uint8)
    right = left.copy()
    left[20:22, 10:50] = INK
    right[20:22, 10 - shift : 50 - shift] = INK
    return StereoPair(left, right)


def test_background_level_is_estimated_and_line_segmented() -> None:
    pair = _line_pair()
    lifted = segment(pair, SegmentationParams(lift_dilate_px=0))
    assert lifted.background == (BG, BG)
    expected = np.zeros((48, 64), bool)
    expected[20:22, 10:50] = True
    assert_close(lifted.P_L, expected)
    assert_close(lifted.P_R, np.roll(expected, -3, axis=1))


def test_rgb_input_is_segmented_like_grey() -> None:
    pair = _line_pair()
    rgb = StereoPair(
        np.repeat(pair.left[:, :, None], 3, 2), np.repeat(pair.right[:, :, None], 3, 2)
    )
    assert_close(segment(rgb).P_L, segment(pair).P_L)


def test_lifting_sets_255_outside_the_mask_eq1() -> None:
    pair = _line_pair()
    lifted = segment(pair, SegmentationParams(lift_dilate_px=0))
    grey = pair.left.astype(np.float32)
    assert lifted.I_L.dtype == np.float32
    assert_close(lifted.I_L[lifted.P_L], grey[lifted.P_L])
    assert np.all(lifted.I_L[~lifted.P_L] == LIFT_VALUE)


@pytest.mark.parametrize("dilate", [1, 2])
def test_lifting_keeps_intensities_on_the_dilated_mask(dilate: int) -> None:
    pair = _line_pair()
    lifted = segment(pair, SegmentationParams(lift_dilate_px=dilate))
    rows, cols = np.nonzero(lifted.P_L)
    yy, xx = np.mgrid[:48, :64]
    # Chebyshev distance of every pixel to the mask (square structuring element).
    dist = np.min(np.maximum(np.abs(yy[..., None] - rows), np.abs(xx[..., None] - cols)), axis=-1)
    near = dist <= dilate
    assert_close(lifted.I_L[near], pair.left.astype(np.float32)[near])
    assert np.all(lifted.I_L[~near] == LIFT_VALUE)


def test_given_masks_replace_thresholding() -> None:
    pair = _line_pair()
    mask = np.zeros((48, 64), bool)
    mask[5:8, 5:9] = True
    masked = StereoPair(pair.left, pair.right, mask, mask)
    lifted = segment(masked, SegmentationParams(lift_dilate_px=0))
    assert_close(lifted.P_L, mask)
    assert_close(lifted.P_R, mask)


def test_empty_segmentation_raises() -> None:
    blank = np.full((32, 32, 3), 255, np.uint8)
    with pytest.raises(ValueError, match="empty segmentation"):
        segment(StereoPair(blank, blank.copy()))


def test_specks_below_min_component_are_dropped() -> None:
    pair = _line_pair()
    left = pair.left.copy()
    left[40, 5] = INK  # a 1-px speck
    lifted = segment(StereoPair(left, pair.right), SegmentationParams(min_component_px=4))
    assert not lifted.P_L[40, 5]
    assert lifted.P_L[20, 20]


def test_size_mismatch_names_both_sizes() -> None:
    with pytest.raises(ValueError, match=r"\(20, 30\).*\(20, 32\)"):
        StereoPair(np.zeros((20, 30), np.uint8), np.zeros((20, 32), np.uint8))


@pytest.mark.parametrize("shape", [(10,), (10, 10, 2), (4, 5, 6, 3)])
def test_wrong_image_shape_names_the_shape(shape: tuple[int, ...]) -> None:
    bad = np.zeros(shape, np.uint8)
    good = np.zeros((10, 10), np.uint8)
    with pytest.raises(ValueError, match=r"left image.*" + re.escape(repr(shape))):
        StereoPair(bad, good)


def test_mask_shape_is_checked() -> None:
    img = np.zeros((16, 16), np.uint8)
    with pytest.raises(ValueError, match="mask_left"):
        StereoPair(img, img, np.zeros((8, 8), bool), np.zeros((16, 16), bool))
    with pytest.raises(ValueError, match="both masks"):
        StereoPair(img, img, np.zeros((16, 16), bool), None)


def test_split_side_by_side_halves_and_rejects_odd_width() -> None:
    img = np.arange(6 * 10).reshape(6, 10)
    left, right = split_side_by_side(img)
    assert_close(left, img[:, :5])
    assert_close(right, img[:, 5:])
    with pytest.raises(ValueError, match=r"even width.*\(6, 11\)"):
        split_side_by_side(np.zeros((6, 11)))
