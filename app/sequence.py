"""Stereo sequences from disk, read lazily (one frame in memory at a time), and tracking over
them.

Sources (:func:`open_sequence`):

* a stereo **video**, side by side (left half | right half), or a left video plus ``right=``
  a right video, decoded frame by frame with PyAV;
* an **image-sequence folder**: side-by-side images (``<stem>_mask.png`` masks and ``<stem>.npy``
  ground-truth control points beside them are used when present, ``calibration.yaml`` in the
  folder too; this is what ``threadrecon generate --sequence`` writes), or ``left/`` and
  ``right/`` sub-folders of equally many images;
* a **ROS1 bag** (``.bag``) or a **ROS2 bag** (folder with ``metadata.yaml``) with two image
  topics (``sensor_msgs/Image`` or ``CompressedImage``) and, when present, their
  ``sensor_msgs/CameraInfo`` (read with the pure-Python ``rosbags``; no ROS installation).

Images are rectified already (the core's assumption); a bag's calibration is built from its
``camera_info`` projection matrices (``P``), in mm.
"""

from __future__ import annotations

import abc
import re
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from threadrecon.app.io import load_calibration, load_ground_truth, read_image, read_mask
from threadrecon.core.calibration import StereoCalibration, make_calibration
from threadrecon.core.segmentation import StereoPair, split_side_by_side

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".mkv", ".avi", ".mov", ".webm", ".m4v")
SYNC_TOLERANCE_S = 0.005  # left and right messages of one stereo frame: stamps within 5 ms
_IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_INFO_TYPE = "sensor_msgs/msg/CameraInfo"


class SequenceError(ValueError):
    """A sequence source that cannot be read; the message names the file and the problem."""


@dataclass(frozen=True)
class SequenceFrame:
    """One stereo frame of a sequence. ``truth``: (M, 3) dense ground-truth curve (calibration
    units) when the source has one; ``stamp``: seconds (bags, videos) or None."""

    index: int
    name: str
    pair: StereoPair
    stamp: float | None = None
    truth: np.ndarray | None = None


class Sequence(abc.ABC):
    """A lazily read stereo sequence: iterate it for :class:`SequenceFrame` s."""

    source: str
    count: int | None
    """Number of frames when known without decoding them all (None otherwise)."""
    calibration: StereoCalibration | None
    """The calibration carried by the source itself (a bag's camera_info, a folder's YAML)."""

    @abc.abstractmethod
    def __iter__(self) -> Iterator[SequenceFrame]:
        """Frames in order, decoded one at a time."""

    _cursor_lock = threading.Lock()  # guards every sequence's cursor (a short critical section)

    def frame(self, k: int) -> SequenceFrame:
        """Frame ``k`` (from 0). This default decodes forward from a kept cursor (a video or a
        bag has no cheap random access): the next frames cost one decode each, a frame before
        the cursor restarts from the first; an image folder reads the one frame."""
        if k < 0 or (self.count is not None and k >= self.count):
            raise SequenceError(f"{self.source}: no frame {k} (frames 0..{(self.count or 0) - 1})")
        with self._cursor_lock:
            cursor = self.__dict__.pop("_cursor", None)
            if cursor is None or cursor[1] > k:
                if cursor is not None:
                    cursor[0].close()
                cursor = (iter(self), 0)
            frames = cursor[0]
            for f in frames:
                if f.index == k:
                    self.__dict__["_cursor"] = (frames, k + 1)
                    return f
        raise SequenceError(f"{self.source}: no frame {k} (the source ended before it)")


def open_sequence(
    source: str | Path,
    right: str | Path | None = None,
    left_topic: str | None = None,
    right_topic: str | None = None,
) -> Sequence:
    """Open a video, an image folder or a ROS bag (see the module docstring)."""
    path = Path(source)
    if not path.exists():
        raise SequenceError(f"{path}: no such file or folder")
    if right is not None:
        return VideoSequence(path, Path(right))
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return BagSequence(path, left_topic, right_topic)
        return ImageFolderSequence(path)
    if path.suffix == ".bag":
        return BagSequence(path, left_topic, right_topic)
    return VideoSequence(path)


# --- videos ------------------------------------------------------------------------------


