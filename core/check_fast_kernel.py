"""Compiled kernels of the check stage's second speed pass (issue 13): one pass where numpy or
scipy took a full-crop scan or built a tree, with the same decisions (the check's results are
identical to the forms they replace).

``close_pairs``: the pairs of points within a distance in the image and apart along the curve,
by a sweep over the points sorted by x, instead of a ``cKDTree`` built and queried for a few
hundred points, most of whose pairs are neighbours along the curve (``check_fold.fold_length``).
(A mask crop's pixels by rows come from the refine stage's row runs: ``check._rows_of_runs``.)
``ring_level``: the median grey level of the ring around the thread and its deviation
(``check._BareBackground``) from one pass over the window and two partitions, instead of a dozen
numpy calls (~40 us a ring). ``rows_contradicted``: the reliable matches in a window around
each curve point read from the reliable pixels' rows (``check_support``), which the check
builds anyway, instead of a NaN image of their bounding box built per stereo result (~0.5 MB
of fresh memory at 640x480). ``contested_runs``: each reliable match's right run among P_R's
row runs and the matches' spread per run (``check_support.contested``), in one pass instead of
some forty numpy calls (~0.3 ms a new segmentation).
"""

from __future__ import annotations

import math

import numpy as np

from threadrecon.core.compiled import kernel


# Compiled ahead of time once per machine (core/compiled.py), so that numba is not loaded.
@kernel("int64[:, ::1](float64[::1], float64[::1], float64[::1], float64, float64)")
def close_pairs(x, y, s, r, gap):  # noqa: ANN001
    """(k, 2) index pairs (i < j) of the points (x, y) whose squared distance
    ``dx * dx + dy * dy`` is at most ``r * r`` (``cKDTree.query_pairs(r)``'s test for p = 2)
    and whose ``s`` (arc length along the curve) differ by more than ``gap``; in no
    particular order. Points must be finite."""
    n = len(x)
    order = np.argsort(x, kind="mergesort")
    r2 = r * r
    reach = r * (1.0 + 1e-9)  # beyond r in x, whatever the rounding: no pair
    cap = 16
    out = np.empty((cap, 2), np.int64)
    k = 0
    for a in range(n):
        i = order[a]
        for b in range(a + 1, n):
            j = order[b]
            if x[j] - x[i] > reach:
                break
            dx = x[i] - x[j]
            dy = y[i] - y[j]
            if dx * dx + dy * dy <= r2 and abs(s[i] - s[j]) > gap:
                if k == cap:  # grow: a dense cluster of points
                    bigger = np.empty((2 * cap, 2), np.int64)
                    bigger[:cap] = out
                    out = bigger
                    cap *= 2
                out[k, 0] = min(i, j)
                out[k, 1] = max(i, j)
                k += 1
    return out[:k].copy()


@kernel("float64[::1](float32[:, :], float64[:, ::1], float64, float64, int64)")
def ring_level(d, grey, lo, hi, min_count):  # noqa: ANN001
    """The grey levels of ``grey`` where ``lo < d <= hi`` (``d``: a distance field on the same
    window): (count, median, median absolute deviation from it), the medians as ``np.median``
    gives them (the mean of the two middle values of an even count); count alone (the rest
    NaN) when there are fewer than ``min_count``."""
    h, w = d.shape
    vals = np.empty(h * w)
    n = 0
    for i in range(h):
        for j in range(w):
            v = d[i, j]
            if v > lo and v <= hi:
                vals[n] = grey[i, j]
                n += 1
    out = np.full(3, np.nan)
    out[0] = n
    if n < min_count or n == 0:
        return out
    k = n // 2  # the k-th smallest (and for an even count the largest below it)
    part = np.partition(vals[:n], k)
    med = part[k] if n % 2 else (part[:k].max() + part[k]) / 2.0
    dev = np.partition(np.abs(part - med), k)
    out[1] = med
    out[2] = dev[k] if n % 2 else (dev[:k].max() + dev[k]) / 2.0
    return out


