"""Tests of the row runs of core/refine.py: their sub-pixel centres lie on the thread's axis
(not on the mask's, which cuts the edges' partial coverage off), their variances match the
centres' spread under noise, and a run beside something that is not background is doubted."""

import numpy as np
import pytest

from threadrecon.core.refine import EDGE_PX, FLANK_PX, _mask_runs, _Runs
from threadrecon.core.synthetic import StereoCamera, _render_tube

ROWS = 40


def _straight_thread(x0: float, slope: float, width: float, noise: float, seed: int):
    """A straight tube of ``width`` px through (x0, 0) with dx/dy = ``slope``, rendered by the
    generator over a flat background of 205: grey image, mask (coverage >= 0.5) and the true
    axis column on every row."""
    cam = StereoCamera(width=64, height=ROWS)
    y = np.linspace(-20.0, ROWS + 20.0, 400)
    uv = np.stack([x0 + slope * y, y], 1)
    z = np.full(len(y), cam.fx * 0.5 / width)  # a 0.5 mm tube seen ``width`` px wide
    bg = np.full((ROWS, 64, 3), 205.0, np.float32)
    img, cov = _render_tube(uv, z, cam, 0.5, np.array([120.0, 120.0, 120.0]), 0.08, bg)
    grey = img.mean(axis=2) + np.random.default_rng(seed).normal(0.0, noise, (ROWS, 64))
    grey = np.clip(np.rint(grey), 0, 255).astype(np.float32)
    return grey, cov >= 0.5, x0 + slope * np.arange(ROWS)


@pytest.mark.parametrize("width", [1.6, 2.5, 3.4, 4.7, 6.2])
def test_run_centres_lie_on_the_axis_where_the_mask_cuts_the_edges_off(width: float) -> None:
    """Over sub-pixel positions of the axis (noise-free), the centres' RMS error is below
    0.08 px (``MODEL_PX``: the sampled shading locks them to the pixels a little), less than
    half that of the mask's own midpoint, which the edge pixels below 0.5 coverage do not
    reach (0.15-0.2 px RMS, up to 0.4 px)."""
    rng = np.random.default_rng(int(width * 10))
    err_c, err_mid = [], []
    for _ in range(6):
        x0, slope = rng.uniform(24.0, 40.0), rng.uniform(-0.3, 0.3)
        grey, mask, axis = _straight_thread(x0, slope, width, 0.0, 0)
        runs = _Runs(mask, grey, 205.0)
        rows = np.arange(ROWS)
        idx = runs.nearest_index(rows, axis)
        c, ln = runs.at(idx)
        assert np.all(idx >= 0)
        err_c.append(c - axis)
        starts = np.array([np.flatnonzero(mask[r])[0] for r in rows])
        err_mid.append(starts + 0.5 * (ln - 1) - axis)
    err_c, err_mid = np.concatenate(err_c), np.concatenate(err_mid)
    rms_c, rms_mid = np.sqrt(np.mean(err_c**2)), np.sqrt(np.mean(err_mid**2))
    assert rms_c < 0.08 and np.abs(err_c).max() < 0.13, (rms_c, np.abs(err_c).max())
    assert rms_c < 0.5 * rms_mid  # what the mask alone gives


def test_run_centre_variance_matches_the_spread_under_noise() -> None:
    """With 4 grey levels of noise, the centres' RMS error about the axis lies within a factor
    1.5 of the predicted standard deviation."""
    errs, sds = [], []
    for seed in range(8):
        grey, mask, axis = _straight_thread(31.3 + 0.17 * seed, 0.1, 3.5, 4.0, seed)
        runs = _Runs(mask, grey, 205.0)
        idx = runs.nearest_index(np.arange(ROWS), axis)
        c, _ = runs.at(idx)
        errs.append(c - axis)
        sds.append(np.sqrt(runs.var[idx]))
    rms = float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))
    sd = float(np.sqrt(np.mean(np.concatenate(sds) ** 2)))
    assert sd / 1.5 < rms < 1.5 * sd + 0.02, (rms, sd)


def test_a_run_beside_an_occluder_is_doubted() -> None:
    """A dark occluder right beside the run on one side (its flanks disagree by 150 grey
    levels): the centre's variance grows by orders of magnitude."""
    grey, mask, _ = _straight_thread(30.2, 0.0, 3.5, 0.0, 0)
    runs = _Runs(mask, grey, 205.0)
    covered = grey.copy()
    covered[:, 34:] = 55.0  # an instrument from column 34 on
    doubted = _Runs(mask & (np.arange(64) < 34), covered, 205.0)
    assert np.all(doubted.var > 100 * runs.var)


