"""Tests of core/camera.py's least-squares refit, Eq. (9)."""

import numpy as np
import pytest
from support import assert_close

from threadrecon.core.camera import _least_squares
from threadrecon.core.spline import basis_matrix


@pytest.mark.parametrize("seed", range(5))
def test_refit_least_squares_equals_the_svd_solution(seed: int) -> None:
    rng = np.random.default_rng(seed)
    k, m = 4, int(rng.integers(6, 90))
    inner = np.sort(rng.uniform(0.0, 1.0, m - k - 1))
    t = np.concatenate([np.zeros(k + 1), inner, np.ones(k + 1)])
    u = np.linspace(0.0, 1.0, max(400, 8 * m))
    B = basis_matrix(u, t, k)
    y = rng.normal(size=(len(u), 3))
    ref = np.linalg.lstsq(B, y, rcond=None)[0]
    assert_close(_least_squares(B, y), ref, rtol=1e-8, atol=1e-8 * np.abs(ref).max())


def test_rank_deficient_refit_falls_back_to_the_minimum_norm_solution() -> None:
    rng = np.random.default_rng(0)
    B = rng.normal(size=(50, 4))
    B = np.column_stack([B, B[:, 0]])  # a repeated column: B^T B is singular
    y = rng.normal(size=(50, 3))
    assert_close(_least_squares(B, y), np.linalg.lstsq(B, y, rcond=None)[0], rtol=1e-9)


def test_compiled_refit_is_the_least_squares_fit_of_the_mapped_curve() -> None:
    """camera_refit (the basis banded, a banded Cholesky factor) against the dense numpy
    form: S(u) at n uniform u by BSpline, Eq. (9) by np.linalg.solve, the normal equations by
    LAPACK; degrees 2-5, uniform and refined knots, several sample counts."""
    from scipy.interpolate import BSpline

    from threadrecon.core import spline_kernel
    from threadrecon.core.camera import COND_FLOOR, image_to_camera
    from threadrecon.core.spline import basis_matrix

    rng = np.random.default_rng(6)
    G = np.array([[800.0, 0.3, 320.0], [0.0, 805.0, 240.0], [0.0, 0.0, 1.0]])
    for _ in range(30):
        k = int(rng.integers(2, 6))
        m = int(rng.integers(k + 1, 60))
        inner = np.sort(rng.uniform(0.0, 1.0, m - k - 1))
        t = np.concatenate([np.zeros(k + 1), inner, np.ones(k + 1)])
        ctrl = np.column_stack(
            [rng.uniform(0, 640, m), rng.uniform(0, 480, m), rng.uniform(60, 150, m)]
        )
        n = int(max(rng.integers(200, 900), 8 * m))
        c, pts, status = spline_kernel.camera_refit(t, k, ctrl, n, np.linalg.inv(G), COND_FLOOR)
        u = np.linspace(0.0, 1.0, n)
        dense = image_to_camera(BSpline(t, ctrl, k)(u), G)
        assert_close(pts, dense, rtol=1e-12, atol=1e-9)
        if status:
            continue  # ill-conditioned knots (random inner knots close together)
        want = _least_squares(basis_matrix(u, t, k), dense)
        assert_close(c, want, rtol=1e-7, atol=1e-7 * np.abs(want).max())


def test_camera_curve_length_is_numpys_norm_sum_bit_for_bit() -> None:
    """to_camera's arc length (the point steps' norms written out, and the paper mode's
    points by spline.evaluate) equals np.linalg.norm(np.diff(points), axis=1).sum() exactly."""
    from types import SimpleNamespace

    from threadrecon.core.camera import CameraParams, to_camera
    from threadrecon.core.spline import SplineResult

    rng = np.random.default_rng(4)
    G = np.array([[800.0, 0.0, 320.0, 0.0], [0.0, 800.0, 240.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    calib = SimpleNamespace(G=G[:, :3], unit="mm")
    for mode in ("refit", "paper"):
        for _ in range(10):
            k, m, length = 4, int(rng.integers(5, 40)), float(rng.uniform(5.0, 200.0))
            t = np.concatenate(
                [np.zeros(k + 1), np.linspace(0.0, length, m - k + 1)[1:-1], np.full(k + 1, length)]
            )
            ctrl = np.column_stack(
                [rng.uniform(0, 640, m), rng.uniform(0, 480, m), rng.uniform(60, 150, m)]
            )
            s = SplineResult(t, ctrl, ctrl, k, length, np.zeros(2), "ok", "", (0.0, 0.0), 0, 0.0)
            curve = to_camera(
                s, calib, CameraParams(n_points=int(rng.integers(200, 900)), mode=mode)
            )
            want = float(np.linalg.norm(np.diff(curve.points, axis=0), axis=1).sum())
            assert curve.length == want
