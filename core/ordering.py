"""Topological ordering of keypoints (paper Sec. III-B, "Topological Ordering of Keypoints").

1. Solidification: every segmented pixel within ``solidify_radius`` px of a cluster joins it.
2. Adjacency graph A: a BFS on P_L (8-neighbours) from a cluster that may not enter other
   clusters reaches exactly the clusters that touch it directly or through a connected region of
   unclustered pixels ("gap"). So A is built without a BFS per cluster: label the gaps once,
   then every cluster touching a gap is adjacent to every other cluster touching it.
3. Greedy DFS from a keypoint of degree 1, always moving to the closest unexplored adjacent
   keypoint. Deviation: every degree-1 keypoint is tried as the start and the walk that keeps
   the most keypoints wins; where the walk ends with unvisited components of A left (a thread
   whose segmentation is broken), it jumps to the nearest keypoint of another component within
   ``bridge_px`` (0 disables this, as in the paper).
4. Endpoint extension: at each end keypoint, the unclustered pixels reachable only from its
   cluster (dead-end gaps) count; with at least ``extension_min_px`` of them the farthest one
   (geodesically, so that a curled tail ends at its tip) becomes a new keypoint with the end
   keypoint's depth. Deviation: otherwise, when the end cluster's own farthest pixel from the
   inward neighbour lies ``tip_px`` or more beyond the end keypoint, that pixel becomes the end.
5. Ends seen in one view only (deviation 33, ``mono_reach_px``, off by default): past the last
   pixel the right view shows, or across a short hidden stretch to a piece of P_L no stereo
   match reaches, the curve follows the left view's thread with depth from the end's
   continuity.

Cost scales with the thread, not the image: steps 1-2 and the geodesics work on the pixel list
of P_L and index images over its bounding box; the walk's steps to neighbours and through
crossings run in a compiled kernel (core/walk_kernel.py), jumps across gaps in numpy.
"""

from __future__ import annotations

import copy
import functools
import math
import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from threadrecon.core import walk_kernel
from threadrecon.core.clustering import Clusters
from threadrecon.core.continuity import depth_of, disparity_of, disparity_room, second_matches
from threadrecon.core.ends import seen_in_right, tip_disparity
from threadrecon.core.lazy import Deferred, LazyField
from threadrecon.core.numeric import distance_to_zero, row_norms
from threadrecon.core.params import Params, param
from threadrecon.core.segmentation import LiftedPair
from threadrecon.core.stereo import StereoResult

OUTLIER_PX = 2.0  # a pixel > 2 px of disparity from its cluster's median is another match
MAX_WALKS = 24  # walks tried per frame (ends, then runner-up turns of the best): bounded time
_NO_END_DISPARITY = np.array([[np.nan, np.inf], [np.nan, np.inf]])  # no end matched
MAX_REJECTED = 4  # rejected continuations kept per decision: a jump may see dozens, few matter


@dataclass(frozen=True)
class OrderingParams(Params):
    solidify_radius: int = param(
        1, lo=0, hi=10, unit="px", slider=(0, 6, 1), label="solidify radius"
    )
    """Segmented pixels within this distance of a cluster join it, px (paper: 1-2)."""
    extension_min_px: int = param(
        6, lo=0, hi=100000, unit="px", slider=(0, 60, 1), label="extension min px"
    )
    """Dead-end gap size at an end keypoint that triggers endpoint extension, px."""
    tip_px: float = param(2.0, lo=0, hi=1000, unit="px", slider=(0.0, 10.0, 0.5), label="tip px")
    """Extend an end to its cluster's tip when the tip lies this far beyond the end keypoint,
    px (0: off, the paper). The keypoint is a centroid, half a cluster short of the tip."""
    bridge_px: float = param(
        300.0, lo=0, hi=10000, unit="px", slider=(0.0, 300.0, 5.0), label="bridge px"
    )
    """Largest jump between components of A the walk may make, px (0: paper, no jump)."""
    metric: Literal["image", "3d"] = "image"
    """Distance for "closest adjacent keypoint": image-plane px (default) or 3D."""
    walk: Literal["bending", "greedy"] = param(
        "bending",
        label="walk",
        doc='"greedy" (paper): closest unexplored adjacent keypoint. "bending": the continuation '
        "of least bending and disparity change, passing through junctions already on the path "
        "(crossings) and across gaps (occlusions) when direction and depth agree.",
    )
    bend_weight: float = param(
        2.0,
        lo=0.0,
        hi=50.0,
        label="bending weight",
        doc="Step cost = distance * (1 + bend_weight * (1 - cos turn)) + ..., 1 (walk=bending).",
    )
    disparity_weight: float = param(
        10.0,
        lo=0.0,
        hi=1000.0,
        unit="px/px",
        label="disparity weight",
        doc="Step cost per px of disparity change from the recent path (walk=bending), px.",
    )
    end_window_px: int = param(7, lo=0, hi=50, unit="px", slider=(0, 20, 1), label="end window px")
    """Radius of the window on each end of the path matched in both views for the end's
    disparity, px (0: paper, the extension copies the end keypoint's depth). The search spans
    the end keypoint's disparity +- this (core/ends.py, deviation 23)."""
    tip_views: Literal["left", "both"] = param(
        "both",
        label="tip seen in",
        doc='Endpoint extension reaches the farthest pixel seen in "both" views (a right-view '
        "thread pixel on its row within end_window_px of the end keypoint's disparity; pixels "
        'only the left view shows have no depth) or in the "left" view alone (paper).',
    )
    max_turn_deg: float = param(
        60.0,
        lo=0.0,
        hi=180.0,
        unit="deg",
        label="max turn at a crossing",
        doc="A step through a crossing turns by at most this (unless nothing else is left); "
        "two touching strands at two depths are broken apart only where each goes on ahead "
        "within this (walk=bending). A jump over a gap turns in and out by at most 90 deg each.",
    )
    walk_runners: int = param(
        2,
        lo=1,
        hi=10,
        label="walk alternatives per step",
        doc="When the best walk leaves keypoints out, the walks branching off it are tried: at "
        "each of its steps, the continuations ranked 2 to this + 1 by cost (the runners-up "
        "of every step first, then the thirds; at most MAX_WALKS walks in all). 1: the "
        "runner-up only (before deviation 41): a stray keypoint just off the thread's "
        "direction, passed by the cheapest step, was then reached only by a zig-zag back "
        "over the strand (walk=bending).",
    )
    dead_end_tip: bool = param(
        False,
        label="dead end's tip depth",
        doc="Deviation 55: the tip of an endpoint extension (a dead end, often along the "
        "image rows where no window inside it matches) is matched in both views beyond "
        "end_window_px of the end keypoint's disparity, following the SSD's descent within "
        "the continuity bound over the dead end (continuity.disparity_room) and cut to the "
        "right image, and the extension takes the tip's depth instead of the end keypoint's: "
        "the dead end is interpolated between the two. Off: deviation 23's tip (the "
        "extension's depth copied, the tip only moves Eq. (8)'s end value).",
    )
    mono_reach_px: float = param(
        0.0,
        lo=0.0,
        hi=1000.0,
        unit="px",
        slider=(0.0, 200.0, 5.0),
        label="one-view end reach px",
        doc="A piece of P_L that no stereo match reaches (no cluster touches it, the right "
        "view does not show it: behind an instrument there) whose nearest pixel lies within "
        "this of a free end, ahead of it, continues the curve in the left view only; its "
        "depth is the end's, extrapolated along the end's slope (docs/method.md, deviation "
        "33; 0: off, the paper, and the default: on held-out frames the check called two "
        "curves it improved suspect or failed; 60 px is the check's max_jump_px).",
    )
    spur_px: float = param(
        6.0,
        lo=0.0,
        hi=1000.0,
        unit="px",
        slider=(0.0, 60.0, 1.0),
        label="side branch px",
        doc="A gap pixel of a link between two keypoints whose way from one to the other through "
        "it is longer than the link's shortest way by more than twice (the thread's width + "
        "this) lies on a side branch reaching this far past the strand (a spur of the mask, a "
        "stub of another strand), not between them: it is on no link, so no extra point of H "
        "leads the curve out along the branch and back (docs/method.md, deviation 35; 0: off, "
        "every pixel of the gap on the link, the paper).",
    )
    hidden_turn_deg: float = param(
        180.0,
        lo=0.0,
        hi=180.0,
        unit="deg",
        slider=(90.0, 180.0, 5.0),
        label="turn under an occluder",
        doc="A jump over a gap whose two ends both run under an occluder in both views (the "
        "pixels just past each end are neither thread nor bare background, in the left view "
        "and at the end's disparity in the right) turns in and out by at most this each, "
        "instead of 90 deg: the thread may bend by any amount where nothing shows it "
        "(docs/method.md, deviation 38; 90 or less: off, every jump 90 deg each; walk=bending).",
    )
    hidden_bridge_px: float = param(
        600.0,
        lo=0.0,
        hi=10000.0,
        unit="px",
        slider=(0.0, 1000.0, 10.0),
        label="jump under an occluder px",
        doc="When no jump within bridge_px is left, a jump of up to this between two ends that "
        "both run under an occluder in both views (deviation 38's hidden ends), its turns in "
        "and out within 90 deg each and its disparity within the continuity bound, whose "
        "straight way lies over no bare background in either view (at most "
        "CHORD_BARE_SHARE of its samples: the occluder could hide the thread all along it): "
        "a thread running under a shaft along its axis and out beyond it (docs/method.md, "
        "deviation 69; bridge_px or less: off, before session 22; walk=bending).",
    )
    join_free_ends: bool = param(
        False,
        label="join free ends",
        doc="A jump may join two ends that both stop over bare background in both views (the "
        "pixels just past each end are the background next to the thread: nothing hides the "
        "thread there, these are its own two ends). False (the default): such a jump is "
        "excluded (docs/method.md, deviation 38; True: as before, the paper; walk=bending).",
    )
    join_one_free_end: bool = param(
        False,
        label="join a free end to a hidden one",
        doc="A jump may join an end that stops over bare background in both views (free) to "
        "one that runs under an occluder in both views (hidden). False (the default): such a "
        "jump is excluded: the hidden stretch would have to leave the free end over the bare "
        "background, where the thread would be seen (docs/method.md, deviation 61; True: as "
        "before; walk=bending).",
    )
    retrace_px: float = param(
        120.0,
        lo=0.0,
        hi=10000.0,
        unit="px",
        slider=(0.0, 300.0, 5.0),
        label="second pass px",
        doc="A walk that comes back to a crossing it passed, with nothing left ahead, may run on "
        "along the path's own keypoints from there (two strands touching along a loop's "
        "crossing) for at most this and leave through an unvisited neighbour of one of them, "
        "each turn within max_turn_deg, the disparity agreeing (docs/method.md, deviation 44; "
        "0: off, the walk ends there; walk=bending).",
    )
    second_matches: bool = param(
        True,
        label="second matches by continuity",
        doc="A short stretch of keypoints that breaks depth continuity along a chain of A takes "
        "its second match where that removes the break (core/continuity.py, deviation 29; "
        "walk=bending).",
    )
    second_refined: bool = param(
        True,
        label="second matches chosen refined",
        doc="The choice of second_matches is made on the second matches it sets, refined on "
        "each cluster's summed energy curve first (none where that has no minimum there); off: "
        "on the pixels' integer median second match, refined after the choice, a keypoint "
        "whose refinement failed keeping its first match alone (docs/method.md, deviation 74).",
    )
    second_own_energy: bool = param(
        True,
        label="second match by its own energy",
        doc="With second_refined: a keypoint whose pixels' own best matches of Eq. (3) (their "
        "median d_min, before the stereo membrane) lie within 1 px of its second match and "
        "over 1 px from its first (the membrane's value) pays the choice's count for keeping "
        "its first match instead (docs/method.md, deviation 74).",
    )


@dataclass(frozen=True)
class Continuation:
    """One candidate next keypoint at a decision of the walk."""

    keypoint: int
    cost: float
    """Step cost of :func:`_walk_from` (px); inf when a rule excluded it (see ``reason``)."""
    reason: str
    """"chosen", "costlier", "turn > max_turn_deg" (through a crossing), "turn across the gap"
    (a jump whose piece does not continue the way the path goes), "two free ends" (a jump
    between two ends the views show stopping over bare background, deviation 38), or
    "cheaper, but its walk kept fewer keypoints" (the chosen walk is a runner-up walk)."""


@dataclass(frozen=True)
class Decision:
    """A step of the chosen walk where the walk had a choice or had to leave A.

    ``step``: index in ``Ordering.order`` of the keypoint ``at`` the walk stood on.
    ``kind``: "neighbour" (adjacent in A), "crossing" (two steps through a keypoint already on
    the path), "jump" (across a gap, within ``bridge_px``), "end" (every continuation excluded).
    ``chosen``: the keypoint the walk went to (-1 at an "end"), ``cost`` its step cost.
    ``rejected``: the other continuations, cheapest first (at most ``MAX_REJECTED``)."""

    step: int
    at: int
    kind: Literal["neighbour", "crossing", "jump", "end"]
    chosen: int
    cost: float
    rejected: tuple[Continuation, ...]


@dataclass(frozen=True)
class OrderingGraph:
    """Why the order came out as it did (the debugger's ordering-graph view).

    ``pieces``: the chains of keypoints of A between junctions and ends (each a tuple of
    keypoint ids in chain order; a keypoint with no neighbour is a piece of its own).
    ``junctions``: (J,) int, keypoints of degree >= 3 in A (crossings, touching turns, side
    branches). ``decisions``: the chosen walk's decisions (walk = "bending"; empty for the
    paper's greedy walk, whose only rule is the nearest neighbour)."""

    pieces: tuple[tuple[int, ...], ...]
    junctions: np.ndarray
    decisions: tuple[Decision, ...]


