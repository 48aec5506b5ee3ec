"""Depth continuity along the thread's pieces (issue 12): a short stretch of keypoints matched
to a neighbouring strand takes its second match.

Two turns of a coil, or the legs of a hairpin, run side by side a few px apart. Where the
distance between them in the left image equals their difference in disparity, the SSD window
of Eq. (2) at a pixel of one strand aligns *both* strands with the right image at the other
strand's disparity, and that wrong match wins by a wide margin (E_next / E_min of 10-20 on
generated spirals: Eq. (6) calls it reliable). The right match is still there, as the second
minimum ``d_next`` of every pixel (generated spiral 8141 #9: three keypoints at 67 px among
49 px, their second match 49 px; 8142 #1, 8144 #8: the free end's last keypoints 58-62 px
among 38 px, second match 38-39 px).

Along a chain of A (keypoints of degree <= 2 between junctions and ends) the disparity of one
strand changes by at most ``DISPARITY_SLACK_PX + DISPARITY_SLOPE * distance`` from keypoint to
keypoint (the ordering's own bound). Each keypoint takes either its first match (the cluster's
median disparity) or its second (the median ``d_next`` of its pixels, refined to sub-pixel on
the cluster's summed energy curve); the choice minimises, per chain, ``VIOLATION_COST`` per
step that breaks continuity plus one per second match taken (dynamic programming over the
chain). So a stretch of up to four keypoints changes its match when that
removes a break, the majority of a chain keeps its own, and a chain whose steps all agree is
never touched (every frame without a break: the same result as before, and no extra time).
Junctions keep their disparity (their pixels are both strands') and end chains.

Deviation 74 (issues 10-12: one pixel of a mask must not move a curve): the choice is made on
the second matches it sets, each refined on its cluster's summed energy before the choice (none
where that has no minimum near the median), and a keypoint whose pixels' own best matches
(``d_min``, before the stereo membrane) are its second match, not its first (the membrane's
value), pays the one for keeping its first match instead of for taking its second.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from threadrecon.core import walk_kernel
from threadrecon.core.segmentation import LIFT_VALUE, LiftedPair
from threadrecon.core.stereo import StereoResult, _Box, _subpixel_kernel

# Depth continuity along one strand: two of its keypoints d px apart in the image differ in
# disparity by at most DISPARITY_SLACK_PX + DISPARITY_SLOPE * d (slope <= B/Z: the thread at
# 45 deg to the image plane; the slack covers the clusters' median disparities' noise).
DISPARITY_SLACK_PX = 1.0
DISPARITY_SLOPE = 0.1
SMOOTH_TIE = 1e-6  # per px of disparity change: among choices of equal cost, the smoother
# (the same from either end of a chain; the counts above are never outweighed)
VIOLATION_COST = 4.5  # second matches one continuity break is worth: a stretch of up to four
# switches (the ordering's BREAK_SIDE of five is a strand of its own); never a tie between
# switching a stretch and keeping its break, so the choice is the same along either direction


def second_matches(
    stereo: StereoResult,
    labels: np.ndarray,
    disp: np.ndarray,
    edges: np.ndarray,
    pos: np.ndarray,
    refined: bool = True,
    own_energy: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """(disp', switched): the keypoints' disparities with short stretches that break depth
    continuity along a chain of A switched to their second match (see the module docstring),
    and a (K,) bool of the switched keypoints. ``labels``: (N,) cluster of each pixel of
    ``stereo`` (-1: none); ``disp``: (K,) the clusters' median disparities, px; ``edges``:
    (E, 2) A; ``pos``: (K, 2) keypoints, px. ``disp`` is returned as is (same object) when no
    step of a chain breaks continuity.

    ``refined`` (deviation 74): the choice is made on the second matches it will set, each
    refined on its cluster's summed energy curve before the choice, none where that curve has
    no minimum there. Else (the previous form) it is made on the pixels' median second match
    and the refinement comes after: a keypoint whose refinement failed kept its first match
    while the rest of its stretch stayed switched, a choice the dynamic programming never
    made, and the integer median's step of one pixel (one pixel of the mask) decided it.
    ``own_energy`` (with ``refined``, deviation 74): a keypoint whose pixels' own best matches
    of Eq. (3) (median ``d_min``, before the stereo membrane) lie within 1 px of its second match
    and over 1 px from its first (the membrane's value) pays the match count for keeping its
    first match, not for taking its second."""
    K = len(disp)
    if pos.shape != (K, 2):
        raise ValueError(f"pos must be ({K}, 2) keypoints in px, got {pos.shape}")
    switched = np.zeros(K, dtype=bool)
    if not len(edges):
        return disp, switched
    degree = np.bincount(edges.ravel(), minlength=K)
    a, b = edges[:, 0], edges[:, 1]
    chain_edge = (degree[a] <= 2) & (degree[b] <= 2)
    broken = _breaks(disp[a], disp[b], pos[a], pos[b]) & chain_edge
    if not broken.any():
        return disp, switched
    alt = walk_kernel.cluster_medians(
        np.ascontiguousarray(labels, dtype=np.int64), stereo.d_next.astype(np.float64), K
    )
    out = disp.copy()
    # a junction next to a chain's end holds it by its own (first) match: a stretch switched
    # there would move its break onto the junction's edge, not remove it
    junction_of = np.full(K, -1, dtype=np.int64)
    done = np.zeros(K, dtype=bool)  # second matches refined already
    lo = stereo.d_range[0]
    cost = np.ones(K)  # of each keypoint's second match, against its first
    to_junction = ~chain_edge & ((degree[a] > 2) != (degree[b] > 2))
    ja, jb = a[to_junction], b[to_junction]
    junction_of[np.where(degree[ja] > 2, jb, ja)] = np.where(degree[ja] > 2, ja, jb)
    for chain in _chains(K, edges[chain_edge], np.unique(a[broken])):
        head, tail = int(junction_of[chain[0]]), int(junction_of[chain[-1]])
        seq = np.array([head] * (head >= 0) + chain.tolist() + [tail] * (tail >= 0), np.int64)
        fixed = np.zeros(len(seq), dtype=bool)
        fixed[0], fixed[-1] = head >= 0, tail >= 0
        if refined:  # the second matches the choice would set, refined first (once)
            for k in seq[~fixed & ~done[seq]].tolist():
                idx = np.flatnonzero(labels == k)
                E = _summed_energy(stereo, idx) if len(idx) else np.zeros(0)
                alt[k] = _subpixel_of(E, lo, alt[k])
                done[k] = True
                # the pixels' own best matches (before the stereo membrane) are the second
                # match, not the first: the first is the membrane's value
                if own_energy and len(idx) and np.isfinite(alt[k]):
                    own = float(np.median(stereo.d_min[idx]))
                    if abs(own - alt[k]) <= 1.0 < abs(own - disp[k]):
                        cost[k] = -1.0
        choice = best_choice(disp[seq], np.where(fixed, np.nan, alt[seq]), pos[seq], cost[seq])
        switched[seq[choice & ~fixed]] = True
    if refined:
        out[switched] = alt[switched]  # each finite: a NaN second match is never taken
        return out, switched
    for k in np.flatnonzero(switched).tolist():
        sub = _subpixel(stereo, np.flatnonzero(labels == k), alt[k])
        if np.isfinite(sub):
            out[k] = sub
        else:
            switched[k] = False
    return out, switched


def depth_of(
    stereo: StereoResult, disparity: np.ndarray, near: np.ndarray | None = None
) -> np.ndarray:
    """Depths at ``disparity`` px (NaN where none), by the stereo result's own reprojection
    (fixed by the pixels ``near`` when two of them have distinct finite depths: fewer to
    search than all of P_L)."""
    slope, icpt = _inverse_depth_line(stereo, near)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = slope * np.asarray(disparity, dtype=np.float64) + icpt
        return np.where(inv > 0, 1.0 / inv, np.nan)


def disparity_of(
    stereo: StereoResult, depth: np.ndarray, near: np.ndarray | None = None
) -> np.ndarray:
    """The disparities, px, at which the stereo result reprojects to ``depth`` (NaN: none)."""
    slope, icpt = _inverse_depth_line(stereo, near)
    z = np.asarray(depth, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(z > 0, (1.0 / z - icpt) / slope, np.nan)


def _inverse_depth_line(stereo: StereoResult, near: np.ndarray | None) -> tuple[float, float]:
    """(a, b) with 1 / depth = a disparity + b: Eq. (4)-(5)'s reprojection of a rectified pair
    is affine in 1 / depth, so two pixels of distinct disparity with a depth fix it (those of
    least and greatest disparity among ``near``, else among all; NaN, NaN when none)."""
    for idx in (near, None):
        d = stereo.disparity if idx is None else stereo.disparity[idx]
        z = stereo.depth if idx is None else stereo.depth[idx]
        ok = np.flatnonzero(np.isfinite(z) & (z > 0))
        if len(ok) < 2:
            continue
        i, j = ok[np.argmin(d[ok])], ok[np.argmax(d[ok])]
        if d[j] > d[i]:
            slope = (1.0 / z[j] - 1.0 / z[i]) / (d[j] - d[i])
            return float(slope), float(1.0 / z[i] - slope * d[i])
    return float("nan"), float("nan")


def disparity_room(distance: Any) -> Any:
    """How far one strand's disparity may change over ``distance`` px of image (its continuity
    bound, shared by the ordering, continuity and bounds stages): slack + slope x distance."""
    return DISPARITY_SLACK_PX + DISPARITY_SLOPE * distance


def _breaks(da: np.ndarray, db: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Steps whose disparity change exceeds one strand's continuity bound (NaN: no break)."""
    dist = np.hypot(*(pa - pb).T)
    return np.abs(da - db) > disparity_room(dist)


def _chains(K: int, edges: np.ndarray, through: np.ndarray | None = None) -> list[np.ndarray]:
    """The chains of ``edges`` (A's edges between keypoints of degree <= 2: paths), each in
    order along A; only those through a keypoint of ``through`` when given (the ends of the
    broken steps: the others need no choice). A closed loop is opened where it was entered."""
    adj: list[list[int]] = [[] for _ in range(K)]
    for u, v in edges.tolist():
        adj[u].append(v)
        adj[v].append(u)
    seen = np.zeros(K, dtype=bool)
    out = []
    for s in range(K) if through is None else through.tolist():
        if seen[s] or not adj[s]:
            continue
        end, prev = s, -1  # to one end of s's chain (or once round a loop)
        while len(adj[end]) == 2:
            nxt = adj[end][0] if adj[end][0] != prev else adj[end][1]
            if nxt == s:
                break
            prev, end = end, nxt
        chain, prev, cur = [end], -1, end
        seen[end] = True
        while True:
            nxt = [v for v in adj[cur] if v != prev and not seen[v]]
            if not nxt:
                break
            prev, cur = cur, nxt[0]
            seen[cur] = True
            chain.append(cur)
        out.append(np.array(chain, dtype=np.int64))
    return out


def best_choice(
    first: np.ndarray, second: np.ndarray, pos: np.ndarray, cost: np.ndarray | None = None
) -> np.ndarray:
    """(n,) bool: which points of a sequence along one strand take their second match, by
    dynamic programming: cost ``VIOLATION_COST`` per step that breaks continuity, 1 per second
    match, and among equal counts the least total disparity change (the same choice along
    either direction). ``first``, ``second``: (n,) disparities, px (a NaN second match is never
    taken; a NaN first match breaks nothing); ``pos``: (n, 2) px; ``cost``: (n,) each second
    match's cost against its first (default 1; -1: the first match costs 1 instead)."""
    n = len(first)
    if n == 0:
        return np.zeros(0, dtype=bool)
    cand = np.stack([first, second], axis=1)  # (n, 2)
    bound = disparity_room(np.hypot(*np.diff(pos, axis=0).T))
    change = np.abs(cand[:-1, :, None] - cand[1:, None, :])  # (n-1, from, to)
    with np.errstate(invalid="ignore"):
        trans = VIOLATION_COST * (change > bound[:, None, None])
    trans = (trans + SMOOTH_TIE * np.nan_to_num(change, nan=0.0)).tolist()
    usable = np.isfinite(second).tolist()
    extra = [1.0] * n if cost is None else np.asarray(cost, dtype=np.float64).tolist()
    inf = float("inf")
    c0, c1 = 0.0, extra[0] if usable[0] else inf
    back = []
    for i in range(1, n):
        t = trans[i - 1]
        a0, b0 = c0 + t[0][0], c1 + t[1][0]
        a1, b1 = c0 + t[0][1], c1 + t[1][1]
        back.append((int(b0 < a0), int(b1 < a1)))  # the first match on a tie
        c0 = min(a0, b0)
        c1 = min(a1, b1) + extra[i] if usable[i] else inf
    choice = np.zeros(n, dtype=bool)
    s = int(c1 < c0)
    for i in range(n - 1, 0, -1):
        choice[i] = bool(s)
        s = back[i - 1][s]
    choice[0] = bool(s)
    return choice


def _subpixel(stereo: StereoResult, idx: np.ndarray, d0: float) -> float:
    """The minimum of the cluster's summed energy curve E(d) of Eq. (2) (its pixels ``idx``)
    nearest ``d0`` px: the local minimum within 1 px of the integer nearest ``d0``, refined by
    a parabola through it and its two neighbours; NaN where there is none."""
    if not len(idx) or not np.isfinite(d0):
        return float("nan")
    return _subpixel_of(_summed_energy(stereo, idx), stereo.d_range[0], d0)


def _summed_energy(stereo: StereoResult, idx: np.ndarray) -> np.ndarray:
    """The cluster's own energy curve: E(d) of Eq. (2) summed over its pixels ``idx``."""
    return _energy(stereo, idx).sum(axis=0)


def _subpixel_of(E: np.ndarray, lo: int, d0: float) -> float:
    """:func:`_subpixel` on the summed curve ``E`` (``lo``: the least disparity searched)."""
    if not np.isfinite(d0):
        return float("nan")
    j = int(round(d0))
    cands = [
        c for c in (j - 1, j, j + 1) if lo < c < len(E) - 1 and np.isfinite(E[c - 1 : c + 2]).all()
    ]
    cands = [c for c in cands if E[c] <= E[c - 1] and E[c] <= E[c + 1]]
    if not cands:
        return float("nan")
    c = min(cands, key=lambda v: E[v])
    den = E[c - 1] - 2.0 * E[c] + E[c + 1]
    step = 0.5 * (E[c - 1] - E[c + 1]) / den if den > 0 else 0.0
    return float(c + np.clip(step, -0.5, 0.5))


def second_match_subpixel(stereo: StereoResult, idx: np.ndarray) -> np.ndarray:
    """(n,) the second matches ``d_next`` of the pixels ``idx`` refined to sub-pixel by the
    stereo stage's own exact minimiser of Eq. (2) on [d_next - 1, d_next + 1] (an integer is
    0.5 px off, 5 % of depth at 10 px; a parabola through the energy locks to pixels: on
    generated hairpins its extra points lay 0.2-0.4 mm off and e_S rose 0.04 -> 0.07 mm), on
    the crop of the pair that holds the pixels' windows and matches."""
    d = stereo.d_next[idx].astype(np.int64)
    if not len(idx):
        return d.astype(np.float64)
    source, crop, at = _crop(stereo, idx)
    box = _Box.of(crop, source.d_hi)
    step, *_ = _subpixel_kernel(
        box.ry[at], box.rx[at], box.I_L_p, box.index, source.window // 2,
        np.ascontiguousarray(crop.I_R), box.y0, box.x0, d, source.d_hi, LIFT_VALUE,
    )  # fmt: skip
    return d + step


def _crop(stereo: StereoResult, idx: np.ndarray) -> tuple[Any, LiftedPair, np.ndarray]:
    """(energy source, the crop of its lifted pair that holds the windows of the pixels
    ``idx`` and every match they search, their indices among the crop's thread pixels in
    row-major order): the whole thread's box costs 0.3-2.5 ms a 640x480 frame."""
    source = stereo.__dict__.get("_source")
    if source is None:
        raise ValueError("this stereo result has no energy source (built by hand or copied)")
    lifted = source.lifted
    r = source.window // 2
    x, y = stereo.pixels[idx, 0], stereo.pixels[idx, 1]
    H, W = lifted.P_L.shape
    y0, y1 = max(0, int(y.min()) - r - 1), min(H, int(y.max()) + r + 2)
    x0, x1 = max(0, int(x.min()) - r - source.d_hi - 2), min(W, int(x.max()) + r + 2)
    box = (slice(y0, y1), slice(x0, x1))
    crop = LiftedPair(  # no score maps: Eq. (2) reads the lifted images and P_L only
        I_L=lifted.I_L[box],
        I_R=lifted.I_R[box],
        P_L=lifted.P_L[box],
        P_R=lifted.P_R[box],
        grey_L=lifted.grey_L[box],
        grey_R=lifted.grey_R[box],
        background=lifted.background,
        method=lifted.method,
    )
    index = np.cumsum(crop.P_L.ravel()) - 1  # row-major order of the crop's thread pixels
    return source, crop, index[(y - y0) * (x1 - x0) + (x - x0)]


def _energy(stereo: StereoResult, idx: np.ndarray) -> np.ndarray:
    """(n, d_hi + 1) float64 E(d, p) of Eq. (2) at the pixels ``idx`` of ``stereo``, from the
    crop of :func:`_crop` (each window's pixels and matches lie inside it)."""
    source, crop, at = _crop(stereo, idx)
    E = type(source)(crop, source.window, source.d_lo, source.d_hi).energy(at)
    return np.asarray(E, dtype=np.float64)
