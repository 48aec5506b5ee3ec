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

from dataclasses import dataclass

import numpy as np

from threadrecon.core.check_fast_kernel import close_pairs
from threadrecon.core.numeric import arc_px, row_norms

FOLD_COS = float(np.cos(np.radians(30.0)))  # passes within 30 deg of one line run along it


def fold_length(
    uv: np.ndarray,
    step: np.ndarray,
    on: np.ndarray,
    disp: np.ndarray,
    radius: float,
    dtol: float,
    s: np.ndarray | None = None,
) -> float:
    """2D length (px) of the curve running over a stretch another part of it already covers.

    ``uv``: (N, 2) left projection (x, y), px; ``step``: (N-1,) its 2D steps; ``on``: (N,)
    bool, samples on the thread pixels; ``disp``: (N,) the curve's disparity, px; ``radius``:
    px, two passes closer than this run over one strand; ``dtol``: px, passes whose disparities
    differ by this or more are strands over each other. Samples count when they are more than
    pi * radius + 3 px apart along the curve (a bend's own samples are closer). Half the length
    of the steps between two such samples (each fold is counted on both its passes). ``s``:
    ``numeric.arc_px(step)`` when the caller has it."""
    uv = np.asarray(uv, dtype=np.float64)
    n = len(uv)
    if uv.ndim != 2 or uv.shape[1] != 2 or len(step) != n - 1 or len(on) != n or len(disp) != n:
        raise ValueError(
            f"fold_length needs uv (N, 2), step (N-1,), on and disp (N,); got {uv.shape}, "
            f"{np.shape(step)}, {np.shape(on)}, {np.shape(disp)}"
        )
    idx = np.flatnonzero(on & np.isfinite(uv).all(axis=1) & np.isfinite(disp))
    if idx.size < 3 or radius <= 0:
        return 0.0
    s = arc_px(step) if s is None else s
    gap = np.pi * radius + 3.0
    q = uv[idx]  # compiled: cKDTree.query_pairs' pairs, only those more than gap apart along
    pairs = close_pairs(q[:, 0].copy(), q[:, 1].copy(), s[idx], float(radius), gap)
    if not len(pairs):
        return 0.0
    t = np.gradient(uv, axis=0)
    t /= np.maximum(row_norms(t)[:, None], 1e-12)
    i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
    along = np.abs(np.sum(t[i] * t[j], axis=1)) > FOLD_COS
    keep = (np.abs(s[i] - s[j]) > gap) & along & (np.abs(disp[i] - disp[j]) < dtol)
    hit = np.zeros(n, dtype=bool)
    hit[i[keep]] = True
    hit[j[keep]] = True
    seg = np.where(np.isfinite(step), step, 0.0)
    return float(0.5 * np.sum(seg * (hit[1:] & hit[:-1])))


REVERSAL_ARM_PX = 6.0  # the turn at a point: between the chords this long before and after it
REVERSAL_COS = float(np.cos(np.radians(120.0)))  # a turn of more than 120 deg turns back
REVERSAL_CHORD_PX = 40.0  # the way either side of a turn: the chord this long along the curve
_ARM_STEPS = int(REVERSAL_ARM_PX)  # the arm in 1 px samples (end_reversal reads a 1 px grid)


@dataclass(frozen=True)
class Reversal:
    """An end branch joined at a point where the curve's left projection turns back.

    ``end``: "start" or "end", the end the branch runs to; ``length``: the branch's 3D length
    (the unit of the lengths given); ``turn_deg``: the turn over 2 ``REVERSAL_ARM_PX`` at the
    point; ``at``: (x, y) the point, px; ``at_px``: its 2D arc length from the start, px."""

    end: str
    length: float
    turn_deg: float
    at: tuple[float, float]
    at_px: float = 0.0


