"""The check stage's distance field of a thread mask: what depends only on the segmentation.

For one (H, W) thread mask P (P_L or P_R of Eq. (1)) the field holds the distance (px) of each
pixel of the mask's bounding box grown by ``reach`` px to the nearest thread pixel (one
distance transform, 3x3 L2 mask, error < 3 %). A pixel outside that box is farther than
``reach`` from every thread pixel. The check reads the reprojection distances of the curve
and the background ring around the thread from it.

Fields are cached by the mask object (a weak reference, so that a freed mask whose id is reused
never hits): the debugger re-runs the check after every slider move of a later stage while the
segmentation, and so the mask object, is unchanged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np

from threadrecon.core.check_kernel import field_at
from threadrecon.core.lru import LRU

FIELD_CACHE = 8  # fields kept: both views of a few frames, the debugger's working set
DERIVED_CACHE = 16  # other per-segmentation values kept (a few kinds for a few frames)
T = TypeVar("T")


@dataclass(frozen=True)
class MaskField:
    """Distance to the nearest thread pixel on the box [y0, y0 + h) x [x0, x0 + w) of the
    image: ``dist`` (h, w) float32 px (read-only); ``total`` the number of thread pixels."""

    dist: np.ndarray
    x0: int
    y0: int
    reach: float
    total: int
    bbox: tuple[int, int, int, int] = (0, 0, 0, 0)
    """(x, y, w, h) of the thread pixels' bounding box in the image."""

    def at(self, uv: np.ndarray) -> np.ndarray:
        """Distance (px) of each (x, y) in ``uv`` (N, 2) to the nearest thread pixel, saturated
        at ``reach``; a non-finite point gets ``reach``. A point off the image adds its
        distance to the nearest image pixel of the box."""
        if self.total == 0:
            return np.full(len(uv), self.reach)
        uv = np.ascontiguousarray(uv, dtype=np.float64)
        return field_at(self.dist, float(self.x0), float(self.y0), float(self.reach), uv)

    def window(self, x: int, y: int, r: int) -> tuple[np.ndarray, slice, slice]:
        """The field on the image window of half-size ``r`` around pixel (x, y), clipped to
        the box, and the window's row and column slices in image coordinates."""
        h, w = self.dist.shape
        r0, r1 = max(y - r, self.y0), min(y + r + 1, self.y0 + h)
        c0, c1 = max(x - r, self.x0), min(x + r + 1, self.x0 + w)
        if r1 <= r0 or c1 <= c0:
            return self.dist[:0, :0], slice(0, 0), slice(0, 0)
        d = self.dist[r0 - self.y0 : r1 - self.y0, c0 - self.x0 : c1 - self.x0]
        return d, slice(r0, r1), slice(c0, c1)


def mask_field(mask: np.ndarray, reach: float) -> MaskField:
    """The (cached) distance field of a boolean (H, W) thread mask up to ``reach`` px."""
    if mask.ndim != 2 or mask.dtype != bool:
        raise ValueError(f"a thread mask must be (H, W) bool, got {mask.shape} {mask.dtype}")
    return _FIELDS.cached((mask,), (float(reach),), lambda: _compute(mask, float(reach)))


def clear_fields() -> None:
    """Forget every cached field and derived value (timings of the check on a new
    segmentation)."""
    _FIELDS.clear()
    _DERIVED.clear()


def derived(owners: tuple[np.ndarray, ...], tag: str, compute: Callable[[], T]) -> T:
    """``compute()``, cached while the arrays ``owners`` are alive (weak references, as for
    the fields): what the check derives from one segmentation or stereo result and re-reads
    after a slider move of a later stage. ``tag`` names the kind of value."""
    return _DERIVED.cached(owners, (tag,), compute)


def _compute(mask: np.ndarray, reach: float) -> MaskField:
    H, W = mask.shape
    m8 = np.ascontiguousarray(mask).view(np.uint8)
    total = cv2.countNonZero(m8)
    if total == 0:
        return MaskField(np.zeros((0, 0), np.float32), 0, 0, reach, 0)
    bx, by, bw, bh = cv2.boundingRect(m8)
    m = int(np.ceil(reach))
    x0, x1 = max(0, bx - m), min(W, bx + bw + m)
    y0, y1 = max(0, by - m), min(H, by + bh + m)
    background = cv2.compare(m8[y0:y1, x0:x1], 0, cv2.CMP_EQ)
    dist = cv2.distanceTransform(background, cv2.DIST_L2, cv2.DIST_MASK_3)
    dist.setflags(write=False)
    return MaskField(dist, x0, y0, reach, int(total), (bx, by, bw, bh))


_FIELDS: LRU[tuple, Any] = LRU(FIELD_CACHE)  # LRU.cached entries
_DERIVED: LRU[tuple, Any] = LRU(DERIVED_CACHE)