@dataclass(frozen=True)
class Ordering:
    """``pixels``: (N, 2) int (x, y) of P_L (``StereoResult.pixels``), ``image_shape``: (H, W).
    ``edges``: (E, 2) int, the adjacency graph A over keypoint ids.
    ``order``: (M,) int, ordered keypoint ids (phi); -1 marks an extension keypoint.
    ``path_px``: (M, 3) ordered keypoints in (x px, y px, z depth).
    ``links``: per consecutive pair of ``order`` (M-1 entries), the gap ids between them.
    ``dropped``: keypoint ids the walk did not keep (side branches).
    ``pixel_node``: (N,) node id of every pixel of P_L, aligned with ``StereoResult.pixels``.
    ``pixel_t``: (N,) position in [0, 1] of each gap pixel along the link it lies in, from the
    geodesic distances d_a, d_b to the link's two clusters (t = d_a / (d_a + d_b)); NaN elsewhere.
    ``pixel_link``: (N,) index of that link, -1 elsewhere.
    ``graph``: the pieces, junctions and the walk's decisions with their rejected
    continuations and costs (:class:`OrderingGraph`).
    ``end_disparity``: (2, 2) float, (disparity px, variance px^2) of the first and the last
    point of ``path_px`` matched on a window holding the tip in both views (core/ends.py);
    NaN, inf where not matched (``end_window_px`` = 0, a tip at the image border, no match).
    ``mono``: how many points at the start and at the end of ``path_px`` lie on a piece of P_L
    only the left view shows (``mono_reach_px``, :func:`_one_view_piece`): order -1, empty
    links, depth from the end's continuity, not from stereo.
    ``dead_end``: whether the first / the last point of ``path_px`` is the tip of a dead end
    (deviation 55, ``dead_end_tip``): an endpoint extension longer than the tip's window
    (2 ``end_window_px`` + 1 px), whose depth is the tip's matched in both views where
    ``end_disparity`` is finite, else the end keypoint's copied.
    """

    pixels: np.ndarray
    image_shape: tuple[int, int]
    n_clusters: int
    edges: np.ndarray
    order: np.ndarray
    path_px: np.ndarray
    links: tuple[tuple[int, ...], ...]
    dropped: np.ndarray
    pixel_node: np.ndarray
    pixel_t: np.ndarray
    pixel_link: np.ndarray
    graph: OrderingGraph = LazyField()  # type: ignore[assignment]  # built when read
    end_disparity: np.ndarray = field(default_factory=lambda: _NO_END_DISPARITY.copy())
    mono: tuple[int, int] = (0, 0)
    dead_end: tuple[bool, bool] = (False, False)

    @functools.cached_property
    def node_image(self) -> np.ndarray:
        """(H, W) int, cluster id (0..K-1) of solidified cluster pixels, K + gap id for
        unclustered segmented pixels, -1 off P_L (built on first use: 16 MB at 1920x1080)."""
        out = np.full(self.image_shape, -1, dtype=np.int64)
        out[self.pixels[:, 1], self.pixels[:, 0]] = self.pixel_node
        return out


def order_keypoints(
    lifted: LiftedPair,
    stereo: StereoResult,
    clusters: Clusters,
    p: OrderingParams = OrderingParams(),
) -> Ordering:
    """Solidify, build A, walk it, extend the ends."""
    if p.solidify_radius < 0:
        raise ValueError(f"solidify_radius must be >= 0, got {p.solidify_radius}")
    K = clusters.count
    H, W = lifted.P_L.shape
    if stereo.shape != (H, W) or len(clusters.labels) != len(stereo.pixels):
        raise ValueError(
            f"stereo result ({stereo.shape}, {len(stereo.pixels)} px) and clusters "
            f"({len(clusters.labels)} labels) do not belong to this {(H, W)} pair"
        )
    # Everything works on the pixel list of P_L and its bounding box: the thread, not the image.
    grid, nb = _pixel_grid(stereo.pixels, max(1, p.solidify_radius))
    cluster_of = _solidify(grid, clusters.labels, p.solidify_radius, nb)
    gaps = cluster_of < 0
    n_gaps, gap_of = grid.components(gaps, nb)
    pixel_node = np.where(gaps, K + gap_of - 1, cluster_of)
    geo = _GapGeodesics(stereo, pixel_node, K, nb=nb)

    pairs = _touching_pairs(pixel_node, geo.nb_node)
    cc = pairs[pairs[:, 1] < K]  # pairs are sorted: (a < b)
    cg = pairs[(pairs[:, 0] < K) & (pairs[:, 1] >= K)]  # (cluster, gap), unique, sorted
    cluster_gaps = _ClusterGaps(cg, K)
    edges = _edges(cc, cg)

    pos = clusters.keypoints_px[:, :2] if p.metric == "image" else clusters.keypoints
    disp = _cluster_median(clusters.labels, stereo.disparity, K)
    broken = edges[:0]
    switched = np.zeros(K, dtype=bool)
    if p.walk == "bending" and p.second_matches:  # a stretch matched to the neighbour
        disp, switched = second_matches(
            stereo,
            clusters.labels,
            disp,
            edges,
            clusters.keypoints_px[:, :2],
            p.second_refined,
            p.second_own_energy,
        )
    if p.walk == "bending":  # two strands touching where the mask lost their crossing
        edges, broken = _depth_breaks(
            edges, clusters.keypoints_px[:, :2], disp, K, _cos_deg(p.max_turn_deg)
        )
    adj = _adjacency(K, edges)
    if p.walk == "greedy":
        walk = _best_walk(K, edges, pos, clusters.keypoints_px[:, :2], p.bridge_px)
    else:
        across = _adjacency(K, broken) if len(broken) else None
        wg = _WalkGraph.of(
            adj,
            clusters.keypoints_px[:, :2],
            disp,
            across,
            lifted if p.hidden_turn_deg > 90 or not p.join_free_ends else None,
        )
        walk = _bending_walk(wg, p)

    links = cluster_gaps.shared(walk)
    key_px = clusters.keypoints_px
    if p.walk == "bending":  # keypoint depth without pixels matched far from the cluster's
        d_med = disp
        lab = clusters.labels
        inlier = (lab >= 0) & np.isfinite(stereo.depth)
        inlier[inlier] &= np.abs(stereo.disparity[inlier] - d_med[lab[inlier]]) <= OUTLIER_PX
        n_in = np.bincount(lab[inlier], minlength=K)
        z_in = np.bincount(lab[inlier], weights=stereo.depth[inlier], minlength=K)
        z_in = np.where(n_in > 0, z_in / np.maximum(n_in, 1), key_px[:, 2])
        if switched.any():  # their second match: no pixel's first match lies near it
            z_in[switched] = depth_of(stereo, disp[switched])
        key_px = np.column_stack([key_px[:, :2], z_in])
    path = [key_px[k] for k in walk]
    order = list(walk)

    # Endpoint extension at both ends, then the geodesic position of every gap pixel.
    gap_size = np.bincount(gap_of[gaps], minlength=n_gaps)
    cut_tips: dict[int, int] = {}  # end -> tip pixel, where the tip stops short of the gap's end
    for end in (0, -1):
        k = order[end]
        dead = cluster_gaps.dead_ends(k)
        n_dead = int(sum(gap_size[g - K + 1] for g in dead))
        if n_dead >= p.extension_min_px:
            every = np.flatnonzero(np.isin(pixel_node, dead))
            sel = _tip_candidates(every, lifted, stereo, disp[k], p)
            if len(walk) > 1:
                sel = _ahead_of_jump(sel, stereo.pixels, key_px, walk, end, adj)
            if not len(sel):
                continue
            d = geo.distance_from(k, sel)
            far = sel[int(np.argmax(np.where(np.isfinite(d), d, -1.0)))]  # geodesically farthest
            if len(sel) < len(every):
                cut_tips[end] = int(far)
        elif p.tip_px > 0 and len(walk) > 1:
            inner = clusters.keypoints_px[walk[1] if end == 0 else walk[-2], :2]
            sel = _tip_candidates(np.flatnonzero(pixel_node == k), lifted, stereo, disp[k], p)
            if not len(sel):
                continue
            far = sel[int(np.argmax(np.sum((stereo.pixels[sel] - inner) ** 2, axis=1)))]
            if np.linalg.norm(stereo.pixels[far] - clusters.keypoints_px[k, :2]) < p.tip_px:
                continue
            dead = []
        else:
            continue
        z_end = key_px[k][2] if switched[k] else clusters.keypoints_px[k][2]
        new = np.array([*stereo.pixels[far], z_end], dtype=np.float64)
        if end == 0:
            path.insert(0, new)
            order.insert(0, -1)
            links.insert(0, tuple(dead))
        else:
            path.append(new)
            order.append(-1)
            links.append(tuple(dead))
    pixel_t, pixel_link = _link_positions(
        geo,
        pixel_node,
        links,
        order,
        K + n_gaps,
        {(0 if e == 0 else len(links) - 1): px for e, px in cut_tips.items()},
        np.array([q[:2] for q in path], dtype=np.float64).reshape(-1, 2),
        stereo.pixels,
        p.spur_px,
    )
    mono = [0, 0]
    if p.mono_reach_px > 0 and walk:
        linked = {g for gap_ids in links for g in gap_ids}
        touched = set(cg[:, 1].tolist())  # gaps some cluster touches: stereo reaches them
        lone = np.array(
            [g for g in range(K, K + n_gaps) if g not in linked and g not in touched], np.int64
        )
        for row, end in enumerate((0, -1)):
            beyond = None
            if end in cut_tips:  # the left view's thread past the last pixel the right shows
                tip_px = cut_tips[end]
                past = np.flatnonzero(
                    (pixel_node == pixel_node[tip_px]) & (pixel_link < 0) & np.isnan(pixel_t)
                )
                d_tip = float(disp[order[1] if end == 0 else order[-2]])
                past = past[stereo.pixels[past, 0] - d_tip >= 0]  # inside the right image
                beyond = (tip_px, past)
            pts, gap = _one_view_piece(
                path, end, lone, pixel_node, geo, lifted, stereo, p, np.array(order) >= 0, beyond
            )
            if not len(pts):
                continue
            mono[row] = len(pts)
            lone = lone[lone != gap]
            n = len(pts)
            if end == 0:
                path[:0] = list(pts[::-1])
                order[:0] = [-1] * n
                links[:0] = [()] * n
                pixel_link = np.where(pixel_link >= 0, pixel_link + n, -1)
            else:
                path += list(pts)
                order += [-1] * n
                links += [()] * n
    end_disparity = _NO_END_DISPARITY.copy()
    dead_end = [False, False]
    if p.end_window_px > 0 and walk:
        r = p.end_window_px
        for row, (e, k) in enumerate(((0, walk[0]), (-1, walk[-1]))):
            # Deviation 55: an extension longer than the tip's window is a dead end, whose
            # tip lies beyond the end keypoint's own evidence (16153's raw suites, masks
            # given: over 90 extensions of 2-15 px the tip's disparity is 0.13 px off the
            # truth on average, the keypoint's 0.10; over 14 of 15-266 px 0.19 and 0.91)
            length = float(np.linalg.norm(path[e][:2] - key_px[k, :2]))
            dead_end[row] = p.dead_end_tip and order[e] < 0 and not mono[row] and length > 2 * r + 1
            seq = walk if e == 0 else walk[::-1]
            own = _window_is_own(
                stereo.pixels, pixel_node, K, seq, key_px, cluster_gaps, path[e], r, grid
            )
            if own and e not in cut_tips and not mono[row]:  # what only the left sees
                reach = float(disparity_room(length)) if dead_end[row] else 0.0
                m = tip_disparity(lifted.I_L, lifted.I_R, path[e][:2], disp[k], r, reach)
                end_disparity[row] = (m.disparity, m.var)
                # the tip's own depth, not the end keypoint's copied, where one strand can
                # run from the keypoint to it (the continuity bound over the dead end; else
                # the keypoint or the tip is wrong, and which is not known: the copy stays,
                # and the tip only moves Eq. (8)'s end value, as deviation 23's)
                if dead_end[row] and abs(m.disparity - disp[k]) <= reach:
                    z_tip = float(depth_of(stereo, np.array([m.disparity]))[0])
                    if np.isfinite(z_tip):
                        path[e] = np.array([path[e][0], path[e][1], z_tip])

    kept = set(walk)
    dropped = np.array([k for k in range(K) if k not in kept], dtype=np.int64)
    lead = mono[0] + int(order[mono[0]] < 0)  # path points before the walk's first keypoint
    explain = (wg, lead) if p.walk == "bending" and walk else None
    return Ordering(
        pixels=stereo.pixels,
        image_shape=(H, W),
        n_clusters=K,
        edges=edges,
        order=np.array(order, dtype=np.int64),
        path_px=np.array(path, dtype=np.float64).reshape(-1, 3),
        links=tuple(links),
        dropped=dropped,
        pixel_node=pixel_node,
        pixel_t=pixel_t,
        pixel_link=pixel_link,
        graph=Deferred(_graph, adj, walk, explain, p),  # no stage reads it: the debugger's
        end_disparity=end_disparity,
        mono=(mono[0], mono[1]),
        dead_end=(dead_end[0], dead_end[1]),
    )


def _graph(
    adj: list[list[int]],
    walk: list[int],
    explain: tuple[_WalkGraph, int] | None,
    p: OrderingParams,
) -> OrderingGraph:
    """:class:`OrderingGraph` of A (``adj``) and the bending walk's decisions (``explain``:
    its walk graph and the offset of the walk in the order; None: no decisions)."""
    degree = np.array([len(a) for a in adj], dtype=np.int64)
    decisions = _explain(walk, explain[0], p, offset=explain[1]) if explain is not None else ()
    return OrderingGraph(_pieces(adj), np.flatnonzero(degree >= 3), decisions)


