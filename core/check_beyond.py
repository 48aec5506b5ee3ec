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

import contextlib
import math
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from threadrecon.core.check_field import derived, derived_entry, piece_index
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
    scores: Callable[[], tuple[np.ndarray | None, np.ndarray | None]] | None = None,
    disparity: dict[str, float] | None = None,
) -> list[Beyond]:
    """The pieces beyond the curve's ``ends`` ("start", "end") found in both views.

    ``uv``: the curve's (N, 2) projections (x, y) in the left and right view; ``masks``: P_L,
    P_R; ``depth``: each end's depth (calib units); ``cover_px``: a piece with a pixel this
    close to the curve is the curve's own; ``max_gap``: the longest gap (calib units, at the
    end's depth) across which a piece counts (the longest bridge the check accepts); ``bare``:
    ``bare(side, samples, end_a, end_b)`` flags samples over bare background (the check's test);
    a gap more than ``bare_share`` bare is no occluder.

    ``scores`` (CheckParams.beyond_one_view; None: not looked at) gives the segmentation's
    thread scores per view (read only when needed: they are computed on their first read) and ``disparity`` (each end's, px): a piece found in one view only
    counts in both when the other view's thread score bears it out (``_borne_out``: the
    other view's segmentation dropped a stretch its score still shows); its reach is then
    the one view's."""
    found = []
    for end in ends:
        per_view: list[tuple[float, float, tuple[float, float], np.ndarray] | None] = []
        for side in (0, 1):
            fr = _end_frame(uv[side], end)
            radius = max_gap * f / depth[end]
            hit = None
            if fr is not None and len(_cone(*fr, masks[side], radius, MAX_TURN_COS, cover_px)[0]):
                hit = _beyond(uv[side], pieces(masks[side]), end, cover_px, radius, side, bare,
                              bare_share)  # fmt: skip
            if hit is None and scores is None:
                break  # no uncovered thread pixel ahead of the end: no piece beyond it
            per_view.append(hit)
        if (
            scores is not None
            and len(per_view) == 2
            and (per_view[0] is None) != (per_view[1] is None)
        ):
            side = 0 if per_view[0] is not None else 1
            hit = per_view[side]
            maps = scores()
            assert hit is not None and disparity is not None
            if (
                maps[0] is not None
                and maps[1] is not None
                and _borne_out(hit[3], side, (maps[0], maps[1]), disparity[end])
            ):
                per_view[1 - side] = hit
        if len(per_view) < 2 or per_view[0] is None or per_view[1] is None:
            continue
        (gap_l, reach_l, rows_l, _), (_, reach_r, rows_r, _) = per_view[0], per_view[1]
        lo, hi = max(rows_l[0], rows_r[0]), min(rows_l[1], rows_r[1])
        if hi - lo < 0.5 * min(rows_l[1] - rows_l[0], rows_r[1] - rows_r[0]):
            continue  # not on the same rows: not the same piece of thread
        reach = min(reach_l, reach_r)
        found.append(Beyond(end, gap_l, reach, reach * depth[end] / f))
    return found


BORNE_LEVEL = 0.5  # the other view's thread score (its line map) at which a pixel shows thread
BORNE_SHARE = 0.8  # of a one-view piece's pixels the other view's score must show at one shift
BORNE_SHIFTS_PX = (-12.0, -4.0, 4.0, 12.0)  # shifts off the end's disparity tried (each +-4 px)


