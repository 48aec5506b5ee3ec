"""The 3D view of one browser tab: a viser client's scene and control panel.

Scene (OpenCV camera frame of the left rectified camera, calibration units, y down): the two
cameras as frustums, then one layer per stage under a path that names it: ``/stereo``,
``/reliability``, ``/clusters``, ``/ordering``, ``/bounds``, ``/spline``. A layer is redrawn only
when one of the stage results it is drawn from changed (the pipeline cache hands back the same
result object otherwise), so a spline slider sends only the spline; a redrawn layer with the
same nodes updates them in place, thinned for display (``app.scene_nodes``, ``app.display``).

Control panel: run buttons, layer switches, one control per core parameter grouped by stage
(``app.controls``), and the pixel inspector. Controls only submit a request to the session;
the session's worker computes and calls back :meth:`SceneView.show`.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import viser

from threadrecon.app.controls import Control, controls
from threadrecon.app.library import LoadedFrame, merge_params
from threadrecon.app.scene_nodes import LayerNodes
from threadrecon.app.session import Session
from threadrecon.app.views import (
    LAYER_STAGE,
    LAYERS,
    layer,
    nearest_to_ray,
    pixel_info,
)
from threadrecon.core.pipeline import STAGES, ReconParams, Reconstruction

POINT_SIZE_FRAC = 0.0025  # base point size as a fraction of the median thread depth
STREAM_PAUSE_S = 0.35  # pause between stages of a streamed run, so each layer can be seen
STATUS_EVERY_S = 0.3  # the status line's pace while a run goes on (a panel re-render each)


class SceneView:
    def __init__(self, client: viser.ClientHandle, session: Session) -> None:
        self.client = client
        self.session = session
        self.scene = client.scene
        self.gui = client.gui
        self._drawn: dict[str, tuple] = {}  # layer -> ids of the results it was drawn from
        self._visible: dict[str, bool] = dict.fromkeys(LAYERS, True)
        self._layers = {name: LayerNodes(self.scene, name, True) for name in LAYERS}
        self._base = 0.1
        self._status_at = 0.0
        self._stereo_id: int | None = None
        self._syncing = threading.local()
        self._inputs: dict[str, tuple[Control, Any]] = {}
        self.scene.set_up_direction("-y")
        self.gui.configure_theme(
            control_layout="fixed", control_width="medium", dark_mode=True, show_logo=False,
            show_share_button=False,
        )  # fmt: skip
        self._build_gui()
        self.scene.on_click()(self._on_click)

    # --- control panel ------------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.gui
        with gui.add_folder("Run"):
            self._status = gui.add_markdown("")
            row = gui.add_button_group("", ("Run", "Next step", "Run all"))
            actions = {"Run": "run", "Next step": "next", "Run all": "all"}
            row.on_click(
                lambda e: self.session.step(actions[e.target.value], pause_s=STREAM_PAUSE_S)
            )
            reset = gui.add_button("Reset parameters")
            reset.on_click(lambda _: self.session.submit(params=ReconParams(), preset="default"))
        with gui.add_folder("Layers", expand_by_default=False):
            for name in LAYERS:
                box = gui.add_checkbox(f"/{name}", True)
                box.on_update(lambda e, n=name: self._toggle(n, e.target.value))
        by_stage: dict[str, list[Control]] = {}
        for c in controls():
            by_stage.setdefault(c.stage, []).append(c)
        for stage in STAGES:
            if stage not in by_stage:
                continue
            with gui.add_folder(f"{STAGES.index(stage) + 1}. {stage}", expand_by_default=False):
                for c in by_stage[stage]:
                    self._inputs[c.key] = (c, self._add_input(c))
        with gui.add_folder("Pixel inspector"):
            self._inspect = gui.add_markdown("Click a point of the cloud (or the left image).")

    def _add_input(self, c: Control) -> Any:
        value = getattr(getattr(self.session.params, c.stage), c.name)
        gui = self.gui
        if c.kind == "slider":
            assert c.min is not None and c.max is not None and c.step is not None
            lo, hi = min(c.min, value), max(c.max, value)
            if c.integer:
                handle = gui.add_slider(c.label, int(lo), int(hi), int(c.step), int(value))
            else:
                handle = gui.add_slider(c.label, float(lo), float(hi), float(c.step), float(value))
        elif c.kind == "checkbox":
            handle = gui.add_checkbox(c.label, bool(value))
        elif c.kind == "dropdown":
            handle = gui.add_dropdown(c.label, c.options, initial_value=value)
        else:
            handle = gui.add_number(c.label, value, min=c.min, max=c.max)
        handle.on_update(lambda e, key=c.key: self._on_input(key, e.target.value))
        return handle

    def _on_input(self, key: str, value: Any) -> None:
        if getattr(self._syncing, "on", False):
            return
        try:
            params = merge_params(self.session.params, {key: value})
        except ValueError as exc:
            self.client.add_notification("Parameter refused", str(exc), auto_close_seconds=6.0)
            return
        self.session.submit(params=params)

    def show_params(self, params: ReconParams) -> None:
        self._syncing.on = True
        try:
            for c, handle in self._inputs.values():
                value = getattr(getattr(params, c.stage), c.name)
                if c.kind == "slider":  # a preset may hold a value beyond the slider's range
                    if value < handle.min:
                        handle.min = value
                    if value > handle.max:
                        handle.max = value
                if handle.value != value:
                    handle.value = value
        finally:
            self._syncing.on = False

    # --- scene --------------------------------------------------------------------------------

    def show_frame(self, loaded: LoadedFrame | None) -> None:
        """New frame: cameras, view point, and every layer cleared."""
        for name in list(self._drawn):
            self._layers[name].remove()
        self._drawn.clear()
        self._stereo_id = None
        if loaded is None:
            return
        calib = loaded.calib
        h, w = calib.image_size
        f = calib.focal
        fov = 2.0 * math.atan(h / (2.0 * f))
        gt = loaded.ground_truth
        depth = float(np.median(gt[:, 2])) if gt is not None else 20.0 * calib.baseline
        self._base = max(POINT_SIZE_FRAC * depth, 1e-6)
        left = loaded.pair.left
        thumb = left[:: max(1, h // 120), :: max(1, w // 160)]
        for side, position, color in (
            ("left", (0.0, 0.0, 0.0), (40, 120, 255)),
            ("right", (calib.baseline, 0.0, 0.0), (255, 120, 40)),
        ):
            self.scene.add_camera_frustum(
                f"/cameras/{side}", fov, w / h, scale=0.06 * depth, color=color,
                image=thumb if side == "left" else None, position=position,
                thickness=1.5, thickness_units="screen",
            )  # fmt: skip
        if gt is not None:
            self._look(np.median(gt, axis=0), float(np.ptp(gt, axis=0).max()))
        else:
            self._look(np.array([0.0, 0.0, depth]), 0.5 * depth)

    def _look(self, target: np.ndarray, extent: float) -> None:
        """Put the viewer camera above and behind the stereo cameras, looking at the thread."""
        cam = self.client.camera
        cam.up_direction = (0.0, -1.0, 0.0)
        cam.position = tuple(float(v) for v in target + np.array([0.0, -0.6, -1.25]) * extent)
        cam.look_at = tuple(float(v) for v in target)

    def show(self, rec: Reconstruction | None, loaded: LoadedFrame | None) -> None:
        """Draw every layer whose stage is in ``rec`` and changed; remove the others. One
        batch of scene updates, sent at once: the viewer applies and renders it as one."""
        with self.client.atomic():
            self._show(rec, loaded)
        self.client.flush()  # no windowing delay: the batch is complete

    def _show(self, rec: Reconstruction | None, loaded: LoadedFrame | None) -> None:
        for name, deps in LAYERS.items():
            if rec is None or loaded is None or LAYER_STAGE[name] not in rec.runs:
                if name in self._drawn:
                    self._layers[name].remove()
                    del self._drawn[name]
                continue
            key = tuple(id(rec.runs[d].result) if d in rec.runs else None for d in deps)
            if self._drawn.get(name) == key:
                continue
            if name == "stereo" and self._stereo_id != key[0]:
                self._stereo_id = key[0]
                self._recentre(rec)
            nodes = layer(name, rec, loaded.calib, loaded.ground_truth)
            self._layers[name].draw(nodes, self._base)  # in place when the same nodes
            self._drawn[name] = key
        # the status line once a request's last stage is in (each update re-renders the
        # viewer's panel), or at a watchable pace while a long or streamed run goes on
        now = time.monotonic()
        final = self.session.running is None or rec is None or rec.failed_stage is not None
        if final or now - self._status_at >= STATUS_EVERY_S:
            text = _status_line(self.session, rec)
            if text != self._status.content:
                self._status.content = text
                self._status_at = now

    def _recentre(self, rec: Reconstruction) -> None:
        pts = rec["stereo"].points
        z = pts[:, 2][np.isfinite(pts[:, 2])]
        if z.size:
            self._base = max(POINT_SIZE_FRAC * float(np.median(z)), 1e-6)
            if self.session.loaded is not None and self.session.loaded.ground_truth is None:
                ok = np.isfinite(pts).all(axis=1)
                self._look(np.median(pts[ok], axis=0), float(np.ptp(pts[ok], axis=0).max()))

    def _toggle(self, name: str, visible: bool) -> None:
        with self.session.draw_lock:  # the worker may be replacing the layer
            self._visible[name] = visible
            self._layers[name].set_visible(visible)

    # --- pixel inspector ----------------------------------------------------------------------

    def _on_click(self, event: viser.SceneClickEvent) -> None:
        s = self.session
        rec = s.rec
        if rec is None or "stereo" not in rec.runs or not self._visible["stereo"]:
            return
        st = rec["stereo"]
        i = nearest_to_ray(st.points, event.ray_origin, event.ray_direction, 3.0 * self._base)
        if i is None:
            return
        x, y = (int(v) for v in st.pixels[i])
        s.set_inspect(pixel_info(rec, x, y, snap_px=0))

    def show_inspect(self, info: dict[str, Any] | None) -> None:
        root = "/inspect"
        if info is None or not info.get("segmented"):
            self.scene.remove_by_name(root)
            self._inspect.content = "Click a point of the cloud (or the left image)."
            return
        self.scene.add_point_cloud(
            root, np.asarray([info["point"]], np.float32), np.array((255, 255, 255), np.uint8),
            point_size=self._base * 8.0, precision="float32", point_shape="diamond",
        )  # fmt: skip
        rel = info.get("R")
        self._inspect.content = (
            f"**pixel** ({info['x']}, {info['y']})  \n"
            f"d_min {info['d_min']}, d_next {info['d_next']}  \n"
            f"E_min {info['E_min']:.4g}, E_next {info['E_next']:.4g}  \n"
            + (f"R {rel:.3f} ({'reliable' if info.get('reliable') else 'not reliable'})  \n" if rel is not None else "")
            + (f"depth {info['depth']:.4g}" if info.get("depth") is not None else "depth: none")
        )  # fmt: skip


def _status_line(session: Session, rec: Reconstruction | None) -> str:
    if session.load_error:
        return f"**failed**: {session.load_error}"
    if rec is None:
        return "running..."
    done = [s for s in STAGES if s in rec.runs]
    total = sum(r.ms for r in rec.runs.values())
    line = f"{session.frame_id}: {len(done)}/{len(STAGES)} stages, {total:.0f} ms"
    if rec.message:
        line += f"  \n**{rec.status}**: {rec.message}"
    return line
