"""The views of the user's mask corrections: the thread masks P the run used (both views) and
the pixels the corrections added and removed, as 2D overlays over the stereo images."""

from __future__ import annotations

from typing import Any

import numpy as np

from threadrecon.app.views.registry import overlay_view
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.corrections import CorrectedPair
from threadrecon.core.pipeline import Reconstruction


def _pixels(mask: np.ndarray) -> list[int]:
    """A mask as the ``pixels`` payload: flat [x0, y0, x1, y1, ...]."""
    ys, xs = np.nonzero(mask)
    return np.stack([xs, ys], axis=1).ravel().tolist()


@overlay_view("mask", "thread mask P", "pixels", ("segment",), "rgba(90,160,255,0.55)", on=False)
def _mask_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    seg = rec["segment"]
    return {"left": _pixels(seg.P_L), "right": _pixels(seg.P_R)}


@overlay_view("added", "added by you", "pixels", ("segment",), "rgba(60,230,110,0.9)", count=True)
def _added_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    seg = rec["segment"]
    if not isinstance(seg, CorrectedPair):
        return {"left": [], "right": []}
    return {"left": _pixels(seg.added_L), "right": _pixels(seg.added_R)}


@overlay_view(
    "removed", "removed by you", "pixels", ("segment",), "rgba(255,70,70,0.9)", count=True
)
def _removed_overlay(rec: Reconstruction, calib: StereoCalibration) -> dict[str, Any]:
    seg = rec["segment"]
    if not isinstance(seg, CorrectedPair):
        return {"left": [], "right": []}
    return {"left": _pixels(seg.removed_L), "right": _pixels(seg.removed_R)}
