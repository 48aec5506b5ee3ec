"""Shared test helpers: one tolerance helper and cached synthetic stereo cases."""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np

from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.metrics import project
from threadrecon.core.segmentation import StereoPair
from threadrecon.core.synthetic import (
    RenderParams,
    StereoCamera,
    SyntheticFrame,
    SyntheticParams,
    ThreadParams,
    generate_frame,
)

# Default (rtol, atol) by dtype kind and size; integers and booleans compare exactly.
_TOLERANCES = {
    np.dtype(np.float16): (1e-3, 1e-3),
    np.dtype(np.float32): (1e-5, 1e-6),
    np.dtype(np.float64): (1e-10, 1e-12),
}


def assert_close(
    actual: np.ndarray | float,
    expected: np.ndarray | float,
    rtol: float | None = None,
    atol: float | None = None,
) -> None:
    """Assert ``actual`` matches ``expected`` in shape and value.

    Tolerances default by the coarser floating dtype of the two (float16/32/64); integer and
    bool arrays must be equal. NaNs must sit at the same positions in both, and an unexpected
    NaN fails loudly instead of comparing as "close".
    """
    a = np.asarray(actual)
    e = np.asarray(expected)
    assert a.shape == e.shape, f"shape {a.shape} != expected {e.shape}"
    floats = [x.dtype for x in (a, e) if np.issubdtype(x.dtype, np.floating)]
    if not floats:
        np.testing.assert_array_equal(a, e)
        return
    coarse = min(floats, key=lambda d: d.itemsize)
    d_rtol, d_atol = _TOLERANCES.get(coarse, (1e-10, 1e-12))
    rtol = d_rtol if rtol is None else rtol
    atol = d_atol if atol is None else atol
    a_nan, e_nan = np.isnan(a.astype(float)), np.isnan(e.astype(float))
    assert np.array_equal(a_nan, e_nan), (
        f"NaN mismatch: {int(a_nan.sum())} NaN in actual, {int(e_nan.sum())} in expected"
    )
    np.testing.assert_allclose(a, e, rtol=rtol, atol=atol, equal_nan=True)


def calibration_for(camera: StereoCamera) -> StereoCalibration:
    """The :class:`StereoCalibration` of a synthetic rectified camera (mm)."""
    return camera.calibration()


@functools.lru_cache(maxsize=64)
def synthetic_frame(seed: int, **thread_kwargs: object) -> SyntheticFrame:
    """Flat-background synthetic frame for ``seed``; ``thread_kwargs`` go to ThreadParams."""
    return generate_frame(SyntheticParams(thread=ThreadParams(**thread_kwargs)), rng=seed)


def suite_frame(key: list[int], **render: object) -> SyntheticFrame:
    """A frame as ``scripts/eval_suites.py`` draws it: the default thread, ``render`` as
    RenderParams, the generator seeded with ``key`` ([seed, suite index, frame index])."""
    params = SyntheticParams(thread=ThreadParams(), render=RenderParams(**render))
    return generate_frame(params, np.random.default_rng(key))


ALL_SUITE: dict[str, object] = dict(
    background="tissue",
    noise_sigma=3.0,
    blur_sigma=0.5,
    thread_colour="random",
    distractors=6,
    instrument=True,
    lighting=0.5,
    jpeg_quality=75,
    specular=0.3,
)
"""The render flags of ``scripts/eval_suites.py``'s "all" suite (index 12): every raw
condition together."""


def all_frame(seed: int, k: int) -> SyntheticFrame:
    """Frame ``k`` of ``scripts/eval_suites.py``'s "all" suite for ``seed``."""
    return suite_frame([seed, 12, k], **ALL_SUITE)


@functools.lru_cache(maxsize=64)
def synthetic_case(
    seed: int, **thread_kwargs: object
) -> tuple[StereoPair, StereoCalibration, np.ndarray]:
    """(pair without masks, calibration, (M, 3) true centerline in mm) for ``seed``."""
    frame = synthetic_frame(seed, **thread_kwargs)
    pair = StereoPair(frame.left, frame.right)
    return pair, calibration_for(frame.camera), frame.truth.centerline


def right_tip_disc(hide_px: int) -> tuple[SyntheticFrame, StereoCalibration, np.ndarray]:
    """Synthetic frame 2, its calibration and the (H, W) bool disc of radius ``hide_px`` around
    the right view's projection of the thread's first end: where tests hide that end."""
    frame = synthetic_frame(2)
    calib = calibration_for(frame.camera)
    tip = project(frame.truth.centerline[:2], calib.P2)[0]
    ys, xs = np.mgrid[: frame.mask_right.shape[0], : frame.mask_right.shape[1]]
    return frame, calib, np.hypot(xs - tip[0], ys - tip[1]) <= hide_px


def write_png(path: Path, img: np.ndarray) -> Path:
    """``img`` (RGB uint8, grey, or a bool mask) as a PNG at ``path`` (folders made)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    elif img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    assert cv2.imwrite(str(path), img)
    return path


def write_calibration(folder: Path, name: str = "calibration.yaml") -> Path:
    """The generator's rig as an OpenCV calibration file ``folder/name``."""
    from rig_support import opencv_yaml

    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_text(opencv_yaml(calibration_for(synthetic_frame(0).camera)))
    return p


def far_spot(mask: np.ndarray, length: int, margin: int) -> tuple[int, int]:
    """(x, y) of the left end of a horizontal run of ``length`` px at least ``margin`` px
    from every mask pixel and from the border (where a test draws a distractor)."""
    dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3)
    ok = dist > margin
    ok[:margin], ok[-margin:], ok[:, :margin], ok[:, -margin - length :] = (
        False,
        False,
        False,
        False,
    )
    run = cv2.erode(ok.astype(np.uint8), np.ones((1, length), np.uint8), anchor=(0, 0))
    ys, xs = np.nonzero(run)
    assert len(ys), "no free spot for a distractor"
    i = len(ys) // 2
    return int(xs[i]), int(ys[i])


def random_mask(
    shape: tuple[int, int], seed: int, fill: tuple[float, float], close_px: int
) -> np.ndarray:
    """A random uint8 mask for kernel tests: speckle of a density drawn from ``fill``, or for an
    odd ``seed`` blobs, strips and lines (the speckle closed by a ``close_px`` square)."""
    rng = np.random.default_rng(seed)
    m = (rng.random(shape) < rng.uniform(*fill)).astype(np.uint8)
    if seed % 2 and min(shape) > 2:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, np.ones((close_px, close_px), np.uint8))
    return m
