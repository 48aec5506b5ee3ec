"""Shared test helpers: one tolerance helper and cached synthetic stereo cases."""

from __future__ import annotations

import functools

import numpy as np

from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.segmentation import StereoPair
from threadrecon.core.synthetic import (
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


@functools.lru_cache(maxsize=64)
def synthetic_case(
    seed: int, **thread_kwargs: object
) -> tuple[StereoPair, StereoCalibration, np.ndarray]:
    """(pair without masks, calibration, (M, 3) true centerline in mm) for ``seed``."""
    frame = synthetic_frame(seed, **thread_kwargs)
    pair = StereoPair(frame.left, frame.right)
    return pair, calibration_for(frame.camera), frame.truth.centerline
