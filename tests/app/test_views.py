"""The debugger's views: stage JSON, overlays, pixel inspector, 3D layers, controls."""

from __future__ import annotations

import json
from dataclasses import fields

import numpy as np
import pytest
from support import synthetic_case

from threadrecon.app.controls import controls
from threadrecon.app.dataset import evaluate_reconstruction
from threadrecon.app.views import (
    LAYERS,
    OVERLAY_VIEWS,
    Label,
    Points,
    Segments,
    layer,
    nearest_to_ray,
    overlay,
    overlay_view,
    palette,
    pixel_info,
    stage_json,
)
from threadrecon.core.metrics import project
from threadrecon.core.pipeline import STAGES, Pipeline, ReconParams, reconstruct


@pytest.fixture(scope="module")
def case():
    pair, calib, gt = synthetic_case(seed=3)
    rec = reconstruct(pair, calib)
    assert rec.status == "ok", rec.message
    return rec, calib, gt


def test_every_stage_serialises_to_strict_json(case):
    rec, _, _ = case
    for stage in STAGES:
        data = stage_json(rec, stage)
        json.dumps(data, allow_nan=False)
        assert data["stage"] == stage and data["ms"] >= 0
    assert "energy" not in stage_json(rec, "stereo")["result"]  # served per pixel instead
    omitted = stage_json(rec, "segment")["result"]["omitted"]
    assert omitted["P_L"]["count"] == int(rec["segment"].P_L.sum())
    with pytest.raises(KeyError):
        stage_json(rec, "nope")


def test_overlay_spline_is_the_projected_camera_curve(case):
    rec, calib, _ = case
    ov = overlay(rec, calib)
    json.dumps(ov, allow_nan=False)
    uv = np.array(ov["spline"]["left"]["points"])
    ref = project(rec["camera"].points, calib.P1)
    # both sample the same curve: every overlay point lies on the projected camera curve
    d = np.linalg.norm(uv[:, None, :] - ref[None, :, :], axis=2).min(axis=1)
    assert d.max() < 1.0
    assert len(ov["reliable"]["left"]) == 2 * rec["reliability"].count


def test_overlay_errors_are_the_evaluation_metrics_exactly(case):
    rec, calib, gt = case
    ov = overlay(rec, calib)
    metrics = evaluate_reconstruction(rec, calib, gt)
    for side in ("left", "right"):
        assert ov["spline"][side]["mean_px"] == metrics[f"{side}_mean_px"]
        assert ov["spline"][side]["max_px"] == metrics[f"{side}_max_px"]
        assert ov["spline"][side]["coverage"] == metrics[f"coverage_{side}"]


def test_pixel_inspector_reports_the_energy_minimum(case):
    rec, _, _ = case
    st = rec["stereo"]
    for i in (0, len(st.pixels) // 2, len(st.pixels) - 1):
        x, y = (int(v) for v in st.pixels[i])
        info = pixel_info(rec, x, y)
        assert (info["x"], info["y"]) == (x, y)
        assert info["d_min"] == int(np.nanargmin(st.energy[i]))
        assert info["R"] == pytest.approx(float(rec["reliability"].R[i]))
    with pytest.raises(ValueError, match="outside"):
        pixel_info(rec, -1, 0)


def test_nearest_to_ray_picks_the_point_under_the_cursor():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (500, 3)) + [0, 0, 10]
    target = 123
    origin = np.array([0.0, 0.0, 0.0])
    direction = pts[target] / np.linalg.norm(pts[target])
    assert nearest_to_ray(pts, origin, direction, tol=1e-6) == target
    assert nearest_to_ray(pts, origin, -direction, tol=0.05) is None  # behind the camera
    pts[target] = np.nan
    assert nearest_to_ray(pts, origin, direction, tol=1e-6) is None


