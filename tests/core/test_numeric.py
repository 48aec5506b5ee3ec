"""core/numeric.py: the hot paths' numpy equivalents return numpy's values bit for bit; the
distance transform is the exact one, whatever the state of OpenCV's IPP switch."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from threadrecon.core.numeric import distance_to_zero, median, row_norms


def test_median_is_numpys_median_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    for n in range(1, 120):
        a = rng.normal(0.0, 1.0, n) * 10.0 ** rng.integers(-5, 5)
        if n % 7 == 0:
            a[rng.integers(0, n)] = a[0]  # ties
        got = median(a)
        assert isinstance(got, float)
        assert np.float64(got).tobytes() == np.median(a).tobytes()
        assert median(a[::2]) == np.median(a[::2])  # strided


def test_median_of_nan_or_nothing_is_nan() -> None:
    assert np.isnan(median(np.array([1.0, np.nan, 3.0])))
    assert np.isnan(median(np.array([np.inf, -np.inf, np.nan])))
    assert np.isnan(median(np.zeros(0)))
    assert median(np.array([np.inf, 1.0, 2.0])) == 2.0
    assert median(np.array([3, 1, 2])) == 2.0  # integers: numpy's own median


@pytest.mark.parametrize("k", [2, 3])
def test_row_norms_are_numpys_norms_bit_for_bit(k: int) -> None:
    # sums of three squares in another order differ in the last bit on ~10 % of the rows
    rng = np.random.default_rng(k)
    v = rng.normal(0.0, 1.0, (20000, k)) * np.exp(rng.normal(0.0, 4.0, (20000, k)))
    v[:5] = [[0.0] * k, [np.nan] * k, [np.inf] * k, [-0.0] * k, [1e-300] * k]
    for a in (v, np.asfortranarray(v), v[::3], np.repeat(v, 2, axis=1)[:, ::2]):
        got = row_norms(a)
        assert got.tobytes() == np.linalg.norm(a, axis=1).tobytes()
    ints = rng.integers(-50, 50, (40, 4))  # another dtype or width: numpy's own norm
    assert np.array_equal(row_norms(ints), np.linalg.norm(ints, axis=1))


def _exact_distance(image: np.ndarray) -> np.ndarray:
    """float32 square root of the integer squared distance to the nearest zero pixel (the
    float64 root rounded to float32 is the correctly rounded float32 root)."""
    iy, ix = ndimage.distance_transform_edt(image, return_distances=False, return_indices=True)
    y, x = np.indices(image.shape)
    return np.sqrt(((iy - y) ** 2 + (ix - x) ** 2).astype(np.float64)).astype(np.float32)


@pytest.mark.parametrize("ipp", [True, False])
def test_distance_to_zero_is_the_exact_euclidean_distance(ipp: bool) -> None:
    rng = np.random.default_rng(11)
    was = cv2.ipp.useIPP()
    cv2.ipp.setUseIPP(ipp)
    try:
        for trial in range(30):
            h, w = rng.integers(5, 90, size=2)
            image = np.where(rng.random((h, w)) < 0.03 + 0.01 * trial, 0, 255).astype(np.uint8)
            image[rng.integers(0, h), rng.integers(0, w)] = 0
            held = np.empty(4 * trial + 1, np.uint8)  # a different heap for every output
            got = distance_to_zero(image)
            assert got.dtype == np.float32 and got.shape == image.shape
            np.testing.assert_array_equal(got, _exact_distance(image))
            del held
        assert cv2.ipp.useIPP() == ipp  # the caller's switch is left as it was
    finally:
        cv2.ipp.setUseIPP(was)


def test_distance_to_zero_refuses_other_images() -> None:
    with pytest.raises(ValueError, match="uint8"):
        distance_to_zero(np.ones((4, 5), np.float32))
    with pytest.raises(ValueError, match=r"\(4, 5, 3\)"):
        distance_to_zero(np.ones((4, 5, 3), np.uint8))
