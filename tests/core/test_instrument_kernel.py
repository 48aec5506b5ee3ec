"""Tests of core/instrument_kernel.py: each kernel gives exactly the numpy/cv2 steps it
replaces in core/instrument.py."""

import cv2
import numpy as np
import pytest

from threadrecon.core.instrument_kernel import label_lookup, ridge_values

_SHAPES = [(1, 1), (1, 7), (7, 1), (2, 3), (37, 51), (120, 160)]


def _mask(shape: tuple[int, int], seed: int) -> np.ndarray:
    """A random uint8 mask: speckle, or blobs and strips (a closing of speckle), by seed."""
    rng = np.random.default_rng(seed)
    m = (rng.random(shape) < rng.uniform(0.1, 0.95)).astype(np.uint8)
    if seed % 2 and min(shape) > 2:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    return m


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
