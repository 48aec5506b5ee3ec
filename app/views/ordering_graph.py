"""Why the order came out as it did: the ordering's pieces, junctions, chosen path and, at each
decision of the walk, the continuations it rejected with their costs (``Ordering.graph``), as a
3D layer and as a 2D overlay over the left image."""

from __future__ import annotations

from typing import Any

import numpy as np

from threadrecon.app.views.registry import (
    Label,
    Layer,
    Points,
    Segments,
    layer_view,
    overlay_view,
    palette,
)
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.ordering import Decision, Ordering
from threadrecon.core.pipeline import Reconstruction

CHOSEN = (40, 220, 90)
REJECTED = (235, 60, 60)
JUNCTION = (255, 255, 255)
CHOSEN_CSS = "#28dc5a"
REJECTED_CSS = "#eb3c3c"
PIECE_ALPHA = 0.55  # pieces drawn faint on the image: the chosen path and decisions stand out
MAX_COST_LABELS = 40  # cost labels in 3D, spread along the walk (one scene node each, ~2 ms to
# send; an HD thread has hundreds of continuations); the 2D overlay labels every one


def cost_text(cost: float, reason: str = "") -> str:
    """A step cost as shown beside its continuation: the number, or the rule that excluded it."""
    if np.isfinite(cost):
        return f"{cost:.1f}"
    return {
        "turn > max_turn_deg": "x turn",
        "turn across the gap": "x gap turn",
        "two free ends": "x free ends",
    }.get(reason, "x")


def _steps(od: Ordering) -> list[tuple[Decision, int, float, str, bool]]:
    """(decision, to, cost, text, chosen) for every continuation of every decision (not the
    excluded-at-the-end ones' missing 'chosen')."""
    out = []
    for d in od.graph.decisions:
        if d.chosen >= 0:
            out.append((d, d.chosen, d.cost, cost_text(d.cost), True))
        for c in d.rejected:
            out.append((d, c.keypoint, c.cost, cost_text(c.cost, c.reason), False))
    return out


# --- 2D overlay ----------------------------------------------------------------------------


@overlay_view(
    "ordering_graph",
    "ordering graph",
    "segments",
    ("clustering", "ordering"),
    REJECTED_CSS,
    on=False,
    count=True,
    reveal="ordering",
)
def _ordering_graph_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    """Pieces (one faint colour each), then every decision's continuations: the chosen one
    green, the rejected ones red, each labelled with its cost at its middle."""
    kp = rec["clustering"].keypoints_px[:, :2]
    od: Ordering = rec["ordering"]
    segments: list[list[float]] = []
    colors: list[str] = []
    pal = palette(max(len(od.graph.pieces), 1))
    for i, piece in enumerate(od.graph.pieces):
        r, g, b = (int(v) for v in pal[i])
        for a, c in zip(piece[:-1], piece[1:], strict=True):
            segments.append([*kp[a], *kp[c]])
            colors.append(f"rgba({r},{g},{b},{PIECE_ALPHA})")
    labels: list[list[Any]] = []
    for d, to, _, text, chosen in _steps(od):
        css = CHOSEN_CSS if chosen else REJECTED_CSS
        segments.append([*kp[d.at], *kp[to]])
        colors.append(css)
        mid = 0.5 * (kp[d.at] + kp[to])
        labels.append([round(float(mid[0]), 1), round(float(mid[1]), 1), text, css])
    return {
        "left": {
            "segments": np.round(np.array(segments, dtype=float).reshape(-1, 4), 2),
            "colors": colors,
            "labels": labels,
        }
    }


# --- 3D layer ------------------------------------------------------------------------------


@layer_view("ordering_graph", needs=("clustering", "ordering"), shows_at="ordering")
def _ordering_graph_layer(
    rec: Reconstruction, calib: StereoCalibration, gt: np.ndarray | None
) -> Layer:
    """``pieces`` (one colour per piece), ``junctions``, ``chosen`` and ``rejected``
    continuations at the walk's decisions, and ``costs/k`` labels (k = 0, 1, ...: the same
    names whichever continuations they label, so a redraw updates them in place) at the
    middles of at most ``MAX_COST_LABELS`` of them."""
    kp = rec["clustering"].keypoints.astype(np.float32)
    od: Ordering = rec["ordering"]
    finite = np.isfinite(kp).all(axis=1)
    nodes: Layer = {}
    pal = palette(max(len(od.graph.pieces), 1))
    steps_of = [
        (a, b, i)
        for i, piece in enumerate(od.graph.pieces)
        for a, b in zip(piece[:-1], piece[1:], strict=True)
    ]
    pairs = np.array(steps_of, dtype=np.int64).reshape(-1, 3)
    pairs = pairs[finite[pairs[:, :2]].all(axis=1)]
    if len(pairs):  # one node for every piece (a node costs ~2 ms to send; HD: hundreds)
        nodes["pieces"] = Segments(kp[pairs[:, :2]], pal[pairs[:, 2]], 2.0)
    junctions = od.graph.junctions[finite[od.graph.junctions]]
    if junctions.size:
        nodes["junctions"] = Points(kp[junctions], np.array(JUNCTION, np.uint8), 5.0)
    chosen: list[tuple[int, int]] = []
    rejected: list[tuple[int, int]] = []
    steps = _steps(od)
    labelled = set(np.linspace(0, len(steps) - 1, min(len(steps), MAX_COST_LABELS)).astype(int))
    n_labels = 0
    for j, (d, to, _, text, is_chosen) in enumerate(steps):
        if not (finite[d.at] and finite[to]):
            continue
        (chosen if is_chosen else rejected).append((d.at, to))
        if j in labelled:
            nodes[f"costs/{n_labels}"] = Label(text, 0.5 * (kp[d.at] + kp[to]))
            n_labels += 1
    for name, pairs, color, width in (
        ("chosen", chosen, CHOSEN, 4.0),
        ("rejected", rejected, REJECTED, 2.0),
    ):
        if pairs:
            nodes[name] = Segments(kp[np.array(pairs)], color, width)
    return nodes
