"""Tests of core/check_fold.py: a curve that runs twice over one strand is a fold; two strands,
a crossing and a hairpin are not. A curve joined at a point from two lines turns back there,
sharper than a thread bends; a hairpin, a hook out and back and a zig-zag do not head back."""

from __future__ import annotations

import numpy as np
import pytest

from threadrecon.core.check_fold import (
    REVERSAL_ARM_PX,
    REVERSAL_COS,
    end_reversal,
    fold_length,
    self_contact,
)
from threadrecon.core.numeric import arc_px


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


def test_fold_length_reads_the_arc_length_given_as_it_computes_it() -> None:
    # the check passes the left projection's arc length it already has (numeric.arc_px)
    uv = _polyline((100, 0), (100, 60), (101, 20), (102, 120))
    step = _steps(uv)
    step[7] = np.nan  # a non-finite step counts as 0 either way
    n = len(uv)
    args = (uv, step, np.ones(n, dtype=bool), np.full(n, 40.0), 3.0, 1.0)
    got = fold_length(*args)
    assert got > 0.0 and fold_length(*args, arc_px(step)) == got


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


def _s3(uv: np.ndarray, mm_per_px: float = 0.2) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(_steps(uv))]) * mm_per_px


def test_a_branch_joined_where_the_curve_turns_back_at_a_point_is_measured() -> None:
    # 16153 all #7's shape: the thread comes in from the right (heading left, a little down),
    # and the curve turns back at a point, up and to the right along a fibre for 150 px
    uv = _polyline((400, 200), (165, 247), (269, 141))
    rev = end_reversal(uv, _s3(uv))
    assert rev is not None and rev.end == "end"
    assert rev.turn_deg > 130.0
    assert rev.length == pytest.approx(0.2 * np.hypot(104, 106), rel=0.02)
    assert np.hypot(rev.at[0] - 165, rev.at[1] - 247) < 2.0
    back = end_reversal(uv[::-1], _s3(uv[::-1]))  # the same curve from the other end
    assert back is not None and back.end == "start"
    assert back.length == pytest.approx(rev.length, rel=0.02)


def test_a_hairpin_a_hook_and_a_zig_zag_are_no_branch_turning_back() -> None:
    a = np.linspace(-np.pi / 2, np.pi / 2, 60)
    bend = np.column_stack([200 + 8 * np.cos(a), 8 + 8 * np.sin(a)])  # a U of radius 8 px
    hairpin = np.concatenate(
        [_polyline((0, 0), (200, 0))[:-1], bend, _polyline((200, 16), (0, 16))[1:]]
    )
    assert end_reversal(hairpin, _s3(hairpin)) is None
    assert end_reversal(_polyline((0, 0), (300, 0)), _s3(_polyline((0, 0), (300, 0)))) is None
    # a hook: down the thread, 30 px out into a fibre, back, and on down the thread
    hook = _polyline((440, 0), (446, 160), (423, 190), (441, 176), (440, 400))
    assert end_reversal(hook, _s3(hook)) is None
    # a zig-zag of 20 px on the way down: the curve goes on the way it came
    zig = _polyline((290, 200), (286, 400), (284, 380), (274, 500))
    assert end_reversal(zig, _s3(zig)) is None


def test_a_turn_back_counts_the_branch_only_not_the_rest_of_the_curve() -> None:
    # a short branch of 30 px after the turn: its 3D length, not the 400 px before it
    uv = _polyline((400, 0), (0, 0), (30, 5))
    rev = end_reversal(uv, _s3(uv, 1.0))
    assert rev is not None and rev.end == "end" and rev.length == pytest.approx(30.4, abs=1.0)