def _borne_out(
    px: np.ndarray, side: int, scores: tuple[np.ndarray, np.ndarray], disparity: float
) -> bool:
    """Whether the thread score of the view other than ``side`` shows the piece ``px`` (k, 2)
    of view ``side``: at one shift within 16 px of the end's ``disparity`` (the piece may lie
    at another depth than the end, across the occluder), at least BORNE_SHARE of its pixels
    (up to PIECE_SAMPLES of them) fall where the other view's line map (``_line_maps``: the
    best within 1 px, the right view's also within FOLLOW_DISPARITY_PX along the row) is at
    least BORNE_LEVEL."""
    if not (math.isfinite(disparity) and disparity > 0):
        return False
    maps = derived(scores, "thread line", lambda: _line_maps(scores))
    step = max(1, len(px) // PIECE_SAMPLES)
    sub = px[::step]
    sign = -1.0 if side == 0 else 1.0  # left x is seen at x - d in the right view
    other = maps[1] if side == 0 else maps[0]
    for off in BORNE_SHIFTS_PX:
        d = disparity + off
        if d <= 0:
            continue
        if side == 1:  # the left map is only 1 px wide: take the best over the row window
            vals = np.max(
                [_bilinear(other, sub + [sign * (d + k), 0.0]) for k in range(-4, 5, 2)], axis=0
            )
        else:
            vals = _bilinear(other, sub + [sign * d, 0.0])
        if float(np.mean(vals >= BORNE_LEVEL)) >= BORNE_SHARE:
            return True
    return False


_FRAMES = threading.local()  # .memo: one check run's end frames (end_frames_kept), or None


@contextlib.contextmanager
def end_frames_kept() -> Iterator[None]:
    """Within this block (one run of the check, whose curve projections are not changed after
    they are made), ``_end_frame`` keeps its result for each projection object and end: the
    rules that read a free end's tip and way (the extension, the cut, the occluder, the pieces
    beyond) take it ~6 times a run from two or four distinct (view, end) pairs. Per thread
    (the server runs pipelines in several); the results are dropped at the block's end."""
    before = getattr(_FRAMES, "memo", None)
    _FRAMES.memo = {}
    try:
        yield
    finally:
        _FRAMES.memo = before


def _end_frame(uv: np.ndarray, end: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``_end_frame_of(uv, end)``, kept by the object ``uv`` inside ``end_frames_kept`` (the
    same result: the function of the same array; the entry holds ``uv``, so its id is not
    reused while kept)."""
    memo = getattr(_FRAMES, "memo", None)
    if memo is None:
        return _end_frame_of(uv, end)
    hit = memo.get((id(uv), end))
    if hit is not None and hit[0] is uv:
        return hit[1]
    fr = _end_frame_of(uv, end)
    memo[(id(uv), end)] = (uv, fr)
    return fr


def _end_frame_of(uv: np.ndarray, end: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The finite curve samples, the ``end``'s tip and its outward unit direction (over
    END_SAMPLES samples); None for a curve too short or without direction.

    A curve whose last samples turn back on themselves (a hook: a spline's end overshoots its
    last observation and returns) reaches farthest before its last sample: the tip is the
    sample of the last END_SAMPLES + 1 that lies farthest along the curve's way just before
    them, and the direction is taken over the END_SAMPLES samples behind that tip. The thread
    ends where the curve reaches, and what lies beyond the end is beyond that point, not back
    over the curve's own thread."""
    curve = uv if np.isfinite(uv).all() else uv[np.isfinite(uv).all(axis=1)]
    if len(curve) < END_SAMPLES + 1:
        return None
    seq = curve if end == "start" else curve[::-1]  # seq[0] is the end's sample
    j = 0
    if len(seq) > 2 * END_SAMPLES:
        # the samples 0, 1, END_SAMPLES and 2 END_SAMPLES, read by slices (a fancy index of
        # four rows costs several times as much)
        (x0, y0), (x1, y1) = seq[:2].tolist()
        (xe, ye), (xb, yb) = seq[END_SAMPLES : 2 * END_SAMPLES + 1 : END_SAMPLES].tolist()
        bx, by = xe - xb, ye - yb  # the way into the end's window
        if (x0 - x1) * bx + (y0 - y1) * by < 0.0:  # the last step turns back: a hook
            j = int(np.argmax((seq[: END_SAMPLES + 1] - seq[END_SAMPLES]) @ np.array([bx, by])))
    tip, back = seq[j], seq[j + END_SAMPLES]
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
    h, w = mask.shape
    tx, ty = float(tip[0]), float(tip[1])
    if not (-radius <= tx <= w + radius and -radius <= ty <= h + radius):
        return np.empty((0, 2)), np.empty(0)  # the fan misses the image (a diverged curve)
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
) -> tuple[float, float, tuple[float, float], np.ndarray] | None:
    """In one view: the nearest uncovered piece beyond ``end`` across an occluder, as (gap px,
    reach px to its far side, its (min, max) rows, its pixels); None when there is none."""
    fr = _end_frame(uv, end)
    if fr is None or not parts:
        return None
    curve, tip, way = fr
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
        best = (gap, float(dist.max()), (float(px[:, 1].min()), float(px[:, 1].max())), px)
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
    ext, _ = extension_far(uv, masks, end, reach_px, cover_px, min_px)
    return ext


def extension_far(
    uv: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    end: str,
    reach_px: float,
    cover_px: float,
    min_px: float,
) -> tuple[tuple[float, float], tuple[np.ndarray | None, np.ndarray | None]]:
    """``extension`` and, per view, the farthest such pixel (x, y) (None when no piece at the
    end reaches beyond it, or only the cheap bound was taken)."""
    out = []
    cones = []
    for side in (0, 1):
        fr = _end_frame(uv[side], end)
        if fr is None:
            return (0.0, 0.0), (None, None)
        px, along = _cone(*fr, masks[side], reach_px, CONE_COS, cover_px)
        cones.append((fr[1], px, along))
        out.append(float(along.max()) if along.size else 0.0)
    if max(out) <= min_px:
        return (out[0], out[1]), (None, None)
    far: list[np.ndarray | None] = [None, None]
    for side, (tip, px, along) in enumerate(cones):
        out[side] = 0.0
        index = piece_index(masks[side], lambda m=masks[side]: pieces(m))
        number = index.at(px)  # the piece of each cone pixel (_rows_in per piece, by lookup)
        for i in index.near(tip, 2.0):  # the pieces the end's projection lies on
            on = np.flatnonzero(number == i)
            if on.size and float(along[on].max()) > out[side]:
                k = on[int(np.argmax(along[on]))]
                out[side], far[side] = float(along[k]), px[k]
    return (out[0], out[1]), (far[0], far[1])


def left_behind(
    uv: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    at: int,
    reach_px: float,
    cover_px: float,
    near_px: float,
) -> tuple[float, float]:
    """Per view: the length (px, a path along the pixels) of the thread pixels that branch off
    where the curve leaves the thread at its sample ``at`` (a bridge's end): the pixels of
    the piece that sample lies on, within ``reach_px`` of it, farther than
    ``cover_px`` from every curve sample and 8-connected among themselves to the sample's
    projection (the first within ``cover_px`` + ``near_px`` of it). The sample is observed: its
    projection lies within ``near_px`` of a thread pixel. 0 when there are none.

    The thread a curve leaves for a bridge passes out of sight there. Thread pixels that go
    on from that point, whichever way they turn (a branch can turn back as sharply as the
    curve turns onto its bridge), and that no part of the curve picks up again, are thread the
    curve left: the path along them from that point bounds how much of it the curve does not
    hold (the thread runs at least that far past where the curve leaves it)."""
    out = [0.0, 0.0]
    for side in (0, 1):
        full = uv[side]
        curve = full[np.isfinite(full).all(axis=1)]
        tip = full[at]
        if not np.isfinite(tip).all() or len(curve) < 2:
            return (0.0, 0.0)
        mask = masks[side]
        parts = pieces(mask)
        index = piece_index(mask, lambda m=mask: pieces(m))
        near = index.near(tip, near_px)  # the pieces the sample's projection lies on
        if not near:
            return (0.0, 0.0)
        px = np.concatenate([parts[i] for i in near])
        rel = px - tip
        px = px[np.hypot(rel[:, 0], rel[:, 1]) <= reach_px]
        # only the samples within reach_px + cover_px of the sample can cover these pixels
        d = curve - tip
        near_curve = curve[np.hypot(d[:, 0], d[:, 1]) <= reach_px + cover_px]
        px = px[~covered_by(px, np.ascontiguousarray(near_curve, dtype=np.float64), cover_px**2)]
        if not len(px):
            return (0.0, 0.0)
        # the uncovered pixels 8-connected to the sample's projection (one small raster)
        x0, y0 = px.min(axis=0).astype(int)
        x1, y1 = px.max(axis=0).astype(int)
        box = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
        ix, iy = px[:, 0].astype(int) - x0, px[:, 1].astype(int) - y0
        box[iy, ix] = 1
        _, labels = cv2.connectedComponents(box, connectivity=8)
        lab = labels[iy, ix]
        touch = np.hypot(px[:, 0] - tip[0], px[:, 1] - tip[1]) <= cover_px + near_px
        if not touch.any():
            return (0.0, 0.0)
        keep = np.isin(lab, np.unique(lab[touch]))
        out[side] = _geodesic_reach(ix[keep], iy[keep], touch[keep])
        if out[side] == 0.0:
            return (0.0, 0.0)
    return (out[0], out[1])


def _geodesic_reach(ix: np.ndarray, iy: np.ndarray, start: np.ndarray) -> float:
    """The longest shortest path (px, 8-connected steps of 1 and sqrt 2) from the pixels
    ``start`` to any pixel of the set (ix, iy) (integer columns and rows): the length of
    thread a branch of pixels holds (a path along it, not a chord across it)."""
    n = len(ix)
    if n < 2:
        return 0.0
    box = np.full((int(iy.max()) + 2, int(ix.max()) + 2), -1, np.int64)
    box[iy, ix] = np.arange(n)
    rows, cols, wts = [], [], []
    for dy, dx, w in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, math.sqrt(2.0)), (1, -1, math.sqrt(2.0))):
        j = box[iy + dy, ix + dx]  # index -1 wraps to the padding column: no pixel there
        ok = j >= 0
        rows.append(np.flatnonzero(ok))
        cols.append(j[ok])
        wts.append(np.full(int(ok.sum()), w))
    graph = csr_matrix(
        (np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    dist = dijkstra(graph, directed=False, indices=np.flatnonzero(start), min_only=True)
    dist = dist[np.isfinite(dist)]
    return float(dist.max()) if dist.size else 0.0


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
    known: tuple[float, float] | None = None,
    front_past: Callable[[int], bool] | None = None,
    tip_seen: bool = False,
    tip_front: Callable[[int, np.ndarray, np.ndarray], bool] | None = None,
) -> CutEnd | None:
    """Whether the curve's free ``end`` is cut by an occluder in one view: one view sees the
    thread (``extension`` up to ``reach_px``) more than ``cut_px`` farther beyond it than the
    other, and in the other view the CUT_PROBE_PX px just beyond the end are not bare
    background (more than ``bare_share`` not bare). None when not. The view that sees farther
    is followed up to ``see_px`` (when larger) to find where its thread stops (``seen``).
    ``known``: ``extension`` with these arguments, when the caller has it. ``front_past``:
    whether stereo measures a surface in front of the end just past it in the given view (an
    occluder); where it does, pixels past the end that look like bare background by their
    grey (an instrument's shaded side can have the tissue's grey) do not make the end free.
    ``tip_seen``: where bare background is not found straight along the end's way past the far
    view's extension, it is looked for past that view's own thread tip (``_own_tip_bare``);
    ``tip_front(side, at, way)``: whether stereo measures a surface in front of the end just
    past ``at`` along ``way`` in view ``side`` (an occluder at the tip: not seen)."""
    ext = extension(uv, masks, end, reach_px, cover_px, cut_px) if known is None else known
    if abs(ext[0] - ext[1]) <= cut_px:
        return None
    stop = 1 if ext[0] > ext[1] else 0  # the view where the thread stops
    fr = _end_frame(uv[stop], end)
    if fr is None:
        return None
    _, tip, way = fr
    if _bare_beyond(bare, stop, tip, way, 0.0, bare_share) and not (
        front_past is not None and front_past(stop)
    ):
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
        if not seen and tip_seen:
            search = max(reach_px, see_px)
            exts, fars = extension_far(uv, masks, end, search, cover_px, cut_px)
            seen = exts[far] + 2.0 <= search and _own_tip_bare(
                masks[far], fars[far], fr_far[0], tip_far, exts[far], cover_px, bare, far,
                bare_share, tip_front,
            )  # fmt: skip
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


TIP_SLACK_PX = 3.0  # px past the extension's reach that an uncovered pixel of its piece may lie
TIP_FAN = tuple(np.radians([0.0, 22.5, -22.5, 45.0, -45.0]))  # rays probed past a seen tip


def _own_tip_bare(
    mask: np.ndarray,
    far_px: np.ndarray | None,
    curve: np.ndarray,
    tip: np.ndarray,
    reach: float,
    cover_px: float,
    bare: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    side: int,
    bare_share: float,
    front: Callable[[int, np.ndarray, np.ndarray], bool] | None = None,
) -> bool:
    """Whether the far view's thread past a cut end stops at its own tip over bare background:
    the piece holding the extension's farthest pixel ``far_px`` has no pixel uncovered by the
    ``curve`` (farther than ``cover_px``) farther than ``reach`` + TIP_SLACK_PX from the end's
    ``tip`` (the piece goes nowhere else: a thread bending out of the end's cone, or another
    strand, leaves it there), the CUT_PROBE_PX px past ``far_px`` look like bare background
    along the chord from ``tip`` to it and along the rays 22.5 and 45 deg either side (a
    thread whose tip touches an occluder has it on one of them), and stereo (``front``) does
    not measure a surface in front of the end just past it. The straight way past the end
    (``cut_end``'s first probe) misses a tip that bends off it and ends beside an occluder."""
    if far_px is None:
        return False
    parts = pieces(mask)
    number = int(piece_index(mask, lambda: parts).at(far_px[None, :])[0])
    if number < 0:
        return False
    px = parts[number]
    px = px[~covered_by(px, np.ascontiguousarray(curve, dtype=np.float64), cover_px**2)]
    if not px.size or float(np.hypot(*(px - tip).T).max()) > reach + TIP_SLACK_PX:
        return False
    way = far_px - tip
    norm = float(np.hypot(way[0], way[1]))
    if norm < 1.0:
        return False
    way = way / norm
    if not all(_bare_beyond(bare, side, far_px, _turned(way, t), 0.0, bare_share) for t in TIP_FAN):
        return False
    return front is None or not front(side, far_px, way)


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


AHEAD_HALF_PX = 6  # half-size of the square patch just beyond an end matched across the views
AHEAD_DEPTH = 4.0  # the search reaches surfaces down to 1 / AHEAD_DEPTH of the end's depth
AHEAD_FAR_PX = 4  # shifts this far from the best one tell whether it is distinct
AHEAD_LEVELS = 4.0  # grey levels: the sensor noise floor (texture and distinctness)
AHEAD_SHARE = 0.5  # at least this share of the patch is not thread (the surface is seen)
AHEAD_EDGE_PX = 2  # px around the thread mask that belong to the thread (its blurred edge)
_EDGE_KERNEL = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * AHEAD_EDGE_PX + 1,) * 2)


