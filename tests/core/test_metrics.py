"""Tests of core/metrics.py: the paper's curve, length and reprojection errors."""

import numpy as np
import pytest
from support import assert_close

from threadrecon.core import metrics
from threadrecon.core.calibration import make_calibration
from threadrecon.core.metrics import (
    _zhang_suen,
    curve_errors,
    frame_errors,
    hidden_ends,
    polyline_length,
    project,
    reprojection_errors,
    resample,
    skeleton,
    visible_part,
)

TRIALS = 10


def _planar_curve(rng: np.random.Generator) -> np.ndarray:
    """A random smooth curve in the plane z = 100 mm, (200, 3)."""
    t = np.linspace(0.0, 1.0, 200)
    a = rng.normal(size=(2, 3))
    x = 40 * t + sum(a[0, k] * np.sin((k + 1) * np.pi * t) for k in range(3))
    y = 10 * sum(a[1, k] * np.cos((k + 1) * np.pi * t) for k in range(3))
    return np.column_stack([x, y, np.full_like(t, 100.0)])


@pytest.mark.parametrize("seed", range(TRIALS))
def test_curve_error_of_a_curve_with_itself_is_zero(seed: int) -> None:
    c = _planar_curve(np.random.default_rng(seed))
    err = curve_errors(c, c)
    assert err.e_S == pytest.approx(0.0, abs=1e-9)
    assert err.e_S_max == pytest.approx(0.0, abs=1e-9)
    assert err.e_length == 0.0
    assert err.length == err.length_gt == pytest.approx(polyline_length(c))


@pytest.mark.parametrize("seed", range(TRIALS))
def test_curve_error_of_a_translated_copy_is_the_translation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    c = _planar_curve(rng)
    dz = float(rng.uniform(0.1, 5.0))
    moved = c + np.array([0.0, 0.0, dz])  # normal to the curve's plane: every distance is dz
    for a, b in ((moved, c), (c, moved)):
        err = curve_errors(a, b)
        assert err.e_S == pytest.approx(dz, rel=1e-9)
        assert err.e_S_max == pytest.approx(dz, rel=1e-9)
        assert err.e_length == pytest.approx(0.0, abs=1e-9)


def test_length_error_is_exact_on_a_known_polyline() -> None:
    bent = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [3.0, 4.0, 12.0]])  # 5 + 12
    straight = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    assert polyline_length(bent) == 17.0
    err = curve_errors(bent, straight)
    assert err.length == 17.0 and err.length_gt == 10.0
    assert err.e_length == 7.0
    assert curve_errors(straight, bent).e_length == 7.0


def test_resample_is_uniform_in_arc_length() -> None:
    bent = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [3.0, 4.0, 12.0]])
    r = resample(bent, 35)
    assert_close(r[[0, -1]], bent[[0, -1]])
    assert_close(np.linalg.norm(np.diff(r, axis=0), axis=1), np.full(34, 0.5), rtol=1e-9)


def test_project_with_identity_camera() -> None:
    P = np.array([[800.0, 0, 320, 0], [0, 800.0, 240, 0], [0, 0, 1, 0]])
    pts = np.array([[0.0, 0.0, 100.0], [10.0, -5.0, 50.0]])
    assert_close(project(pts, P), np.array([[320.0, 240.0], [480.0, 160.0]]))


def _line_mask() -> np.ndarray:
    mask = np.zeros((100, 100), bool)
    mask[49:52, 10:91] = True  # 3 px wide, 81 px long
    return mask


def test_points_on_mask_have_zero_reprojection_error_and_full_coverage() -> None:
    mask = _line_mask()
    pixels = np.column_stack([np.arange(10, 91), np.full(81, 50)]).astype(float)  # pixel centres
    err = reprojection_errors(pixels, mask)
    assert err.mean == 0.0 and err.max == 0.0
    assert err.coverage == 1.0


