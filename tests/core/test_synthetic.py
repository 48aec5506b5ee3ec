"""Tests of the synthetic stereo thread generator (core/synthetic.py).

The rendered thread is measured independently of the generator's internals: the darkness
(background - pixel) centroid of each row or column cut across the thread is compared with the
ground truth spline, evaluated here with scipy from the returned control points and knots.
"""

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.interpolate import BSpline

from threadrecon.core.synthetic import (
    THREAD_COLOURS,
    RenderParams,
    StereoCamera,
    SyntheticFrame,
    SyntheticParams,
    ThreadParams,
    generate_frame,
    thread_knots,
)

FLAT = SyntheticParams()  # flat grey background, no noise, no blur
SEEDS = (0, 1, 2)
MIN_CUT_SIN = math.sin(math.radians(40.0))  # cuts only where the thread is steep to the cut line


@pytest.fixture(scope="module")
def flat_frames() -> list[SyntheticFrame]:
    return [generate_frame(FLAT, seed) for seed in SEEDS]


def _gt_curve(frame: SyntheticFrame, n: int = 20001) -> np.ndarray:
    """(n, 3) ground-truth curve points, evaluated from control points and knots, mm."""
    t = frame.truth
    return BSpline(t.knots, t.control_points, t.degree)(np.linspace(0.0, 1.0, n))


def _grey(image: np.ndarray) -> np.ndarray:
    return image.astype(float).mean(axis=2)


def _cut_centroids(
    dark: np.ndarray, uv: np.ndarray, z: np.ndarray, width_px: float
) -> list[tuple[int, float, float, float]]:
    """Darkness centroids of row cuts matched to the single ground-truth crossing of the row.

    ``dark`` (H, W) darkness, ``uv`` (N, 2) projected ground truth (x, y). Returns
    (row, centroid x, ground-truth x, ground-truth Z) for cuts where exactly one steep part of
    the thread crosses the row, away from the ends and the image border.
    """
    h, w = dark.shape
    seg_lo, seg_hi = uv[:-1], uv[1:]
    d = seg_hi - seg_lo
    sin = np.abs(d[:, 1]) / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    ends = uv[[0, -1]]
    out = []
    for row in range(h):
        on = np.concatenate([[False], dark[row] > 0.5, [False]])
        edges = np.flatnonzero(np.diff(on.astype(np.int8)))
        starts, stops = edges[::2], edges[1::2]
        cross = np.flatnonzero((seg_lo[:, 1] - row) * (seg_hi[:, 1] - row) < 0)
        t = (row - seg_lo[cross, 1]) / d[cross, 1]
        x_gt = seg_lo[cross, 0] + t * d[cross, 0]
        z_gt = z[cross] + t * (z[cross + 1] - z[cross])
        for a, b in zip(starts, stops, strict=True):
            near = np.flatnonzero((x_gt > a - 2 * width_px) & (x_gt < b + 2 * width_px))
            if near.size != 1 or a == 0 or b == w:
                continue
            k = near[0]
            pt = np.array([x_gt[k], row])
            if (
                sin[cross[k]] < MIN_CUT_SIN
                or np.min(np.linalg.norm(ends - pt, axis=1)) < 4 * width_px
            ):
                continue
            x = np.arange(a, b, dtype=float)
            v = dark[row, a:b]
            out.append((row, float((x * v).sum() / v.sum()), float(x_gt[k]), float(z_gt[k])))
    return out


def _centreline_errors(frame: SyntheticFrame, view: int, background: float = 205.0) -> np.ndarray:
    """|darkness centroid - ground truth| (px) over row cuts and column cuts of one view."""
    image = frame.left if view == 0 else frame.right
    dark = np.clip(background - _grey(image), 0.0, None)
    p = _gt_curve(frame)
    uv = frame.camera.project(p)[view]
    width = frame.camera.fx * 0.5 / p[:, 2].min()
    rows = _cut_centroids(dark, uv, p[:, 2], width)
    cols = _cut_centroids(dark.T, uv[:, ::-1], p[:, 2], width)
    return np.array([abs(c - g) for _, c, g, _ in rows + cols])