class VideoSequence(Sequence):
    """Side-by-side video, or left and right videos; decoded one frame at a time."""

    def __init__(self, path: Path, right: Path | None = None) -> None:
        import av  # PyAV: FFmpeg's decoders without loading the file

        self._av = av
        self.source = str(path)
        self.paths = (path,) if right is None else (path, right)
        counts = []
        for p in self.paths:
            if not p.is_file():
                raise SequenceError(f"{p}: video file not found")
            try:
                with av.open(str(p)) as c:
                    if not c.streams.video:
                        raise SequenceError(f"{p}: no video stream")
                    counts.append(int(c.streams.video[0].frames) or None)
            except av.error.FFmpegError as exc:
                raise SequenceError(f"{p}: not a readable video ({exc})") from None
        self.count = None if None in counts else min(counts)  # type: ignore[type-var]
        self.calibration = None

    def __iter__(self) -> Iterator[SequenceFrame]:
        containers = [self._av.open(str(p)) for p in self.paths]
        try:
            streams = [c.streams.video[0] for c in containers]
            decoders = [c.decode(s) for c, s in zip(containers, streams, strict=True)]
            for k, frames in enumerate(zip(*decoders, strict=False)):
                images = [f.to_ndarray(format="rgb24") for f in frames]
                if len(images) == 1:
                    if images[0].shape[1] % 2:
                        raise SequenceError(
                            f"{self.source}: a side-by-side video needs an even width, got "
                            f"{images[0].shape[1]} px (give the right view with --right)"
                        )
                    left, right = split_side_by_side(images[0])
                else:
                    left, right = images
                t = frames[0].time
                yield SequenceFrame(
                    k, f"frame_{k:06d}", StereoPair(np.ascontiguousarray(left), right), t
                )
        finally:
            for c in containers:
                c.close()


def write_video(path: Path, frames: Iterator[np.ndarray], fps: float = 30.0) -> int:
    """Encode RGB frames (H, W, 3) uint8 to a lossless-enough H.264 file, one at a time;
    returns the number of frames. The first frame fixes the size (even sizes are required)."""
    import av

    n = 0
    with av.open(str(path), mode="w") as out:
        stream = None
        for img in frames:
            if stream is None:
                h, w = img.shape[:2]
                if h % 2 or w % 2:
                    raise ValueError(f"video frames must have even sizes, got {w}x{h}")
                stream = out.add_stream("libx264", rate=int(round(fps)))
                stream.width, stream.height = w, h
                stream.pix_fmt = "yuv444p"  # no chroma subsampling: thin threads keep colour
                stream.options = {"crf": "12", "preset": "veryfast"}
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            for packet in stream.encode(frame):
                out.mux(packet)
            n += 1
        if stream is not None:
            for packet in stream.encode():
                out.mux(packet)
    return n


# --- image folders -----------------------------------------------------------------------


def _natural_key(path: Path) -> tuple[Any, ...]:
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name))


def _images(folder: Path) -> list[Path]:
    return sorted(
        (
            p
            for p in folder.iterdir()
            if p.suffix.lower() in IMAGE_SUFFIXES and not p.stem.endswith("_mask")
        ),
        key=_natural_key,
    )


class ImageFolderSequence(Sequence):
    """Side-by-side images of a folder (natural order), or its ``left/`` and ``right/``."""

    def __init__(self, folder: Path, masks: bool = True) -> None:
        self.source = str(folder)
        self.folder = folder
        self.masks = masks
        """Use the ``<stem>_mask.png`` files (False: raw frames, segmented from the images)."""
        if (folder / "left").is_dir() and (folder / "right").is_dir():
            self.lefts, self.rights = _images(folder / "left"), _images(folder / "right")
            if len(self.lefts) != len(self.rights):
                raise SequenceError(
                    f"{folder}: left/ has {len(self.lefts)} images, right/ {len(self.rights)}"
                )
        else:
            self.lefts, self.rights = _images(folder), []
        if not self.lefts:
            raise SequenceError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
        self.count = len(self.lefts)
        calib = folder / "calibration.yaml"
        self.calibration = load_calibration(calib) if calib.is_file() else None

    def __iter__(self) -> Iterator[SequenceFrame]:
        for k in range(len(self.lefts)):
            yield self.frame(k)

    def frame(self, k: int) -> SequenceFrame:
        """Frame ``k`` (from 0), read from its own files."""
        if not 0 <= k < len(self.lefts):
            raise SequenceError(f"{self.source}: no frame {k} (frames 0..{len(self.lefts) - 1})")
        left_path = self.lefts[k]
        if self.rights:
            pair = StereoPair(read_image(left_path), read_image(self.rights[k]))
        else:
            L, R = split_side_by_side(read_image(left_path))
            mask = left_path.with_name(f"{left_path.stem}_mask.png")
            mL = mR = None
            if self.masks and mask.is_file():
                mL, mR = (m.astype(bool) for m in split_side_by_side(read_mask(mask)))
            pair = StereoPair(L, R, mL, mR)
        gt_path = left_path.with_suffix(".npy")
        truth = load_ground_truth(gt_path) if gt_path.is_file() else None
        return SequenceFrame(k, left_path.stem, pair, None, truth)


# --- ROS bags ----------------------------------------------------------------------------


