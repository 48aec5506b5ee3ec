"""The check's compiled band distances against a direct numpy measurement and OpenCV's band."""

from __future__ import annotations

import math

import cv2
import numpy as np

from threadrecon.core import check_kernel


def band_d2(
    mask: np.ndarray, ox: float, oy: float, xy: np.ndarray, r: float, done: float = 0.0
) -> np.ndarray:
    """The kernel on a mask's thread pixels by rows (as check._crop lists them)."""
    rows, cols = np.nonzero(mask)
    row_ptr = np.searchsorted(rows, np.arange(mask.shape[0] + 1)).astype(np.int64)
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    return check_kernel.band_d2(cols.astype(np.int64), row_ptr, ox, oy, xy, r, done)


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


def test_band_counts_at_or_above_the_stop_distance_are_exact() -> None:
    """With ``done`` > 0 a pixel stops at the first segment within sqrt(done): the set of
    pixels and every count below a threshold T >= done stay those of the exact distances."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        mask = (rng.random((70, 90)) < 0.35).astype(np.uint8)
        xy = np.ascontiguousarray(np.cumsum(rng.normal(0, 2.5, (60, 2)), axis=0) + [45, 35])
        r, done = 11.5, float(rng.choice([0.0, 3.5**2, 6.5**2]))
        exact = band_d2(mask, -3.0, 2.0, xy, r)
        fast = band_d2(mask, -3.0, 2.0, xy, r, done)
        assert len(fast) == len(exact)
        for T in (done, done + 0.5, 5.5**2, 9.5**2, r * r):
            if done <= T:
                assert np.count_nonzero(fast <= T) == np.count_nonzero(exact <= T)


def _band_two_passes(cols, row_ptr, ox, oy, xy, r, done):  # noqa: ANN001, ANN202
    """``_band_best`` as two full passes over every thread pixel (the kernel's own pass run as
    Python): the first over the boxes grown by sqrt(done), the second over the r boxes."""
    m = len(xy)
    seg = np.zeros((max(m - 1, 1), 5))
    for k in range(len(seg)):
        k1 = min(k + 1, m - 1)
        dx, dy = xy[k1, 0] - xy[k, 0], xy[k1, 1] - xy[k, 1]
        ll = dx * dx + dy * dy
        seg[k] = xy[k, 0], xy[k, 1], dx, dy, 1.0 / ll if ll > 0.0 else 0.0
    best = np.full(len(cols), np.inf)
    band_pass = check_kernel._band_pass.fn
    if done > 0.0:
        band_pass(cols, row_ptr, ox, oy, xy, seg, best, min(math.sqrt(done), r), done)
    band_pass(cols, row_ptr, ox, oy, xy, seg, best, r, done)
    return best[best <= r * r]


def test_band_second_pass_over_the_unsettled_pixels_is_both_full_passes() -> None:
    """The kernel's second pass runs over the pixels the first left above ``done`` only: bit
    for bit the values of two passes over every pixel (a settled pixel is skipped by its
    first test there), and above ``done`` the exact distances."""
    rng = np.random.default_rng(12)
    for trial in range(12):
        mask = (rng.random((50, 64)) < (0.2, 0.5, 0.9)[trial % 3]).astype(np.uint8)
        xy = np.ascontiguousarray(np.cumsum(rng.normal(0, 2.5, (30, 2)), axis=0) + [32, 25])
        rows, cols = np.nonzero(mask)
        row_ptr = np.searchsorted(rows, np.arange(mask.shape[0] + 1)).astype(np.int64)
        cols = cols.astype(np.int64)
        for r, done in ((11.5, 4.5**2), (11.5, 3.5**2), (3.0, 4.5**2), (9.5, 0.0)):
            got = check_kernel.band_d2(cols, row_ptr, -2.0, 1.0, xy, r, done)
            want = _band_two_passes(cols, row_ptr, -2.0, 1.0, xy, r, done)
            assert got.tobytes() == want.tobytes()
            if r * r < done:
                continue  # (a band narrower than the stop distance: only counts above it hold)
            exact = band_d2(mask, -2.0, 1.0, xy, r)
            assert got[exact > done].tobytes() == exact[exact > done].tobytes()
            assert np.array_equal(got <= done, exact <= done)


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


def _cone_numpy(curve, tip, way, mask, radius, cos, cover_px, margin=4):  # noqa: ANN001, ANN202
    """check_beyond._cone as numpy and OpenCV ran it before the kernel."""
    h, w = mask.shape
    half = math.acos(min(max(cos, -1.0), 1.0))
    a0 = math.atan2(way[1], way[0])
    xs, ys = [float(tip[0])], [float(tip[1])]
    for k in range(9):
        a = a0 + half * (k / 4.0 - 1.0)
        xs.append(tip[0] + radius * math.cos(a))
        ys.append(tip[1] + radius * math.sin(a))
    x0 = max(int(math.floor(min(xs))) - margin, 0)
    y0 = max(int(math.floor(min(ys))) - margin, 0)
    x1 = min(int(math.ceil(max(xs))) + margin + 1, w)
    y1 = min(int(math.ceil(max(ys))) + margin + 1, h)
    if x1 <= x0 or y1 <= y0:
        return np.zeros((0, 2)), np.zeros(0)
    nz = cv2.findNonZero(np.ascontiguousarray(mask[y0:y1, x0:x1]).view(np.uint8))
    if nz is None:
        return np.zeros((0, 2)), np.zeros(0)
    px = nz.reshape(-1, 2).astype(np.float64) + [x0, y0]
    rel = px - tip
    dist = np.hypot(rel[:, 0], rel[:, 1])
    along = rel[:, 0] * way[0] + rel[:, 1] * way[1]
    keep = (dist <= radius) & (along >= cos * dist) & (along > cover_px)
    px, along = px[keep], along[keep]
    near = curve[np.hypot(*(curve - tip).T) <= radius + cover_px]
    if not len(px) or not len(near):
        return px, along
    d2 = ((px[:, None, :] - near[None, :, :]) ** 2).sum(2)
    free = ~(d2 <= cover_px**2).any(1)
    return px[free], along[free]


def test_cone_pixels_are_the_fans_uncovered_thread_pixels() -> None:
    """The compiled fan search beyond a curve's end against its numpy and OpenCV form: random
    masks, tips inside and near the image's borders, every direction, narrow and wide fans."""
    rng = np.random.default_rng(11)
    for trial in range(120):
        mask = rng.random((int(rng.integers(20, 90)), int(rng.integers(20, 90)))) < 0.3
        h, w = mask.shape
        tip = np.array([rng.uniform(-5, w + 5), rng.uniform(-5, h + 5)])
        a = rng.uniform(-np.pi, np.pi)
        way = np.array([np.cos(a), np.sin(a)])
        curve = tip - np.outer(np.linspace(0, 30, 40), way) + rng.normal(0, 1.0, (40, 2))
        radius, cos = float(rng.uniform(2.0, 40.0)), float(rng.choice([0.0, 0.7071, 0.866]))
        cover = float(rng.uniform(0.5, 3.0))
        want_px, want_al = _cone_numpy(curve, tip, way, mask, radius, cos, cover)
        px, al = check_kernel.cone_pixels(
            curve, tip[0], tip[1], way[0], way[1], mask.view(np.uint8), radius, cos, cover, 4
        )
        assert np.array_equal(px, want_px), trial
        np.testing.assert_allclose(al, want_al, rtol=0, atol=1e-12)


