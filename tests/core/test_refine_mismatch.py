"""Tests of core/refine.py's test for a strand matched to its neighbour (``_mismatched``): its
tolerance grows with the runs' length, as the run-centre disparity's uncertainty does, and
stays below the distance of the neighbour strand; and of NaN-safe image rows."""

import warnings

import numpy as np
import pytest

from threadrecon.core.bounds import Bounds
from threadrecon.core.refine import MISMATCH_PX, _mismatched, _rows, _Runs, _tolerance

FB = 3000.0  # f B, px mm: depth = FB / disparity
ROW = 5
LENGTH = 57  # px: two strands along the rows, as the raw rig's seed 98 (issue 14)


def _two_long_strands() -> tuple[_Runs, _Runs]:
    """Row ``ROW`` holds two runs of ``LENGTH`` px one pixel apart in both views; the right
    view's are the left's shifted by 30 px (disparity 30 px for both strands)."""
    left = np.zeros((10, 300), dtype=bool)
    right = np.zeros_like(left)
    a, b = 100, 100 + LENGTH + 1  # strand A [100, 157), strand B [158, 215)
    for x0 in (a, b):
        left[ROW, x0 : x0 + LENGTH] = True
        right[ROW, x0 - 30 : x0 - 30 + LENGTH] = True
    grey = np.full(left.shape, 100.0)
    return _Runs(left, grey, 200.0), _Runs(right, grey, 200.0)


def _bounds(x: np.ndarray, disparity: float) -> Bounds:
    """Points of H on row ``ROW`` at columns ``x`` with the stereo depth of ``disparity``."""
    n = len(x)
    z = np.full(n, FB / disparity)
    return _bounds_at(np.column_stack([x, np.full(n, float(ROW)), z]), np.asarray(x, float) - x[0])


def _bounds_at(H: np.ndarray, s: np.ndarray) -> Bounds:
    """Bounds of the points H (every one a keypoint) at arc lengths s, +-10 % of their depth."""
    z = H[:, 2]
    return Bounds(
        H=H,
        is_key=np.ones(len(H), bool),
        s=s,
        centre=z,
        lower=0.9 * z,
        upper=1.1 * z,
        end_values=(float(z[0]), float(z[-1])),
        end_slopes=(0.0, 0.0),
        r_k=2,
    )


def test_a_long_run_along_the_rows_off_its_centre_disparity_is_not_a_mismatch() -> None:
    # Seed 98 of the raw rig: stereo 30 px, the runs' centres 24 px apart on a 57 px run. The
    # run pins its centre only to +- 57 / sqrt(12) = 16 px: 6 px is well within (it was
    # flagged with the fixed 4 px).
    runs_L, runs_R = _two_long_strands()
    out, shared = _mismatched(_bounds(np.array([110.0, 128.0, 146.0]), 36.0), runs_L, runs_R, FB)
    assert not out.any() and not shared.any()


def test_a_long_strand_matched_to_its_adjacent_neighbour_is_still_a_mismatch() -> None:
    # Strand B (left centre 186) matched to the right view's strand A (centre 98): 88 px
    # instead of 30, the smallest error two disjoint runs of 57 px allow (L + 1 = 58 px).
    runs_L, runs_R = _two_long_strands()
    out, _ = _mismatched(_bounds(np.array([170.0, 186.0, 200.0]), 88.0), runs_L, runs_R, FB)
    assert out.all()


@pytest.mark.parametrize("length", [1, 2, 3, 5, 10, 57, 400])
def test_tolerance_grows_with_the_runs_but_below_the_distance_of_two_disjoint_runs(
    length: int,
) -> None:
    # Two disjoint runs of length L on a row have centres at least L + 1 apart: where the
    # tolerance grows past the fixed MISMATCH_PX, a depth of the neighbour strand still
    # exceeds it on equally long runs.
    L = np.array([float(length)])
    tol = _tolerance(L, L)[0]
    sigma = np.sqrt(2 * length**2 / 12.0)  # the run-centre disparity's standard deviation
    assert tol >= max(MISMATCH_PX, sigma)
    if tol > MISMATCH_PX:
        assert tol < length + 1


def test_tolerance_is_fixed_on_short_runs_and_infinite_without_a_run() -> None:
    t = _tolerance(np.array([2.0, 3.0, np.inf]), np.array([2.0, 4.0, 3.0]))
    assert t[0] == MISMATCH_PX and t[1] == MISMATCH_PX and np.isinf(t[2])


def test_rows_of_nan_or_huge_ordinates_are_outside_the_image_without_a_warning() -> None:
    y = np.array([3.4, 3.6, np.nan, np.inf, -np.inf, 1.3e40, -2.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rows = _rows(y)
    assert rows.dtype == np.int64
    assert rows.tolist() == [3, 4, -1, -1, -1, -1, -2]


def _three_strands(disparity: float) -> tuple[_Runs, _Runs, Bounds]:
    """Rows 0-9 hold three 2 px runs in both views (a coil's turns, 10 px apart; the right
    view's are the left's shifted by 6 px) and H runs down the middle strand with the stereo
    depth of ``disparity``."""
    left = np.zeros((10, 40), dtype=bool)
    right = np.zeros_like(left)
    for x0 in (10, 20, 30):
        left[:, x0 : x0 + 2] = True
        right[:, x0 - 6 : x0 - 4] = True
    grey = np.full(left.shape, 100.0)
    y = np.arange(10.0)
    z = np.full(10, FB / disparity)
    bounds = _bounds_at(np.column_stack([np.full(10, 20.5), y, z]), y.copy())
    return _Runs(left, grey, 200.0), _Runs(right, grey, 200.0), bounds


def test_rows_of_three_runs_without_a_coil_candidate_do_not_read_the_curve() -> None:
    # Every point's stereo depth is its own strand's (disparity 6): no point names another
    # left run's partner, so the sections are the same whatever the curve's disparity, found
    # once with the stereo match (a spline re-run neither computes d_run nor reads it).
    rl, rr, bounds = _three_strands(6.0)

    def unread() -> np.ndarray:
        raise AssertionError("d_run was computed")

    out, shared = _mismatched(bounds, rl, rr, FB, unread)
    assert not out.any() and not shared.any()
    out2, _ = _mismatched(bounds, rl, rr, FB, np.full(rl.centre.size, 16.0))
    assert np.array_equal(out, out2)


def test_a_coil_candidate_reads_the_curve_s_disparity() -> None:
    # Disparity 16 (x_R = 4.5: the right partner of the left strand at 10-11) on every point:
    # the curve's own disparity on that strand decides, so d_run is read; there it is 6 px,
    # the rank pairing's: the middle strand was matched to its neighbour's partner.
    rl, rr, bounds = _three_strands(16.0)
    calls = []

    def d_run() -> np.ndarray:
        calls.append(1)
        return np.full(rl.centre.size, 6.0)

    out, shared = _mismatched(bounds, rl, rr, FB, d_run)
    assert calls
    assert out.all() and shared.any()
