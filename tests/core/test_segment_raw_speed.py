"""Tests of the raw segmentation's speed-ups across stages (core/segment_raw.py called from
core/segmentation.py): each gives exactly what the plain computation gives."""

from dataclasses import replace

import numpy as np
import pytest

from threadrecon.core import segment_raw as sr
from threadrecon.core.lazy import Deferred
from threadrecon.core.segmentation import SegmentationParams, StereoPair, _Grey, segment
from threadrecon.core.synthetic import RenderParams, SyntheticParams, ThreadParams, generate_frame

_TISSUE = RenderParams(background="tissue", noise_sigma=2.0, blur_sigma=0.5)


def _layouts(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """uint8 images in the layouts a view comes in."""
    bgr = rng.integers(0, 256, (37, 51, 3), dtype=np.uint8)
    wide = rng.integers(0, 256, (37, 102, 3), dtype=np.uint8)
    return {
        "rgb": np.ascontiguousarray(bgr),
        "rgb view of bgr": bgr[:, :, ::-1],
        "half of a side-by-side pair": wide[:, 51:],
        "grey": bgr[:, :, 0].copy(),
        "one channel": bgr[:, :, :1].copy(),
        "rgba": rng.integers(0, 256, (37, 51, 4), dtype=np.uint8),
    }


@pytest.mark.parametrize("seed", range(3))
def test_segmentation_grey_equals_the_raw_view_grey_for_every_uint8_layout(seed: int) -> None:
    """segment() hands its grey levels to segment_raw (the surface test's images): for uint8
    views they are the ones the raw view computes itself."""
    for name, img in _layouts(np.random.default_rng(seed)).items():
        v = sr._View.__new__(sr._View)
        v.img, v._grey = img, None
        own = v.grey()
        shared = _Grey(img).f32
        assert shared.dtype == own.dtype == np.float32, name
        np.testing.assert_array_equal(shared, own, err_msg=name)


@pytest.mark.parametrize(
    ("seed", "render"),
    [
        (1, _TISSUE),
        (2, replace(_TISSUE, instrument=True)),
        (3, replace(_TISSUE, thread_colour="random", distractors=6)),
        (4, replace(_TISSUE, specular=0.4, lighting=0.6)),
    ],
)
def test_segment_gives_the_masks_and_scores_of_segment_raw_alone(
    seed: int, render: RenderParams
) -> None:
    """segment() (shared grey levels, scores computed when read) gives bit for bit the masks
    and scores that segment_raw gives alone (its own grey levels, scores at once)."""
    frame = generate_frame(
        SyntheticParams(thread=ThreadParams(), render=render), np.random.default_rng(seed)
    )
    p = SegmentationParams(method="raw")
    try:
        P_L, P_R, s_L, s_R = sr.segment_raw(frame.left, frame.right, p)
    except ValueError as exc:
        with pytest.raises(ValueError, match="no thread found"):
            segment(StereoPair(frame.left, frame.right), p)
        pytest.skip(f"no thread found in this frame: {exc}")
    lifted = segment(StereoPair(frame.left, frame.right), p)
    assert isinstance(lifted.__dict__["_lazy_score_L"], Deferred)  # not computed yet
    np.testing.assert_array_equal(lifted.P_L, P_L)
    np.testing.assert_array_equal(lifted.P_R, P_R)
    assert isinstance(s_L, np.ndarray) and s_L.dtype == np.float32
    np.testing.assert_array_equal(lifted.score_L, s_L)
    np.testing.assert_array_equal(lifted.score_R, s_R)
    assert lifted.score_L.min() >= 0.0 and lifted.score_L.max() <= 1.0


def test_deferred_score_is_the_clipped_scaled_response() -> None:
    s = np.array([[0.0, 0.5, 1.0, 3.0]], np.float32)
    np.testing.assert_array_equal(sr._score(s, 2.0), np.array([[0.0, 0.25, 0.5, 1.0]], np.float32))


def test_deferred_scores_keep_no_line_response_alive() -> None:
    """A deferred score holds the view's image (held by the pair anyway) and recomputes the
    line response when read: the (H, W) float32 response is freed with the segmentation (the
    lifted images then reuse its memory, no fresh pages), and the score read is the eager one
    (test_segment_gives_the_masks_and_scores_of_segment_raw_alone)."""
    frame = generate_frame(
        SyntheticParams(thread=ThreadParams(), render=_TISSUE), np.random.default_rng(1)
    )
    p = SegmentationParams(method="raw")
    *_, s_L, s_R = sr.segment_raw(frame.left, frame.right, p, defer_score=True)
    for d, img in ((s_L, frame.left), (s_R, frame.right)):
        assert isinstance(d, Deferred)
        assert not any(isinstance(a, np.ndarray) and a.dtype == np.float32 for a in d.args)
        assert any(a is img for a in d.args)


@pytest.mark.parametrize("seed", range(4))
def test_logs_of_whole_levels_are_looked_up_as_computed(seed: int) -> None:
    """_log_of(levels=True) (a table of every level's float32 log) gives _log_of's computed
    float32 logs bit for bit: for the block means of uint8 views (every layout) and for every
    level at every position of a vector of the computation (numpy's SIMD log and its tail)."""
    rng = np.random.default_rng(seed)
    for name, img in _layouts(rng).items():
        a = img if img.ndim == 3 else img[:, :, None]
        a_q = sr._quarter(a[:, :, :3])
        assert np.array_equal(a_q, np.round(a_q)), name  # whole levels
        assert np.array_equal(sr._log_of(a_q, levels=True), sr._log_of(a_q)), name
    for n in range(1, 40):  # every level at each of the first positions, the rest random
        levels = np.roll(np.arange(256), seed * 40 + n)[: 256 - n % 7]
        a = levels.astype(np.float32).reshape(1, -1, 1)
        assert np.array_equal(sr._log_of(a, levels=True), sr._log_of(a))


@pytest.mark.parametrize("seed", range(3))
def test_free_blocks_and_quarter_index_are_the_divisions(seed: int) -> None:
    """_qi shifts and _free_blocks writes a flat index: the values of index // _Q clipped
    and of the two-index assignment, at every row and column (the last block taking the
    rest of a side that is no multiple of 4)."""
    rng = np.random.default_rng(seed)
    h, w = 4 * 30 + seed, 4 * 41 + 2 * seed
    index = np.arange(max(h, w))
    for n in (h // 4, w // 4):
        np.testing.assert_array_equal(sr._qi(index, n), np.minimum(index // 4, n - 1))
    rows, cols = rng.integers(0, h, 900), rng.integers(0, w, 900)
    shape = (h // 4, w // 4)
    want = np.ones(shape, np.float32)
    want[np.minimum(rows // 4, shape[0] - 1), np.minimum(cols // 4, shape[1] - 1)] = 0.0
    got = sr._free_blocks(rows, cols, shape)
    assert got.shape == shape and got.dtype == np.float32
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("columns", [1, 2, 3])
def test_row_norms_are_numpy_s_row_norms_bit_for_bit(dtype: type, columns: int) -> None:
    rng = np.random.default_rng(columns)
    # contrasts of every magnitude, signed zeros, and the extremes of the dtype
    a = rng.standard_normal((5000, columns)) * 10.0 ** rng.integers(-6, 6, (5000, 1))
    a[:10] = 0.0
    a[10:20] = -0.0
    a[20, 0] = np.finfo(dtype).max
    a[21, -1] = np.finfo(dtype).tiny
    a[22, 0] = np.inf
    a = a.astype(dtype)
    for x in (a, a[:, ::-1], a[::3]):  # contiguous and strided, as _same_dye's slices
        got, want = sr._row_norms(x), np.linalg.norm(x, axis=1)
        assert got.dtype == want.dtype
        assert np.array_equal(got.view(np.uint8), want.view(np.uint8))


def test_same_dye_equals_its_plain_cosines() -> None:
    """_same_dye (row norms by :func:`_row_norms`) against the cosines written out with
    numpy's norms, for coloured and grey references, pieces' (float64) and pixels' (float32)
    contrasts."""
    rng = np.random.default_rng(7)
    for dtype in (np.float64, np.float32):
        delta = (rng.standard_normal((3000, 3)) * 20.0).astype(dtype)
        for ref in (np.array([-5.0, 3.0, -2.0]), np.array([8.0, 0.01, -0.02])):
            d, r = delta[:, 1:], ref[1:]
            same_sign = delta[:, 0] * ref[0] >= 0
            nr = float(np.linalg.norm(r))
            if nr < sr._GREY_CHROMA:
                ok = (np.linalg.norm(d, axis=1) < 2 * sr._GREY_CHROMA) & same_sign
                want = np.where(ok, 1.0, -1.0)
            else:
                cos = (d @ r) / np.maximum(np.linalg.norm(d, axis=1) * nr, 1e-9)
                whole = (delta @ ref) / np.maximum(
                    np.linalg.norm(delta, axis=1) * np.linalg.norm(ref), 1e-9
                )
                want = np.where(same_sign, cos, np.minimum(cos, whole))
            assert np.array_equal(sr._same_dye(delta, ref), want)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("columns", [1, 2, 3])
def test_mean_rows_is_numpy_s_mean_of_the_selected_rows_bit_for_bit(
    dtype: type, columns: int
) -> None:
    rng = np.random.default_rng(11)
    for size in (1, 2, 7, 8, 9, 100, 4096, 20001):  # below and above numpy's blocks of 8
        scale = 10.0 ** rng.integers(-3, 4)
        a = (rng.standard_normal((size, columns)) * scale).astype(dtype)
        where = rng.random(size) < rng.random()
        where[rng.integers(size)] = True
        got, want = sr._mean_rows(a, where), a[where].mean(axis=0)
        assert got.dtype == want.dtype
        assert np.array_equal(got.view(np.uint8), want.view(np.uint8))


def test_row_keys_are_sorted_for_pixels_in_any_order() -> None:
    rng = np.random.default_rng(5)
    rows, cols = np.divmod(np.sort(rng.choice(480 * 640, 3000, replace=False)), 640)
    for r, c in ((rows, cols), (rows[::-1], cols[::-1]), (rows[rng.permutation(3000)], cols)):
        assert np.array_equal(sr._row_keys(r, c, 640, 60), np.sort(r * (640 + 61) + c))
