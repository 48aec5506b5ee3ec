"""Tests of core/shift_information.py: a stereo window's information about a horizontal shift
is large across a steep thread and on a thread with shading along its length, near zero on a
uniform thread along the rows; the MVS measurement's s.d. scales with it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from support import synthetic_case

from threadrecon.core.metrics import curve_errors
from threadrecon.core.pipeline import Pipeline, ReconParams
from threadrecon.core.shift_information import WINDOW_HALF, scale, shift_information

H, W = 40, 60


def _line(vertical: bool, shading: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A 3 px dark line through the image's middle, along the columns or along the rows, over
    a background of 200; ``shading`` grey levels of a sine along its length."""
    grey = np.full((H, W), 200.0)
    mask = np.zeros((H, W), dtype=bool)
    if vertical:
        mask[:, 29:32] = True
        grey[:, 29:32] = 80.0 + shading * np.sin(np.arange(H) / 2.0)[:, None]
    else:
        mask[19:22, :] = True
        grey[19:22, :] = 80.0 + shading * np.sin(np.arange(W) / 2.0)[None, :]
    return grey, mask


def test_a_window_across_a_steep_thread_knows_the_shift_one_along_the_rows_does_not() -> None:
    """Across a vertical line the window holds two edges of 120 grey levels; along a uniform
    horizontal line it holds no horizontal gradient at all; shading along that line (the SSD
    locks on it) gives the information back."""
    steep = shift_information(*_line(True), np.array([[30.0, 20.0]]))
    flat = shift_information(*_line(False), np.array([[30.0, 20.0]]))
    shaded = shift_information(*_line(False, shading=30.0), np.array([[30.0, 20.0]]))
    assert flat[0] == 0.0
    assert steep[0] > 1e4 and shaded[0] > 1e3


def test_information_is_the_window_sum_of_squared_row_differences() -> None:
    """Exact on a random image: the brute-force sum over the window's mask pixels of the
    squared central difference (one-sided at the border), windows cut at the image border,
    zero outside the image or for a point that is not finite."""
    rng = np.random.default_rng(3)
    grey = rng.uniform(0, 255, (H, W))
    mask = rng.random((H, W)) < 0.4
    pts = np.array([[10.2, 7.6], [0.0, 0.0], [59.4, 39.0], [-3.0, 5.0], [np.nan, 4.0], [30, 50]])
    got = shift_information(grey, mask, pts)
    for (x, y), g in zip(pts, got, strict=True):
        if not (np.isfinite(x) and 0 <= round(x) < W and 0 <= round(y) < H):
            assert g == 0.0
            continue
        cx, cy, want = round(x), round(y), 0.0
        for yy in range(cy - WINDOW_HALF, cy + WINDOW_HALF + 1):
            for xx in range(cx - WINDOW_HALF, cx + WINDOW_HALF + 1):
                if 0 <= yy < H and 0 <= xx < W and mask[yy, xx]:
                    a, b = min(xx + 1, W - 1), max(xx - 1, 0)
                    want += ((grey[yy, a] - grey[yy, b]) / (a - b)) ** 2
        assert g == pytest.approx(want, rel=1e-12)


def test_scale_is_one_at_the_median_and_grows_as_the_information_falls() -> None:
    info = np.array([400.0, 100.0, 100.0, 25.0, 0.0])
    use = np.array([True, True, True, True, False])
    f = scale(info, use)
    assert f[1] == 1.0 and f[0] == 0.5 and f[3] == 2.0  # sqrt(median / J)
    assert np.isfinite(f[4]) and f[4] >= 1e3  # no information: doubted, not infinite
    assert np.all(scale(np.zeros(3), np.ones(3, bool)) == 1.0)  # nothing to compare with


def test_bad_shapes_are_named() -> None:
    grey, mask = _line(True)
    with pytest.raises(ValueError, match=r"\(P, 2\)"):
        shift_information(grey, mask, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="must be one"):
        shift_information(grey, mask[:, :10], np.zeros((3, 2)))
    with pytest.raises(ValueError, match="differ in shape"):
        scale(np.ones(3), np.ones(2, bool))


def test_the_refinement_stays_on_the_truth_with_and_without_the_information() -> None:
    """On generated frames (the MVS prior's weights change, nothing else) the refined curve
    stays within 0.3 mm mean error of the truth either way, and the switch (off by default)
    reaches the solve (the depths differ)."""
    for seed in (5, 6):
        pair, calib, truth = synthetic_case(seed)
        pipe = Pipeline(pair, calib)
        off = ReconParams()
        on = replace(off, refine=replace(off.refine, shift_information=True))
        rec_on, rec_off = pipe.run(on), pipe.run(off)
        assert rec_on["refine"].ok and rec_off["refine"].ok
        e_on = curve_errors(rec_on["camera"].points, truth).e_S
        e_off = curve_errors(rec_off["camera"].points, truth).e_S
        assert e_on < 0.3 and e_off < 0.3, (e_on, e_off)
        assert not np.array_equal(rec_on["refine"].ctrl, rec_off["refine"].ctrl)