def surface_ahead(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    tip: np.ndarray,
    way: np.ndarray,
    disparity: float,
    offset: float = 0.0,
) -> tuple[float | None, float | None]:
    """How much nearer (px of disparity, > 0: in front of the end) the surface just beyond an
    end lies, measured by stereo, and the patch's mean grey (its thread pixels left out) when
    it is untextured (None otherwise): the square patch of view ``side`` (2 AHEAD_HALF_PX + 1
    px) whose near side lies 2 px beyond ``offset`` px past ``tip`` along ``way``, its thread
    pixels (``masks``, grown by AHEAD_EDGE_PX: the thread's blurred edge) left out, is matched
    along its row of the other view (rectified), over disparities 0 (far away) to AHEAD_DEPTH
    times the end's ``disparity`` (a surface at a quarter of the end's depth). The disparity is
    None when the pair cannot tell: the patch leaves a view, is mostly thread, is untextured
    (standard deviation under AHEAD_LEVELS), or its best shift is not distinct (the median cost
    AHEAD_FAR_PX or more away is not AHEAD_LEVELS higher: e.g. a shaft along the rows).

    An occluder's silhouette moves with the occluder's disparity, so a patch over an occluder
    or its edge matches in front of the thread; the tissue the thread lies on matches at the
    end's depth or behind it."""
    h, w = greys[side].shape
    r = AHEAD_HALF_PX
    t = patch_t(offset)
    cx, cy = float(tip[0]) + t * float(way[0]), float(tip[1]) + t * float(way[1])
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(disparity)):
        return None, None
    cx, cy = int(round(cx)), int(round(cy))
    if disparity <= 0 or cx - r < 0 or cy - r < 0 or cx + r >= w or cy + r >= h:
        return None, None
    # the rest depends on the segmentation, the patch's pixel and the search's width only:
    # kept with the segmentation for the next run of the check (most ends stay on their pixel)
    d_hi = int(math.ceil(AHEAD_DEPTH * disparity))
    d_best, grey = derived_entry(
        (*greys, *masks), "ahead matches", (side, cx, cy, d_hi),
        lambda: _match_ahead(greys, masks, side, cx, cy, d_hi),
    )  # fmt: skip
    return (None, grey) if d_best is None else (float(d_best - disparity), None)


_UNTEXTURED_MARGIN = 0.5  # grey levels squared: a variance this far under AHEAD_LEVELS**2 is
# untextured whatever the order of the sums (cv2's sums in double and these differ by far
# less); a patch nearer the limit is left to _match_ahead's own test


def untold_patches(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    sides: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
) -> np.ndarray:
    """(K,) bool: True where ``_match_ahead`` surely measures no disparity for the patch of
    view ``sides`` centred on pixel (``cx``, ``cy``) ((K,) int each, inside the image as
    ``surface_ahead``'s): the patch is mostly thread, or untextured by a margin
    (_UNTEXTURED_MARGIN). The same tests, for many patches at once and before any match (on a
    plain background every patch is untextured); False: the patch is to be matched (also where
    its grown mask would leave the image)."""
    r, e = AHEAD_HALF_PX, AHEAD_EDGE_PX
    n = 2 * (r + e) + 1
    untold = np.zeros(len(cx), dtype=bool)
    wins, patches, where = [], [], []
    for side in (0, 1):
        h, w = masks[side].shape
        full = (sides == side) & (cx >= r + e) & (cy >= r + e) & (cx < w - r - e)
        full &= cy < h - r - e
        if full.any():
            x, y = cx[full], cy[full]
            wins.append(_windows(masks[side].view(np.uint8), n)[y - r - e, x - r - e])
            patches.append(_windows(greys[side], 2 * r + 1)[y - r, x - r])
            where.append(np.flatnonzero(full))
    if not where:
        return untold
    win = np.concatenate(wins) if len(wins) > 1 else wins[0]
    k = len(win)
    # each patch's mask grown by e (_thread_and_edges, as it reads the mask: the same pixels):
    # the windows e px wider stacked in one image, a patch's rows reaching only its own window
    grown = cv2.dilate(win.reshape(k * n, n), _EDGE_KERNEL).reshape(k, n, n)
    seen = grown[:, e : e + 2 * r + 1, e : e + 2 * r + 1] == 0
    n_seen = np.count_nonzero(seen.reshape(k, -1), axis=1)
    g = np.concatenate(patches) if len(patches) > 1 else patches[0]
    g = g.astype(np.float64) * seen
    m = np.maximum(n_seen, 1)
    mean = np.einsum("kij->k", g) / m
    var = np.einsum("kij,kij->k", g, g) / m - mean * mean
    untold[np.concatenate(where)] = (n_seen < AHEAD_SHARE * (2 * r + 1) ** 2) | (
        var < AHEAD_LEVELS**2 - _UNTEXTURED_MARGIN
    )
    return untold


def _windows(image: np.ndarray, n: int) -> np.ndarray:
    """(H - n + 1, W - n + 1, n, n) view of every n x n window of the (H, W) ``image``, indexed
    by its top left pixel (row, column): no copy."""
    shape = (image.shape[0] - n + 1, image.shape[1] - n + 1, n, n)
    if image.flags.c_contiguous:  # the view made directly (as_strided costs ~10 us a call)
        view = np.ndarray(shape, image.dtype, image, 0, image.strides * 2)
        view.flags.writeable = False
        return view
    return np.lib.stride_tricks.as_strided(image, shape, image.strides * 2, writeable=False)


