"""Tests of core/ends.py and its use in core/ordering.py and core/bounds.py: the tip of a thread
matched in both views gives the end's disparity, and Eq. (8)'s end value weighs it against the
window line of Eq. (7) by their variances (deviation 23)."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from support import right_tip_disc, synthetic_case

from threadrecon.core.bounds import _line_variance, _tip_ends, _window_line_fits
from threadrecon.core.ends import NO_MATCH, QUANT_VAR, fuse_end, seen_in_right, tip_disparity
from threadrecon.core.metrics import project
from threadrecon.core.ordering import OrderingParams, _PixelGrid, _window_is_own
from threadrecon.core.pipeline import Pipeline, ReconParams
from threadrecon.core.segmentation import StereoPair


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


def _along_the_rows(tip: np.ndarray, disparity: float, length: float) -> tuple[np.ndarray, ...]:
    """Both views of a thread ending at ``tip`` that runs ``length`` px along the rows,
    seen at ``disparity``."""
    left = _thread((160, 240), tip, (-1.0, 0.0), length=length)
    right = _thread((160, 240), tip - (disparity, 0.0), (-1.0, 0.0), length=length)
    return left, right


def test_a_tip_beyond_the_window_search_is_found_by_following_the_descent() -> None:
    # Deviation 55: a dead end along the rows whose tip lies 9 px of disparity beyond the end
    # keypoint's (copied along the dead end): the best shift of d_ref +- 7 lies on the search's
    # edge (no match); with reach the SSD's descent is followed out to the tip's own shift.
    tip = np.array([150.0, 80.0])
    left, right = _along_the_rows(tip, 39.0, 80.0)
    assert tip_disparity(left, right, tip, d_ref=30.0, radius=7) == NO_MATCH
    m = tip_disparity(left, right, tip, d_ref=30.0, radius=7, reach=10.0)
    assert abs(m.disparity - 39.0) < 0.35, m
    # ... but not beyond the reach: the minimum then lies on the edge of the wider search
    assert tip_disparity(left, right, tip, d_ref=30.0, radius=7, reach=1.0) == NO_MATCH
    # a tip within the window's search is found as before, reach or not
    near = tip_disparity(left, right, tip, d_ref=36.0, radius=7)
    assert tip_disparity(left, right, tip, d_ref=36.0, radius=7, reach=10.0) == near


def test_a_tip_near_the_left_border_is_searched_inside_the_right_image() -> None:
    # Raw 16153 lighting #17's tip: x = 43, disparity 33.4, d_ref 36.3: the search d_ref +- 7
    # leaves the right image (no match); with reach it is cut to the shifts inside it.
    tip = np.array([43.0, 80.0])
    left, right = _along_the_rows(tip, 33.4, 150.0)
    assert tip_disparity(left, right, tip, d_ref=36.3, radius=7) == NO_MATCH
    m = tip_disparity(left, right, tip, d_ref=36.3, radius=7, reach=2.0)
    assert abs(m.disparity - 33.4) < 0.35, m
    # the shifts left inside the right image hold no minimum: no match
    assert tip_disparity(left, right, tip, d_ref=45.0, radius=7, reach=2.0) == NO_MATCH


@pytest.mark.parametrize("radius", [2, 7])
def test_ssd_curves_of_a_wider_search_extend_the_kernels(radius: int) -> None:
    from threadrecon.core.walk_kernel import tip_costs

    rng = np.random.default_rng(radius)
    n, extra = 2 * radius + 1, 5
    strip = rng.normal(100, 40, (n + 2, 4 * radius + 1 + 2 * extra))
    A = np.ascontiguousarray(rng.normal(100, 40, (n, n)))
    wide = tip_costs(A, strip, radius, 1, n + 2 * extra)
    inner = tip_costs(A, np.ascontiguousarray(strip[:, extra:-extra]), radius, 1, n)
    assert np.array_equal(wide[:, extra:-extra], inner)  # the same means bit for bit
    k = np.arange(n + 2 * extra)
    cols = (n + 2 * extra - 1 - k)[:, None] + np.arange(n)[None, :]
    for t in range(3):  # and numpy's own np.mean of the (shifts, n, n) block
        block = (A[None, :, :] - strip[t : t + n][:, cols].transpose(1, 0, 2)) ** 2
        assert np.array_equal(wide[t], np.mean(block, axis=(1, 2)))


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
    # the ordering itself is unchanged: its extensions are a few px long, no dead end (55)
    assert o_on.dead_end == (False, False) and (o_on.order[[0, -1]] < 0).all()
    assert np.array_equal(o_off.path_px, o_on.path_px)
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


def test_seen_in_right_needs_a_right_thread_pixel_on_the_row_near_the_disparity() -> None:
    P_R = np.zeros((20, 40), dtype=bool)
    P_R[10, 12] = True
    px = np.array([[42 - 30, 10], [42, 10], [42, 11], [42, 9], [42, 12], [46, 10], [47, 10]])
    # x - d = 12 on rows 9-11 (one row of slack); 3 columns of tolerance: 46 -> 16 is 4 away
    got = seen_in_right(px, P_R, d_ref=30.0, tol=3)
    assert got.tolist() == [False, True, True, True, False, False, False]
    assert seen_in_right(px[[5]], P_R, d_ref=30.0, tol=4).tolist() == [True]
    assert not seen_in_right(px, P_R, d_ref=float("nan"), tol=3).any()
    # columns off either side of the image are clipped, not wrapped
    assert not seen_in_right(np.array([[2, 10], [39, 10]]), P_R, d_ref=-30.0, tol=3).any()
    assert seen_in_right(np.empty((0, 2), int), P_R, 30.0, 3).shape == (0,)


def _seen_in_right_by_prefix_sums(px: np.ndarray, P_R: np.ndarray, d_ref: float, tol: int):
    """seen_in_right as numpy formulas: prefix sums of the rows needed, window sums by two reads."""
    H, W = P_R.shape
    out = np.zeros(len(px), dtype=bool)
    centre = np.rint(px[:, 0] - d_ref).astype(np.int64)
    lo, hi = np.clip(centre - tol, 0, W), np.clip(centre + tol + 1, 0, W)
    cs = np.concatenate([np.zeros((H, 1), np.int64), np.cumsum(P_R, axis=1)], axis=1)
    for dy in (-1, 0, 1):
        y = px[:, 1] + dy
        inside = (y >= 0) & (y < H)
        yy = np.clip(y, 0, H - 1)
        out |= inside & (cs[yy, hi] > cs[yy, lo])
    return out


@pytest.mark.parametrize("seed", range(20))
def test_seen_in_right_equals_the_prefix_sum_formulas(seed: int) -> None:
    rng = np.random.default_rng(seed)
    H, W = int(rng.integers(1, 30)), int(rng.integers(1, 50))
    P_R = rng.random((H, W)) < rng.choice([0.02, 0.1, 0.5])
    if seed % 3 == 0:
        P_R = np.asfortranarray(P_R)  # any memory layout
    px = np.stack([rng.integers(-10, W + 60, 40), rng.integers(-3, H + 3, 40)], axis=1)
    d_ref, tol = float(rng.uniform(-20, 60)), int(rng.integers(0, 6))
    got = seen_in_right(px, P_R, d_ref, tol)
    assert got.dtype == bool and np.array_equal(
        got, _seen_in_right_by_prefix_sums(px, P_R, d_ref, tol)
    )


def _hidden_tip_case(hide_px: int):
    """A generated frame (exact masks) whose right view does not show the last ``hide_px`` px of
    the thread's first end (painted over with the background and cut from P_R), as a real rig's
    hand mask or a glint does; (pair, calibration, the right mask)."""
    frame, calib, near = right_tip_disc(hide_px)
    right, m_R = frame.right.copy(), frame.mask_right.copy()
    right[near & m_R] = np.median(frame.right[~m_R], axis=0).astype(np.uint8)
    m_R[near] = False
    return StereoPair(frame.left, right, frame.mask_left, m_R), calib, m_R


def test_an_end_the_right_view_does_not_show_is_not_extended_into() -> None:
    pair, calib, m_R = _hidden_tip_case(9)
    both = Pipeline(pair, calib).run(until="camera")
    left = Pipeline(pair, calib).run(
        ReconParams(ordering=OrderingParams(tip_views="left")), until="camera"
    )
    tips = {n: r["ordering"].path_px[[0, -1], :2] for n, r in (("both", both), ("left", left))}
    # the left-only extension reaches into the hidden part; the two-view one stops short of it
    gap = np.linalg.norm(tips["left"] - tips["both"], axis=1)
    assert gap.max() >= 4.0, gap
    # and the final curve's projection stays on the right view's thread
    on = cKDTree(np.argwhere(m_R)[:, ::-1])
    assert on.query(project(both["camera"].points, calib.P2))[0].max() <= 3.0
    assert on.query(project(left["camera"].points, calib.P2))[0].max() > 4.0


def test_an_end_both_views_show_is_extended_as_before() -> None:
    pair, calib, _ = synthetic_case(2)
    o_both = Pipeline(pair, calib).run(until="ordering")["ordering"]
    o_left = Pipeline(pair, calib).run(
        ReconParams(ordering=OrderingParams(tip_views="left")), until="ordering"
    )["ordering"]
    assert np.array_equal(o_both.path_px, o_left.path_px)


@pytest.mark.parametrize("radius", [1, 3, 7, 8, 12, 25, 50])
def test_tip_costs_are_the_numpy_means_bit_for_bit(radius: int) -> None:
    """The compiled SSD curves of tip_disparity equal ``np.mean`` of the (shifts, n, n) block
    of squared differences bit for bit: n^2 below 8, up to 128, one split (n = 15) and the
    split tree of numpy's pairwise sum (n^2 = 10201); grey levels and real-valued images."""
    from threadrecon.core.walk_kernel import tip_costs

    rng = np.random.default_rng(radius)
    n = 2 * radius + 1
    for trial in range(20):
        shape = (n + 2, 4 * radius + 1)
        strip = rng.integers(0, 256, shape).astype(np.float64)
        A = rng.integers(0, 256, (n, n)).astype(np.float64)
        if trial % 2:
            strip, A = strip + rng.normal(0, 30, shape), A * 0.37 + rng.normal(0, 3, (n, n))
        got = tip_costs(A, strip, radius, 1, n)
        k = np.arange(n)
        cols = (2 * radius - k)[:, None] + np.arange(n)[None, :]
        for t in range(3):
            rows = strip[t : t + n]
            want = np.mean((A[None, :, :] - rows[:, cols].transpose(1, 0, 2)) ** 2, axis=(1, 2))
            assert np.array_equal(got[t], want), (trial, t)