def test_layers_are_finite_float32_geometry(case):
    rec, calib, gt = case
    for name in LAYERS:
        nodes = layer(name, rec, calib, gt)
        assert nodes, name
        for node in nodes.values():
            if isinstance(node, Points):
                assert node.points.dtype == np.float32 and node.points.shape[1] == 3
                assert np.isfinite(node.points).all()
                assert node.colors.dtype == np.uint8
            elif isinstance(node, Segments):
                assert node.points.shape[1:] == (2, 3) and np.isfinite(node.points).all()
            else:
                assert isinstance(node, Label)
    members = layer("clusters", rec, calib, gt)["members"]
    assert len(members.points) == int((rec["clustering"].labels >= 0).sum())


def test_path_index_labels_are_named_by_slot(case):
    """labels/0, labels/1, ... whichever path indices they show: a redraw with as many labels
    updates them in place (app.scene_nodes)."""
    rec, calib, gt = case
    nodes = layer("ordering", rec, calib, gt)
    names = [k for k in nodes if k.startswith("labels/")]
    assert names == [f"labels/{k}" for k in range(len(names))] and len(names) > 2
    n = len(rec["ordering"].path_px)
    assert nodes[names[0]].text == "0" and nodes[names[-1]].text == str(n - 1)


def test_palette_colours_are_distinct():
    p = palette(40)
    assert len({tuple(c) for c in p}) == 40


def test_controls_cover_every_parameter_and_hold_the_defaults():
    ctl = {c.key: c for c in controls()}
    defaults = ReconParams()
    for stage in STAGES:
        group = getattr(defaults, stage)
        for f in fields(group):
            value = getattr(group, f.name)
            key = f"{stage}.{f.name}"
            if value is None:
                continue  # "auto" values are set in presets
            assert key in ctl, key
            c = ctl[key]
            if c.kind == "slider":
                assert c.min <= value <= c.max, key
    for key in ("segment.seg_delta", "stereo.alpha", "stereo.window", "reliability.eps1",
                "reliability.eps2", "reliability.eps3", "reliability.threshold",
                "clustering.min_size", "clustering.max_size", "clustering.radius",
                "ordering.solidify_radius", "bounds.r_k_frac", "bounds.bound_scale",
                "bounds.widen_px", "spline.n_ctrl", "spline.degree", "spline.max_iter"):  # fmt: skip
        assert ctl[key].kind == "slider", key


PAYLOAD_CHECKS = {
    "pixels": lambda p: (
        isinstance(p, list) and len(p) % 2 == 0 and all(isinstance(v, int) for v in p)
    ),
    "circles": lambda p: all(len(q) == 2 for q in p),
    "squares": lambda p: all(len(q) == 3 and isinstance(q[2], bool) for q in p),
    "polyline": lambda p: (
        all(len(q) == 2 for q in p["points"])
        and ("colors" not in p or len(p["colors"]) == len(p["points"]))
    ),
    "segments": lambda p: (
        all(len(q) == 4 for q in p["segments"])
        and ("colors" not in p or len(p["colors"]) == len(p["segments"]))
        and all(len(q) == 4 and isinstance(q[2], str) for q in p.get("labels", []))
    ),
}


def test_every_registered_overlay_has_the_payload_of_its_kind(case):
    rec, calib, _ = case
    ov = overlay(rec, calib)
    assert set(OVERLAY_VIEWS) <= set(ov)  # every stage ran: every overlay is there
    assert set(ov["_pixels"]) == {k for k, v in OVERLAY_VIEWS.items() if v.kind == "pixels"}
    for key, view in OVERLAY_VIEWS.items():
        assert ov[key], key
        for side, payload in ov[key].items():
            assert side in ("left", "right"), (key, side)
            assert PAYLOAD_CHECKS[view.kind](payload), (key, side)


def test_overlays_wait_for_their_stages():
    pair, calib, _ = synthetic_case(seed=3)
    rec = Pipeline(pair, calib).run(until="stereo")
    ov = overlay(rec, calib)
    assert "segmented" in ov and "reliable" not in ov and "spline" not in ov


def test_an_overlay_on_an_unknown_stage_is_refused():
    with pytest.raises(ValueError, match="unknown stages"):
        overlay_view("x", "x", "pixels", ("nope",), "#fff")(lambda rec, calib: {})
    assert "x" not in OVERLAY_VIEWS


