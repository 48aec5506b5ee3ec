"""Tests of core/check_score.py: the per-point expected error behind the confidence, and the
typical error behind the automatic score."""

from __future__ import annotations

import numpy as np
import pytest
from support import synthetic_case

from threadrecon.core.check import CheckParams
from threadrecon.core.check_score import _expected_error, _local_mean, _typical
from threadrecon.core.pipeline import Pipeline


def test_local_mean_averages_over_the_window_along_the_arc() -> None:
    s = np.arange(10.0)  # unit spacing
    x = np.zeros(10)
    x[5] = 3.0
    m = _local_mean(x, s, 2.0)  # samples within 1 of each: three in the middle
    np.testing.assert_allclose(m[4:7], 1.0)
    assert m[0] == m[2] == m[8] == 0.0
    np.testing.assert_allclose(_local_mean(np.ones(10), s, 100.0), 1.0)  # window past the ends


def test_expected_error_is_twice_as_large_at_an_end_and_grows_with_the_residual() -> None:
    pair, calib, _ = synthetic_case(0)
    spline = Pipeline(pair, calib).run()["spline"]
    n, p = 201, CheckParams()
    z, step = np.full(n, 100.0), np.ones(n - 1)
    s3 = np.linspace(0.0, 100.0, n)  # mm
    e = _expected_error(z, np.full(n, 0.2), step, s3, spline, 500.0, p)
    mid = e[n // 2]
    np.testing.assert_allclose(e[[0, -1]], 2.0 * mid, rtol=1e-6)
    np.testing.assert_allclose(mid, 100.0**2 / 500.0 * np.hypot(p.sigma_disparity_px, 0.2))
    r = np.full(n, 0.2)
    r[90:110] = 2.0  # a stretch that disagrees with its reliable matches
    worse = _expected_error(z, r, step, s3, spline, 500.0, p)
    assert worse[n // 2] > 3 * mid and np.all(worse >= e - 1e-12)


def test_typical_error_is_not_swamped_by_a_few_large_points() -> None:
    e = np.full(100, 0.2)
    e[:3] = 50.0  # an interpolated stretch
    assert _typical(e) < 0.25 < float(np.mean(e))
    assert _typical(np.full(5, np.inf)) == pytest.approx(1e6)
