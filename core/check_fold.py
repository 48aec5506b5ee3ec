"""The check's look for a fold: a curve that runs twice over one strand of the thread.

A wrong ordering can walk a stretch of thread back and forth (a Z: down, back up, down again).
Every pass lies on the thread pixels, at the thread's depth, and covers them: the reprojection,
coverage and depth checks all pass, yet the curve is longer than the thread by twice the fold.
The cue: two samples of the curve's left projection far apart along the curve, within
``radius`` (a thread's half-width) of each other, running along the same line (parallel or
antiparallel tangents) at the same disparity. Two distinct strands lie a thread width or more
apart (centre to centre), a crossing runs across (not along), and two strands over each other
differ in disparity: none of them is a fold.
"""

from __future__ import annotations

import numpy as np

from threadrecon.core.check_fast_kernel import close_pairs

FOLD_COS = float(np.cos(np.radians(30.0)))  # passes within 30 deg of one line run along it


def fold_length(
    uv: np.ndarray,
    step: np.ndarray,
    on: np.ndarray,
    disp: np.ndarray,
    radius: float,
    dtol: float,
) -> float:
    """2D length (px) of the curve running over a stretch another part of it already covers.

    ``uv``: (N, 2) left projection (x, y), px; ``step``: (N-1,) its 2D steps; ``on``: (N,)
    bool, samples on the thread pixels; ``disp``: (N,) the curve's disparity, px; ``radius``:
    px, two passes closer than this run over one strand; ``dtol``: px, passes whose disparities
    differ by this or more are strands over each other. Samples count when they are more than
    pi * radius + 3 px apart along the curve (a bend's own samples are closer). Half the length
    of the steps between two such samples (each fold is counted on both its passes)."""
    uv = np.asarray(uv, dtype=np.float64)
    n = len(uv)
    if uv.ndim != 2 or uv.shape[1] != 2 or len(step) != n - 1 or len(on) != n or len(disp) != n:
        raise ValueError(
            f"fold_length needs uv (N, 2), step (N-1,), on and disp (N,); got {uv.shape}, "
            f"{np.shape(step)}, {np.shape(on)}, {np.shape(disp)}"
        )
    seg = np.where(np.isfinite(step), step, 0.0)
    idx = np.flatnonzero(on & np.all(np.isfinite(uv), axis=1) & np.isfinite(disp))
    if idx.size < 3 or radius <= 0:
        return 0.0
    s = np.concatenate([[0.0], np.cumsum(seg)])
    gap = np.pi * radius + 3.0
    q = uv[idx]  # compiled: cKDTree.query_pairs' pairs, only those more than gap apart along
    pairs = close_pairs(q[:, 0].copy(), q[:, 1].copy(), s[idx], float(radius), gap)
    if not len(pairs):
        return 0.0
    t = np.gradient(uv, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
    along = np.abs(np.sum(t[i] * t[j], axis=1)) > FOLD_COS
    keep = (np.abs(s[i] - s[j]) > gap) & along & (np.abs(disp[i] - disp[j]) < dtol)
    hit = np.zeros(n, dtype=bool)
    hit[i[keep]] = True
    hit[j[keep]] = True
    return float(0.5 * np.sum(seg * (hit[1:] & hit[:-1])))
