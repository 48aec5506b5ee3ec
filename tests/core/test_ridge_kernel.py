"""Tests of core/ridge_kernel.py: the compiled filters of the raw segmentation give what the
cv2 calls they replace give, to float32 rounding, on every image size down to one pixel."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from support import random_mask

from threadrecon.core import ridge_kernel as rk

_SIZES = [(480, 640), (37, 51), (2, 3), (1, 1), (1, 7), (6, 1)]


def _cv2_line(g: np.ndarray, r: float, norm: float, edge_k: float) -> np.ndarray:
    """The response as cv2 calls: Sobel derivatives, the formula, the norm over channels."""
    d = {}
    for name, (dx, dy, k) in {
        "gx": (1, 0, 0.125 * r), "gy": (0, 1, 0.125 * r), "hxx": (2, 0, 0.25 * r * r),
        "hyy": (0, 2, 0.25 * r * r), "hxy": (1, 1, 0.25 * r * r),
    }.items():  # fmt: skip
        d[name] = cv2.Sobel(g, cv2.CV_64F, dx, dy, ksize=3, scale=k)
    a = np.abs(d["hxx"] + d["hyy"]) / 2
    dd = np.hypot(d["hxx"] - d["hyy"], 2 * d["hxy"]) / 2
    line = 2 * norm * norm * np.minimum(a, dd) - edge_k * norm * np.hypot(d["gx"], d["gy"])
    line = np.maximum(line, 0.0)
    return line if line.ndim == 2 else np.sqrt((line**2).sum(axis=2))


def _image(shape: tuple[int, ...], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.random(shape).astype(np.float32) * 50
    return cv2.GaussianBlur(img, (0, 0), 1.0) if min(shape[:2]) > 1 else img


@pytest.mark.parametrize("shape", _SIZES)
@pytest.mark.parametrize("c", [1, 3])
def test_line_response_is_the_cv2_sobel_formula(shape: tuple[int, int], c: int) -> None:
    g = _image(shape if c == 1 else (*shape, c), seed=shape[0] * 7 + c)
    r, norm, edge_k = 0.5, 2.0, 2.0
    out = np.full(shape, -1.0, np.float32)
    planes = g if c == 1 else np.ascontiguousarray(np.moveaxis(g, 2, 0))  # (c, H, W)
    got = rk.line_response(
        planes.reshape(-1, shape[1]), c, np.float32(0.125 * r), np.float32(0.25 * r * r),
        np.float32(2 * norm * norm), np.float32(edge_k * norm), out,
    )  # fmt: skip
    assert got is out
    want = _cv2_line(g.astype(np.float64), r, norm, edge_k)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-4 * max(float(want.max()), 1.0))


def test_line_response_is_zero_on_a_flat_and_on_a_linear_image() -> None:
    ramp = np.add.outer(np.arange(20.0), 3 * np.arange(30.0)).astype(np.float32)
    for g in (np.full((20, 30), 7.0, np.float32), ramp):
        out = rk.line_response(g, 1, np.float32(0.125), np.float32(0.25), np.float32(2.0),
                               np.float32(0.0), np.empty_like(g))  # fmt: skip
        # A linear image has no second derivative, but the reflected border bends it.
        assert not out[1:-1, 1:-1].any()


def test_line_response_peaks_on_a_thin_dark_line() -> None:
    img = np.full((40, 40), 100.0, np.float32)
    img[:, 20] = 60.0
    g = cv2.GaussianBlur(img, (0, 0), 1.0)
    out = rk.line_response(g, 1, np.float32(0.125), np.float32(0.25), np.float32(2.0),
                           np.float32(2.0), np.empty_like(g))  # fmt: skip
    assert set(np.argmax(out, axis=1).tolist()) == {20}
    assert out[:, 20].min() > 5 * out[:, :15].max()


@pytest.mark.parametrize("shape", _SIZES)
@pytest.mark.parametrize("channels", [0, 1, 3, 4])
def test_log_planes_are_the_log_channels_and_their_pyrdown(
    shape: tuple[int, int], channels: int
) -> None:
    from threadrecon.core.segment_raw import _log_channels, _log_planes

    rng = np.random.default_rng(shape[0] + channels)
    img = rng.integers(0, 256, (*shape, max(channels, 1)), dtype=np.uint8)
    img = img[:, :, 0] if channels == 0 else img[:, :, ::-1]  # a strided view, as loaded
    grey, half = _log_planes(img)
    f = _log_channels(img if channels != 4 else img[:, :, :3])
    assert grey.shape == shape and half.shape == (f.shape[2], (shape[0] + 1) // 2,
                                                  (shape[1] + 1) // 2)  # fmt: skip
    np.testing.assert_allclose(grey, f[:, :, 0], rtol=0, atol=1e-4)
    want = np.moveaxis(cv2.pyrDown(f).reshape(half.shape[1:] + half.shape[:1]), 2, 0)
    np.testing.assert_allclose(half, want, rtol=0, atol=1e-4)


def _reflect101(i: np.ndarray, n: int) -> np.ndarray:
    """Indices with cv2's BORDER_REFLECT_101 (..., 2, 1, 0, 1, 2, ...) into 0..n-1."""
    if n == 1:
        return np.zeros_like(i)
    period = 2 * n - 2
    i = np.abs(i) % period
    return np.where(i >= n, period - i, i)


