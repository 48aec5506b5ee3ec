"""Tests of the load step's resampling (core/rectify.py, core/remap_kernel.py): images at the
maps' exact positions, masks that keep the thread's half-coverage edge."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from support import assert_close

from threadrecon.core.rectify import rectify_mask
from threadrecon.core.remap_kernel import lanczos4_remap

H, W = 80, 120
ANGLE = np.deg2rad(1.5)  # the map's rotation: a raw rig's few degrees
SHIFT = (0.37, -0.21)  # px: the map's sub-pixel offset (x, y)
BAR_PX = 4.0  # the bar's width, px (a thread at working depth: 3-6 px)
SUPER = 8  # sub-samples per pixel and axis of the exact area coverage


def _affine_map() -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 maps of a rotation by ANGLE about the centre plus SHIFT."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    cx, cy = (W - 1) / 2, (H - 1) / 2
    c, s = np.cos(ANGLE), np.sin(ANGLE)
    mx = c * (u - cx) - s * (v - cy) + cx + SHIFT[0]
    my = s * (u - cx) + c * (v - cy) + cy + SHIFT[1]
    return mx.astype(np.float32), my.astype(np.float32)


def _bar_coverage(to_raw: bool) -> np.ndarray:
    """(H, W) exact area coverage of a straight bar (BAR_PX wide, 20 deg to the rows) in the
    raw grid, or in the rectified grid whose pixels the affine map sends into the raw one."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    off = (np.arange(SUPER) + 0.5) / SUPER - 0.5
    cover = np.zeros((H, W))
    theta = np.deg2rad(20.0)
    normal = np.array([-np.sin(theta), np.cos(theta)])
    cx, cy = (W - 1) / 2, (H - 1) / 2
    c, s = np.cos(ANGLE), np.sin(ANGLE)
    for dy in off:
        for dx in off:
            x, y = u + dx, v + dy
            if to_raw:  # the rectified sub-sample's raw position: the same affine map
                x, y = (
                    c * (x - cx) - s * (y - cy) + cx + SHIFT[0],
                    s * (x - cx) + c * (y - cy) + cy + SHIFT[1],
                )
            dist = (x - cx) * normal[0] + (y - cy - 3.3) * normal[1]
            cover += np.abs(dist) <= BAR_PX / 2
    return cover / SUPER**2


def _image(cover: np.ndarray, thread: float = 80.0, background: float = 200.0) -> np.ndarray:
    g = background + (thread - background) * cover
    return np.repeat(np.rint(g)[..., None], 3, axis=2).astype(np.uint8)