def _coverage_numpy(mask, uv, inside, x0, y0, bx, by, cover_px, band_px=8):  # noqa: ANN001, ANN202
    """check._coverage's count as numpy ran it around band_d2 before coverage_count."""
    xy = uv[inside] - [x0, y0]
    poly = np.rint(xy * 4) / 4
    length = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
    widest = int(np.ceil(cover_px + band_px)) + 1.5
    done = (min(int(np.ceil(cover_px)), band_px) + 1.5) ** 2
    d2 = band_d2(mask, float(bx - x0), float(by - y0), poly, widest, done)
    band = float(np.count_nonzero(d2 <= (band_px + 1.5) ** 2))
    half = min(0.5 * band / max(length, 1.0), band_px)
    reach = int(np.ceil(cover_px + half))
    return int(np.count_nonzero(d2 <= (reach + 1.5) ** 2)), done


def test_coverage_count_is_the_numpy_count_around_the_band() -> None:
    """Random masks and wiggly curves (some points outside), several cover distances: the
    compiled count equals the count numpy made from band_d2's distances."""
    rng = np.random.default_rng(8)
    for trial in range(40):
        mask = (rng.random((70, 90)) < rng.uniform(0.02, 0.5)).astype(np.uint8)
        n = int(rng.integers(2, 300))
        uv = np.cumsum(rng.normal(0, rng.uniform(0.3, 3.0), (n, 2)), axis=0) + [45, 35]
        inside = rng.random(n) < 0.9
        inside[:2] = True
        x0, y0, bx, by = (int(v) for v in rng.integers(-5, 6, 4))
        cover = float(rng.choice([0.0, 1.0, 2.5, 3.0, 7.0]))
        want, done = _coverage_numpy(mask, uv, inside, x0, y0, bx, by, cover)
        rows, cols = np.nonzero(mask)
        row_ptr = np.searchsorted(rows, np.arange(mask.shape[0] + 1)).astype(np.int64)
        got = check_kernel.coverage_count(
            np.ascontiguousarray(uv), inside, float(x0), float(y0), cols.astype(np.int64),
            row_ptr, float(bx - x0), float(by - y0), cover, 8.0, float(done),
        )  # fmt: skip
        assert got == want, trial


