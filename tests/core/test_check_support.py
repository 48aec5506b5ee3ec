"""The reliable matches under the curve (core/check_support.py): contradicted depth."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from threadrecon.core.check_support import contradicted


def _matches(xy: list[tuple[int, int]], disp: list[float]):
    stereo = SimpleNamespace(
        pixels=np.array(xy, dtype=np.int64), disparity=np.array(disp, dtype=np.float64)
    )
    rel = SimpleNamespace(reliable=np.ones(len(xy), dtype=bool))
    return stereo, rel


def test_a_point_is_contradicted_only_when_every_match_under_it_disagrees() -> None:
    # Two strands crossing at (10, 10): one at disparity 30, one at 20.
    stereo, rel = _matches([(10, 10), (11, 10), (30, 30)], [30.0, 20.0, 25.0])
    uv = np.array([[10.0, 10.0], [10.2, 9.6], [10.0, 10.0], [50.0, 50.0], [31.4, 30.0]])
    d = np.array([30.4, 24.0, 19.5, 30.0, 10.0])
    got = contradicted(stereo, rel, uv, d, 1, 1.0)
    # 0: agrees with the strand at 30; 1: both matches differ by >= 4 px; 2: agrees with 20;
    # 3: no match near (unsupported, not contradicted); 4: the match 1 px away disagrees
    assert got.tolist() == [False, True, False, False, True]
    assert not contradicted(stereo, rel, uv, d, 0, 1.0)[4]  # the window is 1 px wide


def test_contradicted_handles_no_reliable_match_and_bad_points() -> None:
    stereo, rel = _matches([(5, 5)], [10.0])
    rel.reliable[:] = False
    uv = np.array([[5.0, 5.0], [np.nan, 1.0]])
    assert not contradicted(stereo, rel, uv, np.array([3.0, 3.0]), 1, 1.0).any()
    stereo, rel = _matches([(5, 5)], [10.0])
    assert not contradicted(stereo, rel, uv, np.array([3.0, 3.0]), 1, 1.0)[1]  # NaN point
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        contradicted(stereo, rel, np.zeros((3, 3)), np.zeros(3), 1, 1.0)
