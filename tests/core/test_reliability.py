"""Tests of core/reliability.py: the reliability measure R of Eq. (6) and pruning."""

import numpy as np
import pytest
from support import assert_close

from threadrecon.core.reliability import ReliabilityParams, prune, reliability
from threadrecon.core.stereo import StereoResult

TRIALS = 20


def test_default_eps_values_are_the_papers() -> None:
    p = ReliabilityParams()
    assert (p.eps1, p.eps2, p.eps3, p.threshold) == (8.0, 5.0, 0.8, 0.9)


@pytest.mark.parametrize("seed", range(TRIALS))
def test_reliability_is_monotone_in_energy_gap(seed: int) -> None:
    rng = np.random.default_rng(seed)
    e_min = float(rng.uniform(1.0, 1e5))
    gaps = np.sort(rng.uniform(0.0, 50.0 * e_min, 200))
    p = ReliabilityParams(
        eps1=float(rng.uniform(1, 20)),
        eps2=float(rng.uniform(1, 10)),
        eps3=float(rng.uniform(0, 2)),
    )
    R = reliability(np.full(gaps.size, e_min), e_min + gaps, p)
    assert np.all(np.isfinite(R))
    assert np.all((R >= 0.0) & (R <= 1.0))
    assert np.all(np.diff(R) >= 0.0)


@pytest.mark.parametrize("seed", range(5))
def test_reliability_decreases_with_e_min_at_fixed_e_next(seed: int) -> None:
    rng = np.random.default_rng(seed)
    e_next = float(rng.uniform(1e3, 1e5))
    e_min = np.sort(rng.uniform(1.0, e_next, 200))
    assert np.all(np.diff(reliability(e_min, np.full(e_min.size, e_next))) <= 0.0)


def test_reliability_matches_sigmoid_formula() -> None:
    rng = np.random.default_rng(7)
    e_min = rng.uniform(1.0, 100.0, 50)
    e_next = e_min + rng.uniform(0.0, 500.0, 50)
    p = ReliabilityParams()
    z = p.eps1 * ((e_next - e_min) / (p.eps2 * e_min) - p.eps3)
    assert_close(reliability(e_min, e_next, p), 1.0 / (1.0 + np.exp(-z)), rtol=1e-12, atol=1e-15)


def test_perfect_match_gives_r_one_without_nan() -> None:
    R = reliability(np.zeros(3), np.array([1.0, 1e3, np.inf]))
    assert not np.any(np.isnan(R))
    assert_close(R, np.ones(3))
    # E_min = E_next = 0 (no contrast at all) is not reliable, and still not NaN.
    R0 = reliability(np.zeros(1), np.zeros(1))
    assert np.isfinite(R0).all() and R0[0] < 0.5
    # No second candidate: E_next = inf.
    assert_close(reliability(np.array([5.0]), np.array([np.inf])), np.ones(1))


def _stereo(E_min: np.ndarray, E_next: np.ndarray, depth: np.ndarray) -> StereoResult:
    n = E_min.size
    pts = np.column_stack([np.zeros(n), np.zeros(n), depth])
    return StereoResult(
        pixels=np.column_stack([np.arange(n), np.zeros(n, int)]),
        d_min=np.zeros(n, int),
        d_next=np.full(n, 4),
        E_min=E_min,
        E_next=E_next,
        disparity=np.ones(n),
        points=pts,
        depth=depth,
        shape=(1, max(n, 1)),
        d_range=(0, 4),
    )


def test_reliable_means_r_strictly_above_threshold_and_finite_depth() -> None:
    rng = np.random.default_rng(3)
    n = 300
    E_min = rng.uniform(1.0, 100.0, n)
    E_next = E_min * (1.0 + rng.uniform(0.0, 20.0, n))
    depth = rng.uniform(50.0, 150.0, n)
    depth[::17] = np.nan
    st = _stereo(E_min, E_next, depth)
    p = ReliabilityParams()
    res = prune(st, p)
    assert_close(res.R, reliability(E_min, E_next, p))
    assert_close(res.reliable, (p.threshold < res.R) & np.isfinite(depth))
    assert res.count == int(res.reliable.sum())
    # R equal to the threshold is not reliable (strict >).
    i = int(np.argmax((res.R > 0.1) & (res.R < 0.99) & np.isfinite(depth)))
    at = prune(st, ReliabilityParams(threshold=float(res.R[i])))
    assert not at.reliable[i]


def test_invalid_parameters_raise() -> None:
    st = _stereo(np.ones(2), np.full(2, 10.0), np.ones(2))
    with pytest.raises(ValueError, match="threshold"):
        prune(st, ReliabilityParams(threshold=1.0))
    with pytest.raises(ValueError, match="eps2"):
        reliability(np.ones(2), np.ones(2), ReliabilityParams(eps2=0.0))
