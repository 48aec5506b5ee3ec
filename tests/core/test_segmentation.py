"""Tests of core/segmentation.py: input pair checks, thresholding and lifting, Eq. (1)."""

import re
from dataclasses import replace

import cv2
import numpy as np
import pytest
from support import assert_close, calibration_for

from threadrecon.core.pipeline import Pipeline
from threadrecon.core.segment_raw import noise_sigma
from threadrecon.core.segmentation import (
    LIFT_VALUE,
    SegmentationParams,
    StereoPair,
    _lift,
    segment,
    split_side_by_side,
)
from threadrecon.core.synthetic import RenderParams, SyntheticParams, ThreadParams, generate_frame

BG, INK = 200, 60


def _line_pair(shift: int = 3) -> StereoPair:
    """Flat background BG with a dark 2-px line (rows 20-21) in both views, shifted by ``shift``."""
    left = np.full((48, 64), BG, np.uint8)
    right = left.copy()
    left[20:22, 10:50] = INK
    right[20:22, 10 - shift : 50 - shift] = INK
    return StereoPair(left, right)


def test_background_level_is_estimated_and_line_segmented() -> None:
    pair = _line_pair()
    lifted = segment(pair, SegmentationParams(lift_dilate_px=0))
    assert lifted.background == (BG, BG)
    expected = np.zeros((48, 64), bool)
    expected[20:22, 10:50] = True
    assert_close(lifted.P_L, expected)
    assert_close(lifted.P_R, np.roll(expected, -3, axis=1))


def test_rgb_input_is_segmented_like_grey() -> None:
    pair = _line_pair()
    rgb = StereoPair(
        np.repeat(pair.left[:, :, None], 3, 2), np.repeat(pair.right[:, :, None], 3, 2)
    )
    assert_close(segment(rgb).P_L, segment(pair).P_L)


def test_lifting_sets_255_outside_the_mask_eq1() -> None:
    pair = _line_pair()
    lifted = segment(pair, SegmentationParams(lift_dilate_px=0))
    grey = pair.left.astype(np.float32)
    assert lifted.I_L.dtype == np.float32
    assert_close(lifted.I_L[lifted.P_L], grey[lifted.P_L])
    assert np.all(lifted.I_L[~lifted.P_L] == LIFT_VALUE)


@pytest.mark.parametrize("dilate", [1, 2])
def test_lifting_keeps_intensities_on_the_dilated_mask(dilate: int) -> None:
    pair = _line_pair()
    lifted = segment(pair, SegmentationParams(lift_dilate_px=dilate))
    rows, cols = np.nonzero(lifted.P_L)
    yy, xx = np.mgrid[:48, :64]
    # Chebyshev distance of every pixel to the mask (square structuring element).
    dist = np.min(np.maximum(np.abs(yy[..., None] - rows), np.abs(xx[..., None] - cols)), axis=-1)
    near = dist <= dilate
    assert_close(lifted.I_L[near], pair.left.astype(np.float32)[near])
    assert np.all(lifted.I_L[~near] == LIFT_VALUE)


