"""Tests of core/bounds.py and core/spline.py: the MVS spline of Eq. (8) stays inside the depth
bounds of Eq. (7), is reversal-symmetric, and reports solver failures with a visible fallback."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.interpolate import BSpline
from support import assert_close, synthetic_case

from core.bounds import Bounds, BoundsParams, depth_bounds
from core.calibration import StereoCalibration
from core.camera import to_camera
from core.pipeline import Pipeline, ReconParams
from core.spline import SplineParams, SplineResult, fit_spline

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
    assert rec.status in ("suspect", "failed")  # the check stage weighs the fallback curve
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
        (SplineParams(xy_tol_px=0.0), "xy_tol_px"),
        (SplineParams(xy_knots="quadratic"), "xy_knots"),  # type: ignore[arg-type]
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


def _hook_bounds(calib: StereoCalibration) -> Bounds:
    """A thread in the image: 600 px straight, a hook of radius 15 px, 150 px straight back;
    points of H every ~8 px, depth a gentle wave with bounds of +-1 mm."""
    line = np.linspace(0.0, 600.0, 76)
    arc = np.linspace(0.0, np.pi, 8)[1:-1]
    xy = np.concatenate(
        [
            np.column_stack([100.0 + line, np.full_like(line, 200.0)]),
            np.column_stack([700.0 + 15.0 * np.sin(arc), 215.0 - 15.0 * np.cos(arc)]),
            np.column_stack([700.0 - line[:20], np.full(20, 230.0)]),
        ]
    )
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    z = 80.0 + 2.0 * np.sin(s / 150.0)
    dz = 2.0 / 150.0 * np.cos(s / 150.0)  # d depth / d s
    return Bounds(
        H=np.column_stack([xy, z]),
        is_key=np.ones(len(s), dtype=bool),
        s=s,
        centre=z,
        lower=z - 1.0,
        upper=z + 1.0,
        end_values=(float(z[0]), float(z[-1])),
        end_slopes=(float(dz[0]), float(dz[-1])),
        r_k=2,
    )


def _miss_px(sp: SplineResult, b: Bounds) -> np.ndarray:
    """2D distance of each point of H to S_x, S_y at its parameter."""
    return np.linalg.norm(BSpline(sp.knots, sp.ctrl, sp.degree)(sp.u_H)[:, :2] - b.H[:, :2], axis=1)


def test_adaptive_knots_gather_at_a_tight_hook() -> None:
    _, calib, _ = synthetic_case(0)
    b = _hook_bounds(calib)
    uni = fit_spline(b, calib, SplineParams(xy_knots="uniform"))
    ada = fit_spline(b, calib, SplineParams(xy_knots="adaptive"))
    assert uni.status == ada.status == "ok"
    assert _miss_px(uni, b).max() > 3.0  # the uniform knots cut the hook
    assert _miss_px(ada, b).max() < 0.5 * _miss_px(uni, b).max()
    assert np.median(_miss_px(ada, b)) < 0.2
    # Knots gather at the hook (s = 600..647 px along the path), none on the long straight.
    s_knots = np.unique(ada.knots) * (b.s[-1] / ada.length)
    added = np.setdiff1d(s_knots, np.unique(uni.knots) * (b.s[-1] / uni.length))
    assert added.size > 0 and np.all(added > 400.0)
    shortest = int(np.argmin(np.diff(s_knots)))
    assert 560.0 < 0.5 * (s_knots[shortest] + s_knots[shortest + 1]) < 690.0
    # The uniform knots stay: S_z keeps its m control points.
    assert np.all(np.isin(np.round(uni.knots, 9), np.round(ada.knots, 9)))


def test_gentle_thread_keeps_the_uniform_knots() -> None:
    _, calib, _ = synthetic_case(0)
    b = _hook_bounds(calib)
    theta = np.linspace(0.0, 0.5, len(b.s))  # a 600 px radius arc: no span misses 1 px
    xy = np.column_stack([400.0 + 600.0 * np.sin(theta), 800.0 - 600.0 * np.cos(theta)])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    gentle = replace(b, H=np.column_stack([xy, b.centre]), s=s)
    uni = fit_spline(gentle, calib, SplineParams(xy_knots="uniform"))
    ada = fit_spline(gentle, calib, SplineParams(xy_knots="adaptive"))
    assert_close(ada.knots, uni.knots)
    assert_close(ada.ctrl, uni.ctrl)


@pytest.mark.parametrize("seed", TRIALS[:4])
def test_adaptive_xy_knots_leave_the_depth_solution_unchanged(seed: int) -> None:
    b, calib = _bounds(seed)
    uni = fit_spline(b, calib, SplineParams(xy_knots="uniform"))
    ada = fit_spline(b, calib, SplineParams(xy_knots="adaptive", xy_tol_px=0.05))
    assert uni.status == ada.status == "ok"
    assert len(ada.ctrl) > len(uni.ctrl)  # a tiny tolerance refines every frame
    assert ada.objective == pytest.approx(uni.objective)
    u = np.linspace(0.0, uni.length, 500)
    for initial in (False, True):
        c_uni = uni.ctrl_init if initial else uni.ctrl
        c_ada = ada.ctrl_init if initial else ada.ctrl
        z_uni = BSpline(uni.knots, c_uni[:, 2], uni.degree)(u)
        z_ada = BSpline(ada.knots, c_ada[:, 2], ada.degree)(u)
        assert_close(z_ada, z_uni, rtol=0, atol=1e-9 * float(np.max(np.abs(z_uni))))


def test_hook_spline_maps_to_the_camera_frame() -> None:
    _, calib, _ = synthetic_case(0)
    b = _hook_bounds(calib)
    sp = fit_spline(b, calib)
    cam = to_camera(sp, calib)
    # The refined spline is one B-spline in (x, y, z): its camera curve reprojects onto S_x, S_y.
    uv = cam.points @ calib.G.T
    xy = sp.curve(len(cam.points))[:, :2]
    assert_close(uv[:, :2] / uv[:, 2:3], xy, rtol=0, atol=1e-6)
