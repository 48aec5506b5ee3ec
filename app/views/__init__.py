"""What the debugger shows, as plain data: stage results as JSON, the 2D overlays of the
stereo images, the pixel inspector, and the 3D layers (numpy arrays in the left camera frame,
calibration units) that ``app.scene`` hands to viser.

Nothing here talks to viser or FastAPI, so every view is testable on its own. A new stage's
views are a module of this package, listed in ``_VIEW_MODULES``: a ``@layer_view`` function
for its 3D layer and an ``@overlay_view`` function for its 2D overlay. The page builds its
layer list and its overlay toggles from these registries (``/api/info``).
"""

from __future__ import annotations

from threadrecon.app.views import check, corrections, ordering_graph, stages
from threadrecon.app.views.data import (
    HEAVY_VALUES,
    SPLINE_SAMPLES,
    OverlayCache,
    nearest_to_ray,
    overlay,
    pixel_info,
    stage_json,
)
from threadrecon.app.views.registry import (
    GREY,
    LAYER_VIEWS,
    OVERLAY_VIEWS,
    Label,
    Layer,
    LayerView,
    OverlayView,
    Points,
    Segments,
    layer,
    layer_view,
    overlay_view,
    palette,
    polyline,
)
from threadrecon.core.pipeline import STAGES

_VIEW_MODULES = (stages, ordering_graph, check, corrections)
"""The modules whose ``@layer_view`` and ``@overlay_view`` functions make the scene's 3D layers
and the 2D overlays, in stage order."""

# The scene's layers in stage order (of the stage that first shows each), whatever the order
# in which their modules were imported.
_ordered = sorted(LAYER_VIEWS.values(), key=lambda v: STAGES.index(v.shows_at))
LAYER_VIEWS.clear()
LAYER_VIEWS.update((v.name, v) for v in _ordered)

# Derived views of the registry, for the scene and the API.
LAYERS: dict[str, tuple[str, ...]] = {v.name: v.needs for v in LAYER_VIEWS.values()}
LAYER_STAGE: dict[str, str] = {v.name: v.shows_at for v in LAYER_VIEWS.values()}

__all__ = [
    "GREY",
    "HEAVY_VALUES",
    "LAYERS",
    "LAYER_STAGE",
    "LAYER_VIEWS",
    "OVERLAY_VIEWS",
    "OverlayCache",
    "SPLINE_SAMPLES",
    "Label",
    "Layer",
    "LayerView",
    "OverlayView",
    "Points",
    "Segments",
    "layer",
    "layer_view",
    "nearest_to_ray",
    "overlay",
    "overlay_view",
    "palette",
    "pixel_info",
    "polyline",
    "stage_json",
]
