"""Tests of core/calibration.py: OpenCV FileStorage YAML in, rectified P1, P2, Q out."""

import numpy as np
import pytest
from support import assert_close

from threadrecon.core.calibration import CalibrationError, parse_calibration

FOCAL = 882.99611514
BASELINE = 5.908927288994923

_MATRICES = {
    "K1": (3, 3, f"{FOCAL}, 0.0, 445.06146749, 0.0, {FOCAL}, 190.24049547, 0., 0., 1."),
    "K2": (3, 3, f"{FOCAL}, 0.0, 445.06146749, 0.0, {FOCAL}, 190.24049547, 0., 0., 1."),
    "D1": (1, 5, "0., 0., 0., 0., 0."),
    "D2": (1, 5, "0., 0., 0., 0., 0."),
    "ImageSize": (1, 2, "480, 640"),
    "T": (3, 1, f"{-BASELINE}, 0., 0."),
    "R": (3, 3, "1., 0., 0., 0., 1., 0., 0., 0., 1."),
}


def _yaml(
    drop: str | None = None,
    override: dict[str, tuple[int, int, str]] | None = None,
    units: str | None = None,
) -> str:
    """Calibration text in OpenCV FileStorage YAML, as the paper dataset writes it."""
    mats = {**_MATRICES, **(override or {})}
    lines = ["%YAML:1.0", "---"]
    for key, (rows, cols, data) in mats.items():
        if key == drop:
            continue
        lines += [
            f"{key}: !!opencv-matrix",
            f"   rows: {rows}",
            f"   cols: {cols}",
            "   dt: d",
            f"   data: [ {data} ]",
        ]
    if units is not None:
        lines.append(f'Units: "{units}"')
    return "\n".join(lines) + "\n"


def test_parse_calibration_gives_rectified_focal_baseline_and_q() -> None:
    calib = parse_calibration(_yaml())
    assert calib.image_size == (480, 640)
    assert calib.unit == "mm"
    assert_close(calib.focal, FOCAL, rtol=1e-9)
    assert_close(calib.baseline, BASELINE, rtol=1e-9)
    assert calib.P1.shape == (3, 4) and calib.P2.shape == (3, 4) and calib.Q.shape == (4, 4)
    assert_close(calib.P2[0, 3], -FOCAL * BASELINE, rtol=1e-9)
    # Eq. (4): Q maps (x, y, d, 1) to a point at depth f B / d.
    x, y, d = 300.0, 200.0, 40.0
    X, Y, Z, W = calib.Q @ np.array([x, y, d, 1.0])
    assert_close(Z / W, FOCAL * BASELINE / d, rtol=1e-9)
    assert_close(calib.disparity_to_depth(d), FOCAL * BASELINE / d, rtol=1e-9)
    assert_close(calib.depth_to_disparity(calib.disparity_to_depth(d)), d, rtol=1e-12)


@pytest.mark.parametrize("key", ["K1", "D1", "K2", "D2", "R", "T", "ImageSize"])
def test_missing_key_raises_calibration_error_naming_it(key: str) -> None:
    with pytest.raises(CalibrationError, match=rf"missing key {key}\b"):
        parse_calibration(_yaml(drop=key), source="cal.yaml")


def test_malformed_key_raises_calibration_error_naming_it() -> None:
    with pytest.raises(CalibrationError, match=r"\bK1\b.*3x3"):
        parse_calibration(_yaml(override={"K1": (2, 2, "1., 0., 0., 1.")}))
    with pytest.raises(CalibrationError, match=r"\bT\b"):
        parse_calibration(_yaml(override={"T": (2, 1, "-5., 0.")}))


def test_calibration_error_is_a_value_error() -> None:
    assert issubclass(CalibrationError, ValueError)


def test_units_key_sets_the_length_unit() -> None:
    calib = parse_calibration(_yaml(units="cm"))
    assert calib.unit == "cm"
    assert calib.mm_per_unit == 10.0
    # Without the key, the caller's default applies.
    assert parse_calibration(_yaml(), unit="cm").unit == "cm"
    assert parse_calibration(_yaml(units="mm"), unit="cm").unit == "mm"


def test_non_yaml_text_raises_calibration_error() -> None:
    with pytest.raises(CalibrationError):
        parse_calibration("this is not a calibration file")


def test_negative_focal_lengths_are_rejected_naming_the_key() -> None:
    """Issue 11: negative focal lengths made every depth negative, status "ok"."""
    neg = f"{-FOCAL}, 0.0, 445.06, 0.0, {-FOCAL}, 190.24, 0., 0., 1."
    with pytest.raises(CalibrationError, match=r"K1 must have positive focal lengths"):
        parse_calibration(_yaml(override={"K1": (3, 3, neg)}), source="cal.yaml")
    with pytest.raises(CalibrationError, match=r"K2 must have positive focal lengths"):
        parse_calibration(_yaml(override={"K2": (3, 3, neg)}))


@pytest.mark.parametrize(
    "R",
    [
        "0., 0., 0., 0., 0., 0., 0., 0., 0.",  # issue 11: R all zeros shifted the curve ~20 mm
        "2., 0., 0., 0., 1., 0., 0., 0., 1.",  # not orthonormal
        "-1., 0., 0., 0., 1., 0., 0., 0., 1.",  # a reflection, det -1
    ],
)
def test_r_must_be_a_proper_rotation(R: str) -> None:
    with pytest.raises(CalibrationError, match=r"key R is not a proper rotation"):
        parse_calibration(_yaml(override={"R": (3, 3, R)}))


def test_rotation_with_six_digit_rounding_is_accepted() -> None:
    c, s = np.cos(0.01), np.sin(0.01)
    R = f"{c:.6f}, {-s:.6f}, 0., {s:.6f}, {c:.6f}, 0., 0., 0., 1."
    assert parse_calibration(_yaml(override={"R": (3, 3, R)})).focal > 0


def test_baseline_must_lie_along_x_after_rectification() -> None:
    with pytest.raises(CalibrationError, match=r"baseline is not along x"):
        parse_calibration(_yaml(override={"T": (3, 1, "-1., -5., 0.")}))
    with pytest.raises(CalibrationError, match=r"right camera lies left of the left camera"):
        parse_calibration(_yaml(override={"T": (3, 1, "5., 0., 0.")}))


@pytest.mark.parametrize("size", ["480.5, 640", ".nan, 640", "480, .inf"])
def test_image_size_must_be_finite_whole_numbers(size: str) -> None:
    with pytest.raises(CalibrationError, match=r"ImageSize must be two finite whole numbers"):
        parse_calibration(_yaml(override={"ImageSize": (1, 2, size)}))
