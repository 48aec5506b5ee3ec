"""Display geometry (app.display): thinned copies of the 3D layers' polylines that stay within
a tolerance of the originals."""

from __future__ import annotations

import numpy as np
import pytest

from threadrecon.app.display import COLOR_STEP, MIN_CHAIN, simplify_polyline, simplify_segments


def _chord_distances(pts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Distance of every vertex to the chord between the kept vertices around it."""
    out = np.zeros(len(pts))
    for i, j in zip(idx[:-1], idx[1:], strict=True):
        a, b = pts[i], pts[j]
        ab = b - a
        for k in range(i + 1, j):
            t = np.clip((pts[k] - a) @ ab / max(ab @ ab, 1e-300), 0.0, 1.0)
            out[k] = np.linalg.norm(pts[k] - a - t * ab)
    return out


def _reference(pts: np.ndarray, tol: float) -> list[int]:
    """Textbook recursive Douglas-Peucker (first farthest vertex splits)."""

    def rec(i: int, j: int) -> list[int]:
        if j - i < 2:
            return [i]
        d = _chord_distances(pts[i : j + 1], np.array([0, j - i]))[1:-1]
        k = int(np.argmax(d))
        if d[k] <= tol:
            return [i]
        m = i + 1 + k
        return rec(i, m) + rec(m, j)

    return [*rec(0, len(pts) - 1), len(pts) - 1]


def _random_curve(rng: np.random.Generator, n: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)
    freq = rng.uniform(1.0, 4.0, size=3)
    phase = rng.uniform(0.0, 6.0, size=3)
    curve = np.sin(2 * np.pi * freq[None, :] * t[:, None] + phase[None, :]) * [10.0, 8.0, 5.0]
    return curve + [0.0, 0.0, 100.0] + rng.normal(0.0, 0.01, size=(n, 3))


def test_simplified_polyline_stays_within_tolerance_and_matches_the_textbook_algorithm():
    rng = np.random.default_rng(1301)
    for _ in range(20):
        pts = _random_curve(rng, int(rng.integers(3, 400)))
        tol = float(rng.uniform(0.005, 0.5))
        idx = simplify_polyline(pts, tol)
        assert idx[0] == 0 and idx[-1] == len(pts) - 1
        assert np.all(np.diff(idx) > 0)
        assert _chord_distances(pts, idx).max() <= tol + 1e-9
        assert idx.tolist() == _reference(pts, tol)


def test_a_straight_line_keeps_its_ends_and_zero_tolerance_keeps_every_bend():
    line = np.linspace([0.0, 0.0, 50.0], [10.0, 5.0, 60.0], 500)
    assert simplify_polyline(line, 1e-6).tolist() == [0, 499]
    zigzag = np.array([[0, 0, 0], [1, 1, 0], [2, 0, 0], [3, 1, 0]], float)
    assert simplify_polyline(zigzag, 0.0).tolist() == [0, 1, 2, 3]
    assert simplify_polyline(zigzag[:2], 5.0).tolist() == [0, 1]


def test_forced_and_non_finite_vertices_are_kept():
    line = np.linspace([0.0, 0.0, 50.0], [10.0, 0.0, 50.0], 11)
    keep = np.zeros(11, bool)
    keep[4] = True
    assert simplify_polyline(line, 1.0, keep).tolist() == [0, 4, 10]
    line[7] = np.nan
    assert simplify_polyline(line, 1.0).tolist() == [0, 7, 10]


@pytest.mark.parametrize(
    ("pts", "tol", "keep"),
    [
        (np.zeros((5, 2)), 0.1, None),
        (np.zeros((5, 3)), -1.0, None),
        (np.zeros((5, 3)), float("nan"), None),
        (np.zeros((5, 3)), 0.1, np.zeros(4, bool)),
    ],
)
def test_simplify_polyline_refuses_bad_input_by_name(pts, tol, keep):
    with pytest.raises(ValueError, match="points|tol|keep"):
        simplify_polyline(pts, tol, keep)


def test_simplified_segments_thin_chains_and_leave_loose_segments_alone():
    rng = np.random.default_rng(7)
    curve = _random_curve(rng, 300).astype(np.float32)
    chain = np.stack([curve[:-1], curve[1:]], axis=1)
    loose = rng.normal(size=(5, 2, 3)).astype(np.float32) + 500.0  # joins nothing
    segs = np.concatenate([chain, loose])
    thin, colors = simplify_segments(segs, None, 0.2)
    assert colors is None and thin.dtype == np.float32
    assert len(thin) - 5 < len(chain) // 2
    assert np.array_equal(thin[-5:], loose)
    kept = np.concatenate([thin[:-5, 0], thin[-6:-5, 1]])  # the chain's kept vertices
    idx = [int(np.flatnonzero((curve == v).all(axis=1))[0]) for v in kept]
    assert _chord_distances(curve.astype(np.float64), np.array(idx)).max() <= 0.2 + 1e-6
    assert np.array_equal(simplify_segments(loose, None, 1e3, min_chain=1)[0], loose)
    short = chain[: MIN_CHAIN - 1]
    mixed = simplify_segments(np.concatenate([short, loose, chain]), None, 0.2)[0]
    assert np.array_equal(mixed[: len(short) + 5], np.concatenate([short, loose]))
    assert np.array_equal(mixed[len(short) + 5 :], thin[:-5])


def test_per_segment_colours_break_the_simplification_where_they_change():
    line = np.linspace([0.0, 0.0, 50.0], [10.0, 0.0, 50.0], 21).astype(np.float32)
    segs = np.stack([line[:-1], line[1:]], axis=1)
    colors = np.zeros((20, 3), np.uint8)
    colors[:, 1] = 200
    colors[12:, 0] = 250  # a change at vertex 12
    colors[5:, 2] = COLOR_STEP // 4  # below a colour step: no break
    assert simplify_segments(segs, colors, 1.0)[0] is segs  # shorter than MIN_CHAIN: as it is
    thin, thin_colors = simplify_segments(segs, colors, 1.0, min_chain=2)
    assert len(thin) == 2
    assert np.array_equal(thin[0], [line[0], line[12]])
    assert np.array_equal(thin[1], [line[12], line[20]])
    assert np.array_equal(thin_colors, colors[[0, 12]])


def test_simplify_segments_refuses_bad_shapes():
    with pytest.raises(ValueError, match="segments"):
        simplify_segments(np.zeros((4, 3)), None, 0.1)
    with pytest.raises(ValueError, match="colors"):
        simplify_segments(np.zeros((4, 2, 3)), np.zeros((3, 3), np.uint8), 0.1)


def test_a_noisy_path_costs_at_most_max_passes_and_stays_within_tolerance():
    from threadrecon.app import display

    rng = np.random.default_rng(11)
    t = np.linspace(0.0, 1.0, 3000)
    pts = np.c_[100 * t, np.zeros_like(t), 50 + np.zeros_like(t)] + rng.normal(0, 0.5, (3000, 3))
    calls = []
    real = display.np.searchsorted  # one call per pass
    display.np.searchsorted = lambda *a, **k: calls.append(1) or real(*a, **k)
    try:
        idx = simplify_polyline(pts, 0.3)
    finally:
        display.np.searchsorted = real
    assert len(calls) <= display.MAX_PASSES
    assert _chord_distances(pts, idx).max() <= 0.3 + 1e-9
    assert set(_reference(pts, 0.3)) <= set(idx.tolist())  # never thinner than the textbook
