"""Input pair, segmentation and lifting, Eq. (1).

The paper leaves segmentation open ("the most modern technique may be used") and uses colour
thresholds: on its Blender frames greyscale values >= 200 are background. We estimate the
background level B of each image as the mode of its grey histogram and call a pixel thread when
it is darker than ``B - seg_delta``. With ``seg_delta = 6`` this reproduces the paper's ``< 200``
on the Blender frames (B = 206) and keeps every hand-segmented pixel of the real frames
(B = 255), with no per-set flag. Masks given by the user replace the thresholding.

Raw frames (tissue, vessels, instruments, uneven light; no mask) need more: ``method="raw"``
(:func:`segment_raw`) finds the thread as the most salient long thin line of one dye with a
partner in the other view, and gives a per-pixel thread score. ``method="auto"`` (default)
thresholds when the background is flat (>= ``flat_share`` of the pixels within 1 grey level of
B: the paper's Blender and hand-segmented frames; parts off the background level wider than
20 px, an instrument, are dropped) and segments raw otherwise (:mod:`core.segment_raw`). A raw
frame in which no piece qualifies raises ``ValueError("no thread found ...")``: never a curve.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, Literal

import cv2
import numpy as np

from threadrecon.core.compiled import kernel
from threadrecon.core.instrument import drop_attached
from threadrecon.core.lazy import Deferred, LazyField
from threadrecon.core.params import Params, param
from threadrecon.core.ridge_kernel import small_components
from threadrecon.core.segment_raw import drop_specks, segment_raw

LIFT_VALUE = 255.0  # Eq. (1): unsegmented pixels are set to 255


@dataclass(frozen=True)
class StereoPair:
    """A rectified stereo pair.

    ``left``, ``right``: (H, W) greyscale or (H, W, 3) RGB images, uint8.
    ``mask_left``, ``mask_right``: optional (H, W) bool thread masks (P_L, P_R).
    """

    left: np.ndarray
    right: np.ndarray
    mask_left: np.ndarray | None = None
    mask_right: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("left", "right"):
            a = getattr(self, name)
            if (
                not isinstance(a, np.ndarray)
                or a.ndim not in (2, 3)
                or (a.ndim == 3 and a.shape[2] not in (1, 3, 4))
            ):
                shape = getattr(a, "shape", type(a).__name__)
                raise ValueError(f"{name} image must be (H, W) or (H, W, 3), got {shape}")
            if a.shape[0] < 8 or a.shape[1] < 8:
                raise ValueError(f"{name} image is too small: {a.shape}")
        if self.left.shape[:2] != self.right.shape[:2]:
            raise ValueError(
                f"left and right images differ in size: {self.left.shape[:2]} vs {self.right.shape[:2]}"
            )
        if (self.mask_left is None) != (self.mask_right is None):
            raise ValueError("give both masks or neither")
        for name in ("mask_left", "mask_right"):
            m = getattr(self, name)
            if m is not None and m.shape[:2] != self.left.shape[:2]:
                raise ValueError(f"{name} must be {self.left.shape[:2]}, got {m.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.left.shape[0]), int(self.left.shape[1]))


def split_side_by_side(image: np.ndarray, what: str = "image") -> tuple[np.ndarray, np.ndarray]:
    """Split a side-by-side composite (left half, right half) into two views; ``what`` names it
    in the error ("image", "mask")."""
    if image.ndim not in (2, 3) or image.shape[1] % 2:
        raise ValueError(f"side-by-side {what} must have an even width, got shape {image.shape}")
    w = image.shape[1] // 2
    return image[:, :w], image[:, w:]


@dataclass(frozen=True)
class SegmentationParams(Params):
    seg_delta: float = param(
        6.0,
        lo=0,
        hi=255,
        unit="grey levels",
        symbol="delta",
        slider=(0, 60, 1),
        label="seg threshold δ",
    )
    """Grey levels below the background level B that count as thread."""
    background: float | None = param(None, lo=0, hi=255, unit="grey levels")
    """Fixed background level B (0-255); None estimates it per image (histogram mode)."""
    min_component_px: int = param(
        4, lo=0, hi=10000, unit="px", slider=(0, 100, 1), label="min component px"
    )
    """Connected thread components smaller than this (px) are dropped as specks."""
    lift_dilate_px: int = param(
        1, lo=0, hi=10, unit="px", slider=(0, 4, 1), label="lift dilation px"
    )
    """Lift (Eq. (1)) outside P dilated by this many px; 0 is the paper's exact Eq. (1).

    Deviation: a thread 1-3 px wide crosses the threshold at different pixels in the two views,
    and lifting those to 255 dominates E(d); keeping the true intensities 1 px around the thread
    raised reliable pixels by 10-60 % and halved the p90 depth error on the Blender frames."""
    method: Literal["auto", "raw", "threshold"] = param(
        "auto",
        label="segmentation method",
        doc="threshold: grey threshold B - seg_delta (paper, pre-segmented frames); raw: thread "
        "found on raw frames by a multi-scale colour ridge, hysteresis, shape and stereo "
        "consistency; auto: threshold when the background is flat (flat_share), without the "
        "parts wider than 20 px off the background level (an instrument), else raw.",
    )
    flat_share: float = param(
        0.9,
        lo=0.0,
        hi=1.0,
        label="auto: flat share",
        doc="auto uses the threshold when at least this share of pixels lies within 1 grey "
        "level of the background level B (a flat or pre-segmented background).",
        slider=(0.5, 1.0, 0.01),
    )
    shading_gaps: bool = param(
        True,
        label="auto: close shading gaps only",
        doc="auto: the gaps (<= 4 px) closed before an instrument's wide parts are measured "
        "are only those between a darker and a lighter pixel (a shading crossing the "
        "background level inside one object), not between two darker ones (a thread beside a "
        "shaft, kept). Off: every gap is closed (a thread along a shaft's edge is taken as "
        "the shaft's).",
    )
    split_wide: bool = param(
        True,
        label="raw: cut wide parts",
        doc="raw: a piece wider than a thread (a disc over 12 px across fits in it) loses its "
        "wide part (and a band around it) and its thin rest is judged piece by piece: a thread "
        "merged with a fibre or vessel it runs beside, or crossing itself at a shallow angle, "
        "is wide there only. Off: the whole piece is dropped (deviation 40).",
    )
    prefer_floating: bool = param(
        True,
        label="raw: prefer a floating piece",
        doc="raw: when the most salient piece that is no mark on the tissue is one the surface "
        "test cannot judge (every vote undecided: dark or untextured tissue beside it), a piece "
        "further down the rank, at least keep_ratio as salient, that the test finds in front of "
        "the tissue is chosen instead (at most two more tested): a thread seen floating over "
        "an undecided fibre. Off: the undecided piece is chosen (deviation 49).",
    )
    tool_rim_px: int = param(
        3,
        lo=0,
        hi=64,
        unit="px",
        label="raw: instrument rim",
        doc="raw: the candidate pixels an instrument takes are those of its coarse mask "
        "(found at quarter resolution and grown by ~8 px) within this distance of one of its "
        "unsaturated pixels (its grey body and its blurred edge); a coloured line farther out "
        "(a thread running along a shaft) stays a candidate; the thread's mask leaves that "
        "body and rim out, and the local background the instrument. 0: every candidate in the "
        "coarse mask is the instrument's, the background as before (deviation 50).",
        slider=(0, 16, 1),
    )
    first_marks: bool = param(
        True,
        label="raw: red pass knows the marks",
        doc="raw: the red pass (a blood-like thread among vessels of its hue) reads the "
        "tissue's disparity beside a blood-like piece from the marks on the tissue it found "
        "itself and from those the first pass found (fibres, non-blood lines moving with the "
        "tissue): a vessel the block-wise surface test leaves open, at the disparity of the "
        "tissue's marks beside it, is a mark too, not a reason to give the pass up. Off: the "
        "red pass's own marks only (deviation 53).",
    )
    contradicted_any: bool = param(
        True,
        label="raw: any tissue reading contradicts",
        doc="raw: a blood-like piece the block-wise surface test votes in front of the tissue is "
        "contradicted (a vessel) when its own disparity is not above the tissue's by either "
        "reading that resolves, its block's background or the nearest mark on the tissue. "
        "Uneven light, fixed in the image, biases a block's background towards disparity 0 "
        "while the marks (vessels, fibres) keep the tissue's own. Off: the first reading that "
        "resolves (the block's background) decides alone (deviation 58).",
    )
    tissue_surface: bool = param(
        False,
        label="raw: tissue-only surface test",
        doc="raw: the surface test (does a line move with the tissue beside it?) reads the "
        "tissue's disparity from background pixels off the instrument found in the view: a "
        "shaft is no tissue, and a thread beside it at its depth is not a mark on the tissue "
        "(nor a mark beside it a floating line). Off: the instrument's pixels are background "
        "samples too (deviation 56).",
    )
    thread_through: bool = param(
        True,
        label="raw: thread through a near block",
        doc="raw: of a kept piece that moves with the tissue in part (a mark merged with the "
        "thread), a block voted 'on the surface' keeps its pixels when their own disparity is "
        "nearer that of the piece's floating part in a block beside it than the tissue's "
        "there: the thread goes on, nearer the tissue than the block test resolves (~3 px). "
        "Off: every such block's pixels are cut as the mark's (deviation 60).",
    )
    thread_depth_join: bool = param(
        True,
        label="raw: joining pieces not behind the thread",
        doc="raw: a piece of the thread's dye that the surface test does not see floating "
        "(undecided, or on the surface in part) does not join the chosen one when its nearest "
        "block's own disparity lies behind the thread's farthest block by more than 1.5 px "
        "plus the thread's depth slope (0.1 px a px) times its gap to the thread, nor when it "
        "lies nearer (by that slope) the depth of such a piece: a light fibre on the tissue "
        "beside a white thread, left open by the surface test, lies behind the whole thread. "
        "Pieces within 12 px of the thread (split from it by a crossing strand), across the "
        "instrument from it, or without a disparity of their own join as before. Off: every "
        "piece of the dye joins (deviation 62).",
    )
    touch_at_tissue: bool = param(
        True,
        label="raw: touching pieces at the tissue's depth",
        doc="raw: a piece of the thread's dye within 12 px of the thread (which deviation 62 "
        "lets join unjudged: a loop's strand past a crossing) does not join when its own "
        "disparity is the tissue's (the background of its block or of one of the eight blocks "
        "around it, within 1.5 px) and lies behind the thread's farthest block by more than "
        "1.5 px plus 0.1 px a px of its gap: a light fibre on the tissue that the thread "
        "crosses. Off: every such piece joins (deviation 65).",
    )
    cut_at_tissue: bool = param(
        True,
        label="raw: a chosen piece's remnant at the tissue's depth",
        doc="raw: where the chosen piece loses a part that moves with the tissue (a fibre "
        "merged with the thread), a remnant of it cut off from the thread by that cut, "
        "nowhere seen in front of the tissue and of at least min_length_px pixels, is judged "
        "as a piece touching the thread (or goes with a remnant so judged nearer it): it is "
        "dropped when its own disparity is the tissue's beside it (within 1.5 px) and lies "
        "behind the thread's farthest block by more than 1.5 px plus 0.1 px a px of its gap "
        "(the fibre's part left open by the surface test). Off: the remnant stays "
        "(deviation 72).",
    )
    red_part_floats: bool = param(
        True,
        label="raw: red piece floating in part",
        doc="raw: in the red pass (a blood-like thread among vessels of its hue), a blood-like "
        "piece that the surface test sees in front of the tissue over as many pixels as a "
        "piece must hold (min_length_px at its width) and over more of it than on the "
        "surface, while another part of it moves with the tissue, is a thread merged with "
        "the vessels it crosses: it is judged by that "
        "floating part (its own disparity above the tissue's, as any floating blood-like "
        "piece), and the part on the surface is cut from it. Off: such a piece, neither "
        "floating nor a mark as a whole, is taken for a vessel and ends the red pass "
        "(deviation 63).",
    )
    blood_speck_px: int = param(
        30,
        lo=0,
        hi=10_000,
        unit="px",
        label="raw: least vessel",
        doc="raw: blood-like pixels (darker and redder than the tissue around) are set aside as "
        "vessels only when the view holds an 8-connected group of at least this many of them "
        "(a vessel is a line; the default is min_length_px's): where all are specks, they are "
        "pixel noise at a thread's faint rim and tip (a noisy grey frame held ~500 in specks "
        "of at most 5), and setting them aside cut the thread's tip off its piece. 0: every "
        "blood-like pixel is set aside (deviation 70).",
        slider=(0, 200, 1),
    )
    local_join: bool = param(
        True,
        label="raw: a red fragment read near the thread",
        doc="raw: in the red pass, an undecided piece of the thread's dye near the thread whose "
        "pixels taken together match no single disparity (a long stretch whose depth changes "
        "along it) is read on its pixels within 32 px (else 64 px) of where it comes nearest "
        "the thread: it joins at the thread's disparity there (the depth slope counted over "
        "the extra reach) and off the tissue's. A piece whose disparity is known where the "
        "thread's is not (a stretch of low contrast) joins when it lies above the tissue's "
        "by more than 3 px by each reading. Off: such pieces do not join (deviation 68).",
    )
    rim_blood: bool = param(
        False,
        label="raw: vessel pixels at the thread's rim",
        doc="raw: off a thread chosen without the blood-like pixels, the mask grown around it "
        "(step 6) takes blood-like pixels too (darker and redder than the tissue around, the "
        "test of step 2 on every grown pixel): a vessel crossing the thread then leaves a "
        "stub of its own on the thread's mask, which stereo matches at the tissue's depth and "
        "carries along a stretch of thread running along the rows. Off (default): a part of "
        "those pixels joined to a vessel (a group of >= 10 blood-like candidates), of >= 8 px "
        "and reaching the band's last ring off the thread, is not grown into the mask "
        "(deviation 78).",
    )
    ridge_hi: float = param(
        6.0,
        lo=0.0,
        hi=1000.0,
        label="raw: seed contrast",
        doc="Seeds of the hysteresis: line response above this many times the image's robust "
        "line-response level (median + MAD scale).",
        slider=(2.0, 20.0, 0.5),
    )
    ridge_lo: float = param(
        3.0,
        lo=0.0,
        hi=1000.0,
        label="raw: grow contrast",
        doc="Pixels above this many robust levels join a seed's piece (hysteresis).",
        slider=(1.0, 10.0, 0.5),
    )
    min_length_px: float = param(
        30.0,
        lo=0.0,
        hi=100_000.0,
        unit="px",
        label="raw: min piece length",
        doc="Pieces shorter than this (skeleton length, px) are not thread.",
        slider=(5.0, 200.0, 1.0),
    )
    keep_ratio: float = param(
        0.45,
        lo=0.0,
        hi=1.0,
        label="raw: keep ratio",
        doc="A piece is kept when its mean line response is at least this fraction of the "
        "strongest piece's (vessels and fibres fainter than the thread are dropped).",
        slider=(0.0, 1.0, 0.05),
    )
    blood_rg: float = param(
        0.1,
        lo=0.0,
        hi=5.0,
        label="raw: vessel redness",
        doc="A dark piece whose R/G ratio exceeds the tissue around it by more than this "
        "(natural log; 0.1 ~ 10 %) looks like blood: a vessel.",
        slider=(0.0, 1.0, 0.01),
    )
    max_disparity_px: int = param(
        80,
        lo=0,
        hi=4096,
        unit="px",
        label="raw: stereo partner range",
        doc="A piece must have a partner on the same rows of the other view within this "
        "disparity (use stereo.alpha).",
        slider=(0, 400, 1),
    )


@dataclass(frozen=True)
class LiftedPair:
    """Eq. (1): ``I_L^lift``, ``I_R^lift`` as (H, W) float32, and the masks P_L, P_R (H, W) bool."""

    I_L: np.ndarray
    I_R: np.ndarray
    P_L: np.ndarray
    P_R: np.ndarray
    grey_L: np.ndarray
    grey_R: np.ndarray
    background: tuple[float, float]
    """Background level B of the left and right image (grey levels)."""
    score_L: np.ndarray | None = LazyField(None)  # type: ignore[assignment]
    """(H, W) float32 per-pixel thread score in [0, 1] of the left view (0.5 ~ the decision
    level); None when the masks were given. The threshold path computes it on first read (no
    stage reads it: a LUT and 1.2 MB of fresh memory a 640x480 view, when the debugger
    shows it)."""
    score_R: np.ndarray | None = LazyField(None)  # type: ignore[assignment]
    """Same for the right view."""
    method: str = "mask"
    """How P was obtained: "mask" (given), "threshold" or "raw"."""


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 greyscale of an RGB or grey uint8 image."""
    grey8 = _grey8(image)
    if grey8 is not None:
        return grey8.astype(np.float32)
    if image.ndim == 2:
        return image.astype(np.float32)
    if image.shape[2] == 1:
        return image[:, :, 0].astype(np.float32)
    return cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2GRAY).astype(
        np.float32
    )


