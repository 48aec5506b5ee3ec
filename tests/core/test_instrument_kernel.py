"""Tests of core/instrument_kernel.py: each kernel gives exactly the numpy/cv2 steps it
replaces in core/instrument.py."""

import cv2
import numpy as np
import pytest
from support import random_mask

from threadrecon.core.instrument_kernel import label_lookup, ridge_values

_SHAPES = [(1, 1), (1, 7), (7, 1), (2, 3), (37, 51), (120, 160)]


def _mask(shape: tuple[int, int], seed: int) -> np.ndarray:
    """A random uint8 mask: speckle, or blobs and strips, by seed."""
    return random_mask(shape, seed, fill=(0.1, 0.95), close_px=5)


@pytest.mark.parametrize("shape", _SHAPES)
@pytest.mark.parametrize("seed", range(4))
def test_label_lookup_is_the_fancy_index_of_the_table(shape: tuple[int, int], seed: int) -> None:
    m = _mask(shape, seed)
    n, labels = cv2.connectedComponents(m, connectivity=8, ltype=cv2.CV_32S)
    table = np.random.default_rng(seed).random(n) < 0.5
    got = label_lookup(labels, table)
    assert got.dtype == np.uint8
    np.testing.assert_array_equal(got, table[labels].view(np.uint8))


@pytest.mark.parametrize("shape", _SHAPES)
@pytest.mark.parametrize("seed", range(6))
def test_ridge_values_are_the_distances_on_the_dilation_maximum(
    shape: tuple[int, int], seed: int
) -> None:
    """dist[(u8 > 0) & (dist >= cv2.dilate(dist, 3 x 3))], in the same (row-major) order, for
    cv2's precise distances (ties and the image's edge included) and for arbitrary values."""
    u8 = _mask(shape, seed + 10)
    dist = cv2.distanceTransform(u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    if seed % 3 == 2:  # arbitrary values, with many ties
        dist = np.round(np.random.default_rng(seed).random(shape) * 4).astype(np.float32)
    want = dist[(u8 > 0) & (dist >= cv2.dilate(dist, np.ones((3, 3), np.uint8)))]
    got = ridge_values(dist, u8)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want)


def test_ridge_values_of_no_piece_are_empty() -> None:
    assert ridge_values(np.zeros((4, 5), np.float32), np.zeros((4, 5), np.uint8)).shape == (0,)


@pytest.mark.parametrize("seed", range(12))
def test_corners_on_the_box_are_those_of_the_whole_image(seed: int) -> None:
    """instrument._corners on the bounding box of ``rest`` (and a 1 px margin) equals the same
    steps on the whole image (pieces touching the image's edge included)."""
    from threadrecon.core import instrument

    rng = np.random.default_rng([5, seed])
    shape = (int(rng.integers(3, 90)), int(rng.integers(3, 90)))
    rest = (rng.random(shape) < rng.uniform(0.02, 0.4)).astype(np.uint8)
    if seed % 3 == 0:  # pieces in a corner only: a small box
        rest[shape[0] // 3 :, :] = 0
        rest[:, shape[1] // 3 :] = 0
    removed = (rng.random(shape) < 0.2).astype(np.uint8) & (1 - rest)
    size = int(rng.integers(1, 8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(rest, connectivity=8)
    near = np.zeros(n, bool)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    near[labels[cv2.dilate(removed, cross) > 0]] = True
    small = (stats[:, cv2.CC_STAT_WIDTH] <= size) & (stats[:, cv2.CC_STAT_HEIGHT] <= size)
    drop = near & small
    drop[0] = False
    np.testing.assert_array_equal(
        instrument._corners(rest, removed, size), drop[labels].view(np.uint8)
    )
