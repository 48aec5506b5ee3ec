"""The views' registries: the 3D layers (points, segments, labels in the left camera frame,
calibration units; ``@layer_view``) and the 2D overlays drawn over the stereo images
(``@overlay_view``). Each is the one place its kind of view is registered; the page builds
its layer list and its overlay toggles from them."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

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
    color: tuple[int, int, int] | np.ndarray
    """One RGB colour, or (M, 3) uint8: one per segment (many colours in one scene node)."""
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


# --- 2D overlays ---------------------------------------------------------------------------

OverlayKind = Literal["pixels", "circles", "squares", "polyline", "segments"]
"""How the page draws an overlay's payload (per side):

- ``pixels``: a flat ``[x0, y0, x1, y1, ...]`` list of integer pixels, one dot each;
- ``circles``: ``[[x, y], ...]``, a small ring each;
- ``squares``: ``[[x, y, flag], ...]``, a small square each, ``color`` if flag else ``color2``;
- ``polyline``: ``{"points": [[x, y], ...]}``, a line through them; optional ``"colors"``
  (one CSS colour per point, for the segment that starts there) and any statistics
  (``mean_px``, ``max_px``, ``coverage``) the page shows beside the image;
- ``segments``: ``{"segments": [[x0, y0, x1, y1], ...]}``, separate line segments; optional
  ``"colors"`` (one CSS colour per segment) and ``"labels"`` (``[[x, y, text, css], ...]``,
  short texts drawn at those pixels, e.g. the costs of the ordering's continuations).
"""


@dataclass(frozen=True)
class OverlayView:
    """One 2D overlay: ``make(rec, calib) -> {side: payload}`` once every stage in ``needs``
    has run."""

    key: str
    label: str
    kind: OverlayKind
    needs: tuple[str, ...]
    color: str
    """CSS colour."""
    on: bool = True
    """Shown when the page opens."""
    color2: str | None = None
    dash: bool = False
    count: bool = False
    """Show the number of items beside the toggle."""
    reveal: str | None = None
    """Shown whatever its toggle while the stepper shows exactly this stage."""
    make: Callable[[Reconstruction, StereoCalibration], dict[str, Any]] = field(
        default=lambda rec, calib: {}, repr=False, compare=False
    )

    def spec(self) -> dict[str, Any]:
        """What the page needs to build the toggle and draw the payload."""
        return {
            "key": self.key,
            "label": self.label,
            "kind": self.kind,
            "color": self.color,
            "color2": self.color2,
            "on": self.on,
            "dash": self.dash,
            "count": self.count,
            "reveal": self.reveal,
        }


OVERLAY_VIEWS: dict[str, OverlayView] = {}
"""The 2D overlays in drawing order (later ones on top)."""


def overlay_view(
    key: str, label: str, kind: OverlayKind, needs: tuple[str, ...], color: str, **options: Any
) -> Callable[[Callable[..., dict[str, Any]]], Callable[..., dict[str, Any]]]:
    """Register ``make(rec, calib) -> {side: payload}`` as the 2D overlay ``key``."""

    def register(make: Callable[..., dict[str, Any]]) -> Callable[..., dict[str, Any]]:
        unknown = set(needs) - set(STAGES)
        if unknown:
            raise ValueError(f"overlay {key!r} needs unknown stages {sorted(unknown)}")
        OVERLAY_VIEWS[key] = OverlayView(key, label, kind, needs, color, make=make, **options)
        return make

    return register
