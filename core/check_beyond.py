"""The check's look beyond the curve's ends: a curve that stops short at an occluder.

A thread that runs under an instrument and out again is seen as two pieces. When the curve
keeps one and stops at the occluder, nothing else in the check sees it: the curve lies on the
thread pixels and covers most of them. The cue here: a piece of thread pixels no part of the
curve covers lies beyond an end of the curve, in the end's direction, across pixels that are
neither thread nor bare background (an occluder), and the same holds in both views with the
two pieces on the same rows (rectified views: the same piece of thread). The piece's far end
then bounds what the curve misses: its distance from the curve's end, at the end's depth.

Thread pixels are split into 8-connected pieces once per segmentation (``check_field.derived``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from threadrecon.core.check_field import derived

END_SAMPLES = 8  # curve samples over which an end's outward direction is taken
MIN_PIECE_PX = 12  # a piece spans at least this many px (smaller: segmentation speckle)
PIECE_SAMPLES = 64  # pixels per piece tested against the curve (evenly spread over it)
GAP_SAMPLES = 24  # samples along the gap between an end and a piece (occluder test)
MAX_TURN_COS = float(np.cos(np.radians(45.0)))  # the piece lies within 45 deg of the end's way


@dataclass(frozen=True)
class Beyond:
    """A piece of thread pixels beyond an end of the curve, in both views: ``end`` "start" or
    "end"; ``gap_px`` from the end to the piece and ``reach_px`` to its far side (left view,
    the smaller of the two views for ``reach_px``); ``missing`` the reach at the end's depth,
    in calib units (a lower bound of what the curve misses)."""

    end: str
    gap_px: float
    reach_px: float
    missing: float


def pieces(mask: np.ndarray) -> list[np.ndarray]:
    """The 8-connected pieces of a thread mask spanning at least MIN_PIECE_PX, each as (k, 2)
    float64 pixels (x, y) (cached with the mask)."""
    return derived((mask,), "pieces", lambda: _pieces(mask))


def _pieces(mask: np.ndarray) -> list[np.ndarray]:
    m8 = np.ascontiguousarray(mask).view(np.uint8)
    if not m8.any():
        return []
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m8, connectivity=8)
    big = [
        k for k in range(1, n)
        if max(stats[k, cv2.CC_STAT_WIDTH], stats[k, cv2.CC_STAT_HEIGHT]) >= MIN_PIECE_PX
    ]  # fmt: skip
    if not big:
        return []
    ys, xs = np.nonzero(np.isin(labels, big))
    lab = labels[ys, xs]
    order = np.argsort(lab, kind="stable")
    xy = np.column_stack([xs, ys]).astype(np.float64)[order]
    cuts = np.flatnonzero(np.diff(lab[order])) + 1
    out = np.split(xy, cuts)
    for a in out:
        a.setflags(write=False)
    return out


def beyond_ends(
    uv: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    ends: tuple[str, ...],
    depth: dict[str, float],
    f: float,
    cover_px: float,
    max_gap: float,
    bare: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    bare_share: float,
) -> list[Beyond]:
    """The pieces beyond the curve's ``ends`` ("start", "end") found in both views.

    ``uv``: the curve's (N, 2) projections (x, y) in the left and right view; ``masks``: P_L,
    P_R; ``depth``: each end's depth (calib units); ``cover_px``: a piece with a pixel this
    close to the curve is the curve's own; ``max_gap``: the longest gap (calib units, at the
    end's depth) across which a piece counts (the longest bridge the check accepts); ``bare``:
    ``bare(side, samples, end_a, end_b)`` flags samples over bare background (the check's test);
    a gap more than ``bare_share`` bare is no occluder."""
    found = []
    for end in ends:
        per_view = []
        for side in (0, 1):
            hit = _beyond(uv[side], pieces(masks[side]), end, cover_px,
                          max_gap * f / depth[end], side, bare, bare_share)  # fmt: skip
            if hit is None:
                break
            per_view.append(hit)
        if len(per_view) < 2:
            continue
        (gap_l, reach_l, rows_l), (_, reach_r, rows_r) = per_view
        lo, hi = max(rows_l[0], rows_r[0]), min(rows_l[1], rows_r[1])
        if hi - lo < 0.5 * min(rows_l[1] - rows_l[0], rows_r[1] - rows_r[0]):
            continue  # not on the same rows: not the same piece of thread
        reach = min(reach_l, reach_r)
        found.append(Beyond(end, gap_l, reach, reach * depth[end] / f))
    return found


def _beyond(
    uv: np.ndarray,
    parts: list[np.ndarray],
    end: str,
    cover_px: float,
    max_gap_px: float,
    side: int,
    bare: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    bare_share: float,
) -> tuple[float, float, tuple[float, float]] | None:
    """In one view: the nearest uncovered piece beyond ``end`` across an occluder, as (gap px,
    reach px to its far side, its (min, max) rows); None when there is none."""
    ok = np.all(np.isfinite(uv), axis=1)
    if ok.sum() < END_SAMPLES + 1 or not parts:
        return None
    curve = uv[ok]
    tip = curve[0] if end == "start" else curve[-1]
    back = curve[END_SAMPLES] if end == "start" else curve[-1 - END_SAMPLES]
    way = tip - back
    norm = float(np.linalg.norm(way))
    if norm == 0.0:
        return None
    way /= norm
    best = None
    for px in parts:
        rel = px - tip
        dist = np.hypot(rel[:, 0], rel[:, 1])
        k = int(np.argmin(dist))
        gap = float(dist[k])
        if gap > max_gap_px or gap <= cover_px or float(rel[k] @ way) < MAX_TURN_COS * gap:
            continue
        if best is not None and gap >= best[0]:
            continue
        if _covered(px, curve, cover_px):
            continue
        t = np.linspace(0.0, 1.0, GAP_SAMPLES + 2)[1:-1, None]
        gap_xy = tip + t * (px[k] - tip)
        if float(np.mean(bare(side, gap_xy, tip, px[k]))) > bare_share:
            continue  # bare background between: the thread would be seen there
        best = (gap, float(dist.max()), (float(px[:, 1].min()), float(px[:, 1].max())))
    return best


def _covered(px: np.ndarray, curve: np.ndarray, cover_px: float) -> bool:
    """Whether any of (up to PIECE_SAMPLES of) the piece's pixels lies within ``cover_px`` of a
    curve sample (the piece is the curve's own)."""
    step = max(1, len(px) // PIECE_SAMPLES)
    sub = px[::step]
    d2 = (sub[:, None, 0] - curve[None, :, 0]) ** 2 + (sub[:, None, 1] - curve[None, :, 1]) ** 2
    return bool(d2.min() <= cover_px**2)
