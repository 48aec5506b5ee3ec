"""User corrections of the thread masks P_L, P_R, applied right after the segment stage.

A correction is one user action on one view's mask, in the rectified image the debugger shows
(pixel ``(x, y)``: x to the right, y down):

- ``remove``: the connected piece of P (8-connected) nearest the click, within ``radius``,
  is dropped (a vessel or fibre taken for thread); with ``stereo``, its partner in the other
  view too (the piece on the same rows at a disparity >= 0, :func:`_partner`);
- ``add``: the piece of thread at the click joins P: around the strongest colour contrast to
  the local (median) background within ``radius`` of the click, the connected pixels whose
  contrast has the same colour and at least half its strength, at most ``ADD_REACH_PX`` from
  the click (see :func:`_evidence_piece`);
- ``erase`` / ``paint``: a brush stroke of radius ``radius`` through ``points`` clears / sets P;
- ``clear``: the view's mask (view "both": both masks) is the segmenter's again; later
  actions apply on top of it;
- ``keep``: only P within ``radius`` of the polyline through ``points`` stays (not a user
  action: the tracker's gate around the thread it predicts, ``core.tracking.gate_corrections``).

Corrections are applied in order, each to the mask the previous ones left, so that a removed
piece stays removed when the segmentation parameters change and the piece moves a little.
The lifted images of Eq. (1) are recomputed from the corrected masks.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Final, Literal

import cv2
import numpy as np

from threadrecon.core.numeric import distance_to_zero
from threadrecon.core.segmentation import LIFT_VALUE, LiftedPair, StereoPair, to_grey

OPS: Final = ("remove", "add", "erase", "paint", "clear", "keep")
VIEWS: Final = ("left", "right")
MAX_RADIUS_PX: Final = 200.0  # a brush larger than this is a mistake, not a correction
MAX_STROKE_POINTS: Final = 5000  # points of one brush stroke (a long drag at 60 Hz is ~1000)
ADD_REACH_PX: Final = 200  # an added piece extends at most this far from the click
ADD_PEAK_FRACTION: Final = 0.5  # an added piece: evidence >= half its peak (half maximum)
ADD_CLICK_SIGMA: Final = 0.5  # peak search: contrast weighted by a Gaussian of radius / 2
ADD_SAME_COLOUR_COS: Final = 0.8  # same dye: contrast directions within ~37 degrees
ADD_MIN_CONTRAST: Final = 6.0  # grey levels: weaker contrast to the background is noise
PARTNER_ROWS: Final = 0.6  # a stereo partner covers the same rows (IoU of the row sets)
PARTNER_SLACK_PX: Final = 2.0  # disparity >= -2 px: a partner is never on the wrong side
PARTNER_CANDIDATES: Final = 50  # pieces looked at (a mask of specks has hundreds)
_MEDIAN_PX: Final = 20  # local background of the contrast cue: median over 20 px (> 3x a thread)
_MEDIAN_STEP: Final = 4  # ... taken at quarter resolution: the background is smooth, 30x faster

Op = Literal["remove", "add", "erase", "paint", "clear", "keep"]
View = Literal["left", "right", "both"]


@dataclass(frozen=True)
class Correction:
    """One user action on one view's mask (see the module docstring).

    ``points``: ((x, y), ...) int pixels of the rectified image: one click, or the points of a
    brush stroke. ``radius``: px, the brush radius (erase, paint) or how far from the click a
    piece is searched (remove, add).
    """

    op: Op
    view: View
    points: tuple[tuple[int, int], ...] = ()
    radius: float = 8.0
    stereo: bool = False
    """remove: the piece's partner in the other view goes too (see :func:`_partner`)."""

    def __post_init__(self) -> None:
        if self.stereo is not False and not (self.stereo is True and self.op == "remove"):
            raise ValueError("stereo (the partner piece in the other view) is for remove only")
        if self.op not in OPS:
            raise ValueError(f"unknown correction {self.op!r} (known: {', '.join(OPS)})")
        if self.view not in VIEWS and not (self.op == "clear" and self.view == "both"):
            raise ValueError(f"view must be left or right, got {self.view!r}")
        if not isinstance(self.radius, int | float) or not math.isfinite(self.radius):
            raise ValueError(f"radius must be a finite number of px, got {self.radius!r}")
        if not 0.5 <= self.radius <= MAX_RADIUS_PX:
            raise ValueError(f"radius must be in [0.5, {MAX_RADIUS_PX:g}] px, got {self.radius:g}")
        pts = self.points
        if not isinstance(pts, tuple) or not all(
            isinstance(p, tuple)
            and len(p) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) for v in p)
            for p in pts
        ):
            raise ValueError("points must be a tuple of (x, y) integer pixels")
        if self.op == "clear":
            if pts:
                raise ValueError("clear takes no points")
        elif not 1 <= len(pts) <= MAX_STROKE_POINTS:
            raise ValueError(f"{self.op} needs 1 to {MAX_STROKE_POINTS} points, got {len(pts)}")
        if self.op in ("remove", "add") and len(pts) != 1:
            raise ValueError(f"{self.op} takes one click point, got {len(pts)}")

    def check_inside(self, shape: tuple[int, int]) -> None:
        """Raise ValueError naming the first point outside an (H, W) image."""
        h, w = shape
        for x, y in self.points:
            if not (0 <= x < w and 0 <= y < h):
                raise ValueError(f"pixel ({x}, {y}) is outside the {w}x{h} {self.view} image")