def _match_ahead(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    cx: int,
    cy: int,
    d_hi: int,
) -> tuple[int | None, float | None]:
    """``surface_ahead``'s match of the patch centred on pixel (cx, cy) of view ``side``
    (inside the image) over disparities 0 .. ``d_hi``: the best disparity (None when the pair
    cannot tell), and the patch's mean grey when it is untextured."""
    grey_a, grey_b = greys[side], greys[1 - side]
    w = grey_a.shape[1]
    r = AHEAD_HALF_PX
    rows, cols = slice(cy - r, cy + r + 1), slice(cx - r, cx + r + 1)
    thread = _thread_and_edges(masks[side], cy, cx, r)
    n_thread = int(np.count_nonzero(thread))
    n_seen = thread.size - n_thread
    if n_seen < AHEAD_SHARE * thread.size:
        return None, None
    patch = np.ascontiguousarray(grey_a[rows, cols], dtype=np.float32)
    seen = None if n_thread == 0 else (~thread).astype(np.uint8)
    mean, sd = cv2.meanStdDev(patch, mask=seen)
    if float(sd[0, 0]) <= AHEAD_LEVELS:
        return None, float(mean[0, 0])  # untextured: the pair cannot tell its depth
    # the other view sees a point of disparity d at x - d (left to right) or x + d
    x0, x1 = (cx - d_hi - r, cx + r + 1) if side == 0 else (cx - r, cx + d_hi + r + 1)
    x0, x1 = max(x0, 0), min(x1, w)
    if x1 - x0 < 2 * r + 1 + 2 * AHEAD_FAR_PX:
        return None, None
    strip = np.ascontiguousarray(grey_b[rows, x0:x1], dtype=np.float32)
    if seen is None:  # the mask's slower path only where thread pixels are left out
        cost = cv2.matchTemplate(strip, patch, cv2.TM_SQDIFF)[0]
    else:
        cost = cv2.matchTemplate(strip, patch, cv2.TM_SQDIFF, mask=seen.astype(np.float32))[0]
    rms = np.sqrt(np.maximum(cost, 0.0) * (1.0 / n_seen))
    k = int(np.argmin(rms))
    far = np.concatenate((rms[: max(k - AHEAD_FAR_PX + 1, 0)], rms[k + AHEAD_FAR_PX :]))
    if (
        far.size == 0
        or float(np.partition(far, far.size // 2)[far.size // 2]) < rms[k] + AHEAD_LEVELS
    ):
        return None, None  # no distinct match (median cost of the far shifts): nothing measured
    return ((cx - (x0 + k + r)) if side == 0 else (x0 + k + r - cx)), None


def _thread_and_edges(mask: np.ndarray, cy: int, cx: int, r: int) -> np.ndarray:
    """The (2r+1, 2r+1) patch of ``mask`` around (cx, cy) grown by AHEAD_EDGE_PX: the
    thread's blurred edge outside its mask is the thread's, not the surface's texture (on a
    plain background it is the only texture, and another strand of the thread beside the end
    would otherwise be measured as a surface in front of it)."""
    e = AHEAD_EDGE_PX
    h, w = mask.shape
    y0, y1, x0, x1 = (
        max(cy - r - e, 0),
        min(cy + r + e + 1, h),
        max(cx - r - e, 0),
        min(cx + r + e + 1, w),
    )
    crop = mask[y0:y1, x0:x1].view(np.uint8)  # cv2 reads the rows in place: no copy first
    if not crop.any():
        return np.zeros((2 * r + 1, 2 * r + 1), dtype=bool)
    grown = cv2.dilate(crop, _EDGE_KERNEL)
    patch = grown[cy - r - y0 : cy + r + 1 - y0, cx - r - x0 : cx + r + 1 - x0]
    # a bool mask grows to 0 and 1: viewed as bool, no conversion
    return patch.view(bool) if mask.dtype == bool else patch.astype(bool)


AHEAD_NEAR_PX = 2.0  # a surface this much nearer than the end still carries it (the thread's
# thickness, the tissue's tilt across the patch, the end's depth error)
AHEAD_AGREE_PX = 8.0  # the two views' occluder disparities agree within this (one surface)
AHEAD_STEP_PX = 2 * AHEAD_HALF_PX + 1  # the walk over an occluder moves a patch at a time
AHEAD_MEET = 2  # an occluder within this many patches of the thread's visible end meets it


@dataclass(frozen=True)
class Occluded:
    """A free end whose thread, in both views, runs into a surface in front of it (an
    occluder) instead of the surface it lies on: ``view`` the one that sees the thread
    farther ("left"/"right"), ``ext_px`` how far its thread pixels reach beyond the curve's
    end, ``front_px`` how much nearer the occluder is (px of disparity, the two views' mean),
    ``hidden_px`` how far beyond the thread's visible end the occluder reaches in that view
    (to where a surface at or behind the end's depth is seen, or the image border), and
    ``reach_px`` = ``ext_px`` + ``hidden_px``: what the curve may miss (at least, when
    ``walked_out``)."""

    view: str
    ext_px: float
    front_px: float
    hidden_px: float
    walked_out: bool = False  # the walk stopped at max_reach_px: the occluder reaches farther
    blank: str | None = None  # the view ("left"/"right") that could not measure the occluder
    # because it is untextured there (``untextured``), or None: both views measured it

    @property
    def reach_px(self) -> float:
        return self.ext_px + self.hidden_px


def end_occluder(
    uv: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    greys: tuple[np.ndarray, np.ndarray],
    end: str,
    disparity: float,
    known: tuple[tuple[float, float], tuple[np.ndarray | None, np.ndarray | None]],
    reach_px: float,
    cover_px: float,
    see_px: float,
    max_reach_px: float,
    plain_sigma: float | None = None,
    untextured: bool = False,
    next_measure: bool = False,
    past_untold: bool = False,
) -> Occluded | None:
    """Whether the thread at the curve's free ``end`` runs, in both views, into an occluder.

    The thread's visible end is the farthest pixel of the piece at the end in the view that
    sees farther (``known``: ``extension_far`` up to ``reach_px``, followed up to ``see_px``
    when it reaches that far), else the end's projection; the same point at the end's
    ``disparity`` in the other view. Just beyond it, along the way from the curve's end to it,
    ``surface_ahead`` measures the surface in both views (AHEAD_MEET patches): a free end is
    followed by the surface the thread lies on (at or behind the end's depth), so both views
    measuring one surface more than AHEAD_NEAR_PX px of disparity in front of the end (within
    AHEAD_AGREE_PX of each other) is an end at an occluder. The occluder is then walked along
    that way a patch at a time in the view that sees farther (the patches the pair cannot
    tell count as occluder) until two patches in a row show a surface at or behind the end's
    depth, or the image border,
    while the reach (extension and hidden stretch) is under ``max_reach_px``. None when the
    end is not at an occluder (or the pair cannot tell).

    ``plain_sigma`` (None: not looked at): where the background beside the thread's visible
    end is plain (untextured: stereo cannot measure it) and the thread stands out from it by
    more than ``plain_sigma`` noise floors, a patch of its grey and as plain is the surface
    the thread lies on, seen (``plain_surface``): a thread there would show. It ends the walk
    like a measured surface, and before the meeting patch it makes the end free.

    ``untextured`` (CheckParams.blank_occluder): when only one view measures a surface in
    front and the other cannot tell because it is blank there (``_unlike_beside``: its
    patches give no disparity, the first is untextured and unlike the surface beside the
    end, e.g. a shaft's dark, uniform tip), the one measure is the occluder's (``blank``
    names the other view). ``next_measure`` (CheckParams.blank_next_measure): nor may the
    first patch farther along the way that the walk's view (the one that sees farther) can
    measure show the surface the thread lies on (at or behind the end's depth): a faint
    texture on a smooth stretch of tissue mismatches once, and the tissue measured farther on
    tells it; a shaft's texture past its blank tip measures the shaft again.

    ``past_untold`` (CheckParams.occluder_exit): the walk also ends at two measures of one
    surface at or behind the end with only patches the pair cannot tell between (``_walk``)."""
    ext, far_px = known
    far = 0 if ext[0] >= ext[1] else 1
    fr = _end_frame(uv[far], end)
    if fr is None or not (math.isfinite(disparity) and disparity > 0):
        return None
    _, tip, way = fr
    tangent = way  # the curve's own way at its end: the axis of the cone the thread is followed in
    edge = far_px[far] is not None and float(np.hypot(*(far_px[far] - tip))) + 3.0 > reach_px
    if edge and see_px > reach_px:  # the thread reaches the search's edge: follow it further
        ext, far_px = extension_far(uv, masks, end, see_px, cover_px, 0.0)
        far = 0 if ext[0] >= ext[1] else 1
        fr = _end_frame(uv[far], end)
        if fr is None:
            return None
        _, tip, way = fr
        tangent = way
    at = tip if far_px[far] is None else far_px[far]
    run = at - tip
    n = float(np.hypot(run[0], run[1]))
    if n > AHEAD_HALF_PX:  # the thread's own way to its visible end (it may bend)
        way = run / n
    shift = np.array([-disparity if far == 0 else disparity, 0.0])  # the other view's x
    plain: list[PlainSource] = [None, None]
    if plain_sigma is not None:  # measured when a patch first needs it (most ends never do)
        for side, xy in ((far, at), (1 - far, at + shift)):
            plain[side] = _Once(
                lambda s=side, p=xy: plain_surface(greys[s], masks[s], p, way, plain_sigma)
            )
    d_far, k = _front(greys, masks, far, at, way, disparity, plain[far])
    if d_far is None and not untextured:
        return None
    d_other, k_other = _front(greys, masks, 1 - far, at + shift, way, disparity, plain[1 - far])
    blank = None
    if (d_far is None) != (d_other is None) and untextured:
        # One view measures a surface in front; the other cannot tell, because its first
        # patch is untextured and unlike the surface beside the thread's end (a shaft's dark,
        # uniform tip, not the tissue or plain background the thread lies on): nothing there
        # contradicts the measure, and no surface the thread lies on is seen (okwrong16).
        side, xy = (1 - far, at + shift) if d_other is None else (far, at)
        seen, xy_seen = (far, at) if d_other is None else (1 - far, at + shift)
        d, kk = (d_far, k) if d_other is None else (d_other, k_other)
        # the measure stands alone: the measuring view's next patch must not show the surface
        # the thread lies on right after it (one mismatching patch, as the walk ignores), and
        # the blank view's patch where it matched must bear it out
        d_next, _ = surface_ahead(
            greys, masks, seen, xy_seen, way, disparity, (kk + 1) * AHEAD_STEP_PX
        )
        stands = d_next is None or d_next > AHEAD_NEAR_PX
        if stands and next_measure:
            # and the first patch farther along the way that the walk's view can measure must
            # not show the surface the thread lies on: the lone measure was a mismatch there
            limit = min(_to_border(at, way, greys[far].shape), max(max_reach_px - ext[far], 0.0))
            farther = _next_measure(greys, masks, far, at, way, disparity, kk + 1, limit)
            stands = farther is None or farther > AHEAD_NEAR_PX
        if (
            stands
            and _unlike_beside(greys, masks, side, xy, way, disparity)
            and _blank_back(greys, masks, seen, xy_seen, way, disparity, d, kk)
        ):
            blank = "left" if side == 0 else "right"
            k, d_far, d_other = kk, d, d
    if d_far is None or d_other is None:
        return None
    if abs(d_far - d_other) > AHEAD_AGREE_PX:
        # Next to an occluder's edge one view sees background the other's occluder hides (a
        # half-occlusion, on the side the occluder shifts away from): that view's patch has no
        # match and measures anything. A measure the other view's own patch at the matched
        # place returns (left-right consistency) is the surface, seen in both views.
        for side, xy, d, kk in ((1 - far, at + shift, d_other, k_other), (far, at, d_far, k)):
            back = _other_patch(greys, masks, side, xy, way, disparity, d, kk)[0]
            if back is not None and abs(back - d) <= AHEAD_AGREE_PX:
                d_far, d_other = d, back
                break
        else:
            return None
    budget = max(max_reach_px - ext[far], 0.0)
    # the hidden thread need not go straight on (it may turn to follow a shaft under which it
    # runs): the way and rays inside the 30-deg cone in which a thread is followed beyond an
    # end (CONE_COS, extension). That cone is the curve's: around its tangent at the end. The
    # visible thread's own way to its farthest pixel may lie up to 30 deg off it (a thread
    # that bends where it meets the occluder, or whose last pixels at the occluder's edge the
    # segmentation missed): the fan is widened by the tangent's rays that lie outside it.
    hidden = 0.0
    rays = [_turned(way, turn) for turn in WALK_TURNS]
    fan_cos = math.cos(max(abs(t) for t in WALK_TURNS)) - 1e-9
    rays += [r for r in (_turned(tangent, t) for t in WALK_TURNS) if float(r @ way) < fan_cos]
    for i, ray in enumerate(rays):
        start = float((k + 1) * AHEAD_STEP_PX) if i == 0 else 0.0  # past the meeting patch
        limit = min(_to_border(at, ray, greys[far].shape), budget)
        walked = _walk(greys, masks, far, at, ray, disparity, start, limit, plain[far], past_untold)
        hidden = max(hidden, walked)
        if ext[far] + hidden >= max_reach_px:
            break
    out = ext[far] + hidden >= max_reach_px
    return Occluded(
        "left" if far == 0 else "right", ext[far], 0.5 * (d_far + d_other), hidden, out, blank
    )


BESIDE_BACK_PX = 18  # px farther back than plain_surface (twice its PLAIN_HALF_PX) the surface
# beside an end is measured for `_unlike_beside`, clear of an occluder's rounded tip at the end
UNLIKE_LEVELS = 3.0  # noise floors (AHEAD_LEVELS) between an untextured patch and the surface


def _next_measure(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    at: np.ndarray,
    way: np.ndarray,
    disparity: float,
    k: int,
    limit: float,
) -> float | None:
    """The first measure (px of disparity in front of the end) of ``surface_ahead``'s patches
    of view ``side`` beyond ``at`` along ``way`` from patch ``k`` on, while the patch's offset
    is under ``limit`` px; None when the pair can tell none of them."""
    offset = float(k * AHEAD_STEP_PX)
    while offset < limit:
        d, _ = surface_ahead(greys, masks, side, at, way, disparity, offset)
        if d is not None:
            return d
        offset += AHEAD_STEP_PX
    return None


def _unlike_beside(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    xy: np.ndarray,
    way: np.ndarray,
    disparity: float,
) -> bool:
    """Whether view ``side`` cannot measure the surface beyond the thread's end at ``xy``
    (going ``way``) because it is blank there: none of the AHEAD_MEET patches of
    ``surface_ahead`` gives a disparity, and the first is untextured and unlike the surface
    beside the end: the median grey of that surface (a square of ``plain_surface``'s size,
    BESIDE_BACK_PX farther back along the thread, clear of what lies at its end; thread
    pixels and their edge left out) lies more than UNLIKE_LEVELS noise floors from the
    patch's mean grey (a smooth stretch of the tissue itself has the tissue's grey)."""
    first = None
    for k in range(AHEAD_MEET):
        d, g = surface_ahead(greys, masks, side, xy, way, disparity, k * AHEAD_STEP_PX)
        if d is not None:
            return False
        first = g if k == 0 else first
    if first is None:
        return False
    grey = greys[side]
    h, w = grey.shape
    r = PLAIN_HALF_PX
    back = BESIDE_BACK_PX + r  # clear of what lies at the end (an occluder's rounded tip)
    cx = int(round(float(xy[0]) - back * float(way[0])))
    cy = int(round(float(xy[1]) - back * float(way[1])))
    if cx - r < 0 or cy - r < 0 or cx + r >= w or cy + r >= h:
        return False
    found = _background_level(grey, masks[side], cx, cy)
    return found is not None and abs(first - found[0]) > UNLIKE_LEVELS * AHEAD_LEVELS


def _background_level(
    grey: np.ndarray, mask: np.ndarray, cx: int, cy: int
) -> tuple[float, np.ndarray] | None:
    """The median grey of the square of half-size PLAIN_HALF_PX centred on pixel (cx, cy)
    (inside the image), thread pixels and their edge left out, and those pixels' greys; None
    when fewer than PLAIN_SHARE of the square is left."""
    r = PLAIN_HALF_PX
    seen = ~_thread_and_edges(mask, cy, cx, r)
    n = int(np.count_nonzero(seen))
    if n < PLAIN_SHARE * seen.size:
        return None
    vals = np.asarray(grey[cy - r : cy + r + 1, cx - r : cx + r + 1], dtype=np.float64)[seen]
    return float(np.partition(vals, n // 2)[n // 2]), vals


def _blank_back(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    at: np.ndarray,
    way: np.ndarray,
    disparity: float,
    d: float,
    k: int,
) -> bool:
    """Whether the other view's patch where view ``side``'s patch ``k`` matched (``d`` px in
    front of the end, as ``_other_patch`` finds it) bears the measure out: it returns ``d``
    (within AHEAD_AGREE_PX), or it is untextured too (the same blank surface seen there). A
    match that lands on textured surface measuring another depth is none (a shaft along the
    rows matches anywhere along them)."""
    d_back, grey_back = _other_patch(greys, masks, side, at, way, disparity, d, k)
    if d_back is not None:
        return abs(d_back - d) <= AHEAD_AGREE_PX
    return grey_back is not None


def _turned(way: np.ndarray, turn: float) -> np.ndarray:
    """The unit ``way`` (x, y) turned by ``turn`` radians."""
    c, s = math.cos(turn), math.sin(turn)
    return np.array([c * way[0] - s * way[1], s * way[0] + c * way[1]])


# the walk's rays off the way: 22.5 deg apart, their 13 px patches touch ~33 px out (45 deg
# rays also flagged ends that stop beside a shaft: c9963r instrument_3, a right curve)
WALK_TURNS = tuple(np.radians([0.0, 22.5, -22.5]))


def _walk(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    at: np.ndarray,
    way: np.ndarray,
    disparity: float,
    offset: float,
    limit: float,
    plain: PlainSource = None,
    past_untold: bool = False,
) -> float:
    """How far (px) past ``at`` along ``way`` an occluder reaches in view ``side``: walked a
    patch at a time from ``offset`` until two patches in a row show a surface at or behind the
    end's depth, or the plain background the thread lies on (``plain``: its grey level and
    tolerance, see ``plain_surface``), else ``limit``. The other patches the pair cannot tell
    count as occluder.

    ``past_untold`` (CheckParams.occluder_exit): two such patches with only patches the pair
    cannot tell between them (no patch measured in front of the end), their measures within
    AHEAD_AGREE_PX of each other (one surface), end the walk at the first as well: smooth
    tissue past a shaft's edge alternates between untextured patches and patches measured
    behind the end, and the occluder, measured in front wherever it is textured, does not
    come back between two measures of one surface behind it along a straight way."""
    bare = None  # the offset of a patch showing the surface under the thread again
    lone = None  # (offset, measure) of the last such patch with only untold patches since
    while offset < limit:
        d, grey = surface_ahead(greys, masks, side, at, way, disparity, offset)
        if d is None and _is_plain(grey, plain):
            d = 0.0  # the plain background the thread lies on: a thread there would show
        if d is None or d > AHEAD_NEAR_PX:
            bare = None
            if d is not None:  # measured in front: the occluder again
                lone = None
        elif bare is None:
            if past_untold and lone is not None and abs(d - lone[1]) <= AHEAD_AGREE_PX:
                return lone[0]  # the same surface twice, only untold patches between
            bare = offset
            lone = (offset, d)
        else:  # two patches in a row (one mismatch on a shaft along the rows is no surface)
            return bare  # the thread, had it gone on this way, would be seen: it ended before
        offset += AHEAD_STEP_PX
    return limit


def _other_patch(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    at: np.ndarray,
    way: np.ndarray,
    disparity: float,
    d: float,
    k: int,
) -> tuple[float | None, float | None]:
    """``surface_ahead`` of the other view's patch where view ``side``'s patch ``k`` beyond
    ``at`` along ``way`` matched, ``d`` px in front of the end's ``disparity``: its measure
    (px of disparity in front of the end; None when it cannot tell) and its grey level."""
    offset = k * AHEAD_STEP_PX
    t = patch_t(offset)  # the patch's centre along the way
    dx = disparity + d  # the surface's disparity: seen dx px left in the right view
    c_other = at + t * way - np.array([dx if side == 0 else -dx, 0.0])
    return surface_ahead(greys, masks, 1 - side, c_other - t * way, way, disparity, offset)


def patch_t(offset: float) -> float:
    """px along an end's way from its tip to the centre of ``surface_ahead``'s patch at
    ``offset``: 2 px clear of the tip, then half a patch."""
    return offset + 2.0 + AHEAD_HALF_PX


def _front(
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    at: np.ndarray,
    way: np.ndarray,
    disparity: float,
    plain: PlainSource = None,
) -> tuple[float | None, int]:
    """The first of the AHEAD_MEET patches beyond ``at`` that shows a surface more than
    AHEAD_NEAR_PX px of disparity in front of the end: by how much, and its number; (None,
    AHEAD_MEET) when none does (the surface beyond is at or behind the end's depth, or the
    pair cannot tell), or when a patch before it shows the plain background the thread lies on
    (``plain``): the thread would show there, so it ended before the occluder."""
    for k in range(AHEAD_MEET):
        d, grey = surface_ahead(greys, masks, side, at, way, disparity, k * AHEAD_STEP_PX)
        if d is not None and d > AHEAD_NEAR_PX:
            return d, k
        if d is None and _is_plain(grey, plain):
            break  # bare plain background between the end and anything beyond: a free end
    return None, AHEAD_MEET


PLAIN_HALF_PX = 9  # half-size of the square beside an end whose background is measured
PLAIN_SHARE = 1.0 / 3.0  # of it off the thread (a thick thread and its blurred edge may take
# 11 of its 19 px across; a third of it, 120 px, still gives the level)


def plain_surface(
    grey: np.ndarray,
    mask: np.ndarray,
    xy: np.ndarray,
    way: np.ndarray,
    sigma: float,
) -> tuple[float, float] | None:
    """The plain background a thread ending at ``xy`` (going ``way``, a unit (x, y)) lies on in
    one view, as (grey level, tolerance), when a thread would be seen on it; else None.
    Measured beside the thread's last stretch: the square of 2 PLAIN_HALF_PX + 1 px centred
    PLAIN_HALF_PX px back from the end (not over what lies ahead of it), its thread pixels and
    their blurred edge left out (at least PLAIN_SHARE of it left), gives the level (median).
    Plain: at least half of those pixels within AHEAD_LEVELS / 1.4826 of it (a robust spread,
    1.4826 MAD, within AHEAD_LEVELS, the noise floor: no texture, so stereo cannot measure
    the surface and grey is all there is); seen: the thread pixels within AHEAD_HALF_PX of
    ``xy`` (their median grey) stand out from the level by more than the tolerance, ``sigma``
    noise floors. A textured background is left to stereo (an untextured patch on it is no
    surface the thread lies on)."""
    h, w = grey.shape
    r, q = PLAIN_HALF_PX, AHEAD_HALF_PX
    xf, yf, wx, wy = float(xy[0]), float(xy[1]), float(way[0]), float(way[1])
    if not (math.isfinite(xf) and math.isfinite(yf) and math.isfinite(wx) and math.isfinite(wy)):
        return None  # (math.isfinite on the four numbers: np.all's layers cost ~20 times more)
    x, y = int(round(xf)), int(round(yf))
    cx, cy = int(round(x - r * wx)), int(round(y - r * wy))
    if min(x - q, y - q, cx - r, cy - r) < 0 or max(x + q, cx + r) >= w or max(y + q, cy + r) >= h:
        return None
    # the levels depend on the view's image and mask and the two pixels only: kept with them
    level, thread = derived_entry(
        (grey, mask), "plain levels", (x, y, cx, cy),
        lambda: _plain_levels(grey, mask, x, y, cx, cy),
    )  # fmt: skip
    if level is None:
        return None
    tol = sigma * AHEAD_LEVELS
    return (level, tol) if abs(thread - level) > tol else None


def _plain_levels(
    grey: np.ndarray, mask: np.ndarray, x: int, y: int, cx: int, cy: int
) -> tuple[float | None, float | None]:
    """``plain_surface``'s grey levels of the plain background in the square centred on pixel
    (cx, cy) and of the thread pixels around (x, y) (both inside the image): (None, None)
    when there are no thread pixels there, too few background pixels, or it is textured."""
    q = AHEAD_HALF_PX
    near = np.asarray(mask[y - q : y + q + 1, x - q : x + q + 1], dtype=bool)
    if not near.any():
        return None, None  # no thread pixels there to measure its contrast with
    found = _background_level(grey, mask, cx, cy)
    if found is None:
        return None, None
    level, vals = found
    if 2 * int(np.count_nonzero(np.abs(vals - level) <= AHEAD_LEVELS / 1.4826)) < len(vals):
        return None, None  # textured: left to stereo
    on = np.asarray(grey[y - q : y + q + 1, x - q : x + q + 1], dtype=np.float64)[near]
    return level, float(np.partition(on, on.size // 2)[on.size // 2])


def _is_plain(grey: float | None, plain: PlainSource) -> bool:
    """Whether an untextured patch of mean ``grey`` (``_ahead``; None: textured or not
    measured) shows the ``plain`` background (``plain_surface``; or a function giving it,
    called only for such a patch): its grey within the tolerance of the background's."""
    if grey is None or plain is None:
        return False
    level = plain() if callable(plain) else plain
    return level is not None and abs(grey - level[0]) <= level[1]


class _Once:
    """``compute()`` on the first call, the same value on every later one: what
    ``functools.cache`` gives a function without arguments, at a fraction of its set-up cost
    (two per free end and run of the check)."""

    __slots__ = ("_compute", "_value")

    def __init__(self, compute: Callable[[], tuple[float, float] | None]) -> None:
        self._compute: Callable[[], tuple[float, float] | None] | None = compute
        self._value: tuple[float, float] | None = None

    def __call__(self) -> tuple[float, float] | None:
        if self._compute is not None:
            self._value, self._compute = self._compute(), None
        return self._value


# the plain background of ``plain_surface`` (grey level, tolerance), a function giving it when
# first needed, or None (no plain background: nothing is taken for it)
PlainSource = tuple[float, float] | Callable[[], tuple[float, float] | None] | None


BRIDGE_SAMPLE_PX = AHEAD_STEP_PX  # px between the bridge samples whose occluder is measured


def bridge_stray(
    uv: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    greys: tuple[np.ndarray, np.ndarray],
    disparity: np.ndarray,
    plain: tuple[tuple[float, float] | None, tuple[float, float] | None],
    limit_px: np.ndarray,
    both_views: bool = True,
) -> float:
    """How far (px, at most ``limit_px``) a thread hidden under the bridge ``uv`` ((k, 2) per
    view, the bridge's samples from one observed end to the other) may stray from it and stay
    hidden in both views: at samples BRIDGE_SAMPLE_PX apart (left view), the occluder is walked
    across the bridge on both sides (``_walk``: until two patches in a row show a surface at
    or behind the bridge's depth, ``disparity`` (k,), or the ``plain`` background) in each view,
    and its farthest side, plus a patch (where the walk stopped, the surface may only begin
    at the patch's far side), bounds the stray there. The largest over the samples is
    returned, relative to each sample's ``limit_px`` (k,): a value >= 1 means the occluder
    reaches the limit somewhere (the walk stopped there). A hidden thread goes where the
    occluder lets it: the bridge's shape is then known to within this stray.

    ``both_views`` (the default since session 22, occ23): on each side of a sample the nearer of the two views'
    reaches bounds the stray there. A thread off the bridge by s px at the sample's depth lies
    s px off it along the same normal in both (rectified) views, so it stays hidden only
    where both occluders reach that far: where either view shows the surface, the thread would
    be seen. False: the farther of the two (before session 22)."""
    uv_l = uv[0]
    step = np.hypot(*np.diff(uv_l, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(step)])
    picks = np.unique(np.searchsorted(s, np.arange(0.0, s[-1] + 1e-9, BRIDGE_SAMPLE_PX)))
    views = min if both_views else max  # how a side's reaches in the two views combine
    worst = 0.0
    for i in picks:
        if i >= len(uv_l):
            continue
        lo, hi = max(i - 1, 0), min(i + 1, len(uv_l) - 1)
        normals = []
        for side in (0, 1):
            t = uv[side][hi] - uv[side][lo]
            nt = float(np.hypot(t[0], t[1]))
            if nt == 0.0 or not np.all(np.isfinite(uv[side][i])):
                return math.inf  # no direction to measure across: not bounded
            normals.append(np.array([-t[1], t[0]]) / nt)
        limit = float(limit_px[i])
        for sign in (1.0, -1.0):
            strays = []
            for side in (0, 1):
                way = sign * normals[side]
                reach = min(_to_border(uv[side][i], way, greys[side].shape), limit)
                d = _walk(greys, masks, side, uv[side][i], way, float(disparity[i]), 0.0,
                          reach, plain[side])  # fmt: skip
                strays.append(limit if d >= reach else d + AHEAD_STEP_PX + 2.0)
            worst = max(worst, views(strays) / limit)
            if worst >= 1.0:
                return worst
    return worst


def surface_past_end(
    uv: np.ndarray,
    greys: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    side: int,
    end: str,
    disparity: float,
    plain: PlainSource = None,
) -> float | None:
    """In view ``side``: how much nearer (px of disparity) than the curve's ``end`` the surface
    just past the end's projection ``uv`` (N, 2) lies, the nearest of the AHEAD_MEET patches
    along the end's way that the pair can measure (``surface_ahead``); None when none can be.
    A patch of the ``plain`` background the thread lies on (``plain_surface``) counts as that
    surface, at the end's depth (0).

    For an end that one view sees cut (``cut_end``): an occluder that hides the thread in
    that view lies in front of the end there; a surface at or behind the end's depth (the
    tissue, or the thread itself where the segmentation missed it) is no occluder.

    A patch measured in front counts only when the other view's own patch at the matched
    place does not measure another surface (left-right consistency, ``_other_patch``, within
    AHEAD_AGREE_PX): an occluder's silhouette is matched back at its disparity from either
    view, while a patch holding another strand of the thread or unsegmented thread (at a
    crossing) can match a strand elsewhere on its row, far in front, where the other view's
    patch sees the tissue at the end's depth. A back-match that cannot tell keeps the
    measure."""
    fr = _end_frame(uv, end)
    if fr is None or not (math.isfinite(disparity) and disparity > 0):
        return None
    _, tip, way = fr
    found = []
    for k in range(AHEAD_MEET):
        d, grey = surface_ahead(greys, masks, side, tip, way, disparity, k * AHEAD_STEP_PX)
        if d is None and _is_plain(grey, plain):
            d = 0.0  # the plain background the thread lies on: a thread there would show
        elif d is not None and d > AHEAD_NEAR_PX:
            back = _other_patch(greys, masks, side, tip, way, disparity, d, k)[0]
            if back is not None and abs(back - d) > AHEAD_AGREE_PX:
                d = None  # a mismatch along the row: the pair does not show this surface
        found.append(d)
    measured = [d for d in found if d is not None]
    return max(measured) if measured else None


def _to_border(at: np.ndarray, way: np.ndarray, shape: tuple[int, int]) -> float:
    """Distance (px) from ``at`` along the unit ``way`` to the border of an image of
    ``shape`` (H, W)."""
    h, w = shape
    t = math.inf
    for x, v, size in ((float(at[0]), float(way[0]), w), (float(at[1]), float(way[1]), h)):
        if v > 1e-12:
            t = min(t, (size - 1 - x) / v)
        elif v < -1e-12:
            t = min(t, x / -v)
    return max(t, 0.0)


FOLLOW_STEP_PX = 3.0  # the thread line beyond a free end is followed this far per step
# its way may turn by at most 20 deg per step (10 deg apart; a bend of radius >= ~9 px: a
# loop), and stays within the 30-deg cone of the curve's way at the end (CONE_COS,
# ``extension``) for its first FOLLOW_CONE_PX (a line crossing near a true end leaves it)
FOLLOW_TURNS = tuple(np.radians([0.0, 10.0, -10.0, 20.0, -20.0]))
FOLLOW_CONE_PX = 20.0
FOLLOW_AHEAD_PX = (2.0, 4.0, 6.0)  # each way is judged by the line's mean score ahead
FOLLOW_GAP_STEPS = 2  # steps below the level in a row that the line may bridge (a speck)
FOLLOW_DISPARITY_PX = 4  # the other view's line within this of the end's disparity
FOLLOW_CURVE_PX = 3.0  # the line ends where it meets the curve's own projection
_DILATE3 = np.ones((3, 3), np.uint8)
_AHEAD = np.array(FOLLOW_AHEAD_PX)
_TURN_ROT = np.array([[[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]] for t in FOLLOW_TURNS])


def thread_line_beyond(
    scores: tuple[np.ndarray, np.ndarray],
    uv: tuple[np.ndarray, np.ndarray],
    end: str,
    disparity: float,
    max_px: float,
    level: float,
) -> float:
    """How far (px, left view) a thread-like line goes on past the curve's free ``end``, seen
    in both views at the end's ``disparity``: the raw segmentation's thread score (``scores``,
    (H, W) in [0, 1] per view) followed from the end's tip in the left view, a step of
    FOLLOW_STEP_PX at a time, along the way (turning at most 20 deg a step, within the
    curve's 30-deg cone for the first FOLLOW_CONE_PX) whose mean score ahead is highest, the
    score at a pixel being the lower of the left view's and the right view's best within
    FOLLOW_DISPARITY_PX of the end's disparity (each the best of its 3 x 3 neighbourhood: a
    line 1-2 px wide between pixel centres). The line ends after more than FOLLOW_GAP_STEPS
    steps in a row below ``level``, where it meets the curve's own projection, or at
    ``max_px``; the length returned is that of its last step at or above ``level``.

    A thread the segmentation dropped past the end (a loop it judged a vessel) goes on in
    both views at about the end's depth and bends smoothly on from the curve's way; a fibre or
    vessel crossing near a true end leaves it at an angle."""
    fr = _end_frame(uv[0], end)
    if fr is None or not (math.isfinite(disparity) and disparity > 0):
        return 0.0
    curve, tip, way = fr
    left, right = derived(scores, "thread line", lambda: _line_maps(scores))
    shift = np.array([float(round(disparity)), 0.0])  # left x is seen at x - d in the right
    near = curve[np.hypot(*(curve - tip).T) <= max_px + FOLLOW_STEP_PX]
    pos, heading = tip.astype(np.float64), way.copy()
    cone = CONE_COS - 1e-9
    walked, found, missed = 0.0, 0.0, 0
    while walked < max_px:
        ways = _TURN_ROT @ heading
        if walked < FOLLOW_CONE_PX:
            ways = ways[ways @ way >= cone]
        if not len(ways):
            break
        ahead = pos + ways[:, None, :] * _AHEAD[None, :, None]
        means = np.minimum(_bilinear(left, ahead), _bilinear(right, ahead - shift)).mean(axis=1)
        best, best_way = -1.0, None
        for mean, w in zip(means.tolist(), ways, strict=True):
            if mean > best + 0.02:  # ties go to the straighter way (tried first)
                best, best_way = mean, w
        if best_way is None or best < 0.0:
            break
        pos, heading = pos + FOLLOW_STEP_PX * best_way, best_way
        walked += FOLLOW_STEP_PX
        if (
            walked > FOLLOW_CONE_PX
            and near.size
            and float(np.min(np.hypot(near[:, 0] - pos[0], near[:, 1] - pos[1]))) < FOLLOW_CURVE_PX
        ):
            break
        if best >= level:
            found, missed = walked, 0
        else:
            missed += 1
            if missed > FOLLOW_GAP_STEPS:
                break
    return found


def _bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``img`` (h, w) at the points ``xy`` (..., 2) (x, y), bilinear; -1 off the image."""
    h, w = img.shape
    x, y = xy[..., 0], xy[..., 1]
    inside = (x >= 0.0) & (x < w - 1) & (y >= 0.0) & (y < h - 1)
    x, y = np.where(inside, x, 0.0), np.where(inside, y, 0.0)
    i, j = x.astype(np.intp), y.astype(np.intp)
    fx, fy = x - i, y - j
    top = img[j, i] * (1 - fx) + img[j, i + 1] * fx
    bottom = img[j + 1, i] * (1 - fx) + img[j + 1, i + 1] * fx
    return np.where(inside, top * (1 - fy) + bottom * fy, -1.0)


def _line_maps(scores: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The views' thread scores (H, W), each pixel the best of its 3 x 3 neighbourhood (a line
    1-2 px wide between pixel centres), the right view's also of +-FOLLOW_DISPARITY_PX along
    its row (the disparity window): once per segmentation."""
    right_kernel = np.ones((3, 3 + 2 * FOLLOW_DISPARITY_PX), np.uint8)
    return (
        cv2.dilate(np.ascontiguousarray(scores[0], np.float32), _DILATE3),
        cv2.dilate(np.ascontiguousarray(scores[1], np.float32), right_kernel),
    )


HIDDEN_SHIFTS_PX = (-16.0, -12.0, -8.0, -4.0, 0.0, 4.0, 8.0, 12.0, 16.0)  # off the end's disparity
HIDDEN_PATCHES = 5  # patches of the other view measured along a one-view piece
HIDDEN_HELD = 0.2  # at most this share of a one-view piece the other view's mask may hold


def hidden_piece(
    uv: tuple[np.ndarray, np.ndarray],
    masks: tuple[np.ndarray, np.ndarray],
    end: str,
    disparity: float,
    cover_px: float,
    max_gap_px: float,
    greys: tuple[np.ndarray, np.ndarray],
    bare: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
) -> tuple[str, float] | None:
    """A piece of thread pixels beyond the curve's free ``end`` across an occluder in one view
    (``_beyond``: within 45 deg of the end's way, the gap not bare) that the other view hides:
    at the end's ``disparity`` its place there is no bare background, and no shift within 16
    px of it puts more than HIDDEN_HELD of the piece on the other view's thread pixels (a
    piece both views hold is ``beyond_ends``'). Returns the view that shows it ("left" /
    "right") and its reach (px from the end to its far side, in that view), the farther of
    the two views' such pieces; None when there is none."""
    if not (math.isfinite(disparity) and disparity > 0):
        return None
    best = None
    for side in (0, 1):
        # the gap lies over the occluder the end runs into (found in both views): not tested
        # as a bridge's (the ring's level at an end touching a shaft mixes shaft and surface)
        hit = _beyond(uv[side], pieces(masks[side]), end, cover_px, max_gap_px, side, bare, 1.0)
        if hit is None:
            continue
        px = hit[3]
        sub = px[:: max(1, len(px) // PIECE_SAMPLES)]
        sign = -1.0 if side == 0 else 1.0  # left x is seen at x - d in the right view
        other = masks[1 - side]
        h, w = other.shape
        held = 0.0
        for off in HIDDEN_SHIFTS_PX:
            q = np.rint(sub + [sign * (disparity + off), 0.0]).astype(np.intp)
            inside = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
            if not inside.all():
                held = 1.0  # off the other image: nothing to tell
                break
            held = max(held, float(np.mean(other[q[:, 1], q[:, 0]])))
        if held > HIDDEN_HELD:
            continue
        # the other view's patches where the piece would lie at the end's depth: stereo
        # measures a surface in front of the end there (the occluder) more often than one at
        # or behind it (the piece's far side may leave the occluder's edge)
        front = behind = 0
        row = np.array([1.0, 0.0])
        for xy in sub[np.linspace(0, len(sub) - 1, HIDDEN_PATCHES).round().astype(int)]:
            at = xy + [sign * disparity, 0.0] - patch_t(0.0) * row
            d, _ = surface_ahead(greys, masks, 1 - side, at, row, disparity)
            if d is not None:
                front += d > AHEAD_NEAR_PX
                behind += d <= AHEAD_NEAR_PX
        if front <= behind:
            continue  # the other view shows the surface there: the thread would be seen
        if best is None or hit[1] > best[1]:
            best = ("left" if side == 0 else "right", hit[1])
    return best
