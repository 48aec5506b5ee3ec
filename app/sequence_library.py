"""The sequences of a data folder: each one is ONE entry of the debugger's frame list.

A data folder may hold, beside still pairs (:mod:`app.dataset`):

* **image sequences**: every folder directly under a folder named ``sequences/`` (what
  ``threadrecon generate --sequence`` writes: frames, masks, ground truth, calibration);
* **videos** (``.mp4``, ``.mkv``, ...) anywhere outside such a folder;
* **ROS bags**: ``.bag`` files (ROS1) and folders holding ``metadata.yaml`` (ROS2).

Frame ``k`` (from 0) of the sequence ``ID`` has the frame id ``ID@k``; ``ID`` is the path
relative to the root (a file keeps its suffix). The frames are read lazily with
:mod:`app.sequence`; the calibration is the source's own (a folder's ``calibration.yaml``, a
bag's ``camera_info``), else ``<video stem>.calib.yaml`` beside a video, else the nearest
``calibration.yaml`` in its folder or a folder above it (up to the data folder).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from threadrecon.app.io import load_calibration
from threadrecon.app.sequence import (
    IMAGE_SUFFIXES,
    VIDEO_SUFFIXES,
    Sequence,
    SequenceError,
    open_sequence,
)
from threadrecon.core.calibration import StereoCalibration

SEQUENCES_DIR = "sequences"  # a folder of this name holds one image sequence per sub-folder
FRAME_SEP = "@"  # frame id of a sequence's frame k: "<sequence id>@<k>"
_FRAME_ID = re.compile(r"^(?P<seq>.+)@(?P<k>\d{1,9})$")


@dataclass(frozen=True)
class SequenceEntry:
    """One sequence of the data folder. ``id``: path relative to the root (posix);
    ``kind``: "images", "video" or "bag"; ``calibration``: a YAML file to use when the source
    carries none (None: the source's own or none)."""

    id: str
    path: Path
    kind: str
    calibration: Path | None

    @property
    def name(self) -> str:
        return self.id.rsplit("/", 1)[-1]

    def frame_id(self, k: int) -> str:
        return f"{self.id}{FRAME_SEP}{k}"

    def open(self) -> Sequence:
        """The lazily read sequence; :class:`SequenceError` when the source is unreadable."""
        return open_sequence(self.path)

    def calib(self, seq: Sequence) -> StereoCalibration:
        """The calibration of the frames: the source's own, else the YAML file found for it."""
        if seq.calibration is not None:
            return seq.calibration
        if self.calibration is None:
            raise SequenceError(
                f"{self.path}: no calibration (put calibration.yaml or "
                f"{self.path.stem}.calib.yaml beside it)"
            )
        return load_calibration(self.calibration)


def split_frame_id(frame_id: str) -> tuple[str, int] | None:
    """``("seq id", k)`` for a sequence frame id ``seq id@k``, None for any other id."""
    m = _FRAME_ID.match(frame_id)
    return None if m is None else (m["seq"], int(m["k"]))


def find_sequences(root: str | Path) -> list[SequenceEntry]:
    """Every sequence under ``root`` (module docstring), sorted by id."""
    root = Path(root)
    found: list[SequenceEntry] = []
    claimed: list[Path] = []
    for folder in sorted(p for p in root.rglob(SEQUENCES_DIR) if p.is_dir()):
        if _hidden(root, folder):
            continue
        for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
            if sub.name.startswith((".", "__")):
                continue
            if (sub / "metadata.yaml").is_file():
                continue  # a ROS2 bag: found below
            if any(p.suffix.lower() in IMAGE_SUFFIXES for p in sub.iterdir()):
                found.append(_entry(root, sub, "images"))
                claimed.append(sub)
    for path in sorted(root.rglob("*")):
        if _hidden(root, path) or any(c == path or c in path.parents for c in claimed):
            continue
        if path.is_dir() and (path / "metadata.yaml").is_file():
            found.append(_entry(root, path, "bag"))
            claimed.append(path)
        elif path.is_file() and path.suffix.lower() == ".bag":
            found.append(_entry(root, path, "bag"))
        elif path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
            found.append(_entry(root, path, "video"))
    return sorted(found, key=lambda e: e.id)


def sequence_folders(entries: list[SequenceEntry]) -> list[Path]:
    """The folders that belong to sequences (their images are no still frames)."""
    return [e.path for e in entries if e.path.is_dir()]


def _hidden(root: Path, path: Path) -> bool:
    return any(part.startswith((".", "__")) for part in path.relative_to(root).parts)


def _entry(root: Path, path: Path, kind: str) -> SequenceEntry:
    calib = None
    if kind != "bag":
        own = path.with_name(f"{path.stem}.calib.yaml") if path.is_file() else None
        if own is not None and own.is_file():
            calib = own
        else:
            d = path if path.is_dir() else path.parent
            while True:
                if (d / "calibration.yaml").is_file():
                    calib = d / "calibration.yaml"
                    break
                if d == root or root not in d.parents:
                    break
                d = d.parent
    return SequenceEntry(path.relative_to(root).as_posix(), path, kind, calib)
