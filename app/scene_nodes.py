"""The viser nodes of one 3D layer, kept between redraws.

A slider move redraws a few layers (a spline move: the spline and the check). Creating a node
costs the server about a millisecond of Python (viser resolves the handle's typed properties
anew for every handle) and the viewer a remount (new React components, geometry and material).
A redraw with the same node names and kinds instead assigns the new arrays to the existing
handles: one property update per changed array, which the viewer applies to the mounted
objects. A redraw where some nodes appear, go or change kind (a colour turns from one to
per-point) replaces only those: an eps slider changes the ordering's and its graph's label
count, and re-creating all their ~50 labels cost the server 45 ms of a move's ~90 ms of
publishing at 1920x1080. Display thinning (``app.display``) happens here, once per drawn node.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from threadrecon.app.display import decimate_cloud, simplify_segments
from threadrecon.app.views import Label, Points, Segments

CLOUD_POINTS = 12_000  # display budget of one point cloud: a 640x480 thread is drawn whole; a
# 1920x1080 one (20-40k points a layer, 15 bytes each, resent on every slider move) every k-th
LINE_TOL_FRAC = 0.2  # a drawn polyline leaves out vertices within this many base point sizes
# (0.05 % of the thread's depth, about a pixel of the default view) of its chord: software
# WebGL pays ~25 us a segment every frame (app.display)

Node = Points | Segments | Label


def _kind(node: Node) -> tuple[str, bool] | None:
    """What kind of viser node ``node`` becomes (None: none, an empty set of segments), and
    whether its colour is one per point or segment: handles are reused only for the same."""
    if isinstance(node, Points):
        return "points", node.colors.ndim == 2
    if isinstance(node, Segments):
        if not len(node.points):
            return None
        return "segments", isinstance(node.color, np.ndarray) and node.color.ndim == 2
    return "label", False


class LayerNodes:
    """The nodes of the layer ``/name`` in a viser scene (``viser.SceneApi``)."""

    def __init__(self, scene: Any, name: str, visible: bool) -> None:
        self.scene = scene
        self.root = f"/{name}"
        self._visible = visible
        self._frame: Any = None
        self._handles: dict[str, tuple[tuple[str, bool], Any]] = {}

    def draw(self, nodes: dict[str, Node], base: float) -> int:
        """Show ``nodes`` (sub-path -> node); point sizes are multiples of ``base``. A node of
        the same sub-path and kind as one drawn before takes the new values in its existing
        handle; the others are created, and the drawn ones not in ``nodes`` removed. Returns
        how many nodes were created (0: every node updated in place)."""
        kinds = {sub: k for sub, node in nodes.items() if (k := _kind(node)) is not None}
        if self._frame is None:
            self._frame = self.scene.add_frame(self.root, show_axes=False, visible=self._visible)
        for sub, (kind, handle) in list(self._handles.items()):
            if kinds.get(sub) != kind:  # gone, or another kind: its handle cannot take it
                handle.remove()
                del self._handles[sub]
        created = 0
        for sub, kind in kinds.items():
            node, path = nodes[sub], f"{self.root}/{sub}"
            old = self._handles[sub][1] if sub in self._handles else None
            created += old is None
            if isinstance(node, Points):
                handle = self._points(path, node, base, old)
            elif isinstance(node, Segments):
                handle = self._segments(path, node, base, old)
            else:
                handle = self._label(path, node, old)
            self._handles[sub] = (kind, handle)
        return created

    def _points(self, path: str, node: Points, base: float, old: Any) -> Any:
        points, colors = decimate_cloud(node.points, node.colors, CLOUD_POINTS)
        if old is None:
            return self.scene.add_point_cloud(
                path, points, colors, point_size=base * node.size, precision="float32",
                point_shape="circle", point_shading="flat",
            )  # fmt: skip
        old.points, old.colors, old.point_size = points, colors, base * node.size
        return old

    def _segments(self, path: str, node: Segments, base: float, old: Any) -> Any:
        per_segment = isinstance(node.color, np.ndarray) and node.color.ndim == 2
        segs, seg_colors = simplify_segments(
            node.points, node.color if per_segment else None, LINE_TOL_FRAC * base
        )
        if seg_colors is not None:  # per segment: one colour for both ends
            color = np.repeat(seg_colors[:, None, :], 2, axis=1)
        else:
            color = np.asarray(node.color, np.uint8)
        if old is None:
            return self.scene.add_line_segments(
                path, segs, color, thickness=node.width, thickness_units="screen"
            )
        old.points, old.colors, old.thickness = segs, color, float(node.width)
        return old

    def _label(self, path: str, node: Label, old: Any) -> Any:
        position = tuple(float(v) for v in node.position)
        if old is None:
            return self.scene.add_label(
                path, node.text, position=position, font_screen_scale=0.7, anchor="bottom-left"
            )
        old.text, old.position = node.text, position
        return old

    def set_visible(self, visible: bool) -> None:
        """Show or hide the whole layer (its nodes stay as they are)."""
        self._visible = visible
        if self._frame is not None:
            self._frame.visible = visible

    def remove(self) -> None:
        """Take the layer out of the scene."""
        self.scene.remove_by_name(self.root)
        self._frame = None
        self._handles.clear()