def end_reversal(uv: np.ndarray, s3: np.ndarray, step: np.ndarray | None = None) -> Reversal | None:
    """The longest end branch of the curve beyond a point where its left projection turns
    back, or None.

    A thread bends over at least its own width: its projection turns by more than 120 deg
    within 2 ``REVERSAL_ARM_PX`` where the curve was joined at a point from two lines (the
    ordering walked from the thread into a fibre that touches it), where it makes a small hook
    out and back (a few px of the curve off and on one strand), or where the thread runs along
    the line of sight (the apex of a narrow loop: the development split's blend6_4). A joined
    branch and such a loop keep heading back: the chord ``REVERSAL_CHORD_PX`` px along the
    curve on either side of the point, and the chord from the point to the branch's end, each
    turn more than 120 deg from the other side's way in. A hook and a zig-zag go on the way
    they came, a hairpin seen across turns back over more than 2 ``REVERSAL_ARM_PX``. The
    geometry alone does not tell a joined branch from a loop (the check's stereo test of the
    surface beside it does: core/check.py). ``uv``: (N, 2) left projection; ``s3``: (N,) the
    curve's cumulative 3D length; ``step``: (N-1,) ``row_norms(uv[1:] - uv[:-1])`` when the
    caller has it. The branch is the stretch from the point to that end (the shorter one when
    both sides head back)."""
    uv = np.asarray(uv, dtype=np.float64)
    if len(uv) < 3 or not np.isfinite(uv).all():
        return None
    if step is None:
        step = row_norms(uv[1:] - uv[:-1])  # (np.diff's subtraction)
    s = np.concatenate([[0.0], step.cumsum()])
    arm, chord = REVERSAL_ARM_PX, REVERSAL_CHORD_PX
    if s[-1] < 2.0 * arm + 2.0:
        return None

    def at(v: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(v, s, uv[:, 0]), np.interp(v, s, uv[:, 1])])

    def cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
        return np.sum(a * b, axis=-1) / np.maximum(na * nb, 1e-12)

    ss = np.arange(arm, s[-1] - arm, 1.0)
    # The samples ss - arm, ss and ss + arm are the whole numbers 0 .. len(ss) + 2 arm - 1
    # (arange's start + i step, exact): the curve is read once at each (the same values as
    # three reads), and the turn is cos's own operations written per coordinate.
    n, k = len(ss), _ARM_STEPS
    grid = np.arange(n + 2 * k, dtype=np.float64)
    gx, gy = np.interp(grid, s, uv[:, 0]), np.interp(grid, s, uv[:, 1])
    hx, hy = gx[k : k + n], gy[k : k + n]
    ax, ay = hx - gx[:n], hy - gy[:n]
    bx, by = gx[2 * k :] - hx, gy[2 * k :] - hy
    norms = np.sqrt(ax * ax + ay * ay) * np.sqrt(bx * bx + by * by)
    turn = (ax * bx + ay * by) / np.maximum(norms, 1e-12)
    sharp = turn < REVERSAL_COS
    if not sharp.any():
        return None
    here = np.column_stack([hx, hy])
    # one point per sharp run: its sharpest sample
    idx = np.flatnonzero(sharp)
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    c = np.array([r[np.argmin(turn[r])] for r in runs])
    sc, pc = ss[c], here[c]
    back, ahead = at(np.maximum(sc - chord, 0.0)), at(np.minimum(sc + chord, s[-1]))
    s3c = np.interp(sc, s, s3)
    way_back = pc - ahead  # the way into the point from the end side
    way_on = pc - back  # the way into the point from the start side
    back_cos = np.maximum(cos(way_back, back - pc), cos(way_back, uv[0] - pc))
    on_cos = np.maximum(cos(way_on, ahead - pc), cos(way_on, uv[-1] - pc))
    to_start, to_end = back_cos < REVERSAL_COS, on_cos < REVERSAL_COS
    # the branch beyond the point to each end; both sides heading back: the shorter one
    lengths = np.column_stack([s3c - s3[0], s3[-1] - s3c])
    lengths = np.where(np.column_stack([to_start, to_end]), lengths, np.inf)
    side = np.argmin(lengths, axis=1)
    length = lengths[np.arange(len(c)), side]
    if not np.isfinite(length).any():
        return None
    k = int(np.argmax(np.where(np.isfinite(length), length, -1.0)))
    return Reversal(
        ("start", "end")[side[k]], float(length[k]),
        float(np.degrees(np.arccos(np.clip(turn[c[k]], -1.0, 1.0)))),
        (float(pc[k, 0]), float(pc[k, 1])), float(sc[k]),
    )  # fmt: skip


