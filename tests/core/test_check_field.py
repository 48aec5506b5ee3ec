"""Tests of core/check_field.py: the check's distance field of a thread mask, cached per mask."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from threadrecon.core.check_beyond import pieces
from threadrecon.core.check_field import CROPS_SHARE, PieceIndex, clear_fields, mask_field

TRIALS = 30


def _mask(rng: np.random.Generator) -> np.ndarray:
    mask = np.zeros((120, 160), dtype=bool)
    for _ in range(3):  # thread-wide strokes
        y, x = rng.integers(30, 90), rng.integers(40, 120)
        mask[y - 1 : y + 2, x - 30 : x + 30] = True
    return mask


def _thread(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A few random polylines 1-5 px wide (curved strokes, crossings, gaps)."""
    h, w = shape
    canvas = np.zeros(shape, np.uint8)
    for _ in range(rng.integers(1, 5)):
        pts = np.cumsum(rng.normal(0, 8, (rng.integers(3, 30), 2)), axis=0)
        pts += [rng.integers(0, w), rng.integers(0, h)]
        cv2.polylines(canvas, [pts.astype(np.int32).reshape(-1, 1, 2)], False, 1,
                      int(rng.integers(1, 6)))  # fmt: skip
    return canvas.astype(bool)


@pytest.mark.parametrize("seed", range(TRIALS))
def test_field_is_the_distance_to_the_thread_saturated_at_its_reach(seed: int) -> None:
    rng = np.random.default_rng(seed)
    mask = _mask(rng)
    field = mask_field(mask, 12.0)
    exact = distance_transform_edt(~mask)  # (rows, cols)
    xy = rng.uniform([0.0, 0.0], [159.0, 119.0], size=(300, 2))  # on the image
    got = field.at(xy)
    rc = np.clip(np.rint(xy[:, ::-1]), 0, [119, 159]).astype(int)
    want = exact[rc[:, 0], rc[:, 1]]
    near = want < 10.0
    # 3x3 L2 mask (< 3 %) plus the rounding of the point to its pixel (< 0.71 px)
    assert np.all(np.abs(got[near] - want[near]) <= 0.03 * want[near] + 0.71)
    assert np.all(got <= 12.0) and np.all(got[want > 13.0] == 12.0)
    assert np.all(field.at(np.array([[np.nan, 3.0]])) == 12.0)
    off = field.at(np.array([[-30.0, 60.0], [200.0, 60.0]]))  # off the image: saturated
    assert np.all(off == 12.0)


