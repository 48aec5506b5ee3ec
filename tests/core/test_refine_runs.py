"""Tests of the row runs of core/refine.py: their sub-pixel centres lie on the thread's axis
(not on the mask's, which cuts the edges' partial coverage off), their variances match the
centres' spread under noise, and a run beside something that is not background is doubted."""

import numpy as np
import pytest

from threadrecon.core.refine import _Runs, _spans
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
