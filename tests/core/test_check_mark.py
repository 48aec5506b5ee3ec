"""The check's look for a mark on the tissue (core/check_mark.py)."""

from __future__ import annotations

import numpy as np
import pytest
from support import suite_frame

from threadrecon.core import check_mark
from threadrecon.core.check_beyond import (
    AHEAD_HALF_PX,
    _match_ahead,
    _thread_and_edges,
    untold_patches,
)
from threadrecon.core.check_mark import Mark, _spread, moves_with_surface
from threadrecon.core.metrics import project
from threadrecon.core.segmentation import to_grey


def _scene(thread_disp: int, tissue_disp: int = 30) -> tuple:
    """A textured tissue at ``tissue_disp`` px of disparity and a dark vertical line (the
    curve, x = 200 in the left view) at ``thread_disp``, both views (H, W) float32 grey,
    the line's masks, and the curve's left and right projections."""
    rng = np.random.default_rng(7)
    h, w = 240, 400
    tex = rng.uniform(60.0, 200.0, (h, w + 200)).astype(np.float32)
    left = tex[:, 100 : 100 + w].copy()
    right = tex[:, 100 + tissue_disp : 100 + tissue_disp + w].copy()
    ys = np.arange(20, 220)
    mask_l = np.zeros((h, w), bool)
    mask_r = np.zeros((h, w), bool)
    mask_l[20:220, 199:202] = True
    mask_r[20:220, 199 - thread_disp : 202 - thread_disp] = True
    left[mask_l], right[mask_r] = 20.0, 20.0
    uv_l = np.column_stack([np.full(len(ys), 200.0), ys.astype(float)])
    uv_r = uv_l - [thread_disp, 0.0]
    return (uv_l, uv_r), (left, right), (mask_l, mask_r), np.full(len(ys), float(thread_disp))


def test_a_line_at_the_tissue_disparity_moves_with_it() -> None:
    uvs, greys, masks, disp = _scene(thread_disp=30)
    m = moves_with_surface(uvs, greys, masks, disp, 1.5, 8, 0.75)
    assert m.measured == 8 and m.along == 8


@pytest.mark.parametrize("thread_disp", [34, 40])
def test_a_line_in_front_of_the_tissue_does_not(thread_disp: int) -> None:
    """A line 4 or 10 px of disparity in front of the tissue: the surface beside it lies
    behind it; the test stops once the share can no longer be reached (3 of 8 disagree)."""
    uvs, greys, masks, disp = _scene(thread_disp)
    m = moves_with_surface(uvs, greys, masks, disp, 1.5, 8, 0.75)
    assert m.along == 0 and m.measured == 3


def test_a_plain_background_measures_nothing() -> None:
    uvs, greys, masks, disp = _scene(thread_disp=30)
    flat = tuple(np.where(mk, 20.0, 128.0).astype(np.float32) for mk in masks)
    m = moves_with_surface(uvs, flat, masks, disp, 1.5, 8, 0.75)
    assert m.measured == 0


def test_spread_orders_every_index_once() -> None:
    for n in (1, 2, 5, 16, 37):
        order = _spread(n)
        assert sorted(order) == list(range(n))
    assert _spread(8)[:2] == (0, 4)


def _generator_scene() -> tuple:
    """Raw colours #6 of seed 20253 (eval_suites' frame): textured tissue, a thread in front
    of it. Its grey levels, exact masks, the true curve's projections and disparity."""
    frame = suite_frame(
        [20253, 7, 6], background="tissue", noise_sigma=2.0, blur_sigma=0.5,
        thread_colour="random",
    )  # fmt: skip
    calib = frame.camera.calibration()
    pts = frame.truth.centerline
    uvs = (project(pts, calib.P1), project(pts, calib.P2))
    greys = (to_grey(frame.left), to_grey(frame.right))
    return uvs, greys, (frame.mask_left, frame.mask_right), uvs[0][:, 0] - uvs[1][:, 0]


def test_patches_skipped_unmatched_would_measure_nothing() -> None:
    """``untold_patches`` (the cheap tests of many patches at once) flags a patch only where
    the patch's own match (``_match_ahead``) measures nothing, and flags every patch that is
    untextured well under the limit: the skip changes no measure."""
    _, greys, masks, _ = _generator_scene()
    rng = np.random.default_rng(3)
    h, w = greys[0].shape
    for side in (0, 1):
        ys, xs = np.nonzero(masks[side])
        pick = rng.integers(0, len(xs), 300)
        cx = np.clip(xs[pick] + rng.integers(-12, 13, 300), 6, w - 7)
        cy = np.clip(ys[pick] + rng.integers(-12, 13, 300), 6, h - 7)
        flags = untold_patches(greys, masks, np.full(300, side), cx, cy)
        for x, y, flag in zip(cx.tolist(), cy.tolist(), flags.tolist(), strict=True):
            d, grey = _match_ahead(greys, masks, side, x, y, 60)
            if flag:
                assert d is None, (side, x, y)
            elif grey is not None and min(x, y) >= 8 and x < w - 8 and y < h - 8:
                r = AHEAD_HALF_PX
                seen = ~_thread_and_edges(masks[side], y, x, r)
                sd = float(np.std(greys[side][y - r : y + r + 1, x - r : x + r + 1][seen]))
                assert sd > 3.9, (side, x, y, sd)  # left to the match: near the limit only
        assert flags.any() and not flags.all()


def test_skipping_untold_patches_changes_no_mark(monkeypatch: pytest.MonkeyPatch) -> None:
    """The mark's measures on the generator frame, the thread's true curve and a line at the
    tissue's disparity, with and without the skip of untold patches."""
    cases = [_generator_scene(), _scene(thread_disp=30), _scene(thread_disp=34)]
    fast = [moves_with_surface(*c, 1.5, 8, 0.75) for c in cases]
    monkeypatch.setattr(check_mark, "untold_patches", lambda g, m, s, x, y: np.zeros(len(x), bool))
    slow = [moves_with_surface(*c, 1.5, 8, 0.75) for c in cases]
    assert fast == slow
    assert fast[0].measured > 0 and fast[1] == Mark(8, 8)
