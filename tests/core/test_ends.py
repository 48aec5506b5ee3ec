"""Tests of core/ends.py and its use in core/ordering.py and core/bounds.py: the tip of a thread
matched in both views gives the end's disparity, and Eq. (8)'s end value weighs it against the
window line of Eq. (7) by their variances (deviation 23)."""

import numpy as np
import pytest
from support import synthetic_case

from threadrecon.core.bounds import _line_variance, _tip_ends, _window_line_fits
from threadrecon.core.ends import NO_MATCH, QUANT_VAR, fuse_end, tip_disparity
from threadrecon.core.ordering import OrderingParams, _PixelGrid, _window_is_own
from threadrecon.core.pipeline import Pipeline, ReconParams


def _thread(shape, tip, direction, length=60.0, width=3.0, background=255.0) -> np.ndarray:
    """A dark thread of ``width`` px ending at ``tip`` (x, y) in a round cap, running back
    ``length`` px along -``direction``, on a bright lifted background (Eq. (1): 255 off the
    thread). Edges are area-weighted over one pixel: sub-pixel positions show in the image."""
    tip = np.asarray(tip, float)
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    ys, xs = np.mgrid[: shape[0], : shape[1]].astype(float)
    rel = np.stack([xs - tip[0], ys - tip[1]], axis=-1)
    t = np.clip(-(rel @ u), 0.0, length)  # position along the thread back from the tip
    dist = np.linalg.norm(rel + t[..., None] * u, axis=-1)
    cover = np.clip(width / 2 + 0.5 - dist, 0.0, 1.0)
    return (background - (background - 60.0) * cover).astype(np.float32)


@pytest.mark.parametrize("d_true", [12.0, 12.5, 30.25, 47.75])
@pytest.mark.parametrize("direction", [(1.0, 0.0), (1.0, 0.3), (0.2, 1.0), (-1.0, -0.1)])
def test_tip_disparity_recovers_the_shift_of_the_tip(d_true, direction) -> None:
    tip = np.array([150.3, 80.6])
    left = _thread((160, 240), tip, direction)
    right = _thread((160, 240), tip - (d_true, 0.0), direction)
    m = tip_disparity(left, right, tip, d_ref=d_true + 2.6, radius=7)
    assert abs(m.disparity - d_true) < 0.35, m
    assert QUANT_VAR <= m.var < 1.0


def test_tip_disparity_allows_one_row_of_rectification_error() -> None:
    # A thread along the rows whose right image lies one row higher (the dev split's real rig).
    tip = np.array([150.0, 80.0])
    left = _thread((160, 240), tip, (1.0, 0.0))
    right = _thread((160, 240), tip - (30.0, 1.0), (1.0, 0.0))
    m = tip_disparity(left, right, tip, d_ref=25.0, radius=7)
    assert abs(m.disparity - 30.0) < 0.35, m


def test_a_window_without_a_tip_gives_no_match() -> None:
    # The thread runs through the window along the rows: every shift looks alike.
    left = _thread((160, 240), (230.0, 80.0), (1.0, 0.0), length=200.0)
    right = _thread((160, 240), (200.0, 80.0), (1.0, 0.0), length=200.0)
    m = tip_disparity(left, right, (120.0, 80.0), d_ref=30.0, radius=7)
    assert m == NO_MATCH or m.var > 1.0


@pytest.mark.parametrize("tip", [(3.0, 80.0), (150.0, 2.0), (236.0, 80.0), (20.0, 80.0)])
def test_a_window_leaving_either_image_gives_no_match(tip) -> None:
    # (20, 80) with disparity 30: the tip lies left of the right image.
    img = _thread((160, 240), tip, (1.0, 0.0))
    m = tip_disparity(img, img, np.array(tip), d_ref=30.0, radius=7)
    assert np.isnan(m.disparity) and m.var == np.inf


def test_tip_disparity_rejects_mismatched_images() -> None:
    with pytest.raises(ValueError, match="two \\(H, W\\) images"):
        tip_disparity(np.zeros((10, 10)), np.zeros((10, 12)), (5.0, 5.0), 2.0, 2)


def test_fuse_end_weighs_by_inverse_variance() -> None:
    z, var = fuse_end(100.0, 4.0, 110.0, 1.0)
    assert z == pytest.approx(108.0) and var == pytest.approx(0.8)
    assert fuse_end(100.0, 4.0, float("nan"), float("inf")) == (100.0, 4.0)
    assert fuse_end(100.0, float("inf"), 110.0, 1.0) == (110.0, 1.0)


def test_line_variance_grows_with_the_residuals_and_the_extrapolation() -> None:
    s = np.arange(10.0)
    rng = np.random.default_rng(3)
    z = 2.0 + 0.5 * s + rng.normal(0, 1.0, 10)
    assert _line_variance(s, z, 4.5) < _line_variance(s, z, 0.0) < _line_variance(s, z, -5.0)
    assert _line_variance(s, 2.0 * (z - 2.0 - 0.5 * s), 0.0) > _line_variance(s, z, 0.0)
    assert _line_variance(s[:2], z[:2], 0.0) == np.inf


