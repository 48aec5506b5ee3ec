"""The ordering-graph views (issue 12): pieces, junctions, the chosen path and the rejected
continuations with their costs, as the stage JSON, the 3D layer and the 2D overlay show them."""

from __future__ import annotations

import json

import numpy as np
import pytest
from support import synthetic_case

from threadrecon.app.views import Label, Points, Segments, layer, overlay, stage_json
from threadrecon.app.views.ordering_graph import MAX_COST_LABELS, cost_text
from threadrecon.core.pipeline import Pipeline, ReconParams


@pytest.fixture(scope="module")
def crossing():
    pair, calib, gt = synthetic_case(seed=1, crossing=True)
    rec = Pipeline(pair, calib).run(ReconParams(), until="ordering")
    assert rec.status == "ok", rec.message
    return rec, calib, gt


def test_ordering_json_carries_the_decisions_with_their_costs(crossing):
    rec, _, _ = crossing
    data = stage_json(rec, "ordering")
    json.dumps(data, allow_nan=False)
    graph = data["result"]["graph"]
    od = rec["ordering"]
    assert len(graph["decisions"]) == len(od.graph.decisions) > 0
    assert sum(len(p) for p in graph["pieces"]) >= od.n_clusters  # junctions end several pieces
    for d, dj in zip(od.graph.decisions, graph["decisions"], strict=True):
        assert dj["at"] == d.at == od.order[d.step]
        assert dj["chosen"] == d.chosen == (od.order[d.step + 1] if d.chosen >= 0 else -1)
        assert dj["kind"] in ("neighbour", "crossing", "jump", "end")
        for c in dj["rejected"]:
            assert c["cost"] is None or c["cost"] >= 0
            assert isinstance(c["reason"], str) and c["reason"]


def test_overlay_labels_every_continuation_with_its_cost(crossing):
    rec, calib, _ = crossing
    payload = overlay(rec, calib)["ordering_graph"]["left"]
    od = rec["ordering"]
    n_cont = sum(len(d.rejected) + (d.chosen >= 0) for d in od.graph.decisions)
    assert len(payload["labels"]) == n_cont
    n_piece_segments = sum(len(p) - 1 for p in od.graph.pieces)
    assert len(payload["segments"]) == len(payload["colors"]) == n_piece_segments + n_cont
    kp = rec["clustering"].keypoints_px[:, :2]
    d = od.graph.decisions[0]
    first = payload["segments"][n_piece_segments]  # the first decision's chosen step
    np.testing.assert_allclose(first, [*kp[d.at], *kp[d.chosen]], atol=0.01)
    assert payload["labels"][0][2] == f"{d.cost:.1f}"


def test_layer_draws_chosen_and_rejected_steps_and_cost_labels(crossing):
    rec, calib, gt = crossing
    nodes = layer("ordering_graph", rec, calib, gt)
    od = rec["ordering"]
    kp = rec["clustering"].keypoints
    n_rej = sum(len(d.rejected) for d in od.graph.decisions)
    assert isinstance(nodes["rejected"], Segments) and len(nodes["rejected"].points) == n_rej
    assert len(nodes["chosen"].points) == sum(d.chosen >= 0 for d in od.graph.decisions)
    labels = [v for k, v in nodes.items() if k.startswith("costs/")]
    assert len(labels) == min(n_rej + len(nodes["chosen"].points), MAX_COST_LABELS)
    # named by slot, not by continuation: a redraw with as many labels updates them in place
    assert [k for k in nodes if k.startswith("costs/")] == [
        f"costs/{k}" for k in range(len(labels))
    ]
    assert all(isinstance(v, Label) for v in labels)
    assert isinstance(nodes["junctions"], Points)
    np.testing.assert_allclose(nodes["junctions"].points, kp[od.graph.junctions], rtol=1e-6)
    pieces = nodes["pieces"]  # one node, one colour per piece
    assert len(pieces.points) == sum(len(p) - 1 for p in od.graph.pieces)
    assert pieces.color.shape == (len(pieces.points), 3)
    assert len({tuple(c) for c in pieces.color}) == sum(len(p) > 1 for p in od.graph.pieces)


def test_excluded_continuations_name_their_rule():
    assert cost_text(12.345) == "12.3"
    assert cost_text(float("inf"), "turn > max_turn_deg") == "x turn"
    assert cost_text(float("inf"), "turn across the gap") == "x gap turn"
    assert cost_text(float("inf"), "two free ends") == "x free ends"
