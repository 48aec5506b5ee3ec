"""Ends seen in one view only (core/ordering.py ``mono_reach_px``, docs/method.md deviation 33):
where the thread goes on in the left view but is hidden behind an instrument in the right, the
curve follows the left view's thread with depth from continuity, and its confidence drops
there; where both views see the end, or the right view shows bare background where the left
shows thread, nothing changes."""

from dataclasses import replace

import numpy as np
from support import calibration_for, right_tip_disc, synthetic_case

from threadrecon.app.dataset import evaluate_reconstruction
from threadrecon.core.metrics import project
from threadrecon.core.ordering import OrderingParams
from threadrecon.core.pipeline import Pipeline, ReconParams
from threadrecon.core.segmentation import StereoPair
from threadrecon.core.synthetic import RenderParams, SyntheticParams, generate_frame

OFF = ReconParams(ordering=OrderingParams(mono_reach_px=0.0))
ON = ReconParams(ordering=OrderingParams(mono_reach_px=60.0))  # off by default (deviation 33)


def _shaft_frame():
    """Generated occlusion frame (exact masks) whose thread passes under the shaft's tip and
    then runs beside the shaft for ~14 mm that the left view sees and the right does not
    (behind the shaft there), with ~5 mm hidden in both views between."""
    frame = generate_frame(
        SyntheticParams(render=RenderParams(occlusion=True)), np.random.default_rng([8158, 15])
    )
    pair = StereoPair(frame.left, frame.right, frame.mask_left, frame.mask_right)
    return pair, calibration_for(frame.camera), frame.truth.centerline


def _run(pair, calib, params):
    return Pipeline(pair, calib).run(params)


def test_an_end_behind_the_shaft_in_the_right_view_follows_the_left_view() -> None:
    pair, calib, truth = _shaft_frame()
    on, off = _run(pair, calib, ON), _run(pair, calib, OFF)
    m_on = evaluate_reconstruction(on, calib, truth)
    m_off = evaluate_reconstruction(off, calib, truth)
    assert off["ordering"].mono == (0, 0)
    assert m_off["e_length_mm"] > 20.0  # stops at the shaft: the one-view stretch is missed
    a, b = on["ordering"].mono
    assert a + b >= 5  # points placed along the left view's piece
    assert abs(m_on["e_length_mm"]) < 5.0 and m_on["e_S_max_mm"] < 5.0
    # the piece's points lie on the left thread pixels (they follow the visible thread)
    path = on["ordering"].path_px
    piece = np.concatenate([path[:a], path[len(path) - b :]])
    ys, xs = np.nonzero(pair.mask_left)
    near = np.min(np.hypot(xs[None] - piece[:, :1], ys[None] - piece[:, 1:2]), axis=1)
    assert near.max() <= 2.0
    # and they are not observed by stereo: the check's confidence is lower there
    conf = on["check"].confidence
    uv = project(on["camera"].points, calib.P1)
    d_piece = np.min(np.hypot(*(uv[:, None, :] - piece[None, :, :2]).transpose(2, 0, 1)), axis=1)
    mono_pts = d_piece <= 3.0
    assert mono_pts.sum() >= 10
    assert np.median(conf[mono_pts]) < 0.6 < np.median(conf[~mono_pts])


def test_the_depth_of_a_one_view_stretch_stays_within_the_continuity_bound() -> None:
    pair, calib, _ = _shaft_frame()
    o = Pipeline(pair, calib).run(ON, until="ordering")["ordering"]
    stereo = Pipeline(pair, calib).run(ON, until="stereo")["stereo"]
    a, b = o.mono
    path = o.path_px
    end = path[len(path) - b - 1]  # the last point seen in both views (the two-view tip)
    fB = calib.focal * calib.baseline
    for q in path[len(path) - b :]:
        s = np.hypot(*(q[:2] - end[:2]))
        assert abs(fB / q[2] - fB / end[2]) <= 1.0 + 0.1 * (s + 60.0) + 0.5
    assert np.all((path[:, 2] > 0) & np.isfinite(path[:, 2]))
    assert stereo.d_range[0] <= np.min(fB / path[:, 2]) - 0.5


def test_nothing_changes_where_both_views_see_the_end() -> None:
    pair, calib, _ = synthetic_case(2)
    on = Pipeline(pair, calib).run(ON, until="bounds")
    off = Pipeline(pair, calib).run(OFF, until="bounds")
    assert on["ordering"].mono == (0, 0)
    assert np.array_equal(on["ordering"].path_px, off["ordering"].path_px)
    assert np.array_equal(on["bounds"].H, off["bounds"].H)


def _painted_right_end(hide_px: int, grey: float | None):
    """Plain generated frame whose right view loses the last ``hide_px`` px of the thread's
    first end: painted with ``grey`` (an occluder) or, for None, the bare background (a mask
    that ends short, a glint)."""
    frame, calib, near = right_tip_disc(hide_px)
    right, m_R = frame.right.copy(), frame.mask_right.copy()
    bg = np.median(frame.right[~m_R], axis=0)
    right[near] = bg.astype(np.uint8) if grey is None else np.full_like(bg, grey).astype(np.uint8)
    if grey is None:
        right[near & ~frame.mask_right] = frame.right[near & ~frame.mask_right]
    m_R[near] = False
    return StereoPair(frame.left, right, frame.mask_left, m_R), calib, frame.truth.centerline


def test_an_end_hidden_by_an_occluder_in_the_right_view_is_followed() -> None:
    pair, calib, truth = _painted_right_end(40, grey=60.0)
    on, off = _run(pair, calib, ON), _run(pair, calib, OFF)
    assert sum(on["ordering"].mono) >= 2 and off["ordering"].mono == (0, 0)
    e_on = evaluate_reconstruction(on, calib, truth)
    e_off = evaluate_reconstruction(off, calib, truth)
    assert abs(e_on["e_length_mm"]) < abs(e_off["e_length_mm"]) - 2.0
    assert e_on["e_S_max_mm"] < e_off["e_S_max_mm"]
    conf = on["check"].confidence
    n = len(conf)
    tail = conf[: n // 20] if on["ordering"].mono[0] else conf[-(n // 20) :]
    assert tail.min() < np.median(conf) - 0.2


def test_an_end_over_bare_background_in_the_right_view_is_not_extended() -> None:
    pair, calib, _ = _painted_right_end(40, grey=None)
    on = Pipeline(pair, calib).run(ON, until="ordering")["ordering"]
    off = Pipeline(pair, calib).run(OFF, until="ordering")["ordering"]
    assert on.mono == (0, 0)
    assert np.array_equal(on.path_px, off.path_px)


def test_the_extension_is_off_in_paper_strict_and_by_default() -> None:
    from threadrecon.app.presets import resolve_preset

    assert resolve_preset("paper-strict").ordering.mono_reach_px == 0.0
    assert ReconParams().ordering == OFF.ordering
    assert replace(ReconParams().ordering, mono_reach_px=60.0) == ON.ordering
