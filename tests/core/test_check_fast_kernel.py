"""The check's second-pass kernels against the numpy and scipy forms they replace."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from threadrecon.core import check_fast_kernel as fk


def _pairs(p: np.ndarray) -> set[tuple[int, int]]:
    return {(int(i), int(j)) for i, j in p}


@pytest.mark.parametrize("r", [0.5, 1.0, 1.5, 3.0, 7.25])
def test_close_pairs_are_the_kd_trees_pairs(r: float) -> None:
    rng = np.random.default_rng(int(r * 100))
    for trial in range(20):
        n = int(rng.integers(0, 300))
        if trial % 2:  # on a grid: many distances exactly r
            p = rng.integers(0, 12, size=(n, 2)).astype(np.float64) * rng.choice([0.5, 1.0])
        else:  # along a wiggly curve, as a projected thread
            p = np.cumsum(rng.normal(0.0, 1.0, (n, 2)), axis=0)
        s = np.arange(n, dtype=np.float64) * rng.uniform(0.5, 2.0)  # arc length
        want = cKDTree(p).query_pairs(r, output_type="ndarray") if n else np.zeros((0, 2), int)
        for gap in (-1.0, 3.0, 7.5):
            got = fk.close_pairs(p[:, 0].copy(), p[:, 1].copy(), s, r, gap)
            assert got.shape[1] == 2 and np.all(got[:, 0] < got[:, 1])
            assert len(got) == len(_pairs(got))  # each pair once
            apart = want[np.abs(s[want[:, 0]] - s[want[:, 1]]) > gap]
            assert _pairs(got) == _pairs(apart), (trial, n, gap)


def test_close_pairs_grow_past_their_first_guess() -> None:
    p = np.zeros((50, 2))  # every pair: 1225 > the first 16
    got = fk.close_pairs(p[:, 0].copy(), p[:, 1].copy(), np.zeros(50), 0.1, -1.0)
    assert _pairs(got) == {(i, j) for i in range(50) for j in range(i + 1, 50)}


def test_ring_level_is_numpys_median_and_deviation_of_the_ring() -> None:
    rng = np.random.default_rng(5)
    for trial in range(30):
        h, w = rng.integers(1, 30, size=2)
        d = (rng.random((h, w)) * 12).astype(np.float32)
        d[rng.random((h, w)) < 0.2] = 3.0  # on the ring's open inner edge: left out
        grey = np.rint(rng.normal(120, 20, (h, w)))  # integer levels: many ties
        got = fk.ring_level(d[:, ::-1], grey, 3.0, 9.0, 10)  # a strided field, as cropped
        ring = (d[:, ::-1] > 3.0) & (d[:, ::-1] <= 9.0)
        vals = grey[ring]
        assert got[0] == vals.size, trial
        if vals.size < 10:
            assert np.isnan(got[1]) and np.isnan(got[2])
            continue
        med = float(np.median(vals))
        assert got[1] == med and got[2] == float(np.median(np.abs(vals - med))), trial


def test_flag_runs_are_the_runs_of_true() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        flag = rng.random(int(rng.integers(0, 40))) < rng.uniform(0.0, 1.0)
        d = np.diff(np.concatenate([[0], flag.astype(np.int8), [0]]))
        want = np.column_stack([np.flatnonzero(d == 1), np.flatnonzero(d == -1)])
        assert np.array_equal(fk.flag_runs(flag), want.reshape(-1, 2))
