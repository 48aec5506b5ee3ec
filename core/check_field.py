"""The check stage's distance field of a thread mask: what depends only on the segmentation.

For one (H, W) thread mask P (P_L or P_R of Eq. (1)) the field gives the distance (px) of each
pixel of the mask's bounding box grown by ``reach`` px to the nearest thread pixel (the values
of one distance transform of that box, 3x3 L2 mask, error < 3 %). A pixel outside that box is
farther than ``reach`` from every thread pixel. The check reads the reprojection distances of
the curve and the background ring around the thread from it. The values are computed where
they are read (small crops, ``MaskField``), not over the whole box: the same numbers at a
fraction of the cost (issue 13).

Fields are cached by the mask object (a weak reference, so that a freed mask whose id is reused
never hits): the debugger re-runs the check after every slider move of a later stage while the
segmentation, and so the mask object, is unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import cv2
import numpy as np

from threadrecon.core.check_kernel import field_at, field_pixels, near_values
from threadrecon.core.lru import LRU
from threadrecon.core.refine import row_runs

FIELD_CACHE = 8  # fields kept: both views of a few frames, the debugger's working set
DERIVED_CACHE = 24  # other per-segmentation values kept (a dozen kinds for two frames)
T = TypeVar("T")


CHUNK = 32  # curve points per crop of the first round (consecutive points: a compact crop)
NEAR_PX = 8  # px of margin around them in the first round (a point on or near the thread)
SIMD_PX = 4  # the transform's values depend on a crop's column modulo this (MaskField)
CROPS_SHARE = 0.5  # crops covering more than this share of the box: the whole box instead
HV = 0.955  # the 3x3 L2 mask's straight step (DIST_MASK_3): its distance >= HV x Chebyshev's


@dataclass(frozen=True)
class MaskField:
    """Distance to the nearest thread pixel on the box [y0, y0 + h) x [x0, x0 + w) of the
    image (``shape`` = (h, w)): the values of one distance transform of the box
    (``cv2.distanceTransform``, 3x3 L2 mask; ``dist``), computed on demand where they are read;
    ``total`` the number of thread pixels.

    Crops: the transform of a crop of the box whose left column lies a multiple of SIMD_PX
    columns from the box's (OpenCV's vectorised passes work on groups of columns counted from
    the crop's left edge) equals the box's at every pixel whose crop value c satisfies
    c <= HV (e - 1), e the pixel's distance to the nearest crop side that is not a side of the
    box (every thread pixel the box's value comes from then lies in the crop); elsewhere the
    crop value is an upper bound and the box's value at least HV e. tests/core/test_check_field
    checks this against the whole box on random masks. A point of the curve is read from a
    crop around its run of CHUNK points (NEAR_PX margin), else from a crop reaching ``reach``
    px around it, else from the whole box (also when the crops, with those of the field's
    earlier reads, would cover more than CROPS_SHARE of it: many points far off the thread,
    now or on the check's earlier runs; the box is then kept for every later read). Most
    points of a curve lie on or next to a thread pixel, where the value is one of a few
    constants (``check_kernel.near_values``): only the others need a crop."""

    mask: np.ndarray
    x0: int
    y0: int
    shape: tuple[int, int]
    reach: float
    total: int
    bbox: tuple[int, int, int, int] = (0, 0, 0, 0)
    """(x, y, w, h) of the thread pixels' bounding box in the image."""
    _state: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def dist(self) -> np.ndarray:
        """(h, w) float32 px: the distance transform of the whole box (read-only)."""
        if "dist" not in self._state:
            h, w = self.shape
            d = self._crop(0, 0, w, h) if h and w else np.zeros((0, 0), np.float32)
            d.setflags(write=False)
            self._state["dist"] = d
        return self._state["dist"]

    def at(self, uv: np.ndarray) -> np.ndarray:
        """Distance (px) of each (x, y) in ``uv`` (N, 2) to the nearest thread pixel, saturated
        at ``reach``; a non-finite point gets ``reach``. A point off the image adds its
        distance to the nearest image pixel of the box."""
        if self.total == 0:
            return np.full(len(uv), self.reach)
        uv = np.ascontiguousarray(uv, dtype=np.float64)
        h, w = self.shape
        pix = field_pixels(float(self.x0), float(self.y0), w, h, uv)
        if "dist" in self._state:  # the whole box was computed (it is not, normally)
            d = self.dist[np.maximum(pix[:, 1], 0), np.maximum(pix[:, 0], 0)]
        else:
            d = self._points(pix)
        return field_at(np.ascontiguousarray(d, dtype=np.float32), float(self.x0),
                        float(self.y0), float(self.reach), uv, pix)  # fmt: skip

    def window(self, x: int, y: int, r: int, upto: float) -> tuple[np.ndarray, slice, slice]:
        """The field on the image window of half-size ``r`` around pixel (x, y), clipped to
        the box, and the window's row and column slices in image coordinates: exact where it
        is at most ``upto`` px, above ``upto`` elsewhere."""
        h, w = self.shape
        r0, r1 = max(y - r, self.y0), min(y + r + 1, self.y0 + h)
        c0, c1 = max(x - r, self.x0), min(x + r + 1, self.x0 + w)
        if r1 <= r0 or c1 <= c0:
            return np.zeros((0, 0), np.float32), slice(0, 0), slice(0, 0)
        if "dist" in self._state:
            d = self.dist[r0 - self.y0 : r1 - self.y0, c0 - self.x0 : c1 - self.x0]
            return d, slice(r0, r1), slice(c0, c1)
        m = int(np.ceil(upto / HV)) + 2  # c <= upto <= HV (m - 1): exact (class docstring)
        bx0, by0 = max(c0 - self.x0 - m, 0), max(r0 - self.y0 - m, 0)
        bx0 -= bx0 % SIMD_PX
        bx1, by1 = min(c1 - self.x0 + m, w), min(r1 - self.y0 + m, h)
        d = self._crop(bx0, by0, bx1, by1)
        sub = d[r0 - self.y0 - by0 : r1 - self.y0 - by0, c0 - self.x0 - bx0 : c1 - self.x0 - bx0]
        return sub, slice(r0, r1), slice(c0, c1)

    def _crop(self, bx0: int, by0: int, bx1: int, by1: int) -> np.ndarray:
        """The distance transform of the crop [by0, by1) x [bx0, bx1) of the box (box px)."""
        m = self.mask[self.y0 + by0 : self.y0 + by1, self.x0 + bx0 : self.x0 + bx1]
        background = cv2.compare(m, 0, cv2.CMP_EQ)
        return cv2.distanceTransform(background, cv2.DIST_L2, cv2.DIST_MASK_3)

    def _points(self, pix: np.ndarray) -> np.ndarray:
        """The box's values at the (column, row) pixels ``pix`` (box px; -1: none), read from
        crops (class docstring): (N,) float32."""
        out = near_values(self.mask, self.x0, self.y0, pix)  # on or next to the thread
        todo = np.flatnonzero((out < 0) & (pix[:, 0] >= 0))
        far = int(np.ceil(self.reach / HV)) + 2  # HV (far - 1) > reach: certified or saturated
        spent = self._state.get("cropped", 0)  # px of crops transformed by earlier reads
        for margin in (NEAR_PX, far):
            if todo.size == 0:
                return out
            todo = todo[~self._chunks(pix[todo], margin, out, todo, spent)]
        if todo.size:  # not certain from the crops (none, normally): the whole box
            out[todo] = self.dist[pix[todo, 1], pix[todo, 0]]
        return out

    def _chunks(
        self, p: np.ndarray, margin: int, out: np.ndarray, idx: np.ndarray, spent: int = 0
    ) -> np.ndarray:
        """Read the pixels ``p`` (k, 2) of the curve points ``idx`` (ascending) into ``out[idx]``
        from one crop around each run of up to CHUNK consecutive points; which were certain
        (exact, or saturated: at least ``reach``). The whole box instead when the crops, with
        the ``spent`` px of crops of earlier reads of this field, would cover more than
        CROPS_SHARE of it: a curve that reads far off the thread once does so again on the
        check's next run (the debugger's slider moves re-check the same segmentation), and
        the whole box, computed once, serves every later read (the same values)."""
        h, w = self.shape
        brk = np.r_[True, np.diff(idx) > 1]  # a run of consecutive curve points: a compact crop
        run_start = np.flatnonzero(brk)
        pos = np.arange(len(p)) - run_start[np.cumsum(brk) - 1]
        starts = np.flatnonzero(pos % CHUNK == 0)  # at most CHUNK points per crop
        x0 = np.maximum(np.minimum.reduceat(p[:, 0], starts) - margin, 0)
        x0 -= x0 % SIMD_PX
        y0 = np.maximum(np.minimum.reduceat(p[:, 1], starts) - margin, 0)
        x1 = np.minimum(np.maximum.reduceat(p[:, 0], starts) + margin + 1, w)
        y1 = np.minimum(np.maximum.reduceat(p[:, 1], starts) + margin + 1, h)
        area = int(np.sum((x1 - x0) * (y1 - y0)))
        if spent + area > CROPS_SHARE * h * w:  # crops cost more than the box
            out[idx] = self.dist[p[:, 1], p[:, 0]]
            return np.ones(len(p), dtype=bool)
        self._state["cropped"] = self._state.get("cropped", 0) + area
        c = np.empty(len(p), np.float32)
        for a, b, c0, r0, c1, r1 in zip(
            starts.tolist(), [*starts[1:].tolist(), len(p)], x0.tolist(), y0.tolist(),
            x1.tolist(), y1.tolist(), strict=True,
        ):  # fmt: skip
            c[a:b] = self._crop(c0, r0, c1, r1)[p[a:b, 1] - r0, p[a:b, 0] - c0]
        n = np.diff(np.append(starts, len(p)))
        x0, y0, x1, y1 = (np.repeat(v, n) for v in (x0, y0, x1, y1))
        big = w + h  # a side of the box is no crop side: nothing lies beyond it
        e = np.minimum(
            np.minimum(
                np.where(x0 > 0, p[:, 0] - x0, big), np.where(x1 < w, x1 - 1 - p[:, 0], big)
            ),
            np.minimum(
                np.where(y0 > 0, p[:, 1] - y0, big), np.where(y1 < h, y1 - 1 - p[:, 1], big)
            ),
        )
        out[idx] = c
        # exact: c <= HV (e - 1); saturated: the box's value is at least HV e >= reach
        return (c <= HV * (e - 1)) | (HV * e * (1 - 1e-4) >= self.reach)


class PieceIndex:
    """Which of a list of pixel sets (a mask's pieces, each (k, 2) float64 integer (x, y)
    pixels, disjoint) holds a pixel: an (h, w) image of piece numbers (-1: none) on the
    pieces' bounding box. Pixel lookups instead of sorting a piece's pixels for each query
    (``np.isin``: ~3 ms a piece at 1920x1080, against microseconds)."""

    def __init__(self, parts: list[np.ndarray]) -> None:
        self.n = len(parts)
        if not parts:
            self.x0 = self.y0 = 0
            self.index = np.full((0, 0), -1, np.int32)
            return
        xy = np.concatenate(parts).astype(np.int64)
        self.x0, self.y0 = int(xy[:, 0].min()), int(xy[:, 1].min())
        h = int(xy[:, 1].max()) - self.y0 + 1
        w = int(xy[:, 0].max()) - self.x0 + 1
        dtype = np.int8 if len(parts) <= 127 else np.int16 if len(parts) <= 32767 else np.int32
        self.index = np.full((h, w), -1, dtype)  # the smallest: ~2 MB a view at 1920x1080
        number = np.repeat(np.arange(len(parts), dtype=dtype), [len(a) for a in parts])
        self.index[xy[:, 1] - self.y0, xy[:, 0] - self.x0] = number
        self.index.setflags(write=False)

    def at(self, px: np.ndarray) -> np.ndarray:
        """(k,) int32 piece number of each pixel of ``px`` (k, 2) (x, y; coordinates truncated
        to integers, as ``astype(int64)`` does), -1 where no piece holds it."""
        h, w = self.index.shape
        x = px[:, 0].astype(np.int64) - self.x0
        y = px[:, 1].astype(np.int64) - self.y0
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        out = np.full(len(px), -1, np.int32)
        out[inside] = self.index[y[inside], x[inside]]
        return out

    def near(self, xy: np.ndarray, r: float) -> list[int]:
        """The pieces (ascending numbers) with a pixel p such that ``np.hypot(*(p - xy))`` <=
        ``r``: the test ``np.min(np.hypot(*(part - xy).T)) <= r`` for each piece, on the pixels
        of the window around ``xy`` only (the same differences and hypot, so the same
        decisions); every piece when ``xy`` is not finite (the comparison with NaN is False:
        no piece is then excluded)."""
        if not (math.isfinite(xy[0]) and math.isfinite(xy[1])):
            return list(range(self.n))
        h, w = self.index.shape
        m = int(math.ceil(r)) + 1  # a window of the integer pixels within r, and a margin
        cx, cy = int(math.floor(xy[0])) - self.x0, int(math.floor(xy[1])) - self.y0
        c0, c1 = max(cx - m, 0), min(cx + m + 1, w)
        r0, r1 = max(cy - m, 0), min(cy + m + 1, h)
        if c1 <= c0 or r1 <= r0:
            return []
        win = self.index[r0:r1, c0:c1]
        ys, xs = np.nonzero(win >= 0)
        if not ys.size:
            return []
        p = np.column_stack([xs + (c0 + self.x0), ys + (r0 + self.y0)]).astype(np.float64)
        close = np.hypot(*(p - xy).T) <= r
        return sorted({int(i) for i in win[ys[close], xs[close]]})


def piece_index(mask: np.ndarray, parts: Callable[[], list[np.ndarray]]) -> PieceIndex:
    """The (cached) :class:`PieceIndex` of ``parts()``, the pieces of ``mask`` (cached with
    it, as :func:`derived`)."""
    return derived((mask,), "piece_index", lambda: PieceIndex(parts()))


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


def derived_entry(
    owners: tuple[np.ndarray, ...], tag: str, key: Hashable, compute: Callable[[], T]
) -> T:
    """``compute()`` for ``key``, kept in one dict per ``owners`` and ``tag`` (``derived``):
    many small values of one kind (a patch's match, a square's grey levels) that a later run
    of the check asks for again, without an LRU entry each."""
    memo = derived(owners, tag, dict)
    found = memo.get(key)
    if found is None:
        found = memo[key] = compute()
    return found


def _compute(mask: np.ndarray, reach: float) -> MaskField:
    H, W = mask.shape
    m8 = np.ascontiguousarray(mask).view(np.uint8)
    # the thread pixels' count and bounding box from the mask's row runs (cached with the
    # mask: the refine stage scanned it already), as cv2.countNonZero and cv2.boundingRect
    row, first, last = row_runs(mask)
    total = int(np.sum(last - first + 1))
    if total == 0:
        return MaskField(m8, 0, 0, (0, 0), reach, 0)
    bx, by = int(first.min()), int(row[0])
    bw, bh = int(last.max()) + 1 - bx, int(row[-1]) + 1 - by
    m = int(np.ceil(reach))
    x0, x1 = max(0, bx - m), min(W, bx + bw + m)
    y0, y1 = max(0, by - m), min(H, by + bh + m)
    return MaskField(m8, x0, y0, (y1 - y0, x1 - x0), reach, int(total), (bx, by, bw, bh))


_FIELDS: LRU[tuple, Any] = LRU(FIELD_CACHE)  # LRU.cached entries
_DERIVED: LRU[tuple, Any] = LRU(DERIVED_CACHE)
