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


def _image(stereo, rel):  # noqa: ANN001, ANN202
    """The reliable pixels' disparities (float32) on their bounding box, NaN elsewhere."""
    sel = np.flatnonzero(rel.reliable)
    if sel.size == 0:
        return 0, 0, np.zeros((0, 0))
    xy = np.asarray(stereo.pixels)[sel].astype(np.int64)
    x0, y0 = int(xy[:, 0].min()), int(xy[:, 1].min())
    shape = (int(xy[:, 1].max()) - y0 + 1, int(xy[:, 0].max()) - x0 + 1)
    img = np.full(shape, np.nan, dtype=np.float32)
    img[xy[:, 1] - y0, xy[:, 0] - x0] = np.asarray(stereo.disparity, dtype=np.float32)[sel]
    return x0, y0, img


def _contradicted_numpy(stereo, rel, uv, disp, near, tol):  # noqa: ANN001, ANN202
    """contradicted as numpy ran it before the kernels: (N, K, K) windows gathered at once
    from an image of the reliable disparities."""
    x0, y0, img = _image(stereo, rel)
    n = len(uv)
    if img.size == 0 or n == 0:
        return np.zeros(n, dtype=bool)
    h, w = img.shape
    ok = np.all(np.isfinite(uv), axis=1) & np.isfinite(disp)
    q = np.rint(np.where(ok[:, None], uv, -1e6)).astype(np.int64) - [x0, y0]
    k = np.arange(-near, near + 1)
    xs = q[:, 0, None, None] + k[None, None, :]
    ys = q[:, 1, None, None] + k[None, :, None]
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    d = img[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]
    d = np.where(inside, d, np.nan).reshape(n, -1)
    seen = np.isfinite(d).any(axis=1)
    with np.errstate(invalid="ignore"):
        agrees = (np.abs(d - disp[:, None]) <= tol).any(axis=1)
    return ok & seen & ~agrees


def test_compiled_windows_equal_the_numpy_windows() -> None:
    """The compiled window test against the (N, K, K) numpy gather it replaced: random
    reliable pixels and disparities, points inside, at and beyond the box, NaN points and
    disparities, windows 0-3 px."""
    rng = np.random.default_rng(2)
    for _ in range(40):
        m = int(rng.integers(1, 300))
        flat = rng.choice(60 * 50, size=m, replace=False)  # P_L's pixels are distinct
        xy = np.column_stack([20 + flat % 60, 10 + flat // 60])
        stereo, rel = _matches([tuple(p) for p in xy], list(rng.uniform(5.0, 40.0, m)))
        stereo.disparity[rng.random(m) < 0.05] = np.nan  # a match without a disparity
        rel.reliable[:] = rng.random(m) < 0.8
        n = int(rng.integers(0, 200))
        uv = rng.uniform(0.0, 100.0, (n, 2))
        disp = rng.uniform(5.0, 40.0, n)
        if n > 4:
            uv[0, 1], disp[1] = np.nan, np.nan
        for near in range(4):
            tol = float(rng.uniform(0.2, 5.0))
            want = _contradicted_numpy(stereo, rel, uv, disp, near, tol)
            assert np.array_equal(contradicted(stereo, rel, uv, disp, near, tol), want)
