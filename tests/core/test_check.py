"""Tests of core/check.py: the check stage's status, reasons, per-point confidence, grasp point
and score, and the reproductions of issue 11 (each came back "ok" and wrong before)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from support import synthetic_case
from threadpoolctl import threadpool_limits

from threadrecon.app.dataset import discover, load_frame
from threadrecon.app.io import load_calibration, load_ground_truth, load_pair
from threadrecon.core.camera import CameraCurve
from threadrecon.core.check import CheckParams, CheckResult, check_curve
from threadrecon.core.metrics import curve_errors
from threadrecon.core.params import specs
from threadrecon.core.pipeline import STAGES, Pipeline, ReconParams, Reconstruction

ROOT = Path(__file__).resolve().parents[2]
TISSUE = ROOT / "sample_data" / "simulated" / "tissue"
PAPER = ROOT.parent / "shared" / "data" / "paper-dataset"
needs_paper = pytest.mark.skipif(not PAPER.is_dir(), reason="../shared/data/paper-dataset absent")


def _run(seed: int, params: ReconParams | None = None) -> Reconstruction:
    pair, calib, _ = synthetic_case(seed)
    return Pipeline(pair, calib).run(params or ReconParams())


def _recheck(seed: int, change) -> CheckResult:
    """The check of seed's reconstruction with its camera-frame curve changed by ``change``."""
    pair, calib, _ = synthetic_case(seed)
    rec = Pipeline(pair, calib).run()
    cam = rec["camera"]
    points = change(cam.points.copy())
    with np.errstate(invalid="ignore"):
        length = float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))
    curve = CameraCurve(cam.ctrl, cam.knots, cam.degree, points, length, cam.unit)
    args = [rec[s] for s in ("segment", "stereo", "reliability", "ordering", "bounds", "spline")]
    return check_curve(*args, curve, calib, CheckParams())


def test_check_is_the_last_stage_and_sets_the_status() -> None:
    assert STAGES[-1] == "check" and STAGES[-2] == "camera"
    rec = _run(0)
    chk = rec["check"]
    assert rec.status == chk.status == "ok"
    assert chk.reasons == () and rec.message is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_good_curve_is_ok_with_confidence_grasp_and_score(seed: int) -> None:
    rec = _run(seed)
    chk, pts = rec["check"], rec["camera"].points
    assert chk.status == "ok", chk.reasons
    assert chk.confidence.shape == (len(pts),)
    assert np.all((chk.confidence >= 0) & (chk.confidence <= 1))
    assert chk.reproj_left_mean < 1.0 and chk.coverage_left > 0.95 and chk.coverage_right > 0.95
    g = chk.grasp
    assert g is not None and 0 <= g.index < len(pts)
    np.testing.assert_allclose(g.point, pts[g.index])
    assert abs(np.linalg.norm(g.tangent) - 1.0) < 1e-9
    assert g.confidence == chk.confidence[g.index]
    p = CheckParams()
    assert abs(g.distance - p.grasp_mm) <= p.grasp_window_mm + 1e-9
    assert chk.score in (1, 2, 3, 4, 5)


def test_grasp_point_is_near_the_true_thread() -> None:
    pair, calib, truth = synthetic_case(1)
    rec = Pipeline(pair, calib).run()
    g = rec["check"].grasp
    assert np.min(np.linalg.norm(truth - g.point, axis=1)) < 1.0  # mm


def test_curve_pushed_off_in_depth_is_not_ok() -> None:
    chk = _recheck(0, lambda p: p * 1.4)  # same left projection, 40 % deeper
    assert chk.status != "ok"
    assert any("right projection" in r for r in chk.reasons)


def test_non_finite_curve_fails_with_a_reason_and_no_grasp() -> None:
    def spoil(p: np.ndarray) -> np.ndarray:
        p[5] = np.nan
        return p

    chk = _recheck(0, spoil)
    assert chk.status == "failed" and chk.grasp is None and chk.score == 1
    assert "not finite" in chk.reasons[0]
    assert np.all(chk.confidence == 0)


def test_curve_behind_the_camera_fails() -> None:
    chk = _recheck(0, lambda p: p * np.array([1.0, 1.0, -1.0]))
    assert chk.status == "failed"
    assert any("behind a camera" in r for r in chk.reasons)


def test_depth_outside_the_disparity_search_fails() -> None:
    def far(p: np.ndarray) -> np.ndarray:
        p[200:] *= 1e4  # same rays, a disparity far below d_min
        return p

    chk = _recheck(0, far)
    assert chk.status == "failed"
    assert any("disparity search allows" in r for r in chk.reasons)


