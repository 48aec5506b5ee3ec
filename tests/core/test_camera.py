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


def test_a_rerun_on_the_same_knots_reuses_the_refit_and_gives_the_same_curve() -> None:
    # A solver parameter's re-run: new control points on a new copy of the same knots. The
    # refit's basis and factor come from the cache; the result is the uncached computation's.
    from dataclasses import replace

    from support import synthetic_case

    from threadrecon.core import camera
    from threadrecon.core.pipeline import Pipeline

    pair, calib, _ = synthetic_case(0)
    sp = Pipeline(pair, calib).run(until="refine")["refine"]
    camera._REFITS.clear()
    first = camera.to_camera(sp, calib)
    assert len(camera._REFITS) == 1
    moved = replace(sp, knots=sp.knots.copy(), ctrl=sp.ctrl + 0.5)
    second = camera.to_camera(moved, calib)
    assert len(camera._REFITS) == 1  # a hit
    camera._REFITS.clear()
    fresh = camera.to_camera(moved, calib)
    assert second.ctrl.tobytes() == fresh.ctrl.tobytes()
    assert second.points.tobytes() == fresh.points.tobytes()
    assert not np.array_equal(first.ctrl, second.ctrl)
