"""Tests of core/corrections.py and of the corrections' way through the pipeline: a removed
piece is exactly the clicked piece, an added piece is the thread at the click and nothing
else, brushes, clear, order, hostile values, and the segment stage's cache."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from support import calibration_for, far_spot, synthetic_frame

from threadrecon.core.corrections import (
    MAX_RADIUS_PX,
    CorrectedPair,
    Correction,
    apply_corrections,
)
from threadrecon.core.pipeline import STAGES, Pipeline, ReconParams
from threadrecon.core.segmentation import SegmentationParams, StereoPair, segment


def _distracted_case(seed: int = 0):
    """A flat frame whose images and given masks hold the thread and a thread-like dark
    stripe away from it (same rows in both views); the exact thread masks."""
    f = synthetic_frame(seed)
    left, right = f.left.copy(), f.right.copy()
    mL, mR = f.mask_left.copy(), f.mask_right.copy()
    x, y = far_spot(mL | np.roll(mR, 20, axis=1), 60, margin=25)
    for img, m, shift in ((left, mL, 0), (right, mR, -20)):
        cv2.line(img, (x + shift, y), (x + shift + 60, y + 8), (40, 40, 40), 2)
        stripe = np.zeros(m.shape, np.uint8)
        cv2.line(stripe, (x + shift, y), (x + shift + 60, y + 8), 1, 2)
        m |= stripe.astype(bool)
    pair = StereoPair(left, right, mL, mR)
    return pair, f, (x + 30, y + 4)


def test_remove_drops_exactly_the_clicked_piece() -> None:
    pair, f, (x, y) = _distracted_case()
    lifted = segment(pair, SegmentationParams())
    fixed = apply_corrections(
        lifted,
        (
            Correction("remove", "left", ((x, y + 3),)),
            Correction("remove", "right", ((x - 20, y),)),
        ),
        images=(pair.left, pair.right),
    )
    assert np.array_equal(fixed.P_L, f.mask_left)
    assert np.array_equal(fixed.P_R, f.mask_right)
    assert fixed.changed_px[0] == int((lifted.P_L & ~f.mask_left).sum()) > 60
    assert np.array_equal(fixed.removed_L, lifted.P_L & ~f.mask_left)
    assert not fixed.added_L.any()
    # Eq. (1) is redone on the corrected mask: the stripe is lifted to 255 again
    assert np.all(fixed.I_L[y - 1 : y + 2, x] == 255.0)


def test_stereo_remove_takes_the_partner_on_the_same_rows_and_never_the_thread() -> None:
    pair, f, (x, y) = _distracted_case()
    lifted = segment(pair, SegmentationParams())
    fixed = apply_corrections(lifted, (Correction("remove", "left", ((x, y),), stereo=True),))
    assert np.array_equal(fixed.P_L, f.mask_left)
    assert np.array_equal(fixed.P_R, f.mask_right)  # the thread of the right view stays
    assert fixed.changed_px[0] == int(
        (lifted.P_L ^ f.mask_left).sum() + (lifted.P_R ^ f.mask_right).sum()
    )
    # from the right view: the partner lies to the right in the left view
    back = apply_corrections(lifted, (Correction("remove", "right", ((x - 20, y),), stereo=True),))
    assert np.array_equal(back.P_L, f.mask_left) and np.array_equal(back.P_R, f.mask_right)


def test_stereo_remove_leaves_a_piece_at_a_negative_disparity() -> None:
    f = synthetic_frame(0)
    mL, mR = f.mask_left.copy(), f.mask_right.copy()
    x, y = far_spot(mL | np.roll(mR, -20, axis=1), 60, margin=25)
    for m, shift in ((mL, 0), (mR, 20)):  # in the right view 20 px to the right: d = -20
        stripe = np.zeros(m.shape, np.uint8)
        cv2.line(stripe, (x + shift, y), (x + shift + 60, y + 8), 1, 2)
        m |= stripe.astype(bool)
    lifted = segment(StereoPair(f.left, f.right, mL, mR))
    fixed = apply_corrections(
        lifted, (Correction("remove", "left", ((x + 30, y + 4),), stereo=True),)
    )
    assert np.array_equal(fixed.P_L, f.mask_left)
    assert np.array_equal(fixed.P_R, mR)


def test_remove_far_from_every_piece_changes_nothing() -> None:
    pair, f, _ = _distracted_case()
    lifted = segment(pair, SegmentationParams())
    x, y = far_spot(lifted.P_L, 5, margin=30)
    fixed = apply_corrections(lifted, (Correction("remove", "left", ((x, y),), radius=8),))
    assert fixed.changed_px == (0,)
    assert np.array_equal(fixed.P_L, lifted.P_L)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_add_restores_the_cut_thread_and_nothing_else(seed: int) -> None:
    f = synthetic_frame(seed)
    ys, xs = np.nonzero(f.mask_left)
    end = f.mask_left & (xs.min() + 0.7 * (xs.max() - xs.min()) < np.arange(f.mask_left.shape[1]))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(end.astype(np.uint8))
    cut = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))  # one piece of the thread
    given = f.mask_left & ~cut
    lifted = segment(StereoPair(f.left, f.right, given, f.mask_right), SegmentationParams())
    cy, cx = np.argwhere(cut)[len(np.argwhere(cut)) // 2]
    fixed = apply_corrections(
        lifted, (Correction("add", "left", ((int(cx) + 2, int(cy) + 2),)),),
        images=(f.left, f.right),
    )  # fmt: skip
    near = cv2.dilate(f.mask_left.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert (fixed.P_L & cut).sum() >= 0.9 * cut.sum()
    assert not (fixed.added_L & ~near).any()  # nothing farther than 2 px from the thread
    assert np.array_equal(fixed.P_R, f.mask_right)


def test_add_on_plain_background_adds_nothing() -> None:
    f = synthetic_frame(0)
    lifted = segment(StereoPair(f.left, f.right, f.mask_left, f.mask_right))
    x, y = far_spot(f.mask_left, 5, margin=40)
    fixed = apply_corrections(
        lifted, (Correction("add", "left", ((x, y),)),), images=(f.left, f.right)
    )
    assert fixed.changed_px == (0,)


def test_brushes_erase_and_paint_a_stroke_of_their_radius() -> None:
    f = synthetic_frame(0)
    lifted = segment(StereoPair(f.left, f.right, f.mask_left, f.mask_right))
    x, y = far_spot(f.mask_left, 40, margin=25)
    painted = apply_corrections(lifted, (Correction("paint", "left", ((x, y), (x + 40, y)), 3),))
    new = painted.P_L & ~f.mask_left
    assert new[y - 3 : y + 4, x : x + 41].all() and new.sum() <= 7 * 48
    erased = apply_corrections(painted, (Correction("erase", "left", ((x + 20, y),), 5),))
    assert not erased.P_L[y - 3 : y + 4, x + 17 : x + 24].any()
    assert erased.P_L[y, x] and erased.P_L[y, x + 40]
    # corrections accumulate: the erased pair remembers both, and its base is the segmenter's
    assert [c.op for c in erased.corrections] == ["paint", "erase"]
    assert np.array_equal(erased.segmented_L, f.mask_left)


def test_clear_returns_to_the_segmentation_and_later_actions_apply_on_top() -> None:
    pair, f, (x, y) = _distracted_case()
    lifted = segment(pair)
    ops = (
        Correction("remove", "left", ((x, y),)),
        Correction("clear", "left"),
    )
    cleared = apply_corrections(lifted, ops)
    assert np.array_equal(cleared.P_L, lifted.P_L)
    again = apply_corrections(lifted, (*ops, Correction("remove", "left", ((x, y),))))
    assert np.array_equal(again.P_L, f.mask_left)
    both = apply_corrections(
        again, (Correction("erase", "right", ((x, y),), 30), Correction("clear", "both"))
    )
    assert np.array_equal(both.P_L, lifted.P_L) and np.array_equal(both.P_R, lifted.P_R)
    assert both.changed_px[-1] > 0


def test_corrections_that_empty_a_view_are_refused_with_advice() -> None:
    f = synthetic_frame(0)
    lifted = segment(StereoPair(f.left, f.right, f.mask_left, f.mask_right))
    h, w = f.mask_left.shape
    wipe = Correction(
        "erase",
        "right",
        tuple((x, y) for y in range(0, h, 100) for x in range(0, w, 100)),
        MAX_RADIUS_PX,
    )
    with pytest.raises(ValueError, match="no thread pixel in the right view.*undo"):
        apply_corrections(lifted, (wipe,))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"op": "grow", "view": "left", "points": ((1, 1),)}, "unknown correction"),
        ({"op": "add", "view": "middle", "points": ((1, 1),)}, "left or right"),
        ({"op": "erase", "view": "both", "points": ((1, 1),)}, "left or right"),
        ({"op": "erase", "view": "left", "points": ((1, 1),), "radius": 1e9}, "radius"),
        ({"op": "erase", "view": "left", "points": ((1, 1),), "radius": float("nan")}, "finite"),
        ({"op": "erase", "view": "left", "points": ()}, "1 to"),
        ({"op": "remove", "view": "left", "points": ((1, 1), (2, 2))}, "one click"),
        ({"op": "add", "view": "left", "points": ((1.5, 1),)}, "integer"),
        ({"op": "clear", "view": "left", "points": ((1, 1),)}, "no points"),
        ({"op": "add", "view": "left", "points": ((1, 1),), "stereo": True}, "remove only"),
    ],
)
def test_bad_corrections_are_refused_by_name(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Correction(**kwargs)


def test_a_point_outside_the_image_is_refused() -> None:
    f = synthetic_frame(0)
    lifted = segment(StereoPair(f.left, f.right, f.mask_left, f.mask_right))
    h, w = f.mask_left.shape
    with pytest.raises(ValueError, match=rf"\({w}, 3\) is outside the {w}x{h} left image"):
        apply_corrections(lifted, (Correction("remove", "left", ((w, 3),)),))


def test_pipeline_reuses_the_segmentation_and_reruns_from_segment_on_a_new_correction() -> None:
    pair, f, (x, y) = _distracted_case()
    calib = calibration_for(f.camera)
    pipe = Pipeline(pair, calib)
    params = ReconParams()
    plain = pipe.run(params, until="stereo")
    assert not isinstance(plain["segment"], CorrectedPair)  # no correction: the stage as is
    ops = (Correction("remove", "left", ((x, y),)), Correction("remove", "right", ((x - 20, y),)))
    fixed = pipe.run(params, until="stereo", corrections=ops)
    assert not fixed.runs["segment"].cached and not fixed.runs["stereo"].cached
    assert np.array_equal(fixed["segment"].P_L, f.mask_left)
    base = pipe._segmented[1]
    more = pipe.run(params, until="stereo", corrections=(*ops, Correction("clear", "right")))
    assert pipe._segmented[1] is base  # a new correction does not segment again
    assert np.array_equal(more["segment"].P_R, pair.mask_right)
    same = pipe.run(params, until="stereo", corrections=ops)
    assert all(r.cached is False for r in same.runs.values())  # the key follows the list
    assert all(pipe.run(params, until="stereo", corrections=ops).runs[s].cached for s in STAGES[:2])


def test_a_frame_without_thread_can_be_painted_by_hand() -> None:
    f = synthetic_frame(0)
    blank_L = np.full_like(f.left, 200)
    blank_R = np.full_like(f.right, 200)
    pair = StereoPair(blank_L, blank_R)
    calib = calibration_for(f.camera)
    params = ReconParams(segment=SegmentationParams(method="raw"))
    rec = Pipeline(pair, calib).run(params, until="segment")
    assert rec.failed_stage == "segment"
    stroke = ((100, 200), (300, 220))
    rec = Pipeline(pair, calib).run(
        params, until="segment",
        corrections=(Correction("paint", "left", stroke, 2), Correction("paint", "right", stroke, 2)),
    )  # fmt: skip
    assert rec.failed_stage is None, rec.error
    assert rec["segment"].P_L[210, 200] and rec["segment"].segment_error.startswith("no thread")
    only_left = Pipeline(pair, calib).run(
        params, until="segment", corrections=(Correction("paint", "left", stroke, 2),)
    )
    assert only_left.failed_stage == "segment"
    assert "no thread found" in only_left.error and "right view" in only_left.error