def test_half_length_curve_covers_about_half_the_thread() -> None:
    mask = _line_mask()
    pixels = np.column_stack([np.arange(10, 51), np.full(41, 50)]).astype(float)
    err = reprojection_errors(pixels, mask)
    assert err.max == 0.0
    assert err.coverage == pytest.approx(0.5, abs=0.1)


def test_reprojection_error_is_distance_to_the_mask() -> None:
    mask = _line_mask()
    pixels = np.array([[50.0, 55.0], [50.0, 51.0]])  # 4 px below the mask's last row, and on it
    err = reprojection_errors(pixels, mask)
    assert err.max == 4.0 and err.mean == 2.0
    with pytest.raises(ValueError, match="non-empty"):
        reprojection_errors(pixels, np.zeros((10, 10), bool))


def test_skeleton_of_a_three_pixel_line_is_one_pixel_wide() -> None:
    mask = _line_mask()
    skel = skeleton(mask)
    assert skel.dtype == bool and skel.shape == mask.shape
    assert np.all(skel <= mask)
    per_column = skel.sum(axis=0)
    assert per_column.max() == 1
    assert np.all(per_column[12:89] == 1)  # only the very ends may be trimmed
    assert np.all(np.nonzero(skel)[0] == 50)


def test_curve_errors_reject_bad_shapes() -> None:
    with pytest.raises(ValueError, match=r"\(3,\)"):
        curve_errors(np.zeros(3), np.zeros((4, 3)))


def test_skeleton_on_the_bounding_box_equals_the_full_image_thinning() -> None:
    rng = np.random.default_rng(7)
    mask = np.zeros((120, 160), dtype=bool)
    for _ in range(3):  # thick random strokes
        y, x = rng.integers(20, 100), rng.integers(20, 140)
        mask[y - 3 : y + 4, x - 25 : x + 25] = True
        mask[y - 20 : y + 20, x - 2 : x + 3] = True
    full = _zhang_suen(mask)
    sk = skeleton(mask)
    assert np.array_equal(sk, full)
    assert sk.sum() > 0 and not sk.flags.writeable
    assert skeleton(mask.copy()) is sk  # same content: cached
    other = mask.copy()
    other[0, 0] = True
    assert skeleton(other) is not sk
    assert not skeleton(np.zeros((10, 12), dtype=bool)).any()


def test_visible_part_keeps_the_run_inside_both_images() -> None:
    P1 = np.array([[100.0, 0, 50, 0], [0, 100.0, 40, 0], [0, 0, 1, 0]])
    P2 = P1.copy()
    P2[0, 3] = -100.0 * 5.0  # baseline 5
    x = np.linspace(-10.0, 60.0, 141)  # at z = 100: u = x + 50 (left), x + 45 (right)
    pts = np.column_stack([x, np.zeros_like(x), np.full_like(x, 100.0)])
    seen = visible_part(pts, P1, P2, (80, 100))
    for P in (P1, P2):
        uv = project(seen, P)
        assert np.all((uv[:, 0] >= -0.5) & (uv[:, 0] <= 99.5))
    assert len(seen) < len(pts) and seen[0, 0] == pts[np.flatnonzero(x + 45 >= -0.5)[0], 0]
    inside = pts[(x > 0) & (x < 40)]
    assert np.array_equal(visible_part(inside, P1, P2, (80, 100)), inside)  # seen whole


def test_frame_errors_judge_a_thread_leaving_the_view_on_its_visible_part() -> None:
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    calib = make_calibration(K, np.zeros(5), K, np.zeros(5), np.eye(3), [-0.5, 0, 0], (80, 100),
                             unit="cm")  # fmt: skip
    x = np.linspace(-1.0, 6.0, 141)  # cm at z = 10 cm: the first part is left of both images
    truth = np.column_stack([x, np.zeros_like(x), np.full_like(x, 10.0)])
    seen = visible_part(truth, calib.P1, calib.P2, calib.image_size)
    assert len(seen) < len(truth)
    e = frame_errors(seen, truth, calib)  # the curve of what both views see is right
    assert e.e_S_max < 0.1 and e.e_length < 0.5  # mm
    whole = curve_errors(seen * 10, truth * 10)  # the whole truth would call it wrong
    assert whole.e_length > 5.0 and whole.e_S_max > 5.0
    assert_close(frame_errors(truth, truth, calib).length_gt, e.length_gt)
    with pytest.raises(ValueError, match="N >= 2"):
        frame_errors(np.zeros((1, 3)), truth, calib)