@pytest.mark.parametrize("seed", range(TRIALS))
def test_field_read_from_crops_equals_the_whole_box_transform_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    shape = (int(rng.integers(60, 300)), int(rng.integers(60, 400)))
    mask = _thread(rng, shape)
    if not mask.any():
        mask[shape[0] // 2, shape[1] // 2] = True
    reach = float(rng.uniform(5.0, 45.0))
    # a curve: a random walk near and across the thread, some points off the image
    ys, xs = np.nonzero(mask)
    k = rng.integers(0, len(xs), 40)
    walk = np.column_stack([xs[k], ys[k]]).astype(float)
    pts = (
        np.repeat(walk, 10, axis=0)
        + rng.normal(0, 1, (400, 2)) * rng.choice([0.5, 3, 15], 400)[:, None]
    )
    pts[::37] += 60.0
    field = mask_field(mask, reach)
    got = field.at(pts)
    # the same reading from the transform of the whole box, computed as before
    box = np.ascontiguousarray(mask[field.y0 : field.y0 + field.shape[0],
                                    field.x0 : field.x0 + field.shape[1]]).view(np.uint8)  # fmt: skip
    dist = cv2.distanceTransform(cv2.compare(box, 0, cv2.CMP_EQ), cv2.DIST_L2, cv2.DIST_MASK_3)
    h, w = dist.shape
    q = pts - [field.x0, field.y0]
    c = np.clip(np.rint(q), 0, [w - 1, h - 1])
    want = dist[c[:, 1].astype(int), c[:, 0].astype(int)] + np.hypot(*(q - c).T)
    want = np.where(want < reach, want, reach)
    assert np.array_equal(got, want)
    assert np.array_equal(field.dist, dist)
    for x, y in pts[::25].astype(int):  # the background ring's windows (exact up to 9 px)
        d, rows, cols = field.window(int(x), int(y), 25, 9.0)
        full = dist[rows.start - field.y0 : rows.stop - field.y0,
                    cols.start - field.x0 : cols.stop - field.x0]  # fmt: skip
        assert d.shape == full.shape
        assert np.array_equal(d[full <= 9.0], full[full <= 9.0]) and np.all(d[full > 9.0] > 9.0)


def test_field_read_off_the_thread_again_and_again_takes_the_whole_box_once() -> None:
    """Crops are counted over the field's reads: once they add up to more than CROPS_SHARE of
    the box, the whole box's transform is computed and kept, and every read after it takes
    its values from there: the same values (ck17: the check's re-runs on one segmentation
    re-read a bridge's points far off the thread, ~1 ms a view in crops each time)."""
    clear_fields()
    mask = np.zeros((220, 220), dtype=bool)
    mask[10, 10:200] = True  # a thread along a row and a speck far below it: a tall box
    mask[200, 100] = True
    field = mask_field(mask, 12.0)
    pts = np.column_stack([np.arange(20.0, 120.0), np.full(100, 16.0)])  # 6 px off the thread
    first = field.at(pts)
    area = field._state["cropped"]  # px of crops a read takes
    assert "dist" not in field._state and area > 0
    h, w = field.shape
    reads = 1
    while "dist" not in field._state:
        assert np.array_equal(field.at(pts + 0.1 * reads), _fresh(mask, pts + 0.1 * reads))
        reads += 1
        assert reads <= 2 + CROPS_SHARE * h * w / area
    assert reads > 1  # the first read took crops only
    assert np.array_equal(field.at(pts), first)
    assert np.array_equal(field.at(pts[::-1]), first[::-1])


def _fresh(mask: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """A reading of a new field of ``mask`` (its first: crops)."""
    clear_fields()
    fresh = mask_field(mask.copy(), 12.0)
    got = fresh.at(pts)
    assert "dist" not in fresh._state
    return got


def test_field_is_cached_by_the_mask_object_not_its_content() -> None:
    clear_fields()
    mask = _mask(np.random.default_rng(0))
    a = mask_field(mask, 10.0)
    assert mask_field(mask, 10.0) is a  # the same segmentation: computed once
    assert mask_field(mask, 20.0) is not a  # another reach
    copy = mask.copy()
    assert mask_field(copy, 10.0) is not a  # another mask object
    assert np.array_equal(mask_field(copy, 10.0).dist, a.dist)
    assert not a.dist.flags.writeable


def test_window_is_clipped_to_the_field_box() -> None:
    mask = np.zeros((50, 60), dtype=bool)
    mask[20, 10:40] = True
    field = mask_field(mask, 5.0)
    d, rows, cols = field.window(12, 21, 4, 5.0)
    assert d.shape == (9, 9) and (rows.start, cols.start) == (17, 8)
    assert d[20 - 17, 12 - 8] == 0.0 and abs(d[21 - 17, 12 - 8] - 1.0) < 0.05  # 3x3 mask
    d, rows, cols = field.window(0, 0, 3, 5.0)  # outside the box (rows 15..25, cols 5..44)
    assert d.size == 0
    empty = mask_field(np.zeros((8, 8), dtype=bool), 5.0)
    assert empty.total == 0 and np.all(empty.at(np.array([[1.0, 1.0]])) == 5.0)


def test_field_rejects_a_mask_that_is_not_boolean_2d() -> None:
    with pytest.raises(ValueError, match="bool"):
        mask_field(np.zeros((4, 4), dtype=np.uint8), 3.0)


def _in_piece(px: np.ndarray, part: np.ndarray) -> np.ndarray:
    """Membership by keys (the search PieceIndex replaces)."""
    key = lambda a: a[:, 1].astype(np.int64) * 1_000_003 + a[:, 0].astype(np.int64)  # noqa: E731
    return np.isin(key(px), key(part))


@pytest.mark.parametrize("seed", range(TRIALS))
def test_piece_index_finds_each_pixels_piece_and_the_pieces_near_a_point(seed: int) -> None:
    rng = np.random.default_rng(seed)
    mask = _thread(rng, (90, 130))
    parts = pieces(mask)
    index = PieceIndex(parts)
    # pixels in and around the image (integers, as the end search's cone gives them)
    px = np.column_stack([rng.integers(-5, 136, 400), rng.integers(-5, 96, 400)]).astype(float)
    number = index.at(px)
    for i, part in enumerate(parts):
        np.testing.assert_array_equal(number == i, _in_piece(px, part))
    assert np.all((number >= 0) == np.any([_in_piece(px, q) for q in parts] or [False], axis=0))
    for _ in range(40):  # points off the pixel grid, near and far from the pieces
        xy = rng.uniform([-4.0, -4.0], [134.0, 94.0])
        if rng.random() < 0.3 and parts:  # on a piece's pixel, or 2 px from it exactly
            q = parts[rng.integers(len(parts))]
            xy = q[rng.integers(len(q))] + [0.0, rng.choice([0.0, 2.0, -2.0])]
        want = [i for i, q in enumerate(parts) if not np.min(np.hypot(*(q - xy).T)) > 2.0]
        assert index.near(xy, 2.0) == want
    assert index.near(np.array([np.nan, 3.0]), 2.0) == list(range(len(parts)))


def test_piece_index_of_no_piece_holds_no_pixel() -> None:
    index = PieceIndex([])
    assert index.at(np.array([[0.0, 0.0], [5.0, 7.0]])).tolist() == [-1, -1]
    assert index.near(np.array([1.0, 1.0]), 2.0) == []


@pytest.mark.parametrize("seed", range(10))
def test_field_count_and_box_are_those_of_opencv(seed: int) -> None:
    """The field's thread-pixel count and bounding box come from the mask's row runs
    (refine.row_runs, shared with the refine stage): cv2.countNonZero's and boundingRect's."""
    clear_fields()
    rng = np.random.default_rng(seed)
    mask = _thread(rng, (int(rng.integers(20, 90)), int(rng.integers(20, 130))))
    field = mask_field(mask, 6.0)
    m8 = mask.view(np.uint8)
    assert field.total == cv2.countNonZero(m8)
    if field.total:
        assert field.bbox == tuple(cv2.boundingRect(m8))
