"""The frames of a data folder, decoded on demand, and parameter patches.

Shared by every debugger session (:mod:`app.session`): a frame is decoded once and kept in a
small LRU cache, whatever the number of tabs looking at it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app.dataset import Frame, discover, load_frame
from threadrecon.app.errors import Invalid, NotFound
from threadrecon.app.presets import validate
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.corrections import Correction
from threadrecon.core.pipeline import STAGES, ReconParams
from threadrecon.core.segmentation import StereoPair

LOADED_FRAMES = 16  # decoded frames kept by the library (bounded memory, whatever the tabs)


@dataclass(frozen=True)
class LoadedFrame:
    frame: Frame
    pair: StereoPair
    calib: StereoCalibration
    ground_truth: np.ndarray | None


class FrameLibrary:
    """The frames of a data folder, decoded on demand and kept in a small LRU cache."""

    def __init__(
        self,
        root: str | Path,
        corrections: Callable[[str], tuple[Correction, ...]] | None = None,
    ) -> None:
        self.root = Path(root)
        self.frames: dict[str, Frame] = {f.id: f for f in discover(self.root)}
        self._cache: OrderedDict[str, LoadedFrame] = OrderedDict()
        self._lock = threading.Lock()
        self._corrections = corrections

    def corrections(self, frame_id: str) -> tuple[Correction, ...]:
        """The user's mask corrections of the frame, in order (every run applies them)."""
        return () if self._corrections is None else self._corrections(frame_id)

    def get(self, frame_id: str) -> Frame:
        """The frame ``frame_id``; :class:`NotFound` (a KeyError too) for an unknown id."""
        try:
            return self.frames[frame_id]
        except KeyError:
            raise NotFound(f"unknown frame {frame_id!r}") from None

    def load(self, frame_id: str) -> LoadedFrame:
        """Raises NotFound for an unknown id, ValueError/OSError for an unreadable frame."""
        frame = self.get(frame_id)
        with self._lock:
            hit = self._cache.get(frame_id)
            if hit is not None:
                self._cache.move_to_end(frame_id)
                return hit
        pair, calib, gt = load_frame(frame)
        loaded = LoadedFrame(frame, pair, calib, gt)
        with self._lock:
            self._cache[frame_id] = loaded
            while len(self._cache) > LOADED_FRAMES:
                self._cache.popitem(last=False)
        return loaded


def merge_params(params: ReconParams, patch: dict[str, Any]) -> ReconParams:
    """``params`` with the values of ``{stage: {name: value}}`` (or ``{"stage.name": value}``)
    applied; raises :class:`Invalid` naming the parameter when a value is refused."""
    if not isinstance(patch, dict):
        raise Invalid("parameters must be an object {stage: {name: value}}")
    data = params.to_dict()
    for key, value in patch.items():
        if isinstance(value, dict):
            if key not in data:
                raise Invalid(f"unknown parameter group {key!r} (known: {', '.join(STAGES)})")
            data[key].update(value)
        else:
            stage, _, name = key.partition(".")
            if stage not in data or not name:
                raise Invalid(f"unknown parameter {key}")
            data[stage][name] = value
    try:
        return validate(data)
    except (ValueError, TypeError, OverflowError) as exc:  # 1e400, 10**400: a refused value
        raise Invalid(str(exc) or f"invalid parameters ({type(exc).__name__})") from None