@pytest.mark.parametrize("dilate", [0, 1, 3])
def test_lift_writes_the_box_of_a_strided_mask_in_place(dilate: int) -> None:
    """_lift reads P's box through its strides and writes the box of its output in place
    (cv2's masked copy): the same values as Eq. (1) on the whole image, for a mask that is a
    strided view, boxes at the image's borders and a given box."""
    rng = np.random.default_rng(5)
    grey = rng.uniform(0, 250, (40, 70)).astype(np.float32)
    wide = np.zeros((40, 140), bool)
    P = wide[:, ::2]  # a view with a column stride of 2
    P[0:6, 60:70] = rng.random((6, 10)) < 0.4
    P[30:40, 0:5] = True
    P[20, 33] = True
    k = np.ones((2 * dilate + 1, 2 * dilate + 1), np.uint8)
    near = cv2.dilate(P.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    expected = np.where(near, grey, np.float32(LIFT_VALUE))
    for box in (None, (slice(0, 40), slice(0, 70)), (slice(0, 40), slice(0, 70, 1))):
        got = _lift(grey, P, dilate, box)
        assert got.dtype == np.float32 and got.flags.c_contiguous
        np.testing.assert_array_equal(got, expected)
    assert not wide[:, 1::2].any()  # the mask is read, never written


def test_given_masks_replace_thresholding() -> None:
    pair = _line_pair()
    mask = np.zeros((48, 64), bool)
    mask[5:8, 5:9] = True
    masked = StereoPair(pair.left, pair.right, mask, mask)
    lifted = segment(masked, SegmentationParams(lift_dilate_px=0))
    assert_close(lifted.P_L, mask)
    assert_close(lifted.P_R, mask)


def test_empty_segmentation_raises() -> None:
    blank = np.full((32, 32, 3), 255, np.uint8)
    with pytest.raises(ValueError, match="empty segmentation"):
        segment(StereoPair(blank, blank.copy()))


def test_specks_below_min_component_are_dropped() -> None:
    pair = _line_pair()
    left = pair.left.copy()
    left[40, 5] = INK  # a 1-px speck
    lifted = segment(StereoPair(left, pair.right), SegmentationParams(min_component_px=4))
    assert not lifted.P_L[40, 5]
    assert lifted.P_L[20, 20]


def test_size_mismatch_names_both_sizes() -> None:
    with pytest.raises(ValueError, match=r"\(20, 30\).*\(20, 32\)"):
        StereoPair(np.zeros((20, 30), np.uint8), np.zeros((20, 32), np.uint8))


@pytest.mark.parametrize("shape", [(10,), (10, 10, 2), (4, 5, 6, 3)])
def test_wrong_image_shape_names_the_shape(shape: tuple[int, ...]) -> None:
    bad = np.zeros(shape, np.uint8)
    good = np.zeros((10, 10), np.uint8)
    with pytest.raises(ValueError, match=r"left image.*" + re.escape(repr(shape))):
        StereoPair(bad, good)


def test_mask_shape_is_checked() -> None:
    img = np.zeros((16, 16), np.uint8)
    with pytest.raises(ValueError, match="mask_left"):
        StereoPair(img, img, np.zeros((8, 8), bool), np.zeros((16, 16), bool))
    with pytest.raises(ValueError, match="both masks"):
        StereoPair(img, img, np.zeros((16, 16), bool), None)


def test_split_side_by_side_halves_and_rejects_odd_width() -> None:
    img = np.arange(6 * 10).reshape(6, 10)
    left, right = split_side_by_side(img)
    assert_close(left, img[:, :5])
    assert_close(right, img[:, 5:])
    with pytest.raises(ValueError, match=r"even width.*\(6, 11\)"):
        split_side_by_side(np.zeros((6, 11)))


# --- raw frames (no mask): method "raw", "auto", "threshold" -----------------------------------

TISSUE = RenderParams(background="tissue", noise_sigma=2.0, blur_sigma=0.5)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / max(float((a | b).sum()), 1.0)


def _raw(render: RenderParams, seed: int, **thread: object) -> tuple[StereoPair, object]:
    frame = generate_frame(SyntheticParams(thread=ThreadParams(**thread), render=render), seed)
    return StereoPair(frame.left, frame.right), frame


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_raw_method_finds_the_thread_on_tissue(seed: int) -> None:
    pair, frame = _raw(TISSUE, seed)
    lifted = segment(pair)
    assert lifted.method == "raw"
    assert _iou(lifted.P_L, frame.mask_left) >= 0.8
    assert _iou(lifted.P_R, frame.mask_right) >= 0.8


@pytest.mark.parametrize("colour", ["violet", "blue", "green", "black", "white"])
def test_raw_method_finds_threads_of_any_dye(colour: str) -> None:
    pair, frame = _raw(replace(TISSUE, thread_colour=colour), 21)
    lifted = segment(pair)
    assert _iou(lifted.P_L, frame.mask_left) >= 0.75
    assert _iou(lifted.P_R, frame.mask_right) >= 0.75


def test_raw_method_leaves_thread_wide_vessels_and_fibres_out() -> None:
    pair, frame = _raw(replace(TISSUE, distractors=8), 31)
    lifted = segment(pair)
    assert _iou(lifted.P_L, frame.mask_left) >= 0.8
    # Little far from the thread: <= 8 % of the segmented pixels lie > 3 px from the true mask.
    near = cv2.dilate(frame.mask_left.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    assert (lifted.P_L & ~near).sum() <= 0.08 * lifted.P_L.sum()


def test_raw_method_survives_uneven_light_jpeg_and_a_grasper() -> None:
    render = replace(TISSUE, lighting=0.6, jpeg_quality=70, instrument=True, noise_sigma=3.0)
    pair, frame = _raw(render, 41)
    lifted = segment(pair)
    assert _iou(lifted.P_L, frame.mask_left) >= 0.7
    assert _iou(lifted.P_R, frame.mask_right) >= 0.7


def test_raw_method_gives_a_score_layer_in_unit_range() -> None:
    pair, frame = _raw(TISSUE, 11)
    lifted = segment(pair)
    for score, mask in ((lifted.score_L, frame.mask_left), (lifted.score_R, frame.mask_right)):
        assert score is not None and score.dtype == np.float32 and score.shape == mask.shape
        assert score.min() >= 0.0 and score.max() <= 1.0
        assert np.median(score[mask]) > 4 * np.median(score[~mask])


@pytest.mark.parametrize("render", [TISSUE, RenderParams(noise_sigma=6.0)])
def test_a_frame_without_a_thread_is_no_thread_found(render: RenderParams) -> None:
    # A thread 1e-6 mm thick covers no pixel: tissue (or noise) only, with vessels and glints.
    empty = generate_frame(
        SyntheticParams(thread=ThreadParams(diameter_mm=1e-6), render=render), 51
    )
    assert not empty.mask_left.any()
    with pytest.raises(ValueError, match="no thread found"):
        segment(StereoPair(empty.left, empty.right), SegmentationParams(method="raw"))


@pytest.mark.parametrize(
    "render",
    [
        TISSUE,
        replace(TISSUE, lighting=0.6),
        replace(TISSUE, noise_sigma=3.0, jpeg_quality=60),
        replace(TISSUE, specular=0.4, noise_sigma=4.0),
        replace(TISSUE, distractors=6),  # fibres and vessels lie on the tissue surface
    ],
)
@pytest.mark.parametrize("seed", [101, 102, 103])
def test_thread_free_tissue_frames_are_no_thread_found(render: RenderParams, seed: int) -> None:
    # Vessels (one hue), fibres, glints and instruments only: none of them is a thread.
    empty = generate_frame(
        SyntheticParams(thread=ThreadParams(diameter_mm=1e-6), render=render), seed
    )
    with pytest.raises(ValueError, match="no thread found"):
        segment(StereoPair(empty.left, empty.right), SegmentationParams(method="raw"))


@pytest.mark.parametrize("side", [0, 1])
def test_a_raw_view_left_empty_after_cleaning_is_no_thread_found(monkeypatch, side: int) -> None:
    """The raw method's last cleaning (specks) can leave one view without a pixel: that view
    shows no thread, the frame's answer is "no thread found" (a threshold's empty view stays
    an "empty segmentation")."""
    from threadrecon.core import segmentation as seg_module

    frame = generate_frame(SyntheticParams(render=TISSUE), 101)
    masks = [frame.mask_left.copy(), frame.mask_right.copy()]
    masks[side][:] = False
    monkeypatch.setattr(seg_module, "segment_raw", lambda *a, **k: (*masks, None, None))
    name = ("left", "right")[side]
    with pytest.raises(ValueError, match=f"^no thread found: no thread pixel in the {name} image"):
        segment(StereoPair(frame.left, frame.right), SegmentationParams(method="raw"))


@pytest.mark.parametrize("seed", [101, 102])
def test_thread_free_frames_with_a_grasper_are_no_thread_found(seed: int) -> None:
    render = replace(TISSUE, instrument=True)
    empty = generate_frame(
        SyntheticParams(thread=ThreadParams(diameter_mm=1e-6), render=render), seed
    )
    with pytest.raises(ValueError, match="no thread found"):
        segment(StereoPair(empty.left, empty.right), SegmentationParams(method="raw"))


@pytest.mark.parametrize("seed", [111, 112, 113])
def test_a_red_thread_is_told_from_the_vessels(seed: int) -> None:
    # A red dye is blood-like, but its hue differs from the frame's vessels.
    pair, frame = _raw(replace(TISSUE, thread_colour="red"), seed)
    lifted = segment(pair)
    assert _iou(lifted.P_L, frame.mask_left) >= 0.7
    assert _iou(lifted.P_R, frame.mask_right) >= 0.7


def test_no_thread_found_stops_the_pipeline_with_that_reason() -> None:
    empty = generate_frame(
        SyntheticParams(thread=ThreadParams(diameter_mm=1e-6), render=TISSUE), 52
    )
    rec = Pipeline(StereoPair(empty.left, empty.right), calibration_for(empty.camera)).run()
    assert rec.status == "failed" and rec.failed_stage == "segment"
    assert "no thread found" in (rec.message or "")
    assert "camera" not in rec.runs


def test_threshold_method_is_the_grey_threshold_unchanged() -> None:
    pair, _ = _raw(TISSUE, 11)
    p = SegmentationParams(method="threshold", min_component_px=1, lift_dilate_px=0)
    lifted = segment(pair, p)
    grey = cv2.cvtColor(pair.left, cv2.COLOR_RGB2GRAY).astype(np.float32)
    level = float(np.argmax(np.bincount(grey.astype(np.uint8).ravel(), minlength=256)))
    assert lifted.method == "threshold"
    assert_close(lifted.P_L, grey < level - p.seg_delta)


@pytest.mark.parametrize("seed", [1, 2])
def test_auto_uses_the_threshold_on_flat_backgrounds(seed: int) -> None:
    pair, _ = _raw(RenderParams(), seed)
    auto = segment(pair)
    threshold = segment(pair, SegmentationParams(method="threshold"))
    assert auto.method == "threshold"
    assert_close(auto.P_L, threshold.P_L)
    assert_close(auto.P_R, threshold.P_R)
    assert_close(auto.I_L, threshold.I_L)


def test_given_masks_skip_segmentation_and_have_no_score() -> None:
    pair, frame = _raw(TISSUE, 11)
    masked = StereoPair(pair.left, pair.right, frame.mask_left, frame.mask_right)
    lifted = segment(masked, SegmentationParams(method="raw"))
    assert lifted.method == "mask" and lifted.score_L is None
    assert_close(lifted.P_L, frame.mask_left)


@pytest.mark.parametrize(
    ("field", "value"), [("method", "magic"), ("flat_share", 1.5), ("ridge_hi", -1.0)]
)
def test_bad_raw_parameters_are_rejected_by_name(field: str, value: object) -> None:
    pair, _ = _raw(TISSUE, 11)
    with pytest.raises(ValueError, match=field):
        segment(pair, replace(SegmentationParams(), **{field: value}))


def test_raw_method_finds_the_thread_on_a_noisy_flat_background() -> None:
    pair, frame = _raw(RenderParams(noise_sigma=6.0, blur_sigma=0.7), 61)
    lifted = segment(pair)
    assert lifted.method == "raw"  # noise: the background is not flat to 1 grey level
    assert _iou(lifted.P_L, frame.mask_left) >= 0.8
    assert _iou(lifted.P_R, frame.mask_right) >= 0.8


@pytest.mark.parametrize("sigma", [0.5, 2.0, 8.0])
def test_noise_sigma_recovers_the_pixel_noise_of_a_textured_image(sigma: float) -> None:
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[:240, :320].astype(np.float32)
    smooth = 4 * np.sin(xx / 40) + 10 * np.cos(yy / 17)  # row-wise steps << the noise
    f = (smooth[:, :, None] + rng.normal(0, sigma, (240, 320, 3))).astype(np.float32)
    assert_close(noise_sigma(f), np.full(3, sigma), rtol=0.1)


def test_a_thread_fainter_than_the_noise_is_no_thread_found() -> None:
    # Contrast 3 grey levels under noise of 6: nothing stands 5 noise sigmas out.
    render = RenderParams(noise_sigma=6.0, thread_rgb=(202.0, 202.0, 202.0), specular=0.0)
    pair, _ = _raw(render, 62)
    with pytest.raises(ValueError, match="no thread found"):
        segment(pair, SegmentationParams(method="raw"))


@pytest.mark.parametrize("seed", [21, 22, 23])
def test_auto_threshold_leaves_an_instrument_over_a_flat_background_out(seed: int) -> None:
    pair, frame = _raw(RenderParams(occlusion=True), seed)
    auto = segment(pair)
    strict = segment(pair, SegmentationParams(method="threshold"))
    assert auto.method == "threshold"
    for P, S, M in (
        (auto.P_L, strict.P_L, frame.mask_left),
        (auto.P_R, strict.P_R, frame.mask_right),
    ):
        near = cv2.dilate(M.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert (S & ~near).sum() > 1000  # the paper's threshold takes the shaft for thread
        assert (P & ~near).sum() <= 0.02 * P.sum()  # auto drops it
        assert (P & M).sum() >= 0.9 * M.sum()  # and keeps the thread on both sides of it


def test_the_wide_parts_quick_reject_is_exact() -> None:
    """_drop_wide skips the disc's erosion where the inscribed square's finds nothing: the
    square lies inside the disc, so that answer is the disc's too."""
    from threadrecon.core import segmentation as seg

    r, h = seg._WIDE_PX, seg._INSCRIBED_SQUARE.shape[0] // 2
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    assert disc[r - h : r + h + 1, r - h : r + h + 1].all()
    rng = np.random.default_rng(4)
    for _ in range(20):  # random blobs: wherever the disc fits, the square fits
        off = np.zeros((120, 160), np.uint8)
        for _ in range(3):
            c = (int(rng.integers(0, 160)), int(rng.integers(0, 120)))
            cv2.circle(off, c, int(rng.integers(3, 16)), 255, -1)
        by_disc = cv2.erode(off, disc) > 0
        by_square = cv2.erode(off, seg._INSCRIBED_SQUARE) > 0
        assert not (by_disc & ~by_square).any()


def _wide_parts_in_full(off8: np.ndarray, dark8: np.ndarray) -> np.ndarray:
    """The shading-aware off-level pixels of :func:`_wide_parts` computed in full: the image
    whose square and disc erosions decide whether there is a wide part."""
    from threadrecon.core import segmentation as seg

    closed = cv2.morphologyEx(off8, cv2.MORPH_CLOSE, seg._GAP_DISC)
    light8 = cv2.bitwise_and(off8, cv2.compare(dark8, 0, cv2.CMP_EQ))
    both = cv2.bitwise_and(cv2.dilate(light8, seg._GAP_DISC), cv2.dilate(dark8, seg._GAP_DISC))
    return cv2.bitwise_or(off8, cv2.bitwise_and(closed, both))


def test_the_wide_parts_shading_is_skipped_when_the_closing_holds_no_square(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A thin thread: no square fits in the closed off-level pixels, so none in the shading-aware
    ones (they lie inside the closing), and _wide_parts answers None without the shading's
    dilations; on random blobs (some wide, some crossing the box's border) its answer is the
    one of the full computation."""
    from threadrecon.core import segmentation as seg

    rng = np.random.default_rng(7)
    square = seg._INSCRIBED_SQUARE
    decided = {True: 0, False: 0}
    for _ in range(60):
        off = np.zeros((90, 120), np.uint8)
        dark = np.zeros_like(off)
        for _ in range(int(rng.integers(1, 5))):
            c = (int(rng.integers(-5, 125)), int(rng.integers(-5, 95)))
            img = dark if rng.random() < 0.5 else off
            cv2.circle(img, c, int(rng.integers(2, 14)), 255, -1)
        off |= dark
        full = _wide_parts_in_full(off, dark)
        assert not (full & ~cv2.morphologyEx(off, cv2.MORPH_CLOSE, seg._GAP_DISC)).any()
        wide = cv2.countNonZero(cv2.erode(full, square)) > 0
        got = seg._wide_parts(off, dark)
        if not wide:
            assert got is None
        decided[wide] += 1
    assert decided[True] and decided[False]

    thread = np.zeros((60, 200), np.uint8)
    cv2.line(thread, (5, 10), (190, 50), 255, 3)

    def no_dilation(*args: object, **kwargs: object) -> None:
        raise AssertionError("the shading's dilation ran for a thin thread")

    monkeypatch.setattr(seg.cv2, "dilate", no_dilation)
    assert seg._wide_parts(thread, thread.copy()) is None


def test_the_auto_threshold_drops_specks_in_place_on_its_own_box(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The auto threshold clears the small components on P's own bounding box, in place: no
    copy of the box and no second bounding box (:func:`drop_specks` is not called), and the
    same masks as drop_specks on the whole image."""
    from threadrecon.core import segmentation as seg
    from threadrecon.core.segment_raw import drop_specks

    rng = np.random.default_rng(11)
    img = np.full((90, 120), 200, np.uint8)
    cv2.polylines(img, [np.array([[5, 10], [60, 70], [115, 30]], np.int32)], False, 60, 2)
    img[rng.integers(0, 90, 15), rng.integers(0, 120, 15)] = 50  # specks
    img[40:42, 100:102] = 50  # a 4 px component
    pair = StereoPair(img, img.copy())
    for min_px in (0, 1, 3, 5, 30):
        p = SegmentationParams(method="auto", flat_share=0.0, min_component_px=min_px)
        grey = img.astype(np.float32)
        expected = drop_specks(grey < 200 - p.seg_delta, min_px)
        with monkeypatch.context() as m:

            def no_copy(*args: object, **kwargs: object) -> None:
                raise AssertionError("the auto threshold called drop_specks")

            m.setattr(seg, "drop_specks", no_copy)
            lifted = segment(pair, p)
        assert np.array_equal(lifted.P_L, expected)
        assert np.array_equal(lifted.P_R, expected)
        assert (expected.sum() < (grey < 200 - p.seg_delta).sum()) == (min_px > 1)


def test_raw_mask_of_a_thin_thread_is_not_wider_than_its_coverage() -> None:
    # A 1-2 px thread steps from one pixel row to the next: the two pixels sharing it hold less
    # than 1.5 px of coverage, and the exact mask (coverage >= 0.5) takes one of them.
    ratios, ious = [], []
    for seed in (31, 32, 33):
        pair, frame = _raw(TISSUE, seed, diameter_mm=0.16)
        lifted = segment(pair)
        for P, M in ((lifted.P_L, frame.mask_left), (lifted.P_R, frame.mask_right)):
            ratios.append(P.sum() / M.sum())
            ious.append(_iou(P, M))
    assert np.mean(ratios) <= 1.3  # 1.36 before the shared-coverage rule
    assert np.mean(ious) >= 0.76  # 0.74 before


def _full_image_reference(pair: StereoPair, p: SegmentationParams) -> dict[str, np.ndarray]:
    """The threshold path of Eq. (1) computed pixel by pixel on the whole float32 image: the
    tables and bounding boxes of core/segmentation.py must give exactly this."""
    from threadrecon.core.instrument import drop_attached
    from threadrecon.core.segment_raw import drop_specks

    out: dict[str, np.ndarray] = {}
    for side, image in (("L", pair.left), ("R", pair.right)):
        grey = image.astype(np.float32)
        hist = np.bincount(image.ravel(), minlength=256)
        bg = float(np.argmax(hist)) if p.background is None else float(p.background)
        P = grey < bg - p.seg_delta
        if p.method == "auto":  # the instrument's wide parts left out
            off = (np.abs(grey - np.float32(bg)) > np.float32(p.seg_delta)).astype(np.uint8) * 255
            gap = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
            closed = cv2.morphologyEx(off, cv2.MORPH_CLOSE, gap)
            if p.shading_gaps:  # only gaps between a darker and a lighter pixel (deviation 39)
                dark = P.astype(np.uint8) * 255
                light = off & ~dark
                both = (cv2.dilate(light, gap) > 0) & (cv2.dilate(dark, gap) > 0)
                off = np.where(both, closed, off)
            else:
                off = closed
            core = cv2.erode(off, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21)))
            wide = cv2.dilate(core, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (25, 25))) > 0
            # The jaws' rule on the whole image: parts wider than the thread reaching the bar
            P = drop_attached(P & ~wide, wide, off > 0)
        P = drop_specks(P, p.min_component_px)
        scale = 1.0 / (2.0 * max(p.seg_delta, 1.0))
        out["P_" + side] = P
        out["score_" + side] = np.clip((bg - grey) * scale, 0.0, 1.0).astype(np.float32)
        d = p.lift_dilate_px
        near = cv2.dilate(P.astype(np.uint8), np.ones((2 * d + 1, 2 * d + 1), np.uint8)) > 0
        out["I_" + side] = np.where(near, grey, np.float32(LIFT_VALUE))
        out["grey_" + side] = grey
    return out


@pytest.mark.parametrize("method", ["auto", "threshold"])
@pytest.mark.parametrize("seed", range(6))
def test_threshold_path_equals_the_whole_image_formulas_bit_for_bit(seed: int, method: str) -> None:
    """Tables per grey level and work on the thread's bounding box change no value: random
    flat frames with dark curves, specks, a wide bar, noise, odd levels and deltas."""
    rng = np.random.default_rng(seed)
    background = [None, 180.7, 200.0][seed % 3]
    views = []
    for _ in range(2):
        level = int(rng.integers(150, 256)) if background is None else round(background)
        img = np.full((120, 160), level, np.uint8)
        for _ in range(3):
            pts = rng.integers(0, [160, 120], size=(6, 2)).astype(np.int32)
            cv2.polylines(img, [pts], False, int(rng.integers(0, 120)), int(rng.integers(1, 4)))
        img[rng.integers(0, 120, 12), rng.integers(0, 160, 12)] = 40  # specks
        if seed % 2:
            img[30:60, 100:140] = 90  # an instrument-wide bar
        noise = rng.normal(0, 1.0 + seed, img.shape) * (rng.random(img.shape) < 0.1)
        views.append(np.clip(img + noise, 0, 255).astype(np.uint8))
    pair = StereoPair(views[0], views[1])
    p = SegmentationParams(
        method=method,
        flat_share=0.0,  # auto always thresholds: its wide-part removal is tested too
        seg_delta=0.0 if seed == 0 else float(rng.choice([3.0, 6.0, 6.5, 17.3])),
        background=background,
        lift_dilate_px=int(rng.integers(0, 4)),
        min_component_px=int(rng.integers(0, 40)),
        shading_gaps=seed < 4,  # both ways of closing the wide parts' gaps
    )
    lifted = segment(pair, p)
    assert lifted.method == "threshold"
    for name, expected in _full_image_reference(pair, p).items():
        got = getattr(lifted, name)
        assert got.dtype == expected.dtype and got.shape == expected.shape, name
        assert np.array_equal(got, expected), name


def test_compiled_histogram_counts_every_grey_level_exactly() -> None:
    from threadrecon.core.segmentation import _Grey

    rng = np.random.default_rng(5)
    for shape in ((7, 9), (120, 161), (3, 1)):  # sizes not a multiple of 4 too
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        img[0, 0] = 255
        hist = _Grey(img).histogram()
        assert hist.dtype == np.int64 and np.array_equal(
            hist, np.bincount(img.ravel(), minlength=256)
        )


def test_one_scan_gives_the_float_copy_histogram_and_level_ranges_exactly() -> None:
    from threadrecon.core.segmentation import _Grey

    rng = np.random.default_rng(17)
    for shape in ((7, 9), (120, 161), (3, 1), (1, 5)):
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        flat = np.where(rng.random(shape) < 0.3, img, np.uint8(rng.integers(0, 256)))
        for view in (img, img[:, ::-1].copy(), flat):  # rows mostly at one level, or not
            g = _Grey(view)
            assert g.f32.dtype == np.float32 and np.array_equal(g.f32, view.astype(np.float32))
            assert np.array_equal(g.histogram(), np.bincount(view.ravel(), minlength=256))
            assert np.array_equal(g.rows[0], view.min(axis=1))
            assert np.array_equal(g.rows[1], view.max(axis=1))
            assert np.array_equal(g.cols[0], view.min(axis=0))
            assert np.array_equal(g.cols[1], view.max(axis=0))


def test_box_of_levels_is_the_bounding_box_of_the_looked_up_image() -> None:
    """The box from the rows' and columns' level ranges equals cv2.boundingRect of the table
    lookup for every table whose zero levels form one run (empty, all, one level, none); other
    tables are left to the lookup (None)."""
    from threadrecon.core.segmentation import _Grey

    rng = np.random.default_rng(3)
    for trial in range(200):
        h, w = rng.integers(1, 40, size=2)
        img = np.full((h, w), rng.integers(0, 256), np.uint8)
        k = rng.integers(0, 6)
        ys, xs = rng.integers(0, h, k), rng.integers(0, w, k)
        img[ys, xs] = rng.integers(0, 256, k)  # a few pixels at other levels
        a = int(rng.integers(0, 257))
        b = int(rng.integers(a, 258))
        table = np.ones(256, np.uint8) * np.uint8(rng.integers(1, 4))
        table[a:b] = 0  # zero levels: one run [a, b), possibly empty or all
        expected = cv2.boundingRect(cv2.LUT(img, table))
        assert _Grey(img).box_of_levels(table) == tuple(expected), trial
    table = np.zeros(256, np.uint8)
    table[[10, 200]] = 1  # the zero levels form two runs: no box from the ranges
    assert _Grey(img).box_of_levels(table) is None


def test_threshold_score_is_computed_on_first_read_once_and_survives_copies() -> None:
    from dataclasses import fields

    from threadrecon.core.corrections import Correction, apply_corrections
    from threadrecon.core.segmentation import LiftedPair

    lifted = segment(_line_pair(), SegmentationParams(method="threshold"))
    assert type(lifted.__dict__["_lazy_score_L"]).__name__ == "Deferred"  # not computed yet
    expected = np.clip((BG - lifted.grey_L) / 12.0, 0.0, 1.0).astype(np.float32)
    score = lifted.score_L
    assert score is lifted.score_L and np.array_equal(score, expected)  # kept after one read
    copied = replace(lifted, method="copied")
    assert copied.score_L is score and np.array_equal(copied.score_R, lifted.score_R)
    assert [f.name for f in fields(LiftedPair)][-3:] == ["score_L", "score_R", "method"]
    erase = Correction(op="erase", view="left", points=((30, 20),), radius=3.0)
    corrected = apply_corrections(lifted, (erase,))  # copies every field of the pair
    assert corrected.score_L is score and not np.array_equal(corrected.P_L, lifted.P_L)


def test_auto_thresholds_a_flat_view_that_a_large_shaft_fills_in_part() -> None:
    # The shaft covers ~25 % of each view: the share of background-level pixels is ~70 %, but
    # of the pixels off the instrument it is ~95 %: a flat background, thresholded.
    views, threads = [], []
    for shift in (0, 12):
        img = np.full((120, 160), 205, np.uint8)
        thread = np.zeros(img.shape, np.uint8)
        cv2.polylines(thread, [np.array([[10, 100], [60, 70], [150, 90]], np.int32) - [shift, 0]],
                      False, 1, 2)  # fmt: skip
        img[thread > 0] = 120
        shaft = np.zeros(img.shape, np.uint8)  # a capsule 30 px wide, in front of the thread
        cv2.line(shaft, (45 - shift, 35), (175 - shift, 35), 1, 30)
        img[shaft > 0] = 150
        thread[shaft > 0] = 0
        views.append(img)
        threads.append(thread > 0)
    lifted = segment(StereoPair(views[0], views[1]))
    assert lifted.method == "threshold"
    for P, T in ((lifted.P_L, threads[0]), (lifted.P_R, threads[1])):
        assert not P[18:52].any()  # no shaft
        assert (P & T).sum() >= 0.9 * T.sum()


def _shaft_and_thread_along_it(shift: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A flat view (grey 200): a horizontal shaft (rows 100-135, grey 150, a highlight of 240
    in rows 113-116, the shading crossing the background level on 2 px rows each side) and a
    5 px thread (grey 120) that comes down from the top left and runs along the shaft's top
    edge 3 px above it (rows 92-96) from x = 100 to 260. Returns the view (RGB) and the
    thread's pixels."""
    g = np.full((240, 400), 200, np.uint8)
    g[100:136, :] = 150
    g[111:113, :] = 200  # the shading crosses the background level: rims to highlight
    g[113:117, :] = 240
    g[117:119, :] = 200
    thread = np.zeros(g.shape, np.uint8)
    cv2.line(thread, (20 + shift, 10), (100 + shift, 94), 255, 3)
    cv2.line(thread, (100 + shift, 94), (260 + shift, 94), 255, 3)
    g[thread > 0] = 120
    return np.repeat(g[:, :, None], 3, axis=2), thread > 0


def test_auto_keeps_a_thread_along_a_shafts_edge() -> None:
    # Closing every 4-px gap joined the thread to the shaft's dark rim: the wide part's disc
    # fit across both and its rim swallowed the thread along the edge. A gap between two
    # darker objects is background, not a shading (deviation 39).
    left, thread_l = _shaft_and_thread_along_it(0)
    right, thread_r = _shaft_and_thread_along_it(-10)
    pair = StereoPair(left, right)
    along = np.zeros(thread_l.shape, bool)
    along[90:100, 110:250] = True  # the thread's stretch along the edge, in both views
    for shading_gaps, kept in ((True, 0.9), (False, None)):
        lifted = segment(pair, SegmentationParams(shading_gaps=shading_gaps))
        assert lifted.method == "threshold"
        for P, T in ((lifted.P_L, thread_l), (lifted.P_R, thread_r)):
            assert not P[100:136].any()  # the shaft is left out either way
            share = (P & T & along).sum() / (T & along).sum()
            if kept is None:
                assert share < 0.1  # every gap closed: the edge's thread is the shaft's
            else:
                assert share >= kept
