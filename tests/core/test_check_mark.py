"""The check's look for a mark on the tissue (core/check_mark.py)."""

from __future__ import annotations

import numpy as np
import pytest

from threadrecon.core.check_mark import _spread, moves_with_surface


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