def _polyline_self_crossings(uv: np.ndarray, min_sep: int) -> int:
    """Number of proper intersections between segments at least ``min_sep`` indices apart."""
    a, d = uv[:-1], np.diff(uv, axis=0)
    i, j = np.triu_indices(len(a), k=min_sep)
    den = d[i, 0] * d[j, 1] - d[i, 1] * d[j, 0]
    r = a[j] - a[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        ti = (r[:, 0] * d[j, 1] - r[:, 1] * d[j, 0]) / den
        tj = (r[:, 0] * d[i, 1] - r[:, 1] * d[i, 0]) / den
    return int(np.count_nonzero((ti > 0) & (ti < 1) & (tj > 0) & (tj < 1)))


# --------------------------------------------------------------------------------------------


def test_ground_truth_uses_the_paper_knot_convention(flat_frames: list[SyntheticFrame]) -> None:
    for frame in flat_frames:
        t = frame.truth
        n = len(t.control_points)
        assert t.control_points.shape == (n, 3) and t.control_points.dtype == np.float64
        assert 7 <= n <= 11 and t.degree == 3
        expected = np.concatenate([[0, 0, 0], np.linspace(0, 1, n - 2), [1, 1, 1]])
        np.testing.assert_array_equal(t.knots, expected)
        np.testing.assert_array_equal(thread_knots(n), expected)
        # The dense centreline lies on the spline and is uniform in arc length.
        steps = np.linalg.norm(np.diff(t.centerline, axis=0), axis=1)
        assert steps.max() - steps.min() < 1e-3
        np.testing.assert_allclose(t.centerline[[0, -1]], t.control_points[[0, -1]], atol=1e-9)


def test_thread_length_depth_and_margin_respect_the_settings(
    flat_frames: list[SyntheticFrame],
) -> None:
    tp = FLAT.thread
    for frame in flat_frames:
        p = _gt_curve(frame)
        length = np.linalg.norm(np.diff(p, axis=0), axis=1).sum()
        assert tp.length_mm[0] - 1e-3 <= length <= tp.length_mm[1] + 1e-3
        assert abs(length - frame.truth.length_mm) < 1e-3
        assert tp.depth_mm[0] - 1e-6 <= p[:, 2].min() and p[:, 2].max() <= tp.depth_mm[1] + 1e-6
        cam = frame.camera
        for uv in cam.project(p):
            assert uv.min(axis=0).min() >= 10 - 1e-6
            assert uv[:, 0].max() <= cam.width - 1 - 10 + 1e-6
            assert uv[:, 1].max() <= cam.height - 1 - 10 + 1e-6


def test_rendered_centreline_matches_projected_ground_truth(
    flat_frames: list[SyntheticFrame],
) -> None:
    for frame in flat_frames:
        for view in (0, 1):
            err = _centreline_errors(frame, view)
            assert err.size > 200
            assert np.percentile(err, 95) < 0.5 and err.max() < 0.5, err.max()
            assert err.mean() < 0.2, err.mean()


def test_disparity_of_rendered_pair_matches_ground_truth_depth(
    flat_frames: list[SyntheticFrame],
) -> None:
    for frame in flat_frames:
        cam = frame.camera
        p = _gt_curve(frame)
        width = cam.fx * 0.5 / p[:, 2].min()
        cuts = []
        for view, image in enumerate((frame.left, frame.right)):
            dark = np.clip(205.0 - _grey(image), 0.0, None)
            cuts.append(_cut_centroids(dark, cam.project(p)[view], p[:, 2], width))
        # Pair the cuts of the same 3D point: same row, same depth, x_right = x_left - f b / Z.
        right = {}
        for row, c, x_gt, z in cuts[1]:
            right.setdefault(row, []).append((c, x_gt, z))
        err = []
        for row, c_left, x_gt, z in cuts[0]:
            for c_right, x_gt_right, z_right in right.get(row, []):
                same = abs(z_right - z) < 1e-3 and abs(x_gt - cam.disparity(z) - x_gt_right) < 1e-2
                if same:
                    err.append((c_left - c_right) - cam.fx * cam.baseline / z)
        assert len(err) > 30
        assert np.max(np.abs(err)) < 0.3, np.max(np.abs(err))


def test_same_seed_gives_identical_frames_and_different_seeds_differ() -> None:
    params = SyntheticParams(render=RenderParams(background="tissue", noise_sigma=2.0))
    a, b = generate_frame(params, 7), generate_frame(params, np.random.default_rng(7))
    np.testing.assert_array_equal(a.left, b.left)
    np.testing.assert_array_equal(a.right, b.right)
    np.testing.assert_array_equal(a.mask_left, b.mask_left)
    np.testing.assert_array_equal(a.truth.control_points, b.truth.control_points)
    c = generate_frame(params, 8)
    assert not np.array_equal(a.left, c.left)
    assert not np.array_equal(a.mask_left, c.mask_left)
    ca, cc = a.truth.control_points, c.truth.control_points
    assert ca.shape != cc.shape or not np.allclose(ca, cc)


def test_masks_match_the_rendered_thread(flat_frames: list[SyntheticFrame]) -> None:
    for frame in flat_frames:
        for image, mask in ((frame.left, frame.mask_left), (frame.right, frame.mask_right)):
            assert image.shape == (480, 640, 3) and image.dtype == np.uint8
            assert mask.shape == (480, 640) and mask.dtype == bool
            dark = 205.0 - _grey(image)
            assert dark[mask].min() > 20  # every mask pixel is clearly thread
            near = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            assert np.all(dark[~near] == 0)  # nothing drawn away from the mask
            n_parts, _ = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
            assert n_parts == 2  # background + one continuous thread
        assert (
            abs(int(frame.mask_left.sum()) - int(frame.mask_right.sum()))
            < 0.1 * frame.mask_left.sum()
        )


def test_crossing_option_crosses_itself_in_the_left_image() -> None:
    params = SyntheticParams(thread=ThreadParams(crossing=True))
    for seed in (0, 1):
        frame = generate_frame(params, seed)
        uv = frame.camera.project(_gt_curve(frame, 2001))[0]
        assert _polyline_self_crossings(uv, 20) >= 1
    for frame in [generate_frame(FLAT, s) for s in SEEDS]:
        uv = frame.camera.project(_gt_curve(frame, 2001))[0]
        assert _polyline_self_crossings(uv, 20) == 0


def test_leaves_image_option_runs_one_end_out_of_both_views() -> None:
    params = SyntheticParams(thread=ThreadParams(leaves_image=True))
    for seed in (0, 1, 2):
        frame = generate_frame(params, seed)
        cam = frame.camera
        for uv, mask in zip(
            cam.project(_gt_curve(frame)), (frame.mask_left, frame.mask_right), strict=True
        ):
            outside = (
                (uv[:, 0] < 0)
                | (uv[:, 0] > cam.width - 1)
                | (uv[:, 1] < 0)
                | (uv[:, 1] > cam.height - 1)
            )
            assert outside.any()
            assert outside[0] != outside[-1]  # exactly one end is outside
            border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
            assert border.any()


def test_tissue_background_is_reddish_with_glints_and_a_darker_thread() -> None:
    params = SyntheticParams(render=RenderParams(background="tissue", noise_sigma=2.0))
    frame = generate_frame(params, 3)
    img = frame.left.astype(float)
    r, g, b = img[..., 0].mean(), img[..., 1].mean(), img[..., 2].mean()
    assert r > g + 40 and r > b + 40
    assert np.count_nonzero(img.min(axis=2) > 235) > 5  # specular glints
    grey = _grey(frame.left)
    assert grey[frame.mask_left].mean() < grey[~frame.mask_left].mean() - 30


def test_occlusion_removes_hidden_thread_from_the_masks() -> None:
    base = generate_frame(FLAT, 4)
    occluded = generate_frame(SyntheticParams(render=RenderParams(occlusion=True)), 4)
    np.testing.assert_array_equal(base.truth.control_points, occluded.truth.control_points)
    for m0, m1 in ((base.mask_left, occluded.mask_left), (base.mask_right, occluded.mask_right)):
        assert not np.any(m1 & ~m0)
        assert 0.5 * m0.sum() <= m1.sum() < m0.sum()


@pytest.mark.parametrize(
    ("factory", "setting"),
    [
        (lambda: ThreadParams(length_mm=(0.0, 10.0)), "length_mm"),
        (lambda: ThreadParams(length_mm=(-5.0, 10.0)), "length_mm"),
        (lambda: ThreadParams(length_mm=(100.0, 50.0)), "length_mm"),
        (lambda: ThreadParams(depth_mm=(150.0, 70.0)), "depth_mm"),
        (lambda: ThreadParams(n_control=(3, 5)), "n_control"),
        (lambda: ThreadParams(n_control=(9, 8)), "n_control"),
        (lambda: ThreadParams(diameter_mm=0.0), "diameter_mm"),
        (lambda: StereoCamera(fx=-1.0), "fx"),
        (lambda: StereoCamera(baseline=0.0), "baseline"),
        (lambda: RenderParams(background="grass"), "background"),  # type: ignore[arg-type]
        (lambda: RenderParams(noise_sigma=-1.0), "noise_sigma"),
        (lambda: RenderParams(blur_sigma=-0.5), "blur_sigma"),
    ],
)
def test_invalid_settings_raise_value_error_naming_the_setting(factory, setting: str) -> None:
    with pytest.raises(ValueError, match=setting):
        factory()


def test_thread_that_cannot_fit_the_view_raises_value_error() -> None:
    too_long = SyntheticParams(
        thread=ThreadParams(length_mm=(900.0, 1000.0), depth_mm=(20.0, 30.0))
    )
    with pytest.raises(ValueError, match="length_mm"):
        generate_frame(too_long, 0)
    hard = SyntheticParams(thread=ThreadParams(length_mm=(140.0, 140.0), depth_mm=(20.0, 25.0)))
    with pytest.raises(ValueError, match="length_mm"):
        generate_frame(hard, 0)


@pytest.mark.parametrize("seed", SEEDS)
def test_hairpin_strands_run_side_by_side_without_touching(seed: int) -> None:
    frame = generate_frame(SyntheticParams(thread=ThreadParams(hairpin=True)), rng=seed)
    n, _ = cv2.connectedComponents(frame.mask_left.astype(np.uint8), connectivity=8)
    assert n == 2  # one thread, strands never merged
    uv, _ = frame.camera.project(frame.truth.centerline)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
    d = np.linalg.norm(uv[:, None] - uv[None, :], axis=2)
    far = np.abs(s[:, None] - s[None, :]) > 60.0  # arc-distant parts of the curve
    assert np.min(d[far]) < 30.0  # yet close in the image: side by side


@pytest.mark.parametrize("seed", SEEDS)
def test_spiral_winds_turns_that_stay_apart_in_3d_and_in_the_image(seed: int) -> None:
    frame = generate_frame(SyntheticParams(thread=ThreadParams(spiral=True)), rng=seed)
    n, _ = cv2.connectedComponents(frame.mask_left.astype(np.uint8), connectivity=8)
    assert n == 2  # one thread, turns never merged in the image
    c = frame.truth.centerline
    uv, _ = frame.camera.project(c)
    heading = np.unwrap(np.arctan2(*np.diff(uv, axis=0).T[::-1]))
    assert np.ptp(heading) >= 2 * math.pi * 1.4  # at least ~1.5 turns in the image
    s = np.arange(len(c)) * 0.25  # the centreline is uniform in arc, 0.25 mm
    d = np.linalg.norm(c[:, None] - c[None, :], axis=2)
    other_turn = np.abs(s[:, None] - s[None, :]) > 8.0
    assert 1.5 <= np.min(d[other_turn]) <= 6.5  # neighbouring turns 2-6 mm apart


def test_spiral_cannot_be_combined_with_hairpin_or_crossing() -> None:
    for other in ({"hairpin": True}, {"crossing": True}):
        with pytest.raises(ValueError, match="spiral"):
            ThreadParams(spiral=True, **other)


def test_hairpin_and_crossing_cannot_both_be_set() -> None:
    with pytest.raises(ValueError, match="hairpin"):
        ThreadParams(hairpin=True, crossing=True)


# --- realism options: dyes, distractors, grasper, lighting, JPEG --------------------------------

TISSUE = RenderParams(background="tissue")


@pytest.mark.parametrize(
    "option",
    [
        {"distractors": 8},
        {"lighting": 0.6},
        {"jpeg_quality": 60},
        {"thread_colour": "green"},
        {"specular": 0.4},
    ],
)
def test_realism_options_keep_the_thread_and_its_mask(option: dict) -> None:
    base = generate_frame(SyntheticParams(render=TISSUE), 7)
    other = generate_frame(SyntheticParams(render=replace(TISSUE, **option)), 7)
    np.testing.assert_array_equal(other.truth.control_points, base.truth.control_points)
    np.testing.assert_array_equal(other.mask_left, base.mask_left)
    np.testing.assert_array_equal(other.mask_right, base.mask_right)
    assert not np.array_equal(other.left, base.left)


@pytest.mark.parametrize("colour", ["violet", "blue", "green", "black", "white", "red"])
def test_thread_colour_paints_the_thread_in_that_dye(colour: str) -> None:
    frame = generate_frame(SyntheticParams(render=replace(TISSUE, thread_colour=colour)), 3)
    core = cv2.erode(frame.mask_left.astype(np.uint8), np.ones((2, 2), np.uint8)).astype(bool)
    mean = frame.left[core].astype(float).mean(axis=0)
    target = np.array(THREAD_COLOURS[colour])
    # The tube is shaded (edges at 75 %) and highlighted: within 30 % of the dye per channel.
    assert np.all(np.abs(mean - target) <= 0.3 * target + 25), (mean, target)


def test_distractors_add_thread_wide_lines_off_the_thread() -> None:
    base = generate_frame(SyntheticParams(render=TISSUE), 9)
    other = generate_frame(SyntheticParams(render=replace(TISSUE, distractors=10)), 9)
    changed = np.abs(other.left.astype(int) - base.left.astype(int)).max(axis=2) > 20
    assert changed[~base.mask_left].sum() > 2000  # new lines on the tissue
    # Lines, not blobs: most changed pixels are within 4 px of an unchanged one.
    thin = cv2.erode(changed.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert thin.sum() < 0.1 * changed.sum()


def test_instrument_hides_thread_only_where_it_covers_it() -> None:
    for seed in range(6):
        base = generate_frame(SyntheticParams(render=TISSUE), seed)
        other = generate_frame(SyntheticParams(render=replace(TISSUE, instrument=True)), seed)
        assert not np.any(other.mask_left & ~base.mask_left)  # coverage only removed
        grey = np.abs(other.left.astype(int) - base.left.astype(int)).max(axis=2) > 30
        assert grey.sum() > 2000  # a shaft is drawn
        hidden = base.mask_left & ~other.mask_left
        # the thread disappears only under the drawn instrument: within 2 px of where the image
        # changed by > 30 grey levels (at the shaft's edge its shading can match the thread's)
        drawn = cv2.dilate(grey.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert np.all(drawn[hidden])


def test_lighting_darkens_part_of_the_view_by_up_to_the_setting() -> None:
    base = generate_frame(SyntheticParams(render=TISSUE), 4)
    lit = generate_frame(SyntheticParams(render=replace(TISSUE, lighting=0.6)), 4)
    ratio = (lit.left.astype(float) + 1) / (base.left.astype(float) + 1)
    assert ratio.max() <= 1.01
    assert 0.35 <= np.percentile(ratio, 1) <= 0.6


@pytest.mark.parametrize(
    ("render", "setting"),
    [
        ({"thread_colour": "pink"}, "render.thread_colour"),
        ({"distractors": -1}, "render.distractors"),
        ({"lighting": 0.9}, "render.lighting"),
        ({"jpeg_quality": 101}, "render.jpeg_quality"),
        ({"background": "flat", "distractors": 3}, "render.distractors"),
    ],
)
def test_invalid_realism_settings_name_the_setting(render: dict, setting: str) -> None:
    with pytest.raises(ValueError, match=setting.replace(".", r"\.")):
        RenderParams(**{"background": "tissue", **render})
