"""A layer's viser nodes (app.scene_nodes): a redraw updates the existing handles of the nodes
with the same sub-path and kind in place, and creates or removes only the others."""

from __future__ import annotations

import contextlib
import io
import socket

import numpy as np
import pytest

from threadrecon.app.scene_nodes import LINE_TOL_FRAC, LayerNodes
from threadrecon.app.views import Label, Points, Segments, polyline


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def scene():
    import viser

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    yield server.scene
    server.stop()


def _nodes(rng: np.random.Generator, n: int, k: int, per_segment: bool = False) -> dict:
    t = np.linspace(0.0, 1.0, k)
    curve = np.c_[np.cos(5 * t), np.sin(5 * t), 10.0 + t].astype(np.float32)
    color = rng.integers(0, 255, (k - 1, 3)).astype(np.uint8) if per_segment else (255, 0, 200)
    return {
        "cloud": Points(
            rng.normal(size=(n, 3)).astype(np.float32), np.array((1, 2, 3), np.uint8), 2.0
        ),
        "curve": Segments(polyline(curve), color, 3.0),
        "tag": Label(f"n={n}", curve[0]),
    }


def test_a_redraw_with_the_same_nodes_updates_the_handles_in_place(scene):
    rng = np.random.default_rng(4)
    nodes = LayerNodes(scene, "t_inplace", visible=True)
    assert nodes.draw(_nodes(rng, 50, 300), base=0.1) == 3  # first draw: created
    handles = {s: h for s, (_, h) in nodes._handles.items()}
    again = _nodes(rng, 70, 200)
    assert nodes.draw(again, base=0.2) == 0  # same names and kinds: in place
    assert all(nodes._handles[s][1] is h for s, h in handles.items())
    cloud = handles["cloud"]
    np.testing.assert_array_equal(cloud.points, again["cloud"].points)
    assert cloud.point_size == pytest.approx(0.2 * 2.0)
    assert handles["tag"].text == "n=70"
    drawn = handles["curve"].points  # thinned for display, within the tolerance, ends kept
    assert len(drawn) < 199 and drawn.shape[1:] == (2, 3)
    np.testing.assert_array_equal(drawn[0, 0], again["curve"].points[0, 0])
    np.testing.assert_array_equal(drawn[-1, 1], again["curve"].points[-1, 1])
    verts = again["curve"].points[:, 0].astype(np.float64)  # each within tol of the drawing
    a, b = drawn[:, 0].astype(np.float64), drawn[:, 1].astype(np.float64)
    ab = b - a
    t = np.clip(((verts[:, None] - a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    d = np.linalg.norm(verts[:, None] - a - t[..., None] * ab, axis=-1).min(axis=1)
    assert d.max() <= LINE_TOL_FRAC * 0.2 + 1e-6
    nodes.remove()


def test_a_redraw_with_other_nodes_replaces_only_those(scene):
    rng = np.random.default_rng(5)
    nodes = LayerNodes(scene, "t_replace", visible=False)
    nodes.draw(_nodes(rng, 10, 300), base=0.1)
    first = {s: h for s, (_, h) in nodes._handles.items()}
    assert nodes.draw(_nodes(rng, 10, 300, per_segment=True), base=0.1) == 1  # colour kind
    assert nodes._handles["curve"][1] is not first["curve"] and first["curve"]._impl.removed
    assert nodes._handles["cloud"][1] is first["cloud"] and not first["cloud"]._impl.removed
    assert nodes._handles["tag"][1] is first["tag"]
    more = _nodes(rng, 10, 300, per_segment=True)  # a label appears (e.g. one more cost)
    more["tag2"] = Label("two", np.zeros(3, np.float32))
    kept = {s: h for s, (_, h) in nodes._handles.items()}
    assert nodes.draw(more, base=0.1) == 1
    assert all(nodes._handles[s][1] is h and not h._impl.removed for s, h in kept.items())
    fewer = dict(more)
    del fewer["tag"], fewer["tag2"]
    assert nodes.draw(fewer, base=0.1) == 0
    assert set(nodes._handles) == {"cloud", "curve"} and kept["tag"]._impl.removed
    assert nodes._handles["curve"][1] is kept["curve"]
    fewer["curve"] = Segments(np.zeros((0, 2, 3), np.float32), (1, 1, 1), 1.0)  # empty: no node
    assert nodes.draw(fewer, base=0.1) == 0
    assert set(nodes._handles) == {"cloud"} and kept["curve"]._impl.removed
    assert nodes._frame.visible is False
    nodes.set_visible(True)
    assert nodes._frame.visible is True
    nodes.remove()
    assert nodes._handles == {} and nodes._frame is None
