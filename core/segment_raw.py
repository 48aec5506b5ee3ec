"""Raw-frame segmentation (no mask given): multi-scale colour ridge, hysteresis, shape and stereo
consistency. :func:`segment_raw` is the ``method="raw"`` of :func:`core.segmentation.segment`.

Speed: every full-resolution pass costs ~0.2-0.5 ms at 640x480, so full-image work is kept to
the line response and one threshold per view; the rest runs on the candidate pixels (a few %,
sparse: the pieces are labelled and measured on their pixel lists), on bounding boxes (the
grown mask, its specks), or at quarter resolution (the local background, the instrument
mask). Percentiles are exact selections on a histogram of float bits; stereo partners are a
sorted-key search. Every shortcut gives the same masks as the plain computation
(tests/core/test_segment_raw.py; scripts/seg_fingerprint.py on whole suites).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

import cv2
import numpy as np
from scipy.spatial import cKDTree

from threadrecon.core.grow_kernel import grow_mask_f32, grow_mask_u8
from threadrecon.core.instrument import grow_into_attached
from threadrecon.core.lazy import Deferred
from threadrecon.core.ridge_kernel import (
    achromatic,
    at_least,
    block_means,
    blocks_at,
    half_widths,
    kth_smallest,
    label_pixels,
    line_response,
    log_planes,
    piece_candidates,
    piece_shapes,
    piece_stats,
    pixels_at,
    small_components,
    upsample_max,
    values_at,
)
from threadrecon.core.segment_surface import (
    BLOCK_PX,
    SAME_DISPARITY_PX,
    SurfaceTest,
    block_of,
    undecidable,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

    from threadrecon.core.segmentation import SegmentationParams

_SCALES: Final = (1.0, 2.0)  # fine and coarse Gaussian scales of the line detector, px
_EDGE_K: Final = 2.0  # gradient penalty; 2 cancels both lobes of a step edge beyond 1 sigma
_LOG_OFFSET: Final = 16.0  # log(I + 16): lighting is a product, contrast a ratio; 16 tames noise
_BAND_PX: Final = 4  # the mask is grown at most this far from a kept piece (half of 6 px + 1)
_BG_SIGMA: Final = 8.0  # local background colour: thread-free Gaussian average, px
_Q_SHIFT: Final = 2
_Q: Final = 1 << _Q_SHIFT  # the local background and the instrument mask are computed at 1/4
# resolution
_CORE_FRACTION: Final = 0.4  # core pixels respond >= 40 % of their piece's mean
_SAME_DYE_COS: Final = 0.8  # pieces of one thread: colour contrasts within ~37 degrees
_SAME_DYE_COS_PX: Final = 0.5  # per pixel (noisier): within 60 degrees
_GREY_CHROMA: Final = 3.0  # chroma contrast below ~10 %: a grey (black, white) dye
MAX_HALF_WIDTH_PX: Final = 6.0  # a piece wider than 12 px (a 6 px thread's response ~8 px)
# is not thread
_RED_THREAD_GAIN: Final = 3.0  # blood-like pieces win when 3x as salient as the rest
_VESSEL_HUE_COS: Final = 0.99  # chroma contrasts within 8 degrees: one absorber (vessels)
_STUB_PX: Final = 8  # a vessel's stub on the mask holds >= 8 px (deviation 78)
_STUB_REACH_PX: Final = _BAND_PX - 0.5  # and reaches the band's last ring, off the thread's rim
_VESSEL_GROUP_PX: Final = 10  # a vessel: >= 10 blood-like candidates in a group (JPEG specks: <= 9)
_MIN_VESSEL_PX: Final = 50  # blood-like pixels needed to tell the frame's vessel hue
_GREY_TOOL: Final = 0.12  # |log R/G|, |log B/G| below this: unsaturated, e.g. steel
_LOG_SCALE: Final = 32.0  # channels are 32 log(.), so 1 unit ~ 3 % of contrast
_GREY_LIMIT: Final = np.float32(_GREY_TOOL * _LOG_SCALE)  # the same in log channel units
# (float32, as numpy compares a float32 image with it)
_BLOOD_RATIO: Final = 0.25  # haemoglobin absorbs G, B far more than R: a vessel reddens by
# >= 1/4 of its darkening (log units) at any strength; dyes other than red redden less or not
_MIN_SNR: Final = 5.0  # a thread piece's mean contrast to its background: >= 5 noise sigmas
_QUANT_SIGMA: Final = _LOG_SCALE / (255.0 * 12**0.5)  # uint8 quantisation noise, log units
_SHARED_PX: Final = 1.5  # two pixels sharing less than 1.5 px of coverage: one thread pixel
_JAW_MIN_PX: Final = 7  # grey parts attached to an instrument and at least 7 px wide (a
# thread is at most 6) belong to it: its jaws
_MARK_SHARE: Final = 0.75  # a piece moving with the tissue on 3/4 of it is a mark on it (a
# block's test errs on ~1 % of blocks; a thread merged with a mark keeps >= 1/4 of its own)
_MAX_SURFACE_TESTS: Final = 8  # a thread less salient than 8 marks on the tissue is not
# told from them: the frame's answer is "no thread found" (bounds the work: ~1 ms a test)
_GLINT_APART_DEG: Final = 25.0  # a thread's contrast and white closer than 25 degrees: grey,
# a highlight on it is not told from its body (the fit's noise gain 1/sin^2 stays <= 5.6)
_GLINT_APART_SIN2: Final = float(np.sin(np.radians(_GLINT_APART_DEG)) ** 2)
_MAX_RED_TESTS: Final = 4  # a red thread less salient than 3 blood-like lines on the tissue
# (vessels) is not told from them: the red pass tests at most 4 pieces a view
_RED_UNDECIDED: Final = 0  # a red thread less salient than an undecided blood-like line is
# not told from the vessels (bounds the red pass's work: ~1 ms a surface test)
_HIGHLIGHT_PX: Final = 4  # a highlight along a thread <= 6 px wide leaves at most 4 px
# between its two sides
_NOISE_ROW_STEP: Final = 16  # noise estimated on every 16th row: 30 rows x 640 px at 640x480


def segment_raw(
    left: np.ndarray,
    right: np.ndarray,
    p: SegmentationParams,
    *,
    greys: tuple[np.ndarray, np.ndarray] | None = None,
    defer_score: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | Deferred, np.ndarray | Deferred]:
    """Thread masks and scores of a raw rectified pair, no mask given.

    1. Line response S: on 32 log(I) (brightness, log R/G, log B/G), the scale-normalised
       Hessian line strength 2 min(|l1 + l2| / 2, |l1 - l2| / 2) sigma^2 (zero on blobs and
       flat parts) minus 2 sigma |gradient| (zero on step edges), max over two scales.
    2. Hysteresis: pieces of S >= ridge_lo * level holding a pixel of S >= ridge_hi * level,
       ``level`` being the image's typical response (90th percentile): no absolute contrast.
       Large unsaturated regions (instruments) hold no candidate, nor their rim of
       ``tool_rim_px`` (:func:`_on_tool`; a coloured thread beside them does). Before the
       pieces are formed, pixels darker and redder than the tissue around them (blood:
       vessels; redder by more than ``blood_rg`` or by >= _BLOOD_RATIO of their darkening,
       which holds for a vessel of any strength) are set aside; they come back when they
       stand out _RED_THREAD_GAIN times more than anything else and their hue differs from
       the mean of the frame's other blood-like pixels by more than ~8 degrees (a red thread;
       the vessels of a frame share one hue), keeping only pixels nearer the thread's hue. A lone
       blood-like line (too few other blood-like pixels) is a vessel. They come back too when
       the line chosen without them runs along them in both views (the highlight on a red
       thread) and the blood-like line chosen lies along it.
    3. Shape: a piece's length >= min_length_px and largest half-width <= MAX_HALF_WIDTH_PX,
       not lying within _BORDER_PX of one image side (the filters' reflected rim,
       :func:`_along_border`); with ``split_wide`` a long piece wider than that loses its wide
       part and its thin rest is judged (:func:`_wide_part`: a thread beside a fibre).
    4. Stereo: a piece keeps >= half of its pixels with a candidate pixel on the same row of the
       other view within [0, max_disparity_px] of disparity, or with the other view's
       instrument in that window (the partner may lie behind it: :func:`_window_hits`).
       Presence: the piece's mean contrast to its local background is >= _MIN_SNR times the
       frame's own pixel noise (per channel, robust): on a thread-free frame nothing passes
       and the answer is "no thread found", not a vessel or a texture line.
    5. Selection: the most salient piece (mean S x sqrt(length)) is the thread; other pieces
       and pixels join it when they share its dye (direction of the colour contrast; a piece
       merged with a fibre by its part of that dye) and their mean S is >= keep_ratio of its.
       Pieces moving with the tissue are marks on it (:mod:`core.segment_surface`; the
       tissue's samples are off the instrument, :meth:`_View.far`: a shaft is none), and so
       are the undecided fragments of a mark (:func:`_continues`, :func:`_like_a_mark`),
       chosen or joining; a kept piece moving with the tissue in part loses that part
       (:func:`_mark_part`; not a block where the thread's own disparity goes on from its
       floating part beside it, :func:`_thread_through`); a joining piece not seen floating
       that lies behind the whole thread, beyond its depth slope over the gap, stays out
       (:func:`_off_thread_depth`: a fibre on the tissue the surface test left open), and a
       piece of two dyes takes that of its part in front of the tissue (:func:`_main_dye`);
       it is no mark when that part,
       tested alone, floats (a thread merged with the fibres it crosses,
       :func:`_a_mark_of_one_dye`). Among
       blood-like pieces, one the surface test leaves open at the tissue's own disparity is a
       vessel (:func:`_at_tissue_disparity`; in the first pass too, any undecided piece
       chosen or joining), and so is one voted in front of it whose own disparity is not above the
       tissue's (:func:`_contradicted`); one seen in front over a piece's worth of pixels
       and over more of it than on the tissue is a red thread merged with the vessels it
       crosses, judged by that part (:func:`_floats_in_part`); a red thread's undecided
       fragments join it at its own disparity (:func:`_at_thread_disparity`; the gap counted
       off the instrument, :func:`_gap_off_tool`; a long one read near the thread,
       :func:`_local_disparity`); an undecided blood-like piece holding the
       highlight the first pass chose is chosen (:func:`_holds`). The cores chosen in the two
       views must be one object (:func:`_one_object`).
    6. Mask: within _BAND_PX of the kept pixels, those with coverage >= 0.5 of a thread colour
       blended over the local background colour (see :func:`_grow_mask`); for a contrast near
       grey, with the runs it encloses across the thread (a highlight, :func:`_fill_across`).
       Off a thread chosen without the blood-like pixels, a part of the grown pixels that are
       blood-like, joined to a vessel's group of candidates and reaching past the thread's
       rim is no thread (a vessel's stub where it crosses the thread, :func:`_vessel_stub`;
       deviation 78, ``rim_blood``).

    Returns P_L, P_R (H, W) bool and score_L, score_R (H, W) float32 in [0, 1] (with
    ``defer_score``: :class:`core.lazy.Deferred` of them, computed when read; no stage reads
    them). ``greys``: the views' grey levels (H, W) float32 as :func:`core.segmentation.to_grey`
    gives them for uint8 views (the surface test's images; computed here when None).
    Raises ``ValueError("no thread found ...")`` when no piece survives in a view.
    """
    views = [_View.build(img, p) for img in (left, right)]
    if greys is not None:  # (the same grey levels as :meth:`_View.grey`'s, computed once)
        views[0]._grey, views[1]._grey = greys
    found, salience, _, floating = _select(views, p)
    rects = _rects(found)  # the cores' bounding boxes, found once for every step below
    red_thread = False  # the thread was chosen among the blood-like pixels (the red pass)
    if any(v.blood.any() for v in views):
        # A red thread is blood-like too: it wins back when it stands out far more than
        # anything left without the blood-like pixels, and when its hue differs from the
        # frame's other blood-like pixels (a frame's vessels share one hue, haemoglobin's);
        # or, whatever its hue, when it is seen in front of the tissue in both views (a
        # vessel is a mark on it) and what was chosen without it is not.
        red_views = [v.with_blood(p) for v in views]
        # The most salient shape-ok piece of each view bounds what a red thread can reach.
        bound = sum(float(np.max(v.pieces[2] * np.sqrt(v.pieces[3]), where=v.pieces[4],
                                 initial=0.0)) for v in red_views)  # fmt: skip
        # A line chosen without them that runs along blood-like pixels in both views may be
        # the highlight along a red thread: the thread is then the blood-like line around it.
        glint = found is not None and all(
            _near_blood(v, c, r) for v, c, r in zip(views, found, rects, strict=True)
        )
        red, red_salience, red_cos, _ = (
            _select(red_views, p, nearest_hue=True, along=found if glint else None)
            if bound >= _RED_THREAD_GAIN * salience or not floating or glint
            else (None, 0.0, 1.0, False)
        )
        # With nearest_hue, a piece is chosen only when seen in front of the tissue.
        if red is not None and (
            not floating
            or (red_salience >= _RED_THREAD_GAIN * salience and red_cos < _VESSEL_HUE_COS)
            or (
                glint
                and all(_near(r, c, rect=b) for r, c, b in zip(red, found, rects, strict=True))
            )
        ):
            views, found = red_views, red
            rects = _rects(found)
            red_thread = True
    if found is not None and not _one_object(found, int(p.max_disparity_px), rects):
        found = None  # each view chose another line: neither is seen in both (no thread)
    if found is None:
        raise ValueError(
            "no thread found: no long thin piece with a partner in the other view stands out "
            f"of the background (raw segmentation; ridge_hi={p.ridge_hi:g}, "
            f"min_length_px={p.min_length_px:g})"
        )
    grown = [_grow_box(v, core, rect) for v, core, rect in zip(views, found, rects, strict=True)]
    stubs: list[np.ndarray | None] = [None, None]
    if not (p.rim_blood or red_thread):
        stubs = [
            _vessel_stub(v, core, g, p.blood_rg)
            for v, core, g in zip(views, found, grown, strict=True)
        ]
    out = []
    for v, core, g, stub in zip(views, found, grown, stubs, strict=True):
        mask = _thread_mask(v, core, max(int(p.min_length_px), 1), grown=g, stub=stub)
        cap = 2.0 * p.ridge_hi * v.level
        out.append((mask, Deferred(_score_of, v.img, cap) if defer_score else _score(v.S, cap)))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def _rects(cores: list[np.ndarray] | None) -> list[tuple[int, int, int, int]]:
    """``cv2.boundingRect`` (x, y, w, h) of each core (H, W) uint8 (none for None)."""
    return [] if cores is None else [cv2.boundingRect(c) for c in cores]


def _thread_mask(
    v: _View,
    core: np.ndarray,
    min_px: int,
    rect: tuple[int, int, int, int] | None = None,
    grown: tuple[np.ndarray, tuple[slice, slice]] | None | bool = False,
    stub: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool thread mask of the view grown from its ``core`` (H, W) uint8
    (:func:`_grow_mask`), off the instrument's body and rim, with the runs it encloses for a
    near-grey contrast (:func:`_fill_across`), without specks of < ``min_px`` pixels.

    Specks are judged on the mask joined with its core: a thread 1-2 px wide is cut where its
    axis passes between pixel centres (coverage < 0.5 on both sides), and its parts stay one
    piece through the core's pixels there. Each step runs on the box the mask is grown on
    (:func:`_grow_box`): the mask and the core lie in it, and so do the runs the mask encloses
    and its components (the same mask as the steps on the whole view, no pass over it).
    ``rect``: the core's bounding box, when known (:func:`_rects`). ``grown``: the
    :func:`_grow_box` of the core, when computed (False: computed here). ``stub``: (H, W)
    bool pixels that are no thread pixels (a vessel's stub, :func:`_vessel_stub`; deviation
    78), or None."""
    mask = np.zeros(core.shape, bool)
    if grown is False:
        grown = _grow_box(v, core, rect)
    if not isinstance(grown, tuple):  # an empty core
        return mask
    box, at = grown
    if v.tool_body is not None:  # the instrument's body and rim are no thread pixels
        box &= ~v.tool_body[at]
    if stub is not None:  # a vessel's stub where it crosses the thread (deviation 78)
        box &= ~stub[at]
    if v.grey_core:  # a highlight on it is not told from its body by colour
        box = _fill_across(box, _HIGHLIGHT_PX)
    box &= drop_specks(box | core[at].view(bool), min_px)
    mask[at] = box
    return mask


def _vessel_stub(
    v: _View,
    core: np.ndarray,
    grown: tuple[np.ndarray, tuple[slice, slice]] | None,
    blood_rg: float,
) -> np.ndarray | None:
    """(H, W) bool: the grown mask pixels of the view off its ``core`` (H, W) uint8 and off the
    instrument that are a vessel's stub (deviation 78); None when the view holds no blood-like
    candidate or is grey. ``grown``: the :func:`_grow_box` of the core.

    A stub is a part of the blood-like grown pixels joined to a vessel (:func:`_vessel_rim`,
    seeded by the view's groups of >= _VESSEL_GROUP_PX candidates only) that holds >= _STUB_PX
    pixels and reaches >= _STUB_REACH_PX off the core: a piece of the vessel beside the thread.
    A few blood-like pixels on the thread's own rim (JPEG's chroma bleeding next to a speck of
    reddened candidates) are thread pixels; so are the rim pixels beside a vessel's crossing
    (a part within 3 px of the core), which the other view's mask holds too."""
    if grown is None or v.img.ndim != 3 or not v.blood.any():
        return None
    box, at = grown
    box = box & ~core[at].view(bool)
    if v.tool_body is not None:
        box &= ~v.tool_body[at]
    out = np.zeros(core.shape, bool)
    rim = _vessel_rim(v, box, at, blood_rg, _VESSEL_GROUP_PX)
    if not rim.any():
        return out
    n, lab = cv2.connectedComponents(rim.view(np.uint8), connectivity=8)
    reach = cv2.distanceTransform((core[at] == 0).view(np.uint8), cv2.DIST_L2, 3)
    far = np.zeros(n, np.float32)
    np.maximum.at(far, lab.ravel(), reach.ravel())
    keep = (np.bincount(lab.ravel(), minlength=n) >= _STUB_PX) & (far >= _STUB_REACH_PX)
    keep[0] = False
    out[at] = keep[lab]
    return out


def _vessel_rim(
    v: _View, grown: np.ndarray, at: tuple[slice, slice], blood_rg: float, vessel_px: int = 1
) -> np.ndarray:
    """(bh, bw) bool: the pixels of ``grown`` (bh, bw) bool (grown mask pixels off the core,
    on the view's box ``at``) that are blood-like (:func:`_blood_like`) and 8-connected through
    blood-like grown pixels to one of the view's blood-like candidates (a vessel's pixels set
    aside in step 2) in a group of >= ``vessel_px`` of them (:func:`_vessel_pixels`)."""
    out = np.zeros(grown.shape, bool)
    r, c = np.nonzero(grown)
    flag = _blood_like(v, r + at[0].start, c + at[1].start, blood_rg)
    if not flag.any():
        return out
    r, c = r[flag], c[flag]
    # A part of the blood-like pixels joins a candidate through blood-like pixels and
    # candidates when it touches one (past a candidate the part is the same): the parts of
    # the blood-like pixels alone, on their box grown by a pixel, cut where a candidate is
    # 8-adjacent.
    y0, x0 = max(int(r.min()) - 1, 0), max(int(c.min()) - 1, 0)
    y1, x1 = min(int(r.max()) + 2, grown.shape[0]), min(int(c.max()) + 2, grown.shape[1])
    part = np.zeros((y1 - y0, x1 - x0), np.uint8)
    part[r - y0, c - x0] = 1
    near = np.zeros_like(part)
    br, bc = _vessel_pixels(v, vessel_px)
    br, bc = br - (at[0].start + y0), bc - (at[1].start + x0)
    inside = (br >= 0) & (br < part.shape[0]) & (bc >= 0) & (bc < part.shape[1])
    if not inside.any():
        return out
    near[br[inside], bc[inside]] = 1
    near = cv2.dilate(near, np.ones((3, 3), np.uint8))
    n, lab = cv2.connectedComponents(part, connectivity=8)
    vessel = np.zeros(n, bool)
    vessel[lab[(near & part).view(bool)]] = True
    vessel[0] = False
    out[y0:y1, x0:x1] = vessel[lab]
    return out


def _vessel_pixels(v: _View, vessel_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (K,) of the view's blood-like candidates in 8-connected groups of >=
    ``vessel_px`` of them (a vessel; a smaller group is a speck, JPEG's chroma on the thread's
    rim or the tissue's grain, deviation 78)."""
    rows, cols = v.rows[v.blood], v.cols[v.blood]
    if rows.size == 0:
        return rows, cols
    big = _group_sizes(rows, cols) >= vessel_px
    return rows[big], cols[big]


def _blood_like(v: _View, rows: np.ndarray, cols: np.ndarray, blood_rg: float) -> np.ndarray:
    """(P,) bool: whether the view's pixels (``rows``, ``cols``) (P,) int are darker and redder
    than the local background (the test :meth:`_View.build` sets the blood-like candidates
    aside by, with ``blood_rg`` its :attr:`SegmentationParams.blood_rg`)."""
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    cols = np.ascontiguousarray(cols, dtype=np.int64)
    if rows.size == 0:
        return np.zeros(0, bool)
    delta = _log_of_pixels(_pixels_at(v.img, rows, cols)) - blocks_at(
        _log_of(v.bg_rgb), rows, cols, _Q
    )
    return _blood_flags(delta, blood_rg)


def _blood_flags(delta: np.ndarray, blood_rg: float) -> np.ndarray:
    """(P,) bool: blood-like contrasts ``delta`` (P, C) to the local background (log
    channels): darker, and redder by more than ``blood_rg`` or by >= _BLOOD_RATIO of the
    darkening."""
    redder = (delta[:, 1] > blood_rg * _LOG_SCALE) | (delta[:, 1] >= -_BLOOD_RATIO * delta[:, 0])
    return redder & (delta[:, 0] < 0)


def _score_of(img: np.ndarray, cap: float) -> np.ndarray:
    """:func:`_score` of the view ``img``'s line response, computed anew (deferred scores, read
    by no stage: the response, 4 B a pixel, is not kept alive for them; the view is held by
    the pair anyway, and the response is the same computation, value for value)."""
    return _score(_line_response(*_log_planes(img)), cap)


def _score(S: np.ndarray, cap: float) -> np.ndarray:
    """(H, W) float32 per-pixel thread score in [0, 1]: the line response ``S`` (H, W) over
    ``cap`` (twice the seed threshold ridge_hi * level), clipped at 1."""
    return cv2.min(S, cap) * (1.0 / cap)


@dataclass
class _View:
    """One view's intermediate results of :func:`segment_raw`."""

    img: np.ndarray
    S: np.ndarray  # (H, W) line response
    level: float
    lo: np.ndarray  # (H, W) uint8, 1 where S >= ridge_lo * level (off instruments)
    rows: np.ndarray  # (M,) of the lo pixels, row-major order
    cols: np.ndarray
    delta: np.ndarray  # (M, C) log-channel contrast of the lo pixels to the local background
    blood: np.ndarray  # (M,) bool, darker and redder than the tissue around
    sigma: np.ndarray  # (C,) pixel noise of each log channel (robust), log units
    bg_rgb: np.ndarray  # (h, w, C) float32 local background colour at quarter resolution
    s_lo: np.ndarray  # (M,) float32 S at the lo pixels
    pieces: tuple = ()
    px: np.ndarray | None = None  # (M, C) uint8 values of the lo pixels (:func:`_pixels_at`)
    grey_core: bool = False  # the chosen core's contrast is near grey (:func:`_grey_contrast`)
    tool: np.ndarray | None = None  # (H, W) bool, the instrument found in the view, if any
    tool_body: np.ndarray | None = None  # (H, W) bool, what of it takes candidates (its body
    # and rim, :func:`_on_tool`; None: all of ``tool``)
    _grey: np.ndarray | None = None
    _far: np.ndarray | None = None
    _surface: SurfaceTest | None = None
    _tool_counts: tuple | None = None
    # lo pixels of each mark on the tissue the first pass found (:func:`_select`), which the red
    # pass's views share: the tissue's disparity beside a vessel (deviation 53)
    first_marks: list[np.ndarray] = field(default_factory=list)
    red_marks: list[np.ndarray] = field(default_factory=list)  # and those the red pass found
    off_tool: bool = False  # the surface test's background leaves ``tool`` out (deviation 56)

    def far(self) -> np.ndarray:
        """(H, W) bool: background pixels beyond _BAND_PX of every candidate (lo) pixel, where
        no line, nor its blurred rim, is (computed once, on demand); with ``off_tool``, not on
        the instrument either (its shaft is no tissue: a line at its depth beside it does not
        move with the tissue, deviation 56)."""
        if self._far is None:
            k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * _BAND_PX + 1, 2 * _BAND_PX + 1))
            self._far = cv2.dilate(self.lo, k) == 0
            if self.off_tool and self.tool is not None:
                self._far &= ~self.tool
        return self._far

    def tool_counts(self) -> tuple[int, int, np.ndarray] | None:
        """Running counts of the instrument mask along its rows (:func:`_row_counts`;
        computed once, on demand; None without an instrument)."""
        if self._tool_counts is None and self.tool is not None:
            self._tool_counts = _row_counts(self.tool)
        return self._tool_counts

    def grey(self) -> np.ndarray:
        """(H, W) float32 grey levels of the view (computed once, on demand)."""
        if self._grey is None:
            img = self.img if self.img.ndim == 3 else self.img[:, :, None]
            if img.dtype != np.uint8:
                img = np.clip(img, 0, 255).astype(np.uint8)
            img = img[:, :, :3]
            if img.shape[2] < 3:
                g = img[:, :, 0]
            elif (bgr := _reversed(img)) is not None:  # RGB as loaded: a view of BGR
                g = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
            else:  # cv2 takes a row-strided array (half a side-by-side frame) as it is
                g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
            self._grey = g.astype(np.float32)
        return self._grey

    @classmethod
    def build(cls, img: np.ndarray, p: SegmentationParams) -> _View:
        grey, half = _log_planes(img)
        c = half.shape[0]
        S = _line_response(grey, half)
        level = _robust_level(S)
        lo = np.empty(S.shape, np.uint8)  # cv2.compare(S, ridge_lo level, CMP_GE) and its points
        rows, cols = at_least(S, np.float32(p.ridge_lo * level), lo)
        a_q = _quarter(img if img.ndim == 3 else img[:, :, None])[:, :, :c]
        tool_q = body = None  # the instrument at quarter resolution, its body and rim
        if c > 1 and len(rows):
            tool = _instrument_mask(_log_of(a_q, levels=img.dtype == np.uint8))
            if tool.any():  # its jaws: grey parts wider than a thread, attached to it
                tool_q = tool
                h, w = lo.shape
                full = tool[_qi(np.arange(h), tool.shape[0])][:, _qi(np.arange(w), tool.shape[1])]
                # full resolution, on instrument frames only: chroma of _log_channels below
                # _GREY_TOOL, from the uint8 pixels in one pass
                unsat = achromatic(_uint8(img), _LOG_LUT, _GREY_LIMIT, np.empty((h, w), np.uint8))
                tool = grow_into_attached(unsat.view(bool), full, _JAW_MIN_PX)
                on_tool, body = _on_tool(tool, unsat, rows, cols, p.tool_rim_px)
            else:
                on_tool = np.zeros(len(rows), bool)
            if on_tool.any():
                lo[rows[on_tool], cols[on_tool]] = 0
                rows, cols = rows[~on_tool], cols[~on_tool]
        else:
            tool = None
        free = _free_blocks(rows, cols, a_q.shape[:2])
        if tool_q is not None and p.tool_rim_px > 0:
            # the instrument's blocks are no background either: a thread kept beside it
            # (deviation 50) is measured against the tissue, not against the shaft's grey
            free[tool_q] = 0.0
        bg_rgb = _background(a_q, free)
        bg = _log_of(bg_rgb)
        px = _pixels_at(img, rows, cols)  # (kept: the chosen core's colour reads them)
        delta = _log_of_pixels(px) - blocks_at(bg, rows, cols, _Q)
        if c > 1:
            blood = _blood_flags(delta, p.blood_rg)
            if (
                p.blood_speck_px > 1
                and blood.any()
                and not _has_group(blood, rows, cols, p.blood_speck_px)
            ):
                blood[:] = False  # specks only: no vessel in the view (deviation 70)
        else:
            blood = np.zeros(len(rows), bool)
        sigma = noise_sigma(_log_channels(img[::_NOISE_ROW_STEP]), row_step=1)
        s_lo = values_at(S, rows, cols)
        v = cls(img, S, level, lo, rows, cols, delta, blood, sigma, bg_rgb, s_lo, px=px)
        if tool is not None and tool.shape == lo.shape and tool.any():
            v.tool, v.tool_body = tool, body
        v.off_tool = p.tissue_surface
        v.pieces = _pieces(~blood if blood.any() else None, v, p)
        return v

    def with_blood(self, p: SegmentationParams) -> _View:
        v = _View(**{k: getattr(self, k) for k in self.__dataclass_fields__ if k != "pieces"})
        v.pieces = _pieces(None, v, p)
        return v


def _has_group(flag: np.ndarray, rows: np.ndarray, cols: np.ndarray, min_px: int) -> bool:
    """Whether the flagged pixels of (rows, cols) (M,) (row-major order) hold an 8-connected
    group of at least ``min_px`` pixels (deviation 70: a vessel, not specks of noise)."""
    at = np.flatnonzero(flag)
    if len(at) < min_px:
        return False
    return int(_group_sizes(rows[at], cols[at]).max()) >= min_px


def _group_sizes(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(M,) int: for each of the pixels (rows, cols) (M,) (row-major order), the size of the
    8-connected group of them it lies in (:func:`label_pixels`)."""
    lab = np.empty(rows.size, np.int64)
    label_pixels(rows, cols, lab)
    return np.bincount(lab)[lab]


def _points(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (M,) int of the nonzero pixels of a uint8 mask, row-major order."""
    pts = cv2.findNonZero(mask)
    if pts is None:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    pts = pts.reshape(-1, 2)
    return pts[:, 1].astype(np.intp), pts[:, 0].astype(np.intp)


def _qi(index: np.ndarray, n: int) -> np.ndarray:
    """Quarter-resolution index of full-resolution rows or columns (>= 0), clipped to ``n``
    (a shift: _Q is a power of two, and an integer division costs ~5x more)."""
    return np.minimum(index >> _Q_SHIFT, n - 1)


def _quarter(a: np.ndarray) -> np.ndarray:
    """(h, w, C) float32 block means of ``a`` (H, W, C) over _Q x _Q blocks (uint8 means are
    rounded: 0.5 grey levels at most)."""
    h, w = a.shape[:2]
    if a.dtype == np.uint8 and a.shape[2] == 3 and h % _Q == 0 and w % _Q == 0 and h * w > 0:
        out = np.empty((h // _Q, (w // _Q) * 3), np.float32)  # cv2's values, 6x faster
        # Each row's pixels one after the other (a view; of an RGB view of BGR, the BGR
        # array's, whose block means are those of its channels in the other order).
        if (rev := _reversed(a)) is not None:
            means = block_means(rev.reshape(h, w * 3), out).reshape(h // _Q, w // _Q, 3)
            return np.ascontiguousarray(means[:, :, ::-1])
        return block_means(a.reshape(h, w * 3), out).reshape(h // _Q, w // _Q, 3)
    size = (max(w // _Q, 1), max(h // _Q, 1))
    if (rev := _reversed(a)) is not None:  # channel by channel: the reversed array's means
        small = cv2.resize(rev, size, interpolation=cv2.INTER_AREA)[:, :, ::-1]
    else:
        small = cv2.resize(a, size, interpolation=cv2.INTER_AREA)
    return small.reshape(small.shape[0], small.shape[1], -1).astype(np.float32, copy=False)


def _reversed(a: np.ndarray) -> np.ndarray | None:
    """``a[:, :, ::-1]`` when that is C-contiguous (an RGB image as loaded is a view of the
    file's BGR array), else None: cv2 copies a strided array first (~1 ms at 640x480), and a
    per-channel operation (or BGR2GRAY for RGB2GRAY) on the reversed array gives the same."""
    if a.ndim != 3 or a.shape[2] < 2 or a.strides[2] >= 0:
        return None
    rev = a[:, :, ::-1]
    return rev if rev.flags.c_contiguous else None


def _log_of(a: np.ndarray, levels: bool = False) -> np.ndarray:
    """The channels of :func:`_log_channels` of a small float image (h, w, C): the log of
    block means stands for the block mean of the logs (texture within a block is small).
    ``levels``: ``a`` holds whole levels 0..255 only (the rounded block means of a uint8
    image, :func:`_quarter`), whose logs are looked up (:data:`_LOG_LUT32`: the same float32
    values, ~7x faster)."""
    if levels:
        logs = cv2.LUT(a.astype(np.uint8), _LOG_LUT32).reshape(a.shape)
    else:
        logs = _LOG_SCALE * np.log(a + _LOG_OFFSET)
    if logs.shape[2] == 1:
        return logs
    return cv2.transform(logs, _LOG_MIX)


def _free_blocks(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) float32, 1 on quarter-resolution blocks that hold no candidate pixel (a
    candidate's colour is not the background's)."""
    free = np.ones(shape[0] * shape[1], np.float32)  # a flat index: ~2.5x faster than two
    free[_qi(rows, shape[0]) * shape[1] + _qi(cols, shape[1])] = 0.0
    return free.reshape(shape)


def _background(a_q: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(h, w, C) local background of the quarter-resolution image ``a_q``: the Gaussian average
    (_BG_SIGMA) of the candidate-free blocks (normalised convolution)."""
    s = _BG_SIGMA / _Q
    c = a_q.shape[2]
    num = cv2.GaussianBlur(a_q * free[:, :, None], (0, 0), s).reshape(a_q.shape[0], -1, c)
    den = cv2.GaussianBlur(free, (0, 0), s)
    return num / np.maximum(den, 1e-3)[:, :, None]


def _select(
    views: list[_View],
    p: SegmentationParams,
    nearest_hue: bool = False,
    along: list[np.ndarray] | None = None,
) -> tuple[list[np.ndarray] | None, float, float, bool]:
    """Core thread pixels (H, W) bool of both views (None when a view has no piece), the
    salience (mean S x sqrt(length), summed over the views) of the chosen pieces (with None:
    of the most salient marks on the tissue, which a red thread must outshine), and the
    largest (over the views) cosine between the chroma contrast of the chosen piece and the
    mean one of the view's other blood-like pixels (its vessels; 1 when there are too few to
    tell: a lone blood-like line is taken for a vessel), and whether the chosen pieces are seen
    in front of the tissue in both views (:func:`_floats`; False with None).

    ``nearest_hue`` (a blood-like thread among vessels): pieces and pixels join the thread only
    when their hue is nearer the thread's than the vessels'. ``along``: per view, the core
    (H, W) uint8 of a line that runs along blood-like pixels (a highlight on a red thread): a
    blood-like piece that holds it is chosen even when the surface test leaves it open."""
    D = int(p.max_disparity_px)
    width = views[0].lo.shape[1]
    keys = [_row_keys(*v.pieces[1], width, D) for v in views]  # shape-ok pixels, sorted
    out = []
    salience = 0.0
    cos_vessels = -1.0
    floating = True
    chosen = []
    for i, v in enumerate(views):
        lab, _, means, length, ok = v.pieces  # lab: piece of each lo pixel (0: none), sparse
        # Only the pixels of shape-ok pieces can join (the rest of the lo pixels is skipped).
        on = np.flatnonzero(ok[lab])
        lab_on = lab[on]
        partner = _has_partner(v.rows[on], v.cols[on], keys[1 - i], width, D, look_left=(i == 0))
        if views[1 - i].tool is not None:  # a partner hidden by the instrument is no absence
            partner |= _window_hits_in(
                views[1 - i].tool_counts(), v.rows[on], v.cols[on], D, look_left=(i == 0)
            )
        k = _consistent(lab_on, partner, ok)
        n = len(k)
        area = np.maximum(np.bincount(lab_on, minlength=n), 1).astype(np.float64)
        delta = np.stack(
            [np.bincount(lab_on, weights=v.delta[on, j], minlength=n) / area
             for j in range(v.delta.shape[1])],
            1,
        )  # fmt: skip
        # Is it there at all: its mean contrast to the background stands out of the pixel noise.
        k &= _row_norms(delta / v.sigma) >= _MIN_SNR
        if nearest_hue:  # a blood-like thread: the pieces of few blood-like pixels were judged
            # without them (the first pass), and an undecided one there is no thread here
            k &= np.bincount(lab_on, weights=v.blood[on], minlength=n) >= 0.5 * area
        if not k.any():
            return None, 0.0, 1.0, False
        rank = np.where(k, means * np.sqrt(length), -1.0)
        best = int(np.argmax(rank))
        top = float(rank[best])  # marks on the tissue count here: a red thread must outshine them
        # A mark on the tissue (vessel, fibre) moves with the texture beside it; a thread in
        # front of the tissue does not: the next most salient piece is tried.
        # Among blood-like pieces (vessels are marks too) the one left must be seen in front
        # of the tissue, not merely undecided (a small leftover).
        marks: list[int] = []  # pieces found to be marks on the tissue, most salient first
        # The red pass reads the tissue's disparity from the first pass's marks too (fibres
        # moving with the tissue; the vessels of a thread's hue are its own marks).
        known = v.first_marks if nearest_hue and p.first_marks else []

        def tissue(marks: list[int] = marks, on: np.ndarray = on, lab_on: np.ndarray = lab_on,
                   known: list[np.ndarray] = known) -> list[np.ndarray]:  # fmt: skip
            return [on[lab_on == m] for m in marks] + known

        votes_of: dict[int, np.ndarray] = {}  # surface votes of the pieces tested
        skipped = 0  # blood-like pieces passed over as not seen in front of the tissue
        for _ in range(_MAX_RED_TESTS if nearest_hue else _MAX_SURFACE_TESTS):
            if rank[best] <= 0:
                break
            votes = votes_of[best] = _surface_votes(views, i, lab_on == best, on, D)
            # A piece too short for the test to decide, continuing a mark of its own dye, is
            # a part of that mark (one line cut in two by a faint stretch of it); one too short
            # for the test to ever decide (fewer blocks than it needs) is taken for one more
            # of the marks of its dye found in the frame.
            is_mark = split = _a_mark(votes)
            if is_mark and not nearest_hue:  # a thread merged with fibres: its part floats
                piece_px = p.min_length_px * area[best] / length[best]  # (its least pixels)
                is_mark, votes = _a_mark_of_one_dye(
                    views, i, lab_on == best, on, D, votes, piece_px
                )
                votes_of[best] = votes
                split = not is_mark  # (then its own part is seen in front of the tissue)
            # (in the red pass, a blood-like piece floating over a piece's worth of pixels
            # and on the surface elsewhere: a red thread merged with the vessels it crosses,
            # judged by its floating part, deviation 63)
            part = (
                nearest_hue
                and p.red_part_floats
                and _floats_in_part(votes, p.min_length_px * area[best] / length[best])
            )
            if not is_mark and not (
                np.all(votes < 0)
                and (
                    _continues(v, on, lab_on, best, marks, delta, length)
                    or _like_a_mark(v, on[lab_on == best], best, marks, delta)
                )
            ):
                # (an undecided blood-like piece whose own disparity lies well above the
                # tissue's beside it is in front of it: a thread, not a vessel)
                nearer = (
                    nearest_hue
                    and p.first_marks
                    and np.all(votes < 0)
                    and _nearer_than_tissue(views, i, on[lab_on == best], tissue(), D)
                )
                if (
                    nearest_hue
                    and not nearer
                    and not (part or _floats(votes))
                    and not _at_tissue_disparity(
                        views, i, on[lab_on == best], tissue(), D, other=p.first_marks
                    )
                ):
                    # undecided or moving with the tissue in part: not told from a vessel of
                    # its hue (it may still join a thread found in front of the tissue), unless
                    # it holds the highlight along its axis (a glossy body, not a vessel)
                    if along is not None and np.all(votes < 0):
                        px = on[lab_on == best]
                        if _holds(along[i], v.rows[px], v.cols[px], p.min_length_px):
                            break
                        k[best] = False  # (another piece may hold it)
                        rank[best] = -1.0
                        best = int(np.argmax(rank))
                        continue
                    skipped += 1
                    if skipped > _RED_UNDECIDED:
                        return None, salience + top, 1.0, False
                    k[best] = False
                    rank[best] = -1.0
                    best = int(np.argmax(rank))
                    continue
                if (
                    nearest_hue
                    and (nearer or part or _floats(votes))
                    and not _contradicted(
                        views, i, on[lab_on == best], votes, tissue, D, p.contradicted_any
                    )
                ) or (
                    not nearest_hue
                    and not (
                        np.all(votes < 0)
                        and _at_tissue_disparity(
                            views, i, on[lab_on == best], [on[lab_on == m] for m in marks], D
                        )
                    )
                ):
                    # (a piece the surface test left open whose own disparity is the tissue's
                    # is a mark on it, in either pass)
                    if not nearest_hue and p.prefer_floating and np.all(votes < 0):
                        alt = _floating_instead(views, i, on, lab_on, k, rank, best, D, p)
                        if alt is not None:  # (a piece seen floating, not one undecided)
                            best, votes = alt
                            votes_of[best], split = votes, False
                    floating &= split or part or _floats(votes)
                    break
            # (a blood-like piece the surface test left open, at the tissue's own disparity:
            # a vessel, as a mark)
            marks.append(best)
            (v.red_marks if nearest_hue else v.first_marks).append(on[lab_on == best])
            k[best] = False
            rank[best] = -1.0
            best = int(np.argmax(rank))
        else:
            return (
                None,
                salience + top,
                1.0,
                False,
            )  # the most salient pieces are marks on the tissue
        if rank[best] <= 0:
            return None, salience + top, 1.0, False
        salience += float(rank[best])
        chosen.append((v, lab, means, length, on, lab_on, k, n, area, delta, rank, best, marks,
                       votes_of, known))  # fmt: skip
    # The pieces that join the chosen ones (tested only once both views have chosen one).
    for i, (v, lab, means, length, on, lab_on, k, n, area, delta, rank, best, marks,
            votes_of, known) in enumerate(chosen):  # fmt: skip
        # A piece of two dyes (a thread merged with a fibre where they cross) is of the dye
        # of its part seen in front of the tissue: the thread's other pieces join it.
        delta[best] = _main_dye(v.delta[on[lab_on == best]], votes_of[best], delta[best])
        # The frame's vessel hue: mean contrast of its blood-like pixels off the chosen piece.
        vessel = v.blood & (lab != best)
        d_vessel = _mean_rows(v.delta, vessel) if vessel.sum() >= _MIN_VESSEL_PX else None
        cos_vessels = max(
            cos_vessels, 1.0 if d_vessel is None else _cosine(d_vessel[1:], delta[best, 1:])
        )
        d_best = delta[best]
        # A blood-like thread is told from the vessels by its hue only where the two differ
        # (beyond ~8 degrees); of the vessels' own hue, by being in front of the tissue only.
        by_hue = (
            nearest_hue
            and d_vessel is not None
            and _cosine(d_vessel[1:], d_best[1:]) < _VESSEL_HUE_COS
        )
        # Other pieces of the same thread (split by an occluder or a crossing) share its dye.
        # A piece merged with a mark where they cross (a fibre) is judged by its part of the
        # thread's dye, when that part is as long as a piece must be (at the thread's width).
        k &= means >= p.keep_ratio * means[best]
        dye = delta
        same = _same_dye(delta, d_best)  # (recomputed only where a piece's dye changes)
        retry = k & (same < _SAME_DYE_COS)  # (only those: their pixels)
        retry[0] = retry[best] = False
        if retry.any():
            sel = retry[lab_on]
            part, count = _dye_part(v.delta[on[sel]], lab_on[sel], d_best, n)
            long_part = retry & (count * (length[best] / area[best]) >= p.min_length_px)
            if long_part.any():
                dye = np.where(long_part[:, None], part, delta)
                same = _same_dye(dye, d_best)
        k &= same >= _SAME_DYE_COS
        if by_hue:
            k &= same > _same_dye(dye, d_vessel)
        k[0] = k[best] = False
        candidates = k.copy()  # the pieces of the thread's dye, bright enough to join it
        # A joining piece is no mark on the tissue either (a fibre as light as a white thread);
        # among blood-like pieces it is seen in front of the tissue, as the chosen one.
        others = np.flatnonzero(k)
        others = others[np.argsort(-rank[others])][:_MAX_SURFACE_TESTS]
        k[:] = False
        for j in others.tolist():
            votes = votes_of[j] = _surface_votes(views, i, lab_on == j, on, D)
            # among blood-like pieces, one seen in front of the tissue at least in part (a
            # part of the thread merged with a vessel where they cross)
            is_mark = _a_mark(votes)
            if is_mark and not nearest_hue:  # a thread merged with fibres: its part floats
                piece_px = p.min_length_px * area[j] / length[j]
                is_mark, votes = _a_mark_of_one_dye(views, i, lab_on == j, on, D, votes, piece_px)
                votes_of[j] = votes
            k[j] = not is_mark and (
                not nearest_hue
                or np.any(votes == 0)
                or (
                    along is not None
                    and _holds(along[i], *_rc(v, on[lab_on == j]), p.min_length_px)
                )
                or (
                    p.first_marks
                    and np.all(votes < 0)
                    and _nearer_than_tissue(
                        views, i, on[lab_on == j], [on[lab_on == m] for m in marks] + known, D
                    )
                )
            )
            if is_mark:
                marks.append(j)
                if not nearest_hue:
                    v.first_marks.append(on[lab_on == j])
        # An undecided piece that is a fragment of a mark of its dye (as in the choice above)
        # does not join either: a fibre cut in two by a faint stretch or by the instrument;
        # nor, in the first pass, one whose own disparity is the tissue's (a fibre of a white
        # thread's dye the block test leaves open: a mark, as when choosing).
        for j in others.tolist():
            if k[j] and np.all(votes_of[j] < 0):
                k[j] = not (
                    _continues(v, on, lab_on, j, marks, delta, length)
                    or _like_a_mark(v, on[lab_on == j], j, marks, delta)
                    or (
                        not nearest_hue
                        and _at_tissue_disparity(
                            views, i, on[lab_on == j], [on[lab_on == m] for m in marks], D
                        )
                    )
                )
        k[best] = True
        if p.thread_depth_join:
            # A piece of the thread lies at its depth, which changes along it by its slope at
            # most: not a fibre on the tissue the surface test left open (deviation 62).
            joining = [j for j in np.flatnonzero(k).tolist()
                       if j != best and not _floats(votes_of.get(j, _NO_VOTE))]  # fmt: skip
            for j in _off_thread_depth(
                views, i, on, lab_on, best, joining, votes_of, D, p.touch_at_tissue
            ):
                k[j] = False
        if nearest_hue:
            # A red thread's fragments between the vessels it crosses are too short for the
            # surface test: they join at the thread's own disparity.
            undecided = [j for j in np.flatnonzero(candidates).tolist()
                         if not k[j] and np.all(votes_of.get(j, _NO_VOTE) < 0)]  # fmt: skip
            floating_px = np.concatenate(
                [on[lab_on == j][votes_of[j] != 1] for j in np.flatnonzero(k) if j in votes_of]
            )
            marks_px = [on[lab_on == j] for j in marks] + known
            for j in _at_thread_disparity(
                views, i, on, lab_on, floating_px, marks_px, undecided, D, p.local_join
            ):
                k[j] = True
        # Within a kept piece: not pixels far fainter than the piece (a branch touching it),
        # nor pixels of another colour (a vessel or fibre merged into the thread's piece),
        # nor, in a piece moving with the tissue in part, that part (a mark merged with it).
        px = on[k[lab_on]]  # the lo pixels of the kept pieces
        d_px = v.delta[px]
        hue = _same_dye(d_px, d_best)
        other = _other_dye_px(d_px, d_best, hue)
        mark = _mark_part(px, on, lab_on, votes_of, k, v if p.thread_through else None)
        other |= mark
        if by_hue:
            other |= hue <= _same_dye(d_px, d_vessel)
        sel = ~other & (v.s_lo[px] >= _CORE_FRACTION * means[lab[px]])  # (s_lo: S at them)
        mine = np.searchsorted(px, on[lab_on == best]) if p.cut_at_tissue and mark.any() else []
        if len(mine) and mark[mine].any():
            # a remnant the mark part's cut leaves of the chosen piece, at the tissue's depth
            # behind the thread: the rest of the fibre merged with it (deviation 72)
            drop = _remnants_at_tissue(
                views, i, px[mine], votes_of[best], sel[mine], D, p.min_length_px
            )
            sel[mine[drop]] = False
        px = px[sel] if sel.any() else np.flatnonzero(lab == best)
        core = np.zeros(v.lo.shape, np.uint8)
        core[v.rows[px], v.cols[px]] = 1
        v.grey_core = _grey_contrast(v, px)
        out.append(core)
    return out, salience, cos_vessels, floating


_NO_VOTE: Final = np.full(1, -1, np.int8)  # a piece the surface test did not look at
_THREAD_SLOPE: Final = 0.1  # a thread's disparity changes by <= 0.1 px per px along it (its
# depth slope: the ordering's DISPARITY_SLOPE)
_LOCAL_PX: Final = 32  # the thread's disparity next to a fragment: its pixels within 32 px
_MAX_GAP_PX: Final = 64  # a fragment farther from the thread than this is not judged by it


def _at_thread_disparity(
    views: list[_View],
    i: int,
    on: np.ndarray,
    lab_on: np.ndarray,
    thread: np.ndarray,
    marks: list[np.ndarray],
    cands: list[int],
    d: int,
    local: bool = False,
) -> list[int]:
    """Of the pieces ``cands`` of view ``i`` (undecided by the surface test), those at the
    thread's own disparity where they come near it: the disparity of the piece
    (:meth:`SurfaceTest.disparity`) is within SAME_DISPARITY_PX + _THREAD_SLOPE x gap of that
    of the thread's pixels within _LOCAL_PX of the point where the piece comes nearest (gap <=
    _MAX_GAP_PX, counted up to _LOCAL_PX), and not at the disparity of the tissue: of the
    background around it (where that resolves, :meth:`SurfaceTest.background_disparity`) or
    of the nearest of the ``marks`` (lo pixels of the pieces found to be marks on it).

    With ``local`` (deviation 68): a piece whose pixels taken together define no disparity (a
    long stretch whose depth changes along it) is read on its pixels near the thread
    (:func:`_local_disparity`), the slope counted over that reading's extra reach; where the
    thread's own disparity is not defined near the piece, one above each tissue reading by
    more than _NEARER_PX joins (as :func:`_nearer_than_tissue` judges a whole piece).

    The thread is its lo pixels ``thread`` not voted "on the surface"; a piece taken extends
    it (the nearest first). A vessel crossing the thread lies on the tissue behind it, at the
    tissue's disparity; the thread's fragments between the vessels it crosses are too short
    for the block-wise surface test (fewer blocks than it needs)."""
    v = views[i]
    if not cands or len(thread) == 0:
        return []
    st = _surface_test(views, i, d)
    pts = {j: (v.rows[on[lab_on == j]], v.cols[on[lab_on == j]]) for j in cands}
    left = list(cands)
    thread_xy = _xy(v.rows[thread], v.cols[thread])
    # each candidate's gap to the thread and the thread's point there (on <= 64 of its
    # pixels: the gap within ~2 px), updated as pieces are taken
    sample = {j: _xy(*pts[j], most=64) for j in left}
    gap, at = _nearest(cKDTree(thread_xy), thread_xy, sample, left)
    if v.tool is not None:  # the thread is hidden under the instrument, not missing there
        for j in left:
            gap[j] = _gap_off_tool(v.tool, sample[j], at[j], gap[j])
    near_marks = _Marks(st, v, marks)
    taken: list[int] = []
    while left:
        j = min(left, key=gap.__getitem__)
        if gap[j] > _MAX_GAP_PX:
            break
        left.remove(j)
        at_px = pts[j]  # the pixels read: the piece's (only for pieces near the thread)
        own = st.disparity(*at_px)
        reach = 0.0  # how much farther along than its gap the piece's reading lies, px
        if own is None and local:
            # a long piece whose disparity changes along it matches no single one: its own
            # disparity where it comes near the thread (deviation 68), read ~ (_LOCAL_PX +
            # radius) / 2 px farther along than the gap from the thread's
            own, at_px, radius = _local_disparity(st, *pts[j], at[j])
            reach = 0.5 * (_LOCAL_PX + radius)
        if own is None:
            continue
        dist = np.hypot(thread_xy[:, 0] - at[j][0], thread_xy[:, 1] - at[j][1])
        # (a stretch along the rows has no disparity of its own: a longer one then)
        d_thread = None
        for radius in (_LOCAL_PX, 2 * _LOCAL_PX):
            near = thread_xy[dist <= radius].astype(np.int64)
            d_thread = st.disparity(near[:, 0], near[:, 1])
            if d_thread is not None:
                break
        if d_thread is None and not local:
            continue
        d_bg = st.background_disparity(*at_px)
        d_mark = near_marks.disparity_near(*at_px)
        tissue = [t for t in (d_bg, d_mark) if t is not None]
        tol = SAME_DISPARITY_PX + _THREAD_SLOPE * (min(gap[j], _LOCAL_PX) + reach)
        if (
            abs(own - d_thread) <= tol
            if d_thread is not None
            # (the thread's own disparity not defined there, deviation 68: a piece nearer
            # than the tissue by each reading, as :func:`_nearer_than_tissue`)
            else bool(tissue) and all(own > t + _NEARER_PX for t in tissue)
        ) and not any(abs(own - t) <= SAME_DISPARITY_PX for t in tissue):
            taken.append(j)
            piece_xy = _xy(*pts[j])
            thread_xy = np.concatenate([thread_xy, piece_xy])
            g2, at2 = _nearest(cKDTree(piece_xy), piece_xy, sample, left)
            if v.tool is not None:
                for m in left:
                    g2[m] = _gap_off_tool(v.tool, sample[m], at2[m], g2[m])
            for m in left:
                if g2[m] < gap[m]:
                    gap[m], at[m] = g2[m], at2[m]
    return taken


def _off_thread_depth(
    views: list[_View],
    i: int,
    on: np.ndarray,
    lab_on: np.ndarray,
    best: int,
    joining: list[int],
    votes_of: dict,
    d: int,
    touch_at_tissue: bool = False,
) -> list[int]:
    """Of the pieces ``joining`` the chosen piece ``best`` of view ``i``, those behind the
    whole thread: the largest disparity of their blocks (:func:`_block_disparities`, of their
    pixels not voted on the surface, ``votes_of`` by piece) lies below the least of the
    thread's blocks another of them confirms (:func:`_farthest_reading`; none: no piece is
    judged) by more than SAME_DISPARITY_PX + _THREAD_SLOPE x gap (the thread's depth
    changes along it by its slope at most; the gap is the piece's least distance to it), or it
    lies nearer (by that slope) the depth of a piece already found behind it than the thread's
    (one object: a fibre's branches). The tissue lies behind the thread; a light fibre on it,
    left open by the block-wise surface test (a shaft or smooth tissue beside it), lies there.
    The thread is the chosen piece's pixels not voted on the surface, grown by every piece
    that joins (the nearest first; its blocks' disparities too). Not judged (they join): a
    piece without a disparity of its own; one within _TOUCH_PX of the thread (split from it by a strand
    crossing it: the chosen piece may be one strand of a loop, the piece past the crossing
    farther than any of it); and one whose straight gap to the thread meets the instrument
    (the thread may run on under it, its depth unknown there) (deviation 62).

    ``touch_at_tissue`` (deviation 65): a piece within _TOUCH_PX of the thread (any of its
    pixels, those voted on the surface too) is judged too
    when its own disparity (of its pixels not voted on the surface) is the tissue's beside it
    (:func:`_tissue_around`) and lies behind the thread's farthest block by more than the
    slope over its gap: a fibre on the tissue that the thread crosses, not a loop's strand past
    a crossing (which floats above the tissue as the thread does)."""
    if not joining:
        return []
    v = views[i]
    st = _surface_test(views, i, d)
    thread = on[lab_on == best][votes_of[best] != 1]
    far = _block_disparities(st, v.rows[thread], v.cols[thread])
    d_far = _farthest_reading(far)  # the thread's farthest block another of its blocks confirms
    if d_far is None:  # none: the thread's own depth is not measured (e.g. a highlight on it)
        return []
    pts = {}
    for j in joining:
        px = on[lab_on == j]
        votes = votes_of.get(j)
        own = px if votes is None or np.all(votes == 1) else px[votes != 1]
        pts[j] = (v.rows[own], v.cols[own])
    sample = {j: _xy(*pts[j], most=64) for j in joining}
    thread_xy = _xy(v.rows[thread], v.cols[thread])
    gap, at = _nearest(cKDTree(thread_xy), thread_xy, sample, joining)
    # (deviation 65: whether a piece touches the thread is read on all its pixels, those voted
    # on the surface too: a fibre's pixels beside the thread may be the ones voted)
    whole: dict = {}
    for j in joining if touch_at_tissue else []:
        px = on[lab_on == j]
        whole[j] = _xy(v.rows[px], v.cols[px], most=64)
    touch, _ = _nearest(cKDTree(thread_xy), thread_xy, whole, list(whole))
    left = list(joining)
    off: list[int] = []
    off_pieces: list[tuple[cKDTree, np.ndarray, int]] = []  # (tree, pixels, disparity) of each
    while left:
        j = min(left, key=(touch if whole else gap).__getitem__)
        left.remove(j)
        blocks = _block_disparities(st, *pts[j])
        if (
            touch_at_tissue
            and blocks
            and touch[j] <= _TOUCH_PX
            and not _crosses(v.tool, sample[j], at[j])
        ):
            own = st.disparity(*pts[j])
            if (
                own is not None
                and d_far - own > SAME_DISPARITY_PX + _THREAD_SLOPE * touch[j]
                and any(abs(own - t) <= SAME_DISPARITY_PX for t in _tissue_around(st, *pts[j]))
            ):
                off.append(j)
                piece_xy = _xy(*pts[j])
                off_pieces.append((cKDTree(piece_xy), piece_xy, own))
                continue
        if blocks and gap[j] > _TOUCH_PX and not _crosses(v.tool, sample[j], at[j]):
            near = _nearest_reading(blocks)  # the piece's nearest block
            # the depth slope (px of disparity a px of gap) it needs, beyond the disparity's
            # own uncertainty, to be the thread behind its farthest block; and to be the
            # object of a piece found behind it (a fibre's branch): it goes with the one that
            # needs the least
            slope = max(d_far - near - SAME_DISPARITY_PX, 0.0) / max(gap[j], 1.0)
            other = min(
                (
                    max(abs(near - d_off) - SAME_DISPARITY_PX, 0.0)
                    / max(_nearest(tree, xy, sample, [j])[0][j], 1.0)
                    for tree, xy, d_off in off_pieces
                ),
                default=np.inf,
            )
            if slope > _THREAD_SLOPE or other < slope:
                off.append(j)
                piece_xy = _xy(*pts[j])
                off_pieces.append((cKDTree(piece_xy), piece_xy, near))
                continue
        # a piece that joins (at the thread's depth, or not judged) extends the thread
        if blocks:
            d_far = min(d_far, *blocks)
        piece_xy = _xy(*pts[j])
        thread_xy = np.concatenate([thread_xy, piece_xy])
        if left:
            g2, at2 = _nearest(cKDTree(piece_xy), piece_xy, sample, left)
            for m in left:
                if g2[m] < gap[m]:
                    gap[m], at[m] = g2[m], at2[m]
            if whole:
                t2, _ = _nearest(cKDTree(piece_xy), piece_xy, whole, left)
                for m in left:
                    touch[m] = min(touch[m], t2[m])
    return off


def _remnants_at_tissue(
    views: list[_View],
    i: int,
    px: np.ndarray,
    votes: np.ndarray,
    kept: np.ndarray,
    d: int,
    min_px: float = 0.0,
) -> np.ndarray:
    """(len(px),) bool: of the chosen piece's lo pixels ``px`` (ascending; surface ``votes``
    (len(px),)) of view ``i``, those of a remnant the cut leaves (``kept`` (len(px),): its
    pixels left once its part moving with the tissue, another dye's and the faint ones are
    cut) that lies at the tissue's depth behind the thread. The kept pixels fall into
    8-connected parts; the thread is those seen in front of the tissue in part (votes 0;
    none: nothing is judged). Another part nowhere seen in front, of at least ``min_px``
    pixels (a piece's least length: a few pixels' disparity is no reading), is dropped when
    its own disparity (:meth:`SurfaceTest.disparity`) is the tissue's beside it (within
    SAME_DISPARITY_PX of :func:`_tissue_around`) and lies behind the thread part's farthest
    confirmed block (:func:`_farthest_reading`, of its pixels not voted on the surface) by
    more than SAME_DISPARITY_PX + _THREAD_SLOPE x its least distance to that part, as
    deviation 65 judges a piece touching the thread, or nearer a part dropped so than the
    thread and at its disparity (one object, as deviation 62 judges a fibre's branches); the
    parts are taken nearest the thread first: a light fibre merged with the thread
    through the part the cut took (the fibre's blocks at the tissue's disparity, left open by
    the block test). A strand of the thread cut off there floats above the tissue as the
    thread does, or lies at its depth. Asked only where :func:`_mark_part` cut the piece; the
    tissue's readings are taken last, for a part behind the thread (deviation 72)."""
    out = np.zeros(len(px), bool)
    if kept.all() or not kept.any() or not np.any(votes[kept] == 0):
        return out  # nothing cut from the piece, or no part of it seen in front of the tissue
    v = views[i]
    rows, cols = v.rows[px], v.cols[px]
    lab = np.empty(int(kept.sum()), np.int64)  # (px ascending: row-major, as label_pixels takes)
    n = label_pixels(rows[kept], cols[kept], lab)
    if n <= 2:
        return out  # one part: the cut split nothing off
    part = np.zeros(len(px), np.int64)
    part[kept] = lab
    front = np.bincount(part[votes == 0], minlength=n) > 0
    front[0] = False
    thread = front[part]
    st = _surface_test(views, i, d)
    sel = thread & (votes != 1)
    d_far = _farthest_reading(_block_disparities(st, rows[sel], cols[sel]))
    if d_far is None:
        return out
    tree = cKDTree(_xy(rows[thread], cols[thread]))
    size = np.bincount(part, minlength=n)
    gaps = {}
    for m in np.flatnonzero((size >= max(min_px, 1)) & ~front).tolist():
        if m == 0:
            continue  # (the pixels cut)
        sel = part == m
        gaps[m] = float(tree.query(_xy(rows[sel], cols[sel], most=64))[0].min())
    behind: list[tuple[cKDTree, int]] = []  # the parts dropped, with their disparities
    for m in sorted(gaps, key=gaps.__getitem__):  # the nearest to the thread first
        sel = part == m
        own = st.disparity(rows[sel], cols[sel])
        if own is None:
            continue
        xy = _xy(rows[sel], cols[sel], most=64)
        # behind the thread beyond its slope, or one object with a part found behind it
        # (nearer to that part than to the thread, at its disparity: a fibre's far stretch)
        with_off = any(
            abs(own - d_off) <= SAME_DISPARITY_PX and float(t.query(xy)[0].min()) < gaps[m]
            for t, d_off in behind
        )
        if not with_off and d_far - own <= SAME_DISPARITY_PX + _THREAD_SLOPE * gaps[m]:
            continue
        # (the tissue's readings last: nine background disparities)
        if any(abs(own - t) <= SAME_DISPARITY_PX for t in _tissue_around(st, rows[sel], cols[sel])):
            out[sel] = True
            behind.append((cKDTree(_xy(rows[sel], cols[sel])), own))
    return out


def _local_disparity(
    st: SurfaceTest, rows: np.ndarray, cols: np.ndarray, at: np.ndarray
) -> tuple[int | None, tuple[np.ndarray, np.ndarray], float]:
    """The disparity (:meth:`SurfaceTest.disparity`) of a piece's pixels (``rows``, ``cols``)
    (M,) within a radius of _LOCAL_PX (else 2 _LOCAL_PX) of its pixel nearest to the thread's
    point ``at`` (2,) (row, column), those pixels and the radius (None, all of them and 0 when
    neither defines one)."""
    near = np.argmin(np.hypot(rows - at[0], cols - at[1]))
    dist = np.hypot(rows - rows[near], cols - cols[near])
    for radius in (_LOCAL_PX, 2 * _LOCAL_PX):
        sel = dist <= radius
        if sel.all():  # (the whole piece: its disparity is known not to be defined)
            break
        own = st.disparity(rows[sel], cols[sel])
        if own is not None:
            return own, (rows[sel], cols[sel]), float(radius)
    return None, (rows, cols), 0.0


def _xy(rows: np.ndarray, cols: np.ndarray, most: int | None = None) -> np.ndarray:
    """(n, 2) float64 (row, column) of the pixels, every k-th of them when ``most`` is given
    (k = len // most, at least 1: about ``most`` of a long piece)."""
    step = 1 if most is None else max(len(rows) // most, 1)
    return np.c_[rows[::step], cols[::step]].astype(np.float64)


_TOUCH_PX: Final = 2 * MAX_HALF_WIDTH_PX  # a piece this near the thread may be split from it
# by a strand crossing it (as wide as a thread's response at most): its nearest thread pixel
# is then the crossing strand's, at another depth


def _tissue_around(st: SurfaceTest, rows: np.ndarray, cols: np.ndarray) -> list[int]:
    """The tissue's disparities (:meth:`SurfaceTest.background_disparity`, where it resolves)
    in the block of the surface test's grid that holds most of the pixels (``rows``,
    ``cols``) and in the eight blocks around it: a thin line's own block is often too smooth
    (or too taken by lines) to resolve the tissue's; the tissue's depth changes little from
    one block to the next (deviation 65)."""
    br, bc = block_of(rows, cols)
    nc = int(bc.max()) + 1
    at = int(np.bincount(br * nc + bc).argmax())
    r0, c0 = at // nc * BLOCK_PX, at % nc * BLOCK_PX
    h, w = st.this.shape
    out = []
    for dr in (-BLOCK_PX, 0, BLOCK_PX):
        for dc in (-BLOCK_PX, 0, BLOCK_PX):
            r, c = r0 + dr, c0 + dc
            if 0 <= r < h and 0 <= c < w:
                t = st.background_disparity(np.array([r]), np.array([c]))
                if t is not None:
                    out.append(t)
    return out


def _confirmed(blocks: list[int]) -> list[int]:
    """The block disparities of ``blocks`` that another of them confirms: within
    _THREAD_SLOPE x the block's size (a line's depth slope from one block to the next)."""
    step = _THREAD_SLOPE * BLOCK_PX
    return [b for n, b in enumerate(blocks)
            if any(abs(b - o) <= step for m, o in enumerate(blocks) if m != n)]  # fmt: skip


def _farthest_reading(blocks: list[int]) -> int | None:
    """The least of block disparities ``blocks`` that another of them confirms
    (:func:`_confirmed`); None where none does: a lone block, or blocks that disagree (a
    highlight's view-dependent match, a partner met by another line) measure no depth of the
    thread."""
    return min(_confirmed(blocks), default=None)


def _nearest_reading(blocks: list[int]) -> int:
    """The largest of a piece's block disparities ``blocks`` that another of its blocks
    confirms (:func:`_confirmed`), or the largest where none does (a block matched off by
    error, e.g. where its partner meets another line, reads alone)."""
    return max(_confirmed(blocks) or blocks)


def _block_disparities(st: SurfaceTest, rows: np.ndarray, cols: np.ndarray) -> list[int]:
    """The disparities (:meth:`SurfaceTest.disparity`) of the pixels (``rows``, ``cols``) in
    each block of the surface test's grid (:func:`segment_surface.block_of`) where one is
    defined (a slanted thread's disparity changes along it)."""
    br, bc = block_of(rows, cols)
    key = br * (int(bc.max()) + 1) + bc if len(rows) else br
    out = []
    for b in np.unique(key).tolist():
        sel = key == b
        dd = st.disparity(rows[sel], cols[sel])
        if dd is not None:
            out.append(dd)
    return out


def _crosses(tool: np.ndarray | None, sample: np.ndarray, at: np.ndarray) -> bool:
    """Whether the straight line from the point of ``sample`` (m, 2) nearest to ``at`` (2,)
    (row and column) to ``at`` meets the instrument ``tool`` (H, W) bool (None: none)."""
    if tool is None:
        return False
    a = sample[np.argmin(np.hypot(*(sample - at).T))]
    n = int(np.ceil(np.hypot(*(at - a)))) + 1
    t = np.linspace(0.0, 1.0, n)
    r = np.rint(a[0] + t * (at[0] - a[0])).astype(np.intp)
    c = np.rint(a[1] + t * (at[1] - a[1])).astype(np.intp)
    return bool(tool[r, c].any())


def _contradicted(
    views: list[_View],
    i: int,
    px: np.ndarray,
    votes: np.ndarray,
    marks: Callable[[], list[np.ndarray]],
    d: int,
    any_reading: bool = False,
) -> bool:
    """Whether the part of the blood-like piece of view ``i`` of lo pixels ``px`` that the
    block-wise surface test voted in front of the tissue (``votes`` == 0, per pixel) is not
    seen nearer than the tissue by its own disparity (:meth:`SurfaceTest.disparity`): at most
    SAME_DISPARITY_PX above the tissue's (of its block's background where that resolves, else
    of the nearest of the marks found on it, lo pixels of each as ``marks()`` gives them). In
    front of the tissue means nearer the cameras, a larger disparity; the two depth cues
    disagree, and a red thread of the vessels' hue is told from them by depth only. Uneven
    light (vignetting, fixed in the image, not on the tissue) biases a dark block's matches
    towards disparity 0, so that a vessel there seemed to float; a thread merged with a
    vessel is judged by its own part. ``any_reading`` (deviation 58): either reading that
    resolves contradicts, not the first alone: the same light biases the block's background
    itself (a vessel at the marks' disparity, its block's background 3-5 px below it)."""
    front = px[votes == 0]
    if len(front) == 0:
        return False
    own, tissue = _own_and_tissue(views, i, front, marks, d)
    if own is None:
        return False
    if any_reading:
        return any(t is not None and own <= t + SAME_DISPARITY_PX for t in tissue)
    first = next((t for t in tissue if t is not None), None)
    return first is not None and own <= first + SAME_DISPARITY_PX


_NEARER_PX: Final = 2 * SAME_DISPARITY_PX  # a piece nearer than the tissue by its own disparity:
# above the tissue's by more than two of the test's steps (deviation 53)
_TISSUE_MARKS: Final = 3  # the tissue's disparity off a resolving block: of the 3 nearest marks


def _nearer_than_tissue(
    views: list[_View], i: int, px: np.ndarray, marks: list[np.ndarray], d: int
) -> bool:
    """Whether the piece of view ``i`` of lo pixels ``px`` has a disparity of its own
    (:meth:`SurfaceTest.disparity`) more than _NEARER_PX above the tissue's, by each of its
    two readings that resolves (at least one): the background of its block, and the median of
    the _TISSUE_MARKS nearest of the ``marks`` (lo pixels of the marks found on the tissue;
    one line at another depth, an instrument's edge taken for a mark, does not move it; in a
    view without marks, the other view's). A block beside the instrument can resolve at a
    disparity off the tissue's (the shaft's edge in it). The counterpart of
    :func:`_at_tissue_disparity`: a blood-like line the block-wise surface test leaves open
    (the tissue beside it seldom resolves) is seen in front of the tissue by its own depth,
    which a vessel, lying on it, is not (deviation 53)."""
    v = views[i]
    st = _surface_test(views, i, d)
    rows, cols = v.rows[px], v.cols[px]
    own = st.disparity(rows, cols)
    if own is None:
        return False
    tissue = [
        st.background_disparity(rows, cols),
        _Marks(st, v, marks).disparity_of_nearest(rows, cols, _TISSUE_MARKS),
    ]
    if tissue[1] is None:  # no mark found in this view yet: the other view's, on the same rows
        tissue[1] = _other_view_tissue(views, i, rows, cols, d)
    known = [t for t in tissue if t is not None]
    return bool(known) and all(own > t + _NEARER_PX for t in known)


def _other_view_tissue(
    views: list[_View], i: int, rows: np.ndarray, cols: np.ndarray, d: int
) -> float | None:
    """The tissue's disparity near the pixels (``rows``, ``cols``) of view ``i`` read from the
    marks found in the other view (by either pass): the median of the _TISSUE_MARKS nearest to
    the same pixels there (a disparity is the same number in both views; the marks' positions
    are off by it, a few tens of px, which the median of the nearest marks spans). None
    without any. A red pass that found no mark in this view yet is not left without the
    tissue's depth (deviation 53)."""
    o = views[1 - i]
    marks = o.first_marks + o.red_marks
    if not marks:
        return None
    st = _surface_test(views, 1 - i, d)
    return _Marks(st, o, marks).disparity_of_nearest(rows, cols, _TISSUE_MARKS)


def _gap_off_tool(tool: np.ndarray, sample: np.ndarray, at: np.ndarray, gap: float) -> float:
    """The part of a fragment's ``gap`` (px) to the thread that lies off the instrument
    ``tool`` (H, W) bool: on the straight line from the fragment's point nearest to the
    thread's point ``at`` (2,) (of its ``sample`` points (m, 2), row and column). A thread
    passing under the shaft is hidden there, not missing; gaps within _MAX_GAP_PX are kept."""
    if gap <= _MAX_GAP_PX:
        return gap
    a = sample[np.argmin(np.hypot(*(sample - at).T))]
    t = np.linspace(0.0, 1.0, int(np.ceil(gap)) + 1)
    r = np.rint(a[0] + t * (at[0] - a[0])).astype(np.intp)
    c = np.rint(a[1] + t * (at[1] - a[1])).astype(np.intp)
    return gap * float(np.count_nonzero(~tool[r, c])) / len(t)


def _nearest(tree: cKDTree, xy: np.ndarray, sample: dict, keys: list[int]) -> tuple[dict, dict]:
    """For each of ``keys``, the least distance from its ``sample`` points (m, 2) to the points
    ``xy`` (N, 2) of ``tree``, and the point of ``xy`` where it is reached (one query)."""
    if not keys:
        return {}, {}
    pts = np.concatenate([sample[j] for j in keys])
    sizes = np.array([len(sample[j]) for j in keys])
    dist, idx = tree.query(pts)
    starts = np.cumsum(sizes) - sizes
    least = np.minimum.reduceat(dist, starts)
    gap, at = {}, {}
    for n, j in enumerate(keys):
        a = int(starts[n] + np.argmin(dist[starts[n] : starts[n] + sizes[n]]))
        gap[j], at[j] = float(least[n]), xy[int(idx[a])]
    return gap, at


def _at_tissue_disparity(
    views: list[_View],
    i: int,
    px: np.ndarray,
    marks: list[np.ndarray],
    d: int,
    other: bool = False,
) -> bool:
    """Whether the piece of view ``i`` of lo pixels ``px`` has a disparity of its own
    (:meth:`SurfaceTest.disparity`) within SAME_DISPARITY_PX of the tissue's: of the background
    of its block (where that resolves) or of the nearest of the ``marks`` (lo pixels of the
    pieces found to be marks on the tissue). A piece the block-wise surface test left open
    (too few blocks resolve) that matches the tissue's disparity is a mark on it too.
    ``other``: or of the marks found in the other view (:func:`_other_view_tissue`)."""
    own, tissue = _own_and_tissue(views, i, px, lambda: marks, d, other)
    return own is not None and any(
        t is not None and abs(own - t) <= SAME_DISPARITY_PX for t in tissue
    )


def _own_and_tissue(
    views: list[_View],
    i: int,
    px: np.ndarray,
    marks: Callable[[], list[np.ndarray]],
    d: int,
    other: bool = False,
) -> tuple[float | None, Iterator[float | None]]:
    """The disparity of view ``i``'s lo pixels ``px`` of their own
    (:meth:`SurfaceTest.disparity`; None where it does not resolve), and the tissue's beside
    them, each read when asked: of the background of their block, then of the nearest of the
    ``marks`` (lo pixels of the pieces found to be marks on the tissue; None where either
    does not resolve)."""
    v = views[i]
    st = _surface_test(views, i, d)
    rows, cols = v.rows[px], v.cols[px]

    def tissue() -> Iterator[float | None]:
        yield st.background_disparity(rows, cols)
        yield _Marks(st, v, marks()).disparity_near(rows, cols)
        if other:
            yield _other_view_tissue(views, i, rows, cols, d)

    return st.disparity(rows, cols), tissue()


def _surface_test(views: list[_View], i: int, d: int) -> SurfaceTest:
    """View ``i``'s :class:`SurfaceTest` against the other view (made once, on demand)."""
    v = views[i]
    if v._surface is None or v._surface.dmax != d:
        v._surface = SurfaceTest(v.grey(), views[1 - i].grey(), v.far(), d, look_left=(i == 0))
    return v._surface


class _Marks:
    """The marks on the tissue found in a view (lo pixels of each, ``marks``): which is
    nearest to a set of pixels (on <= 256 sampled pixels of each mark, one k-d tree), and
    its disparity (:meth:`SurfaceTest.disparity`, computed once per mark)."""

    def __init__(self, st: SurfaceTest, v: _View, marks: list[np.ndarray]) -> None:
        self.st, self.v, self.marks = st, v, marks
        self.known: dict[int, int | None] = {}
        self.tree: cKDTree | None = None
        if marks:
            steps = [max(len(px) // 256, 1) for px in marks]
            xy = [
                np.c_[v.rows[px[::s]], v.cols[px[::s]]] for px, s in zip(marks, steps, strict=True)
            ]
            self.owner = np.concatenate([np.full(len(a), m) for m, a in enumerate(xy)])
            self.tree = cKDTree(np.concatenate(xy).astype(np.float64))

    def disparity_near(self, rows: np.ndarray, cols: np.ndarray) -> int | None:
        """The disparity of the mark nearest to the pixels (``rows``, ``cols``) (on <= 64 of
        them), None without marks."""
        if self.tree is None or len(rows) == 0:
            return None
        dist, idx = self.tree.query(_xy(rows, cols, most=64))
        m = int(self.owner[int(idx[int(np.argmin(dist))])])
        if m not in self.known:
            px = self.marks[m]
            self.known[m] = self.st.disparity(self.v.rows[px], self.v.cols[px])
        return self.known[m]

    def disparity_of_nearest(self, rows: np.ndarray, cols: np.ndarray, n: int) -> float | None:
        """The median disparity of the ``n`` marks nearest to the pixels (``rows``, ``cols``)
        (on <= 64 of them; of those whose disparity resolves), None without any: the tissue's
        beside them, which one line at another depth (an instrument's edge taken for a mark)
        does not move."""
        if self.tree is None or len(rows) == 0:
            return None
        # each mark's sampled pixels to the nearest of those pixels
        dist, _ = cKDTree(_xy(rows, cols, most=64)).query(self.tree.data)
        least = np.full(len(self.marks), np.inf)
        np.minimum.at(least, self.owner, dist)
        found = []
        for m in np.argsort(least).tolist():
            if m not in self.known:
                px = self.marks[m]
                self.known[m] = self.st.disparity(self.v.rows[px], self.v.cols[px])
            if self.known[m] is not None:
                found.append(self.known[m])
            if len(found) == n:
                break
        return float(np.median(found)) if found else None


def _near_blood(v: _View, core: np.ndarray, rect: tuple[int, int, int, int] | None = None) -> bool:
    """:func:`_near` of the view's blood-like candidate pixels and ``core`` (H, W) uint8 (of
    bounding box ``rect``, when known)."""
    rows, cols = v.rows[v.blood], v.cols[v.blood]
    return _near(None, core, (rows, cols), rect)


def _near(
    other: np.ndarray | None,
    core: np.ndarray,
    other_px: tuple | None = None,
    rect: tuple[int, int, int, int] | None = None,
) -> bool:
    """Whether at least half of the ``core`` (H, W) uint8 pixels have a pixel of ``other``
    (H, W) uint8 (or of the pixels ``other_px``, rows and columns) within _GLINT_SIDE_PX (a
    highlight's distance to the sides of its thread); on the core's bounding box grown by
    that (``rect``: the core's, when known)."""
    x, y, w, h = cv2.boundingRect(core) if rect is None else rect
    if w == 0:
        return False
    m = _GLINT_SIDE_PX
    H, W = core.shape
    r0, r1, c0, c1 = max(y - m, 0), min(y + h + m, H), max(x - m, 0), min(x + w + m, W)
    if other is not None:
        near = np.ascontiguousarray(other[r0:r1, c0:c1])
    else:
        rows, cols = other_px
        inside = (rows >= r0) & (rows < r1) & (cols >= c0) & (cols < c1)
        near = np.zeros((r1 - r0, c1 - c0), np.uint8)
        near[rows[inside] - r0, cols[inside] - c0] = 1
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
    reach = cv2.dilate(near, k)
    c = core[r0:r1, c0:c1]
    return cv2.countNonZero(reach & c) >= 0.5 * cv2.countNonZero(c)


_GLINT_SIDE_PX: Final = 3  # a highlight along a thread <= 6 px wide: its sides within 3 px


def _rc(v: _View, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the view's lo pixels ``px``."""
    return v.rows[px], v.cols[px]


def _holds(core: np.ndarray, rows: np.ndarray, cols: np.ndarray, min_px: float) -> bool:
    """Whether the piece of pixels (``rows``, ``cols``) holds a stretch of the line ``core``
    (H, W) uint8 along it: at least ``min_px`` (a piece's least length) of the core's pixels
    lie within _GLINT_SIDE_PX of the piece's (on the piece's bounding box)."""
    if len(rows) == 0:
        return False
    m = _GLINT_SIDE_PX
    H, W = core.shape
    r0, r1 = max(int(rows.min()) - m, 0), min(int(rows.max()) + m + 1, H)
    c0, c1 = max(int(cols.min()) - m, 0), min(int(cols.max()) + m + 1, W)
    piece = np.zeros((r1 - r0, c1 - c0), np.uint8)
    piece[rows - r0, cols - c0] = 1
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
    return cv2.countNonZero(cv2.dilate(piece, k) & core[r0:r1, c0:c1]) >= min_px


def _main_dye(d_px: np.ndarray, votes: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """The contrast (C,) of a piece: its mean contrast ``mean`` (C,), or, when its pixels'
    contrasts ``d_px`` (M, C) are of two dyes (:func:`_two_dyes`: a dark thread and a light
    fibre that cross), the mean of the part with more pixels voted in front of the tissue
    (surface ``votes`` (M,), :func:`_surface_votes`; a fibre is a mark on it)."""
    dark = _two_dyes(d_px)
    if dark is None:
        return mean
    floats = [int(np.count_nonzero(votes[part] == 0)) for part in (dark, ~dark)]
    if floats[0] == floats[1]:
        return mean  # nothing tells the two apart
    part = dark if floats[0] > floats[1] else ~dark
    return _mean_rows(d_px, part)


def _two_dyes(d_px: np.ndarray, min_px: float | None = None) -> np.ndarray | None:
    """(M,) bool, the darker part of a piece's pixels (contrasts ``d_px`` (M, C)) when they
    split by brightness sign into two parts of >= _MIXED_SHARE each (or, given ``min_px``, of
    >= ``min_px`` pixels each: as long as a piece must be) and of different dyes
    (:func:`_same_dye` < _SAME_DYE_COS), else None."""
    dark = d_px[:, 0] < 0
    n_dark = int(np.count_nonzero(dark))
    least = _MIXED_SHARE * len(dark) if min_px is None else min(_MIXED_SHARE * len(dark), min_px)
    if min(n_dark, len(dark) - n_dark) < least:
        return None
    parts = [_mean_rows(d_px, dark), _mean_rows(d_px, ~dark)]
    if _same_dye(parts[0][None], parts[1])[0] >= _SAME_DYE_COS:
        return None
    return dark


def _a_mark_of_one_dye(
    views: list[_View],
    i: int,
    sel: np.ndarray,
    on: np.ndarray,
    d: int,
    votes: np.ndarray,
    min_px: float,
) -> tuple[bool, np.ndarray]:
    """Whether a piece of view ``i`` (its lo pixels ``on[sel]``, surface ``votes`` (M,)) is a
    mark on the tissue (:func:`_a_mark`) as a whole, and its votes: not when it is of two dyes
    (:func:`_two_dyes`) and the part of one of them, tested alone, is seen in front of the
    tissue (:func:`_floats`); that part's pixels then take their own votes. A thread merged
    with the fibres it crosses is one piece whose votes the fibres outnumber: a block that
    holds both takes the fibres' disparity. (It loses the fibres' part later:
    :func:`_mark_part` and the pixels' dye.) One more surface test, on such pieces only. Each
    dye's part is >= 1/4 of the pixels or >= ``min_px`` (a piece's least length at this
    piece's width): a short fibre merged into a long thread takes a block's votes too."""
    if not _a_mark(votes):
        return False, votes
    v = views[i]
    px = on[sel]
    dark = _two_dyes(v.delta[px], min_px)
    if dark is None:
        return True, votes
    # the part that votes "on the surface" least (the other made the piece a mark)
    share = [np.count_nonzero(votes[m] == 1) / max(np.count_nonzero(votes[m] >= 0), 1)
             for m in (dark, ~dark)]  # fmt: skip
    part = dark if share[0] <= share[1] else ~dark
    sub = np.zeros(len(on), bool)
    sub[np.flatnonzero(sel)[part]] = True
    own = _surface_votes(views, i, sub, on, d)
    if not _floats(own):
        return True, votes
    out = votes.copy()
    out[part] = own
    return False, out


_MIXED_SHARE: Final = 1.0 - _MARK_SHARE  # a thread merged with a mark keeps >= 1/4 of its own


def _one_object(
    cores: list[np.ndarray], d: int, rects: list[tuple[int, int, int, int]] | None = None
) -> bool:
    """Whether the core pixels (H, W) uint8 chosen in the two views are one object seen twice:
    at least half of one view's core pixels have a core pixel of the other view on the same
    row within [0, d] of disparity (:func:`_has_partner`; the view where more of the thread is
    hidden holds the fewer pixels, and those have their partners). ``rects``: the cores'
    bounding boxes, when known."""
    pts = []
    for j, c in enumerate(cores):  # on each core's bounding box: a few % of the image
        x, y, w, h = cv2.boundingRect(c) if rects is None else rects[j]
        rows, cols = _points(c[y : y + h, x : x + w])
        pts.append((rows + y, cols + x))
    width = cores[0].shape[1]
    for i in range(2):
        rows, cols = pts[i]
        if len(rows) == 0:
            continue
        keys = _row_keys(*pts[1 - i], width, d)
        hits = _has_partner(rows, cols, keys, width, d, look_left=(i == 0))
        if np.count_nonzero(hits) >= 0.5 * len(rows):
            return True
    return False


def _surface_votes(
    views: list[_View], i: int, sel: np.ndarray, on: np.ndarray, d: int
) -> np.ndarray:
    """Per pixel ``on[sel]`` (indices of view ``i``'s lo pixels) of a piece: 1 where it moves
    with the tissue beside it, 0 where not, -1 undecided
    (:meth:`core.segment_surface.SurfaceTest.votes`)."""
    v = views[i]
    v._surface = _surface_test(views, i, d)
    px = on[sel]
    return v._surface.votes(v.rows[px], v.cols[px])


_FLOATING_TESTS: Final = 2  # pieces, marks not counted, tried past an undecided first choice


def _floating_instead(
    views: list[_View],
    i: int,
    on: np.ndarray,
    lab_on: np.ndarray,
    k: np.ndarray,
    rank: np.ndarray,
    best: int,
    d: int,
    p: SegmentationParams,
) -> tuple[int, np.ndarray] | None:
    """The piece (and its surface votes) to choose instead of ``best``, which the surface test
    left wholly undecided (deviation 49): the first piece by rank, at least ``keep_ratio`` as
    salient, seen in front of the tissue (:func:`_floats`), among the next _FLOATING_TESTS
    that are no marks on it (marks are passed over; at most _MAX_SURFACE_TESTS tested); None
    when none is."""
    cand = np.flatnonzero(k & (rank >= p.keep_ratio * rank[best]))
    cand = cand[cand != best]
    left = _FLOATING_TESTS
    for j in cand[np.argsort(-rank[cand])][:_MAX_SURFACE_TESTS].tolist():
        votes = _surface_votes(views, i, lab_on == j, on, d)
        if _floats(votes):
            return j, votes
        if not _a_mark(votes):
            left -= 1
            if left == 0:
                break
    return None


def _like_a_mark(v: _View, px: np.ndarray, piece: int, marks: list[int], delta: np.ndarray) -> bool:
    """Whether ``piece`` (its lo pixels ``px``) lies in fewer blocks than the surface test
    needs to decide (:mod:`core.segment_surface`: it can never be decided) and shares the dye
    (:func:`_same_dye` >= _SAME_DYE_COS of the mean contrasts ``delta`` (n, C)) of one of the
    ``marks`` found in the view: a fragment of the frame's fibres or vessels, not a thread."""
    if not marks:
        return False
    m = np.asarray(marks)
    if not np.any(_same_dye(delta[m], delta[piece]) >= _SAME_DYE_COS):
        return False
    return undecidable(v.rows[px], v.cols[px], v.lo.shape[1])


def _continues(
    v: _View,
    on: np.ndarray,
    lab_on: np.ndarray,
    piece: int,
    marks: list[int],
    delta: np.ndarray,
    length: np.ndarray,
) -> bool:
    """Whether ``piece`` is a fragment of one of the ``marks`` (pieces found to be marks on the
    tissue): it is no longer than that mark (``length`` (n,) px: the mark was long enough for
    the surface test to decide, the fragment too short), shares its dye (:func:`_same_dye` >=
    _SAME_DYE_COS of the pieces' mean contrasts ``delta`` (n, C)) and comes within _BAND_PX of
    it. ``on`` (M,) indexes the view's lo pixels of the shape-ok pieces, ``lab_on`` (M,) their
    pieces. (A long piece left undecided is so for want of texture around it, not of length.)"""
    if not marks:
        return False
    marks_a = np.asarray(marks)
    marks_a = marks_a[
        (_same_dye(delta[marks_a], delta[piece]) >= _SAME_DYE_COS)
        & (length[marks_a] >= length[piece])
    ]
    if len(marks_a) == 0:
        return False
    px = on[lab_on == piece]
    rows, cols = v.rows[px], v.cols[px]
    r0, c0 = int(rows.min()) - _BAND_PX, int(cols.min()) - _BAND_PX
    h, w = int(rows.max()) + _BAND_PX + 1 - r0, int(cols.max()) + _BAND_PX + 1 - c0
    mk = on[np.isin(lab_on, marks_a)]
    mr, mc = v.rows[mk] - r0, v.cols[mk] - c0
    near = (mr >= 0) & (mr < h) & (mc >= 0) & (mc < w)
    if not near.any():
        return False
    box = np.zeros((h, w), np.uint8)  # the piece's box grown by the band (may pass the edge)
    box[mr[near], mc[near]] = 1
    box = cv2.dilate(box, np.ones((2 * _BAND_PX + 1, 2 * _BAND_PX + 1), np.uint8))
    meet = box[rows - r0, cols - c0] > 0  # the piece's pixels within the band of a mark
    if not meet.any():
        return False
    # One line: where they meet, the piece runs on in the mark's direction (a thread passing
    # under an instrument meets its edge, a line as well, at an angle).
    at = np.array([rows[meet].mean(), cols[meet].mean()])
    mine = np.hypot(rows - at[0], cols - at[1]) <= _MEET_PX
    theirs = np.hypot(v.rows[mk] - at[0], v.cols[mk] - at[1]) <= _MEET_PX
    return _direction_cos(rows[mine], cols[mine], v.rows[mk][theirs], v.cols[mk][theirs]) >= (
        _ONE_LINE_COS
    )


_MEET_PX: Final = 4 * _BAND_PX  # a line's direction where two pieces meet: within 16 px
_ONE_LINE_COS: Final = float(np.cos(np.radians(30.0)))  # one line bends < 30 deg over that


def _direction_cos(r1: np.ndarray, c1: np.ndarray, r2: np.ndarray, c2: np.ndarray) -> float:
    """|cos| of the angle between the principal axes of two pixel sets (0 when either has
    fewer than 3 pixels: no direction)."""
    axes = []
    for r, c in ((r1, c1), (r2, c2)):
        if len(r) < 3:
            return 0.0
        cov = np.cov(np.stack([r, c]).astype(np.float64))
        axes.append(np.linalg.eigh(cov)[1][:, -1])
    return float(abs(axes[0] @ axes[1]))


def _mark_part(
    px: np.ndarray,
    on: np.ndarray,
    lab_on: np.ndarray,
    votes_of: dict,
    keep: np.ndarray,
    v: _View | None = None,
) -> np.ndarray:
    """(len(px),) bool: of the lo pixels ``px`` (ascending) of the kept pieces (``keep`` (n,)),
    those voted "on the surface" (:func:`_surface_votes`, ``votes_of`` by piece) in a piece
    that moves with the tissue in part: more of its decided votes than the block test's errors
    (over 1 - _MARK_SHARE of them) say so. ``on`` (M,) indexes the view's lo pixels of the
    shape-ok pieces (ascending), ``lab_on`` (M,) their pieces. Given the view ``v`` (its
    surface test, ``thread_through``), not those of a block where the thread goes on
    (:func:`_thread_through`)."""
    out = np.zeros(len(px), bool)
    for j, votes in votes_of.items():
        if not keep[j]:
            continue
        decided = np.count_nonzero(votes >= 0)
        surface = votes == 1
        if decided == 0 or np.count_nonzero(surface) <= (1.0 - _MARK_SHARE) * decided:
            continue
        if v is not None:
            surface &= ~_thread_through(v, on[lab_on == j], votes)
        # the piece's pixels on[lab_on == j] are ascending, as px: find them in px
        out[np.searchsorted(px, on[lab_on == j][surface])] = True
    return out


_RESOLVED_PX: Final = 2.0 * SAME_DISPARITY_PX  # disparities this far apart are two surfaces
# to the block test (its _RESOLVE_PX)


def _thread_through(v: _View, px: np.ndarray, votes: np.ndarray) -> np.ndarray:
    """(len(px),) bool: of a kept piece's lo pixels ``px`` (surface ``votes`` (len(px),)),
    those voted "on the surface" in a block (:func:`segment_surface.block_of`) where their own
    disparity is nearer that of the piece's part seen in front of the tissue in a block beside
    it (8-neighbours) than the tissue's disparity in their block (the background the vote
    compared them with, :meth:`SurfaceTest.background_disparity` near it), that part being
    itself in front of that tissue by _RESOLVED_PX at least: the thread goes on through that
    block, nearer the tissue than the block test resolves (~3 px), and no mark (at the
    tissue's depth) merged with it is there. A mark's own floating vote (a block test's error)
    is at the tissue's disparity and keeps nothing; nor does a block where a disparity is not
    defined.
    (Deviation 60.)"""
    out = np.zeros(len(px), bool)
    st = v._surface  # the view's surface test that gave ``votes``
    if st is None or not np.any(votes == 0):
        return out
    rows, cols = v.rows[px], v.cols[px]
    br, bc = block_of(rows, cols)
    nb = int(bc.max()) + 2  # (a block beside the last column keys apart from the next row)
    key = br * nb + bc
    floating = np.unique(key[votes == 0])
    own: dict[int, int | None] = {}  # the floating part's disparity in its blocks

    def floating_d(f: int) -> int | None:
        if f not in own:
            sel = (key == f) & (votes == 0)
            own[f] = st.disparity(rows[sel], cols[sel])
        return own[f]

    for b in np.unique(key[votes == 1]).tolist():
        beside = floating[(np.abs(floating // nb - b // nb) <= 1)
                          & (np.abs(floating % nb - b % nb) <= 1)]  # fmt: skip
        if not len(beside):
            continue
        sel = (key == b) & (votes == 1)
        d = st.disparity(rows[sel], cols[sel])
        if d is None:
            continue
        tissue = st.background_disparity(rows[sel], cols[sel], near=d)
        if tissue is None:
            continue
        for f in beside.tolist():
            d_f = floating_d(f)
            if d_f is not None and d_f - tissue >= _RESOLVED_PX and abs(d - d_f) < abs(d - tissue):
                out[sel] = True
                break
    return out


def _floats(votes: np.ndarray) -> bool:
    """Whether a piece is seen in front of the tissue: it has decided votes
    (:func:`_surface_votes`) and at most 1 - _MARK_SHARE of them say "on the surface"."""
    decided = np.count_nonzero(votes >= 0)
    return decided > 0 and np.count_nonzero(votes == 1) <= (1.0 - _MARK_SHARE) * decided


def _floats_in_part(votes: np.ndarray, piece_px: float) -> bool:
    """Whether a piece is seen in front of the tissue over at least ``piece_px`` of its pixels
    (votes 0, :func:`_surface_votes`: as many as a piece of its width must hold) and over more
    of them than it is seen on the surface (votes 1): a thread merged with the marks it
    crosses, mostly thread (deviation 63). A vessel under uneven light, voted in front over a
    third of it, is not."""
    front = np.count_nonzero(votes == 0)
    return front >= piece_px and front > np.count_nonzero(votes == 1)


def _a_mark(votes: np.ndarray) -> bool:
    """Whether a piece is a mark on the tissue: >= _MARK_SHARE of its decided votes
    (:func:`_surface_votes`) say it moves with the tissue. A thread merged with a fibre or a
    vessel where they cross is a mark only in part, and stays (without that part)."""
    decided = np.count_nonzero(votes >= 0)
    return decided > 0 and np.count_nonzero(votes == 1) >= _MARK_SHARE * decided


def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    """Cosine of the angle between two contrast vectors (C,)."""
    return float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-9)


def noise_sigma(f: np.ndarray, row_step: int = _NOISE_ROW_STEP) -> np.ndarray:
    """(C,) robust pixel-noise sigma of each channel of ``f`` (H, W, C): the median absolute
    difference of horizontal neighbours on every ``row_step``-th row (texture and edges
    are sparse there; the differences are symmetric about 0), as a Gaussian sigma; at least
    the uint8 quantisation noise."""
    sub = f[::row_step]
    d = cv2.absdiff(sub[:, 1:], sub[:, :-1]).reshape(-1, f.shape[2])  # (N, C)
    mid = d.shape[0] // 2
    d = np.ascontiguousarray(d.T)  # (C, N): each channel's row is read without a copy
    mad = np.array([_kth_smallest(d[j : j + 1], mid) for j in range(d.shape[0])], np.float32)
    return np.maximum(1.4826 * mad / np.sqrt(2.0), _QUANT_SIGMA)


def _same_dye(delta: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Cosine between colour contrasts (M, C) and ``ref`` (C,): on the chroma channels (hue
    of the contrast, independent of its strength and of lighting) when there is colour, and
    where the brightness contrast has the other sign at most the cosine of the whole contrasts
    (brightness and chroma); the brightness sign alone for grey.

    A dye that differs from the tissue mostly in hue (green on pink) has a brightness contrast
    near 0 whose sign is shading and noise: its whole contrast keeps its direction there. A
    light fibre and a dark thread of one hue differ in the direction of the whole contrast."""
    same_sign = delta[:, 0] * ref[0] >= 0
    if delta.shape[1] == 1:
        return np.where(same_sign, 1.0, -1.0)
    d, r = delta[:, 1:], ref[1:]
    nr = float(np.linalg.norm(r))
    if nr < _GREY_CHROMA:  # a grey thread (black, white): chroma contrast must stay small too
        ok = (_row_norms(d) < 2 * _GREY_CHROMA) & same_sign
        return np.where(ok, 1.0, -1.0)
    cos = (d @ r) / np.maximum(_row_norms(d) * nr, 1e-9)
    if same_sign.all():
        return cos
    whole = (delta @ ref) / np.maximum(_row_norms(delta) * np.linalg.norm(ref), 1e-9)
    return np.where(same_sign, cos, np.minimum(cos, whole))


def _row_norms(a: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(a, axis=1)`` of a float (M, C) ``a``, bit for bit (its squares in a's
    dtype, summed from the first column on, as numpy's row norm adds them) without numpy's
    reduction over C elements a row (~10x faster at C = 2, 3)."""
    s = a[:, 0] * a[:, 0]
    for j in range(1, a.shape[1]):
        s += a[:, j] * a[:, j]
    return np.sqrt(s)


def _mean_rows(a: np.ndarray, where: np.ndarray) -> np.ndarray:
    """``a[where].mean(axis=0)`` of a float (M, C) ``a`` and (M,) bool ``where``, bit for bit:
    for C = 2, 3 numpy adds the rows in order in a's dtype (each column's running sum, here
    np.cumsum's, without numpy's reduction over C elements a row) and divides by their count
    in float64 (an np.intp) before rounding to a's dtype; ~2x faster. One column (numpy sums
    it pairwise), or no row: numpy's own."""
    at = np.flatnonzero(where)
    if len(at) == 0 or a.shape[1] not in (2, 3):
        return a[at].mean(axis=0)
    sums = np.cumsum(np.take(a.T, at, axis=1), axis=1)[:, -1]  # (C,) in a's dtype
    return (sums.astype(np.float64) / len(at)).astype(a.dtype)


def _dye_part(
    delta: np.ndarray, lab: np.ndarray, ref: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per piece (n,): the mean contrast (n, C) of its pixels of the dye of contrast ``ref``
    (C,) (:func:`_other_dye_px`) and their count (n,); ``delta`` (M, C) the pixels'
    contrasts, ``lab`` (M,) their pieces."""
    mine = ~_other_dye_px(delta, ref, None)
    count = np.bincount(lab[mine], minlength=n).astype(np.float64)
    sums = np.stack(
        [np.bincount(lab[mine], weights=delta[mine, j], minlength=n) for j in range(len(ref))], 1
    )
    return sums / np.maximum(count, 1.0)[:, None], count


def _other_dye_px(delta: np.ndarray, ref: np.ndarray, hue: np.ndarray | None) -> np.ndarray:
    """(M,) bool: pixels of contrasts ``delta`` (M, C) not of the dye of contrast ``ref`` (C,);
    ``hue`` (M,) is :func:`_same_dye` of them (None: computed here when needed).

    A grey dye is told by the brightness sign and small chroma (``hue``). A coloured dye is
    told by its hue (chroma cosine >= _SAME_DYE_COS_PX) and by the direction of the whole
    contrast (brightness and chroma, cosine >= _SAME_DYE_COS), not by the brightness sign: a
    thread that differs from the tissue in hue only (green on pink) has a brightness contrast
    near 0 whose sign is noise and shading, and a light fibre merged into its piece (the same
    hue, less red than tissue) differs from it in how much brighter than its chroma it is. A
    blend of one dye over the background keeps that direction at any coverage (to first order
    in the log contrast)."""
    if delta.shape[1] == 1 or float(np.linalg.norm(ref[1:])) < _GREY_CHROMA:
        return (_same_dye(delta, ref) if hue is None else hue) < _SAME_DYE_COS_PX
    # cos >= t as dot >= 0 and dot^2 >= t^2 |a|^2 |b|^2: no square roots per pixel
    b, d1, d2 = (delta[:, j].astype(np.float64) for j in range(3))
    dot_c = d1 * ref[1] + d2 * ref[2]
    n_c = d1 * d1 + d2 * d2
    dot = dot_c + b * ref[0]
    r_c = float(ref[1] ** 2 + ref[2] ** 2)
    r_all = r_c + float(ref[0] ** 2)
    chroma_ok = (n_c > 0) & (dot_c >= 0) & (dot_c * dot_c >= _SAME_DYE_COS_PX**2 * n_c * r_c)
    whole_ok = (dot >= 0) & (dot * dot >= _SAME_DYE_COS**2 * (n_c + b * b) * r_all)
    return ~(chroma_ok & whole_ok)


def _instrument_mask(f_q: np.ndarray) -> np.ndarray:
    """(h, w) bool at quarter resolution: large unsaturated regions (metal or plastic
    instruments) of the quarter-resolution log channels ``f_q``. A grey region survives an
    opening by a 5 x 5 disc there (~20 px): a white or black thread, a fibre or a glint is
    thinner and does not. When grey covers most of the view it is the scene itself (a flat
    grey background), and nothing is masked."""
    chroma = np.maximum(np.abs(f_q[:, :, 1]), np.abs(f_q[:, :, 2]))
    grey = (chroma < _GREY_TOOL * _LOG_SCALE).view(np.uint8)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    tool = cv2.dilate(cv2.morphologyEx(grey, cv2.MORPH_OPEN, disc), disc)
    if np.count_nonzero(tool) > 0.5 * tool.size:  # a grey scene (flat background), not a tool
        return np.zeros(tool.shape, bool)
    return tool.view(bool)


def _on_tool(
    tool: np.ndarray, unsat: np.ndarray, rows: np.ndarray, cols: np.ndarray, rim_px: int
) -> tuple[np.ndarray, np.ndarray | None]:
    """(M,) bool: the candidate pixels (``rows``, ``cols``) the instrument takes: those of its
    mask ``tool`` (H, W) bool (quarter resolution, grown by a 5 x 5 disc there: ~8 px beyond
    its grey body, and into its jaws) within ``rim_px`` (an ellipse) of one of its unsaturated
    pixels (``unsat`` (H, W) uint8, 1 where unsaturated): its grey body and the blurred edge
    whose line response runs along it. A coloured thread running beside a shaft lies in the
    coarse mask's margin, farther out, and stays a candidate (deviation 50). ``rim_px`` 0:
    every candidate in ``tool``. Also returns that part of ``tool``, (H, W) bool (the
    thread's mask grown around its core leaves it out: a dark edge of the shaft blends like
    a thread), None with ``rim_px`` 0."""
    on = tool[rows, cols]
    if rim_px <= 0:
        return on, None
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rim_px + 1, 2 * rim_px + 1))
    # On the mask's bounding box: what is dilated lies in it, and the result is cut to it.
    tool8 = np.ascontiguousarray(tool, dtype=bool).view(np.uint8)
    body = np.zeros(tool.shape, bool)
    x, y, w, h = cv2.boundingRect(tool8)
    if w > 0:
        t8 = tool8[y : y + h, x : x + w]
        grown = cv2.dilate(cv2.bitwise_and(unsat[y : y + h, x : x + w], t8), disc)
        body[y : y + h, x : x + w] = grown.view(bool) & t8.view(bool)
    sel = np.flatnonzero(on)
    on[sel[~body[rows[sel], cols[sel]]]] = False
    return on, body


def _log_channels(img: np.ndarray) -> np.ndarray:
    """(H, W, C) float32: 32 log of the brightness and, for colour, 32 log(R/G), 32 log(B/G).

    Logarithms turn lighting (vignetting, shading) into an additive, smooth term that the
    second derivatives ignore; the two ratios see a thread that differs from tissue in hue only.
    Brightness is the luminance-weighted geometric mean of R, G, B.
    """
    u8 = img if img.dtype == np.uint8 else np.clip(img, 0, 255).astype(np.uint8)
    if u8.ndim == 2 or u8.shape[2] == 1:
        return cv2.LUT(u8.reshape(u8.shape[0], u8.shape[1]), _LOG_LUT)[:, :, None]
    logs = cv2.LUT(np.ascontiguousarray(u8[:, :, :3]), _LOG_LUT)
    return cv2.transform(logs, _LOG_MIX, dst=logs)  # in place: one 12 B/px buffer, not two


_LOG_LUT: Final = (_LOG_SCALE * np.log(np.arange(256, dtype=np.float64) + _LOG_OFFSET)).astype(
    np.float32
)
# _LOG_SCALE log(level + _LOG_OFFSET) of every level as :func:`_log_of` computes it, in
# float32 (_LOG_LUT rounds the float64 logs: the two may differ in the last bit)
_LOG_LUT32: Final = _LOG_SCALE * np.log(np.arange(256, dtype=np.float32) + _LOG_OFFSET)
_LOG_MIX: Final = np.array(
    [[0.299, 0.587, 0.114], [1.0, -1.0, 0.0], [0.0, -1.0, 1.0]], np.float32
)  # (brightness, log R/G, log B/G) from (log R, log G, log B)


def _uint8(img: np.ndarray) -> np.ndarray:
    """``img`` (H, W) or (H, W, C) as uint8 (H, W, 1 or 3) (clipped; its first 3 channels, or
    its first one), a view when it is uint8 already."""
    u8 = img if img.dtype == np.uint8 else np.clip(img, 0, 255).astype(np.uint8)
    if u8.ndim == 2:
        return u8[:, :, None]
    return u8[:, :, :1] if u8.shape[2] < 3 else u8[:, :, :3]


def _log_planes(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The channels of :func:`_log_channels` as the line response reads them: the first
    (brightness) at full resolution (H, W) float32, and all C of them at half resolution as
    cv2.pyrDown gives them, channel by channel (C, h, w) float32 (planes: each filter pass
    reads one contiguous row of a channel), h = (H + 1) // 2, w = (W + 1) // 2; one compiled
    pass (:func:`threadrecon.core.ridge_kernel.log_planes`), no (H, W, C) image."""
    u8 = _uint8(img)
    h, w, c = u8.shape
    grey = np.empty((h, w), np.float32)
    half = np.empty((c * ((h + 1) // 2), (w + 1) // 2), np.float32)
    mix = _LOG_MIX if c == 3 else np.ones((1, 1), np.float32)
    log_planes(u8, _LOG_LUT, mix, grey, half)
    return grey, half.reshape(c, -1, half.shape[1])


def _log_at(img: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(M, C) channels of :func:`_log_channels` at the pixels (rows, cols) only."""
    return _log_of_pixels(_pixels_at(img, rows, cols))


def _pixels_at(img: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(M, C) uint8 values of :func:`_uint8` of ``img`` at the pixels (rows, cols)."""
    return pixels_at(
        _uint8(img), np.ascontiguousarray(rows, np.int64), np.ascontiguousarray(cols, np.int64)
    )


def _log_of_pixels(px: np.ndarray) -> np.ndarray:
    """(M, C) channels of :func:`_log_channels` of the uint8 pixel values ``px`` (M, C)."""
    if len(px) == 0:
        return np.zeros((0, px.shape[1]), np.float32)
    return _log_channels(px[None]).reshape(len(px), -1)


def _line_response(grey: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(H, W) float32 multi-scale line strength of the channels of :func:`_log_planes`: the
    brightness ``grey`` (H, W) and all C channels at half resolution ``half`` (C, h, w), both
    overwritten.

    The fine scale sees the grey channel only (a 1-2 px thread differs from tissue mostly in
    brightness); the coarse scale sees every channel at half resolution (pyrDown) and is
    upsampled (bilinear, as cv2.resize): the same response for a quarter of the work.
    """
    fine = _line_at(grey, _SCALES[0], _SCALES[0])
    coarse = _line_at(half, 0.5 * _SCALES[1], _SCALES[1])
    return upsample_max(coarse, fine)


def _line_at(f: np.ndarray, sigma: float, norm: float) -> np.ndarray:
    """Line strength at Gaussian scale ``sigma`` px of this image (overwritten: it is blurred
    in place, and one channel becomes the response), normalised as scale ``norm``: one
    compiled pass over the smoothed image (:func:`threadrecon.core.ridge_kernel.line_response`;
    the same formula as fifteen cv2 calls, to float32 rounding, without their buffers).
    ``f``: (H, W), or C planes (C, H, W)."""
    planes = f if f.ndim == 3 else f[None]
    c, h, w = planes.shape
    for plane in planes:  # cv2 blurs the channels of an (H, W, C) image alike, one by one
        cv2.GaussianBlur(plane, (0, 0), sigma, dst=plane)
    r = sigma / norm  # derivatives per original pixel: a half-resolution pixel is 2 px
    # Sobel 3x3 sums 4 (first) or 16 (second derivative) times the derivative; the response
    # is 2 norm^2 min(|l1 + l2| / 2, |l1 - l2| / 2) - _EDGE_K norm |gradient|, at least 0.
    return line_response(
        planes.reshape(c * h, w),
        c,
        np.float32(0.125 * r),
        np.float32(0.25 * r * r),
        np.float32(2.0 * norm * norm),
        np.float32(_EDGE_K * norm),
        planes[0] if c == 1 else np.empty((h, w), np.float32),  # one channel: in place
    )


def _robust_level(s: np.ndarray) -> float:
    """Typical response of the background: the 90th percentile (thread px are < 5 %) of every
    second pixel of every second row."""
    sample = s[::2, ::2]
    k = int(0.9 * (sample.size - 1))
    return max(_kth_smallest(sample, k), 1e-3)


def _kth_smallest(x: np.ndarray, k: int) -> float:
    """The ``k``-th smallest (0-based) of the non-negative float32 values ``x`` (N,) or a 2-D
    view, exactly ``np.partition(x.ravel(), k)[k]`` in a fraction of its time (a histogram of
    the values' top bits, then the one bin: :func:`threadrecon.core.ridge_kernel.kth_smallest`)."""
    if x.dtype != np.float32 or x.ndim not in (1, 2) or not 0 <= k < x.size:
        raise ValueError(f"_kth_smallest needs (N,) or 2-D float32 and 0 <= k < N, got "
                         f"{x.dtype} {x.shape}, k={k}")  # fmt: skip
    return float(kth_smallest(x if x.ndim == 2 else x[None], k))


def _pieces(
    sub: np.ndarray | None, v: _View, p: SegmentationParams, thin_only: bool = False
) -> tuple:
    """Hysteresis pieces of the view's lo pixels where ``sub`` (M,) is True (all when None),
    8-connected: the piece of each lo pixel (M,) (0: none), rows and columns of the shape-ok
    pieces' pixels, per-piece mean S, length (exact where shape ok), shape ok. Labelled and
    measured on the pixel lists (:mod:`threadrecon.core.ridge_kernel`): cv2.connectedComponents'
    labels and cv2.distanceTransform's half-widths (to float32 rounding), no label image.

    With ``p.split_wide`` (deviation 40), a long piece too wide for a thread loses its wide
    part (:func:`_wide_part`; those pixels belong to no piece) and the pieces are formed again
    without it (``thin_only``: once; no piece is wider then)."""
    at = None if sub is None else np.flatnonzero(sub)  # (gathers by index: ~2x by mask)
    rows, cols = (v.rows, v.cols) if at is None else (v.rows[at], v.cols[at])
    lab = np.empty(len(rows), np.int64)
    n = label_pixels(rows, cols, lab)
    s_px = v.s_lo if at is None else v.s_lo[at]
    # pixels, summed S, seeds (S >= ridge_hi level, compared in float32 as numpy compares
    # float32 S with a Python float) and bounding boxes of the pieces, in one pass
    area, sums, seeded, boxes = piece_stats(
        lab, rows, cols, s_px, np.float32(p.ridge_hi * v.level), n
    )
    # Half-width of a piece: its largest distance to the outside; length: area / width (a loop
    # or a coil is long in a small box), at least the bounding box diagonal. Both only matter
    # for seeded pieces that can reach min_length_px: length <= max(diag, area / (2 a)), a =
    # 0.955 the chamfer's smallest distance, and diag <= sqrt(2) area (a connected piece's box
    # sides are <= its area). Those are few (a few % of the pieces); each is measured alone.
    # The other pieces' boxes are not needed (0, as their length); the pieces off the image's
    # border only (:func:`_along_border`). Per piece, in one compiled pass each side of the
    # half-widths (numpy's float64 steps, bit for bit: tests/core/test_segment_raw.py).
    h, w = v.lo.shape
    min_len = float(p.min_length_px)
    means, cands, diag = piece_candidates(
        area, sums, seeded, boxes, min_len, _SQRT2, 2.0 * _CHAMFER_A, h, w, _BORDER_PX
    )
    half = half_widths(lab, rows, cols, np.flatnonzero(cands), boxes, h, w)
    length, ok, wide = piece_shapes(area, diag, half, cands, min_len, MAX_HALF_WIDTH_PX)
    if p.split_wide and not thin_only and wide.any():
        # A thread merged with a line it runs beside (or crossing itself at a shallow angle)
        # is wider than a thread there only: that part goes, the rest is judged as pieces.
        drop = _wide_part(lab, rows, cols, np.flatnonzero(wide), boxes, h, w)
        if drop.any():
            keep = np.ones(len(v.rows), bool) if sub is None else sub.copy()
            keep[np.flatnonzero(keep)[drop]] = False
            return _pieces(keep, v, p, thin_only=True)
    on = ok[lab]
    lab_all = lab if at is None else _scatter(lab, at, len(sub))
    return lab_all, (rows[on], cols[on]), means, length, ok


_CHAMFER_A: Final = 0.95  # below cv2's DIST_L2 3x3 step (0.955): no piece is thinner
_SQRT2: Final = float(np.sqrt(2.0))  # a connected piece's box diagonal over its area, at most


def _wide_part(
    lab: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    ids: np.ndarray,
    boxes: np.ndarray,
    h: int,
    w: int,
) -> np.ndarray:
    """(M,) bool: the pixels (``rows``, ``cols``, of pieces ``lab``) of the pieces ``ids``
    that a disc wider than a thread inside the piece reaches: within L + 1 px (an ellipse) of
    a pixel farther than L from the piece's outside, for L = MAX_HALF_WIDTH_PX (6), 7, 8, ...
    (the distance of cv2.distanceTransform, DIST_L2 3x3, as :func:`ridge_kernel.half_widths`,
    the outside of the image far). The 1 px beyond the disc: where two lines part. ``boxes``
    (4, n): the pieces' first and last rows and columns."""
    out = np.zeros(len(rows), bool)
    for k in ids.tolist():
        r0, r1, c0, c1 = (int(b) for b in boxes[:, k])
        # the box grown by one pixel of zeros where that stays in the image (else far, as cv2)
        y0, y1, x0, x1 = max(r0 - 1, 0), min(r1 + 1, h - 1), max(c0 - 1, 0), min(c1 + 1, w - 1)
        sel = np.flatnonzero(lab == k)
        m = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
        m[rows[sel] - y0, cols[sel] - x0] = 1
        out[sel] = _disc_reach(m)[rows[sel] - y0, cols[sel] - x0] > 0
    return out


def _disc_reach(m: np.ndarray) -> np.ndarray:
    """(h, w) uint8, nonzero where a disc wider than a thread inside the mask ``m`` (h, w)
    uint8 reaches (:func:`_wide_part`)."""
    dt = cv2.distanceTransform(m, cv2.DIST_L2, 3)
    reach = np.zeros(m.shape, np.uint8)
    level = MAX_HALF_WIDTH_PX
    while True:
        centres = (dt > level).view(np.uint8)
        if not centres.any():
            return reach
        r = int(np.floor(level)) + 1
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        reach |= cv2.dilate(centres, disc)
        level = np.floor(level) + 1.0


_BORDER_PX: Final = int(np.ceil(2 * _SCALES[-1]))  # the coarse scale's reflected rim, px


def _along_border(boxes: np.ndarray, h: int, w: int) -> np.ndarray:
    """Per piece (n,) bool: its bounding box ``boxes`` (4, n) (rows r0..r1, columns c0..c1)
    lies within _BORDER_PX of one side of the (h, w) image. The line filters reflect the image
    at its border, so any brightness gradient across it becomes a ridge along it: there the
    response is no evidence of a line (a thread leaving the image crosses the border)."""
    r0, r1, c0, c1 = boxes
    m = _BORDER_PX
    return (r1 < m) | (r0 >= h - m) | (c1 < m) | (c0 >= w - m)


def _scatter(values: np.ndarray, at: np.ndarray, n: int) -> np.ndarray:
    """(n,) array holding ``values`` at the indices ``at`` (increasing) and 0 elsewhere."""
    out = np.zeros(n, values.dtype)
    out[at] = values
    return out


def _row_keys(rows: np.ndarray, cols: np.ndarray, width: int, d: int) -> np.ndarray:
    """(M,) sorted keys ``row (width + d + 1) + col`` of pixels: a window of d + 1 columns
    never spans two rows."""
    keys = rows.astype(np.int64) * (width + d + 1) + cols
    # pixels in row-major order (the lo pixels, subsets of them) give them sorted already
    return keys if np.all(keys[1:] >= keys[:-1]) else np.sort(keys)


def _has_partner(
    rows: np.ndarray, cols: np.ndarray, keys: np.ndarray, width: int, d: int, look_left: bool
) -> np.ndarray:
    """(M,) bool: a pixel of ``keys`` (the other view, :func:`_row_keys`) at (r, c - j)
    (``look_left``) or (r, c + j), 0 <= j <= max(d, 0), for each pixel (r, c)."""
    d = max(d, 0)
    q = rows.astype(np.int64) * (width + d + 1) + cols
    lo, hi = (q - d, q) if look_left else (q, q + d)
    return np.searchsorted(keys, hi, side="right") > np.searchsorted(keys, lo, side="left")


def _window_hits(
    mask: np.ndarray, rows: np.ndarray, cols: np.ndarray, d: int, look_left: bool
) -> np.ndarray:
    """(M,) bool: a pixel of ``mask`` (H, W) bool (the other view's instrument) at (r, c - j)
    (``look_left``) or (r, c + j), 0 <= j <= max(d, 0), for each pixel (r, c): where the
    instrument covers part of the window, the partner may lie behind it (a thread passing
    under it in one view only), and its absence is no evidence."""
    return _window_hits_in(_row_counts(mask), rows, cols, d, look_left)


def _row_counts(mask: np.ndarray) -> tuple[int, int, np.ndarray] | None:
    """Running counts along the rows of ``mask`` (H, W) bool on its bounding box: (first row,
    first column, (h, w + 1) int32 counts with a leading 0), None when it is empty."""
    x, y, w, h = cv2.boundingRect(np.ascontiguousarray(mask, dtype=bool).view(np.uint8))
    if w == 0:
        return None
    counts = np.zeros((h, w + 1), np.int32)
    np.cumsum(mask[y : y + h, x : x + w], axis=1, dtype=np.int32, out=counts[:, 1:])
    return y, x, counts


def _window_hits_in(
    box: tuple[int, int, np.ndarray] | None,
    rows: np.ndarray,
    cols: np.ndarray,
    d: int,
    look_left: bool,
) -> np.ndarray:
    """:func:`_window_hits` from the mask's running counts (:func:`_row_counts`)."""
    out = np.zeros(len(rows), bool)
    if box is None or len(rows) == 0:
        return out
    y, x, counts = box
    h, w = counts.shape[0], counts.shape[1] - 1
    d = max(d, 0)
    lo, hi = (cols - d - x, cols - x) if look_left else (cols - x, cols + d - x)
    r = rows - y
    sel = (r >= 0) & (r < h) & (hi >= 0) & (lo < w)  # the window meets the box
    r, lo, hi = r[sel], np.maximum(lo[sel], 0), np.minimum(hi[sel], w - 1)
    out[sel] = counts[r, hi + 1] > counts[r, lo]
    return out


def _consistent(lab: np.ndarray, partner: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Shape-ok pieces with a stereo partner for at least half of their pixels; ``lab`` (M,)
    the piece of each labelled pixel, ``partner`` (M,) bool whether it has a partner."""
    n = len(ok)
    cand = ok[lab]
    lab = lab[cand]
    hits = np.bincount(lab, weights=partner[cand], minlength=n)
    area = np.bincount(lab, minlength=n).astype(np.float64)
    return ok & (hits >= 0.5 * np.maximum(area, 1.0))


def _grow_mask(v: _View, core: np.ndarray) -> np.ndarray:
    """Thread pixels near ``core`` (uint8): coverage >= 0.5 of a linear blend thread over
    background.

    A pixel blending thread colour T over local background B with coverage c has
    I - B = c (T - B): c is its contrast along the thread's own contrast direction u (the
    summed contrast of the core pixels within the band, :func:`_body_contrast`) over |T - B|,
    the largest such contrast of a core pixel within the band (a box of radius _BAND_PX; the
    thread's axis is there). Projected on u, texture and noise across it no longer widen
    the mask (the length |I - B| adds them all). B is the candidate-free average of the view
    (:func:`_background`). Where a highlight lies inside the thread (pixels enclosed by
    thread pixels: a 3 x 3 closing of the mask), a pixel takes its coverage net of it; beside
    the thread the same fit would take the colour bleeding out of it (JPEG chroma) for thread.
    Coverage is conserved: a cross-section of two pixels (its outer neighbours below 0.5)
    whose coverages sum to < _SHARED_PX holds less than that much thread (a 1-2 px thread
    crossing from one pixel row or column to the next); coverage 0.5 takes the larger only.

    Computed on the core's bounding box grown by the band and by the 2 px the coverage test
    looks at (zeros there, as in the full image; exact: the band reaches no further), clipped
    to the image, by one compiled pass (:mod:`threadrecon.core.grow_kernel`, the
    same arithmetic as the numpy and cv2 steps, bit for bit).
    """
    out = np.zeros(core.shape, bool)
    if (grown := _grow_box(v, core)) is not None:
        box, at = grown
        out[at] = box
    return out


def _grow_box(
    v: _View, core: np.ndarray, rect: tuple[int, int, int, int] | None = None
) -> tuple[np.ndarray, tuple[slice, slice]] | None:
    """:func:`_grow_mask` on the box it is computed on: the mask there (bh, bw) bool and the
    box (rows, columns) of the view; None for an empty ``core`` (an empty mask). ``rect``:
    the core's bounding box (x, y, w, h), when known."""
    h, w = core.shape
    if rect is None:
        rect = cv2.boundingRect(np.ascontiguousarray(core, np.uint8))
    x0, y0, bw, bh = rect
    if bw == 0:
        return None
    m = _BAND_PX + 2
    r0, r1, c0, c1 = max(y0 - m, 0), min(y0 + bh + m, h), max(x0 - m, 0), min(x0 + bw + m, w)
    a = v.img if v.img.ndim == 3 else v.img[:, :, None]
    a = a[r0:r1, c0:c1, : v.bg_rgb.shape[2]]
    grow = grow_mask_u8
    if a.dtype != np.uint8:
        a, grow = a.astype(np.float32), grow_mask_f32
    box = grow(
        a,
        np.ascontiguousarray(v.bg_rgb, np.float32),
        core[r0:r1, c0:c1],
        _DISC,
        r0,
        c0,
        _Q,
        _BAND_PX,
        np.float32(_GLINT_APART_SIN2),
        np.float32(_SHARED_PX),
    )
    return box.view(bool), (slice(r0, r1), slice(c0, c1))


_DISC: Final = cv2.getStructuringElement(
    cv2.MORPH_ELLIPSE, (2 * _BAND_PX + 1, 2 * _BAND_PX + 1)
)  # the band around the core


def _body_contrast(
    diff: np.ndarray, rows: np.ndarray, cols: np.ndarray, on_core: np.ndarray, shape_q: tuple
) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Contrast of pixels (rows, cols) (M,) along the thread's own colour contrast: ((M,)
    projected, (M,) net of a highlight) and (M,) bool where the highlight fit applies.

    ``diff`` (M, C) is I - B, ``on_core`` (M,) marks the core pixels, ``shape_q`` the quarter
    resolution (h, w) of the view. The direction u at a pixel: the summed contrast of the core
    pixels in its _Q x _Q block and the 8 blocks around (one dye, locally one background).
    Dichromatic reflection: a thread's highlight adds the illuminant's colour W (white) to its
    body colour, I - B = c (T - B) + s W, s >= 0; where u and W differ (a coloured thread: by
    > _GLINT_APART_DEG) the least-squares c of the pixels with s > 0 is the body contrast net
    of the highlight. A grey thread's contrast is along W itself: a highlight cannot be told
    apart there (no fit). This is the plain form of the step: :func:`_grow_mask` computes it
    within its compiled pass (core/grow_kernel.py), bit for bit (tests/core/test_grow_kernel.py
    compares the two).
    """
    c = diff.shape[1]
    qr, qc = _qi(rows, shape_q[0]), _qi(cols, shape_q[1])
    r0, c0 = int(qr.min()), int(qc.min())
    hq, wq = int(qr.max()) - r0 + 1, int(qc.max()) - c0 + 1
    flat = (qr - r0) * wq + (qc - c0)
    sums = np.stack(
        [np.bincount(flat[on_core], weights=diff[on_core, j], minlength=hq * wq)
         for j in range(c)],
        1,
    ).astype(np.float32).reshape(hq, wq, c)  # fmt: skip
    sums = cv2.boxFilter(sums, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    sums = sums.reshape(hq * wq, c)
    sums *= (1.0 / np.sqrt(np.maximum(np.einsum("ij,ij->i", sums, sums), 1e-12)))[:, None]
    proj = np.einsum("ij,ij->i", diff, sums[flat])  # along u, per block
    if c != 3:
        return (proj, proj), np.zeros(len(proj), bool)
    uw_b = sums.sum(axis=1) * np.float32(3**-0.5)  # u . W per block, W = (1, 1, 1) / sqrt(3)
    den_b = np.float32(1.0) - uw_b * uw_b
    uw, den = uw_b[flat], den_b[flat]
    dw = diff.sum(axis=1) * np.float32(3**-0.5)
    glint = (den >= _GLINT_APART_SIN2) & (dw > proj * uw)  # s > 0
    net = (proj - dw * uw) / np.maximum(den, np.float32(_GLINT_APART_SIN2))
    return (proj, net), glint


def _grey_contrast(v: _View, at: np.ndarray) -> bool:
    """Whether the summed colour contrast (RGB) of the core pixels (the lo pixels ``at`` (M,)
    of the view) to the view's local background lies within _GLINT_APART_DEG of grey (white
    or black): there a highlight (white added) is not told from the thread's own contrast by
    colour (:func:`_body_contrast`). Their values are those the view read (``v.px``: no
    second read of the image)."""
    if len(at) == 0 or v.bg_rgb.shape[2] != 3:
        return len(at) > 0
    r64, c64 = (
        np.ascontiguousarray(v.rows[at], np.int64),
        np.ascontiguousarray(v.cols[at], np.int64),
    )
    values = _pixels_at(v.img, r64, c64) if v.px is None else v.px[at]
    px = values.astype(np.float64)
    bg = blocks_at(np.ascontiguousarray(v.bg_rgb, np.float32), r64, c64, _Q)
    u = (px - bg).sum(axis=0)
    n2 = float(u @ u)
    if n2 <= 0.0:
        return True
    uw2 = float(u.sum()) ** 2 / (3.0 * n2)  # cos^2 of the angle to white
    return 1.0 - uw2 < _GLINT_APART_SIN2


def _fill_across(mask: np.ndarray, gap: int) -> np.ndarray:
    """``mask`` (H, W) bool with the runs of at most ``gap`` pixels it encloses along a row, a
    column or a diagonal (a pixel's nearest mask pixels on its two sides, in one of the four
    directions, at most ``gap + 1`` steps apart in all).

    A dark thread's specular highlight adds white to it, against its own contrast (the
    body-contrast fit cannot tell the two apart along a grey direction): the coverage test
    takes the two dark sides and leaves the highlight between them out. Geometry tells it: a
    run enclosed across a thread no wider than 6 px is inside it. A 1-2 px thread's staircase
    encloses nothing (its corner pixels have mask neighbours on two adjacent sides only).

    A closing by a segment of ``gap + 1`` pixels fills exactly the runs shorter than it; one
    closing per direction, on the mask's bounding box padded by ``gap + 1`` zeros (a run that
    reaches the image's edge is not enclosed)."""
    u8 = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    x, y, w, h = cv2.boundingRect(u8)
    if w == 0 or gap < 1:
        return mask
    m = gap + 1
    box = cv2.copyMakeBorder(u8[y : y + h, x : x + w], m, m, m, m, cv2.BORDER_CONSTANT, value=0)
    fill = np.zeros_like(box)
    for k in _segments(m):
        # closing by the segment: dilation, then erosion by its reflection (the anchor at the
        # other end: an even segment has no centre)
        grown = cv2.dilate(box, k, anchor=(0, 0))
        fill |= cv2.erode(grown, k, anchor=(k.shape[1] - 1, k.shape[0] - 1))
    fill = fill[m : m + h, m : m + w]
    if not cv2.countNonZero(fill & ~u8[y : y + h, x : x + w] & 1):
        return mask
    out = mask.copy()
    out[y : y + h, x : x + w] |= fill.view(bool)
    return out


def _segments(n: int) -> tuple[np.ndarray, ...]:
    """Structuring elements of ``n`` pixels in a row, a column and the two diagonals."""
    eye = np.eye(n, dtype=np.uint8)
    return np.ones((1, n), np.uint8), np.ones((n, 1), np.uint8), eye, eye[::-1].copy()


def drop_specks(mask: np.ndarray, min_px: int) -> np.ndarray:
    """``mask`` (H, W) bool without its 8-connected components smaller than ``min_px`` (``mask``
    itself when it has none)."""
    if min_px <= 1:
        return mask
    u8 = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    # Labelled on the pixels' bounding box only: the same components, hence the same sizes.
    x, y, w, h = cv2.boundingRect(u8)
    if w == 0:
        return mask
    box = u8[y : y + h, x : x + w]
    if small_components(box, min_px, False) == 0:  # the common case: nothing to drop
        return mask
    out = np.array(mask, dtype=bool)
    small_components(out.view(np.uint8)[y : y + h, x : x + w], min_px, True)
    return out
