"""Tests of core/segment_surface.py: a mark on the tissue moves with the texture beside it."""

import cv2
import numpy as np
import pytest

from threadrecon.core import segment_surface as ss
from threadrecon.core.ridge_kernel import block_residuals, excess_stats
from threadrecon.core.segment_surface import _BLOCK_PX, SurfaceTest, _unique

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


@pytest.mark.parametrize("trial", range(30))
def test_block_residuals_equal_the_fancy_index_and_reduceat(trial: int) -> None:
    """The kernel's residuals, grouping and block means are numpy's to the last bit (the
    plain computation it replaces), with blocks of up to ~1000 pixels (pairwise sums split)."""
    rng = np.random.default_rng([41, trial])
    h, w = int(rng.integers(1, 40)), int(rng.integers(1, 60))
    this = (rng.normal(100, 30, (h, w)) * rng.choice([1e-3, 1.0, 1e3])).astype(np.float32)
    other = (rng.normal(100, 30, (h, w)) * rng.choice([1e-3, 1.0, 1e3])).astype(np.float32)
    n = int(rng.integers(1, [50, 400, 2500][trial % 3]))
    r, c = rng.integers(0, h, n), rng.integers(0, w, n)
    n_blocks = int(rng.integers(1, 6))
    block = rng.integers(0, n_blocks, n)
    d0, nd, look_left = int(rng.integers(0, 10)), int(rng.integers(1, 20)), bool(trial % 2)
    ds = np.arange(d0, d0 + nd)
    # The plain computation.
    order = np.argsort(block, kind="stable")
    r, c, blk = r[order], c[order], block[order]
    cc = c[:, None] - ds[None, :] if look_left else c[:, None] + ds[None, :]
    want_inside = (cc >= 0) & (cc < w)
    want = np.abs(this[r, c][:, None] - np.take(other, (r * w)[:, None] + np.clip(cc, 0, w - 1)))
    size = np.bincount(blk, minlength=n_blocks)
    starts = np.concatenate([[0], np.cumsum(size)[:-1]])
    total = np.zeros((n_blocks, nd), np.float32)
    count = np.zeros((n_blocks, nd), np.float32)
    seen = np.flatnonzero(size)
    total[seen] = np.add.reduceat(want * want_inside, starts[seen], axis=0)
    count[seen] = np.add.reduceat(want_inside.astype(np.float32), starts[seen], axis=0)
    valid = count >= np.maximum(0.5 * size, 1.0)[:, None]
    want_mean = np.where(valid, total / np.maximum(count, 1.0), np.inf)
    diff, inside, got_size, mean = block_residuals(
        this, other, r[np.argsort(order)], c[np.argsort(order)], block, n_blocks, d0, nd, look_left
    )
    assert np.array_equal(inside, want_inside)
    assert np.array_equal(diff, want)
    assert np.array_equal(got_size, size)
    assert np.array_equal(mean, want_mean)


