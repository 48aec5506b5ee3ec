"""Synthetic stereo *sequences*: a thread that moves over time, rendered frame by frame with the
single-frame generator of :mod:`core.synthetic`, ground truth per frame.

Motions (``MotionParams.kind``):

* ``"drag"``: the whole thread slides and turns (rigid motion) along a smooth random path.
* ``"pull"``: one end is pulled away along its tangent while the rest follows less and less
  (weight ``(i / (n - 1)) ** 2`` on control point i), on top of a slow drag.
* ``"instrument"``: a slow drag while an instrument shaft sweeps across the image in front of
  the thread, hiding a moving piece of it (masks exclude the hidden pixels).

Conventions are those of :mod:`core.synthetic`: left camera frame, OpenCV axes, mm; images RGB.
Frame t (from 0) is rendered with ``default_rng([seed, 1, t])``; the shape is drawn with
``default_rng([seed, 0])``, so a frame does not depend on the sequence length.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Final, Literal

import numpy as np

from threadrecon.core.synthetic import (
    StereoCamera,
    SyntheticFrame,
    SyntheticParams,
    _make_truth,  # the generator's ground truth of given control points
    _render_pair,  # the generator's renderer of given control points
    generate_frame,
)

Motion = Literal["drag", "pull", "instrument"]
MOTIONS: Final = ("drag", "pull", "instrument")
_FIT_TRIES: Final = 12  # halvings of the motion amplitude before the thread is left still
_ROOM_PX: Final = 60.0  # extra margin of the first frame, px, so that the thread can move
_SHAFT_DEPTH: Final = 0.75  # the shaft floats at this fraction of the depth of the thread point


@dataclass(frozen=True)
class MotionParams:
    """How the thread moves over a sequence."""

    kind: Motion = "drag"
    n_frames: int = 60
    speed_mm: float = 0.6  # mean speed of the thread's centroid, mm per frame
    turn_deg: float = 0.4  # peak rotation rate about the optical axis, degrees per frame
    pull_mm: float = 25.0  # how far the pulled end travels over the sequence, mm ("pull")
    shaft_px: float = 18.0  # half-width of the instrument shaft, px ("instrument")

    def __post_init__(self) -> None:
        if self.kind not in MOTIONS:
            raise ValueError(f"motion.kind must be one of {MOTIONS}, got {self.kind!r}")
        if int(self.n_frames) != self.n_frames or self.n_frames < 1:
            raise ValueError(f"motion.n_frames must be an integer >= 1, got {self.n_frames}")
        for name in ("speed_mm", "turn_deg", "pull_mm", "shaft_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"motion.{name} must be >= 0, got {v}")


@dataclass(frozen=True)
class SequenceParams:
    """A sequence: the single-frame settings (shape, camera, look) and the motion."""

    frame: SyntheticParams = field(default_factory=SyntheticParams)
    motion: MotionParams = field(default_factory=MotionParams)


def thread_motion(
    ctrl0: np.ndarray, cam: StereoCamera, motion: MotionParams, margin_px: float, rng
) -> np.ndarray:
    """(T, n, 3) control points of every frame, mm, starting at ``ctrl0`` (n, 3).

    The random path is shrunk (amplitude halved) until every frame keeps ``margin_px`` to the
    image borders in both views; if it never does, the thread stays still.
    """
    ctrl0 = np.asarray(ctrl0, dtype=np.float64)
    if ctrl0.ndim != 2 or ctrl0.shape[1] != 3:
        raise ValueError(f"ctrl0 must be (n, 3), got {ctrl0.shape}")
    rng = np.random.default_rng(rng)
    T = int(motion.n_frames)
    t = np.arange(T, dtype=float)
    # Smooth random path: per axis two sines of random phase; speed normalised to speed_mm.
    freq = rng.uniform(0.5, 1.5, (2, 3)) * 2 * math.pi / max(T, 8)
    phase = rng.uniform(0, 2 * math.pi, (2, 3))
    amp = np.array([1.0, 1.0, 0.3])  # mostly in the image plane
    path = (amp * (np.sin(freq[0] * t[:, None] + phase[0]) - np.sin(phase[0]))).copy()
    path += 0.5 * amp * (np.sin(freq[1] * t[:, None] + phase[1]) - np.sin(phase[1]))
    step = np.linalg.norm(np.diff(path, axis=0), axis=1).mean() if T > 1 else 1.0
    path *= motion.speed_mm / max(step, 1e-9)
    turn = math.radians(motion.turn_deg) * np.sin(rng.uniform(0.5, 1.5) * t / max(T, 8) * 2)
    angle = np.cumsum(turn)
    n = len(ctrl0)
    pull_dir = ctrl0[-1] - ctrl0[-2]
    pull_dir /= max(np.linalg.norm(pull_dir), 1e-9)
    pull_w = (np.arange(n) / max(n - 1, 1)) ** 2
    if motion.kind == "pull":
        path *= 0.3  # the pull dominates
    centre = ctrl0.mean(axis=0)
    for _ in range(_FIT_TRIES):
        frames = np.empty((T, n, 3))
        for k in range(T):
            c, s = math.cos(angle[k]), math.sin(angle[k])
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            pts = (ctrl0 - centre) @ rot.T + centre + path[k]
            if motion.kind == "pull":
                pts = pts + pull_w[:, None] * pull_dir * motion.pull_mm * k / max(T - 1, 1)
            frames[k] = pts
        if _in_view(frames, cam, margin_px):
            return frames
        path, angle = 0.5 * path, 0.5 * angle
        pull_dir = 0.5 * pull_dir
    return np.repeat(ctrl0[None], T, axis=0)


def generate_sequence(
    params: SequenceParams | None = None, seed: int = 0
) -> Iterator[SyntheticFrame]:
    """Yield the frames of a moving thread one at a time (nothing holds the whole sequence).

    Each frame is a :class:`core.synthetic.SyntheticFrame` with that frame's ground truth.
    Raises ``ValueError`` naming the setting when the first thread cannot be placed.
    """
    p = params if params is not None else SequenceParams()
    fp, motion = p.frame, p.motion
    if fp.render.occlusion:
        raise ValueError(
            "render.occlusion draws a still random instrument per frame; use motion kind "
            "'instrument' for one that moves across the sequence"
        )
    cam = fp.camera
    # Room to move: the first frame keeps a wider margin (the given one if that cannot be met).
    roomy = replace(fp, thread=replace(fp.thread, margin_px=fp.thread.margin_px + _ROOM_PX))
    try:
        first = generate_frame(roomy, np.random.default_rng([seed, 0]))
    except ValueError:
        first = generate_frame(fp, np.random.default_rng([seed, 0]))
    ctrls = thread_motion(first.truth.control_points, cam, motion, fp.thread.margin_px, [seed, 2])
    shaft = _shaft_path(ctrls, cam, motion, np.random.default_rng([seed, 3]))
    for k, ctrl in enumerate(ctrls):
        rng = np.random.default_rng([seed, 1, k])
        left, right, mask_left, mask_right = _render_pair(
            ctrl, cam, fp.thread.diameter_mm, replace(fp.render, occlusion=False), rng
        )
        if shaft is not None:
            (a, b), z_shaft = shaft[k]
            d = float(cam.disparity(z_shaft))
            for view, (img, mask) in enumerate(((left, mask_left), (right, mask_right))):
                off = np.array([d if view else 0.0, 0.0])
                cov, colour = _shaft(cam, a - off, b - off, motion.shaft_px)
                blend = cov[..., None] * colour + (1 - cov[..., None]) * img.astype(np.float32)
                img[...] = np.clip(np.rint(blend), 0, 255).astype(np.uint8)
                mask &= cov < 0.5
        yield SyntheticFrame(left, right, mask_left, mask_right, _make_truth(ctrl), cam)


# ----------------------------------------------------------------------------------------------


def _in_view(frames: np.ndarray, cam: StereoCamera, margin: float) -> bool:
    pts = frames.reshape(-1, 3)
    if np.any(pts[:, 2] <= 1.0):
        return False
    for uv in cam.project(pts):
        if (
            uv[:, 0].min() < margin
            or uv[:, 1].min() < margin
            or uv[:, 0].max() > cam.width - 1 - margin
            or uv[:, 1].max() > cam.height - 1 - margin
        ):
            return False
    return True


def _shaft_path(
    ctrls: np.ndarray, cam: StereoCamera, motion: MotionParams, rng: np.random.Generator
) -> list[tuple[tuple[np.ndarray, np.ndarray], float]] | None:
    """Per frame the shaft's tip segment (far end, tip) in left px and its depth, mm: the tip
    sweeps along a straight line across the thread's middle over the sequence."""
    if motion.kind != "instrument":
        return None
    T = len(ctrls)
    mid = ctrls[:, len(ctrls[0]) // 2]
    uv_mid = cam.project(mid)[0]
    angle = rng.uniform(0, 2 * math.pi)
    axis = np.array([math.cos(angle), math.sin(angle)])  # shaft direction, towards its tip
    normal = np.array([-axis[1], axis[0]])
    sweep = rng.uniform(60.0, 120.0)  # px the shaft travels across, either side of the middle
    out = []
    for k in range(T):
        f = -1.0 + 2.0 * k / max(T - 1, 1)
        tip = uv_mid[k] + normal * sweep * f + axis * motion.shaft_px
        far = tip - axis * 4 * (cam.width + cam.height)
        out.append(((far, tip), _SHAFT_DEPTH * float(mid[k, 2])))
    return out


def _shaft(
    cam: StereoCamera, a: np.ndarray, b: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Anti-aliased coverage (H, W) and grey metallic colour (H, W, 3) of a capsule a-b, px."""
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
    ab = b - a
    t = np.clip(((xs - a[0]) * ab[0] + (ys - a[1]) * ab[1]) / float(ab @ ab), 0.0, 1.0)
    dx, dy = xs - (a[0] + t * ab[0]), ys - (a[1] + t * ab[1])
    dist = np.sqrt(dx * dx + dy * dy)
    cov = np.clip(radius - dist + 0.5, 0.0, 1.0)
    v = np.clip(dist / max(radius, 1e-6), 0.0, 1.0)  # 0 on the shaft axis, 1 at its edge
    shade = 0.45 + 0.45 * np.sqrt(1.0 - v * v)
    colour = shade[..., None] * np.array([185.0, 190.0, 196.0], np.float32)
    return cov.astype(np.float32), colour.astype(np.float32)
