"""Tests of core/check_score.py: the per-point expected error behind the confidence, and the
typical error behind the automatic score."""

from __future__ import annotations

import numpy as np
import pytest
from support import synthetic_case

from threadrecon.core.check import CheckParams
from threadrecon.core.check_score import (
    _expected_error,
    _local_mean,
    _rating,
    _score,
    _typical,
    _unit_grid,
    _unsupported_gap,
    grasp_point,
    point_errors,
    quality_score,
)
from threadrecon.core.numeric import arc_px
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
    r[90:110] = 0.9  # a stretch that disagrees with its reliable matches (still supported)
    worse = _expected_error(z, r, step, s3, spline, 500.0, p)
    assert worse[n // 2] > 2 * mid and np.all(worse >= e - 1e-12)


def test_a_residual_beyond_the_support_tolerance_counts_as_the_tolerance() -> None:
    """A match that disagrees by 16 px (another strand's, on the same rows) says nothing
    more about the curve's error than one that disagrees by just over support_tol_px."""
    pair, calib, _ = synthetic_case(0)
    spline = Pipeline(pair, calib).run()["spline"]
    n, p = 201, CheckParams()
    z, step, s3 = np.full(n, 100.0), np.ones(n - 1), np.linspace(0.0, 100.0, n)
    r = np.full(n, 0.1)
    r[90:110] = 16.0
    at_tol = r.copy()
    at_tol[90:110] = p.support_tol_px
    e16 = _expected_error(z, r, step, s3, spline, 500.0, p)
    np.testing.assert_array_equal(e16, _expected_error(z, at_tol, step, s3, spline, 500.0, p))


def test_unsupported_points_drift_with_their_distance_to_a_supported_point() -> None:
    s3 = np.arange(11.0)  # mm
    sup = np.zeros(11, dtype=bool)
    sup[[2, 8]] = True
    np.testing.assert_array_equal(_unsupported_gap(s3, sup), [2, 1, 0, 1, 2, 3, 2, 1, 0, 1, 2])
    np.testing.assert_array_equal(_unsupported_gap(s3, np.zeros(11, dtype=bool)), np.full(11, 10.0))
    p = CheckParams()
    n = 11
    r = np.where(sup, 0.0, 5.0)
    pe = point_errors(
        np.full(n, 100.0), np.zeros(n, dtype=bool), r, np.zeros(n), np.zeros(n), np.ones(n - 1),
        s3 * 10.0, _FakeSpline(), 500.0, 5e4, 1.0, p,
    )  # fmt: skip
    d = pe.e_mm - _expected_error(
        np.full(n, 100.0), r, np.ones(n - 1), s3 * 10.0, _FakeSpline(), 5e4, p
    )
    np.testing.assert_allclose(d, p.bridge_error * _unsupported_gap(s3 * 10.0, sup))
    np.testing.assert_allclose(pe.confidence, np.exp(-pe.e_mm / p.conf_mm))


def test_reprojection_within_a_thread_pixel_adds_no_lateral_error() -> None:
    """The distance field reads up to half a pixel's diagonal at a point inside a thread
    pixel's cell (pixel quantisation); only the distance beyond it is a lateral error."""
    n, p = 11, CheckParams()
    s3 = np.arange(11.0) * 10.0

    def errors(rho: float):
        return point_errors(
            np.full(n, 100.0), np.zeros(n, dtype=bool), np.zeros(n), np.full(n, rho),
            np.zeros(n), np.ones(n - 1), s3, _FakeSpline(), 500.0, 5e4, 1.0, p,
        )  # fmt: skip

    on = errors(0.0)
    np.testing.assert_array_equal(errors(0.7).e_mm, on.e_mm)
    np.testing.assert_array_equal(errors(0.7).lateral_mm, 0.0)
    off = errors(2.0)
    np.testing.assert_allclose(off.lateral_mm, 100.0 / 500.0 * (2.0 - np.sqrt(0.5)))
    np.testing.assert_allclose(off.e_mm - on.e_mm, off.lateral_mm)


class _FakeSpline:
    ctrl = np.zeros((6, 3))
    degree = 3


def test_score_is_the_rounded_rating_and_falls_with_the_typical_error() -> None:
    m, q = 0.25, 2.0
    errors = np.geomspace(0.01, 100.0, 400)
    scores = [_score(e, "ok", m, q) for e in errors]
    ratings = [_rating(e, "ok", m, q) for e in errors]
    assert scores[0] == 5 and scores[-1] == 1
    assert np.all(np.diff(scores) <= 0) and np.all(np.diff(ratings) <= 0)
    assert all(1.0 <= x <= 5.0 for x in ratings)
    for s, x in zip(scores, ratings, strict=True):
        assert s == max(1, min(5, int(np.floor(x + 0.5)))) or abs(x - round(x) - 0.5) < 1e-9
    assert _score(0.1, "ok", m, q) == 5 and _score(0.3, "ok", m, q) == 4
    assert _score(0.6, "ok", m, q) == 3 and _score(1.5, "ok", m, q) == 2
    assert _score(2.5, "ok", m, q) == 1
    assert _score(0.01, "suspect", m, q) == 2 and _rating(0.01, "suspect", m, q) == 2.0
    assert _score(0.01, "failed", m, q) == 1 and _rating(0.01, "failed", m, q) == 1.0
    assert _rating(np.inf, "ok", m, q) == 1.0


def test_typical_error_is_not_swamped_by_a_few_large_points() -> None:
    e = np.full(100, 0.2)
    e[:3] = 50.0  # an interpolated stretch
    assert _typical(e, 2.0, "geometric") < 0.25 < float(np.mean(e))
    assert _typical(np.full(5, np.inf), 2.0, "geometric") == pytest.approx(1e6)
    # the mean-confidence error: the stretch counts by its share of the curve, never more
    assert _typical(e, 2.0, "confidence") < 0.2 - 2.0 * np.log(1.0 - 0.03) < 0.3 < float(np.mean(e))
    assert _typical(np.full(5, np.inf), 2.0, "confidence") == np.inf


def test_typical_error_is_the_error_of_the_curves_mean_confidence() -> None:
    """Equal e_i give that e; otherwise exp(-e / conf_mm) is the mean of the points'
    confidences, and the error lies between the geometric and the arithmetic mean of e_i for
    a spread of small errors (it ranks curves by their mean error, not by a few good points)."""
    assert _typical(np.full(7, 0.4), 2.0, "confidence") == pytest.approx(0.4)
    e = np.array([0.1, 0.2, 0.4, 0.8, 1.6])
    t = _typical(e, 2.0, "confidence")
    assert np.exp(-t / 2.0) == pytest.approx(np.mean(np.exp(-e / 2.0)))
    assert _typical(e, 2.0, "geometric") < t < float(np.mean(e))
    # two curves of one geometric mean: the one with the larger mean error reads worse
    a, b = np.array([0.2, 0.2]), np.array([0.04, 1.0])
    assert _typical(a, 2.0, "geometric") == pytest.approx(_typical(b, 2.0, "geometric"))
    assert _typical(b, 2.0, "confidence") > _typical(a, 2.0, "confidence")


def test_quality_score_reads_the_configured_average() -> None:
    e = np.array([0.04, 1.0])  # geometric mean 0.2 (score 5), mean-confidence error 0.46 (4)
    assert quality_score(e, "ok", CheckParams())[0] == 5  # the default: the geometric mean
    score, rating = quality_score(e, "ok", CheckParams(score_average="confidence"))
    assert score == 4 and rating == pytest.approx(
        _rating(_typical(e, 2.0, "confidence"), "ok", 0.25, 2.0)
    )


def test_typical_error_is_the_clipped_geometric_mean_bit_for_bit() -> None:
    # np.clip's values by np.minimum / np.maximum (issue 13): NaN stays NaN, inf clips to 1e6
    rng = np.random.default_rng(19)
    for e in (
        rng.lognormal(size=400),
        np.array([0.0, 1e-12, 2.0, np.inf]),
        np.array([np.nan, 1.0]),
    ):
        with np.errstate(divide="ignore"):
            want = float(np.exp(np.mean(np.log(np.clip(e, 1e-9, 1e6)))))
        got = _typical(e, 2.0, "geometric")
        assert got == want or (np.isnan(got) and np.isnan(want))


def test_unit_grid_is_linspace_and_read_only() -> None:
    for n in (2, 3, 400, 401):
        u = _unit_grid(n)
        assert u.tobytes() == np.linspace(0.0, 1.0, n).tobytes() and not u.flags.writeable
    assert _unit_grid(400) is _unit_grid(400)


def test_grasp_point_takes_the_free_end_away_from_the_border() -> None:
    # the start lies at the image border in the right view (or is not finite there): the grasp
    # point is taken from the end, whatever the confidence near the start
    p = CheckParams()
    n = 200
    x = np.linspace(2.0, 300.0, n)
    pts = np.column_stack([x * 0.1, np.full(n, 5.0), np.full(n, 100.0)])
    uv_l = np.column_stack([x + 20.0, np.full(n, 240.0)])
    conf = np.linspace(1.0, 0.1, n)  # the start is the more confident
    for bad in (2.0, np.nan):
        uv_r = uv_l - [20.0, 0.0]
        uv_r[0, 0] = bad
        g = grasp_point(pts, conf, uv_l, uv_r, (480, 640), 1.0, p)
        assert g is not None and g.from_end == "end"
    g = grasp_point(pts, conf, uv_l, uv_l - [10.0, 0.0], (480, 640), 1.0, p)
    assert g is not None and g.from_end == "start"


def test_the_arc_length_given_or_computed_gives_the_same_errors() -> None:
    # the check passes the left projection's arc length it already has (issue 13): the same
    # bits as point_errors computing it, non-finite steps counted as 0
    rng = np.random.default_rng(7)
    n, p = 60, CheckParams()
    step = rng.uniform(0.5, 2.0, n - 1)
    step[[5, 40]] = [np.nan, np.inf]
    s2 = arc_px(step)
    assert (
        s2[0] == 0.0
        and s2.tobytes()
        == np.concatenate([[0.0], np.cumsum(np.where(np.isfinite(step), step, 0.0))]).tobytes()
    )
    args = (
        rng.uniform(80, 120, n), np.zeros(n, dtype=bool), rng.uniform(0, 3, n),
        rng.uniform(0, 2, n), np.zeros(n), step, np.arange(n) * 1.5, _FakeSpline(), 500.0,
        5e4, 1.0, p,
    )  # fmt: skip
    a, b = point_errors(*args), point_errors(*args, s2=s2)
    assert a.e_mm.tobytes() == b.e_mm.tobytes()
    assert a.confidence.tobytes() == b.confidence.tobytes()