@dataclass(frozen=True)
class CorrectedPair(LiftedPair):
    """A :class:`LiftedPair` whose masks P_L, P_R (and lifted images) carry the corrections;
    the masks the segmenter gave are kept to show what changed."""

    segmented_L: np.ndarray | None = None
    """(H, W) bool, P_L before the corrections."""
    segmented_R: np.ndarray | None = None
    corrections: tuple[Correction, ...] = ()
    changed_px: tuple[int, ...] = ()
    """Pixels of P each correction changed, in order (0: it found nothing to change)."""
    segment_error: str | None = None
    """Why the segmenter gave no mask (e.g. "no thread found"): the masks are the user's."""

    @property
    def added_L(self) -> np.ndarray:
        return self.P_L & ~self.segmented_L  # type: ignore[operator]

    @property
    def added_R(self) -> np.ndarray:
        return self.P_R & ~self.segmented_R  # type: ignore[operator]

    @property
    def removed_L(self) -> np.ndarray:
        return self.segmented_L & ~self.P_L  # type: ignore[operator]

    @property
    def removed_R(self) -> np.ndarray:
        return self.segmented_R & ~self.P_R  # type: ignore[operator]


def apply_corrections(
    lifted: LiftedPair,
    corrections: tuple[Correction, ...],
    lift_dilate_px: int = 1,
    images: tuple[np.ndarray, np.ndarray] | None = None,
) -> CorrectedPair:
    """The segment stage's result with ``corrections`` applied in order and Eq. (1) redone.

    ``lift_dilate_px`` is the segment stage's (``SegmentationParams.lift_dilate_px``);
    ``images``: the pair's (left, right) (H, W, 3) RGB or (H, W) uint8 images, whose colour
    finds an added piece (default: the grey images). Raises
    ValueError when a point lies outside the image or when the corrections leave a view without
    thread pixels (the message says which view, and that an undo brings it back).
    """
    base = lifted.segmented_L if isinstance(lifted, CorrectedPair) else lifted.P_L
    base_R = lifted.segmented_R if isinstance(lifted, CorrectedPair) else lifted.P_R
    assert base is not None and base_R is not None
    before = (
        lifted.corrections if isinstance(lifted, CorrectedPair) else (),
        lifted.changed_px if isinstance(lifted, CorrectedPair) else (),
    )
    masks = {"left": lifted.P_L.copy(), "right": lifted.P_R.copy()}
    segmented = {"left": base, "right": base_R}
    if images is None:
        images = (lifted.grey_L, lifted.grey_R)
    for name, img in zip(VIEWS, images, strict=True):
        if img.shape[:2] != lifted.P_L.shape:
            raise ValueError(f"{name} image is {img.shape}, the masks {lifted.P_L.shape}")
    evidence = dict(zip(VIEWS, images, strict=True))
    changed = []
    for c in corrections:
        if not isinstance(c, Correction):
            raise ValueError(f"a correction must be a Correction, got {type(c).__name__}")
        c.check_inside(lifted.P_L.shape)
        if c.view == "both":  # clear both views
            changed.append(sum(int(np.count_nonzero(masks[v] != segmented[v])) for v in VIEWS))
            masks = {v: segmented[v].copy() for v in VIEWS}
            continue
        old = masks[c.view]
        new = _apply_one(c, old, segmented[c.view], evidence[c.view])
        changed.append(int(np.count_nonzero(new != old)))
        masks[c.view] = new
        if c.stereo and changed[-1]:
            other = "right" if c.view == "left" else "left"
            partner = _partner(old & ~new, masks[other], look_left=c.view == "left")
            changed[-1] += int(np.count_nonzero(partner))
            masks[other] = masks[other] & ~partner
    error = lifted.segment_error if isinstance(lifted, CorrectedPair) else None
    for view, m in masks.items():
        if not m.any():
            if error is not None:
                raise ValueError(f"{error}; the corrections add no thread pixel in the {view} view")
            raise ValueError(
                f"the corrections leave no thread pixel in the {view} view (undo the last one)"
            )
    base_fields = {f.name: getattr(lifted, f.name) for f in dataclasses.fields(LiftedPair)}
    base_fields.update(
        P_L=masks["left"],
        P_R=masks["right"],
        I_L=lift(lifted.grey_L, masks["left"], lift_dilate_px),
        I_R=lift(lifted.grey_R, masks["right"], lift_dilate_px),
    )
    return CorrectedPair(
        **base_fields,
        segmented_L=base,
        segmented_R=base_R,
        corrections=before[0] + tuple(corrections),
        changed_px=before[1] + tuple(changed),
        segment_error=error,
    )


