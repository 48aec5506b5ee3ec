"""Recordings: the 3D view of one frame or of a whole sequence saved as one self-contained HTML
file (viser's scene serializer and static viewer) that opens in a browser with no server.

The scene follows the debugger's 3D view: left camera frame, calibration units, up = -y
(OpenCV); the viewer's camera starts above and behind the stereo cameras. Each frame's curves
replace the previous frame's; a sequence plays at ``fps`` with viser's playback bar.
"""

from __future__ import annotations

import contextlib
import io
import socket
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CURVE_RGB = {
    "tracked": (255, 60, 160),  # the tracked curve
    "single": (60, 160, 255),  # the single-frame curve beside it
    "truth": (60, 200, 90),  # ground truth, when known
}
LINE_PX = 3.0  # curve width on screen, px


@dataclass(frozen=True)
class RecordedFrame:
    """Curves of one frame, name -> (N, 3) points (left camera frame, calibration units)."""

    curves: dict[str, np.ndarray] = field(default_factory=dict)
    title: str = ""


def save_recording(
    frames: Iterable[RecordedFrame],
    path: str | Path,
    fps: float = 15.0,
    baseline: float | None = None,
) -> int:
    """Write the frames as a self-contained HTML recording; returns the number of frames.

    ``baseline`` (calibration units) draws the two cameras, as in the debugger.
    """
    html, n = recording_html(frames, fps, baseline)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(html, encoding="utf-8")
    return n


def recording_html(
    frames: Iterable[RecordedFrame], fps: float = 15.0, baseline: float | None = None
) -> tuple[str, int]:
    """The frames as one self-contained HTML page (see :func:`save_recording`), and their
    number; ValueError for no frames or a curve that is not (N >= 2, 3)."""
    import viser

    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    with contextlib.redirect_stdout(io.StringIO()):  # viser's address banner: no one connects
        server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        server.scene.set_up_direction("-y")
        serializer = server.get_scene_serializer()
        n = 0
        drawn: set[str] = set()
        for frame in frames:
            for name, pts in frame.curves.items():
                shape = np.shape(pts)
                if len(shape) != 2 or shape[1] != 3 or shape[0] < 2:
                    raise ValueError(f"curve {name!r} must be (N >= 2, 3) points, got {shape}")
            pts_all = [np.asarray(p, float) for p in frame.curves.values() if p is not None]
            if n == 0:
                _place_camera(server, pts_all, baseline)
            for name in drawn - set(frame.curves):
                server.scene.remove_by_name(f"/curves/{name}")
            drawn = set()
            for name, pts in frame.curves.items():
                if pts is None:
                    continue
                pts = np.asarray(pts, dtype=np.float32)
                segments = np.stack([pts[:-1], pts[1:]], axis=1)
                server.scene.add_line_segments(
                    f"/curves/{name}",
                    segments,
                    colors=CURVE_RGB.get(name, (230, 230, 230)),
                    thickness=LINE_PX,
                    thickness_units="screen",
                )
                drawn.add(name)
            serializer.insert_sleep(1.0 / fps)
            n += 1
        if n == 0:
            raise ValueError("nothing to record: no frames")
        html = serializer.as_html()
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
    return html, n


def _place_camera(server, pts_all: list[np.ndarray], baseline: float | None) -> None:
    pts = np.vstack(pts_all) if pts_all else np.array([[0.0, 0.0, 100.0]])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    target = np.median(pts, axis=0)
    extent = float(np.ptp(pts, axis=0).max()) or 1.0
    cam = server.initial_camera
    cam.up = (0.0, -1.0, 0.0)
    cam.position = tuple(float(v) for v in target + np.array([0.0, -0.6, -1.25]) * extent)
    cam.look_at = tuple(float(v) for v in target)
    if baseline is not None:
        depth = float(target[2])
        for side, x, rgb in (("left", 0.0, (40, 120, 255)), ("right", baseline, (255, 120, 40))):
            server.scene.add_camera_frustum(
                f"/cameras/{side}", 0.8, 4 / 3, scale=0.06 * depth, color=rgb, position=(x, 0, 0)
            )


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