def test_frame_errors_keep_the_truth_between_reconstructions(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The truth's visible part, resampling, k-d tree and length are kept by content: a second
    reconstruction of the frame (a slider move) builds only its own tree, with the values of
    the computation from scratch; another truth of the same shape gets its own."""
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    calib = make_calibration(K, np.zeros(5), K, np.zeros(5), np.eye(3), [-0.5, 0, 0], (80, 100),
                             unit="cm")  # fmt: skip
    x = np.linspace(-1.0, 6.0, 141)
    truth = np.column_stack([x, 0.1 * np.sin(x), np.full_like(x, 10.0)])
    built = []
    real = metrics.cKDTree
    monkeypatch.setattr(metrics, "cKDTree", lambda data: built.append(len(data)) or real(data))
    for k, shift in enumerate((0.0, 0.02, 0.05)):
        curve = truth + np.array([0.0, shift, 0.01 * k])
        before = len(built)
        e = frame_errors(curve, truth, calib)
        assert k == 0 or len(built) - before == 1  # the truth's tree: once
        seen = visible_part(truth, calib.P1, calib.P2, calib.image_size)
        assert e == curve_errors(curve * 10, seen * 10)  # bit for bit
    other = truth + np.array([0.0, 0.03, 0.0])
    e = frame_errors(truth, other, calib)
    assert e == curve_errors(truth * 10, visible_part(other, calib.P1, calib.P2, (80, 100)) * 10)
    assert e.e_S > 0.29  # mm: the other truth, not the kept one


def test_hidden_ends_measure_the_truth_no_view_shows() -> None:
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    calib = make_calibration(K, np.zeros(5), K, np.zeros(5), np.eye(3), [-5.0, 0, 0], (80, 100))
    x = np.linspace(0.0, 40.0, 401)  # mm at z = 100: u = x + 50 (left), x + 45 (right)
    truth = np.column_stack([x, np.zeros_like(x), np.full_like(x, 100.0)])
    cols = np.arange(100)
    mask_l = np.zeros((80, 100), dtype=bool)
    mask_l[40, (cols >= 50) & (cols <= 80)] = True  # the left view shows x in [0, 30]
    mask_r = np.zeros((80, 100), dtype=bool)
    mask_r[40, (cols >= 45) & (cols <= 70)] = True  # the right view shows x in [0, 25]
    start, end = hidden_ends(truth, calib, mask_l, mask_r)
    assert start == 0.0
    assert_close(end, 40.0 - 31.5, atol=0.11)  # the left view shows 30 mm, + 1 px grown, + rounding
    both = hidden_ends(truth, calib, np.zeros_like(mask_l), mask_r)
    assert_close(both[1], 40.0 - 26.5, atol=0.11)  # now only the right view shows it
    assert hidden_ends(truth, calib, mask_l * 0, mask_r * 0) == (40.0, 40.0)  # nothing seen
    wide = np.column_stack([x - 60.0, np.zeros_like(x), np.full_like(x, 100.0)])  # x < -50: out
    assert (
        hidden_ends(wide, calib, mask_l[:, ::-1] * 0, mask_r * 0)
        == (polyline_length(visible_part(wide, calib.P1, calib.P2, (80, 100))),) * 2
    )  # out of the image is not hidden
    with pytest.raises(ValueError, match=r"\(H, W\) thread masks"):
        hidden_ends(truth, calib, mask_l[0], mask_r)