def unsegmented(pair: StereoPair, error: str) -> CorrectedPair:
    """Empty masks for a pair the segmenter found no thread in (its ``error``), for the user
    to add the thread to by hand."""
    grey_L, grey_R = to_grey(pair.left), to_grey(pair.right)
    empty = np.zeros(pair.shape, bool)
    lifted = np.full(pair.shape, LIFT_VALUE, np.float32)
    return CorrectedPair(
        I_L=lifted, I_R=lifted, P_L=empty, P_R=empty, grey_L=grey_L, grey_R=grey_R,
        background=(float("nan"), float("nan")), method="none", segmented_L=empty,
        segmented_R=empty, segment_error=error,
    )  # fmt: skip


def lift(grey: np.ndarray, P: np.ndarray, dilate_px: int) -> np.ndarray:
    """Eq. (1): the grey image on P (dilated by ``dilate_px``, as the segment stage does),
    ``LIFT_VALUE`` elsewhere; (H, W) float32."""
    if dilate_px > 0:
        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        P = cv2.dilate(P.astype(np.uint8), k).astype(bool)
    return np.where(P, grey, np.float32(LIFT_VALUE)).astype(np.float32)


def _apply_one(
    c: Correction, mask: np.ndarray, segmented: np.ndarray, image: np.ndarray
) -> np.ndarray:
    if c.op == "clear":
        return segmented.copy()
    if c.op in ("erase", "paint", "keep"):
        brush = _stroke(mask.shape, c.points, c.radius)
        return (
            mask & brush if c.op == "keep" else mask & ~brush if c.op == "erase" else mask | brush
        )
    (x, y), r = c.points[0], c.radius
    if c.op == "remove":
        return _remove_piece(mask, x, y, r)
    return mask | _evidence_piece(image, x, y, r)


def _stroke(
    shape: tuple[int, ...], points: tuple[tuple[int, int], ...], radius: float
) -> np.ndarray:
    """(H, W) bool: the pixels within ``radius`` of the polyline through ``points``."""
    line = np.ones(shape[:2], np.uint8)
    pts = np.asarray(points, np.int32).reshape(-1, 1, 2)
    cv2.polylines(line, [pts], False, 0, thickness=1, lineType=cv2.LINE_8)
    for x, y in points[:1]:
        line[y, x] = 0  # a click (one point) is a disc
    return distance_to_zero(line) <= radius


def _window(shape: tuple[int, ...], x: int, y: int, half: int) -> tuple[slice, slice]:
    h, w = shape[:2]
    return slice(max(y - half, 0), min(y + half + 1, h)), slice(
        max(x - half, 0), min(x + half + 1, w)
    )


