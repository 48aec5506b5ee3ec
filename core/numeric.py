"""Small numeric helpers of the hot paths that return exactly what numpy returns, faster.

``np.median`` of a short 1-D array costs ~20-40 us, most of it in its generic layers (axis
handling, ``np.mean`` of the middle values, a NaN check on the partitioned copy); a spline
re-run takes three of them.
"""

from __future__ import annotations

import numpy as np


def median(a: np.ndarray) -> float:
    """``float(np.median(a))`` of a 1-D float array, bit for bit: the middle order statistic
    (``np.partition``), or the two middle ones' sum halved (``np.mean`` of two values); NaN
    when a value is NaN (numpy's NaN check) or the array is empty (numpy warns there)."""
    a = np.asarray(a)
    if a.ndim != 1 or a.dtype.kind != "f":
        return float(np.median(a))
    n = a.size
    if n == 0 or np.isnan(a).any():
        return float("nan")
    h = n // 2
    if n % 2:
        return float(np.partition(a, h)[h])
    part = np.partition(a, (h - 1, h))
    return float((part[h - 1] + part[h]) / 2.0)