def test_runs_without_a_flank_or_contrast_fall_back_to_the_mask() -> None:
    """At the image border (no flank) or without contrast the centre is the run's midpoint and
    its variance that of a uniform position over the run, (L^2 + 1) / 12."""
    mask = np.zeros((2, 12), dtype=bool)
    mask[0, 0:3] = True  # touches the left border
    mask[1, 5:9] = True  # no contrast: the grey image is flat
    runs = _Runs(mask, np.full(mask.shape, 205.0, np.float32), 205.0)
    np.testing.assert_allclose(runs.centre, [1.0, 6.5])
    np.testing.assert_allclose(runs.var, [10.0 / 12.0, 17.0 / 12.0])


def test_spans_enumerate_every_column_of_each_span() -> None:
    item, col = _spans(np.array([3, 7, 5, 0]), np.array([5, 6, 5, 1]))  # the second is empty
    np.testing.assert_array_equal(item, [0, 0, 0, 2, 3, 3])
    np.testing.assert_array_equal(col, [3, 4, 5, 5, 0, 1])


def _runs_by_nonzero(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row, first and last column of each run, from np.nonzero (row-major)."""
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return ys, xs, xs
    new = np.ones(len(xs), dtype=bool)
    new[1:] = (np.diff(xs) != 1) | (np.diff(ys) != 0)
    start = np.flatnonzero(new)
    end = np.append(start[1:], len(xs)) - 1
    return ys[start], xs[start], xs[end]


@pytest.mark.parametrize("width", [64, 61, 8, 1])
def test_mask_runs_are_those_of_nonzero(width: int) -> None:
    """The kernel's runs (a word at a time where the width is a multiple of 8, else inside
    the bounding box) are the maximal row segments of np.nonzero, for random, empty and full
    masks and runs touching the image's borders."""
    rng = np.random.default_rng(width)
    masks = [
        rng.random((30, width)) < 0.3,
        np.zeros((30, width), bool),
        np.ones((30, width), bool),
        np.pad(rng.random((20, max(width - 6, 1))) < 0.5, ((4, 6), (3, 3)))[:, :width],
    ]
    for mask in masks:
        got = _mask_runs(mask)
        want = _runs_by_nonzero(mask)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("seed", range(6))
def test_run_centres_are_the_numpy_models_bit_for_bit(seed: int) -> None:
    """The compiled centres and variances equal the numpy form of the model (below) to the
    last bit: random masks of several strands on a noisy, textured grey image, a dark and a
    light thread, runs at the image borders and close together (their windows share the gap)."""
    rng = np.random.default_rng(seed)
    H, W = 40, 72 if seed % 2 else 67
    grey = 150.0 + 30.0 * np.sin(np.arange(W) / 5.0)[None, :] + rng.normal(0, 3, (H, W))
    mask = rng.random((H, W)) < 0.15 + 0.05 * seed
    mask[:, :2] |= seed == 3  # runs at the left border
    grey = np.where(mask, grey + (60.0 if seed == 4 else -70.0), grey)
    grey = np.clip(np.rint(grey), 0, 255).astype(np.float32)
    runs = _Runs(mask, grey, 200.0)
    row, a, b = _runs_by_nonzero(mask)
    c, v = _edge_centres(row, a, b, grey, 200.0, W)
    assert runs.centre.size == len(a) > 50
    np.testing.assert_array_equal(runs.centre.view(np.uint64), c.view(np.uint64))
    np.testing.assert_array_equal(runs.var.view(np.uint64), v.view(np.uint64))
    assert (runs.centre != 0.5 * (a + b)).mean() > 0.3  # mostly from the contrast, not the mask