def _disc_near(shape: tuple[int, ...], x: int, y: int, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows and cols of the pixels within ``r`` of (x, y), nearest first."""
    half = math.ceil(r)
    rows, cols = np.mgrid[_window(shape, x, y, half)]
    d2 = (cols - x) ** 2 + (rows - y) ** 2
    keep = d2 <= r * r
    order = np.argsort(d2[keep], kind="stable")
    return rows[keep][order], cols[keep][order]


def _remove_piece(mask: np.ndarray, x: int, y: int, r: float) -> np.ndarray:
    rows, cols = _disc_near(mask.shape, x, y, r)
    hit = np.flatnonzero(mask[rows, cols])
    if hit.size == 0:
        return mask
    _, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    piece = labels[rows[hit[0]], cols[hit[0]]]
    return mask & (labels != piece)


def _partner(piece: np.ndarray, other: np.ndarray, look_left: bool) -> np.ndarray:
    """(H, W) bool: the piece of the ``other`` view's mask that is the stereo partner of
    ``piece``, or nothing. A partner lies on the same rows (row-set IoU >= ``PARTNER_ROWS``:
    a thread merged with the partner spans other rows and is never taken) at a disparity
    >= 0 (to the left in the right view when ``look_left``); of several, the best row match."""
    rows = np.flatnonzero(piece.any(axis=1))
    if rows.size == 0 or not other.any():
        return np.zeros_like(other)
    n, labels = cv2.connectedComponents(other.astype(np.uint8), connectivity=8)
    lo, hi = rows[0], rows[-1] + 1
    band = labels[lo:hi]
    cands = np.unique(band[band > 0])
    best, best_iou = 0, PARTNER_ROWS
    mean_col = _row_mean_cols(piece)
    for k in cands[:PARTNER_CANDIDATES]:  # the pieces crossing the clicked piece's rows: a few
        cand = labels == k
        cand_rows = np.flatnonzero(cand.any(axis=1))
        iou = np.intersect1d(rows, cand_rows).size / np.union1d(rows, cand_rows).size
        if iou < best_iou:
            continue
        common = np.intersect1d(rows, cand_rows)
        d = np.median(mean_col[common] - _row_mean_cols(cand)[common])  # disparity x_L - x_R
        if (d if look_left else -d) >= -PARTNER_SLACK_PX:
            best, best_iou = int(k), iou
    return labels == best if best else np.zeros_like(other)


def _row_mean_cols(mask: np.ndarray) -> np.ndarray:
    """(H,) mean column of the mask pixels of each row (NaN for an empty row)."""
    cols = np.arange(mask.shape[1], dtype=np.float64)
    count = mask.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (mask * cols).sum(axis=1) / count


def _evidence_piece(image: np.ndarray, x: int, y: int, r: float) -> np.ndarray:
    """(H, W) bool: the thread piece at the click (see the module docstring); empty when the
    click has no evidence.

    Evidence is the colour contrast c = I - median(I) (per channel, over ``_MEDIAN_PX``): the
    peak is the pixel of largest |c| within ``r`` of the click, weighted by a Gaussian of the
    distance to the click (sigma ``r / 2``); a pixel belongs to its piece
    when its contrast projects onto the peak's to at least half of |c_peak| (half maximum) and
    points the same way (cosine >= ``ADD_SAME_COLOUR_COS``: the thread's dye, not a vessel's).
    """
    out = np.zeros(image.shape[:2], bool)
    win = _window(image.shape, x, y, ADD_REACH_PX)
    cx, cy = x - win[1].start, y - win[0].start
    u8 = np.ascontiguousarray(np.clip(image[win], 0, 255).astype(np.uint8))
    c = u8.astype(np.float32) - _background(u8)
    c = c.reshape(c.shape[0], c.shape[1], -1)
    norm = np.sqrt(np.einsum("ijk,ijk->ij", c, c))
    rows, cols = _disc_near(norm.shape, cx, cy, r)
    # the click is the user's cue: strong contrast a few px away (a glint) weighs less
    d2 = (rows - cy) ** 2 + (cols - cx) ** 2
    k = int(np.argmax(norm[rows, cols] * np.exp(-d2 / (2.0 * (ADD_CLICK_SIGMA * r) ** 2))))
    peak_row, peak_col = rows[k], cols[k]
    peak = float(norm[peak_row, peak_col])
    if peak < ADD_MIN_CONTRAST:
        return out
    unit = c[peak_row, peak_col] / peak
    along = c @ unit  # projection on the peak's contrast
    region = (along >= ADD_PEAK_FRACTION * peak) & (along >= ADD_SAME_COLOUR_COS * norm)
    _, labels = cv2.connectedComponents(region.astype(np.uint8), connectivity=8)
    out[win] = labels == labels[peak_row, peak_col]
    return out


def _background(u8: np.ndarray) -> np.ndarray:
    """(h, w[, C]) float32 local background: the median over ``_MEDIAN_PX`` px, computed on the
    ``_MEDIAN_STEP``-times smaller image (a thread a few px wide is a minority of every
    window there too) and interpolated back."""
    h, w = u8.shape[:2]
    small = cv2.resize(
        u8, (max(w // _MEDIAN_STEP, 1), max(h // _MEDIAN_STEP, 1)), interpolation=cv2.INTER_AREA
    )
    k = max(_MEDIAN_PX // _MEDIAN_STEP, 1) | 1  # odd kernel
    bg = cv2.resize(cv2.medianBlur(small, k), (w, h), interpolation=cv2.INTER_LINEAR)
    return bg.astype(np.float32).reshape(u8.shape)
