"""Tests of core/ridge_kernel.py's piece kernels: labels and boxes of pixel lists are those of
cv2.connectedComponents on the mask image, bit for bit, and half-widths those of
cv2.distanceTransform to float32 rounding."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage
from support import random_mask

from threadrecon.core import ridge_kernel as pk

_SIZES = [(1, 1), (1, 9), (9, 1), (2, 2), (37, 51), (120, 160), (480, 640)]


def _mask(shape: tuple[int, int], seed: int) -> np.ndarray:
    """A random uint8 mask: speckle, or blobs and lines, by seed."""
    return random_mask(shape, seed, fill=(0.05, 0.7), close_px=3)


def _pixels(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.nonzero(m)  # row-major order
    return rows.astype(np.int64), cols.astype(np.int64)


def _boxes(lab: np.ndarray, rows: np.ndarray, cols: np.ndarray, n: int) -> np.ndarray:
    """The pieces' boxes (4, n) as piece_stats gives them."""
    return pk.piece_stats(lab, rows, cols, np.zeros(len(lab), np.float32), np.float32(1), n)[3]


def _cv2_half_width(piece: np.ndarray) -> float:
    """The largest cv2 distance (DIST_L2, 3x3) of a piece (H, W) bool to its outside, on its
    bounding box grown by one pixel within the image (the image's edge is far)."""
    r, c = np.nonzero(piece)
    h, w = piece.shape
    box = piece[max(r.min() - 1, 0) : r.max() + 2, max(c.min() - 1, 0) : c.max() + 2]
    return float(cv2.distanceTransform(box.astype(np.uint8), cv2.DIST_L2, 3).max())


@pytest.mark.parametrize("shape", _SIZES)
@pytest.mark.parametrize("seed", range(4))
def test_labels_of_the_pixels_are_cv2_connected_components(
    shape: tuple[int, int], seed: int
) -> None:
    m = _mask(shape, seed + shape[0])
    n, labels = cv2.connectedComponents(m, connectivity=8, ltype=cv2.CV_32S)
    rows, cols = _pixels(m)
    lab = np.empty(len(rows), np.int64)
    assert pk.label_pixels(rows, cols, lab) == n
    np.testing.assert_array_equal(lab, labels[rows, cols])  # the same numbering too


def test_labels_of_no_pixel_count_the_background_only() -> None:
    empty = np.zeros(0, np.int64)
    assert pk.label_pixels(empty, empty, empty.copy()) == 1


@pytest.mark.parametrize("shape", _SIZES)
@pytest.mark.parametrize("seed", range(4))
def test_boxes_and_half_widths_are_those_of_each_piece_alone(
    shape: tuple[int, int], seed: int
) -> None:
    m = _mask(shape, 100 + seed + shape[1])
    n, labels = cv2.connectedComponents(m, connectivity=8, ltype=cv2.CV_32S)
    rows, cols = _pixels(m)
    lab = labels[rows, cols].astype(np.int64)
    boxes = _boxes(lab, rows, cols, n)
    ids = np.arange(1, n, 2, dtype=np.int64)  # every second piece
    half = pk.half_widths(lab, rows, cols, ids, boxes, *shape)
    expected = np.zeros(n)
    chosen = set(ids.tolist())
    # each piece seen through its bounding box (scipy) grown by one pixel within the image:
    # the window _cv2_half_width takes of the whole image, without n passes over the image
    objects = ndimage.find_objects(labels)
    assert len(objects) == n - 1
    for k, (rs, cs) in enumerate(objects, start=1):
        assert tuple(boxes[:, k]) == (rs.start, rs.stop - 1, cs.start, cs.stop - 1)
        if k in chosen:
            window = labels[max(rs.start - 1, 0) : rs.stop + 1, max(cs.start - 1, 0) : cs.stop + 1]
            expected[k] = _cv2_half_width(window == k)
    # float32 sums of the same steps along another path: the last bits (of ~100 steps) differ.
    np.testing.assert_allclose(half, expected, rtol=2e-6, atol=0)
    assert half[0] == 0.0 and tuple(boxes[:, 0]) == (0, 0, 0, 0)


@pytest.mark.parametrize("seed", range(6))
def test_piece_stats_are_numpys_counts_sums_and_seeds(seed: int) -> None:
    """Counts, sums and seeds per label as segment_raw._pieces computed them with numpy:
    np.bincount's float64 counts and its weighted sums (added in pixel order, to the last
    bit), and a label seeded where one of its float32 values is >= the threshold as numpy
    compares float32 values with a Python float (in float32); labels without pixels count 0."""
    rng = np.random.default_rng([8, seed])
    m = int(rng.integers(0, 3000))
    n = int(rng.integers(1, 60))
    lab = np.sort(rng.integers(1, n, m)) if n > 1 else np.zeros(0, np.int64)
    if seed % 2:  # in any order
        rng.shuffle(lab)
    m = len(lab)
    rows, cols = rng.integers(0, 480, m), rng.integers(0, 640, m)
    s = (rng.random(m) * rng.uniform(1, 1e4)).astype(np.float32)
    thr = float(np.quantile(s, 0.97)) if m else 1.0
    if m:  # a value at the threshold's float32 rounding, above the float64 threshold
        thr = float(np.nextafter(np.float32(thr), np.float32(0))) + 1e-12
    area, sums, seeded, boxes = pk.piece_stats(lab, rows, cols, s, np.float32(thr), n)
    np.testing.assert_array_equal(area, np.bincount(lab, minlength=n).astype(np.float64))
    assert np.array_equal(sums, np.bincount(lab, weights=s, minlength=n))  # bit for bit
    want = np.zeros(n, bool)
    want[lab[s >= thr]] = True
    np.testing.assert_array_equal(seeded, want)
    for k in range(n):
        at = lab == k
        if at.any():
            assert tuple(boxes[:, k]) == (rows[at].min(), rows[at].max(), cols[at].min(),
                                          cols[at].max())  # fmt: skip
        else:
            assert tuple(boxes[:, k]) == (0, 0, 0, 0)


def test_a_piece_filling_the_image_is_as_far_as_cv2_says() -> None:
    m = np.ones((5, 7), np.uint8)
    rows, cols = _pixels(m)
    lab = np.ones(len(rows), np.int64)
    boxes = _boxes(lab, rows, cols, 2)
    half = pk.half_widths(lab, rows, cols, np.array([1]), boxes, 5, 7)
    assert half[1] == _cv2_half_width(m.astype(bool))


def test_half_width_of_a_bar_grows_with_its_width() -> None:
    widths = []
    for wide in (1, 3, 5, 9):
        m = np.zeros((40, 60), np.uint8)
        m[10 : 10 + wide, 5:55] = 1
        rows, cols = _pixels(m)
        lab = np.ones(len(rows), np.int64)
        boxes = _boxes(lab, rows, cols, 2)
        widths.append(pk.half_widths(lab, rows, cols, np.array([1]), boxes, 40, 60)[1])
    assert widths[0] == pytest.approx(0.955, abs=1e-6)
    assert np.all(np.diff(widths) > 0.9)