def _grey8(image: np.ndarray) -> np.ndarray | None:
    """(H, W) uint8 greyscale of a uint8 image (the grey levels of :func:`to_grey`, before their
    conversion to float32); None for another dtype."""
    if image.dtype != np.uint8:
        return None
    if image.ndim == 2:
        return np.ascontiguousarray(image)
    if image.shape[2] == 1:
        return np.ascontiguousarray(image[:, :, 0])
    # cv2 reads an (H, W, 3) view with a row stride (a half of a side-by-side pair) in place:
    # no copy of the colour image first
    rgb = image if image.shape[2] == 3 else np.ascontiguousarray(image[:, :, :3])
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


class _Grey:
    """One view's grey levels: ``f32`` (H, W) float32 and, for a uint8 image, ``u8`` (H, W)
    uint8 holding the same values. A pixelwise function of a uint8 image takes 256 values:
    :meth:`map` evaluates it once per level and looks the image up in that table (cv2.LUT,
    ~0.1 ms at 640x480 against 0.3-1.5 ms for float32 arithmetic), so its result is the
    function's own, value for value."""

    def __init__(self, image: np.ndarray) -> None:
        self.u8 = _grey8(image)
        self._hist: np.ndarray | None = None
        self.rows: tuple[np.ndarray, np.ndarray] | None = None
        """(H,) uint8 least and greatest level of each row (uint8 views)."""
        self.cols: tuple[np.ndarray, np.ndarray] | None = None
        """(W,) uint8 least and greatest level of each column (uint8 views)."""
        if self.u8 is None:
            self.f32 = to_grey(image)
        else:  # one pass: the float32 copy, the histogram and the rows' and columns' ranges
            self.f32, self._hist, rmin, rmax, cmin, cmax = _scan_kernel(self.u8)
            self.rows, self.cols = (rmin, rmax), (cmin, cmax)

    def map(self, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """``fn(f32)`` for a pixelwise ``fn`` returning float32 or bool."""
        if self.u8 is None:
            return fn(self.f32)
        table = np.asarray(fn(_LEVELS))
        if table.dtype == bool:
            return cv2.LUT(self.u8, table.view(np.uint8)).view(bool)
        return cv2.LUT(self.u8, table.astype(np.float32, copy=False))

    def histogram(self) -> np.ndarray:
        """(256,) int64 pixel counts of the grey levels 0..255 (values clipped to 0-255 and
        truncated to integers, as a uint8 conversion does)."""
        if self._hist is not None:
            return self._hist
        g = self.u8 if self.u8 is not None else np.clip(self.f32, 0, 255).astype(np.uint8)
        return _histogram_kernel(np.ascontiguousarray(g))

    def box_of_levels(self, table: np.ndarray) -> tuple[int, int, int, int] | None:
        """``cv2.boundingRect(cv2.LUT(u8, table))`` as (x, y, w, h) without the lookup of the
        image, for a (256,) uint8 ``table`` whose zero levels form one run (else None: the
        caller looks the image up): a row or column holds a nonzero entry iff its least or
        greatest level does (its levels lie between the two)."""
        if self.rows is None or self.cols is None:
            return None
        zero = np.flatnonzero(table == 0)
        if zero.size and zero[-1] - zero[0] + 1 != zero.size:
            return None
        hit_r = (table[self.rows[0]] != 0) | (table[self.rows[1]] != 0)
        ys = np.flatnonzero(hit_r)
        if not ys.size:
            return (0, 0, 0, 0)
        xs = np.flatnonzero((table[self.cols[0]] != 0) | (table[self.cols[1]] != 0))
        return (int(xs[0]), int(ys[0]), int(xs[-1] - xs[0] + 1), int(ys[-1] - ys[0] + 1))


_LEVELS: Final = np.arange(256, dtype=np.float32)  # every grey level of a uint8 image


def segment(pair: StereoPair, p: SegmentationParams = SegmentationParams()) -> LiftedPair:
    """Segment (unless masks are given) and lift the pair, Eq. (1).

    Raises ``ValueError("no thread found ...")`` when the raw method finds no thread piece, and
    ``ValueError("empty segmentation ...")`` when the threshold leaves a view empty.
    """
    if p.seg_delta < 0:
        raise ValueError(f"seg_delta must be >= 0, got {p.seg_delta}")
    if p.lift_dilate_px < 0:
        raise ValueError(f"lift_dilate_px must be >= 0, got {p.lift_dilate_px}")
    Params._check(p)  # type: ignore[arg-type]  # declared ranges of every field
    views = (_Grey(pair.left), _Grey(pair.right))
    hists = [v.histogram() for v in views]
    bg = (_background_level(hists[0], p), _background_level(hists[1], p))
    score_L: np.ndarray | Deferred | None = None
    score_R: np.ndarray | Deferred | None = None
    box_L = box_R = None  # boxes known to hold P_L, P_R (else their bounding boxes)
    if pair.mask_left is not None and pair.mask_right is not None:
        P_L, P_R = pair.mask_left.astype(bool), pair.mask_right.astype(bool)
        method = "mask"
    else:
        method = p.method
        if method == "auto":
            flat = min(
                _flat_share(hists[0], views[0], bg[0]), _flat_share(hists[1], views[1], bg[1])
            )
            if flat < p.flat_share:  # an instrument may fill more than 1 - flat_share of a view
                flat = min(
                    _flat_share_off_tools(h, v, b, p)
                    for h, v, b in zip(hists, views, bg, strict=True)
                )
            method = "threshold" if flat >= p.flat_share else "raw"
        if method == "threshold":
            (P_L, box_L), (P_R, box_R) = (
                _threshold(v, b, p) for v, b in zip(views, bg, strict=True)
            )
            score_L, score_R = (  # read by no stage: computed when read (core.lazy)
                Deferred(v.map, functools.partial(_threshold_score, level=b, delta=p.seg_delta))
                for v, b in zip(views, bg, strict=True)
            )
        else:
            # (read by no stage, the scores are computed when read; the surface test's grey
            # levels are the views' own, as :func:`to_grey` gives them for uint8 views)
            uint8 = pair.left.dtype == np.uint8 and pair.right.dtype == np.uint8
            greys = (views[0].f32, views[1].f32) if uint8 else None
            P_L, P_R, score_L, score_R = segment_raw(
                pair.left, pair.right, p, greys=greys, defer_score=True
            )
    for side, P in (("left", P_L), ("right", P_R)):
        if not P.any():  # the raw method's cleaning can leave a view empty: no thread there
            what = "no thread found" if method == "raw" else "empty segmentation"
            raise ValueError(f"{what}: no thread pixel in the {side} image")
    I_L = _lift(views[0].f32, P_L, p.lift_dilate_px, box_L)
    I_R = _lift(views[1].f32, P_R, p.lift_dilate_px, box_R)
    return LiftedPair(
        I_L=I_L,
        I_R=I_R,
        P_L=P_L,
        P_R=P_R,
        grey_L=views[0].f32,
        grey_R=views[1].f32,
        background=bg,
        score_L=score_L,
        score_R=score_R,
        method=method,
    )


def _threshold(
    view: _Grey, level: float, p: SegmentationParams
) -> tuple[np.ndarray, tuple[slice, slice] | None]:
    """P of one view: darker than B - delta; with ``method="auto"`` without the wide parts
    (:func:`_drop_wide`); components under ``min_component_px`` dropped. Returns P and a box
    (row and column slices) that holds it (None: P is empty). Past the threshold itself, the
    work is on the bounding box of what it marks."""
    threshold = level - p.seg_delta
    if p.method == "auto" and view.u8 is not None:
        return _threshold_auto8(view, level, p)
    if p.method != "auto" and view.u8 is not None:  # the lookup on P's box only (exact)
        table = np.less(_LEVELS, threshold).view(np.uint8)
        rect = view.box_of_levels(table)
        if rect is not None:
            out = np.zeros(view.u8.shape, bool)
            x, y, w, h = rect
            if w == 0:
                return out, None
            box = (slice(y, y + h), slice(x, x + w))
            out[box] = drop_specks(cv2.LUT(view.u8[box], table).view(bool), p.min_component_px)
            return out, box
    P = view.map(lambda g: g < threshold)
    if p.method == "auto":  # an instrument over a flat background is no thread
        P = _drop_wide(P, view, level, p.seg_delta, p.shading_gaps)
    box = _box(P, 0)
    if box is None:
        return P, None
    out = np.zeros_like(P)
    out[box] = drop_specks(np.ascontiguousarray(P[box]), p.min_component_px)
    return out, box


def _threshold_auto8(
    view: _Grey, level: float, p: SegmentationParams
) -> tuple[np.ndarray, tuple[slice, slice] | None]:
    """:func:`_threshold` of ``method="auto"`` for a uint8 view, the same P from one table
    lookup: bit 0 thread (below B - delta), bit 1 off the background level (what
    :func:`_drop_wide` reads), looked up on the box of the marked pixels only (found from the
    rows' and columns' level ranges, :meth:`_Grey.box_of_levels`). Everything else works on
    the bounding box of the marked pixels grown by _CLOSE_MARGIN, which holds P and the box :func:`_drop_wide` would take (a larger
    box changes no value there: see it)."""
    u8 = view.u8
    thread = np.less(_LEVELS, level - p.seg_delta)  # the table of view.map(g < B - delta)
    table = (thread | (_off_level(_LEVELS, level, p.seg_delta) << 1)).astype(np.uint8)
    rect = view.box_of_levels(table)  # the box of the marked pixels, without a lookup
    codes = None
    if rect is None:
        codes = cv2.LUT(u8, table)
        rect = cv2.boundingRect(codes)
    x, y, w, h = rect
    out = np.zeros(u8.shape, bool)
    if w == 0:
        return out, None
    H, W = u8.shape
    m = _CLOSE_MARGIN
    y0, y1, x0, x1 = max(y - m, 0), min(y + h + m, H), max(x - m, 0), min(x + w + m, W)
    # the lookup on the box only: the same codes there
    cb = codes[y0:y1, x0:x1] if codes is not None else cv2.LUT(u8[y0:y1, x0:x1], table)
    P = cv2.bitwise_and(cb, 1)
    dark8 = cv2.compare(P, 0, cv2.CMP_GT) if p.shading_gaps else None  # 255 below B - delta
    parts = _wide_parts(cv2.compare(cb, 2, cv2.CMP_GE), dark8)  # off8: 255 off the level
    if parts is not None:  # the shaft, then the jaws attached to it (wider than the thread)
        wide, body = parts
        P = drop_attached(P.view(bool) & ~wide, wide, body).view(np.uint8)
    bx, by, bw, bh = cv2.boundingRect(P)
    if bw == 0:
        return out, None
    box = (slice(y0 + by, y0 + by + bh), slice(x0 + bx, x0 + bx + bw))
    Pb = P[by : by + bh, bx : bx + bw]  # P's own bounding box: drop_specks' box, no copy
    if p.min_component_px > 1:  # :func:`drop_specks` in place (P is this call's own array)
        small_components(Pb, p.min_component_px, True)
    out[box] = Pb.view(bool)
    return out, box


def _box(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """Row and column slices of the bounding box of ``mask`` (H, W) bool grown by ``margin``
    px and clipped to the image; None for an empty mask."""
    x, y, w, h = cv2.boundingRect(np.ascontiguousarray(mask).view(np.uint8))
    if w == 0:
        return None
    H, W = mask.shape
    return (
        slice(max(y - margin, 0), min(y + h + margin, H)),
        slice(max(x - margin, 0), min(x + w + margin, W)),
    )


def _flat_share(hist: np.ndarray, view: _Grey, level: float) -> float:
    """Share of pixels within 1 grey level of ``level`` (``hist``: the view's histogram)."""
    if view.u8 is None:
        near = cv2.compare(cv2.absdiff(view.f32, float(level)), 1.0, cv2.CMP_LE)
        return cv2.countNonZero(near) / view.f32.size
    near = cv2.compare(cv2.absdiff(_LEVELS, float(level)), 1.0, cv2.CMP_LE).ravel() > 0
    return int(hist[near].sum()) / view.f32.size


def _flat_share_off_tools(
    hist: np.ndarray, view: _Grey, level: float, p: SegmentationParams
) -> float:
    """Share of the pixels within 1 grey level of ``level`` among those off the instrument
    (:func:`_wide_parts` of the pixels off the level by more than ``seg_delta``): a flat
    background with a large shaft in front of it is still flat where it is seen, and the
    threshold path drops the shaft (``hist``: the view's histogram). 0 when even with every
    off-level pixel taken for the instrument the share stays below ``flat_share`` (tissue:
    the wide parts are not looked for)."""
    n = view.f32.size
    near = _flat_share(hist, view, level) * n
    if view.u8 is None:
        off = _off_level(view.f32, level, p.seg_delta).reshape(view.f32.shape)
        n_off = cv2.countNonZero(off.view(np.uint8))
    else:  # counted on the histogram: the off-level pixels are those of the off levels
        off_levels = _off_level(_LEVELS, level, p.seg_delta)
        n_off = int(hist[off_levels].sum())
    if near < p.flat_share * max(n - n_off, 1):  # an upper bound of the share: not flat
        return 0.0
    if view.u8 is not None:  # (the image looked up only where the bound leaves it open)
        off = cv2.LUT(view.u8, off_levels.view(np.uint8)).view(bool)
    box = _box(off, _CLOSE_MARGIN)
    if box is None:
        return near / n
    parts = _wide_parts(
        np.ascontiguousarray(off[box]).view(np.uint8) * np.uint8(255),
        _dark8(view.f32[box], level, p.seg_delta) if p.shading_gaps else None,
    )
    if parts is None:
        return near / n
    wide = parts[0].view(np.uint8)
    g = view.f32[box]
    near_wide = cv2.countNonZero(cv2.compare(cv2.absdiff(g, float(level)), 1.0, cv2.CMP_LE) & wide)
    return (near - near_wide) / max(n - cv2.countNonZero(wide), 1)


_WIDE_PX: Final = 10  # half-width of an instrument, at least; the raw method's thread <= 6 px
_WIDE_RIM_PX: Final = 2  # a wide part's anti-aliased rim (1 px) and blur, px
_GAP_DISC: Final = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))  # gaps <= 4 px closed
# The largest square inside the disc of radius _WIDE_PX (half-side 7 for cv2's 21 px ellipse):
# where no such square fits, no disc fits either, and a square's erosion is separable (10x
# cheaper than the disc's). tests/core/test_segmentation.py checks the inclusion.
_INSCRIBED_SQUARE: Final = np.ones((15, 15), np.uint8)
# The closing (dilation then erosion by _GAP_DISC) of a box grown by this margin equals the
# whole image's on the box: pixels beyond 2 px of the marked ones stay 0 either way.
_CLOSE_MARGIN: Final = 4


