"""The check's compiled band distances against a direct numpy measurement and OpenCV's band."""

from __future__ import annotations

import cv2
import numpy as np

from threadrecon.core import check_kernel


def band_d2(mask: np.ndarray, ox: float, oy: float, xy: np.ndarray, r: float) -> np.ndarray:
    """The kernel on a mask's thread pixels by rows (as check._crop lists them)."""
    rows, cols = np.nonzero(mask)
    row_ptr = np.searchsorted(rows, np.arange(mask.shape[0] + 1)).astype(np.int64)
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    return check_kernel.band_d2(cols.astype(np.int64), row_ptr, ox, oy, xy, r)


def _direct(mask: np.ndarray, ox: float, oy: float, xy: np.ndarray, r: float) -> np.ndarray:
    ii, jj = np.nonzero(mask)
    p = np.column_stack([jj + ox, ii + oy]).astype(float)
    a, b = xy[:-1], xy[1:]
    d = b - a
    ll = np.maximum((d**2).sum(1), 1e-300)
    t = np.clip(((p[:, None] - a[None]) * d[None]).sum(2) / ll, 0, 1)
    e = p[:, None] - (a[None] + t[..., None] * d[None])
    d2 = (e**2).sum(2).min(1)
    return np.sort(d2[d2 <= r * r])


def test_band_distances_are_the_pixels_distance_to_the_polyline() -> None:
    rng = np.random.default_rng(3)
    mask = (rng.random((60, 80)) < 0.4).astype(np.uint8)
    xy = np.cumsum(rng.normal(0, 3, (40, 2)), axis=0) + [40, 30]
    for ox, oy, r in ((0.0, 0.0, 4.5), (-7.0, 5.0, 2.5), (3.0, -2.0, 9.5)):
        got = np.sort(band_d2(mask, ox, oy, np.ascontiguousarray(xy), r))
        np.testing.assert_allclose(got, _direct(mask, ox, oy, xy, r), rtol=1e-12, atol=1e-12)


def test_band_counts_agree_with_a_drawn_thick_polyline() -> None:
    """The geometric band (centre within r + 1.5: OpenCV's rectangles of half-width r + 1 and
    discs of radius r + 1 for a line 2 r + 1 px wide, grown by the half pixel its filling
    rounds outwards) holds about the drawn pixels."""
    rng = np.random.default_rng(8)
    mask = np.ones((200, 240), np.uint8)
    xy = np.rint((np.cumsum(rng.normal(0, 4, (60, 2)), axis=0) + [120, 100]) * 4) / 4
    for r in (3, 8, 11):
        drawn = np.zeros_like(mask)
        poly = (xy * 4).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(drawn, [poly], False, 1, 2 * r + 1, cv2.LINE_8, 2)
        n = len(band_d2(mask, 0.0, 0.0, xy, r + 1.5))
        assert abs(n - int(drawn.sum())) <= 0.08 * drawn.sum()


def test_band_of_pixels_far_from_the_curve_is_empty() -> None:
    mask = np.ones((10, 10), np.uint8)
    xy = np.array([[100.0, 100.0], [120.0, 100.0]])
    assert band_d2(mask, 0.0, 0.0, xy, 3.0).size == 0
    one = np.array([[5.0, 5.0]])  # a single point: the disc around it
    assert len(band_d2(mask, 0.0, 0.0, one, 1.0)) == 5