def test_a_dead_end_along_the_rows_is_interpolated_to_its_tip() -> None:
    """Raw 16153 ``lighting`` #17 (masks given): the thread's last 270 px run along the rows
    with no reliable match to the left border. Deviation 23's tip search (the end keypoint's
    disparity +- 7 px) left the right image: no tip, the extension copied 122.6 mm (truth 133)
    and the curve dipped 10 mm. Deviation 55 matches the tip (33.4 px) and the dead end is
    interpolated to it (docs/method.md)."""
    from support import suite_frame

    from threadrecon.core.metrics import frame_errors

    frame = suite_frame(
        [16153, 9, 17], background="tissue", noise_sigma=2.0, blur_sigma=0.5, lighting=0.6
    )
    calib = frame.camera.calibration()
    pair = StereoPair(frame.left, frame.right, frame.mask_left, frame.mask_right)
    true_tip = frame.truth.centerline[0, 2]
    runs = {}
    for on in (True, False):
        params = ReconParams(ordering=OrderingParams(dead_end_tip=on))
        rec = Pipeline(pair, calib).run(params)
        e = frame_errors(rec["camera"].points, frame.truth.centerline, calib)
        runs[on] = (rec["ordering"], e)
    (o_on, e_on), (o_off, e_off) = runs[True], runs[False]
    assert o_on.order[0] < 0 and o_on.path_px[0, 0] < 50  # the extension to the left border
    assert o_on.dead_end == (True, False) and o_off.dead_end == (False, False)
    assert np.isnan(o_off.end_disparity[0, 0])
    assert abs(o_off.path_px[0, 2] - true_tip) > 8.0  # the end keypoint's copy
    assert abs(o_on.path_px[0, 2] - true_tip) < 2.0  # the tip's own depth
    assert e_off.e_S_max > 7.0 and e_on.e_S_max < 4.0, (e_off, e_on)