def _drop_wide(
    mask: np.ndarray, view: _Grey, level: float, delta: float, shading_gaps: bool = True
) -> np.ndarray:
    """``mask`` without the wide parts of a flat image: pixels off the background level (darker
    or lighter by more than ``delta``, gaps up to 4 px closed) that hold a disc of radius
    _WIDE_PX (an instrument shaft with its dark and bright bands; a thread, or two threads
    side by side, up to 20 px wide hold none),
    and _WIDE_RIM_PX around them. A thread passing under an instrument keeps both its ends.
    The paper's frames (thread half-widths <= 5.1 px) are unchanged.

    Computed on the bounding box of the off-level pixels grown by _CLOSE_MARGIN (``mask`` lies
    inside it): erosions there see the same pixels as on the whole image, and the dilation of
    the core is only read on ``mask``."""

    if view.u8 is None:
        off = _off_level(view.f32, level, delta).reshape(view.f32.shape)
    else:
        off = cv2.LUT(view.u8, _off_level(_LEVELS, level, delta).view(np.uint8)).view(bool)
    box = _box(off, _CLOSE_MARGIN)
    if box is None:
        return mask
    parts = _wide_parts(
        np.ascontiguousarray(off[box]).view(np.uint8) * np.uint8(255),
        _dark8(view.f32[box], level, delta) if shading_gaps else None,
    )
    if parts is None:
        return mask
    wide, body = parts
    out = mask.copy()
    out[box] = drop_attached(out[box] & ~wide, wide, body)  # jaws: attached, wider than thread
    return out


