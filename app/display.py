"""Display geometry for the 3D viewer: what a layer's nodes cost the viewer, and thinned
copies of them that look the same on screen.

A viewer without a GPU (Chromium's software WebGL) draws a screen-width line segment as one
instance of a small mesh, and each instance costs it about 25 us per frame whatever its
length: the 2000-point true curve alone was 50 ms of every frame, the scene's ~3600 segments
about 90 ms. A smooth polyline sampled finely for the stage results loses nothing visible when
the points that lie within a small distance of the chord between their neighbours are left
out (Douglas-Peucker). The point clouds are one draw each (no instancing) and are thinned by
``decimate_cloud`` only beyond a budget. The stage results themselves are never thinned: the
pixel inspector, the exports and the metrics read them, not these copies.
"""

from __future__ import annotations

import numpy as np

MIN_CHAIN = 128  # chains of fewer segments are drawn as they are: thinning one costs the server
# about as much once as the ~30 segments it saves cost the viewer over a move's few frames
MAX_PASSES = 16  # Douglas-Peucker passes (tree levels) at most: a noisy pixel path splits one
# vertex off a run per pass; after these, every vertex of a run still open is kept (never wrong,
# only less thin), so the cost stays MAX_PASSES vectorised passes over the polyline
COLOR_STEP = 16  # per-segment colours are compared in steps of this many (of 255) levels: a
# run of segments whose colours differ by less is drawn as one colour (its first segment's)


def decimate_cloud(
    points: np.ndarray, colors: np.ndarray, budget: int
) -> tuple[np.ndarray, np.ndarray]:
    """At most ``budget`` of the (N, 3) points, for display: every k-th (the points of a layer
    follow the pixels of P_L in row-major order, so a stride thins them evenly along the
    thread), with their colours ((N, 3) per point, or one (3,) colour). The pixel inspector
    still picks among all points of the stage result."""
    if budget < 1:
        raise ValueError(f"budget must be >= 1, got {budget}")
    n = len(points)
    if n <= budget:
        return points, colors
    k = -(-n // budget)  # ceil
    per_point = colors.ndim == 2 and len(colors) == n
    return points[::k], colors[::k] if per_point else colors


def simplify_polyline(points: np.ndarray, tol: float, keep: np.ndarray | None = None) -> np.ndarray:
    """Indices (sorted, first and last included) of the vertices of the (N, 3) polyline that
    Douglas-Peucker keeps: every left-out vertex lies within ``tol`` of the chord between the
    kept vertices around it. ``keep``: (N,) bool, vertices kept whatever their distance (e.g.
    where a colour changes). A non-finite vertex is always kept (it is never bridged)."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    if not tol >= 0.0:  # NaN fails too
        raise ValueError(f"tol must be >= 0, got {tol!r}")
    n = len(pts)
    if n <= 2:
        return np.arange(n)
    forced = np.zeros(n, bool) if keep is None else np.asarray(keep, bool).copy()
    if forced.shape != (n,):
        raise ValueError(f"keep must be ({n},) bool, got {forced.shape}")
    forced |= ~np.isfinite(pts).all(axis=1)
    forced[[0, -1]] = True
    # Douglas-Peucker one level at a time: every open run between kept vertices finds its
    # farthest vertex at once (grouped maxima), so a few vectorised passes do the whole tree
    kept = forced.copy()
    active = np.ones(n, bool)  # vertices of runs not settled yet
    tol2 = tol * tol
    for _ in range(MAX_PASSES):
        ki = np.flatnonzero(kept)
        cand = np.flatnonzero(active & ~kept)
        if not len(cand):
            break
        run = np.searchsorted(ki, cand) - 1  # the run (ki[run], ki[run + 1]) holding each
        a, b = pts[ki[run]], pts[ki[run + 1]]
        ab = b - a
        L2 = (ab * ab).sum(axis=1)
        t = np.clip(((pts[cand] - a) * ab).sum(axis=1) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
        d2 = ((pts[cand] - a - t[:, None] * ab) ** 2).sum(axis=1)  # to the chord, clamped
        first = np.flatnonzero(np.r_[True, run[1:] != run[:-1]])  # each run's first candidate
        worst = np.maximum.reduceat(d2, first)
        far = worst > tol2
        if not far.any():
            break
        # the first farthest vertex of each run that is too far is kept
        per = np.repeat(np.arange(len(first)), np.diff(np.r_[first, len(cand)]))
        hit = (d2 == worst[per]) & far[per]
        pick = np.minimum.reduceat(np.where(hit, np.arange(len(cand)), len(cand)), first)
        kept[cand[pick[far]]] = True
        active[cand[~far[per]]] = False  # runs within tol are settled
    else:
        kept |= active  # runs still open after MAX_PASSES keep every vertex
    return np.flatnonzero(kept)


def simplify_segments(
    segments: np.ndarray, colors: np.ndarray | None, tol: float, min_chain: int = MIN_CHAIN
) -> tuple[np.ndarray, np.ndarray | None]:
    """Thin the (M, 2, 3) segments for display: each chain of consecutive segments (one
    segment's end is the next one's start) is simplified by :func:`simplify_polyline`; with
    per-segment ``colors`` ((M, 3) uint8) a vertex where the colour changes by ``COLOR_STEP``
    or more is kept, and a kept segment takes the colour of the first one it replaces.
    Segments in no chain of ``min_chain`` or more are returned as they are. Returns
    (segments, colors)."""
    seg = np.asarray(segments)
    if seg.ndim != 3 or seg.shape[1:] != (2, 3):
        raise ValueError(f"segments must be (M, 2, 3), got {seg.shape}")
    m = len(seg)
    if colors is not None and np.shape(colors) != (m, 3):
        raise ValueError(f"colors must be ({m}, 3), got {np.shape(colors)}")
    if m < max(2, min_chain):
        return seg, colors
    joined = np.all(seg[1:, 0] == seg[:-1, 1], axis=1)  # segment i+1 continues segment i
    starts = np.flatnonzero(np.r_[True, ~joined])  # first segment of each chain
    ends = np.r_[starts[1:], m]  # one past its last segment
    long = ends - starts >= min_chain
    if not long.any():
        return seg, colors
    out_seg, out_col = [], []
    done = 0  # segments before this one are in the output
    for s, e in zip(starts[long], ends[long], strict=True):
        out_seg.append(seg[done:s])  # the shorter chains in between, as they are
        if colors is not None:
            out_col.append(np.asarray(colors[done:s]))
        verts = np.concatenate([seg[s:e, 0], seg[e - 1 : e, 1]])  # the chain's vertices
        keep = None
        if colors is not None:
            level = np.asarray(colors[s:e], np.int32) // COLOR_STEP
            change = np.any(level[1:] != level[:-1], axis=1)
            keep = np.r_[False, change, False]  # vertex k starts segment k of the chain
        idx = simplify_polyline(verts, tol, keep)
        out_seg.append(np.stack([verts[idx[:-1]], verts[idx[1:]]], axis=1))
        if colors is not None:
            out_col.append(np.asarray(colors[s:e])[idx[:-1]])
        done = e
    out_seg.append(seg[done:])
    if colors is not None:
        out_col.append(np.asarray(colors[done:]))
    thin = np.concatenate(out_seg).astype(seg.dtype, copy=False)
    return thin, (np.concatenate(out_col) if colors is not None else None)
