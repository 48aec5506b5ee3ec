"""The same ordering walked from the other end: what the stages after the ordering must treat
as the same problem (issue 12: the curve must not depend on which end the walk started at).

The ordering stage picks a start end (its walk is greedy from one end); everything after it,
the depth bounds of Eq. (7), the Minimum Variation Spline of Eq. (8), the two-view refinement
and the self-check, should give the same curve, traversed the other way, for the reversed
ordering. :func:`reversed_ordering` builds that reversed input, for tests and for
``scripts/direction_check.py``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from threadrecon.core.ordering import Ordering


def reversed_ordering(o: Ordering) -> Ordering:
    """``o`` walked from its last keypoint to its first: ``order``, ``path_px``, ``links``,
    the ends' tip disparities, dead ends and one-view end points reversed; every gap pixel's
    link renumbered from the other end and its position t along the link mirrored (1 - t);
    the walk's decisions re-indexed. The graph A, the pixels and their nodes are the same."""
    M = len(o.order)
    on_link = o.pixel_link >= 0
    pixel_link = np.where(on_link, (M - 2) - o.pixel_link, -1)
    pixel_t = np.where(on_link, 1.0 - o.pixel_t, o.pixel_t)
    decisions = tuple(dataclasses.replace(d, step=M - 1 - d.step) for d in o.graph.decisions)
    return dataclasses.replace(
        o,
        order=o.order[::-1].copy(),
        path_px=o.path_px[::-1].copy(),
        links=tuple(o.links[::-1]),
        pixel_t=pixel_t,
        pixel_link=pixel_link,
        graph=dataclasses.replace(o.graph, decisions=decisions[::-1]),
        end_disparity=o.end_disparity[::-1].copy(),
        dead_end=o.dead_end[::-1],
        mono=o.mono[::-1],
    )
