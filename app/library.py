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
from threadrecon.app.sequence import ImageFolderSequence, Sequence
from threadrecon.app.sequence_library import (
    SequenceEntry,
    find_sequences,
    sequence_folders,
    split_frame_id,
)
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.corrections import Correction
from threadrecon.core.pipeline import STAGES, ReconParams
from threadrecon.core.segmentation import StereoPair

LOADED_FRAMES = 16  # decoded frames kept by the library (bounded memory, whatever the tabs)
OPEN_SEQUENCES = 8  # sequences kept open (an image folder's file list, a bag's index)


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
        self.sequences: dict[str, SequenceEntry] = {e.id: e for e in find_sequences(self.root)}
        try:
            stills = discover(self.root, skip=sequence_folders(list(self.sequences.values())))
        except FileNotFoundError:
            if not self.sequences or not self.root.is_dir():
                raise
            stills = []  # a folder of sequences only
        self.frames: dict[str, Frame] = {f.id: f for f in stills}
        """The still frames (a sequence's frames are reached through :meth:`get`)."""
        self._cache: OrderedDict[str, LoadedFrame] = OrderedDict()
        self._opened: OrderedDict[str, Sequence] = OrderedDict()
        self._lock = threading.Lock()
        self._corrections = corrections

    def corrections(self, frame_id: str) -> tuple[Correction, ...]:
        """The user's mask corrections of the frame, in order (every run applies them)."""
        return () if self._corrections is None else self._corrections(frame_id)

    def first_id(self) -> str | None:
        """The first entry's frame: the first still frame, else the first sequence's frame 0."""
        if self.frames:
            return next(iter(self.frames))
        if self.sequences:
            return next(iter(self.sequences.values())).frame_id(0)
        return None

    def get(self, frame_id: str) -> Frame:
        """The frame ``frame_id`` (a still frame, or ``<sequence id>@k``); :class:`NotFound`
        (a KeyError too) for an unknown id."""
        frame = self.frames.get(frame_id)
        if frame is not None:
            return frame
        parts = split_frame_id(frame_id)
        if parts is None or parts[0] not in self.sequences:
            raise NotFound(f"unknown frame {frame_id!r}")
        entry, k = self.sequences[parts[0]], parts[1]
        seq = self.sequence(entry.id)
        if seq.count is not None and k >= seq.count:
            raise NotFound(f"unknown frame {frame_id!r}: {entry.id} has {seq.count} frames")
        files: dict[str, Any] = {}
        if isinstance(seq, ImageFolderSequence):
            if seq.rights:
                files = {"left": seq.lefts[k], "right": seq.rights[k]}
            else:
                mask = seq.lefts[k].with_name(f"{seq.lefts[k].stem}_mask.png")
                files = {"stereo": seq.lefts[k], "mask": mask if mask.is_file() else None}
            gt = seq.lefts[k].with_suffix(".npy")
            files["ground_truth"] = gt if gt.is_file() else None
        kind = "simulated" if files.get("ground_truth") is not None else "real"
        return Frame(frame_id, kind, entry.calibration or entry.path, **files)

    def sequence(self, sequence_id: str) -> Sequence:
        """The opened sequence ``sequence_id`` (kept open: its file list, its frame count);
        NotFound for an unknown id, Invalid for an unreadable source."""
        entry = self.sequences.get(sequence_id)
        if entry is None:
            raise NotFound(f"unknown sequence {sequence_id!r}")
        with self._lock:
            seq = self._opened.get(sequence_id)
            if seq is not None:
                self._opened.move_to_end(sequence_id)
                return seq
        try:
            seq = entry.open()
        except (ValueError, OSError, ImportError) as exc:
            raise Invalid(f"cannot open sequence {sequence_id}: {exc}") from None
        with self._lock:
            self._opened[sequence_id] = seq
            while len(self._opened) > OPEN_SEQUENCES:
                self._opened.popitem(last=False)
        return seq

    def load(self, frame_id: str) -> LoadedFrame:
        """Raises NotFound for an unknown id, ValueError/OSError for an unreadable frame."""
        frame = self.get(frame_id)
        with self._lock:
            hit = self._cache.get(frame_id)
            if hit is not None:
                self._cache.move_to_end(frame_id)
                return hit
        parts = split_frame_id(frame_id) if frame_id not in self.frames else None
        if parts is not None:
            entry = self.sequences[parts[0]]
            seq = self.sequence(entry.id)
            got = seq.frame(parts[1])
            loaded = LoadedFrame(frame, got.pair, entry.calib(seq), got.truth)
        else:
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