@kernel(
    "boolean[::1](int64[::1], int64[::1], int64, float64[::1], int64[:, ::1], boolean[::1], "
    "float64[::1], int64, float64)"
)
def rows_contradicted(xs, row_ptr, y0, disp, q, ok, qdisp, near, tol):  # noqa: ANN001
    """``check_support.contradicted`` per point on the reliable pixels by rows (CSR as
    ``check._rows`` gives them: row y0 + k holds the columns ``xs[row_ptr[k]:row_ptr[k + 1]]``,
    ascending, with disparities ``disp``): point i (``ok[i]``) at pixel ``q[i]`` (x, y) has a
    reliable pixel with a finite disparity in its (2 ``near`` + 1)^2 window and none within
    ``tol`` of ``qdisp[i]``. The disparities are compared at float32 precision (those of
    the sparse image this replaces)."""
    n_rows = len(row_ptr) - 1
    out = np.zeros(len(q), dtype=np.bool_)
    for i in range(len(q)):
        if not ok[i]:
            continue
        seen = False
        agrees = False
        x0, x1 = q[i, 0] - near, q[i, 0] + near
        for y in range(q[i, 1] - near, q[i, 1] + near + 1):
            r = y - y0
            if r < 0 or r >= n_rows:
                continue
            lo, hi = row_ptr[r], row_ptr[r + 1]
            while lo < hi:  # the row's first column >= x0
                mid = (lo + hi) >> 1
                if xs[mid] < x0:
                    lo = mid + 1
                else:
                    hi = mid
            for j in range(lo, row_ptr[r + 1]):
                if xs[j] > x1:
                    break
                v = np.float64(np.float32(disp[j]))
                if math.isfinite(v):
                    seen = True
                    if abs(v - qdisp[i]) <= tol:
                        agrees = True
        out[i] = seen and not agrees
    return out


@kernel(
    "boolean[::1](int64[::1], int64[::1], float64[::1], int64[::1], int64[::1], int64[::1], "
    "int64, int64, float64)"
)
def contested_runs(x, y, xr, row, first, last, h, w, slack):  # noqa: ANN001
    """``check_support.contested`` on the reliable matches (left pixel ``x``, ``y``; right
    position ``xr`` = rint(x - d), not finite: no match) and P_R's row runs (``row``,
    ``first``, ``last`` column, row-major: ``refine.row_runs``) of an (h, w) mask: a match's
    run holds xr, else xr - 1, else xr + 1 on its row (0 <= y < h, 0 <= column < w); a match
    is contested when another of its run lies farther from it than the run's width plus
    ``slack`` (the left x compared as numpy compares int64 with float64)."""
    n = len(x)
    r = len(row)
    run = np.full(n, -1, np.int64)
    for i in range(n):
        if not math.isfinite(xr[i]) or y[i] < 0 or y[i] >= h:
            continue
        xi = np.int64(xr[i])
        for o in (0, -1, 1):
            v = xi + o
            if v < 0 or v >= w:
                continue
            key = y[i] * w + v
            lo, hi = 0, r  # the first run starting after key: runs sorted by row * w + first
            while lo < hi:
                mid = (lo + hi) >> 1
                if row[mid] * w + first[mid] <= key:
                    lo = mid + 1
                else:
                    hi = mid
            j = lo - 1
            if j >= 0 and row[j] == y[i] and last[j] >= v:
                run[i] = j
                break
    lo_x = np.full(r, 9223372036854775807, np.int64)
    hi_x = np.full(r, -9223372036854775807 - 1, np.int64)
    for i in range(n):
        k = run[i]
        if k >= 0:
            lo_x[k] = min(lo_x[k], x[i])
            hi_x[k] = max(hi_x[k], x[i])
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        k = run[i]
        if k >= 0:
            reach = np.float64(last[k] - first[k] + 1) + slack
            out[i] = np.float64(hi_x[k] - x[i]) > reach or np.float64(x[i] - lo_x[k]) > reach
    return out


@kernel("int64[:, ::1](boolean[::1])")
def flag_runs(flag):  # noqa: ANN001
    """(k, 2) (start, stop) of each run of True in ``flag``, in order."""
    n = len(flag)
    k = 0
    for i in range(n):
        if flag[i] and (i == 0 or not flag[i - 1]):
            k += 1
    out = np.empty((k, 2), np.int64)
    k = 0
    for i in range(n):
        if flag[i] and (i == 0 or not flag[i - 1]):
            out[k, 0] = i
        if flag[i] and (i == n - 1 or not flag[i + 1]):
            out[k, 1] = i + 1
            k += 1
    return out
