"""Parts of an instrument that a width test misses: the jaws of a grasper.

An instrument's shaft is wide and is found as such (``segmentation._drop_wide`` on a flat
background, ``segment_raw._instrument_mask`` on tissue); its jaws are as thin as a few thread
widths and stay in the thread mask as stubs attached to the shaft. One thread has one width
along its length, so the part of a piece attached to the instrument that is markedly wider
than the thread (read along the medial axis of the pieces: the thread makes most of it)
belongs to the instrument, also when a jaw touches the thread and they form one piece. A
thread passing under the instrument touches it too, but keeps its own width.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np

from threadrecon.core.instrument_kernel import label_lookup, ridge_values
from threadrecon.core.numeric import distance_to_zero
from threadrecon.core.ridge_kernel import attached

WIDER_THAN_THREAD: Final = 1.5  # a piece 1.5x as wide as the thread is not the same thread
# (the width of a 1-6 px thread varies by < 30 % along it at this resolution; a jaw is >= 2x)
_CROSS: Final = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


def drop_attached(mask: np.ndarray, tool: np.ndarray, body: np.ndarray | None = None) -> np.ndarray:
    """``mask`` (H, W) bool without the parts wider than the thread of the pieces that touch
    ``tool`` (H, W) bool, the instrument found so far: what a disc WIDER_THAN_THREAD times as
    wide as the thread covers inside them (an opening) where that reaches the tool, and the
    corners it cannot reach where
    such a part meets the tool (:func:`_corners`). Pieces are those of ``body`` (H, W) bool
    outside ``tool`` (default ``mask``): the pixels off the background level, dark or bright,
    so that a jaw's highlight is part of the jaw and its width is the jaw's, not that of its
    dark rims.

    The thread's width is that of the longest piece (its perimeter: both sides of a strip),
    read along its medial axis (:func:`thread_half_width`), not as its mean: a jaw
    touching the thread is one piece with it, and only its own part is wider. A piece no
    wider than the thread anywhere (a thread end leaving the tool) holds no such disc and stays
    whole. When the thread is mostly hidden and the jaws make most of that piece's medial axis, the reference is the jaws' width and nothing is dropped: there is no
    thinner reference to tell a jaw from the thread.
    """
    if mask.shape != tool.shape or mask.ndim != 2:
        raise ValueError(f"drop_attached needs two (H, W) masks, got {mask.shape}, {tool.shape}")
    body = mask if body is None else body
    if body.shape != mask.shape:
        raise ValueError(f"drop_attached: body {body.shape} differs from mask {mask.shape}")
    if not mask.any() or not tool.any():
        return mask
    u8 = (np.ascontiguousarray(body, dtype=bool) & ~tool).view(np.uint8)
    n, labels = cv2.connectedComponents(u8, connectivity=8, ltype=cv2.CV_32S)
    tool8 = np.ascontiguousarray(tool, dtype=bool).view(np.uint8)
    rim = cv2.dilate(tool8, _CROSS)
    touching = np.zeros(n, bool)
    touching[labels[rim > 0]] = True
    touching[0] = False
    if not touching.any():
        return mask
    # The thread's width: that of the longest piece (the thread, or the longest of its visible
    # parts, with the jaws that touch it if any).
    edge = (u8 > cv2.erode(u8, _CROSS, borderType=cv2.BORDER_REPLICATE)).ravel()
    perimeter = np.bincount(labels.ravel()[edge], minlength=n)
    perimeter[0] = -1
    half = thread_half_width(labels == int(np.argmax(perimeter)))
    if half is None:
        return mask
    # A strip w px wide has a medial distance (w + 1) / 2: the disc's radius is
    # WIDER_THAN_THREAD half-widths of the thread, (w - 1) / 2 < r (it fits in no thread).
    r = max(int(np.ceil(WIDER_THAN_THREAD * (half - 0.5))), 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    attached = label_lookup(labels, touching) & u8  # touching[labels]
    wide = cv2.erode(attached, disc)
    if not wide.any():
        return mask
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 3, 2 * r + 3))
    wide = cv2.dilate(wide, grow)  # the opening, and its 1 px anti-aliased rim
    # Only the wide parts that reach the tool themselves (a jaw is attached to the shaft; a
    # thread crossing itself is wide where it crosses, away from the tool).
    m, parts = cv2.connectedComponents(wide, connectivity=8, ltype=cv2.CV_32S)
    reach = np.zeros(m, bool)
    reach[parts[rim > 0]] = True
    reach[0] = False
    if not reach.any():
        return mask
    wide = label_lookup(parts, reach)  # reach[parts]
    wide |= _corners(attached & (wide == 0), wide | tool8, 2 * r + 3)
    return mask & (wide == 0)


def thread_half_width(pieces: np.ndarray) -> float | None:
    """The thread's half-width (px, a strip w px wide gives (w + 1) / 2) read from ``pieces``
    (H, W) bool: the median distance to the outside along their medial axis (the pixels no
    neighbour of which is farther inside), so that the longest width wins over short wider
    parts (jaws, crossings); None when there is no piece."""
    u8 = np.ascontiguousarray(pieces, dtype=bool).view(np.uint8)
    if not u8.any():
        return None
    dist = distance_to_zero(u8)
    # dist[(u8 > 0) & (dist >= cv2.dilate(dist, 3 x 3))], on the piece's pixels only
    return float(np.median(ridge_values(dist, np.ascontiguousarray(u8))))


def _corners(rest: np.ndarray, removed: np.ndarray, size: int) -> np.ndarray:
    """(H, W) uint8, 1 on the 8-connected pieces of ``rest`` (uint8, what is left of the pieces
    attached to the tool) that touch ``removed`` (uint8, the tool and the wide parts taken) and
    fit in a ``size`` x ``size`` box: the corner where a jaw meets the shaft, which the
    opening's disc does not reach. A thread piece that short beside an instrument is no usable
    part of the thread either.

    Computed on the bounding box of ``rest`` grown by one pixel (the pieces and their sizes
    are those of the whole image; the cross dilation of ``removed`` reaches the box's pixels
    from that margin only), zeros elsewhere."""
    out = np.zeros(rest.shape, np.uint8)
    x, y, w, h = cv2.boundingRect(rest)
    if w == 0:
        return out
    H, W = rest.shape
    r0, r1, c0, c1 = max(y - 1, 0), min(y + h + 1, H), max(x - 1, 0), min(x + w + 1, W)
    box = np.ascontiguousarray(rest[r0:r1, c0:c1])
    n, labels, stats, _ = cv2.connectedComponentsWithStats(box, connectivity=8)
    if n <= 1:
        return out
    near = np.zeros(n, bool)
    near[labels[cv2.dilate(np.ascontiguousarray(removed[r0:r1, c0:c1]), _CROSS) > 0]] = True
    small = (stats[:, cv2.CC_STAT_WIDTH] <= size) & (stats[:, cv2.CC_STAT_HEIGHT] <= size)
    drop = near & small
    drop[0] = False
    out[r0:r1, c0:c1] = label_lookup(labels, drop)  # drop[labels]
    return out


def grow_into_attached(grey: np.ndarray, tool: np.ndarray, min_width_px: int) -> np.ndarray:
    """``tool`` (H, W) bool grown by the parts of ``grey`` (H, W) bool (pixels of the
    instrument's colour) that are at least ``min_width_px`` wide (they hold a disc that wide)
    and touch it: the jaws of a grasper, attached to its shaft and wider than any thread, but
    thinner than the shaft-sized opening that found the tool. A thread of the tool's colour
    (white, black) no wider than ``min_width_px - 1`` holds no such disc and is not grown into.
    """
    if grey.shape != tool.shape or grey.ndim != 2:
        raise ValueError(
            f"grow_into_attached needs two (H, W) masks, got {grey.shape}, {tool.shape}"
        )
    if min_width_px < 1:
        raise ValueError(f"min_width_px must be >= 1, got {min_width_px}")
    tool8 = np.ascontiguousarray(tool, dtype=bool).view(np.uint8)
    if not tool8.any():
        return tool
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (min_width_px, min_width_px))
    wide = cv2.morphologyEx(
        np.ascontiguousarray(grey, dtype=bool).view(np.uint8), cv2.MORPH_OPEN, disc
    )
    # the components of wide | tool that hold a tool pixel (they hold the tool), from their
    # row runs in one compiled pass: no label image
    return attached(wide, tool8, np.empty_like(wide)).view(bool)