_PAPER = Path(__file__).resolve().parents[3] / "shared" / "data" / "paper-dataset"


@pytest.mark.skipif(not _PAPER.is_dir(), reason="../shared/data/paper-dataset absent")
def test_a_dead_end_tip_out_of_one_strands_reach_keeps_the_copy() -> None:
    """The development split's real thread2_116: a 28 px dead end whose tip matched 4.7 px
    from its end keypoint's disparity, beyond one strand's continuity bound over 28 px (3.8
    px): keypoint or tip is wrong, the extension keeps the keypoint's depth (deviation 55's
    gate; without it the first knot span fell 24 mm to the tip and the curve was suspect)."""
    from threadrecon.app.dataset import discover, load_frame
    from threadrecon.core.continuity import disparity_room

    frame = next(f for f in discover(_PAPER) if f.id.endswith("thread2_116_final"))
    pair, calib, _ = load_frame(frame)
    rec = Pipeline(pair, calib).run(ReconParams(ordering=OrderingParams(dead_end_tip=True)))
    o = rec["ordering"]
    assert o.dead_end[0] and np.isfinite(o.end_disparity[0, 0])
    fB = calib.focal * calib.baseline
    length = float(np.linalg.norm(o.path_px[0, :2] - o.path_px[1, :2]))
    assert abs(o.end_disparity[0, 0] - fB / o.path_px[1, 2]) > disparity_room(length)
    assert o.path_px[0, 2] == o.path_px[1, 2]  # the copy
    assert rec.status == "ok", rec.message