def _off_level(g: np.ndarray, level: float, delta: float) -> np.ndarray:
    """Flat bool: grey levels ``g`` off the background level by more than ``delta``."""
    return cv2.compare(cv2.absdiff(g, float(level)), float(delta), cv2.CMP_GT).ravel() > 0


def _dark8(g: np.ndarray, level: float, delta: float) -> np.ndarray:
    """uint8, 255 where grey levels ``g`` lie below ``level - delta`` (the thread's side)."""
    return cv2.compare(g, float(level) - float(delta), cv2.CMP_LT)


def _wide_parts(
    off8: np.ndarray, dark8: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """(h, w) bool: the wide parts (and their rim) of the off-level pixels ``off8`` (uint8, 255
    off the level) of a box (:func:`_drop_wide`), and those pixels with gaps up to 4 px closed
    (the body that :func:`core.instrument.drop_attached` measures widths on); None when there
    is no wide part. With ``dark8`` (uint8, 255 below the level: :func:`_dark8`) a gap is
    closed only where it lies within 4 px of a darker and of a lighter pixel: a shading that
    crosses the background level inside one object (a shaft's dark rim and its highlight),
    not the background between two darker objects (a thread along a shaft's dark edge, which
    the disc would otherwise fit across and the rim swallow; deviation 39)."""
    closed = cv2.morphologyEx(off8, cv2.MORPH_CLOSE, _GAP_DISC)  # a shading splits none
    # What the square's erosion reads below lies inside ``closed`` (a closing keeps its input,
    # and the gaps joined are some of its): no square in ``closed``, none there (exact), and
    # the usual thin thread skips the shading's two dilations and five masks.
    if dark8 is not None and not cv2.countNonZero(cv2.erode(closed, _INSCRIBED_SQUARE)):
        return None
    if dark8 is None:
        off8 = closed
    else:  # a gap is closed between a darker and a lighter pixel only (a shading, one object)
        light8 = cv2.bitwise_and(off8, cv2.compare(dark8, 0, cv2.CMP_EQ))
        both = cv2.bitwise_and(cv2.dilate(light8, _GAP_DISC), cv2.dilate(dark8, _GAP_DISC))
        off8 = cv2.bitwise_or(off8, cv2.bitwise_and(closed, both))
    if not cv2.countNonZero(cv2.erode(off8, _INSCRIBED_SQUARE)):
        return None  # the usual case, a thin thread only: no square, so no disc fits (exact)
    r = _WIDE_PX
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    core = cv2.erode(off8, disc)
    if not core.any():
        return None
    grow = 2 * (r + _WIDE_RIM_PX) + 1
    wide = cv2.dilate(core, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (grow, grow))) > 0
    return wide, off8 > 0