def _turn_three_reads(uv: np.ndarray) -> np.ndarray:
    """end_reversal's turn at every 1 px sample as it first read the curve: three reads of
    it (at s - arm, s, s + arm) and np.linalg.norm."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
    arm = REVERSAL_ARM_PX

    def at(v: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(v, s, uv[:, 0]), np.interp(v, s, uv[:, 1])])

    ss = np.arange(arm, s[-1] - arm, 1.0)
    here = at(ss)
    a, b = here - at(ss - arm), at(ss + arm) - here
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    return np.sum(a * b, axis=-1) / np.maximum(na * nb, 1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_end_reversal_reads_the_turns_of_three_reads_bit_for_bit(seed: int) -> None:
    # one read of the curve on the whole-px grid, the turn written per coordinate: the same
    # turns to the bit (random walks, spirals, hairpins, out and back), so the same reversals
    rng = np.random.default_rng(seed)
    for t in range(60):
        n = int(rng.integers(4, 300))
        if t % 3 == 0:
            uv = 300 + np.cumsum(rng.normal(0.0, rng.uniform(0.3, 6.0), (n, 2)), axis=0)
        elif t % 3 == 1:
            a = np.linspace(0.0, rng.uniform(1.0, 12.0), n)
            uv = 200 + rng.uniform(5, 80) * np.column_stack([np.cos(a), np.sin(a * 1.7)])
        else:
            half = np.linspace(0.0, 1.0, n // 2)
            uv = np.column_stack([np.linspace(0, rng.uniform(1, 60), n),
                                  np.concatenate([half, half[::-1], [0.0] * (n % 2)]) * 200])  # fmt: skip
        turn = _turn_three_reads(uv)
        s3 = np.cumsum(rng.uniform(0.01, 2.0, n))
        rev = end_reversal(uv, s3)
        if not (turn < REVERSAL_COS).any():
            assert rev is None
            continue
        if rev is not None:  # (a sharp turn with neither side heading back is none)
            c = np.flatnonzero(turn < REVERSAL_COS)
            degs = np.degrees(np.arccos(np.clip(turn[c], -1.0, 1.0)))
            assert rev.turn_deg in degs.tolist()


F_PX = 900.0  # focal length of the self-contact tests, px (a width of 6 px is 0.87 mm at 130 mm)


def _lift(uv: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A curve at depths ``z`` (mm) whose left projection is ``uv`` (px from the principal point):
    its 3D points and cumulative 3D length."""
    pts = np.column_stack([uv * z[:, None] / F_PX, z])
    s3 = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    return uv, pts, s3


def test_a_curve_coming_back_through_a_point_of_itself_passes_through_itself() -> None:
    # right 200 px, a loop up and back down across the first pass at x = 100, on at one depth
    uv = _polyline((0, 0), (200, 0), (200, -150), (100, -150), (100, 150), spacing=1.0)
    got = self_contact(*_lift(uv, np.full(len(uv), 130.0)), 3.0, F_PX, 20.0)
    assert got is not None
    assert got.distance < 0.1 and got.limit == pytest.approx(3.0 * 130.0 / F_PX)
    assert got.apart > 50.0 and abs(got.at[0] - 100.0) <= 1.5 and abs(got.at[1]) <= 1.5


def test_strands_a_width_apart_a_crossing_in_front_and_a_short_loop_do_not_touch() -> None:
    # the same crossing with the second pass 2 mm in front of the first: a thread crossing over
    uv = _polyline((0, 0), (200, 0), (200, -150), (100, -150), (100, 150), spacing=1.0)
    z = np.full(len(uv), 130.0)
    z[np.arange(len(uv)) > 400] = 128.0
    z = np.convolve(np.pad(z, 20, mode="edge"), np.ones(41) / 41, mode="valid")  # smooth step
    assert self_contact(*_lift(uv, z), 3.0, F_PX, 20.0) is None
    # a hairpin, its legs 6 px (a thread's width) apart at one depth
    pin = _polyline((0, 0), (200, 0), (200, 6), (0, 6), spacing=1.0)
    assert self_contact(*_lift(pin, np.full(len(pin), 130.0)), 3.0, F_PX, 20.0) is None
    # a loop closing on itself within the gap along the curve (a small curl, not far apart)
    curl = _polyline((0, 0), (40, 0), (40, -20), (20, -20), (20, 20), spacing=1.0)
    lifted = _lift(curl, np.full(len(curl), 130.0))
    assert lifted[2][-1] < 20.0 and self_contact(*lifted, 3.0, F_PX, 20.0) is None
    assert self_contact(*lifted, 3.0, F_PX, 5.0) is not None  # the same curl, a shorter gap
