"""Tests of core/check_fold.py: a curve that runs twice over one strand is a fold; two strands,
a crossing and a hairpin are not."""

from __future__ import annotations

import numpy as np
import pytest

from threadrecon.core.check_fold import fold_length


def _steps(uv: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(uv, axis=0), axis=1)


def _polyline(*corners: tuple[float, float], spacing: float = 0.5) -> np.ndarray:
    out = []
    for a, b in zip(corners[:-1], corners[1:], strict=True):
        a, b = np.asarray(a, float), np.asarray(b, float)
        k = max(int(np.ceil(np.linalg.norm(b - a) / spacing)), 1)
        out.append(a + np.linspace(0.0, 1.0, k, endpoint=False)[:, None] * (b - a))
    out.append(np.asarray(corners[-1], float)[None])
    return np.concatenate(out)


def _fold(uv: np.ndarray, disp: np.ndarray | None = None, radius: float = 3.0) -> float:
    n = len(uv)
    d = np.full(n, 40.0) if disp is None else disp
    return fold_length(uv, _steps(uv), np.ones(n, dtype=bool), d, radius, 1.0)


def test_a_z_fold_over_one_strand_is_measured() -> None:
    # down 60 px, back up 40 px one px to the side, down again 100 px two px to the side
    uv = _polyline((100, 0), (100, 60), (101, 20), (102, 120))
    got = _fold(uv)
    assert 60.0 <= got <= 110.0  # about the 40 px walked back, counted on both passes


def test_two_strands_a_width_apart_a_crossing_and_a_straight_thread_are_no_fold() -> None:
    straight = _polyline((0, 0), (300, 0))
    assert _fold(straight) == 0.0
    a = np.linspace(-np.pi / 2, np.pi / 2, 40)
    bend = np.column_stack([200 + 4 * np.cos(a), 4 + 4 * np.sin(a)])  # legs 8 px apart
    hairpin = np.concatenate(
        [_polyline((0, 0), (200, 0))[:-1], bend, _polyline((200, 8), (0, 8))[1:]]
    )
    assert _fold(hairpin) == 0.0
    crossing = _polyline((0, 0), (200, 200), (200, 120), (0, 120), (80, 0))  # crosses at 90 deg
    assert _fold(crossing) == 0.0


def test_passes_at_different_depths_are_strands_over_each_other() -> None:
    uv = _polyline((100, 0), (100, 60), (101, 20), (102, 120))
    disp = np.where(np.arange(len(uv)) < 120, 40.0, 45.0)  # the later passes 5 px nearer
    assert _fold(uv, disp) < _fold(uv)


def test_fold_length_rejects_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match="fold_length needs"):
        fold_length(np.zeros((5, 3)), np.zeros(4), np.ones(5, bool), np.zeros(5), 3.0, 1.0)