def _threshold_score(grey: np.ndarray, level: float, delta: float) -> np.ndarray:
    """Darkness below B scaled so that the threshold B - delta scores 0.5."""
    scale = 1.0 / (2.0 * max(delta, 1.0))
    return np.clip((level - grey) * scale, 0.0, 1.0).astype(np.float32)


def _lift(
    grey: np.ndarray, P: np.ndarray, dilate_px: int, box: tuple[slice, slice] | None = None
) -> np.ndarray:
    """Eq. (1): keep the image on P (dilated by ``dilate_px``), 255 elsewhere. Computed on the
    bounding box of P (or ``box``, known to hold it) grown by ``dilate_px``: the dilation
    reaches no farther."""
    out = np.full(grey.shape, LIFT_VALUE, np.float32)
    if box is None:
        box = _box(P, dilate_px)
    else:
        H, W = P.shape
        box = (
            slice(max(box[0].start - dilate_px, 0), min(box[0].stop + dilate_px, H)),
            slice(max(box[1].start - dilate_px, 0), min(box[1].stop + dilate_px, W)),
        )
    if box is None:
        return out
    # cv2 reads the box of P and writes the box of ``out`` in place, through their row strides
    # (no copy of P's box; cv2.copyTo's masked copy is ~3x numpy's copyto(where=) on a box)
    Pb = np.asarray(P[box], dtype=bool).view(np.uint8)
    if dilate_px > 0:
        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        Pb = cv2.dilate(Pb, k)
    dst = out[box]
    got = cv2.copyTo(np.asarray(grey[box], dtype=np.float32), Pb, dst)
    if got is not dst and not np.may_share_memory(got, dst):  # (cv2 could not write in place)
        dst[...] = got
    return out