def test_unmeasured_length_is_numpys_masked_sum() -> None:
    """The compiled sum equals numpy's ``np.sum(extra, where=...)`` to the bit on random
    steps, depths and supports, with non-finite steps and depths among them."""
    rng = np.random.default_rng(12)
    for trial in range(60):
        n = int(rng.integers(2, 900))
        step = rng.uniform(0.0, 3.0, n - 1)
        step3 = step * rng.uniform(0.5, 2.0, n - 1)
        z = rng.uniform(50.0, 150.0, n)
        step[rng.random(n - 1) < 0.02] = np.nan
        z[rng.random(n) < 0.01] = np.inf
        supported = rng.random(n) < rng.uniform(0.0, 1.0)
        half = 0.5 / float(rng.uniform(5.0, 20.0))
        free = ~(supported[1:] & supported[:-1])
        with np.errstate(invalid="ignore"):
            extra = step3[free] - step[free] * half * (z[1:][free] + z[:-1][free])
            want = float(np.sum(extra, where=np.isfinite(extra) & (extra > 0.0)))
        got = check_kernel.unmeasured_length(step3, step, z, supported, half)
        assert got == want, trial


def _unsupported_numpy(z: np.ndarray, supported: np.ndarray) -> float:
    """check._unsupported_travel as numpy ran it before the kernel."""
    tv = np.abs(np.diff(z))
    idx = np.flatnonzero(supported)
    if idx.size == 0:
        return float(tv.sum())
    edges = np.concatenate([[0], idx, [len(z) - 1]])
    csum = np.concatenate([[0.0], np.cumsum(tv)])
    travel = csum[edges[1:]] - csum[edges[:-1]]
    net = np.abs(z[edges[1:]] - z[edges[:-1]])
    net[[0, -1]] = 0.0
    return float(np.sum(travel - net))


def test_unsupported_travel_is_numpys_to_the_bit() -> None:
    rng = np.random.default_rng(13)
    for _ in range(60):
        n = int(rng.integers(2, 1200))
        z = 100.0 + np.cumsum(rng.normal(0.0, rng.uniform(0.01, 2.0), n))
        supported = rng.random(n) < rng.choice([0.0, 0.05, 0.5, 1.0])
        assert check_kernel.unsupported_travel(z, supported) == _unsupported_numpy(z, supported)
