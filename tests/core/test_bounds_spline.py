"""Tests of core/bounds.py and core/spline.py: the MVS spline of Eq. (8) stays inside the depth
bounds of Eq. (7), is reversal-symmetric, and reports solver failures with a visible fallback."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.interpolate import BSpline
from support import assert_close, synthetic_case

from core.bounds import Bounds, BoundsParams, depth_bounds
from core.calibration import StereoCalibration
from core.pipeline import Pipeline, ReconParams
from core.spline import SplineParams, fit_spline

TRIALS = tuple(range(8))


def _bounds(seed: int) -> tuple[Bounds, StereoCalibration]:
    pair, calib, _ = synthetic_case(seed)
    rec = Pipeline(pair, calib).run(until="bounds")
    assert rec.status == "ok", rec.message
    return rec["bounds"], calib


def _reversed(b: Bounds) -> Bounds:
    """The same bounds with the thread walked from its other end."""
    return replace(
        b,
        H=b.H[::-1].copy(),
        is_key=b.is_key[::-1].copy(),
        s=b.s[-1] - b.s[::-1],
        centre=b.centre[::-1].copy(),
        lower=b.lower[::-1].copy(),
        upper=b.upper[::-1].copy(),
        end_values=(b.end_values[1], b.end_values[0]),
        end_slopes=(-b.end_slopes[1], -b.end_slopes[0]),
    )


@pytest.mark.parametrize("seed", TRIALS)
def test_bounds_are_ordered_and_cover_the_keypoints(seed: int) -> None:
    b, calib = _bounds(seed)
    P = len(b.H)
    assert b.H.shape == (P, 3) and b.s.shape == b.centre.shape == b.lower.shape == (P,)
    assert np.all(np.diff(b.s) >= 0) and b.s[0] == 0
    assert np.all(b.lower < b.centre) and np.all(b.centre < b.upper)
    assert_close(b.centre[b.is_key], b.H[b.is_key, 2])
    # Half-widths at keypoints are at least widen_px of disparity (Eq. (7) widening).
    p = BoundsParams()
    min_half = p.widen_px * b.centre**2 / (calib.focal * calib.baseline)
    assert np.all((b.upper - b.lower)[b.is_key] / 2 >= min_half[b.is_key] * (1 - 1e-9))


@pytest.mark.parametrize("seed", TRIALS)
def test_spline_stays_inside_its_depth_bounds(seed: int) -> None:
    b, calib = _bounds(seed)
    p = SplineParams()
    sp = fit_spline(b, calib, p)
    assert sp.status == "ok", sp.message
    assert sp.max_violation <= p.bound_tol
    # Independent check at the points of H.
    z = sp.curve(4000)
    z_H = BSpline(sp.knots, sp.ctrl, sp.degree)(sp.u_H)[:, 2]
    half = 0.5 * (b.upper - b.lower)
    excursion = np.maximum(b.lower - z_H, z_H - b.upper) / half
    assert np.all(excursion <= p.bound_tol + 1e-9)
    assert np.all(np.isfinite(z))


@pytest.mark.parametrize("seed", TRIALS[:5])
def test_reversing_the_thread_reverses_the_curve(seed: int) -> None:
    b, calib = _bounds(seed)
    fwd = fit_spline(b, calib)
    rev = fit_spline(_reversed(b), calib)
    assert fwd.status == rev.status == "ok"
    c_fwd, c_rev = fwd.curve(200), rev.curve(200)[::-1]
    depth_range = float(np.ptp(b.centre)) or 1.0
    assert np.max(np.abs(c_fwd[:, :2] - c_rev[:, :2])) < 0.05
    assert np.max(np.abs(c_fwd[:, 2] - c_rev[:, 2])) < 1e-3 * depth_range


def test_solver_failure_returns_the_initial_spline_as_visible_fallback() -> None:
    pair, calib, _ = synthetic_case(0)
    params = ReconParams(spline=SplineParams(max_iter=1))
    rec = Pipeline(pair, calib).run(params)
    sp = rec["spline"]
    assert sp.status != "ok"
    assert not sp.ok
    assert_close(sp.ctrl, sp.ctrl_init)
    assert sp.objective[0] == sp.objective[1]
    assert rec.status == "failed"
    assert rec.failed_stage is None  # the stage ran; its result was rejected
    assert "fallback" in rec.message
    assert "camera" in rec.runs  # the fallback curve is still shown


def test_impossible_bounds_are_reported_not_hidden() -> None:
    b, calib = _bounds(1)
    # Upper below lower everywhere: no spline satisfies Eq. (8)'s constraints.
    bad = replace(b, lower=b.upper + 1.0, upper=b.lower - 1.0)
    sp = fit_spline(bad, calib)
    assert sp.status in ("solver_failed", "out_of_bounds")
    assert_close(sp.ctrl, sp.ctrl_init)
    assert sp.message


def test_optimise_false_keeps_the_initial_spline() -> None:
    b, calib = _bounds(2)
    sp = fit_spline(b, calib, SplineParams(optimise=False))
    assert sp.status == "skipped" and sp.ok
    assert_close(sp.ctrl, sp.ctrl_init)


@pytest.mark.parametrize(
    ("params", "match"),
    [
        (SplineParams(degree=1), "degree"),
        (SplineParams(degree=6), "degree"),
        (SplineParams(degree=4, n_ctrl=4), "n_ctrl"),
        (SplineParams(max_iter=0), "max_iter"),
        (SplineParams(quad_per_span=0), "quad_per_span"),
    ],
)
def test_invalid_spline_parameters_raise(params: SplineParams, match: str) -> None:
    b, calib = _bounds(0)
    with pytest.raises(ValueError, match=match):
        fit_spline(b, calib, params)


def test_invalid_bounds_parameters_raise() -> None:
    pair, calib, _ = synthetic_case(0)
    rec = Pipeline(pair, calib).run(until="ordering")
    with pytest.raises(ValueError, match="extra_px"):
        depth_bounds(rec["stereo"], rec["ordering"], calib, BoundsParams(extra_px=0))
    with pytest.raises(ValueError, match="bound_scale"):
        depth_bounds(rec["stereo"], rec["ordering"], calib, BoundsParams(bound_scale=0.0))