def _background_level(hist: np.ndarray, p: SegmentationParams) -> float:
    """B: the fixed ``background`` or else the mode of the grey histogram ``hist`` (256,)."""
    if p.background is not None:
        return float(p.background)
    return float(np.argmax(hist))


# --- compiled kernel ---------------------------------------------------------------------------
# Compiled ahead of time once per machine, loaded without numba (core/compiled.py).


@kernel("int64[::1](uint8[:, ::1])")
def _histogram_kernel(g):  # noqa: ANN001
    """(256,) counts of the levels of ``g``, one pass (four partial histograms, so that runs of
    one level do not wait on their own increments)."""
    part = np.zeros((4, 256), dtype=np.int64)
    flat = g.ravel()
    n = flat.size
    m = n - n % 4
    for i in range(0, m, 4):
        part[0, flat[i]] += 1
        part[1, flat[i + 1]] += 1
        part[2, flat[i + 2]] += 1
        part[3, flat[i + 3]] += 1
    for i in range(m, n):
        part[0, flat[i]] += 1
    out = np.zeros(256, dtype=np.int64)
    for v in range(256):
        out[v] = part[0, v] + part[1, v] + part[2, v] + part[3, v]
    return out


@kernel(
    "Tuple((float32[:, ::1], int64[::1], uint8[::1], uint8[::1], uint8[::1], uint8[::1]))"
    "(uint8[:, ::1])"
)
def _scan_kernel(g):  # noqa: ANN001
    """One pass over a view's grey levels ``g`` (H, W): their float32 copy, the (256,) counts
    of the levels, and the least and greatest level of each row and of each column (the box of
    any set of levels outside one interval, with no pass over the image:
    :meth:`_Grey.box_of_levels`).

    Counting: a row mostly at its first pixel's level (a flat background) counts that level in
    a register while copying and sends only the other pixels to the tables; other rows go to
    eight partial tables in turn (increments of one level do not wait on each other)."""
    h, w = g.shape
    f = np.empty((h, w), dtype=np.float32)
    part = np.zeros((8, 256), dtype=np.int64)
    rmin = np.empty(h, dtype=np.uint8)
    rmax = np.empty(h, dtype=np.uint8)
    cmin = np.full(w, 255, dtype=np.uint8)
    cmax = np.zeros(w, dtype=np.uint8)
    m = w - w % 8
    for y in range(h):
        row = g[y]
        fr = f[y]
        ref = row[0]
        lo = np.uint8(255)
        hi = np.uint8(0)
        same = 0
        for x in range(w):
            v = row[x]
            fr[x] = v
            lo = min(lo, v)
            hi = max(hi, v)
            cmin[x] = min(cmin[x], v)
            cmax[x] = max(cmax[x], v)
            same += np.int64(v == ref)
        rmin[y] = lo
        rmax[y] = hi
        if 2 * same >= w:
            part[0, ref] += same
            k = 0
            for x in range(w):
                v = row[x]
                if v != ref:
                    part[k, v] += 1
                    k = (k + 1) & 7
        else:
            for x in range(0, m, 8):
                for k in range(8):
                    part[k, row[x + k]] += 1
            for x in range(m, w):
                part[0, row[x]] += 1
    out = np.zeros(256, dtype=np.int64)
    for v in range(256):
        t = 0
        for k in range(8):
            t += part[k, v]
        out[v] = t
    return f, out, rmin, rmax, cmin, cmax