def test_thresholds_are_documented_parameters() -> None:
    for spec in specs(CheckParams):
        assert spec.doc, spec.name
    with pytest.raises(ValueError, match="coverage_min"):
        CheckParams(coverage_min=1.5)


def test_confidence_is_lower_where_the_curve_leaves_the_evidence() -> None:
    def bump(p: np.ndarray) -> np.ndarray:
        p[150:250] *= 1.2  # a depth bump along the rays: the right view disagrees there
        return p

    chk = _recheck(2, bump)
    assert chk.confidence[150:250].mean() < 0.5 * chk.confidence[:100].mean()


def test_check_results_do_not_depend_on_blas_threads() -> None:
    pair, calib, _ = synthetic_case(3)
    params = ReconParams(spline=replace(ReconParams().spline, n_ctrl=40))
    out = []
    for n in (1, 2):
        with threadpool_limits(limits=n, user_api="blas"):
            rec = Pipeline(pair, calib).run(params)
        out.append((rec.status, rec["camera"].points))
    assert out[0][0] == out[1][0]
    np.testing.assert_array_equal(out[0][1], out[1][1])


# --- reproductions of issue 11 ----------------------------------------------------------


def test_tissue_frame_without_mask_is_not_ok() -> None:
    """tissue_2 without its mask: the grey threshold segments tissue; 879 m long, was "ok".
    The raw-frame segmentation (the default without a mask) finds the thread: ok and right."""
    pair = load_pair(stereo=TISSUE / "tissue_2.png")
    calib = load_calibration(TISSUE / "calibration.yaml")
    grey = ReconParams()
    grey = replace(grey, segment=replace(grey.segment, method="threshold"))
    rec = Pipeline(pair, calib).run(grey)
    assert rec.status in ("suspect", "failed")
    assert rec.reasons and rec.message
    raw = Pipeline(pair, calib).run()
    assert raw.status == "ok", raw.message
    gt = load_ground_truth(TISSUE / "tissue_2.npy")
    assert curve_errors(raw["camera"].points, gt).e_S < 2.0


def _paper(name: str, **changes: dict) -> tuple[Reconstruction, np.ndarray, float]:
    frame = next(f for f in discover(PAPER) if f.name == name)
    pair, calib, gt = load_frame(frame)
    params = ReconParams()
    for stage, values in changes.items():
        params = replace(params, **{stage: replace(getattr(params, stage), **values)})
    return Pipeline(pair, calib).run(params), gt, calib.mm_per_unit


@needs_paper
def test_paper_small_alpha_and_negative_eps3_is_not_ok() -> None:
    """blend4_2, alpha = 8, eps3 = -5: 135 m long, depth -344 m to 238 m, was "ok"."""
    rec, _, _ = _paper("blend4_2", stereo={"alpha": 8}, reliability={"eps3": -5.0})
    assert rec.status in ("suspect", "failed"), rec.message


@needs_paper
def test_paper_unoptimised_40_control_points_is_not_ok() -> None:
    """blend4_4, max_size = 73, n_ctrl = 40, optimise = false: length 1.3e40, was "ok"."""
    rec, _, _ = _paper(
        "blend4_4", clustering={"max_size": 73}, spline={"n_ctrl": 40, "optimise": False}
    )
    assert rec.status in ("suspect", "failed"), rec.message


@needs_paper
def test_paper_n_ctrl_40_same_with_one_and_several_blas_threads() -> None:
    """blend3_1, n_ctrl = 40: "failed" with one BLAS thread, "ok" and 552 km with several."""
    out = []
    for n in (1, 2):
        with threadpool_limits(limits=n, user_api="blas"):
            rec, _, _ = _paper("blend3_1", spline={"n_ctrl": 40})
        out.append((rec.status, rec["camera"].points))
    assert out[0][0] == out[1][0] != "ok"
    np.testing.assert_array_equal(out[0][1], out[1][1])


@needs_paper
def test_paper_dataset_default_curves_are_all_ok_and_right() -> None:
    for frame in discover(PAPER):
        pair, calib, gt = load_frame(frame)
        rec = Pipeline(pair, calib).run()
        assert rec.status == "ok", (frame.id, rec.message)
        if gt is not None:
            e = curve_errors(rec["camera"].points * calib.mm_per_unit, gt * calib.mm_per_unit)
            assert e.e_length < 20 and e.e_S_max < 20, frame.id