@pytest.mark.parametrize("shape", [(480, 640), (37, 51), (5, 9), (2, 3), (1, 1), (1, 7), (6, 1)])
@pytest.mark.parametrize("channels", [1, 3])
def test_log_planes_are_their_float32_steps_bit_for_bit(
    shape: tuple[int, int], channels: int
) -> None:
    """log_planes against its float32 steps in numpy, in the kernel's order (each operation
    rounds to float32 alike): the channels m0 lut[R] + m1 lut[G] + m2 lut[B] left to right,
    each row of the half-resolution planes ((((r0 + 4 r1) + 6 r2) + 4 r3) + r4) down the five
    reflected rows, then the same taps along it at the even columns, times 1/256. Equal to
    the last bit, so a faster form of the kernel gives the same masks (the chroma rows of
    _LOG_MIX are computed as lr - lg and lb - lg there)."""
    from threadrecon.core.segment_raw import _LOG_LUT, _LOG_MIX, _log_planes

    rng = np.random.default_rng(shape[0] * 7 + channels)
    img = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)[:, :, ::-1]  # a strided view
    img = img if channels == 3 else img[:, :, :1]
    grey, half = _log_planes(img)
    _assert_log_planes_steps(img, _LOG_LUT, _LOG_MIX, grey, half)


