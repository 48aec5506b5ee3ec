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

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from threadrecon.core.check_field import derived, piece_index
from threadrecon.core.check_kernel import cone_pixels, covered_by

END_SAMPLES = 8  # curve samples over which an end's outward direction is taken
MIN_PIECE_PX = 12  # a piece spans at least this many px (smaller: segmentation speckle)
PIECE_SAMPLES = 64  # pixels per piece tested against the curve (evenly spread over it)
GAP_SAMPLES = 24  # samples along the gap between an end and a piece (occluder test)
FAN_MARGIN_PX = 4  # px around the cone's sampled outline (its arc bulges between samples)
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
    bx, by, bw, bh = cv2.boundingRect(m8)
    if bw == 0 or bh == 0:
        return []
    crop = np.ascontiguousarray(m8[by : by + bh, bx : bx + bw])
    n, labels, stats, _ = cv2.connectedComponentsWithStats(crop, connectivity=8)
    keep = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]) >= MIN_PIECE_PX
    keep[0] = False  # the background
    if not keep.any():
        return []
    ys, xs = np.nonzero(crop)
    lab = labels[ys, xs]
    sel = keep[lab]
    ys, xs, lab = ys[sel], xs[sel], lab[sel]
    order = np.argsort(lab, kind="stable")
    xy = np.column_stack([xs + bx, ys + by]).astype(np.float64)[order]
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
            fr = _end_frame(uv[side], end)
            radius = max_gap * f / depth[end]
            if fr is None or not len(_cone(*fr, masks[side], radius, MAX_TURN_COS, cover_px)[0]):
                break  # no uncovered thread pixel ahead of the end: no piece beyond it
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


def _end_frame(uv: np.ndarray, end: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The finite curve samples, the ``end``'s tip and its outward unit direction (over
    END_SAMPLES samples); None for a curve too short or without direction."""
    curve = uv if np.isfinite(uv).all() else uv[np.all(np.isfinite(uv), axis=1)]
    if len(curve) < END_SAMPLES + 1:
        return None
    tip = curve[0] if end == "start" else curve[-1]
    back = curve[END_SAMPLES] if end == "start" else curve[-1 - END_SAMPLES]
    way = tip - back
    norm = float(np.hypot(way[0], way[1]))
    if norm == 0.0:
        return None
    return curve, tip, way / norm


def _cone(
    curve: np.ndarray,
    tip: np.ndarray,
    way: np.ndarray,
    mask: np.ndarray,
    radius: float,
    cos: float,
    cover_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Thread pixels (k, 2) within ``radius`` of the tip, within acos(cos) of its way and more
    than ``cover_px`` along it, that no curve sample covers (farther than ``cover_px``), and
    their distance along the way: a cheap superset of any piece beyond the end."""
    if not math.isfinite(radius):
        raise ValueError(f"the search radius beyond an end is not finite ({radius})")
    m = mask if mask.flags.c_contiguous else np.ascontiguousarray(mask)
    return cone_pixels(
        np.ascontiguousarray(curve, dtype=np.float64),
        float(tip[0]),
        float(tip[1]),
        float(way[0]),
        float(way[1]),
        m.view(np.uint8),
        float(radius),
        float(cos),
        float(cover_px),
        FAN_MARGIN_PX,
    )  # compiled (check_kernel.cone_pixels): the box's pixels tested in one pass


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
    sub = np.ascontiguousarray(px[::step], dtype=np.float64)
    return bool(covered_by(sub, np.ascontiguousarray(curve, dtype=np.float64), cover_px**2).any())


CUT_PROBE_PX = 8  # px beyond an end where the view that stops is probed for an occluder
CONE_COS = float(np.cos(np.radians(30.0)))  # pixels within 30 deg of an end's way extend it


