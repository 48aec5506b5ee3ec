"""Tests of core/reversal.py and of the stages after the ordering: the same ordering walked
from the other end gives the same curve, traversed the other way (issue 12)."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree
from support import synthetic_case
from threadpoolctl import threadpool_limits

from threadrecon.core import ordering as ordering_module
from threadrecon.core.pipeline import STAGE_TABLE, STAGES, Pipeline
from threadrecon.core.reversal import reversed_ordering
from threadrecon.core.segmentation import StereoPair
from threadrecon.core.synthetic import SyntheticParams, ThreadParams, generate_frame

TRIALS = tuple(range(6))
AFTER = STAGE_TABLE[STAGES.index("ordering") + 1 :]


def _after_ordering(pipe: Pipeline, rec, ordering) -> dict:
    """The stages after the ordering on ``ordering`` in place of ``rec``'s."""
    out = {s: rec[s] for s in STAGES[: STAGES.index("ordering")]}
    out |= {"ordering": ordering, "pair": pipe.pair, "calib": pipe.calib}
    for st in AFTER:
        out[st.name] = st.run(*(out[i] for i in st.inputs), getattr(rec.params, st.name))
    return out


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance from a point of ``a`` (N, 3) to the polyline ``b`` resampled finely."""
    seg = np.linalg.norm(np.diff(b, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    u = np.linspace(0.0, s[-1], 200 * len(b))
    dense = np.column_stack([np.interp(u, s, b[:, j]) for j in range(3)])
    return float(cKDTree(dense).query(a)[0].max())


def test_reversed_ordering_twice_is_the_ordering() -> None:
    pair, calib, _ = synthetic_case(0)
    o = Pipeline(pair, calib).run(until="ordering")["ordering"]
    r = reversed_ordering(o)
    assert np.array_equal(r.order, o.order[::-1])
    assert np.array_equal(r.path_px, o.path_px[::-1])
    back = reversed_ordering(r)
    for name in ("order", "path_px", "pixel_link", "end_disparity"):
        assert np.array_equal(getattr(back, name), getattr(o, name)), name
    assert back.links == o.links
    np.testing.assert_allclose(back.pixel_t, o.pixel_t, atol=1e-15)
    one = dataclasses.replace(o, dead_end=(True, False))  # deviation 55's dead end: its end
    assert reversed_ordering(one).dead_end == (False, True)
    seen = dataclasses.replace(o, mono=(3, 0))  # deviation 33: 3 start points the left sees only
    assert reversed_ordering(seen).mono == (0, 3)


@pytest.mark.parametrize("seed", TRIALS)
def test_reversed_ordering_gives_the_same_curve_reversed(seed: int) -> None:
    # H, its bounds and the final curve are those of the forward walk, reversed; the check
    # says the same.
    pair, calib, _ = synthetic_case(seed)
    pipe = Pipeline(pair, calib)
    with threadpool_limits(1):
        rec = pipe.run()
        assert rec.failed_stage is None, rec.message
        back = _after_ordering(pipe, rec, reversed_ordering(rec["ordering"]))
    bf, bb = rec["bounds"], back["bounds"]
    assert np.array_equal(bf.H[::-1], bb.H)
    np.testing.assert_allclose(bf.lower[::-1], bb.lower, rtol=1e-9)
    np.testing.assert_allclose(bf.upper[::-1], bb.upper, rtol=1e-9)
    a, b = rec["camera"].points, back["camera"].points
    tol = 1e-4 * rec["camera"].length
    assert _distance(a, b) < tol and _distance(b, a) < tol
    assert np.linalg.norm(a[0] - b[-1]) < tol and np.linalg.norm(a[-1] - b[0]) < tol
    assert back["check"].status == rec.status


def test_extra_point_runs_are_the_same_from_either_end_on_a_coil() -> None:
    # Generated spiral 7352 #10: the runs of a link's gap pixels split as np.array_split
    # (longer runs first) gave e_S^max 0.35 mm one way and 3.55 mm the other.
    syn = SyntheticParams(thread=ThreadParams(spiral=True))
    fr = generate_frame(syn, np.random.default_rng([7352, 10]))
    pipe = Pipeline(
        StereoPair(fr.left, fr.right, fr.mask_left, fr.mask_right), syn.camera.calibration()
    )
    with threadpool_limits(1):
        rec = pipe.run()
        back = _after_ordering(pipe, rec, reversed_ordering(rec["ordering"]))
    assert np.array_equal(rec["bounds"].H[::-1], back["bounds"].H)
    assert _distance(rec["camera"].points, back["camera"].points) < 0.01  # mm


@pytest.mark.parametrize("seed", (1, 12))
def test_walk_reversed_inside_the_ordering_gives_the_same_links(seed: int, monkeypatch) -> None:
    # Generated crossings (seed 8130): a gap on two links went to the later one, so that
    # the walk's direction moved extra points (0.76 mm between the two curves on #1).
    syn = SyntheticParams(thread=ThreadParams(crossing=True))
    fr = generate_frame(syn, np.random.default_rng([8130, seed]))
    pair = StereoPair(fr.left, fr.right, fr.mask_left, fr.mask_right)
    calib = syn.camera.calibration()
    with threadpool_limits(1):
        rec = Pipeline(pair, calib).run(until="ordering")
        walk = ordering_module._bending_walk
        monkeypatch.setattr(ordering_module, "_bending_walk", lambda *a: walk(*a)[::-1])
        monkeypatch.setattr(ordering_module, "_explain", lambda *a, **k: ())
        other = Pipeline(pair, calib).run(until="ordering")
    o, r = rec["ordering"], reversed_ordering(other["ordering"])
    assert np.array_equal(o.order, r.order)
    assert np.array_equal(o.pixel_link, r.pixel_link)
    shared = np.flatnonzero(
        np.bincount(np.array([g for gs in o.links for g in gs], dtype=np.int64)) > 1
    )
    assert shared.size  # the frame has a gap on two links
    ok = np.isfinite(o.pixel_t)
    assert np.array_equal(ok, np.isfinite(r.pixel_t))
    np.testing.assert_allclose(o.pixel_t[ok], r.pixel_t[ok], atol=1e-12)


def test_a_border_keypoint_between_two_equally_near_safe_ones_is_the_same_both_ways() -> None:
    # Keypoint 4 (x = 3 px, a cut search: d = 0.002 px) lies two steps from safe keypoints at
    # 118 and 126 mm on either side: their mean, from either end (before: the earlier one).
    from threadrecon.core.bounds import _border_depths

    fB = 4450.0
    x = np.array([300.0, 280.0, 260.0, 4.0, 3.0, 5.0, 260.0, 280.0, 300.0])
    z = np.array([118.0] * 3 + [fB / 0.002] * 3 + [126.0] * 3)
    path = np.column_stack([x, np.full(9, 200.0), z])
    out = _border_depths(path, fB)
    back = _border_depths(path[::-1].copy(), fB)[::-1]
    assert out[4, 2] == pytest.approx(122.0)
    np.testing.assert_array_equal(out, back)
    assert out[3, 2] == 118.0 and out[5, 2] == 126.0