@pytest.mark.parametrize("shape", [(48, 64), (37, 51), (5, 9)])
def test_log_planes_of_any_mix_are_their_float32_steps_bit_for_bit(shape: tuple[int, int]) -> None:
    """The kernel's general mix (rows other than the log ratios, and a look-up table with
    negative and zero entries) against the same float32 steps."""
    from threadrecon.core.ridge_kernel import log_planes

    rng = np.random.default_rng(shape[1])
    img = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)[:, :, ::-1]
    lut = rng.normal(0.0, 50.0, 256).astype(np.float32)
    lut[:8] = 0.0
    for mix in (
        rng.normal(0.0, 1.0, (3, 3)).astype(np.float32),
        np.array([[0.299, 0.587, 0.114], [1.0, -1.0, 0.0], [0.0, -1.0, 1.0]], np.float32),
    ):
        h, w = shape
        grey = np.empty(shape, np.float32)
        half = np.empty((3 * ((h + 1) // 2), (w + 1) // 2), np.float32)
        log_planes(img, lut, mix, grey, half)
        _assert_log_planes_steps(img, lut, mix, grey, half.reshape(3, (h + 1) // 2, -1))


def _assert_log_planes_steps(
    img: np.ndarray, lut: np.ndarray, mix: np.ndarray, grey: np.ndarray, half: np.ndarray
) -> None:
    logs = lut[img]  # (H, W, c) float32
    if img.shape[2] == 3:
        f = [(mix[j, 0] * logs[:, :, 0] + mix[j, 1] * logs[:, :, 1]) + mix[j, 2] * logs[:, :, 2]
             for j in range(3)]  # fmt: skip
    else:
        f = [logs[:, :, 0]]
    h, w = img.shape[:2]
    assert np.array_equal(grey, f[0])
    taps = [np.float32(t) for t in (1, 4, 6, 4, 1)]
    ys, xs = 2 * np.arange((h + 1) // 2), 2 * np.arange((w + 1) // 2)
    for j, plane in enumerate(f):
        rows = [plane[_reflect101(ys + k - 2, h)] for k in range(5)]
        v = rows[0]
        for k in range(1, 5):
            v = v + taps[k] * rows[k] if k < 4 else v + rows[k]
        cols = [v[:, _reflect101(xs + k - 2, w)] for k in range(5)]
        out = cols[0]
        for k in range(1, 5):
            out = out + taps[k] * cols[k] if k < 4 else out + cols[k]
        assert np.array_equal(half[j], out * np.float32(1.0 / 256.0)), j


def test_achromatic_is_the_log_chroma_of_every_colour_pair_below_the_limit() -> None:
    """The kernel against the steps it replaces (segment_raw._View.build, instrument frames):
    the full-resolution log channels, max(|log R/G|, |log B/G|) by cv2, compared with
    _GREY_TOOL * _LOG_SCALE by numpy; on every (R, G) and every (B, G) pair of levels (R the
    row, G the column, B = 7 R + 13 G mod 256 takes every level down a column), as a strided
    RGB view of BGR (as loaded)."""
    from threadrecon.core import segment_raw as sr

    r, g = np.meshgrid(np.arange(256), np.arange(256), indexing="ij")
    rgb = np.stack([r, g, (7 * r + 13 * g) % 256], -1).astype(np.uint8)
    img = np.ascontiguousarray(rgb[:, :, ::-1])[:, :, ::-1]
    f = sr._log_channels(img)
    chroma = cv2.max(cv2.absdiff(f[:, :, 1], 0.0), cv2.absdiff(f[:, :, 2], 0.0))
    want = chroma < sr._GREY_TOOL * sr._LOG_SCALE
    got = rk.achromatic(img, sr._LOG_LUT, sr._GREY_LIMIT, np.empty((256, 256), np.uint8))
    assert 0 < want.sum() < want.size
    np.testing.assert_array_equal(got.view(bool), want)


def test_log_at_gives_the_log_channels_of_those_pixels_bit_for_bit() -> None:
    from threadrecon.core.segment_raw import _log_at, _log_channels

    rng = np.random.default_rng(5)
    for img in (rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)[:, :, ::-1],
                rng.integers(0, 256, (30, 40), dtype=np.uint8)):  # fmt: skip
        rows, cols = np.nonzero(rng.random((30, 40)) < 0.2)
        np.testing.assert_array_equal(_log_at(img, rows, cols), _log_channels(img)[rows, cols])
        assert _log_at(img, rows[:0], cols[:0]).shape == (0, 1 if img.ndim == 2 else 3)


@pytest.mark.parametrize("shape", [(480, 640), (37, 51), (2, 3), (1, 1), (1, 7), (6, 1)])
def test_upsample_max_is_cv2_resize_then_max(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(shape[1])
    coarse = rng.random(((shape[0] + 1) // 2, (shape[1] + 1) // 2), dtype=np.float32)
    fine = rng.random(shape, dtype=np.float32)
    want = np.maximum(fine, cv2.resize(coarse, shape[::-1], interpolation=cv2.INTER_LINEAR))
    got = rk.upsample_max(coarse, fine)
    assert got is fine
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("shape", [(480, 640), (37, 52), (3, 4), (6, 2)])
def test_upsample_max_of_twice_the_width_is_the_general_formula_bit_for_bit(
    shape: tuple[int, int],
) -> None:
    # (even widths: the kernel's doubled-width path; the reference is its general formula)
    rng = np.random.default_rng(shape[0])
    h, w = (shape[0] + 1) // 2, shape[1] // 2
    coarse = rng.random((h, w), dtype=np.float32) * 30
    fine = rng.random(shape, dtype=np.float32) * 30

    def source(n: int, big_n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        f = (np.arange(big_n) + 0.5) * (n / big_n) - 0.5
        i = np.floor(f).astype(np.int64)
        a = (f - i).astype(np.float32)
        a[(i < 0) | (i >= n - 1)] = 0.0
        i = np.clip(i, 0, n - 1)
        return i, np.minimum(i + 1, n - 1), a

    x0, x1, ax = source(w, shape[1])
    y0, y1, by = source(h, shape[0])
    one = np.float32(1.0)
    across = (one - ax) * coarse[:, x0] + ax * coarse[:, x1]
    want = np.maximum(fine, (one - by)[:, None] * across[y0] + by[:, None] * across[y1])
    got = rk.upsample_max(coarse, fine.copy())
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))


def test_line_response_in_place_is_the_response_into_another_buffer() -> None:
    for shape in _SIZES:
        g = _image(shape, seed=shape[1])
        args = (1, np.float32(0.125), np.float32(0.25), np.float32(2.0), np.float32(2.0))
        want = rk.line_response(g, *args, np.empty_like(g))
        got = rk.line_response(g, *args, g)
        assert got is g
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("trial", range(10))
def test_kth_smallest_of_a_strided_view_is_partition_of_its_values(trial: int) -> None:
    rng = np.random.default_rng([91, trial])
    s = np.maximum(rng.normal(0, 1, (int(rng.integers(1, 60)), 70)), 0).astype(np.float32)
    for view in (s[::2, ::2], s[:, 3:4], s[1:, ::-3]):
        flat = view.ravel()
        for k in (0, flat.size // 2, int(0.9 * (flat.size - 1)), flat.size - 1):
            assert rk.kth_smallest(view, k) == np.partition(flat, k)[k]


def test_kth_smallest_gathers_its_bin_exactly_at_every_rank() -> None:
    # The bin's values are gathered at the next free slot, which only they advance: a bin
    # holding every value, none but the last, or values of one level (ties, zeros with the
    # sign set), and every rank, including the last value of the array in the bin.
    rng = np.random.default_rng(93)
    mostly_zero = np.where(rng.random(301) < 0.8, 0.0, rng.random(301)).astype(np.float32)
    mostly_zero[::7] = -0.0
    cases = [
        np.full(13, 2.5, np.float32),
        np.r_[np.full(40, 7.0), 1.0].astype(np.float32),  # the k-th smallest comes last
        np.r_[rng.random(50) + 100.0, 1.0, 1.0 + 2**-20].astype(np.float32),
        mostly_zero,
        (1.0 + rng.integers(0, 4, 64) * 2**-22).astype(np.float32),  # one sub-bin, four levels
    ]
    for x in cases:
        for view in (x[None], x[None, ::-1], x[: len(x) - len(x) % 3].reshape(-1, 3)[:, ::2]):
            flat = view.ravel()
            for k in range(flat.size):
                assert rk.kth_smallest(view, k) == np.partition(flat, k)[k]


def _drop_specks_by_labels(mask: np.ndarray, min_px: int) -> np.ndarray:
    """The plain computation: cv2's 8-connected labels of the whole mask, sizes, keep."""
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    keep = np.bincount(labels.ravel(), minlength=n) >= min_px
    keep[0] = False
    return keep[labels]


@pytest.mark.parametrize("trial", range(60))
def test_drop_specks_equals_the_labelling_of_the_whole_mask(trial: int) -> None:
    from threadrecon.core.segment_raw import drop_specks

    rng = np.random.default_rng([13, trial])
    shape = (int(rng.integers(1, 50)), int(rng.integers(1, 50)))
    mask = rng.random(shape) < rng.choice([0.05, 0.3, 0.6])
    if trial % 3 == 0:  # thin lines (diagonal steps join 8-neighbours only) and specks
        mask[:] = False
        for _ in range(3):
            r, c = rng.integers(0, shape[0]), rng.integers(0, shape[1])
            for _ in range(int(rng.integers(1, 40))):
                mask[r % shape[0], c % shape[1]] = True
                r, c = r + rng.integers(0, 2), c + rng.integers(0, 2)
    for min_px in (0, 2, 5, 20):
        before = mask.copy()
        got = drop_specks(mask, min_px)
        want = mask if min_px <= 1 else _drop_specks_by_labels(mask, min_px)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(mask, before)  # the input is never written


def test_small_components_counts_and_clears_only_the_small_ones() -> None:
    m = np.zeros((6, 12), np.uint8)
    m[1, 1:4] = 1  # 3 px
    m[2, 4] = 1  # joins it diagonally: 4 px
    m[0:6, 8] = 1  # 6 px
    view = m[:, ::-1]  # strided
    assert rk.small_components(view, 5, False) == 4
    assert rk.small_components(view, 7, False) == 10
    assert rk.small_components(view, 5, True) == 4
    assert m.sum() == 6 and m[:, 8].all()


def test_noise_sigma_of_the_sampled_rows_is_that_of_the_image() -> None:
    from threadrecon.core.segment_raw import _NOISE_ROW_STEP, _log_channels, noise_sigma

    img = np.random.default_rng(8).integers(0, 256, (100, 90, 3), dtype=np.uint8)[:, :, ::-1]
    f = _log_channels(img)
    rows = _log_channels(img[::_NOISE_ROW_STEP])
    np.testing.assert_array_equal(noise_sigma(rows, row_step=1), noise_sigma(f))


@pytest.mark.parametrize("shape", [(480, 640), (2, 1), (3, 7)])  # cv2 takes 1x1 as a scalar
def test_at_least_is_cv2_compare_and_find_non_zero(shape: tuple[int, int]) -> None:
    from threadrecon.core.segment_raw import _points

    s = np.random.default_rng(shape[1]).random(shape, dtype=np.float32)
    s[0, 0] = np.float32(0.3)  # exactly at the threshold: kept
    for t in (0.3, 0.9, 2.0, 1 / 3):
        lo = np.empty(shape, np.uint8)
        rows, cols = rk.at_least(s, np.float32(t), lo)
        want = cv2.compare(s, t, cv2.CMP_GE)
        np.testing.assert_array_equal(lo, want)
        want_rows, want_cols = _points(want)
        np.testing.assert_array_equal(rows, want_rows)
        np.testing.assert_array_equal(cols, want_cols)


@pytest.mark.parametrize("m", [0, 1, 500])
def test_pixels_and_blocks_at_are_numpy_indexing(m: int) -> None:
    rng = np.random.default_rng(m)
    side = rng.integers(0, 256, (37, 2 * 51, 3), dtype=np.uint8)
    for img in (side[:, :51], side[:, 51:, ::-1], side[:, :51, :1]):  # strided views
        rows, cols = rng.integers(0, 37, m), rng.integers(0, 51, m)
        np.testing.assert_array_equal(rk.pixels_at(img, rows, cols), img[rows, cols])
    a = rng.random((9, 12, 3)).astype(np.float32)  # 37 // 4 = 9 rows: the last takes 4 + 1
    got = rk.blocks_at(a, rows, cols, 4)
    np.testing.assert_array_equal(got, a[np.minimum(rows // 4, 8), np.minimum(cols // 4, 11)])
    # a block side that is a power of two is a shift, any other a division: the same blocks
    for q in (1, 2, 3, 5, 8):
        b = rng.random((37 // q, 51 // q, 2)).astype(np.float32)
        want = b[np.minimum(rows // q, 37 // q - 1), np.minimum(cols // q, 51 // q - 1)]
        np.testing.assert_array_equal(rk.blocks_at(b, rows, cols, q), want, err_msg=str(q))


@pytest.mark.parametrize("shape", [(480, 640), (8, 12), (4, 4)])
def test_block_means_are_cv2_inter_area(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(shape[1])
    side = rng.integers(0, 256, (shape[0], 2 * shape[1], 3), dtype=np.uint8)
    img = side[:, : shape[1]]  # a strided view, as a side-by-side frame's half
    h, w = shape[0] // 4, shape[1] // 4
    got = rk.block_means(img.reshape(shape[0], -1), np.empty((h, 3 * w), np.float32))
    want = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA).reshape(h, 3 * w)
    np.testing.assert_array_equal(got, want)
    # Sums of exactly half a grey level round to the even neighbour, as cv2's do.
    flat = np.zeros((4, 4, 3), np.uint8)
    flat[0, :2] = 1  # 2 / 16 -> 0; 8 / 16 -> 0 (even); 24 / 16 -> 2 (even)
    flat[:, :, 1] = 0
    flat[:2, :, 1] = 1
    flat[:, :, 2] = 1
    flat[:2, :, 2] = 2
    got = rk.block_means(flat.reshape(4, 12), np.empty((1, 3), np.float32))
    want = cv2.resize(flat, (1, 1), interpolation=cv2.INTER_AREA).reshape(1, 3)
    np.testing.assert_array_equal(got, want)
    assert got.tolist() == [[0.0, 0.0, 2.0]]


def test_values_at_equals_the_fancy_index() -> None:
    rng = np.random.default_rng(3)
    a = rng.random((30, 40), dtype=np.float32)
    rows, cols = rng.integers(0, 30, 100), rng.integers(0, 40, 100)
    assert np.array_equal(rk.values_at(a, rows, cols), a[rows, cols])


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (7, 1), (2, 3), (37, 51), (120, 160)])
@pytest.mark.parametrize("seed", range(6))
def test_attached_is_the_components_holding_a_seed(shape: tuple[int, int], seed: int) -> None:
    """The 8-connected components of mask | seeds that hold a seed pixel, as
    cv2.connectedComponents labels them (diagonal contacts, runs at the image's edges, seeds
    outside the mask, no seed at all)."""
    rng = np.random.default_rng([3, seed])
    mask = random_mask(shape, seed + 20, fill=(0.1, 0.95), close_px=5)
    seeds = (rng.random(shape) < (0.0 if seed == 5 else 0.01 * (1 + seed))).astype(np.uint8)
    if seed % 2:  # seeds as blocks (an instrument), partly outside the mask
        seeds = cv2.dilate(seeds, np.ones((3, 3), np.uint8))
    both = mask | seeds
    n, labels = cv2.connectedComponents(both, connectivity=8, ltype=cv2.CV_32S)
    touching = np.zeros(n, bool)
    touching[labels[seeds > 0]] = True
    touching[0] = False
    out = np.full(shape, 7, np.uint8)  # every pixel is written
    got = rk.attached(mask, seeds, out)
    assert got is out
    np.testing.assert_array_equal(got, touching[labels].view(np.uint8))


def test_attached_joins_runs_that_touch_at_a_corner_only() -> None:
    mask = np.zeros((4, 8), np.uint8)
    mask[0, 0:2] = 1
    mask[1, 2:4] = 1  # touches (0, 1) diagonally
    mask[2, 5:7] = 1  # one column apart from (1, 3): not touching
    seeds = np.zeros_like(mask)
    seeds[0, 0] = 1
    got = rk.attached(mask, seeds, np.empty_like(mask))
    assert got[0, 0:2].all() and got[1, 2:4].all() and not got[2].any()