def test_tip_ends_move_only_the_end_values_towards_the_tip() -> None:
    # Depth curves at the first end (a quadratic): the line extrapolated there is biased; a
    # tip matched with a small variance pulls L_{k_1} to the tip's depth; the last end has no
    # tip and keeps its line.
    s = np.arange(0.0, 200.0, 10.0)
    z = 100.0 + 0.01 * (s - 60.0) ** 2
    key_idx = np.arange(len(s))
    line, slope = _window_line_fits(s, z, key_idx, 4)
    fB = 1000.0
    end_disp = np.array([[fB / z[0], 1e-4], [np.nan, np.inf]])
    out, out_slope = _tip_ends(line, slope, end_disp, s, z, key_idx, 4, fB)
    assert abs(out[0] - z[0]) < 0.25 * abs(line[0] - z[0])
    assert out[-1] == line[-1] and out_slope[-1] == slope[-1]
    assert np.array_equal(out[1:-1], line[1:-1]) and np.array_equal(out_slope[1:-1], slope[1:-1])
    assert out_slope[0] < 0 < slope[-1]  # depth falls into the vertex at s = 60


def test_end_window_zero_is_the_papers_extension() -> None:
    pair, calib, _ = synthetic_case(2)
    off = ReconParams(ordering=OrderingParams(end_window_px=0))
    rec_off = Pipeline(pair, calib).run(off, until="bounds")
    rec_on = Pipeline(pair, calib).run(until="bounds")
    o_off, o_on = rec_off["ordering"], rec_on["ordering"]
    assert np.isnan(o_off.end_disparity[:, 0]).all() and np.isinf(o_off.end_disparity[:, 1]).all()
    assert np.isfinite(o_on.end_disparity).all()  # a generated thread ends inside both views
    assert np.array_equal(o_off.path_px, o_on.path_px)  # the ordering itself is unchanged
    b_off = rec_off["bounds"]
    line, _ = _window_line_fits(b_off.s, b_off.H[:, 2], np.flatnonzero(b_off.is_key), b_off.r_k)
    assert b_off.end_values == (float(line[0]), float(line[-1]))


def test_a_tip_window_holding_another_strand_is_not_matched() -> None:
    # Keypoints 0, 1, 2 run from the tip at (10, 10) along +x; keypoint 3 is far along the walk
    # (its strand crosses near the tip). Pixels: clusters 0 and 1 by the tip, gap node K + 0
    # between 0 and 1, and a pixel of keypoint 3 inside the window or outside it.
    K = 4
    key_px = np.array([[12.0, 10.0, 1.0], [18.0, 10.0, 1.0], [60.0, 10.0, 1.0], [40.0, 40.0, 1.0]])
    seq = [0, 1, 2, 3]
    gaps = {0: {K}, 1: {K}}
    tip = np.array([10.0, 10.0])
    pixels = np.array([[10, 10], [12, 10], [15, 10], [18, 10]])
    nodes = np.array([0, 0, K, 1])
    assert _window_is_own(pixels, nodes, K, seq, key_px, gaps, tip, 7)
    crossing = (np.vstack([pixels, [[13, 14]]]), np.append(nodes, 3))
    assert not _window_is_own(*crossing, K, seq, key_px, gaps, tip, 7)
    outside = (np.vstack([pixels, [[13, 30]]]), np.append(nodes, 3))
    assert _window_is_own(*outside, K, seq, key_px, gaps, tip, 7)
    foreign_gap = (np.vstack([pixels, [[13, 14]]]), np.append(nodes, K + 1))
    assert not _window_is_own(*foreign_gap, K, seq, key_px, gaps, tip, 7)
    # read from the pixels' index image: the same answers, the window's edge included (17 in,
    # 18 out for a tip at 10.4 and radius 7)
    edge_in, edge_out = (np.vstack([pixels, [[x, 17]]]) for x in (17, 18))
    for px, nd in (
        (pixels, nodes), crossing, outside, foreign_gap, (edge_in, np.append(nodes, 3)),
        (edge_out, np.append(nodes, 3)), (edge_out[[4]], np.array([3])),
    ):  # fmt: skip
        for t in (tip, tip + 0.4, np.array([100.0, -50.0])):
            want = _window_is_own(px, nd, K, seq, key_px, gaps, t, 7)
            got = _window_is_own(px, nd, K, seq, key_px, gaps, t, 7, _PixelGrid(px, 1))
            assert want == got
    assert not _window_is_own(edge_in, np.append(nodes, 3), K, seq, key_px, gaps, tip, 7)
    assert _window_is_own(edge_out, np.append(nodes, 3), K, seq, key_px, gaps, tip, 7)