def _plain(mask: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    return cv2.remap(mask.astype(np.float32), mx, my, cv2.INTER_LINEAR) >= 0.5


def _rectified(raw_img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    out = lanczos4_remap(np.ascontiguousarray(raw_img), mx, my)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def test_rectified_mask_keeps_the_half_coverage_edge_that_bilinear_misses() -> None:
    """A thread mask (the pixels the thread covers at least half) resampled into a rotated,
    sub-pixel shifted grid: bilinear + 0.5 puts edge pixels on the wrong side; deciding the
    band by the resampled grey recovers the half-coverage mask of the new grid."""
    mx, my = _affine_map()
    raw_cover, ideal_cover = _bar_coverage(False), _bar_coverage(True)
    raw_mask, ideal = raw_cover >= 0.5, ideal_cover >= 0.5
    img = _image(raw_cover)
    got = rectify_mask(raw_mask, img, _rectified(img, mx, my), mx, my)
    inner = np.zeros((H, W), bool)
    inner[8:-8, 8:-8] = True  # away from the bar's ends at the image border
    # pixels whose coverage is within 0.05 of one half are a coin toss for any rule
    clear = inner & (np.abs(ideal_cover - 0.5) > 0.05)
    wrong_plain = (_plain(raw_mask, mx, my) != ideal)[clear].sum()
    wrong = (got != ideal)[clear].sum()
    assert wrong_plain > 20, wrong_plain  # the staircase of a staircase
    assert wrong <= 0.2 * wrong_plain, (wrong, wrong_plain)  # 2 against 31 when written


def test_lighter_thread_gives_the_same_mask() -> None:
    """The rule compares levels, not a sign: a thread lighter than its background too."""
    mx, my = _affine_map()
    cover = _bar_coverage(False)
    dark, light = _image(cover, 80.0, 200.0), _image(cover, 200.0, 80.0)
    a = rectify_mask(cover >= 0.5, dark, _rectified(dark, mx, my), mx, my)
    b = rectify_mask(cover >= 0.5, light, _rectified(light, mx, my), mx, my)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, _plain(cover >= 0.5, mx, my))  # the rule was used


@pytest.mark.parametrize("mask_kind", ["dilated", "eroded", "flat image"])
def test_mask_that_does_not_follow_the_thread_is_resampled_as_it_is(mask_kind: str) -> None:
    """A mask drawn a pixel wider or narrower than the thread (or over an image without
    contrast) does not follow the half-coverage rule: bilinear + 0.5, unchanged."""
    mx, my = _affine_map()
    cover = _bar_coverage(False)
    mask = cover >= 0.5
    img = _image(cover)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    if mask_kind == "dilated":
        mask = cv2.dilate(mask.astype(np.uint8), cross) > 0
    elif mask_kind == "eroded":
        mask = cv2.erode(mask.astype(np.uint8), cross) > 0
    else:
        img = np.full_like(img, 128)
    got = rectify_mask(mask, img, _rectified(img, mx, my), mx, my)
    assert np.array_equal(got, _plain(mask, mx, my))


def _lanczos_reference(src: np.ndarray, x: float, y: float) -> np.ndarray:
    """Lanczos-4 at one position with np.sinc weights, float64 (an independent form)."""
    ix, iy = int(np.floor(x)), int(np.floor(y))
    k = np.arange(-3, 5)
    wx = np.sinc(x - ix - k) * np.sinc((x - ix - k) / 4)
    wy = np.sinc(y - iy - k) * np.sinc((y - iy - k) / 4)
    wx, wy = wx / wx.sum(), wy / wy.sum()
    rows = np.clip(iy + k, 0, src.shape[0] - 1)
    cols = np.clip(ix + k, 0, src.shape[1] - 1)
    patch = src[np.ix_(rows, cols)].astype(np.float64)
    return np.einsum("j,i,jic->c", wy, wx, patch)


def test_lanczos_kernel_is_lanczos4_at_the_exact_position() -> None:
    """The kernel's weights (angle-difference form) are Lanczos-4's; integer positions copy
    the image; the border repeats the edge pixel."""
    rng = np.random.default_rng(0)
    src = rng.integers(0, 256, size=(20, 30, 3), dtype=np.uint8)
    mx = rng.uniform(-4, 33, size=(6, 7)).astype(np.float32)
    my = rng.uniform(-4, 23, size=(6, 7)).astype(np.float32)
    mx[0, :3] = [0.0, 5.0, 12.0]  # integer positions among them
    my[0, :3] = [0.0, 7.0, 19.0]
    out = lanczos4_remap(src, mx, my)
    ref = np.array(
        [[_lanczos_reference(src, mx[r, c], my[r, c]) for c in range(7)] for r in range(6)]
    )
    assert_close(out.astype(np.float64), ref, atol=1e-3, rtol=0)
    assert_close(out[0, :3].astype(np.float64), src[[0, 7, 19], [0, 5, 12]].astype(np.float64))


def test_lanczos_kernel_moves_with_a_hundredth_of_a_pixel_where_cv2_does_not() -> None:
    """cv2.remap rounds positions to 1/32 px; the kernel follows a 0.01 px step of the map on a
    smooth image (the derivative times the step), which a disparity of a near-epipolar run
    needs."""
    x = np.arange(64, dtype=np.float64)
    row = 128 + 60 * np.sin(2 * np.pi * x / 16)
    src = np.ascontiguousarray(np.repeat(np.tile(row, (16, 1))[..., None], 1, axis=2))
    src = np.rint(src).astype(np.uint8)
    v, u = np.mgrid[4:12, 20:40].astype(np.float32)
    base = u + np.float32(0.25)
    a = lanczos4_remap(src, base, v)[..., 0].astype(np.float64)
    b = lanczos4_remap(src, base + np.float32(0.01), v)[..., 0].astype(np.float64)
    slope = (
        lanczos4_remap(src, base + np.float32(0.05), v)[..., 0].astype(np.float64)
        - lanczos4_remap(src, base - np.float32(0.05), v)[..., 0].astype(np.float64)
    ) / 0.1
    moved = np.abs(slope) > 10  # grey levels / px
    assert moved.sum() > 50
    assert_close((b - a)[moved], 0.01 * slope[moved], atol=0.02, rtol=0.05)
    # cv2 on float images: the same positions, rounded to 1/32 px: no change at all
    f = src[..., 0].astype(np.float32)
    c_a = cv2.remap(f, base, v, cv2.INTER_LANCZOS4)
    c_b = cv2.remap(f, base + np.float32(0.01), v, cv2.INTER_LANCZOS4)
    assert np.array_equal(c_a, c_b)
