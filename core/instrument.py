"""Parts of an instrument that a width test misses: the jaws of a grasper.

An instrument's shaft is wide and is found as such (``segmentation._drop_wide`` on a flat
background, ``segment_raw._instrument_mask`` on tissue); its jaws are as thin as a few thread
widths and stay in the thread mask as stubs attached to the shaft. One thread has one width
along its length, so a piece attached to the instrument that is markedly wider than the
frame's longest piece (the thread, or the longest of its visible parts) belongs to the
instrument. A thread passing under the instrument touches it too, but keeps its own width.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np

WIDER_THAN_THREAD: Final = 1.5  # a piece 1.5x as wide as the thread is not the same thread
# (the width of a 1-6 px thread varies by < 30 % along it at this resolution; a jaw is >= 2x)
_CROSS: Final = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


def drop_attached(mask: np.ndarray, tool: np.ndarray, body: np.ndarray | None = None) -> np.ndarray:
    """``mask`` (H, W) bool without the wide part of the pieces that touch ``tool`` (H, W)
    bool, the instrument found so far, and are more than WIDER_THAN_THREAD times as wide as the
    longest piece (the wide part: what a disc WIDER_THAN_THREAD times as wide as that piece
    covers inside it). Pieces are those of ``body`` (H, W) bool outside ``tool`` (default ``mask``): the
    pixels off the background level, dark or bright, so that a jaw's highlight is part of the
    jaw and its width is the jaw's, not that of its dark rims.

    A piece's mean width is 2 area / perimeter (perimeter: its pixels with a 4-neighbour
    outside it, which counts both sides of a strip); its length is half that perimeter. When the
    longest piece is itself attached and as wide as the rest (the thread mostly hidden), nothing
    is dropped: there is no thinner reference to tell a jaw from the thread.
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
    if n <= 2:  # one piece: nothing to compare it with
        return mask
    rim = cv2.dilate(np.ascontiguousarray(tool, dtype=bool).view(np.uint8), _CROSS)
    touching = np.zeros(n, bool)
    touching[labels[rim > 0]] = True
    touching[0] = False
    if not touching.any():
        return mask
    area = np.bincount(labels.ravel(), minlength=n).astype(np.float64)
    edge = (u8 > cv2.erode(u8, _CROSS, borderType=cv2.BORDER_REPLICATE)).ravel()
    perimeter = np.bincount(labels.ravel()[edge], minlength=n).astype(np.float64)
    area[0] = perimeter[0] = 0.0
    width = 2.0 * area / np.maximum(perimeter, 1.0)
    ref = int(np.argmax(perimeter))  # the longest piece: the thread or its longest part
    drop = touching & (width > WIDER_THAN_THREAD * width[ref])
    if not drop.any():
        return mask
    # Only the wide part of such a piece: a thread end touching a jaw is in the same piece,
    # thinner than the disc that fits in the jaw (radius WIDER_THAN_THREAD thread half-widths).
    r = max(int(np.ceil(0.5 * WIDER_THAN_THREAD * width[ref])), 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    wide = cv2.erode(drop[labels].view(np.uint8) & u8, disc)
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 3, 2 * r + 3))
    wide = cv2.dilate(wide, grow)  # the opening, and its 1 px anti-aliased rim
    return mask & (wide == 0)


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
    wide |= tool8
    n, labels = cv2.connectedComponents(wide, connectivity=8, ltype=cv2.CV_32S)
    touching = np.zeros(n, bool)
    touching[labels[tool8 > 0]] = True
    touching[0] = False
    return touching[labels] | tool