def extension(
    uv: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    end: str,
    reach_px: float,
    cover_px: float,
    min_px: float,
) -> tuple[float, float]:
    """Per view: how far (px) the thread pixels of the piece at the curve's ``end`` reach
    beyond the end's projection, not covered by the curve, along its outward direction
    (within 30 deg of it, up to ``reach_px``); 0 when nothing does. When neither view reaches
    beyond ``min_px``, the cheap bound (any thread pixel there) is returned without looking
    for the pieces."""
    out = []
    cones = []
    for side in (0, 1):
        fr = _end_frame(uv[side], end)
        if fr is None:
            return 0.0, 0.0
        px, along = _cone(*fr, masks[side], reach_px, CONE_COS, cover_px)
        cones.append((fr[1], px, along))
        out.append(float(along.max()) if along.size else 0.0)
    if max(out) <= min_px:
        return out[0], out[1]
    for side, (tip, px, along) in enumerate(cones):
        out[side] = 0.0
        index = piece_index(masks[side], lambda m=masks[side]: pieces(m))
        number = index.at(px)  # the piece of each cone pixel (_rows_in per piece, by lookup)
        for i in index.near(tip, 2.0):  # the pieces the end's projection lies on
            on = number == i
            if on.any():
                out[side] = max(out[side], float(along[on].max()))
    return out[0], out[1]


def cut_end(
    uv: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    end: str,
    reach_px: float,
    cut_px: float,
    cover_px: float,
    bare: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    bare_share: float,
    see_px: float = 0.0,
) -> CutEnd | None:
    """Whether the curve's free ``end`` is cut by an occluder in one view: one view sees the
    thread (``extension`` up to ``reach_px``) more than ``cut_px`` farther beyond it than the
    other, and in the other view the CUT_PROBE_PX px just beyond the end are not bare
    background (more than ``bare_share`` not bare). None when not. The view that sees farther
    is followed up to ``see_px`` (when larger) to find where its thread stops (``seen``)."""
    ext = extension(uv, masks, end, reach_px, cover_px, cut_px)
    if abs(ext[0] - ext[1]) <= cut_px:
        return None
    stop = 1 if ext[0] > ext[1] else 0  # the view where the thread stops
    fr = _end_frame(uv[stop], end)
    if fr is None:
        return None
    _, tip, way = fr
    if _bare_beyond(bare, stop, tip, way, 0.0, bare_share):
        return None  # bare background just beyond the end there: a free end
    far = 1 - stop
    seen = False  # the far view's thread stops inside the search, before bare background
    fr_far = _end_frame(uv[far], end)
    reach_far = ext[far]
    if reach_far + 2.0 > reach_px and see_px > reach_px:  # follow it further in that view
        reach_far = extension(uv, masks, end, see_px, cover_px, cut_px)[far]
        ext = (reach_far, ext[1]) if far == 0 else (ext[0], reach_far)
    if fr_far is not None and reach_far + 2.0 <= max(reach_px, see_px):  # stops in the search
        _, tip_far, way_far = fr_far
        seen = _bare_beyond(bare, far, tip_far, way_far, reach_far, bare_share)
    return CutEnd("left" if stop == 1 else "right", ext, seen)


@dataclass(frozen=True)
class CutEnd:
    """An end cut by an occluder in one view: ``view`` is the one that sees farther ("left" or
    "right"), ``ext`` both views' extensions beyond the end (px, left and right), ``seen``
    whether that view shows the thread's own free end there (bare background just beyond
    its extension, inside the search): then the thread stops there, and the curve misses the
    extension only, not an unknown length hidden under the occluder."""

    view: str
    ext: tuple[float, float]
    seen: bool


def _bare_beyond(
    bare: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    side: int,
    tip: np.ndarray,
    way: np.ndarray,
    offset: float,
    bare_share: float,
) -> bool:
    """Whether the CUT_PROBE_PX px beyond ``offset`` px past ``tip`` along ``way`` look like
    bare background in view ``side`` (more than ``bare_share`` of them)."""
    at = tip + offset * way
    probe = at + np.arange(2.0, 2.0 + CUT_PROBE_PX)[:, None] * way
    return float(np.mean(bare(side, probe, at, at))) > bare_share