@dataclass(frozen=True)
class SelfContact:
    """Two points of the curve far apart along it that lie closer together in 3D than half a
    thread's width: the curve passes through itself.

    ``distance``: their 3D distance and ``limit`` half a thread's width at their depth;
    ``apart``: the curve's 3D length between them (the unit of the points given); ``at``:
    (x, y) the first point's left projection, px."""

    distance: float
    limit: float
    apart: float
    at: tuple[float, float]


def self_contact(
    uv: np.ndarray, pts: np.ndarray, s3: np.ndarray, radius: float, focal: float, gap: float
) -> SelfContact | None:
    """The closest pair of the curve's points more than ``gap`` apart along it (3D length)
    whose left projections lie within ``radius`` px (a thread's half-width) of each other and
    whose 3D distance is less than ``radius`` px at their mean depth (half a thread's width),
    or None.

    Two strands of a thread lie a thread's width or more apart centre to centre, in front of
    each other where they cross (a crossing at different depths) or side by side (a hairpin,
    a spiral): no part of a thread comes back through another. A curve that does joined its
    pieces in a wrong order: it leaves a strand and comes back to the same point of it
    (masked 17145 instrument #7: two bridges under a shaft meet the visible strand at one
    point, 72 mm apart along the curve, 0.1 mm apart in 3D). Half a width leaves the other
    half for the depth error of the two passes (the closest right pair on the tuning seeds:
    1.05 mm, a crossing of 0.46 mm thread). ``uv``: (N, 2) left projection; ``pts``: (N, 3)
    the curve, ``s3``: (N,) its cumulative 3D length, both in one unit; ``focal``: px."""
    uv = np.asarray(uv, dtype=np.float64)
    pts = np.asarray(pts, dtype=np.float64)
    s3 = np.asarray(s3, dtype=np.float64)
    n = len(uv)
    if uv.shape != (n, 2) or pts.shape != (n, 3) or s3.shape != (n,):
        raise ValueError(
            f"self_contact needs uv (N, 2), pts (N, 3) and s3 (N,); got {uv.shape}, "
            f"{pts.shape}, {s3.shape}"
        )
    idx = np.flatnonzero(
        np.isfinite(uv).all(axis=1) & np.isfinite(pts).all(axis=1) & (pts[:, 2] > 0)
    )
    if idx.size < 2 or radius <= 0 or focal <= 0:
        return None
    q = uv[idx]  # compiled: the pairs within radius in the image, more than gap apart along
    pairs = close_pairs(q[:, 0].copy(), q[:, 1].copy(), s3[idx].copy(), float(radius), gap)
    if not len(pairs):
        return None
    i, j = idx[pairs[:, 0]], idx[pairs[:, 1]]
    dist = np.linalg.norm(pts[i] - pts[j], axis=1)
    limit = radius * 0.5 * (pts[i, 2] + pts[j, 2]) / focal
    k = int(np.argmin(dist / limit))
    if dist[k] >= limit[k]:
        return None
    return SelfContact(
        float(dist[k]), float(limit[k]), float(abs(s3[j[k]] - s3[i[k]])),
        (float(uv[i[k], 0]), float(uv[i[k], 1])),
    )  # fmt: skip
