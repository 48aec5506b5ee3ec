"""core/numeric.py: the hot paths' numpy equivalents return numpy's values bit for bit."""

from __future__ import annotations

import numpy as np

from threadrecon.core.numeric import median


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
