"""The check's look for a mark on the tissue: a curve that moves with the surface beside it.

Vessels and fibres are marks on the tissue: in the other view they appear at the disparity of
the tissue texture right next to them. A thread is a body of its own: where it runs in front of
the tissue, the surface beside it lies behind it (``core/segment_surface``, the raw
segmentation's own test of each piece, asks the same question of the pieces it can decide). A
piece that test leaves open (too few 64 px blocks, e.g. a short piece at the image border)
can be chosen when the thread itself is lost; its curve is then measured here.

The cue: along the curve, in both views, the square patch just beside it on each side
(``check_beyond.surface_ahead``: its thread pixels left out, matched along its row of the
other view) measures the surface there. A patch at the curve's own disparity (within
``same_px``) moves with it; one farther off does not (behind: the tissue under a thread;
in front: an occluder); one the pair cannot tell abstains. The curve is a mark when, of the
first ``measures`` patches that measure a surface (taken spread along the curve, alternately
in the two views and on the two sides; at most LOOKS_PER_MEASURE times as many looked at),
at least ``share`` move with it.

Limit: a thread resting on the tissue along its whole visible length moves with it too and is
taken for a mark (as by the segmentation's test).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from threadrecon.core.check_beyond import (
    AHEAD_HALF_PX,
    AHEAD_STEP_PX,
    patch_t,
    surface_ahead,
    untold_patches,
)
from threadrecon.core.numeric import arc_px, row_norms

LOOKS_PER_MEASURE = 4  # patches looked at per patch needed (most abstain on smooth tissue or a
# plain background, where the pair cannot tell): the work is bounded
BESIDE_OFFSET_PX = 2.0  # px past the curve's axis where the patch's clearance starts: its near
# side 4 px from the axis, its centre 10 px (a 6 px thread and its blurred edge are masked out)


@dataclass(frozen=True)
class Mark:
    """Patches beside the curve that measured a surface: ``measured`` of them, ``along`` at
    the curve's own disparity (moving with it)."""

    measured: int
    along: int


@functools.lru_cache(maxsize=256)
def _spread(n: int) -> tuple[int, ...]:
    """0 .. n-1 in an order that spreads every prefix over the range (bit-reversed ranks)."""
    if n <= 1:
        return tuple(range(n))
    bits = max(int(math.ceil(math.log2(n))), 1)
    rev = (int(f"{i:0{bits}b}"[::-1], 2) for i in range(1 << bits))
    return tuple(i for i in rev if i < n)


def moves_with_surface(
    uvs: tuple[np.ndarray, np.ndarray],
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    disp: np.ndarray,
    same_px: float,
    measures: int,
    share: float,
) -> Mark:
    """How the surface just beside the curve moves against it (module docstring).

    ``uvs``: (N, 2) left and right projections of the curve, px; ``greys``, ``masks``: the
    views' grey levels and thread masks (H, W); ``disp``: (N,) the curve's disparity, px.
    Positions AHEAD_STEP_PX apart along each projection (a patch's width); the patches are
    measured spread along the curve, both views and both sides in turn, until ``measures`` of
    them measured a surface, fewer than ``share`` of ``measures`` can still move with it, or
    LOOKS_PER_MEASURE ``measures`` patches were looked at."""
    looks = (LOOKS_PER_MEASURE * measures + 1) // 2  # positions: two patches a position
    per_view: list[tuple[int, ...]] = []
    for uv in uvs:
        s = arc_px(row_norms(uv[1:] - uv[:-1]))
        if len(uv) < 3 or not s[-1] >= AHEAD_STEP_PX:
            per_view.append(())
            continue
        at = np.arange(0.5 * AHEAD_STEP_PX, s[-1], AHEAD_STEP_PX)
        idx = np.clip(np.searchsorted(s, at), 1, len(uv) - 2).tolist()
        per_view.append(tuple(idx[j] for j in _spread(len(idx))[:looks]))  # a view's first
    cand = [
        (side, v[k])
        for k in range(max(len(v) for v in per_view))
        for side, v in enumerate(per_view)
        if k < len(v)
    ][:looks]
    need = int(math.ceil(share * measures))
    # each position's tangent, point and disparity, a view's positions at once
    at: dict[tuple[int, int], tuple[list[float], list[float], float]] = {}
    for side in (0, 1):
        ii = np.array([i for v, i in cand if v == side], dtype=np.intp)
        if len(ii):
            uv = uvs[side]
            rows = zip(
                (uv[ii + 1] - uv[ii - 1]).tolist(), uv[ii].tolist(), disp[ii].tolist(), strict=True
            )
            at.update(((side, i), r) for i, r in zip(ii.tolist(), rows, strict=True))
    # the patches in the order looked at: view, point index, unit normal (x, y), disparity
    patches: list[tuple[int, int, float, float, float]] = []
    tips: list[list[float]] = []
    for side, i in cand:
        (tx, ty), tip, d_i = at[side, i]
        norm = math.hypot(tx, ty)
        if not (math.isfinite(norm) and norm > 0.0 and math.isfinite(d_i)):
            continue
        for sign in (1.0, -1.0):
            patches.append((side, i, -sign * ty / norm, sign * tx / norm, d_i))
            tips.append(tip)
    untold = _untold(patches, tips, greys, masks)
    measured = along = 0
    for (side, i, nx, ny, d_i), skip in zip(patches, untold, strict=True):
        if skip:
            continue  # surely no measure (mostly thread, untextured): not matched
        normal = np.array([nx, ny])
        d, _ = surface_ahead(greys, masks, side, uvs[side][i], normal, d_i, BESIDE_OFFSET_PX)
        if d is None:
            continue
        measured += 1
        along += abs(d) <= same_px
        if measured - along > measures - need or measured >= measures:
            return Mark(measured, along)  # decided: the share is reached or cannot be
    return Mark(measured, along)


def _untold(
    patches: list[tuple[int, int, float, float, float]],
    tips: list[list[float]],
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
) -> list[bool]:
    """For each patch (``moves_with_surface``'s, beside the point ``tips``), True where
    ``surface_ahead`` surely measures nothing (``check_beyond.untold_patches``, every patch
    at once); a patch off the image is left to ``surface_ahead``, which measures nothing there
    either."""
    if not patches:
        return []
    p = np.array(patches)
    views, ways, disp = p[:, 0].astype(np.intp), p[:, 2:4], p[:, 4]
    # surface_ahead's centre, elementwise (the same float operations, rounded half to even)
    c = np.array(tips) + patch_t(BESIDE_OFFSET_PX) * ways
    finite = np.isfinite(c).all(axis=1) & np.isfinite(disp)
    c = np.rint(np.where(finite[:, None], c, 0.0)).astype(np.intp)
    r = AHEAD_HALF_PX
    h, w = np.array([g.shape for g in greys])[views].T
    ok = finite & (disp > 0) & (c.min(axis=1) - r >= 0) & (c[:, 0] + r < w) & (c[:, 1] + r < h)
    untold = np.zeros(len(p), dtype=bool)
    if ok.any():
        untold[ok] = untold_patches(greys, masks, views[ok], c[ok, 0], c[ok, 1])
    return untold.tolist()