def test_unique_and_the_block_grid_equal_numpys() -> None:
    rng = np.random.default_rng(42)
    for n in (1, 7, 80):
        key = rng.integers(0, n, int(rng.integers(1, 300)))
        ids, inv = _unique(key, n)
        want_ids, want_inv = np.unique(key, return_inverse=True)
        assert np.array_equal(ids, want_ids) and np.array_equal(inv, want_inv)
    # Every block of an image whose size is no multiple of the block: the grid of np.mgrid.
    h, w = 150, 200
    free = rng.random((h, w)) < 0.7
    t = SurfaceTest(np.zeros((h, w), np.float32), np.zeros((h, w), np.float32), free, 8, True)
    for key in range(t.nb * 3):
        r0, c0 = key // t.nb * _BLOCK_PX, key % t.nb * _BLOCK_PX
        rr, cc = np.mgrid[r0 + 1 : min(r0 + _BLOCK_PX, h) : 2, c0 + 1 : min(c0 + _BLOCK_PX, w) : 2]
        rr, cc = rr.ravel(), cc.ravel()
        ok = free[rr, cc] & ((rr // 2 + cc // 2) % 2 == 0)
        got = t._background(key)
        assert np.array_equal(got[0], rr[ok]) and np.array_equal(got[1], cc[ok])


@pytest.mark.parametrize("trial", range(30))
def test_excess_stats_equal_numpys_mean_and_std(trial: int) -> None:
    rng = np.random.default_rng([43, trial])
    n, nd = int(rng.integers(1, [20, 300, 1500][trial % 3])), 9
    diff = (np.abs(rng.normal(0, 1, (n, nd))) * rng.uniform(0.1, 100)).astype(np.float32)
    inside = rng.random((n, nd)) < [1.0, 0.9, 0.3][trial % 3]
    start = int(rng.integers(0, n))
    size = int(rng.integers(0, n - start + 1))
    at, own = int(rng.integers(0, nd)), int(rng.integers(0, nd))
    cap = float(rng.uniform(1, 200))
    sl = slice(start, start + size)
    x = diff[sl, at] - diff[sl, own]
    x = np.clip(x[inside[sl, at] & inside[sl, own]], -cap, cap)
    got = excess_stats(diff, inside, start, size, at, own, np.float32(cap))
    want = (len(x), float(np.mean(x)), float(np.std(x))) if len(x) else (0, 0.0, 0.0)
    assert got == want


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("extra", [0, 4, 10])
def test_a_pieces_own_disparity_and_the_backgrounds_are_found(seed: int, extra: int) -> None:
    tex = _texture(np.random.default_rng(seed))
    left = np.ascontiguousarray(tex[:, :W])
    right = np.ascontiguousarray(tex[:, D_BG : D_BG + W])
    _line(left, 100)
    _line(right, 100 - D_BG - extra)
    rows, cols, free = _piece(100)
    test = SurfaceTest(left, right, free, D_MAX, look_left=True)
    assert test.disparity(rows, cols) == D_BG + extra
    assert test.background_disparity(rows, cols) == D_BG


def test_a_line_along_the_rows_has_no_disparity_of_its_own() -> None:
    rng = np.random.default_rng(3)
    left = 128.0 + rng.normal(0.0, 1.0, (H, W)).astype(np.float32)
    right = 128.0 + rng.normal(0.0, 1.0, (H, W)).astype(np.float32)
    left[60:63, 20:180] = 40.0  # a long dark line along the rows: it matches at every shift
    right[60:63, 8:168] = 40.0
    rows, cols = (a.ravel() for a in np.mgrid[60:63, 60:140])
    test = SurfaceTest(left, right, np.ones((H, W), bool), D_MAX, look_left=True)
    assert test.disparity(rows, cols) is None
    assert test.disparity(rows[:0], cols[:0]) is None
    # camera noise only around it: the background resolves no disparity
    assert test.background_disparity(rows, cols) is None


def _plain_background_vote(t: SurfaceTest, rr: np.ndarray, cc: np.ndarray, d: int) -> int:
    """A background block's vote as the Python steps gave it before they were compiled
    (:class:`_Residuals` of the block and its ``resolves``): -1 undecided; else 1 where the
    block matches at ``d`` (within SAME_DISPARITY_PX) about as well as at its own best, its
    excess mean residual there under half of that _RESOLVE_PX away, 0 where not."""
    ds = np.arange(max(d - ss._WINDOW_PX, 0), min(d + ss._WINDOW_PX, t.dmax) + 1)
    bg = ss._Residuals(t.this, t.other, rr, cc, np.zeros(len(rr), np.intp), 1, ds, t.look_left)
    if not bg.resolves(0):
        return -1
    lo = max(int(np.ceil(d - ss.SAME_DISPARITY_PX)) - int(ds[0]), 0)
    hi = min(int(np.floor(d + ss.SAME_DISPARITY_PX)) - int(ds[0]), len(ds) - 1)
    if hi < lo:
        return 0
    m, least = bg.mean[0], float(bg.least[0])
    excess = float(np.min(m[lo : hi + 1])) - least
    ref = min(float(m[i]) for i in bg._sides(0)) - least
    return int(excess < 0.5 * ref)


@pytest.mark.parametrize("trial", range(40))
def test_background_vote_equals_the_residuals_steps(trial: int) -> None:
    """The compiled vote of a background block (SurfaceTest.votes) is the Python steps' on
    textured, shifted, flat and noisy backgrounds, at disparities near 0 and near the largest
    (a side of the optimum outside the window), with few and many samples, both views."""
    rng = np.random.default_rng([44, trial])
    tex = _texture(rng)
    shift = int(rng.integers(0, D_BG + 1))
    left = np.ascontiguousarray(tex[:, shift : shift + W])
    right = np.ascontiguousarray(tex[:, :W])
    if trial % 5 == 1:  # a flat, noisy background: it does not resolve its disparity
        left = (120 + rng.normal(0, 2, (H, W))).astype(np.float32)
    if trial % 5 == 2:  # an unrelated view: it resolves at some other disparity, or not
        right = _texture(rng)[:, :W].copy()
    look_left = trial % 2 == 0
    this, other = (left, right) if look_left else (right, left)
    dmax = int(rng.choice([3, 12, D_MAX]))
    t = SurfaceTest(this, other, np.ones((H, W), bool), dmax, look_left=look_left)
    for key in range(t.nb * 2):
        rr, cc = t._background(key)
        keep = rng.random(len(rr)) < [1.0, 0.05, 0.5][trial % 3]  # down to a few samples
        rr, cc = rr[keep], cc[keep]
        if len(rr) == 0:
            continue
        for d in {0, 1, shift, dmax - 1, dmax, int(rng.integers(0, dmax + 1))}:
            if not 0 <= d <= dmax:
                continue
            got = ss.background_vote(
                this, other, rr, cc, d, dmax, ss._WINDOW_PX, look_left, ss._RESOLVE_PX,
                ss._MIN_BLOCK_SAMPLES, ss.SAME_DISPARITY_PX, ss._TAIL, ss._T_SAME,
            )  # fmt: skip
            assert got == _plain_background_vote(t, rr, cc, d), (key, d)