class BagSequence(Sequence):
    """Two image topics of a ROS1 or ROS2 bag, paired by header stamp (within 5 ms)."""

    def __init__(
        self, path: Path, left_topic: str | None = None, right_topic: str | None = None
    ) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.source = str(path)
        self._open = lambda: AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        try:
            with self._open() as reader:
                images = {c.topic: c for c in reader.connections if c.msgtype in _IMAGE_TYPES}
                self.left_topic, self.right_topic = _pick_topics(
                    path, sorted(images), left_topic, right_topic
                )
                self.count = min(
                    images[self.left_topic].msgcount, images[self.right_topic].msgcount
                )
                self.calibration = self._camera_info(reader)
        except SequenceError:
            raise
        except Exception as exc:  # rosbags raises its own types for a broken bag
            raise SequenceError(f"{path}: not a readable ROS bag ({exc})") from None

    def _camera_info(self, reader: Any) -> StereoCalibration | None:
        infos = {c.topic: c for c in reader.connections if c.msgtype == _INFO_TYPE}
        found = []
        for topic in (self.left_topic, self.right_topic):
            ns = topic.rsplit("/", 1)[0]
            match = [c for t, c in infos.items() if t.rsplit("/", 1)[0] == ns]
            if not match:
                return None
            conn, _, raw = next(reader.messages(connections=match[:1]))
            found.append(reader.deserialize(raw, conn.msgtype))
        left, right = found
        # ROS2 names the projection matrix ``p``, ROS1 ``P``
        P1, P2 = (
            np.asarray(m.p if hasattr(m, "p") else m.P, dtype=float).reshape(3, 4)
            for m in (left, right)
        )
        if P1[0, 0] <= 0 or P2[0, 0] <= 0:
            raise SequenceError(f"{self.source}: camera_info has no projection matrix P")
        baseline_m = -P2[0, 3] / P2[0, 0]  # ROS: P_right[0, 3] = -fx * B, B in m
        if not baseline_m > 0:
            raise SequenceError(
                f"{self.source}: right camera_info P[0, 3] = {P2[0, 3]} gives no positive "
                "baseline (are the topics swapped?)"
            )
        return make_calibration(
            P1[:, :3],
            np.zeros((1, 5)),
            P2[:, :3],
            np.zeros((1, 5)),
            np.eye(3),
            np.array([[-1000.0 * baseline_m], [0.0], [0.0]]),
            (int(left.height), int(left.width)),
            unit="mm",
            source=f"{self.source} camera_info",
        )

    def __iter__(self) -> Iterator[SequenceFrame]:
        with self._open() as reader:
            conns = [
                c for c in reader.connections if c.topic in (self.left_topic, self.right_topic)
            ]
            pending: dict[str, tuple[float, np.ndarray]] = {}
            k = 0
            for conn, _, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                side = "left" if conn.topic == self.left_topic else "right"
                other = "right" if side == "left" else "left"
                image = _decode_image(msg, conn.msgtype, f"{self.source}:{conn.topic}")
                if other in pending and abs(pending[other][0] - stamp) <= SYNC_TOLERANCE_S:
                    images = {side: image, other: pending.pop(other)[1]}
                    pair = StereoPair(images["left"], images["right"])
                    yield SequenceFrame(k, f"frame_{k:06d}", pair, stamp)
                    k += 1
                else:
                    pending[side] = (stamp, image)  # an unmatched older one is dropped


def _pick_topics(
    path: Path, topics: list[str], left: str | None, right: str | None
) -> tuple[str, str]:
    for name, t in (("left", left), ("right", right)):
        if t is not None and t not in topics:
            raise SequenceError(f"{path}: no image topic {t!r} ({name}); image topics: {topics}")
    if left is not None and right is not None:
        return left, right
    lefts = [t for t in topics if "left" in t.lower()]
    rights = [t for t in topics if "right" in t.lower()]
    left = left or (lefts[0] if len(lefts) == 1 else None)
    right = right or (rights[0] if len(rights) == 1 else None)
    if left is None or right is None:
        raise SequenceError(
            f"{path}: cannot tell the left and right image topics apart among {topics}; "
            "give --left-topic and --right-topic"
        )
    return left, right


def _decode_image(msg: Any, msgtype: str, where: str) -> np.ndarray:
    """An Image or CompressedImage message -> (H, W, 3) RGB or (H, W) grey uint8."""
    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise SequenceError(f"{where}: undecodable compressed image ({msg.format})")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc1": 1, "8uc3": 3}
    enc = msg.encoding.lower()
    if enc not in channels:
        raise SequenceError(
            f"{where}: image encoding {msg.encoding!r} is not supported (8-bit only)"
        )
    c = channels[enc]
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.step < msg.width * c or data.size < msg.step * msg.height:
        raise SequenceError(
            f"{where}: image data ({data.size} B) does not fit {msg.width}x{msg.height} {enc}"
        )
    img = data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, : msg.width * c]
    img = img.reshape(msg.height, msg.width, c)
    if c == 1:
        return np.ascontiguousarray(img[:, :, 0])
    if enc.startswith("bgr"):
        img = img[:, :, 2::-1]
    return np.ascontiguousarray(img[:, :, :3])
