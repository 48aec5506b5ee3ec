"""The 3D layers' registry: what a layer draws (points, segments, labels in the left camera
frame, calibration units) and the one place a layer is registered (``@layer_view``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.pipeline import STAGES, Reconstruction


@dataclass(frozen=True)
class Points:
    points: np.ndarray
    """(N, 3) float32, left camera frame."""
    colors: np.ndarray
    """(N, 3) uint8 or (3,) uint8."""
    size: float
    """Point size as a multiple of the scene's base point size."""


@dataclass(frozen=True)
class Segments:
    points: np.ndarray
    """(M, 2, 3) float32 line segments."""
    color: tuple[int, int, int]
    width: float
    """Screen-space width, px."""


@dataclass(frozen=True)
class Label:
    text: str
    position: np.ndarray


Layer = dict[str, Points | Segments | Label]
"""Node name (relative to the layer root) -> what to draw there."""

GREY = (150, 150, 150)


def palette(n: int) -> np.ndarray:
    """n distinct colours (golden-ratio hues), (n, 3) uint8."""
    h = (np.arange(n) * 0.618033988749895) % 1.0
    k = (np.array([5.0, 3.0, 1.0])[None, :] + h[:, None] * 6.0) % 6.0
    rgb = 1.0 - 0.75 * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)  # HSV with s=0.75, v=1
    return (rgb * 255).astype(np.uint8)


def polyline(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float32)
    return np.stack([p[:-1], p[1:]], axis=1) if len(p) > 1 else np.zeros((0, 2, 3), np.float32)


@dataclass(frozen=True)
class LayerView:
    """One 3D layer of the scene: drawn from the results of ``needs``, first shown once the
    stage ``shows_at`` has run."""

    name: str
    needs: tuple[str, ...]
    shows_at: str
    draw: Callable[[Reconstruction, StereoCalibration, np.ndarray | None], Layer]


LAYER_VIEWS: dict[str, LayerView] = {}
"""The scene's layers in stage order: the one place a stage's 3D view is registered."""


def layer_view(
    name: str, needs: tuple[str, ...], shows_at: str | None = None
) -> Callable[[Callable[..., Layer]], Callable[..., Layer]]:
    """Register ``draw(rec, calib, ground_truth) -> Layer`` as the layer ``name``."""

    def register(draw: Callable[..., Layer]) -> Callable[..., Layer]:
        unknown = set(needs) - set(STAGES)
        if unknown:
            raise ValueError(f"layer {name!r} needs unknown stages {sorted(unknown)}")
        LAYER_VIEWS[name] = LayerView(name, needs, shows_at or needs[0], draw)
        return draw

    return register


def layer(
    name: str, rec: Reconstruction, calib: StereoCalibration, ground_truth: np.ndarray | None
) -> Layer:
    """The nodes of one layer from the stage results available in ``rec``."""
    view = LAYER_VIEWS.get(name)
    if view is None:
        raise KeyError(f"unknown layer {name!r} (layers: {', '.join(LAYER_VIEWS)})")
    return view.draw(rec, calib, ground_truth)
