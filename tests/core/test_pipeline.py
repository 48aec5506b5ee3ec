"""Tests of core/pipeline.py: end-to-end accuracy on synthetic frames, per-stage caching, and
failures reported with the stage that failed."""

from dataclasses import replace

import numpy as np
import pytest
from support import calibration_for, synthetic_case, synthetic_frame

from threadrecon.core.metrics import curve_errors
from threadrecon.core.pipeline import STAGES, Pipeline, ReconParams, reconstruct
from threadrecon.core.reliability import ReliabilityParams
from threadrecon.core.segmentation import StereoPair
from threadrecon.core.spline import SplineParams


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_reconstruction_of_flat_frame_is_accurate(seed: int) -> None:
    pair, calib, truth = synthetic_case(seed)
    rec = reconstruct(pair, calib)
    assert rec.status == "ok", rec.message
    assert rec.message is None
    assert list(rec.runs) == list(STAGES)
    curve = rec["camera"]
    assert curve.points.shape[0] >= 200 and curve.unit == "mm"
    assert np.all(np.isfinite(curve.points))
    err = curve_errors(curve.points, truth)
    assert err.e_S < 1.0
    assert err.e_length < 5.0


def test_changing_n_ctrl_reruns_only_spline_refine_and_camera() -> None:
    pair, calib, _ = synthetic_case(0)
    pipe = Pipeline(pair, calib)
    params = ReconParams()
    first = pipe.run(params)
    assert first.status == "ok"
    assert not any(run.cached for run in first.runs.values())
    again = pipe.run(params)
    assert all(run.cached for run in again.runs.values())
    changed = pipe.run(replace(params, spline=replace(params.spline, n_ctrl=12)))
    cached = {name: run.cached for name, run in changed.runs.items()}
    assert cached == {name: name not in ("spline", "refine", "camera", "check") for name in STAGES}
    assert changed["stereo"] is first["stereo"]
    sp = changed["spline"]
    # 12 control points: the 8 uniform spans of S_z (S_x, S_y may split some of them).
    uniform = np.linspace(0.0, sp.length, 12 - sp.degree + 1)
    assert np.all(np.min(np.abs(sp.knots[:, None] - uniform[None, :]), axis=0) < 1e-9)
    assert sp.ctrl.shape[0] >= 12
    assert all(changed.runs[name].ms == 0.0 for name in STAGES[:6])


def test_no_reliable_pixels_fails_at_clustering() -> None:
    pair, calib, _ = synthetic_case(0)
    # eps1 = 0: R = sigma(0) = 0.5 for every pixel, below the threshold 0.9.
    params = ReconParams(reliability=ReliabilityParams(eps1=0.0))
    rec = reconstruct(pair, calib, params)
    assert rec.status == "failed"
    assert rec.failed_stage == "clustering"
    assert "no reliable pixels" in rec.error
    assert rec.message.startswith("clustering:")
    assert set(rec.runs) == {"segment", "stereo", "reliability"}


def test_empty_segmentation_fails_at_segment() -> None:
    frame = synthetic_frame(0)
    blank = np.full_like(frame.left, 255)
    rec = reconstruct(StereoPair(blank, blank.copy()), calibration_for(frame.camera))
    assert rec.status == "failed"
    assert rec.failed_stage == "segment"
    assert "empty segmentation" in rec.error
    assert rec.runs == {}


def test_failed_stage_is_recomputed_after_a_fix() -> None:
    pair, calib, _ = synthetic_case(1)
    pipe = Pipeline(pair, calib)
    bad = pipe.run(ReconParams(reliability=ReliabilityParams(eps1=0.0)))
    assert bad.failed_stage == "clustering"
    good = pipe.run(ReconParams())
    assert good.status == "ok"
    assert good.runs["segment"].cached and good.runs["stereo"].cached
    assert not good.runs["reliability"].cached


def test_image_calibration_size_mismatch_raises() -> None:
    pair, calib, _ = synthetic_case(0)
    small = replace(calib, image_size=(240, 320))
    with pytest.raises(ValueError, match=r"\(480, 640\).*\(240, 320\)"):
        Pipeline(pair, small)
    with pytest.raises(ValueError, match="calibration"):
        reconstruct(pair, small)


def test_unknown_until_stage_raises() -> None:
    pair, calib, _ = synthetic_case(0)
    with pytest.raises(ValueError, match="unknown stage"):
        Pipeline(pair, calib).run(until="render")


def test_params_round_trip_to_dict() -> None:
    d = ReconParams(spline=SplineParams(n_ctrl=9)).to_dict()
    assert set(d) == set(STAGES)
    assert d["spline"]["n_ctrl"] == 9