# --- display decimation (HD frames): the overlays and clouds, never the computation ----------


@pytest.mark.parametrize("seed", range(5))
def test_decimated_pixel_blocks_cover_every_pixel_within_the_budget(seed):
    from threadrecon.app.views.data import decimate_pixels

    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 4000))
    pixels = np.unique(rng.integers(0, 400, size=(n, 2)), axis=0)
    budget = int(rng.integers(10, len(pixels) + 1))
    blocks, step = decimate_pixels(pixels, budget)
    assert len(blocks) <= budget
    if step > 1:  # the smallest such step: one less would exceed the budget
        assert len(np.unique(pixels // (step - 1), axis=0)) > budget
    # every pixel lies in exactly one block (top-left corners on the step grid, no duplicates)
    assert np.all(blocks % step == 0)
    assert len(np.unique(blocks, axis=0)) == len(blocks)
    corners = {tuple(b) for b in blocks.tolist()}
    assert all(((x // step) * step, (y // step) * step) in corners for x, y in pixels.tolist())
    # and every block holds a pixel
    assert len(corners) == len(
        {((x // step) * step, (y // step) * step) for x, y in pixels.tolist()}
    )


def test_pixels_within_the_budget_are_sent_unchanged():
    from threadrecon.app.views.data import decimate_pixels

    pixels = np.array([[5, 1], [3, 2], [9, 9]])
    blocks, step = decimate_pixels(pixels, 3)
    assert step == 1 and blocks.tolist() == pixels.tolist()
    with pytest.raises(ValueError, match="budget"):
        decimate_pixels(pixels, 0)


def test_overlay_reports_the_full_counts_when_it_decimates(case, monkeypatch):
    from threadrecon.app.views import data

    rec, calib, _ = case
    n_seg = len(rec["stereo"].pixels)
    monkeypatch.setattr(data, "OVERLAY_PIXELS", n_seg // 3)
    ov = overlay(rec, calib)
    meta = ov["_pixels"]
    assert meta["segmented"]["left"]["count"] == n_seg
    assert meta["reliable"]["left"]["count"] == rec["reliability"].count
    assert meta["segmented"]["left"]["step"] >= 2
    assert len(ov["segmented"]["left"]) // 2 <= n_seg // 3


def test_decimated_cloud_keeps_per_point_colours_aligned():
    from threadrecon.app.display import decimate_cloud

    pts = np.arange(30_000, dtype=np.float32)[:, None] * np.ones(3, np.float32)
    cols = (np.arange(30_000) % 256).astype(np.uint8)[:, None] * np.ones(3, np.uint8)
    p, c = decimate_cloud(pts, cols, 10_000)
    assert len(p) <= 10_000 and len(p) == len(c)
    assert np.array_equal(c[:, 0], (p[:, 0].astype(int) % 256).astype(np.uint8))
    single = np.array((1, 2, 3), np.uint8)
    p, c = decimate_cloud(pts, single, 7)
    assert len(p) <= 7 and c is single
    p, c = decimate_cloud(pts[:5], cols[:5], 7)
    assert len(p) == 5


# --- overlay cache: a slider rebuilds and resends only the overlays of the stages it changed --


def test_overlay_cache_rebuilds_only_the_overlays_of_changed_stages():
    from threadrecon.app.library import merge_params
    from threadrecon.app.views import OverlayCache

    pair, calib, _ = synthetic_case(seed=3)
    pipe = Pipeline(pair, calib)
    cache = OverlayCache()
    first = cache.answer(pipe.run(), calib)
    assert set(first["_tags"]) == set(OVERLAY_VIEWS)  # every stage ran
    assert first == {**overlay(pipe.run(), calib), "_tags": first["_tags"], "_later": []}
    n_ctrl = ReconParams().spline.n_ctrl
    rec = pipe.run(merge_params(ReconParams(), {"spline": {"n_ctrl": n_ctrl + 2}}))
    known = frozenset(first["_tags"].values())
    again = cache.answer(rec, calib, known)
    spline_only = {
        k for k, v in OVERLAY_VIEWS.items() if set(v.needs) <= {"spline", "camera", "check"}
    }
    changed = {k for k in again["_tags"] if again["_tags"][k] != first["_tags"][k]}
    assert changed == spline_only & changed and {"spline", "spline_initial"} <= changed
    assert set(again) - {"shape", "_pixels", "_tags", "_later"} == changed  # the rest left out
    assert again["_pixels"] == first["_pixels"]  # decimation figures are always there
    assert cache.answer(rec, calib, known | set(again["_tags"].values())).keys() == {
        "shape",
        "_pixels",
        "_tags",
        "_later",
    }


def test_an_overlay_the_page_does_not_show_is_built_once_it_is_asked_for(monkeypatch):
    # the ordering graph's overlay is off when the page opens: a slider's answer neither builds
    # nor sends it (at 1920x1080 ~180 kB, and the graph ~90 ms), but names it for later
    import dataclasses

    from threadrecon.app.views import OverlayCache

    pair, calib, _ = synthetic_case(seed=3)
    rec = Pipeline(pair, calib).run()
    made: list[str] = []
    view = OVERLAY_VIEWS["ordering_graph"]
    counted = dataclasses.replace(
        view, make=lambda r, c: (made.append(view.key), view.make(r, c))[1]
    )
    monkeypatch.setitem(OVERLAY_VIEWS, "ordering_graph", counted)
    shown = frozenset(k for k, v in OVERLAY_VIEWS.items() if v.on)
    assert "ordering_graph" not in shown
    cache = OverlayCache()
    first = cache.answer(rec, calib, keys=shown)
    assert not made and "ordering_graph" not in first and "ordering_graph" not in first["_tags"]
    assert set(first["_later"]) == set(OVERLAY_VIEWS) - shown and set(first["_tags"]) == shown
    held = frozenset(first["_tags"].values())
    later = cache.answer(rec, calib, held, shown | {"ordering_graph"})  # turned on
    assert made == ["ordering_graph"]
    assert set(later["_later"]) == set(first["_later"]) - {"ordering_graph"}
    assert set(later) - {"shape", "_pixels", "_tags", "_later"} == {"ordering_graph"}
    assert later["ordering_graph"] == json.loads(json.dumps(overlay(rec, calib)["ordering_graph"]))
    assert later["_tags"]["spline"] == first["_tags"]["spline"]  # the rest held, not rebuilt


def test_a_layer_is_redrawn_when_any_result_it_is_drawn_from_changes():
    # the stereo cloud is coloured by R (reliability), the spline layer shows the camera
    # stage's control points: a layer keyed on fewer stages would keep stale nodes
    pair, calib, gt = synthetic_case(seed=3)
    rec = Pipeline(pair, calib).run()

    def before(stage):
        runs = {k: v for k, v in rec.runs.items() if STAGES.index(k) < STAGES.index(stage)}
        return type(rec)(runs, None, None, rec.params)

    grey = layer("stereo", before("reliability"), calib, gt)["depth"].colors
    assert grey.shape == (3,) and layer("stereo", rec, calib, gt)["depth"].colors.ndim == 2
    assert "reliability" in LAYERS["stereo"]
    assert "control_points" not in layer("spline", before("camera"), calib, gt)
    assert "control_points" in layer("spline", rec, calib, gt)
    assert "camera" in LAYERS["spline"]


def test_the_ground_truth_is_a_layer_of_its_own_that_no_slider_redraws():
    pair, calib, gt = synthetic_case(seed=3)
    rec = Pipeline(pair, calib).run()
    assert LAYERS["ground_truth"] == ()  # keyed on no stage result: drawn once per frame
    assert "ground_truth" not in layer("spline", rec, calib, gt)
    curve = layer("ground_truth", rec, calib, gt)["curve"]
    np.testing.assert_allclose(curve.points[:, 0], gt[:-1], rtol=1e-6)
    assert layer("ground_truth", rec, calib, None) == {}
