"""Tests of core/segment_surface.py: a mark on the tissue moves with the texture beside it."""

import cv2
import numpy as np
import pytest

from threadrecon.core.segment_surface import SurfaceTest

H, W, D_BG, D_MAX = 120, 200, 12, 40


def _texture(rng: np.random.Generator) -> np.ndarray:
    noise = rng.normal(0.0, 1.0, (H, W + D_BG)).astype(np.float32)
    return 120.0 + 40.0 * cv2.GaussianBlur(noise, (0, 0), 1.5)


def _line(img: np.ndarray, col: int) -> None:
    img[20:100, col : col + 3] = 40.0  # a dark vertical line 3 px wide


def _piece(col: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rows, cols = np.mgrid[20:100, col : col + 3]
    free = np.ones((H, W), bool)
    free[14:106, col - 6 : col + 9] = False  # the line and its rim are no background
    return rows.ravel(), cols.ravel(), free


@pytest.mark.parametrize("seed", range(5))
def test_a_line_drawn_on_the_texture_moves_with_it(seed: int) -> None:
    tex = _texture(np.random.default_rng(seed))
    _line(tex, 90 + D_BG)  # on the surface: in both views at the texture's disparity
    left, right = tex[:, :W], np.ascontiguousarray(tex[:, D_BG : D_BG + W])
    left = np.ascontiguousarray(left)
    rows, cols, free = _piece(90 + D_BG)
    assert SurfaceTest(left, right, free, D_MAX, look_left=True).on_surface(rows, cols)
    # the right view's piece: partner to the right
    rows_r, cols_r, free_r = _piece(90)
    assert SurfaceTest(right, left, free_r, D_MAX, look_left=False).on_surface(rows_r, cols_r)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("extra", [4, 10])
def test_a_line_in_front_of_the_texture_does_not_move_with_it(seed: int, extra: int) -> None:
    tex = _texture(np.random.default_rng(seed))
    left = np.ascontiguousarray(tex[:, :W])
    right = np.ascontiguousarray(tex[:, D_BG : D_BG + W])
    _line(left, 100)
    _line(right, 100 - D_BG - extra)  # nearer the cameras: a larger disparity
    rows, cols, free = _piece(100)
    assert not SurfaceTest(left, right, free, D_MAX, look_left=True).on_surface(rows, cols)


def test_an_untextured_background_tells_nothing() -> None:
    rng = np.random.default_rng(7)
    left = 128.0 + rng.normal(0.0, 2.0, (H, W)).astype(np.float32)  # camera noise only
    right = 128.0 + rng.normal(0.0, 2.0, (H, W)).astype(np.float32)
    _line(left, 100)
    _line(right, 100 - D_BG)
    rows, cols, free = _piece(100)
    assert not SurfaceTest(left, right, free, D_MAX, look_left=True).on_surface(rows, cols)


def test_shapes_are_checked() -> None:
    a = np.zeros((H, W), np.float32)
    with pytest.raises(ValueError, match=r"\(120, 199\)"):
        SurfaceTest(a, a[:, 1:], a > 0, D_MAX, True)