def _edges(cc: np.ndarray, cg: np.ndarray) -> np.ndarray:
    """(E, 2) edges of A, sorted, a < b: the clusters that touch (``cc``) and every two clusters
    touching one gap (``cg``: (cluster, gap) pairs, sorted), all gaps at once."""
    o = np.argsort(cg[:, 1], kind="stable")  # by gap, clusters ascending within a gap
    c, g = cg[o, 0], cg[o, 1]
    start = np.flatnonzero(np.concatenate([[True], g[1:] != g[:-1]])) if g.size else g
    size = np.diff(np.append(start, g.size))
    rank = np.arange(g.size) - np.repeat(start, size)  # position within its gap
    after = np.repeat(size, size) - 1 - rank  # members after it in its gap
    first = np.repeat(np.arange(g.size), after)  # each pair (i, j > i) of a gap's members
    j = np.arange(first.size) - np.repeat(np.cumsum(after) - after, after) + first + 1
    both = np.concatenate([cc, np.stack([c[first], c[j]], axis=1)]).astype(np.int64)
    m = int(both.max()) + 1 if both.size else 1
    key = np.unique(both[:, 0] * m + both[:, 1])  # rows sorted: (a, b) as one integer
    return np.stack([key // m, key % m], axis=1)


class _ClusterGaps:
    """The gaps each cluster touches and the clusters each gap touches, from the sorted unique
    (cluster, gap) pairs ``cg`` (no dict of sets per cluster: 600-800 keypoints at 1920x1080).
    ``get(c, default)``: the set of gaps of cluster c, as a dict of sets would give it."""

    def __init__(self, cg: np.ndarray, K: int) -> None:
        self.cg = cg
        self.ptr = np.searchsorted(cg[:, 0], np.arange(K + 1))  # cluster c: cg[ptr[c]:ptr[c+1]]
        self.m = int(cg[:, 1].max()) + 1 if len(cg) else 1
        self.key = cg[:, 0] * self.m + cg[:, 1]  # sorted
        gaps, count = np.unique(cg[:, 1], return_counts=True)
        self.single = set(gaps[count == 1].tolist())  # gaps touching one cluster only

    def gaps(self, c: int) -> np.ndarray:
        """The gaps cluster c touches, ascending."""
        return self.cg[self.ptr[c] : self.ptr[c + 1], 1]

    def get(self, c: int, default: set[int] | None = None) -> set[int] | None:
        g = self.gaps(c)
        return set(g.tolist()) if g.size else default

    def dead_ends(self, c: int) -> list[int]:
        """The gaps that touch cluster c and no other, ascending."""
        return [g for g in self.gaps(c).tolist() if g in self.single]

    def shared(self, walk: list[int]) -> list[tuple[int, ...]]:
        """Per consecutive pair (a, b) of ``walk``, the gaps both touch, ascending."""
        if len(walk) < 2:
            return []
        a, b = np.array(walk[:-1], np.int64), np.array(walk[1:], np.int64)
        lo, hi = self.ptr[a], self.ptr[a + 1]
        n = hi - lo
        link = np.repeat(np.arange(len(a)), n)  # an entry per (link, gap of its a)
        idx = np.arange(link.size) - np.repeat(np.cumsum(n) - n, n) + lo[link]
        want = b[link] * self.m + self.cg[idx, 1]
        at = np.minimum(np.searchsorted(self.key, want), max(len(self.key) - 1, 0))
        hit = self.key[at] == want if len(self.key) else np.zeros(0, bool)
        out: list[list[int]] = [[] for _ in range(len(a))]
        for i, g in zip(link[hit].tolist(), self.cg[idx[hit], 1].tolist(), strict=True):
            out[i].append(g)
        return [tuple(x) for x in out]


def _window_is_own(
    pixels: np.ndarray,
    pixel_node: np.ndarray,
    K: int,
    seq: list[int],
    key_px: np.ndarray,
    cluster_gaps: Mapping[int, set[int]] | _ClusterGaps,
    tip: np.ndarray,
    radius: int,
    grid: _PixelGrid | None = None,
) -> bool:
    """True when every pixel of P_L in the (2 radius + 1)^2 window on ``tip`` belongs to the
    thread's own last stretch: a cluster of the walk ``seq`` (from this end) whose keypoint lies
    within 3 ``radius`` px of arc of the tip (and the next one), or a gap touching one. Another
    strand in the window (the end pokes out past a crossing, a hairpin's other leg) moves by
    its own disparity, and the tip's match, which assumes one strand, is then wrong (generated
    crossing frame: 4.4 px off with a 0.3 px sd). ``grid``: the pixels' index image
    (:class:`_PixelGrid` of ``pixels``), to read the window from instead of testing every
    pixel."""
    cx, cy = np.round(tip[:2])
    if grid is None:
        inbox = np.all(np.abs(pixels - np.array([cx, cy])) <= radius, axis=1)
        window = pixel_node[inbox]
    else:
        window = pixel_node[grid.window(cx, cy, radius)]
    nodes = set(window.tolist())  # each node once (the test below reads no order)
    xy = key_px[seq, :2]
    arc = np.linalg.norm(xy[0] - tip[:2]) + np.concatenate(
        [[0.0], np.cumsum(row_norms(np.diff(xy, axis=0)))]
    )
    own = set(seq[: int(np.searchsorted(arc, 3.0 * radius, side="right")) + 1])
    own_gaps = set().union(*(cluster_gaps.get(c, set()) for c in own))
    return all((n in own) if n < K else (n in own_gaps) for n in nodes)


class _GapGeodesics:
    """Geodesic (8-connected, unit/sqrt2 steps) distances inside gaps from a cluster's border.

    The gap graph (an edge between 8-neighbours of the same gap) is never built: the compiled
    search (:func:`walk_kernel.gap_distances`) reads it from the neighbour table and the nodes."""

    def __init__(
        self,
        stereo: StereoResult,
        pixel_node: np.ndarray,
        K: int,
        nb: np.ndarray | None = None,
    ) -> None:
        """``nb``: (N, 8) neighbour pixel indices of :meth:`_PixelGrid.neighbours`, if known."""
        if nb is None:
            nb = _PixelGrid(stereo.pixels, 1).neighbours()
        self.nb = np.ascontiguousarray(nb, dtype=np.int32)
        self.node = np.ascontiguousarray(pixel_node, dtype=np.int64)
        self.K = K
        self.nb_node = np.where(nb >= 0, pixel_node[np.maximum(nb, 0)], -1)

    def distances(self, src: np.ndarray) -> np.ndarray:
        """(N,) geodesic distances from the pixels ``src`` inside their gaps, px; inf where
        unreachable (the multi-source search of scipy's ``csgraph.dijkstra(min_only=True)``)."""
        return walk_kernel.gap_distances(
            self.nb, self.node, self.K, _STEPS_8, np.ascontiguousarray(src, dtype=np.int64)
        )

    def distance_from(self, cluster: int, sel: np.ndarray) -> np.ndarray:
        """Distances of pixels ``sel`` (whole gaps) from the border of ``cluster``, px."""
        src = sel[np.any(self.nb_node[sel] == cluster, axis=1)]
        if src.size == 0:
            return np.full(sel.size, np.nan)
        d = self.distances(src)[sel]
        return np.where(np.isinf(d), np.nan, d + 1.0)


def _cluster_median(labels: np.ndarray, values: np.ndarray, K: int) -> np.ndarray:
    """(K,) median of ``values`` over each cluster's pixels (finite values only; NaN if none).

    A single pixel matched at the wrong disparity (e.g. 0.09 px among 31 px: 50 m deep) moves a
    cluster's mean depth by metres; its median not at all. Compiled
    (:func:`walk_kernel.cluster_medians`: the order of ``np.lexsort((values, labels))``, 1.2 ms
    of it at 1920x1080)."""
    if values.dtype != np.float64:
        raise ValueError(f"cluster medians need float64 values, got {values.dtype}")
    return walk_kernel.cluster_medians(
        np.ascontiguousarray(labels, dtype=np.int64), np.ascontiguousarray(values), K
    )


def _ahead_of_jump(
    sel: np.ndarray,
    pixels: np.ndarray,
    key_px: np.ndarray,
    walk: list[int],
    end: int,
    adj: list[list[int]],
) -> np.ndarray:
    """The pixels of ``sel`` (an end keypoint's dead-end gaps) ahead of the end, where the walk
    reached it by a jump (the end and its inner neighbour are not adjacent in A): a dead end
    behind the end keypoint (towards the inner one) is the thread the jump passed over (its
    side of an occluder), not the thread's free end: extended to, the curve ran out to the
    end and back over it (generated raw frame 13170 all #2: a 31 px fold at the shaft)."""
    k, inner = (walk[0], walk[1]) if end == 0 else (walk[-1], walk[-2])
    if inner in adj[k] or not len(sel):
        return sel
    out = key_px[k, :2] - key_px[inner, :2]
    return sel[(pixels[sel] - key_px[k, :2]) @ out > 0]


def _tip_candidates(
    sel: np.ndarray, lifted: LiftedPair, stereo: StereoResult, d_ref: float, p: OrderingParams
) -> np.ndarray:
    """The pixels of ``sel`` (indices into ``stereo.pixels``) an end may extend to: all of them
    (``tip_views = "left"``, the paper), or those the right view shows too (:func:`seen_in_right`
    within ``end_window_px`` of the end keypoint's disparity ``d_ref``)."""
    if p.tip_views == "left" or not np.isfinite(d_ref):
        return sel
    return sel[seen_in_right(stereo.pixels[sel], lifted.P_R, d_ref, max(p.end_window_px, 1))]


MONO_MIN_PX = 15  # a piece of P_L smaller than a tip window (2 x 7 + 1 px) is no thread's end
MONO_STEP_PX = 12  # px of geodesic length per point placed on a one-view piece
MONO_FIT_KEYPOINTS = 4  # the end's depth slope: least squares over its last keypoints
MONO_MAX_TURN_DEG = 90.0  # the jump onto the piece turns in and out by at most this (28's)


def _one_view_piece(
    path: list[np.ndarray],
    end: int,
    lone: np.ndarray,
    pixel_node: np.ndarray,
    geo: _GapGeodesics,
    lifted: LiftedPair,
    stereo: StereoResult,
    p: OrderingParams,
    is_key: np.ndarray,
    beyond: tuple[int, np.ndarray] | None = None,
) -> tuple[np.ndarray, int]:
    """Points (x px, y px, z depth), from the end outwards, on the piece of P_L that continues
    the path's ``end`` (0 or -1) in the left view only, and the piece's gap id (-1: none).

    ``beyond``: (tip pixel, pixels) where the endpoint extension stopped at the last pixel the
    right view shows (``tip_views = "both"``) and left view's thread goes on (the pixels past
    that tip whose right-view position lies inside the right image: hidden there, not cut by
    its border). Those pixels, when at least ``MONO_MIN_PX``, are the piece, entered at the tip.

    ``lone``: the gaps no cluster touches (no reliable stereo match reaches them) and no link
    holds. A candidate's nearest pixel lies within ``mono_reach_px`` of the end's tip, the jump
    to it turns by at most ``MONO_MAX_TURN_DEG`` from the end's way, and the piece leaves that
    pixel turning by at most as much from the jump; the right view does not show it (most of
    its pixels have no right thread pixel near the end's disparity, :func:`seen_in_right`):
    behind an instrument there, so stereo has no depth for it. The nearest such piece wins.

    Its pixels are ordered by geodesic distance from that entry pixel and cut into runs of
    ``MONO_STEP_PX``, one point per run (the centroid) and the farthest pixel as the new tip.
    Each pixel constrains the thread to its ray; the depth along it is not observed and is
    taken from continuity: the end keypoints' least-squares line of depth against 2D arc
    length (the last ``MONO_FIT_KEYPOINTS``), extrapolated over the hidden jump and along the
    piece, its disparity held within the ordering's continuity bound from the end's
    (``continuity.disparity_room`` of the distance) and within the disparities the
    stereo searched. No piece where the right view shows bare background at most of those
    points (:func:`_bare_in_right`): there it would see the thread, so nothing hides it."""
    none = np.zeros((0, 3)), -1
    if len(path) < 2 or (not len(lone) and beyond is None):
        return none
    P = np.array(path, dtype=np.float64)
    if end == 0:
        P = P[::-1]
    tip = P[-1, :2]
    # the end's way: from the point about a tip window back to the tip
    back = np.linalg.norm(P[:, :2] - tip, axis=1)
    far = np.flatnonzero(back >= MONO_MIN_PX)
    if not len(far):
        return none
    way = tip - P[far[-1], :2]
    way /= np.linalg.norm(way)
    cos_max = math.cos(math.radians(MONO_MAX_TURN_DEG))
    if beyond is not None and len(beyond[1]) >= MONO_MIN_PX:
        entry, sel = beyond
        g = int(pixel_node[entry])
    else:
        on = np.flatnonzero(np.isin(pixel_node, lone))
        if not len(on):
            return none
        xy = stereo.pixels[on].astype(np.float64)
        dist = np.hypot(*(xy - tip).T)
        best: tuple[float, int] | None = None
        for g in np.unique(pixel_node[on]).tolist():
            mine = pixel_node[on] == g
            if mine.sum() < MONO_MIN_PX:
                continue
            i = int(np.argmin(np.where(mine, dist, np.inf)))
            if dist[i] > p.mono_reach_px or (best is not None and dist[i] >= best[0]):
                continue
            jump = xy[i] - tip
            if dist[i] > 0 and float(jump @ way) < cos_max * dist[i]:
                continue  # behind or beside the end
            best = (float(dist[i]), g)
        if best is None:
            return none
        g = best[1]
        sel = on[pixel_node[on] == g]
        entry = sel[int(np.argmin(np.hypot(*(stereo.pixels[sel] - tip).T)))]
    d = geo.distances(np.array([entry]))[sel]
    ok = np.isfinite(d)
    sel, d = sel[ok], d[ok]
    run = (d // MONO_STEP_PX).astype(np.int64)
    n_run = int(run.max()) + 1
    cnt = np.bincount(run, minlength=n_run)
    keep = cnt > 0
    pix = stereo.pixels[sel].astype(np.float64)
    cx = np.bincount(run, weights=pix[:, 0], minlength=n_run)[keep] / cnt[keep]
    cy = np.bincount(run, weights=pix[:, 1], minlength=n_run)[keep] / cnt[keep]
    s_in = np.bincount(run, weights=d, minlength=n_run)[keep] / cnt[keep]
    pts = np.column_stack([cx, cy])
    out_tip = pix[int(np.argmax(d))]
    pts = np.vstack([pts, out_tip])
    s_in = np.append(s_in, d.max())
    if len(pts) >= 2:  # the piece leaves its entry along the jump, not back towards the end
        lead = pts[min(1, len(pts) - 1)] - stereo.pixels[entry]
        jump = stereo.pixels[entry] - tip
        nl, nj = np.linalg.norm(lead), np.linalg.norm(jump)
        if nl > 0 and nj > 0 and float(lead @ jump) < cos_max * nl * nj:
            return none
    # depth from continuity: the end keypoints' line, from the last one outwards
    kp = P[np.asarray(is_key, dtype=bool)[::-1] if end == 0 else np.asarray(is_key, dtype=bool)]
    kp = kp[-MONO_FIT_KEYPOINTS:]
    if not len(kp) or not np.all(np.isfinite(kp[:, 2]) & (kp[:, 2] > 0)):
        return none
    s_kp = np.concatenate([[0.0], np.cumsum(row_norms(np.diff(kp[:, :2], axis=0)))])
    s_kp -= s_kp[-1]
    z0, slope = float(kp[-1, 2]), 0.0
    if len(kp) >= 2:
        ds = s_kp - s_kp.mean()
        slope = float(ds @ (kp[:, 2] - kp[:, 2].mean())) / float(ds @ ds)
        z0 = float(kp[:, 2].mean() + slope * (0.0 - s_kp.mean()))
    d_end = float(disparity_of(stereo, np.array([z0]))[0])
    if not (np.isfinite(d_end) and d_end > 0):
        return none
    seen = seen_in_right(pix.astype(np.int64), lifted.P_R, d_end, max(p.end_window_px, 1))
    if beyond is None and np.mean(seen) >= 0.5:
        return none  # the right view shows it: not hidden there
    s = float(np.hypot(*(tip - kp[-1, :2]))) + float(np.hypot(*(stereo.pixels[entry] - tip))) + s_in
    z = z0 + slope * s
    with np.errstate(divide="ignore", invalid="ignore"):
        d_lin = disparity_of(stereo, z)
    d_lin = np.where(np.isfinite(d_lin), d_lin, d_end)
    room = disparity_room(s)
    d_lo, d_hi = stereo.d_range
    d_new = np.clip(np.clip(d_lin, d_end - room, d_end + room), max(d_lo, 1), d_hi)
    z = depth_of(stereo, d_new)
    if not np.all(np.isfinite(z) & (z > 0)):
        return none
    if _bare_in_right(lifted, pts, d_new):
        return none  # the right view shows what lies beside the thread there: no thread
    return np.column_stack([pts, z]), g


MONO_BARE_LEVELS = 10.0  # grey levels: the right view's pixel is the bare background within this


def _bare_in_right(lifted: LiftedPair, pts: np.ndarray, d: np.ndarray) -> bool:
    """Whether the right view shows bare background where most points ``pts`` ((P, 2) x, y px,
    left view) project at disparities ``d``: the median grey of the 3 x 3 right pixels there
    within ``MONO_BARE_LEVELS`` of the median grey of the left view's non-thread pixels in the
    15 x 15 window around the point (what lies beside the thread). An instrument in front of
    the thread shows its own grey; bare background means the right view would see the thread
    there, and it does not (a mask that ends short, a glint): no thread for it to hide."""
    H, W = lifted.P_L.shape
    bare = 0
    r = MONO_MIN_PX // 2
    for (x, y), dd in zip(np.rint(pts).astype(np.int64), np.asarray(d, float), strict=True):
        xr = int(round(x - dd))
        if not (1 <= y < H - 1 and 1 <= xr < W - 1):
            continue
        win = (slice(max(y - r, 0), y + r + 1), slice(max(x - r, 0), x + r + 1))
        side = lifted.grey_L[win][~lifted.P_L[win]]
        if not side.size:
            continue
        g_r = float(np.median(lifted.grey_R[y - 1 : y + 2, xr - 1 : xr + 2]))
        bare += abs(g_r - float(np.median(side))) <= MONO_BARE_LEVELS
    return 2 * bare > len(pts)


def _link_positions(
    geo: _GapGeodesics,
    pixel_node: np.ndarray,
    links: list[tuple[int, ...]],
    order: list[int],
    n_nodes: int,
    tips: dict[int, int] | None = None,
    path_xy: np.ndarray | None = None,
    pixels: np.ndarray | None = None,
    spur_px: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """``pixel_t``, ``pixel_link`` of every gap pixel on a link, from two multi-source geodesic
    searches (from the link's first cluster and from its second, all links at once: gaps are
    disjoint, and the gap graph has no edge between two gaps).

    An extension link runs from its end keypoint (t = 0 at the end, 1 at the start's tip) to
    the gap's farthest pixel, or to ``tips[link]`` (a pixel index) where the extension stopped
    short of it: the pixels beyond that tip lie on no link. ``path_xy``: (M, 2) px, the ordered
    keypoints (``order``'s), and ``pixels``: (N, 2) (x, y) of P_L, to split a gap on three
    links or more, or on two of four distinct keypoints, along the strands
    (:func:`_split_shared`). ``spur_px`` > 0: a pixel of a link between two keypoints whose
    detour d_a + d_b exceeds the link's shortest way (the least d_a + d_b over its pixels) by
    more than 2 (w + ``spur_px``) lies on a side branch: on no link (a spur walked out and back
    by the extra points otherwise). A pixel across the strand detours by up to about 2 w (w:
    the thread's width, the links' pixels per px of shortest way), one on a branch reaching l
    px past the strand by 2 (w + l)."""
    n = len(pixel_node)
    pixel_t = np.full(n, np.nan)
    pixel_link = np.full(n, -1, dtype=np.int64)
    link_of = np.full(n_nodes, -1, dtype=np.int64)
    link_lo = np.full(n_nodes, len(links), dtype=np.int64)
    if links:
        n_ids = [len(g) for g in links]
        ids = np.fromiter((g for gap_ids in links for g in gap_ids), np.int64, sum(n_ids))
        np.maximum.at(link_of, ids, np.repeat(np.arange(len(links)), n_ids))
        np.minimum.at(link_lo, ids, np.repeat(np.arange(len(links)), n_ids))
    ends = np.array(order, dtype=np.int64)
    px_link = np.where(pixel_node >= 0, link_of[np.maximum(pixel_node, 0)], -1)
    if np.any((link_lo < link_of)[np.maximum(pixel_node, 0)] & (pixel_node >= 0)):
        gap_links: dict[int, list[int]] = {}
        for i, gap_ids in enumerate(links):
            for g in gap_ids:
                gap_links.setdefault(g, []).append(i)
        gap_links = {g: ls for g, ls in gap_links.items() if len(ls) > 1}
        geo, px_link = _split_shared(
            geo, pixel_node, px_link, link_lo, ends, path_xy, pixels, gap_links
        )
    sel = np.flatnonzero(px_link >= 0)
    if sel.size == 0:
        return pixel_t, pixel_link
    lk = px_link[sel]
    a, b = ends[lk], ends[lk + 1]
    nb = geo.nb_node[sel]
    d = []
    for end in (a, b):
        src = sel[(end >= 0) & np.any(nb == end[:, None], axis=1)]
        if src.size == 0:
            d.append(np.full(sel.size, np.nan))
            continue
        dist = geo.distances(src)[sel]
        d.append(np.where(np.isinf(dist), np.nan, dist + 1.0))
    da, db = d
    top_a = np.zeros(len(links))
    top_b = np.zeros(len(links))
    np.fmax.at(top_a, lk, np.where(np.isfinite(da), da, 0.0))
    np.fmax.at(top_b, lk, np.where(np.isfinite(db), db, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        t = da / (da + db)
        t = np.where(a < 0, 1.0 - db / top_b[lk], t)  # extension at the start: reversed
        t = np.where(b < 0, da / top_a[lk], t)
    beyond = np.zeros(sel.size, dtype=bool)
    for link, tip in (tips or {}).items():  # the tip's own distance sets the scale
        on, at = lk == link, sel == tip
        if not at.any():
            continue
        if b[at][0] < 0:
            t[on] = da[on] / da[at][0]
        else:
            t[on] = 1.0 - db[on] / db[at][0]
        beyond |= on & ((t < 0.0) | (t > 1.0))
    if spur_px > 0:  # a side branch of an interior link: its detour through the pixel
        way = da + db
        inner = (a >= 0) & (b >= 0) & np.isfinite(way)
        short = np.full(len(links), np.inf)
        np.fmin.at(short, lk[inner], way[inner])
        fin = np.isfinite(short)
        width = np.count_nonzero(inner) / max(float(np.sum(short[fin])), 1.0)
        beyond |= inner & (way - short[lk] > 2.0 * (width + spur_px))
    pixel_t[sel] = np.where(np.isfinite(t) & ~beyond, t, np.nan)
    pixel_link[sel] = np.where(beyond, -1, lk)
    return pixel_t, pixel_link


def _split_shared(
    geo: _GapGeodesics,
    pixel_node: np.ndarray,
    px_link: np.ndarray,
    link_lo: np.ndarray,
    ends: np.ndarray,
    path_xy: np.ndarray | None = None,
    pixels: np.ndarray | None = None,
    gap_links: dict[int, list[int]] | None = None,
) -> tuple[_GapGeodesics, np.ndarray]:
    """A gap on two links (it touches three clusters, or four at a crossing) split between
    them, the same whichever end the walk started from (issue 12): each of its pixels goes to
    the link whose own end (one the other link does not share) is geodesically nearer, none on
    a tie. A gap on three links or more, or on two of four distinct keypoints (a crossing, or
    two strands that touch side by side over a stretch with no keypoint: a loop's crossing
    along its tangent), is split along the strands instead (with ``path_xy``, ``pixels`` and
    ``gap_links``, gap id -> the links it is on): each pixel goes to the link whose curve (a
    cubic from its keypoint to the next, leaving and arriving along the path's own steps there)
    passes nearest, none on a tie (geodesically nearer ends cut two strands side by side
    across, and the min/max links of a gap on six took all of it: generated crossing 8158
    #15). Returns the gap geodesics with each part a gap of its own (a link's distances stay
    inside its part) and ``px_link`` (N,) with the split pixels' links."""
    on = pixel_node >= 0
    hi = px_link
    lo = np.where(on, link_lo[np.maximum(pixel_node, 0)], -1)
    shared = np.flatnonzero(on & (hi >= 0) & (lo < hi))
    d = []
    for own, other in ((lo[shared], hi[shared]), (hi[shared], lo[shared])):
        mine = np.column_stack([ends[own], ends[own + 1]])
        theirs = np.column_stack([ends[other], ends[other + 1]])
        excl = np.where(np.isin(mine, theirs) | (mine < 0), -2, mine)  # -2: no cluster
        nb = geo.nb_node[shared]
        src = shared[np.any((nb[:, :, None] == excl[:, None, :]) & (nb[:, :, None] >= 0), (1, 2))]
        d.append(geo.distances(src)[shared] if src.size else np.full(shared.size, np.inf))
    d_lo, d_hi = d
    out = px_link.copy()
    out[shared] = np.where(d_lo < d_hi, lo[shared], np.where(d_hi < d_lo, hi[shared], -1))
    node = geo.node.copy()  # the lower link's part and the ties become gaps of their own
    n_nodes = int(node.max()) + 1
    node[shared] += np.where(out[shared] == lo[shared], n_nodes, 0)
    node[shared] += np.where(out[shared] < 0, 2 * n_nodes, 0)
    if path_xy is None or pixels is None or not gap_links:
        return _with_node(geo, node), out
    for g, ls in gap_links.items():
        distinct = {int(ends[i]) for i in ls} | {int(ends[i + 1]) for i in ls}
        if len(ls) < 3 and not (len(distinct) == 4 and min(distinct) >= 0):
            continue  # two links through one keypoint: their own ends tell them apart
        sel = shared[pixel_node[shared] == g]
        if not sel.size:
            continue
        xy = pixels[sel].astype(np.int64)
        D = _curve_distances(xy, ls, path_xy)
        best = np.argmin(D, axis=1)
        tie = np.sort(D, axis=1)[:, 1] == D[np.arange(len(sel)), best]
        out[sel] = np.where(tie, -1, np.array(ls)[best])
        node[sel] = geo.node[sel] + np.where(tie, 2 * n_nodes, (3 + best) * n_nodes)
    return _with_node(geo, node), out


def _with_node(geo: _GapGeodesics, node: np.ndarray) -> _GapGeodesics:
    """``geo`` with the gaps ``node`` (split parts of shared gaps as gaps of their own)."""
    split = copy.copy(geo)
    split.node = node
    return split


_PAIRS_DIRECT = 50_000  # pixels x curve samples up to which a gap's links are measured at once
# by the least integer squared distance ((P, M) int64: 0.4 MB), above by a transform per link


def _curve_distances(xy: np.ndarray, links: list[int], path_xy: np.ndarray) -> np.ndarray:
    """(P, m) px: :func:`_curve_distance` of the pixels ``xy`` (P, 2) int to each link of
    ``links`` (m), the same values: the curves sampled and rounded as it does (its linspace's
    and polynomial's operations, element by element, on every link's samples at once) and the
    distance transform's value, the float32 square root of the least integer squared distance
    to a sample, taken directly (a gap on several links is ~5 links of a few px at 1920x1080,
    where each transform and its curve cost ~25 numpy calls)."""
    i = np.asarray(links, dtype=np.int64)
    last = len(path_xy) - 1
    a, b = path_xy[i], path_xy[i + 1]
    chord = b - a
    L = np.hypot(chord[:, 0], chord[:, 1])
    num = np.maximum(2, np.ceil(2 * L).astype(np.int64) + 1)
    if len(xy) * int(num.sum()) > _PAIRS_DIRECT:
        return np.column_stack([_curve_distance(xy, k, path_xy) for k in links])
    t_a = np.where((i >= 1)[:, None], a - path_xy[np.maximum(i - 1, 0)], chord)
    t_b = np.where((i + 2 <= last)[:, None], path_xy[np.minimum(i + 2, last)] - b, chord)
    t_a = t_a / np.maximum(np.hypot(t_a[:, 0], t_a[:, 1]), 1e-9)[:, None] * L[:, None]
    t_b = t_b / np.maximum(np.hypot(t_b[:, 0], t_b[:, 1]), 1e-9)[:, None] * L[:, None]
    starts = np.cumsum(num) - num
    link = np.repeat(np.arange(len(i)), num)
    s = (np.arange(len(link)) - starts[link]).astype(np.float64)  # np.linspace(0, 1, num):
    s *= (1.0 / (num - 1))[link]  # k * (1 / (num - 1)) + 0.0, its last 1.0
    s += 0.0
    s[starts + num - 1] = 1.0
    s = s[:, None]
    curve = (
        (1 + 2 * s) * (1 - s) ** 2 * a[link]
        + s * (1 - s) ** 2 * t_a[link]
        + s**2 * (3 - 2 * s) * b[link]
        - s**2 * (1 - s) * t_b[link]
    )
    c = np.round(curve).astype(np.int64)
    d2 = ((xy[:, None, :] - c[None, :, :]) ** 2).sum(axis=2)
    return np.sqrt(np.minimum.reduceat(d2, starts, axis=1).astype(np.float32)).astype(np.float64)


def _curve_distance(xy: np.ndarray, i: int, path_xy: np.ndarray) -> np.ndarray:
    """(P,) px, distance of each pixel ``xy`` (P, 2) int (x, y) to the cubic Hermite curve of
    link ``i``: from ``path_xy[i]`` to ``path_xy[i + 1]``, its tangents the path's steps into
    the first and out of the second (the chord where the path has none), scaled by the chord's
    length. The curve is sampled every half px or less and rounded to pixels, and the exact
    distance transform of those pixels read (cv2; a KD-tree query per link cost ~1 ms on a
    gap of a few thousand px). Symmetric: the same curve from either end."""
    a, b = path_xy[i], path_xy[i + 1]
    chord = b - a
    L = float(np.hypot(*chord))
    t_a = a - path_xy[i - 1] if i >= 1 else chord
    t_b = path_xy[i + 2] - b if i + 2 < len(path_xy) else chord
    t_a = t_a / max(float(np.hypot(*t_a)), 1e-9) * L
    t_b = t_b / max(float(np.hypot(*t_b)), 1e-9) * L
    s = np.linspace(0.0, 1.0, max(2, math.ceil(2 * L) + 1))[:, None]
    curve = (
        (1 + 2 * s) * (1 - s) ** 2 * a
        + s * (1 - s) ** 2 * t_a
        + s**2 * (3 - 2 * s) * b
        - s**2 * (1 - s) * t_b
    )
    c = np.round(curve).astype(np.int64)
    lo = np.minimum(c.min(axis=0), xy.min(axis=0))
    hi = np.maximum(c.max(axis=0), xy.max(axis=0))
    img = np.full((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), 255, dtype=np.uint8)
    img[c[:, 1] - lo[1], c[:, 0] - lo[0]] = 0
    dt = distance_to_zero(img)
    return dt[xy[:, 1] - lo[1], xy[:, 0] - lo[0]].astype(np.float64)


def _normalised(d: np.ndarray) -> np.ndarray:
    top = np.nanmax(d) if np.any(np.isfinite(d)) else np.nan
    return d / top if top and np.isfinite(top) else np.full_like(d, np.nan)


class _PixelGrid:
    """The pixels of P_L in an index image over their bounding box, padded by ``pad`` px."""

    def __init__(self, pixels: np.ndarray, pad: int) -> None:
        n = len(pixels)
        self.n = n
        self.pad = pad
        xs, ys = pixels[:, 0], pixels[:, 1]  # per column: 4x faster than axis=0 on (N, 2)
        self.x0, self.y0 = (int(xs.min()), int(ys.min())) if n else (0, 0)
        x1, y1 = (int(xs.max()), int(ys.max())) if n else (0, 0)
        self.x = pixels[:, 0] - self.x0 + pad
        self.y = pixels[:, 1] - self.y0 + pad
        shape = (y1 - self.y0 + 1 + 2 * pad, x1 - self.x0 + 1 + 2 * pad)
        self.index = np.full(shape, -1, dtype=np.int32)  # int32: 8 MB for a whole 1920x1080 box
        self.index[self.y, self.x] = np.arange(n)

    def window(self, cx: float, cy: float, radius: int) -> np.ndarray:
        """Indices of the pixels with |x - cx| <= radius and |y - cy| <= radius (``cx``,
        ``cy``: whole numbers, px; none for a non-finite centre)."""
        h, w = self.index.shape
        if not (math.isfinite(cx) and math.isfinite(cy)):
            return np.zeros(0, dtype=np.int64)
        x0 = max(math.ceil(cx - radius) - self.x0 + self.pad, 0)
        x1 = min(math.floor(cx + radius) - self.x0 + self.pad + 1, w)
        y0 = max(math.ceil(cy - radius) - self.y0 + self.pad, 0)
        y1 = min(math.floor(cy + radius) - self.y0 + self.pad + 1, h)
        if x0 >= x1 or y0 >= y1:
            return np.zeros(0, dtype=np.int64)
        ids = self.index[y0:y1, x0:x1].ravel()
        return ids[ids >= 0].astype(np.int64)

    def neighbours(self) -> np.ndarray:
        """(N, 8) index of each pixel's 8-neighbours in P_L (order ``_OFFSETS_8``), -1 if none."""
        if self.pad < 1:
            raise ValueError(f"the neighbours need a grid padded by >= 1 px, not {self.pad}")
        return walk_kernel.grid_neighbours(
            self.index,
            np.ascontiguousarray(self.y, dtype=np.int64),
            np.ascontiguousarray(self.x, dtype=np.int64),
        )

    def components(
        self, member: np.ndarray, nb: np.ndarray | None = None
    ) -> tuple[int, np.ndarray]:
        """8-connected components of the pixels where ``member``: their count + 1 (as cv2
        counts, with the background) and (N,) label 1.. in the order of each component's first
        pixel in the pixel list (0 where not ``member``). ``nb``: :meth:`neighbours`, if known
        (then no image of the box: :func:`walk_kernel.member_components`)."""
        if nb is not None:
            lab = walk_kernel.member_components(
                np.ascontiguousarray(nb, dtype=np.int32), np.ascontiguousarray(member, dtype=bool)
            )
            return int(lab.max(initial=0)) + 1, lab
        # cv2's own numbering follows its 2x2 blocks and its threads' stripes (it changes with
        # the box and with cv2.setNumThreads): renumbered by first pixel
        h, w = self.index.shape
        img = np.zeros((h, w), np.uint8)
        img[self.y[member], self.x[member]] = 1
        n, lab = cv2.connectedComponents(img, connectivity=8)
        lab = lab[self.y, self.x]
        first = np.full(n, self.n, dtype=np.int64)  # first pixel (row-major) of each label
        np.minimum.at(first, lab[member], np.flatnonzero(member))
        rank = np.zeros(n, dtype=np.int64)
        rank[np.argsort(first[1:], kind="stable") + 1] = np.arange(1, n)
        return n, np.where(member, rank[lab], 0)


_GRID_LAST: list[tuple] = []  # at most one: (weak reference to a pixel list, pad, grid, nb)


def _pixel_grid(pixels: np.ndarray, pad: int) -> tuple[_PixelGrid, np.ndarray]:
    """The :class:`_PixelGrid` of P_L's pixel list and its neighbour table, kept for the last
    pixel list while it lives (the stereo result's; 4 MB at 1920x1080, dropped with it): a
    re-run of the ordering after a reliability, clustering or ordering parameter changed (a
    slider) finds them. Shared: read only."""
    last = next(iter(_GRID_LAST), None)
    if last is not None and last[0]() is pixels and last[1] == pad:
        return last[2], last[3]
    grid = _PixelGrid(pixels, pad)
    nb = grid.neighbours()

    def drop(ref: weakref.ref) -> None:  # the pixel list was freed: so are its grid and table
        if _GRID_LAST and _GRID_LAST[0][0] is ref:
            _GRID_LAST.clear()

    _GRID_LAST[:] = [(weakref.ref(pixels, drop), pad, grid, nb)]
    return grid, nb


_OFFSETS_8 = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))
_STEPS_8 = np.array([np.hypot(dy, dx) for dy, dx in _OFFSETS_8])  # their lengths, px


def _solidify(
    grid: _PixelGrid, labels: np.ndarray, radius: int, nb: np.ndarray | None = None
) -> np.ndarray:
    """(N,) cluster of each pixel of P_L after solidification: an unclustered pixel within
    ``radius`` px (8-neighbourhood steps) of a cluster joins it; where two clusters are in reach
    the higher id wins (the grey dilation of the label image, on the pixel list). ``nb``: the
    grid's neighbour table, if known (radius 1: read from it, no image of the box)."""
    out = labels.copy()
    if radius == 0 or not (labels >= 0).any():
        return out
    if radius == 1 and nb is not None:
        free = np.flatnonzero(labels < 0)
        near = nb[free]
        grown = np.where(near >= 0, labels[np.maximum(near, 0)] + 1, 0).max(axis=1, initial=0)
        out[free] = grown - 1
        return out
    if radius > grid.pad:
        raise ValueError(f"the pixel grid is padded by {grid.pad} px, not {radius}")
    img = np.zeros(grid.index.shape, dtype=np.int32)
    img[grid.y, grid.x] = labels + 1
    free = np.flatnonzero(labels < 0)
    y, x = grid.y[free], grid.x[free]
    grown = np.zeros(free.size, dtype=np.int32)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            np.maximum(grown, img[y + dy, x + dx], out=grown)
    out[free] = grown - 1
    return out


def _touching_pairs(pixel_node: np.ndarray, nb_node: np.ndarray) -> np.ndarray:
    """(P, 2) unique pairs (a < b, sorted) of different nodes that are 8-neighbours somewhere."""
    m = int(pixel_node.max()) + 1 if pixel_node.size else 1
    key = walk_kernel.touching_keys(
        np.ascontiguousarray(pixel_node, dtype=np.int64),
        np.ascontiguousarray(nb_node, dtype=np.int64),
        m,
    )
    # Neighbouring pixels repeat a pair: dropping a key equal to the one before leaves the same
    # set for np.unique, 4-6 times smaller (0.6 ms of sorting at 1920x1080).
    if key.size:
        key = np.unique(key[np.concatenate([[True], key[1:] != key[:-1]])])
    return np.stack([key // m, key % m], axis=1)


def _best_walk(
    K: int, edges: np.ndarray, pos: np.ndarray, pos_px: np.ndarray, bridge_px: float
) -> list[int]:
    adj: list[list[int]] = [[] for _ in range(K)]
    for a, b in edges:
        adj[a].append(int(b))
        adj[b].append(int(a))
    comp = _components(K, adj)
    degree = np.array([len(a) for a in adj])
    starts = [int(k) for k in np.flatnonzero(degree == 1)]
    if not starts:  # a closed loop or a single keypoint: start from the lowest degree
        starts = [int(np.argmin(degree))]
    best: list[int] = []
    best_key = (-1, 0.0)
    for s in starts:
        walk = _greedy_walk(s, adj, pos, pos_px, comp, bridge_px)
        length = (
            float(np.linalg.norm(np.diff(pos_px[walk], axis=0), axis=1).sum())
            if len(walk) > 1
            else 0.0
        )
        key = (len(walk), -length)
        if key > best_key:
            best, best_key = walk, key
    return best


def _greedy_walk(
    start: int,
    adj: list[list[int]],
    pos: np.ndarray,
    pos_px: np.ndarray,
    comp: np.ndarray,
    bridge_px: float,
) -> list[int]:
    visited = np.zeros(len(adj), dtype=bool)
    done_comp = {int(comp[start])}
    walk = [start]
    visited[start] = True
    cur = start
    while True:
        cand = [v for v in adj[cur] if not visited[v]]
        if cand:
            d = np.linalg.norm(pos[cand] - pos[cur], axis=1)
            cur = cand[int(np.argmin(d))]
        else:
            other = np.flatnonzero(~visited & ~np.isin(comp, list(done_comp)))
            if bridge_px <= 0 or other.size == 0:
                break
            d = np.linalg.norm(pos_px[other] - pos_px[cur], axis=1)
            j = int(np.argmin(d))
            if d[j] > bridge_px:
                break
            cur = int(other[j])
            done_comp.add(int(comp[cur]))
        visited[cur] = True
        walk.append(cur)
    return walk


def _components(K: int, adj: list[list[int]]) -> np.ndarray:
    comp = np.full(K, -1)
    c = 0
    for s in range(K):
        if comp[s] >= 0:
            continue
        stack = [s]
        comp[s] = c
        while stack:
            u = stack.pop()
            for v in adj[u]:
                if comp[v] < 0:
                    comp[v] = c
                    stack.append(v)
        c += 1
    return comp


def _adjacency(K: int, edges: np.ndarray) -> list[list[int]]:
    adj: list[list[int]] = [[] for _ in range(K)]
    for a, b in edges.tolist():
        adj[a].append(b)
        adj[b].append(a)
    return adj


def _bending_walk(g: _WalkGraph, p: OrderingParams) -> list[int]:
    """Best of the walks from every end keypoint (degree 1 in A), see :func:`_walk_from`; when
    the best walk leaves keypoints out, the runner-up continuation at each junction it passed
    is tried too (a wrong turn at a crossing strands the rest of the thread)."""
    K = len(g.adj)
    degree = np.diff(g.indptr)
    starts = [int(k) for k in np.flatnonzero(degree <= 1)]
    if not starts:  # a closed loop: start from the lowest degree
        starts = [int(np.argmin(degree))]
    best_walk: list[int] = []
    best_steps: list[float] = []
    best_alts: list[tuple[int, int]] = []
    best_key = (-1, 0.0)
    tried = 0
    queue: list[tuple[Any, Any, int | None]] = [([s], [], None) for s in starts]
    while queue and tried < MAX_WALKS:
        prefix, prefix_steps, forced = queue.pop(0)
        walk, steps, alts = _walk_from(prefix, prefix_steps, forced, g, p, max_alts=MAX_WALKS)
        tried += 1
        key = (len(walk), -sum(steps))
        if key > best_key:
            best_walk, best_steps, best_alts, best_key = walk, steps, alts, key
        if not queue and len(best_walk) < K and best_alts:
            # Branch at each decision of the best walk so far, in path order (the prefixes as
            # views of one array each: no list of hundreds of keypoints per branch)
            walk_a, steps_a = np.array(best_walk, np.int64), np.array(best_steps, np.float64)
            queue = [
                (walk_a[: i + 1], steps_a[:i], alt)
                for i, alt in best_alts[: MAX_WALKS - tried]  # the rest would never be tried
            ]
            best_alts = []
    return best_walk


@dataclass(frozen=True)
class _WalkGraph:
    """A, positions and disparities as the walk kernel takes them (built once per frame)."""

    adj: list[list[int]]
    indptr: np.ndarray  # (K + 1,) int64, CSR of A in the order of ``adj``
    indices: np.ndarray
    pos: np.ndarray  # (K, 2) float64, contiguous
    disp: np.ndarray  # (K,) float64
    scratch: tuple[np.ndarray, np.ndarray, np.ndarray] = field(
        default_factory=lambda: (np.empty(0, np.int64), np.empty(0), np.empty(0))
    )
    """(K,) int64, float64, float64 buffers that :func:`_continuations` hands to the kernel
    (one walk at a time uses them; what it returns is copied out)."""
    broken: list[list[int]] = field(default_factory=list)
    """Per keypoint, its neighbours whose edge :func:`_depth_breaks` took out of A (empty
    lists, or no list at all, where none was): the walk's last resort."""
    lifted: LiftedPair | None = None
    """The views, for what they show at a jump's ends (:func:`_end_state`); None: no such
    test (every jump turns by at most 90 deg each, free ends are joined)."""
    states: dict[tuple[int, int, int, bool], str] = field(default_factory=dict)
    """:func:`_end_state` per (end keypoint, the keypoint its way is taken from, the one its
    background is taken at, ``clear``), filled as the walks ask."""

    def end_state(
        self, k: int, toward: int, behind: int, way: np.ndarray, clear: bool = False
    ) -> str:
        """:func:`_end_state` of the end at keypoint ``k``, outward unit direction ``way`` (from
        keypoint ``toward``), its background taken at keypoint ``behind``."""
        key = (k, toward, behind, clear)
        if key not in self.states:
            assert self.lifted is not None
            inner = self.pos[behind]
            self.states[key] = _end_state(
                self.lifted, self.pos[k], way, float(self.disp[k]), inner, clear
            )
        return self.states[key]

    @classmethod
    def of(
        cls,
        adj: list[list[int]],
        pos: np.ndarray,
        disp: np.ndarray,
        broken: list[list[int]] | None = None,
        lifted: LiftedPair | None = None,
    ) -> _WalkGraph:
        K = len(adj)
        indptr = np.zeros(K + 1, dtype=np.int64)
        indptr[1:] = np.cumsum([len(a) for a in adj])
        indices = np.array([v for a in adj for v in a], dtype=np.int64)
        return cls(
            adj,
            indptr,
            indices,
            np.ascontiguousarray(pos, dtype=np.float64),
            np.ascontiguousarray(disp, dtype=np.float64),
            (np.empty(K, np.int64), np.empty(K), np.empty(K)),
            broken if broken is not None and any(broken) else [],
            lifted,
        )


def _walk_from(
    prefix: list[int] | np.ndarray,
    prefix_steps: list[float] | np.ndarray,
    forced: int | None,
    g: _WalkGraph,
    p: OrderingParams,
    max_alts: int | None = None,
) -> tuple[list[int], list[float], list[tuple[int, int]]]:
    """Walk A on from ``prefix`` (its first step ``forced`` when given), each step to the
    continuation of least cost of :func:`_continuations`. Returns the walk, the cost of each
    step and the ``walk_runners`` next cheapest continuations at each step that had them (as
    (index in the walk, keypoint): every step's runner-up in path order, then every step's
    third, ...; the first ``max_alts`` of them when given). ``prefix``, ``prefix_steps``:
    lists or arrays. Steps to neighbours and through crossings run in
    :func:`walk_kernel.walk_on`; a jump across a gap (a few per walk) here."""
    K = len(g.adj)
    cos_max = _cos_deg(p.max_turn_deg)
    visited = np.zeros(K, dtype=bool)
    visited[prefix] = True
    walk = np.zeros(K, dtype=np.int64)
    walk[: len(prefix)] = prefix
    steps = np.zeros(K)
    steps[: len(prefix_steps)] = prefix_steps
    runners = max(1, p.walk_runners)
    alt_at = np.zeros(K * runners, dtype=np.int64)
    alt_kp = np.zeros(K * runners, dtype=np.int64)
    alt_rank = np.zeros(K * runners, dtype=np.int64)
    n, n_alt = len(prefix), 0
    pending = -1 if forced is None else forced
    while True:
        n, n_alt, state = walk_kernel.walk_on(
            walk, n, len(prefix), steps, pending, visited, g.indptr, g.indices, g.pos, g.disp,
            float(p.bend_weight), float(p.disparity_weight), cos_max, alt_at, alt_kp, alt_rank,
            n_alt, runners,
        )  # fmt: skip
        if state == walk_kernel.WALK_END:
            break
        cand, cost, _, _ = _continuations(walk, n, visited, g, p)
        if not cand:  # no jump either
            break
        rank = np.argsort(cost, kind="stable")
        j = int(rank[0])
        if pending >= 0 and n == len(prefix):
            if pending not in cand:
                break
            j = cand.index(pending)
        else:
            for r in range(1, min(runners, len(rank) - 1) + 1):
                if not np.isfinite(cost[rank[r]]):
                    break
                alt_at[n_alt], alt_kp[n_alt], alt_rank[n_alt] = n - 1, cand[rank[r]], r
                n_alt += 1
        if not np.isfinite(cost[j]):
            break
        visited[cand[j]] = True
        walk[n] = cand[j]
        steps[n - 1] = cost[j]
        n += 1
    # the runners-up of every step in path order first, then the thirds, ...
    by_rank = np.argsort(alt_rank[:n_alt], kind="stable")
    n_alt = n_alt if max_alts is None else min(n_alt, max_alts)
    alts = list(
        zip(alt_at[by_rank[:n_alt]].tolist(), alt_kp[by_rank[:n_alt]].tolist(), strict=True)
    )
    return walk[:n].tolist(), steps[: n - 1].tolist(), alts


_TIERS = ("neighbour", "crossing", "jump")


@functools.lru_cache(maxsize=8)
def _cos_deg(deg: float) -> float:
    """cos of ``deg`` degrees (``max_turn_deg``: computed once, not at every step)."""
    return float(np.cos(np.radians(deg)))


def _continuations(
    walk: np.ndarray, n: int, visited: np.ndarray, g: _WalkGraph, p: OrderingParams
) -> tuple[list[int], np.ndarray, int, list[str]]:
    """The candidates for the walk's next step, their costs

        distance * (1 + bend_weight * (1 - cos turn)) + disparity_weight * |disparity change|,

    the tier they come from and, per candidate, why it is excluded ("" if it is not; its cost
    is then inf; the disparity change is from the mean of the walk's last three keypoints that
    are no junction: a crossing's keypoints carry the other strand's disparity).
    Tiers, in this order of preference: 0, unvisited neighbours in A (at a three-way junction
    also the unvisited neighbours of an unvisited adjacent three-way junction: a crossing split
    in two is passed straight through, the junction passed over left for the other strand);
    1, unvisited keypoints two steps away through a keypoint already on the path (the other
    strand of a crossing; a turn of more than ``max_turn_deg`` only when nothing else is left:
    a touching turn); 2, unvisited keypoints within ``bridge_px`` whose disparity agrees and whose piece
    continues the same way (across an occlusion or a break in the segmentation): the turn into
    the jump and the turn out of it at most 90 deg each.
    Last, when no jump is left either: the unvisited neighbours across a depth break
    (:func:`_depth_breaks`), at tier 0's cost, reported as tier 0.

    ``walk[:n]``: the path so far ((K,) int64 buffer). Tiers 0 and 1 are computed by
    :func:`walk_kernel.step_costs` (the walk's own kernel), tier 2 here."""
    cand_buf, cost_buf, cos_buf = g.scratch
    if len(cand_buf) != len(g.adj):  # a graph built without its buffers
        cand_buf = np.empty(len(g.adj), dtype=np.int64)
        cost_buf, cos_buf = np.empty(len(g.adj)), np.empty(len(g.adj))
    cos_max = _cos_deg(p.max_turn_deg)
    m, tier = walk_kernel.step_costs(
        walk, n, visited, g.indptr, g.indices, g.pos, g.disp,
        float(p.bend_weight), float(p.disparity_weight), cos_max, cand_buf, cost_buf, cos_buf,
    )  # fmt: skip
    if m:
        cost = cost_buf[:m].copy()
        why = [""] * m
        if tier == 1 and np.isinf(cost).any():
            why = ["" if c >= cos_max else "turn > max_turn_deg" for c in cos_buf[:m]]
        return cand_buf[:m].tolist(), cost, tier, why
    cand, cost, tier, why = _jumps(walk, n, visited, g, p)
    if g.broken and not np.isfinite(cost).any():
        across = _across_breaks(walk, n, visited, g, p)
        if across[0]:
            return across
    if p.retrace_px > 0 and not np.isfinite(cost).any():
        again = _second_pass(walk, n, visited, g, p)
        if again[0]:
            return again
    return cand, cost, tier, why


def _second_pass(
    walk: np.ndarray, n: int, visited: np.ndarray, g: _WalkGraph, p: OrderingParams
) -> tuple[list[int], np.ndarray, int, list[str]]:
    """:func:`_continuations`' last resort (deviation 44): the walk came back to a crossing it
    passed (a junction of A on the path, adjacent to the walk's keypoint, not the step it came
    from) and nothing is left ahead. Its strand runs on along the path's own keypoints from
    the junction (two strands touching along a loop's crossing share their keypoints), the
    way the walk comes in (the path's step on from the junction turning by at most
    ``max_turn_deg`` from the walk's heading; past it the path's own turns, which the first
    strand took), for at most ``retrace_px``; it leaves them
    through an unvisited neighbour in A of a keypoint it passes, turning by at most
    ``max_turn_deg`` there too, whose disparity agrees with the walk's (as a jump's, over the
    way's length). Cost: the way's length along the shared keypoints plus the step's cost from
    the keypoint it leaves at (tier 1, a crossing)."""
    cur, prev = int(walk[n - 1]), int(walk[n - 2]) if n >= 2 else -1
    degree = np.diff(g.indptr)
    pos, disp = g.pos, g.disp
    cos_max = _cos_deg(p.max_turn_deg)
    ref = _ref_disparity(walk, n, g)
    best: dict[int, float] = {}
    path_l: list[int] | None = None
    for jn in g.adj[cur]:
        if not visited[jn] or jn == prev or degree[jn] < 3:
            continue
        if path_l is None:
            path = walk[: n - 1]
            path_l = path.tolist()
            # once per call: the path's step lengths (the same hypot per step, either way), and
            # which of its keypoints have an unvisited neighbour (the only ones a way can leave
            # at: past the others the way only runs on, and their heading is never read)
            step_px = np.diff(pos[path], axis=0)
            step_px = np.hypot(step_px[:, 0], step_px[:, 1]).tolist()
            exit_kp = np.zeros(len(degree), dtype=bool)
            exit_kp[np.repeat(np.arange(len(degree)), degree)[~visited[g.indices]]] = True
            exits = exit_kp[path].tolist()
        at = np.flatnonzero(path == jn)  # a walk visits a keypoint once
        if not at.size:
            continue
        i = int(at[0])
        for sgn in (1, -1):  # along the path either way from the junction
            u, j = int(jn), i
            if not 0 <= j + sgn < n - 1:
                continue
            come = pos[u] - pos[prev if prev >= 0 else cur]  # the heading over two steps
            on = pos[int(walk[j + sgn])] - pos[u]  # the path's own way on from the junction
            if float(come @ on) < cos_max * float(np.hypot(*come) * np.hypot(*on)):
                continue
            head = pos[u] - pos[cur]
            run = float(np.hypot(*head))
            if run <= 0:
                break
            head = head / run
            while run <= p.retrace_px:
                for v in g.adj[u] if exits[j] else ():
                    if visited[v]:
                        continue
                    out = pos[v] - pos[u]
                    d = max(float(np.hypot(*out)), 1e-9)
                    c = float(out @ head) / d
                    gap = abs(float(disp[v]) - ref)
                    if c < cos_max or gap > disparity_room(run + d):
                        continue
                    cost = run + d * (1.0 + p.bend_weight * (1.0 - c)) + p.disparity_weight * gap
                    if cost < best.get(v, np.inf):
                        best[v] = cost
                j += sgn
                if not 0 <= j < n - 1:
                    break
                w = path_l[j]
                s = step_px[j - 1 if sgn > 0 else j]  # |pos[w] - pos[u]|
                if s <= 0:
                    break
                if exits[j]:
                    head = (pos[w] - pos[u]) / s
                run, u = run + s, w  # the path's own turns: no test
    if not best:
        return [], np.zeros(0), 1, []
    cand = sorted(best)
    return cand, np.array([best[v] for v in cand]), 1, [""] * len(cand)


def _jumps(
    walk: np.ndarray, n: int, visited: np.ndarray, g: _WalkGraph, p: OrderingParams
) -> tuple[list[int], np.ndarray, int, list[str]]:
    """Tier 2 of :func:`_continuations`: the jumps across a gap."""
    tier = 2
    if p.bridge_px <= 0:
        return [], np.zeros(0), tier, []
    pos, disp, adj = g.pos, g.disp, g.adj
    cur = int(walk[n - 1])
    back = int(walk[n - 3] if n >= 3 else walk[0])
    heading = pos[cur] - pos[back]
    hn = float(np.hypot(*heading))
    heading = heading / hn if hn > 0 else None
    ref = _ref_disparity(walk, n, g)
    cand: list[int] = []
    if heading is not None:
        free = np.flatnonzero(~visited)
        d = np.linalg.norm(pos[free] - pos[cur], axis=1)
        near = d <= p.bridge_px
        near &= np.abs(disp[free] - ref) <= disparity_room(d)
        cand = [int(v) for v in free[near]]
    if not cand:
        if heading is not None and p.hidden_bridge_px > p.bridge_px and g.lifted is not None:
            return _hidden_jumps(walk, n, visited, g, p, heading, ref)
        return [], np.zeros(0), tier, []
    chord, cos_t, cost = _jump_costs(np.array(cand), cur, heading, ref, g, p)
    # across a gap: turn in and turn out each <= 90 deg (the hidden stretch heads from each
    # end towards the other; a bend under an occluder may add up to 180 deg)
    turn_in = np.degrees(np.arccos(np.clip(cos_t, -1.0, 1.0)))
    # the turn out only where the turn in leaves the jump possible (else it decides nothing)
    turn_out = np.array(
        [
            _turn_out(v, chord[i], adj, visited, pos) if turn_in[i] <= 90.0 else 0.0
            for i, v in enumerate(cand)
        ]
    )
    ok = (turn_in <= 90.0) & (turn_out <= 90.0)
    why = ["" if k else "turn across the gap" for k in ok]
    if g.lifted is not None:  # what the views show at the two ends (deviation 38)
        _by_the_ends(cand, cost, chord, ok, why, turn_in, walk, n, heading, visited, g, p)
    cost = np.where(ok, cost, np.inf)
    if (
        not np.isfinite(cost).any() and p.hidden_bridge_px > p.bridge_px and g.lifted is not None
    ):  # nothing within bridge_px: a longer jump under an occluder (deviation 69)
        far = _hidden_jumps(walk, n, visited, g, p, heading, ref)
        if far[0]:
            return far
    return cand, cost, 2, why


def _jump_costs(
    c: np.ndarray, cur: int, heading: np.ndarray, ref: float, g: _WalkGraph, p: OrderingParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(chord (k, 2), cos of the turn into it (k,), cost (k,)) of the jumps from keypoint
    ``cur`` (heading ``heading``, unit; reference disparity ``ref``) to the keypoints ``c``:
    the chord's length, weighted by the bend into it, plus the disparity change."""
    chord = g.pos[c] - g.pos[cur]
    dist = np.maximum(np.linalg.norm(chord, axis=1), 1e-9)
    # chord . heading as two products and a sum (not BLAS, which may fuse them: one rounding
    # less), the operations of walk_kernel.step_costs
    cos_t = (chord[:, 0] * heading[0] + chord[:, 1] * heading[1]) / dist
    cost = dist * (1.0 + p.bend_weight * (1.0 - cos_t)) + p.disparity_weight * np.abs(
        g.disp[c] - ref
    )
    return chord, cos_t, cost


CHORD_BARE_SHARE = 0.25  # a jump under an occluder: at most this share of its way's samples
# looks like the bare background in either view (deviation 69)
CHORD_STEP_PX = 2.0  # px between the samples of a jump's way
CHORD_NEAR_PX = 12  # half side of the square about a sample where the hidden thread may pass


def _hidden_jumps(
    walk: np.ndarray,
    n: int,
    visited: np.ndarray,
    g: _WalkGraph,
    p: OrderingParams,
    heading: np.ndarray,
    ref: float,
) -> tuple[list[int], np.ndarray, int, list[str]]:
    """Deviation 69 (``hidden_bridge_px``): the jumps longer than ``bridge_px`` (up to
    ``hidden_bridge_px``) from the walk's end onto the end of an unvisited piece, both ends
    running under an occluder in both views (:func:`_end_state` "hidden"), the disparity
    within the continuity bound over the jump, the turns in and out within 90 deg each, and
    the straight way between them over no bare background in either view (at most
    CHORD_BARE_SHARE of its samples, :func:`_chord_bare_share`): a thread that runs under a
    shaft along its axis and comes out beyond it. Cost as any jump's; the cheapest allowed
    two are returned (the walk takes the first and may branch at the second)."""
    pos, disp, adj = g.pos, g.disp, g.adj
    assert g.lifted is not None
    cur = int(walk[n - 1])
    free = np.flatnonzero(~visited)
    d = np.linalg.norm(pos[free] - pos[cur], axis=1)
    far = (d > p.bridge_px) & (d <= p.hidden_bridge_px)
    far &= np.abs(disp[free] - ref) <= disparity_room(d)
    if not far.any():
        return [], np.zeros(0), 2, []
    c = free[far]
    chord, cos_t, cost = _jump_costs(c, cur, heading, ref, g, p)
    back = int(walk[n - 3] if n >= 3 else walk[0])
    back_k = int(walk[max(n - 1 - HIDDEN_BACK_STEPS, 0)])
    here: str | None = None
    cand: list[int] = []
    kept: list[float] = []
    for i in np.argsort(cost, kind="stable").tolist():
        if len(cand) == 2:
            break
        v = int(c[i])
        if cos_t[i] < 0.0:  # the turn into the jump over 90 deg
            continue
        nb = _piece_end(v, adj, visited)
        if nb < 0 or _turn_out(v, chord[i], adj, visited, pos) > 90.0:
            continue
        if here is None:
            here = g.end_state(cur, back, back_k, heading)
        if here != "hidden":
            return [], np.zeros(0), 2, []
        way = pos[v] - pos[nb]
        wn = float(np.hypot(*way))
        if wn <= 0:
            continue
        behind = _into_piece(v, adj, visited, HIDDEN_BACK_STEPS)
        if g.end_state(v, nb, behind, way / wn) != "hidden":
            continue
        share = _chord_bare_share(
            g.lifted, pos[cur], pos[v], float(disp[cur]), float(disp[v]), pos[back_k]
        )
        if share is None or share > CHORD_BARE_SHARE:
            continue
        cand.append(v)
        kept.append(float(cost[i]))
    return cand, np.array(kept), 2, [""] * len(cand)


def _chord_bare_share(
    lifted: LiftedPair,
    a: np.ndarray,
    b: np.ndarray,
    d_a: float,
    d_b: float,
    inner: np.ndarray,
) -> float | None:
    """The share of the samples (CHORD_STEP_PX apart, HIDDEN_SEARCH_PX clear of either end,
    where the thread's own pixels may go on) of the straight way from ``a`` to ``b`` (left
    view, px) near which no point could hold the thread hidden in both views: no left pixel
    within CHORD_NEAR_PX (a square) that is no bare background in the left view and whose
    partner at the disparity interpolated from ``d_a`` to ``d_b`` is none in the right view
    either (the thread under a shaft need not run straight: only near the chord). Bare: off
    the thread, within max(MONO_BARE_LEVELS, 3 robust deviations) of the median grey of the
    view's non-thread pixels around ``inner`` (a point of the thread behind the end at ``a``,
    as :func:`_end_state`'s). None when no sample is left or a view's level cannot be
    taken."""
    length = float(np.hypot(*(b - a)))
    t = np.arange(HIDDEN_SEARCH_PX, length - HIDDEN_SEARCH_PX + 1e-9, CHORD_STEP_PX) / max(
        length, 1e-9
    )
    if not t.size:
        return None
    xy = a[None, :] + t[:, None] * (b - a)[None, :]
    shift = d_a + t * (d_b - d_a)
    H, W = lifted.P_L.shape
    r = CHORD_NEAR_PX
    xs = np.rint(xy[:, 0]).astype(np.int64)
    ys = np.rint(xy[:, 1]).astype(np.int64)
    xrs = xs - np.rint(shift).astype(np.int64)
    # the views' pixels the samples' squares can reach (a crop: the way, not the image)
    y0, y1 = max(int(ys.min()) - r, 0), min(int(ys.max()) + r + 1, H)
    covered = []  # per view: pixels that may hide the thread (no bare background), cropped
    for grey, P, s, cols in (
        (lifted.grey_L, lifted.P_L, 0.0, xs),
        (lifted.grey_R, lifted.P_R, d_a, xrs),
    ):
        cx, cy = int(round(inner[0] - s)), int(round(inner[1]))
        h = HIDDEN_WINDOW_PX
        win = (slice(max(cy - h, 0), max(cy + h + 1, 0)), slice(max(cx - h, 0), max(cx + h + 1, 0)))
        side = np.asarray(grey[win], dtype=np.float64)[~P[win]]
        if side.size < 10:
            return None
        level = float(np.median(side))
        tol = max(MONO_BARE_LEVELS, 3.0 * 1.4826 * float(np.median(np.abs(side - level))))
        x0, x1 = max(int(cols.min()) - r, 0), min(int(cols.max()) + r + 1, W)
        if y1 <= y0 or x1 <= x0:  # the way lies off the image in this view
            covered.append((np.zeros((1, 1), dtype=bool), 0, 0))
            continue
        g = np.asarray(grey[y0:y1, x0:x1], dtype=np.float64)
        covered.append((P[y0:y1, x0:x1] | (np.abs(g - level) > tol), y0, x0))
    (cov_l, oy_l, ox_l), (cov_r, oy_r, ox_r) = covered
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    # (samples, square) pixel indices at once; every pixel inside both images lies in both
    # crops (they span the samples' squares)
    x = xs[:, None] + dx.ravel()[None, :]
    y = ys[:, None] + dy.ravel()[None, :]
    xr = xrs[:, None] + dx.ravel()[None, :]
    inside = (x >= 0) & (y >= 0) & (x < W) & (y < H) & (xr >= 0) & (xr < W)
    both = np.zeros(x.shape, dtype=bool)
    yi, xi, xri = y[inside], x[inside], xr[inside]
    both[inside] = cov_l[yi - oy_l, xi - ox_l] & cov_r[yi - oy_r, xri - ox_r]
    # a sample with no pixel inside both images is off them: the thread may be hidden there
    bare = inside.any(axis=1) & ~both.any(axis=1)
    return float(bare.mean())


def _depth_breaks(
    edges: np.ndarray, pos: np.ndarray, disp: np.ndarray, K: int, cos_max: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """(kept, broken) edges of A: an edge between two keypoints that are no junction (degree
    <= 2 in A) is broken where the disparities on its two sides differ by more than one
    strand's depth can change over their distance (``DISPARITY_SLACK_PX + DISPARITY_SLOPE *
    distance``). Such clusters touch in the image but lie on two strands at two depths: where
    a raw mask lost the pixels of a crossing, an X becomes two touching turns, > and <, whose
    clusters are each other's only neighbours (generated crossing frames: 6 px of disparity
    over 8 px). A side's disparity is the median over its first ``BREAK_SIDE`` keypoints
    along its chain (no junction): one cluster matched wrong (a hairpin's legs: 11 px against
    33 px on both sides) is an outlier of its strand, not a second strand, and breaks nothing.
    And both strands must go on beyond the touch, each straighter than across it: each
    side's chain, followed through its end keypoint, points at another keypoint of its own
    disparity (:func:`_ahead_cos`) with a turn under ``acos(cos_max)`` (``max_turn_deg``) and
    under the turn from one chain onto the other (:func:`_turn_cos`), as a crossing's arms
    do. A stretch matched wrong leads nowhere at its depth (a hairpin whose bend four
    clusters match at 11 px, hard suite 8130 #6), or runs on straight where the strand does
    (a spiral's turn matched to the next turn, 55 px among 37 px, hard suite 8130 #6 too):
    neither is a second strand.
    A junction's own disparity is either strand's (its pixels are both's): its edges stay.
    ``pos``: (K, 2) keypoints, px; ``disp``: (K,) their median disparities, px (NaN: no
    match, never a break)."""
    if not len(edges):
        return edges, edges[:0]
    degree = np.bincount(edges.ravel(), minlength=K)
    a, b = edges[:, 0], edges[:, 1]
    dist = np.hypot(*(pos[a] - pos[b]).T)
    bound = disparity_room(dist)
    cut = (np.abs(disp[a] - disp[b]) > bound) & (degree[a] <= 2) & (degree[b] <= 2)
    if not cut.any():
        return edges, edges[:0]
    adj = _adjacency(K, edges)
    for i in np.flatnonzero(cut).tolist():
        u, v = int(a[i]), int(b[i])
        chain_u = _chain_away(u, v, adj, degree, BREAK_SIDE)
        chain_v = _chain_away(v, u, adj, degree, BREAK_SIDE)
        side_u, side_v = np.median(disp[chain_u]), np.median(disp[chain_v])
        if abs(side_u - side_v) <= bound[i]:
            cut[i] = False
            continue
        ahead = min(
            _ahead_cos(chain_u, side_u, chain_v, pos, disp),
            _ahead_cos(chain_v, side_v, chain_u, pos, disp),
        )
        cut[i] = ahead >= cos_max and ahead > _turn_cos(chain_u, chain_v, pos)
    return edges[~cut], edges[cut]


def _turn_cos(chain_u: list[int], chain_v: list[int], pos: np.ndarray) -> float:
    """cos of the turn of a path that comes along ``chain_u`` to its end keypoint and leaves
    along ``chain_v`` from its end (each chain's direction over up to two steps); 1 (no turn)
    for a chain of one keypoint."""
    if len(chain_u) < 2 or len(chain_v) < 2:
        return 1.0
    come = pos[chain_u[0]] - pos[chain_u[min(2, len(chain_u) - 1)]]
    leave = pos[chain_v[min(2, len(chain_v) - 1)]] - pos[chain_v[0]]
    n = float(np.hypot(*come)) * float(np.hypot(*leave))
    return 1.0 if n == 0 else float(come @ leave) / n


def _ahead_cos(
    chain: list[int], side: float, other: list[int], pos: np.ndarray, disp: np.ndarray
) -> float:
    """The largest cos of the turn from the direction of ``chain`` at its end keypoint
    ``chain[0]`` (from ``chain[2]``, or its last, to it) to a keypoint outside ``chain`` and
    ``other`` whose disparity lies within the depth-continuity bound of the chain's median
    ``side``; -inf where there is none (or the chain has one keypoint)."""
    if len(chain) < 2:
        return -np.inf
    end = pos[chain[0]]
    heading = end - pos[chain[min(2, len(chain) - 1)]]
    hn = float(np.hypot(*heading))
    if hn == 0:
        return -np.inf
    chord = pos - end
    dist = np.maximum(np.hypot(chord[:, 0], chord[:, 1]), 1e-9)
    cos = (chord @ heading) / (dist * hn)
    same = np.abs(disp - side) <= disparity_room(dist)
    same[chain + other] = False
    return float(cos[same].max()) if same.any() else -np.inf


BREAK_SIDE = 5  # keypoints per side of a depth break: the median outvotes two wrong clusters


def _chain_away(u: int, v: int, adj: list[list[int]], degree: np.ndarray, n: int) -> list[int]:
    """Up to ``n`` keypoints from ``u`` along its chain away from its neighbour ``v``, through
    keypoints of degree <= 2 (a junction ends it)."""
    out, prev = [u], v
    while len(out) < n and degree[out[-1]] == 2:
        nxt = adj[out[-1]][0] if adj[out[-1]][0] != prev else adj[out[-1]][1]
        if degree[nxt] > 2 or nxt == u:
            break
        prev = out[-1]
        out.append(nxt)
    return out


def _across_breaks(
    walk: np.ndarray, n: int, visited: np.ndarray, g: _WalkGraph, p: OrderingParams
) -> tuple[list[int], np.ndarray, int, list[str]]:
    """The unvisited neighbours of the walk's keypoint across a depth break, at tier 0's
    cost (:func:`_continuations`' last resort: a thread whose depth the stereo got wrong on
    a stretch is still one thread)."""
    cur = int(walk[n - 1])
    cand = [v for v in g.broken[cur] if not visited[v]]
    if not cand:
        return [], np.zeros(0), 0, []
    back = int(walk[n - 3] if n >= 3 else walk[0])
    heading = g.pos[cur] - g.pos[back]
    hn = float(np.hypot(*heading))
    c = np.array(cand)
    chord = g.pos[c] - g.pos[cur]
    dist = np.maximum(np.hypot(chord[:, 0], chord[:, 1]), 1e-9)
    cos_t = (chord @ heading) / (dist * hn) if hn > 0 else np.ones(len(c))
    ref = _ref_disparity(walk, n, g)
    cost = dist * (1.0 + p.bend_weight * (1.0 - cos_t)) + p.disparity_weight * np.abs(
        g.disp[c] - ref
    )
    return cand, cost, 0, [""] * len(cand)


def _ref_disparity(walk: np.ndarray, n: int, g: _WalkGraph) -> float:
    """The walk's disparity reference of :func:`walk_kernel.step_costs`, in numpy: the mean
    disparity of the last ``REF_KEYPOINTS`` keypoints of ``walk[:n]`` that are no junction,
    among its last ``REF_LOOKBACK``; of its last ``REF_KEYPOINTS`` where there is none."""
    last = walk[max(0, n - walk_kernel.REF_LOOKBACK) : n]
    own = last[np.diff(g.indptr)[last] < 3][-walk_kernel.REF_KEYPOINTS :]
    if not len(own):
        own = walk[max(0, n - walk_kernel.REF_KEYPOINTS) : n]
    ref = 0.0
    for d in g.disp[own].tolist():  # oldest first, as the kernel sums
        ref += d
    return ref / len(own)


def _explain(
    walk: list[int], g: _WalkGraph, p: OrderingParams, offset: int
) -> tuple[Decision, ...]:
    """The decisions of ``walk``, replayed: every step with more than one continuation or
    outside A, and the end when continuations were left but all excluded. ``offset``: index in
    ``order`` of ``walk[0]`` (1 after an extension at the start)."""
    visited = np.zeros(len(g.adj), dtype=bool)
    path = np.array(walk, dtype=np.int64)
    out: list[Decision] = []
    n_on = 0  # visited holds path[:n_on]
    for i in _decision_steps(path, g):
        visited[path[n_on : i + 1]] = True
        n_on = i + 1
        cand, cost, tier, why = _continuations(path, i + 1, visited, g, p)
        if not cand:
            continue
        nxt = walk[i + 1] if i + 1 < len(walk) else -1
        if nxt < 0 and np.isfinite(cost).any():
            continue  # cannot happen for a walk of _walk_from; kept honest for other callers
        if nxt >= 0 and len(cand) == 1 and tier == 0:
            continue  # the only neighbour: no decision
        j = cand.index(nxt) if nxt >= 0 else -1
        best = float(np.min(cost))
        rejected = []
        for r in np.argsort(cost, kind="stable"):
            if int(r) == j:
                continue
            reason = why[r] or "costlier"
            if j >= 0 and cost[r] < cost[j]:
                reason = "cheaper, but its walk kept fewer keypoints"
            rejected.append(Continuation(int(cand[r]), float(cost[r]), reason))
        out.append(
            Decision(
                step=offset + i,
                at=int(walk[i]),
                kind="end" if j < 0 else _TIERS[tier],  # type: ignore[arg-type]
                chosen=int(nxt),
                cost=float(cost[j]) if j >= 0 else best,
                rejected=tuple(rejected[:MAX_REJECTED]),
            )
        )
    return tuple(out)


LONG_WALK = 150  # keypoints: from here on numpy finds the decision steps faster than a loop


def _decision_steps(path: np.ndarray, g: _WalkGraph) -> list[int]:
    """The steps i of the walk ``path`` that are not a single step (:func:`_single_steps`; a
    step from a three-way junction always counts, for its candidates include the arms of an
    adjacent one, see :func:`walk_kernel.step_costs`):
    by a loop over a short walk, in numpy over a long one (0.7 against 1.1 ms at 1920x1080)."""
    if len(path) >= LONG_WALK:
        return np.flatnonzero(~_single_steps(path, g)).tolist()
    walk, adj = path.tolist(), g.adj
    on_path = [False] * len(adj)
    out = []
    for i, at in enumerate(walk):
        on_path[at] = True
        free = [v for v in adj[at] if not on_path[v]]
        if len(adj[at]) == 3 or not (
            len(free) == 1 and i + 1 < len(walk) and walk[i + 1] == free[0]
        ):
            out.append(i)
    return out


def _single_steps(path: np.ndarray, g: _WalkGraph) -> np.ndarray:
    """(n,) bool over the steps of the walk ``path``: step i went to the only neighbour of
    ``path[i]`` in A not on ``path[: i + 1]``, and ``path[i]`` has no degree 3 (most steps; no
    decision to replay there). All
    steps at once, from each neighbour's first position on the path."""
    n = len(path)
    first = np.full(len(g.adj), n, dtype=np.int64)  # first position on the path, n: never
    np.minimum.at(first, path, np.arange(n))
    lo, hi = g.indptr[path], g.indptr[path + 1]
    step = np.repeat(np.arange(n), hi - lo)  # an entry per (step, neighbour of its keypoint)
    nb = g.indices[
        np.arange(step.size) - np.repeat(np.cumsum(hi - lo) - (hi - lo), hi - lo) + lo[step]
    ]
    free = first[nb] > step  # not on path[: step + 1]
    n_free = np.bincount(step[free], minlength=n)
    nxt = np.append(path[1:], -1)
    to_next = np.zeros(n, dtype=bool)
    to_next[step[free & (nb == nxt[step])]] = True
    split = (hi - lo) == 3  # a three-way junction's step may go to the next one's arm
    return (n_free == 1) & to_next & ~split


def _pieces(adj: list[list[int]]) -> tuple[tuple[int, ...], ...]:
    """The chains of A: maximal paths whose inner keypoints have degree 2, from one keypoint of
    degree != 2 to another; a cycle of degree-2 keypoints is one piece (closed on itself)."""
    K = len(adj)
    degree = [len(a) for a in adj]
    used: set[tuple[int, int]] = set()
    pieces: list[tuple[int, ...]] = []
    seen = np.zeros(K, dtype=bool)

    def follow(a: int, b: int) -> tuple[int, ...]:
        chain = [a, b]
        while degree[chain[-1]] == 2 and chain[-1] != a:
            u, v = chain[-2], chain[-1]
            chain.append(adj[v][0] if adj[v][0] != u else adj[v][1])
        # a chain starts only at a keypoint of degree != 2: its two end steps are all that a
        # later start could take again (from the other end)
        used.add((a, b))
        used.add((chain[-1], chain[-2]))
        return tuple(chain)

    for k in range(K):
        if degree[k] == 2:
            continue
        seen[k] = True
        if degree[k] == 0:
            pieces.append((k,))
        for v in adj[k]:
            if (k, v) not in used:
                chain = follow(k, v)
                seen[list(chain)] = True
                pieces.append(chain)
    for k in range(K):  # closed loops of degree-2 keypoints only
        if not seen[k]:
            chain = follow(k, adj[k][0])
            seen[list(chain)] = True
            pieces.append(chain)
    return tuple(pieces)


def _turn_out(
    v: int, chord: np.ndarray, adj: list[list[int]], visited: np.ndarray, pos: np.ndarray
) -> float:
    """Angle, deg, between a jump ``chord`` and the way the unvisited piece at ``v`` leaves it."""
    nb = [u for u in adj[v] if not visited[u]]
    if not nb:
        return 0.0  # a lone keypoint
    out = pos[nb].mean(axis=0) - pos[v]
    n = float(np.hypot(*out)) * float(np.hypot(*chord))
    return 0.0 if n == 0 else float(np.degrees(np.arccos(np.clip(out @ chord / n, -1.0, 1.0))))


# Deviation 38: what the views show where a jump's ends stop (_end_state)
HIDDEN_SEARCH_PX = 30  # the thread's own pixels may reach this far past its end keypoint
HIDDEN_DISC_PX = 6  # radius of the disc around where the end leaves its thread pixels
HIDDEN_SHARE = 0.3  # at least this share of the disc's other pixels: neither thread nor bare
HIDDEN_FREE_SHARE = 0.05  # a free end: at most this share of its disc is no bare background
HIDDEN_TIP_PX = 3.0  # a ray may leave a free end's tip by its side: thread this far ahead
HIDDEN_RIM_PX = 1  # pixels this close to the thread's are its rim (partly covered), not bare
HIDDEN_WINDOW_PX = 15  # half side of the window the bare background's level is taken in
HIDDEN_BACK_STEPS = 3  # keypoints behind an end where its background level is taken
HIDDEN_FAN_DEG = (0.0, -15.0, 15.0, -30.0, 30.0)  # rays around the end's way (its bend)


def _by_the_ends(
    cand: list[int],
    cost: np.ndarray,
    chord: np.ndarray,
    ok: np.ndarray,
    why: list[str],
    turn_in: np.ndarray,
    walk: np.ndarray,
    n: int,
    heading: np.ndarray,
    visited: np.ndarray,
    g: _WalkGraph,
    p: OrderingParams,
) -> None:
    """Deviation 38 on the jumps of :func:`_jumps` (``ok``, ``why`` updated in place): a jump
    turning by more than 90 deg in or out (at most ``hidden_turn_deg`` each) is allowed when
    both its ends run under an occluder in both views; a jump between two free ends is not
    (``join_free_ends`` False), nor, deviation 61, one between a hidden end and a free one with
    bare background all around its tip (``join_one_free_end`` False). Only a jump onto a piece's
    end is judged (a jump into a piece's middle has no end's way to look along). Candidates are
    judged cheapest first until two are left allowed: the walk takes the cheapest and branches
    at the runner-up, no other is ever taken (the views are read a few times per jump, not for
    every keypoint in reach)."""
    wide = p.hidden_turn_deg
    pos, adj = g.pos, g.adj
    cur = int(walk[n - 1])
    here = None
    left = 2
    for i in np.argsort(cost, kind="stable").tolist():
        if left == 0:
            break
        bend = not ok[i] and wide > 90.0 and turn_in[i] <= wide
        if not ok[i] and not bend:
            continue
        nb = _piece_end(cand[i], adj, visited)
        if nb < 0 or (ok[i] and p.join_free_ends):
            left -= int(ok[i])
            continue
        if here is None:
            back = int(walk[n - 3] if n >= 3 else walk[0])
            back_k = int(walk[max(n - 1 - HIDDEN_BACK_STEPS, 0)])  # background behind the end
            here = g.end_state(cur, back, back_k, heading)
        one_free = ok[i] and not p.join_one_free_end and here == "hidden"
        if (bend and here != "hidden") or (ok[i] and here != "free" and not one_free):
            left -= int(ok[i])
            continue
        v = cand[i]
        if bend and _turn_out(v, chord[i], adj, visited, pos) > wide:
            continue
        way = pos[v] - pos[nb]
        wn = float(np.hypot(*way))
        there = "unknown"
        if wn > 0:
            behind = _into_piece(v, adj, visited, HIDDEN_BACK_STEPS)
            there = g.end_state(v, nb, behind, way / wn)
        if ok[i] and there == "free" and here == "free":  # the thread's own two ends
            ok[i], why[i] = False, "two free ends"
        elif (
            ok[i]
            and not p.join_one_free_end
            and {here, there} == {"free", "hidden"}
            and (
                g.end_state(cur, back, back_k, heading, clear=True)
                if here == "free"
                else g.end_state(v, nb, behind, way / wn, clear=True)
            )
            == "free"
        ):  # deviation 61: bare background all around the free end's tip in both views
            ok[i], why[i] = False, "a free end and a hidden one"
        elif bend and there == "hidden":  # a bend under an occluder in both views
            ok[i], why[i] = True, ""
        left -= int(ok[i])


def _piece_end(v: int, adj: list[list[int]], visited: np.ndarray) -> int:
    """The one unvisited neighbour of ``v`` when ``v`` ends an unvisited piece, else -1 (a lone
    keypoint or one inside a piece: no end's way to look along)."""
    nb = -1
    for u in adj[v]:
        if not visited[u]:
            if nb >= 0:
                return -1
            nb = u
    return nb


def _into_piece(v: int, adj: list[list[int]], visited: np.ndarray, steps: int) -> int:
    """The keypoint ``steps`` along the unvisited piece that ends at ``v`` (or its last)."""
    prev, cur = -1, v
    for _ in range(steps):
        nxt = [u for u in adj[cur] if u != prev and not visited[u]]
        if len(nxt) != 1:
            break
        prev, cur = cur, nxt[0]
    return cur


def _end_state(
    lifted: LiftedPair,
    xy: np.ndarray,
    way: np.ndarray,
    d: float,
    inner: np.ndarray,
    clear: bool = False,
) -> Literal["hidden", "free", "unknown"]:
    """What the views show where the thread at an end keypoint ``xy`` (left view, px) stops.
    Along a ray from the end, to where it leaves the thread pixels (P_L; P_R at the end's
    disparity ``d``; within ``HIDDEN_SEARCH_PX``): the share of the disc of radius
    ``HIDDEN_DISC_PX`` there (its pixels off the thread) that is no bare background. Per view:
    "hidden" when the ray straight along the end's outward ``way`` (unit) finds at least
    ``HIDDEN_SHARE``; else "free" when it finds at most ``HIDDEN_FREE_SHARE`` off the thread's
    rim (bare background all around where the thread stops: nothing hides it, the thread's
    own end); else "hidden" when a ray within 30 deg of ``way`` finds ``HIDDEN_SHARE`` (the
    thread may bend where it goes under). The end's state is the views' when both agree, else
    "unknown" (also at the image border, or where the thread goes on). Bare: within
    max(``MONO_BARE_LEVELS``, 3 robust deviations) grey levels of the median of the view's
    non-thread pixels in a window around ``inner`` (a point of the thread behind the end,
    away from what the end runs into). With ``clear``, "free" also asks for a plain
    background (its tolerance at the floor, ``MONO_BARE_LEVELS``: on a textured one an
    occluder's grey may pass for the background's) and that at most ``HIDDEN_FREE_SHARE`` of
    the pixels within ``FREE_CLEAR_PX`` of the tip (off the thread and its rim) are no bare
    background (:func:`_share_around_tip`), else "unknown": an end beside an occluder it does
    not point at may still bend under it (deviation 61)."""
    states = []
    for grey, P, shift in ((lifted.grey_L, lifted.P_L, 0.0), (lifted.grey_R, lifted.P_R, d)):
        H, W = P.shape
        cx, cy = int(round(inner[0] - shift)), int(round(inner[1]))
        r = HIDDEN_WINDOW_PX
        win = (slice(max(cy - r, 0), max(cy + r + 1, 0)), slice(max(cx - r, 0), max(cx + r + 1, 0)))
        side = np.asarray(grey[win], dtype=np.float64)[~P[win]]
        if side.size < 10:
            return "unknown"
        level = float(np.median(side))
        tol = max(MONO_BARE_LEVELS, 3.0 * 1.4826 * float(np.median(np.abs(side - level))))
        straight = _occluded_share(grey, P, xy[0] - shift, xy[1], way, level, tol)
        if straight is not None and straight[0] >= HIDDEN_SHARE:
            states.append("hidden")
        elif straight is not None and straight[1] <= HIDDEN_FREE_SHARE:
            if clear and tol > MONO_BARE_LEVELS:
                return "unknown"  # a textured background: its grey cannot rule an occluder out
            # clear: bare background all around the tip too (however the thread would bend)
            wide = (
                _share_around_tip(grey, P, xy[0] - shift, xy[1], way, level, tol) if clear else 0.0
            )
            if wide is None or wide > HIDDEN_FREE_SHARE:
                return "unknown"
            states.append("free")
        elif any(  # the thread may bend where it goes under
            sh is not None and sh[0] >= HIDDEN_SHARE
            for sh in (
                _occluded_share(grey, P, xy[0] - shift, xy[1], _turned_by(way, a), level, tol)
                for a in HIDDEN_FAN_DEG[1:]
            )
        ):
            states.append("hidden")
        else:
            return "unknown"
    return states[0] if states[0] == states[1] else "unknown"


FREE_CLEAR_PX = 15  # a clear free end: bare background within this of its tip (half the
# thread's search past its end keypoint: a bend of 30 deg under an occluder starts within it)


def _share_around_tip(
    grey: np.ndarray, P: np.ndarray, x0: float, y0: float, way: np.ndarray, level: float, tol: float
) -> float | None:
    """The share of the pixels within FREE_CLEAR_PX of where the ray from (x0, y0) along
    ``way`` (unit) leaves the thread pixels ``P`` (the end's tip), off the thread and its
    1 px rim, that are no bare background (grey further than ``tol`` from ``level``); None
    when the ray stays on the thread or leaves the image, or no such pixel is left."""
    H, W = P.shape
    steps = np.arange(HIDDEN_SEARCH_PX + 1, dtype=np.float64)
    x = np.rint(x0 + steps * way[0]).astype(np.int64)
    y = np.rint(y0 + steps * way[1]).astype(np.int64)
    inside = (x >= 0) & (y >= 0) & (x < W) & (y < H)
    off = np.flatnonzero(~inside | ~P[np.clip(y, 0, H - 1), np.clip(x, 0, W - 1)])
    if not off.size or not inside[off[0]]:
        return None
    cx, cy, r = int(x[off[0]]), int(y[off[0]]), FREE_CLEAR_PX
    xa, xb, ya, yb = max(cx - r, 0), min(cx + r + 1, W), max(cy - r, 0), min(cy + r + 1, H)
    thread = np.ascontiguousarray(P[ya:yb, xa:xb], dtype=np.uint8)
    rim = cv2.dilate(thread, np.ones((2 * HIDDEN_RIM_PX + 1,) * 2, np.uint8)) > 0
    dx = np.arange(xa, xb)[None, :] - cx
    dy = np.arange(ya, yb)[:, None] - cy
    disc = (dx * dx + dy * dy <= r * r) & ~rim
    if not disc.any():
        return None
    other = np.abs(np.asarray(grey[ya:yb, xa:xb], dtype=np.float64) - level) > tol
    return float(np.mean(other[disc]))


def _turned_by(way: np.ndarray, deg: float) -> np.ndarray:
    """``way`` turned by ``deg`` degrees (image axes)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([c * way[0] - s * way[1], s * way[0] + c * way[1]])


def _occluded_share(
    grey: np.ndarray,
    P: np.ndarray,
    x0: float,
    y0: float,
    way: np.ndarray,
    level: float,
    tol: float,
) -> tuple[float, float] | None:
    """Where the ray from (x0, y0) along ``way`` leaves the thread pixels ``P``, the share of
    the disc's non-thread pixels farther than ``tol`` from the bare background's grey
    ``level``: of all of them, and of those off the thread's rim (not next to a thread pixel:
    a pixel the thread covers in part is neither), 1 when thread pixels lie in the disc more
    than ``HIDDEN_TIP_PX`` ahead of where the ray left the thread (it left a strand that goes
    on by its side, not its end); None when the ray stays on the thread over the search,
    leaves the image or the disc holds thread pixels only."""
    found, share, clean = walk_kernel.occluded_share(
        np.asarray(grey, dtype=np.float32), np.asarray(P, dtype=bool), float(x0), float(y0),
        float(way[0]), float(way[1]), HIDDEN_SEARCH_PX, float(level), float(tol), HIDDEN_DISC_PX,
        HIDDEN_RIM_PX, HIDDEN_TIP_PX,
    )  # fmt: skip
    return (float(share), float(clean)) if found else None
