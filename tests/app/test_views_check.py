"""The check stage's views: the curve coloured by confidence (3D and 2D), the grasp point and
its tangent, and the verdict the status panel shows."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from support import synthetic_case

from threadrecon.app.views import LAYER_VIEWS, Points, Segments, layer, overlay
from threadrecon.app.views.check import check_json, confidence_colors
from threadrecon.core.metrics import project
from threadrecon.core.pipeline import Pipeline, ReconParams, reconstruct


@pytest.fixture(scope="module")
def case():
    pair, calib, gt = synthetic_case(seed=5)
    rec = reconstruct(pair, calib)
    assert rec.status == "ok", rec.message
    return rec, calib, gt


def test_confidence_colours_run_red_to_green_and_survive_nan():
    c = confidence_colors(np.array([0.0, 0.5, 1.0, np.nan, 7.0]))
    assert c.dtype == np.uint8 and c.shape == (5, 3)
    assert c[0, 0] > 200 and c[0, 1] < 60  # red
    assert c[1, 0] > 200 and c[1, 1] > 180  # yellow
    assert c[2, 1] > 180 and c[2, 0] < 60  # green
    assert (c[3] == c[0]).all() and (c[4] == c[2]).all()  # NaN as 0, clipped above 1


def test_check_layer_colours_every_curve_segment_by_its_confidence(case):
    rec, calib, gt = case
    assert list(LAYER_VIEWS)[-1] == "check"  # after the stages' layers
    nodes = layer("check", rec, calib, gt)
    chk = rec["check"]
    pts = nodes["points"]
    assert isinstance(pts, Points)
    np.testing.assert_array_equal(pts.colors, confidence_colors(chk.confidence))
    segs = nodes["confidence"]
    assert isinstance(segs, Segments) and len(segs.points) == len(rec["camera"].points) - 1
    np.testing.assert_array_equal(segs.points[1:, 0], segs.points[:-1, 1])  # one chain
    weaker = np.minimum(chk.confidence[:-1], chk.confidence[1:])
    np.testing.assert_array_equal(segs.color, confidence_colors(weaker))
    g = chk.grasp
    np.testing.assert_allclose(nodes["grasp/point"].points[0], g.point, rtol=1e-6)
    tangent = nodes["grasp/tangent"]
    assert isinstance(tangent, Segments)
    d = tangent.points[1, 1] - tangent.points[0, 0]
    np.testing.assert_allclose(d / np.linalg.norm(d), g.tangent, atol=1e-5)  # along the tangent


def test_confidence_overlay_is_the_projected_curve_with_one_colour_per_point(case):
    rec, calib, _ = case
    ov = overlay(rec, calib)
    json.dumps(ov, allow_nan=False)
    conf = ov["confidence"]
    for side, P in (("left", calib.P1), ("right", calib.P2)):
        uv = np.array(conf[side]["points"])
        np.testing.assert_allclose(uv, project(rec["camera"].points, P), atol=0.006)
        colors = conf[side]["colors"]
        assert len(colors) == len(uv) and all(c.startswith("#") and len(c) == 7 for c in colors)
    g = rec["check"].grasp
    grasp_uv = np.array(ov["grasp"]["left"][0])
    np.testing.assert_allclose(grasp_uv, project(np.stack([g.point] * 2), calib.P1)[0], atol=0.006)
    line = np.array(ov["grasp_tangent"]["left"]["points"])
    assert line.shape == (3, 2)
    np.testing.assert_allclose(line[1], grasp_uv)  # the tangent passes through the grasp point


def test_check_json_names_status_reasons_score_and_grasp(case):
    rec, _, _ = case
    got = check_json(rec)
    json.dumps(got, allow_nan=False)
    chk = rec["check"]
    assert got["status"] == chk.status and got["reasons"] == list(chk.reasons)
    assert got["score"] == chk.score and 1 <= got["score"] <= 5
    assert got["rating"] == chk.rating and abs(got["rating"] - got["score"]) <= 0.5
    assert got["grasp"]["confidence"] == chk.grasp.confidence
    assert 0 <= got["confidence_min"] <= got["confidence_mean"] <= 1


def test_check_json_of_a_suspect_curve_lists_every_reason():
    pair, calib, _ = synthetic_case(seed=5)
    strict = replace(ReconParams().check, reproj_mean_px=0.0, reproj_max_px=0.0)
    rec = Pipeline(pair, calib).run(replace(ReconParams(), check=strict))
    got = check_json(rec)
    assert got["status"] == "suspect"
    assert len(got["reasons"]) >= 2 and any("left projection" in r for r in got["reasons"])


def test_check_json_waits_for_the_check_stage():
    pair, calib, _ = synthetic_case(seed=5)
    assert check_json(None) is None
    assert check_json(Pipeline(pair, calib).run(until="camera")) is None
