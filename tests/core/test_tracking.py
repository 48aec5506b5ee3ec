"""Tracking across frames (core/tracking.py) and moving-thread sequences (core/sequence_synth.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from threadrecon.core.corrections import VIEWS, apply_corrections
from threadrecon.core.segmentation import LiftedPair
from threadrecon.core.sequence_synth import (
    MotionParams,
    SequenceParams,
    generate_sequence,
    thread_motion,
)
from threadrecon.core.synthetic import RenderParams, StereoCamera, SyntheticParams
from threadrecon.core.tracking import (
    TrackParams,
    TrackState,
    gate_corrections,
    motion_error,
    polyline_length,
    resample,
    search_alpha,
    start_corrections,
    track_step,
)

CAM = StereoCamera()


def _arc(n: int = 300, z: float = 100.0) -> np.ndarray:
    """A 100 mm planar arc at depth ~z, (n, 3) mm."""
    t = np.linspace(0, 1, n)
    return np.column_stack([100 * t - 50, 15 * np.sin(np.pi * t), z + 5 * t])


def _P() -> tuple[np.ndarray, np.ndarray]:
    K = CAM.K
    P1 = np.hstack([K, np.zeros((3, 1))])
    P2 = np.hstack([K, np.array([[-CAM.fx * CAM.baseline], [0], [0]])])
    return P1, P2


def test_search_alpha_is_the_predicted_largest_disparity_plus_the_margin():
    p = TrackParams(n_samples=50)
    x = resample(_arc(z=100.0), 50)
    state = TrackState(x, np.zeros_like(x))
    d_max = CAM.fx * CAM.baseline / x[:, 2].min()
    assert search_alpha(state, *_P(), p) == int(np.ceil(d_max + p.alpha_margin_px))
    assert search_alpha(None, *_P(), p) is None
    assert search_alpha(state, *_P(), TrackParams(n_samples=50, enabled=False)) is None


def test_first_frame_starts_the_track_from_the_observation():
    obs = _arc()
    res, state = track_step(obs, None, TrackParams())
    assert res.status == "ok" and res.restarted and not res.flagged
    assert state is not None and np.allclose(state.velocity, 0)
    assert res.length == pytest.approx(polyline_length(obs), rel=1e-3)


def test_a_reversed_observation_keeps_the_tracked_start():
    p = TrackParams()
    _, state = track_step(_arc(), None, p)
    res, _ = track_step(_arc()[::-1], state, p)
    assert res.reversed
    assert np.linalg.norm(res.points[0] - _arc()[0]) < 1.0


def test_a_hidden_end_is_filled_from_the_motion_prior_and_flagged():
    p = TrackParams()
    full = _arc()
    _, state = track_step(full, None, p)
    shift = np.array([0.5, 0.2, 0.0])
    _, state = track_step(full + shift, state, p)  # now moving at 0.5 mm/frame
    truth = full + 2 * shift
    seen = truth[: int(0.55 * len(truth))]  # the far end is hidden
    res, _ = track_step(seen, state, p)
    assert res.filled > 30.0
    assert res.flagged
    assert abs(res.length - polyline_length(truth)) < 2.0
    assert np.abs(resample(res.points, 200) - resample(truth, 200)).max() < 2.0


def test_a_hidden_end_is_pulled_onto_the_stereo_points_where_it_has_some():
    p = TrackParams()
    full = _arc()
    _, state = track_step(full, None, p)
    bent = full.copy()
    bent[200:, 1] += np.linspace(0, 3.0, 100)  # the far end moved 3 mm in y, unlike the prior
    seen = bent[:150]
    res_prior, _ = track_step(seen, state, p)
    res_cloud, _ = track_step(seen, state, p, cloud=bent[::2])
    err = [np.abs(resample(r.points, 300)[-40:] - bent[-40:]).max() for r in (res_prior, res_cloud)]
    assert err[1] < 0.5 * err[0]


def test_temporal_smoothness_damps_noise_of_a_still_thread():
    rng = np.random.default_rng(3)
    p = TrackParams()
    truth = _arc(200)
    state = None
    raw_steps, tracked_steps = [], []
    prev_raw = prev_tr = None
    for _ in range(20):
        obs = truth + rng.normal(0, 0.3, truth.shape)
        res, state = track_step(obs, state, p)
        if prev_raw is not None:
            raw_steps.append(motion_error(prev_raw, obs, truth, truth))
            tracked_steps.append(motion_error(prev_tr, res.points, truth, truth))
        prev_raw, prev_tr = obs, res.points
    assert np.mean(tracked_steps) < 0.8 * np.mean(raw_steps)


def test_a_failed_frame_is_predicted_then_the_track_is_lost():
    p = TrackParams(max_coast=2)
    _, state = track_step(_arc(), None, p)
    statuses = []
    for _ in range(3):
        res, state = track_step(None, state, p)
        statuses.append(res.status)
    assert statuses == ["predicted", "predicted", "lost"] and state is None


def test_an_observation_elsewhere_restarts_the_track():
    p = TrackParams()
    _, state = track_step(_arc(), None, p)
    res, new = track_step(_arc() + np.array([0.0, 60.0, 0.0]), state, p)
    assert res.restarted and res.flagged and np.allclose(new.velocity, 0)


def test_tracking_off_returns_the_single_frame_curve():
    p = TrackParams(enabled=False)
    _, state = track_step(_arc(), None, p)
    res, _ = track_step(_arc() + 1.0, state, p)
    assert not res.restarted and np.allclose(res.points, resample(_arc() + 1.0, p.n_samples))


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match=r"single must be \(M >= 2, 3\)"):
        track_step(np.zeros((5, 2)), None, TrackParams())
    with pytest.raises(ValueError, match="cloud must be"):
        track_step(_arc(), None, TrackParams(), cloud=np.zeros(3))
    with pytest.raises(ValueError, match="smooth"):
        TrackParams(smooth=2.0)


def test_motion_error_is_zero_for_exact_curves_and_the_noise_otherwise():
    a, b = _arc(), _arc() + np.array([1.0, 0.0, 0.0])
    assert motion_error(a, b, a, b) == pytest.approx(0.0, abs=1e-9)
    assert motion_error(a, b[::-1], a, b) == pytest.approx(0.0, abs=1e-9)  # a flip is no motion
    assert motion_error(a, b + np.array([0.0, 0.5, 0.0]), a, b) == pytest.approx(0.5, abs=1e-6)


# --- sequences --------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["drag", "pull"])
def test_thread_motion_stays_in_view_and_moves(kind):
    ctrl0 = _arc(8)
    ctrl0[:, :2] *= 0.4  # 40 mm wide at 100 mm: fits the view with room to move
    motion = MotionParams(kind=kind, n_frames=40)
    frames = thread_motion(ctrl0, CAM, motion, 10.0, 0)
    assert frames.shape == (40, 8, 3)
    for uv in CAM.project(frames.reshape(-1, 3)):
        assert uv.min() >= 10.0 and uv[:, 0].max() <= CAM.width - 11
    assert np.linalg.norm(frames[-1] - frames[0], axis=1).max() > 2.0


def test_instrument_sequence_hides_a_moving_piece_and_has_truth_per_frame():
    params = SequenceParams(motion=MotionParams(kind="instrument", n_frames=5))
    frames = list(generate_sequence(params, seed=4))
    again = next(iter(generate_sequence(params, seed=4)))
    assert len(frames) == 5
    assert np.array_equal(frames[0].left, again.left)  # deterministic per seed
    shaft_px = [int((f.left.astype(int).sum(2) > 3 * 150).sum()) for f in frames]
    assert min(shaft_px) > 1000  # a bright metallic shaft is in every frame
    for f in frames:
        assert f.truth.centerline.shape[1] == 3 and f.truth.length_mm > 50
        assert f.mask_left.sum() > 200
    assert not np.array_equal(frames[0].mask_left, frames[-1].mask_left)


def test_a_still_random_occluder_is_refused_for_sequences():
    p = SequenceParams(frame=SyntheticParams(render=RenderParams(occlusion=True)))
    with pytest.raises(ValueError, match="instrument"):
        next(iter(generate_sequence(p, 0)))
    with pytest.raises(ValueError, match="motion.kind"):
        MotionParams(kind="spin")


def test_an_end_hidden_little_by_little_is_kept_since_the_thread_does_not_stretch():
    p = TrackParams()
    full = _arc(400)
    _, state = track_step(full, None, p)
    for k in range(1, 16):  # 1 mm (4 samples) more of the far end hidden every frame
        res, state = track_step(full[: len(full) - 4 * k], state, p)
    assert res.length == pytest.approx(polyline_length(full), abs=1.5)
    assert res.filled > 10.0


def test_an_end_without_stereo_support_is_trimmed_and_taken_from_the_prior():
    p = TrackParams()
    full = _arc(400)
    _, state = track_step(full, None, p, cloud=full)
    wild = full.copy()
    wild[340:, 2] += np.linspace(0, 30, 60)  # the spline ran on past its data, in depth
    res, _ = track_step(wild, state, p, cloud=full[:330])
    assert np.abs(resample(res.points, 400) - full).max() < 1.5
    res_no_cloud, _ = track_step(wild, state, p)
    assert np.abs(resample(res_no_cloud.points, 400) - full).max() > 10.0


def _farthest(curve: np.ndarray, truth: np.ndarray) -> float:
    """Largest distance of a point of ``curve`` to the (dense) polyline ``truth``."""
    return float(cKDTree(resample(truth, 4000)).query(curve)[0].max())


def test_a_piece_hidden_in_the_middle_is_taken_from_the_prior():
    p = TrackParams()
    full = _arc(400)
    full[:, 1] += 10.0 * np.exp(-(((np.arange(400) - 200) / 30.0) ** 2))  # a bump under it
    _, state = track_step(full, None, p, cloud=full)
    bridged = full.copy()
    bridged[150:250] = np.linspace(full[150], full[249], 100)  # the spline cut across the gap
    cloud = np.vstack([full[:150], full[250:]])  # no stereo point where the instrument is
    res, _ = track_step(bridged, state, p, cloud=cloud)
    assert res.filled > 10.0
    assert _farthest(res.points, full) < 0.5 * p.support_mm  # what remains is the supported part
    res_plain, _ = track_step(bridged, state, p)  # without stereo points: nothing is hidden
    assert _farthest(res_plain.points, full) > 4.0


def test_filled_ends_add_no_more_than_the_known_length_misses():
    p = TrackParams()
    full = _arc(400)
    _, state = track_step(full, None, p)
    # A prior that grew a spurious 50 mm tail (a wrong earlier frame) beyond the known length.
    tail = full[-1] + np.linspace(0, 50, 100)[:, None] * np.array([1.0, 0.0, 0.0])
    grown = resample(np.vstack([full, tail[1:]]), p.n_samples)
    state = TrackState(grown, np.zeros_like(grown), 0, polyline_length(full))
    res, new = track_step(full, state, p)
    assert res.length < polyline_length(full) + p.cover_mm + 0.5
    assert new.length_ref == pytest.approx(polyline_length(full), rel=1e-3)


def test_a_doubted_curve_is_believed_only_where_it_agrees_with_the_prior():
    p = TrackParams()
    full = _arc(400)
    _, state = track_step(full, None, p, cloud=full)
    wrong = full.copy()
    wrong[180:260, 1] += 25.0 * np.sin(np.linspace(0, np.pi, 80))  # on another strand's pixels
    cloud = np.vstack([full, wrong[180:260]])  # ... which stereo supports
    trusted, _ = track_step(wrong, state, p, cloud=cloud)
    doubted, _ = track_step(wrong, state, p, cloud=cloud, check="suspect")
    assert _farthest(trusted.points, full) > 20.0
    assert _farthest(doubted.points, full) < p.disagree_mm  # only what agrees with the prior


def test_a_failed_curve_never_starts_a_track_but_serves_with_a_prior():
    p = TrackParams()
    full = _arc(400)
    res, state = track_step(full, None, p, cloud=full, check="failed")
    assert res.status == "lost" and state is None
    _, state = track_step(full, None, p, cloud=full)
    moved = full + np.array([0.5, 0.0, 0.0])
    res, new = track_step(moved, state, p, cloud=moved, check="failed")
    assert res.status == "ok" and new is not None
    assert np.abs(resample(res.points, 400) - moved).max() < 1.0
    res, _ = track_step(moved, state, p, cloud=None, check="failed")  # nothing supports it
    assert res.status == "predicted"


def test_only_an_ok_curve_starts_a_track():
    p = TrackParams()
    full = _arc(400)
    for check in ("suspect", "failed"):
        res, state = track_step(full, None, p, cloud=full, check=check)
        assert res.status == "lost" and res.points is None and state is None
        assert "starts from an ok one" in res.reason or check == "failed"
    res, state = track_step(full, None, p, cloud=full, check="ok")
    assert res.status == "ok" and res.restarted and state is not None


def test_a_doubted_curve_elsewhere_is_predicted_not_restarted_from():
    p = TrackParams()
    _, state = track_step(_arc(), None, p)
    elsewhere = _arc() + np.array([0.0, 60.0, 0.0])  # e.g. an instrument's shaft
    res, new = track_step(elsewhere, state, p, cloud=elsewhere, check="suspect")
    assert res.status == "predicted" and not res.restarted
    assert np.allclose(res.points, state.predicted) and new.coasted == 1


def test_gate_keeps_a_band_around_the_reprojected_prediction_widened_by_the_motion():
    P1, P2 = _P()
    p = TrackParams(gate_px=10.0)
    x = _arc(200) * np.array([0.5, 1.0, 1.0])  # in view
    v = np.tile([1.0, 0.0, 0.0], (len(x), 1))  # 1 mm a frame to the right
    gate = gate_corrections(TrackState(x, v), P1, P2, (CAM.height, CAM.width), p)
    assert [c.op for c in gate] == ["keep", "keep"] and tuple(c.view for c in gate) == VIEWS
    for c, P in zip(gate, (P1, P2), strict=True):
        uv = np.column_stack([x + v, np.ones(len(x))]) @ P.T
        uv = uv[:, :2] / uv[:, 2:]
        pts = np.array(c.points, dtype=float)
        assert cKDTree(pts).query(uv)[0].max() < 2.0  # the prediction, not the last curve
        motion = CAM.fx * 1.0 / x[:, 2].min()  # px of 1 mm at the nearest sample
        assert c.radius == pytest.approx(10.0 + motion, rel=0.02)
    # applied to masks: a piece on the predicted curve stays, one far from it goes
    mask = np.zeros((CAM.height, CAM.width), bool)
    uv = np.rint(np.array(gate[0].points)).astype(int)
    mask[uv[:, 1], uv[:, 0]] = True
    mask[10:30, 10:200] = True  # an instrument far from the thread
    grey = np.zeros(mask.shape, np.float32)
    lifted = LiftedPair(I_L=grey, I_R=grey, P_L=mask, P_R=mask, grey_L=grey, grey_R=grey,
               background=(0.0, 0.0), method="test")  # fmt: skip
    out = apply_corrections(lifted, gate, 0)
    assert out.P_L[uv[:, 1], uv[:, 0]].all() and not out.P_L[10:30, 10:200].any()
    assert out.removed_L[10:30, 10:200].all()


def test_gate_is_empty_without_a_prior_or_with_tracking_off():
    P1, P2 = _P()
    x = _arc(50)
    state = TrackState(x, np.zeros_like(x))
    assert gate_corrections(None, P1, P2, (480, 640), TrackParams()) == ()
    assert gate_corrections(state, P1, P2, (480, 640), TrackParams(enabled=False)) == ()
    assert gate_corrections(state, P1, P2, (480, 640), TrackParams(gate_px=0.0)) == ()
    behind = TrackState(x * np.array([1, 1, -1]), np.zeros_like(x))
    assert gate_corrections(behind, P1, P2, (480, 640), TrackParams()) == ()


def test_gate_points_outside_the_image_are_clamped_to_its_border():
    P1, P2 = _P()
    x = _arc(100) * np.array([20.0, 1.0, 1.0])  # 2 m wide: far out of view on both sides
    gate = gate_corrections(TrackState(x, np.zeros_like(x)), P1, P2, (480, 640), TrackParams())
    for c in gate:
        c.check_inside((480, 640))  # raises for a point outside


def test_start_hypotheses_remove_the_largest_pieces_first():
    mask = np.zeros((100, 200), bool)
    mask[10:40, 10:150] = True  # largest (an instrument's shaft)
    mask[60, 20:180] = True  # the thread
    mask[90:92, 5:8] = True  # a speck
    hyps = start_corrections(mask)
    assert len(hyps) == 3
    sizes = []
    for (c,) in hyps:
        assert c.op == "remove" and c.stereo and c.view == "left"
        x, y = c.points[0]
        assert mask[y, x]
        sizes.append(int(mask[10:40, 10:150].sum()) if y < 40 else (160 if y == 60 else 6))
    assert sizes == sorted(sizes, reverse=True)
    assert start_corrections(mask[:50]) == []  # one piece: nothing to try
    with pytest.raises(ValueError, match="mask"):
        start_corrections(np.zeros(5, bool))


def test_gate_erases_what_is_thicker_than_a_thread_where_it_crosses_the_band():
    P1, P2 = _P()
    x = _arc(200) * np.array([0.5, 1.0, 1.0])
    state = TrackState(x, np.zeros_like(x))
    shape = (CAM.height, CAM.width)
    p = TrackParams(gate_px=10.0, thick_px=6.0)
    masks, threads = [], []
    for P in (P1, P2):
        thread, shaft = np.zeros(shape, np.uint8), np.zeros(shape, np.uint8)
        uv = np.column_stack([x, np.ones(len(x))]) @ P.T
        uv = np.round(uv[:, :2] / uv[:, 2:]).astype(np.int32)
        cv2.polylines(thread, [uv.reshape(-1, 1, 2)], False, 1, thickness=3)  # the thread, 3 px
        mid = uv[len(uv) // 2]
        cv2.line(shaft, (0, int(mid[1]) - 60), (int(mid[0]) + 40, int(mid[1]) + 20), 1, 30)
        masks.append((thread | shaft).astype(bool))
        threads.append(thread.astype(bool) & ~cv2.dilate(shaft, np.ones((3, 3))).astype(bool))
    gate = gate_corrections(state, P1, P2, shape, p, (masks[0], masks[1]))
    assert {c.op for c in gate} == {"keep", "erase"}
    grey = np.zeros(shape, np.float32)
    lifted = LiftedPair(I_L=grey, I_R=grey, P_L=masks[0], P_R=masks[1], grey_L=grey,
                        grey_R=grey, background=(0.0, 0.0), method="test")  # fmt: skip
    out = apply_corrections(lifted, gate, 0)
    for kept, thread in ((out.P_L, threads[0]), (out.P_R, threads[1])):
        dist = cv2.distanceTransform(kept.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        assert dist.max() < p.thick_px  # nothing thicker than a thread is left
        assert (kept & thread).sum() >= 0.97 * thread.sum()  # the visible thread stays
        assert (kept & ~thread).sum() < 0.1 * thread.sum()  # the shaft's fringe at most
    with pytest.raises(ValueError, match="masks"):
        gate_corrections(state, P1, P2, shape, p, (masks[0][:10], masks[1]))
    plain = gate_corrections(state, P1, P2, shape, TrackParams(thick_px=0.0), (masks[0], masks[1]))
    assert [c.op for c in plain] == ["keep", "keep"]


def test_an_observation_of_another_run_is_flagged_against_the_single_frame_curve():
    p = TrackParams()
    full = _arc(400)
    _, state = track_step(full, None, p, cloud=full)
    moved = full + np.array([0.3, 0.0, 0.0])
    shaft = moved + np.array([0.0, 40.0, -20.0])  # the single-frame run took an instrument
    res, new = track_step(moved, state, p, cloud=moved, check="suspect", single_frame=shaft)
    assert res.status == "ok" and res.flagged and res.disagreement > 40
    assert res.reason.startswith("tracked and single-frame curves differ by")
    assert res.single is shaft and new is not None
    same, _ = track_step(moved, state, p, cloud=moved, check="suspect")
    assert not same.flagged and np.allclose(same.points, res.points)
    none, _ = track_step(moved, state, p, cloud=moved, check="suspect", single_frame=None)
    assert none.flagged and "no single-frame curve" in none.reason


@pytest.mark.parametrize("angle", [10.0, 35.0, 60.0, 85.0, 120.0])
def test_first_start_hypothesis_removes_exactly_what_is_thicker_than_a_thread(angle):
    shape, r = (240, 320), 6.0
    m = np.zeros(shape, np.uint8)
    cv2.polylines(m, [np.array([[20, 200], [120, 150], [300, 190]], np.int32)], False, 1, 3)
    t = np.deg2rad(angle)
    c, d = np.array([160, 120]), 400 * np.array([np.cos(t), np.sin(t)])
    p0, p1 = (c - d).astype(int), (c + d).astype(int)
    cv2.line(m, tuple(int(v) for v in p0), tuple(int(v) for v in p1), 1, 25)  # touches the thread
    mask = m.astype(bool)
    hyps = start_corrections(mask, mask, thick_px=r)
    thick = hyps[0]
    assert {c.op for c in thick} == {"erase"} and {c.view for c in thick} == {"left", "right"}
    assert len(thick) <= 6  # a shaft is a stroke or a few, not one per row
    grey = np.zeros(shape, np.float32)
    lifted = LiftedPair(I_L=grey, I_R=grey, P_L=mask, P_R=mask, grey_L=grey, grey_R=grey,
                        background=(0.0, 0.0), method="test")  # fmt: skip
    out = apply_corrections(lifted, thick, 0)
    dist = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    opening = cv2.dilate((dist >= r).astype(np.uint8), cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (2 * int(r) + 1, 2 * int(r) + 1))).astype(bool) & mask  # fmt: skip
    assert np.count_nonzero(out.P_L ^ (mask & ~opening)) <= 0.01 * mask.sum()
    plain = start_corrections(mask, mask, thick_px=0.0)  # piece removals only
    assert all(c.op == "remove" for h in plain for c in h)