# The numpy form of the run centres that core/refine_kernel.py's edge_centres replaced (its
# floating-point operations in the same order): the reference of the bit-for-bit test above.
def _edge_centres(
    row: np.ndarray, a: np.ndarray, b: np.ndarray, grey: np.ndarray, background: float, W: int
) -> tuple[np.ndarray, np.ndarray]:
    """Centres (R,) px and variances (R,) px^2 of the runs a..b on rows ``row``: the model
    of ``refine_kernel.edge_centres`` in numpy."""
    n = len(a)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    g = grey
    same_prev = np.zeros(n, dtype=bool)
    same_prev[1:] = row[1:] == row[:-1]
    prev_end = np.full(n, -1)
    prev_end[1:] = np.where(same_prev[1:], b[:-1], -1)
    next_start = np.full(n, W)
    next_start[:-1] = np.where(same_prev[1:], a[1:], W)
    lo = a - np.minimum(EDGE_PX, (a - prev_end - 1) // 2)
    hi = b + np.minimum(EDGE_PX, (next_start - b - 1) // 2)
    fl_lo, fl_hi = np.maximum(lo - FLANK_PX, prev_end + 1), lo - 1  # left flank
    fr_lo, fr_hi = hi + 1, np.minimum(hi + FLANK_PX, next_start - 1)  # right flank
    it_l, x_l = _spans(fl_lo, fl_hi)
    it_r, x_r = _spans(fr_lo, fr_hi)
    v_l, v_r = g[row[it_l], x_l].astype(np.float64), g[row[it_r], x_r].astype(np.float64)
    n_l, n_r = np.maximum(fl_hi - fl_lo + 1, 0), np.maximum(fr_hi - fr_lo + 1, 0)
    flanked = (n_l > 0) & (n_r > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        b_l = np.where(flanked, np.bincount(it_l, v_l, minlength=n) / n_l, background)
        b_r = np.where(flanked, np.bincount(it_r, v_r, minlength=n) / n_r, background)
    x0 = np.where(flanked, 0.5 * (fl_lo + fl_hi), lo - 1.0)  # the flanks' mean columns
    x1 = np.where(flanked, 0.5 * (fr_lo + fr_hi), hi + 1.0)
    noise = _noise_var(it_l, x_l, v_l, it_r, x_r, v_r)
    it, x = _spans(lo, hi)
    slope = (b_r - b_l) / (x1 - x0)
    w = b_l[it] + slope[it] * (x - x0[it]) - g[row[it], x]  # contrast, signed
    on_run = (x >= a[it]) & (x <= b[it])
    lighter = np.bincount(it, np.where(on_run, w, 0.0), minlength=n) < 0  # than its background
    sign = np.where(lighter, -1.0, 1.0)
    sw = sign * np.bincount(it, w, minlength=n)
    swx = sign * np.bincount(it, w * x, minlength=n)
    # sums over the window's columns: n, sum x, sum x^2 (closed forms)
    s0 = (hi - lo + 1).astype(np.float64)
    s1 = 0.5 * s0 * (lo + hi)
    s2 = (hi * (hi + 1.0) * (2 * hi + 1.0) - (lo - 1.0) * lo * (2 * lo - 1.0)) / 6.0
    with np.errstate(invalid="ignore", divide="ignore"):
        c = swx / sw
        sdx2 = s2 - 2.0 * c * s1 + s0 * c * c  # sum (x - c)^2
        sdx_tau = (s2 - (c + x0) * s1 + s0 * c * x0) / (x1 - x0)  # sum (x - c) tau
        sdx_1mtau = s1 - s0 * c - sdx_tau  # sum (x - c) (1 - tau)
        s_b = noise / FLANK_PX + 0.25 * (b_l - b_r) ** 2  # variance of each flank level
        var = (noise * sdx2 + s_b * (sdx_1mtau**2 + sdx_tau**2)) / sw**2
    mid = 0.5 * (a + b)
    var_mask = ((b - a + 1.0) ** 2 + 1.0) / 12.0
    # significant contrast: the centroid's noise below the mask's own uncertainty
    good = flanked & (sw > 0) & np.isfinite(c) & (c >= lo) & (c <= hi) & (var < var_mask)
    return np.where(good, c, mid), np.where(good, var, var_mask)


def _spans(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Item index and column of every column of the spans lo..hi (inclusive; empty where
    hi < lo), item by item."""
    counts = np.maximum(hi - lo + 1, 0)
    item = np.repeat(np.arange(len(lo)), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return item, np.arange(int(counts.sum())) - np.repeat(first - lo, counts)


def _noise_var(
    it_l: np.ndarray,
    x_l: np.ndarray,
    v_l: np.ndarray,
    it_r: np.ndarray,
    x_r: np.ndarray,
    v_r: np.ndarray,
) -> float:
    """Pixel noise variance sigma_n^2, grey levels^2, from the differences of neighbouring
    flank pixels (median of their squares / 0.4549, the median of chi^2 with one degree of
    freedom, / 2 for a difference of two pixels); at least two roundings to 8 bits."""
    diffs = [
        v[1:][(it[1:] == it[:-1]) & (x[1:] == x[:-1] + 1)]
        - v[:-1][(it[1:] == it[:-1]) & (x[1:] == x[:-1] + 1)]
        for it, x, v in ((it_l, x_l, v_l), (it_r, x_r, v_r))
    ]
    d = np.concatenate(diffs)
    est = float(np.median(d * d)) / 0.4549 / 2.0 if d.size >= 20 else 0.0
    return max(est, 2.0 / 12.0)
