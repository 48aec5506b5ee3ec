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
B: the paper's Blender and hand-segmented frames) and segments raw otherwise. A raw frame in
which no piece qualifies raises ``ValueError("no thread found ...")``: never a curve.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Literal

import cv2
import numpy as np

from threadrecon.core.params import Params, param

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
        "consistency; auto: threshold when the background is flat (flat_share), else raw.",
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
    score_L: np.ndarray | None = None
    """(H, W) float32 per-pixel thread score in [0, 1] of the left view (0.5 ~ the decision
    level); None when the masks were given."""
    score_R: np.ndarray | None = None
    """Same for the right view."""
    method: str = "mask"
    """How P was obtained: "mask" (given), "threshold" or "raw"."""


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 greyscale of an RGB or grey uint8 image."""
    if image.ndim == 2:
        return image.astype(np.float32)
    if image.shape[2] == 1:
        return image[:, :, 0].astype(np.float32)
    return cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2GRAY).astype(
        np.float32
    )


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
    grey_L, grey_R = to_grey(pair.left), to_grey(pair.right)
    bg = (_background_level(grey_L, p), _background_level(grey_R, p))
    score_L = score_R = None
    if pair.mask_left is not None and pair.mask_right is not None:
        P_L, P_R = pair.mask_left.astype(bool), pair.mask_right.astype(bool)
        method = "mask"
    else:
        method = p.method
        if method == "auto":
            flat = min(_flat_share(grey_L, bg[0]), _flat_share(grey_R, bg[1]))
            method = "threshold" if flat >= p.flat_share else "raw"
        if method == "threshold":
            P_L = _drop_specks(grey_L < bg[0] - p.seg_delta, p.min_component_px)
            P_R = _drop_specks(grey_R < bg[1] - p.seg_delta, p.min_component_px)
            score_L = _threshold_score(grey_L, bg[0], p.seg_delta)
            score_R = _threshold_score(grey_R, bg[1], p.seg_delta)
        else:
            P_L, P_R, score_L, score_R = segment_raw(pair.left, pair.right, p)
    if not P_L.any():
        raise ValueError("empty segmentation: no thread pixel in the left image")
    if not P_R.any():
        raise ValueError("empty segmentation: no thread pixel in the right image")
    I_L = _lift(grey_L, P_L, p.lift_dilate_px)
    I_R = _lift(grey_R, P_R, p.lift_dilate_px)
    return LiftedPair(
        I_L=I_L,
        I_R=I_R,
        P_L=P_L,
        P_R=P_R,
        grey_L=grey_L,
        grey_R=grey_R,
        background=bg,
        score_L=score_L,
        score_R=score_R,
        method=method,
    )


def _flat_share(grey: np.ndarray, level: float) -> float:
    """Share of pixels within 1 grey level of ``level``."""
    return float(np.count_nonzero(np.abs(grey - level) <= 1.0)) / grey.size


def _threshold_score(grey: np.ndarray, level: float, delta: float) -> np.ndarray:
    """Darkness below B scaled so that the threshold B - delta scores 0.5."""
    scale = 1.0 / (2.0 * max(delta, 1.0))
    return np.clip((level - grey) * scale, 0.0, 1.0).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Raw frames: multi-scale colour ridge, hysteresis, shape and stereo consistency

_SCALES: Final = (1.0, 2.0)  # fine and coarse Gaussian scales of the line detector, px
_EDGE_K: Final = 2.0  # gradient penalty; 2 cancels both lobes of a step edge beyond 1 sigma
_LOG_OFFSET: Final = (
    16.0  # log(I + 16): lighting is a product, contrast a ratio; 16 tames dark noise
)
_BAND_PX: Final = 4  # the mask is grown at most this far from a kept piece (half of 6 px + 1)
_BG_SIGMA: Final = 8.0  # local background colour: thread-free Gaussian average, px
_CORE_FRACTION: Final = 0.4  # core pixels respond >= 40 % of their piece's mean
_SAME_DYE_COS: Final = 0.8  # pieces of one thread: colour contrasts within ~37 degrees
_SAME_DYE_COS_PX: Final = 0.5  # per pixel (noisier): within 60 degrees
_GREY_CHROMA: Final = 3.0  # chroma contrast below ~10 %: a grey (black, white) dye
_MAX_HALF_WIDTH_PX: Final = (
    6.0  # a piece wider than 12 px (a 6 px thread's response ~8 px) is not thread
)
_RED_THREAD_GAIN: Final = 3.0  # blood-like pieces win when 3x as salient as the rest
_VESSEL_HUE_COS: Final = 0.99  # chroma contrasts within 8 degrees: one absorber (vessels)
_MIN_VESSEL_PX: Final = 50  # blood-like pixels needed to tell the frame's vessel hue
_GREY_TOOL: Final = 0.12  # |log R/G|, |log B/G| below this: unsaturated, e.g. steel
_LOG_SCALE: Final = 32.0  # channels are 32 log(.), so 1 unit ~ 3 % of contrast
_BLOOD_RATIO: Final = 0.25  # haemoglobin absorbs G, B far more than R: a vessel reddens by
# >= 1/4 of its darkening (log units) at any strength; dyes other than red redden less or not
_MIN_SNR: Final = 5.0  # a thread piece's mean contrast to its background: >= 5 noise sigmas
_QUANT_SIGMA: Final = _LOG_SCALE / (255.0 * 12**0.5)  # uint8 quantisation noise, log units


def segment_raw(
    left: np.ndarray, right: np.ndarray, p: SegmentationParams = SegmentationParams()
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Thread masks and scores of a raw rectified pair, no mask given.

    1. Line response S: on 32 log(I) (brightness, log R/G, log B/G), the scale-normalised
       Hessian line strength 2 min(|l1 + l2| / 2, |l1 - l2| / 2) sigma^2 (zero on blobs and
       flat parts) minus 2 sigma |gradient| (zero on step edges), max over two scales.
    2. Hysteresis: pieces of S >= ridge_lo * level holding a pixel of S >= ridge_hi * level,
       ``level`` being the image's typical response (90th percentile): no absolute contrast.
       Before the pieces are formed, pixels darker and redder than the tissue around them
       (blood: vessels; redder by more than ``blood_rg`` or by >= _BLOOD_RATIO of their
       darkening, which holds for a vessel of any strength) are set aside; they come back
       when they stand out _RED_THREAD_GAIN times more than anything else and their hue
       differs from the mean of the frame's other blood-like pixels by more than ~8 degrees (a
       red thread; the vessels of a frame share one hue), keeping only pixels nearer the
       thread's hue. A lone blood-like line (too few other blood-like pixels) is a vessel.
    3. Shape: a piece's length >= min_length_px and mean width <= 8 px.
    4. Stereo: a piece keeps >= half of its pixels with a candidate pixel on the same row of the
       other view within [0, max_disparity_px] of disparity.
       Presence: the piece's mean contrast to its local background is >= _MIN_SNR times the
       frame's own pixel noise (per channel, robust): on a thread-free frame nothing passes
       and the answer is "no thread found", not a vessel or a texture line.
    5. Selection: the most salient piece (mean S x sqrt(length)) is the thread; other pieces
       and pixels join it when they share its dye (direction of the colour contrast) and their
       mean S is >= keep_ratio of its.
    6. Mask: within _BAND_PX of the kept pixels, those with coverage >= 0.5 of a thread colour
       blended over the local background colour (see :func:`_grow_mask`).

    Returns P_L, P_R (H, W) bool and score_L, score_R (H, W) float32 in [0, 1].
    Raises ``ValueError("no thread found ...")`` when no piece survives in a view.
    """
    views = [_View.build(img, p) for img in (left, right)]
    found, salience, _ = _select(views, p)
    if any(v.blood.any() for v in views):
        # A red thread is blood-like too: it wins back when it stands out far more than
        # anything left without the blood-like pixels, and when its hue differs from the
        # frame's other blood-like pixels (a frame's vessels share one hue, haemoglobin's).
        red_views = [v.with_blood(p) for v in views]
        red, red_salience, red_cos = _select(red_views, p, nearest_hue=True)
        if (
            red is not None
            and red_salience >= _RED_THREAD_GAIN * salience
            and red_cos < _VESSEL_HUE_COS
        ):
            views, found = red_views, red
    if found is None:
        raise ValueError(
            "no thread found: no long thin piece with a partner in the other view stands out "
            f"of the background (raw segmentation; ridge_hi={p.ridge_hi:g}, "
            f"min_length_px={p.min_length_px:g})"
        )
    out = []
    for v, core in zip(views, found, strict=True):
        mask = _drop_specks(_grow_mask(v.img, core), max(int(p.min_length_px), 1))
        score = np.clip(v.S / (2.0 * p.ridge_hi * v.level), 0.0, 1.0).astype(np.float32)
        out.append((mask, score))
    return out[0][0], out[1][0], out[0][1], out[1][1]


@dataclass
class _View:
    """One view's intermediate results of :func:`segment_raw`."""

    img: np.ndarray
    S: np.ndarray  # (H, W) line response
    level: float
    lo: np.ndarray  # (H, W) bool, S >= ridge_lo * level
    rows: np.ndarray  # (M,) of the lo pixels
    cols: np.ndarray
    delta: np.ndarray  # (M, C) log-channel contrast of the lo pixels to the local background
    blood: np.ndarray  # (M,) bool, darker and redder than the tissue around
    sigma: np.ndarray  # (C,) pixel noise of each log channel (robust), log units
    pieces: tuple = ()

    @classmethod
    def build(cls, img: np.ndarray, p: SegmentationParams) -> _View:
        f = _log_channels(img)
        S = _line_response(f)
        level = _robust_level(S)
        lo = S >= p.ridge_lo * level  # noqa: SIM300
        if f.shape[2] > 1:
            lo &= ~_instrument_mask(f)
        rows, cols = np.nonzero(lo)
        delta = _contrast(f, lo, rows, cols)
        if f.shape[2] > 1:
            redder = (delta[:, 1] > p.blood_rg * _LOG_SCALE) | (
                delta[:, 1] >= -_BLOOD_RATIO * delta[:, 0]
            )
            blood = redder & (delta[:, 0] < 0)
        else:
            blood = np.zeros(len(rows), bool)
        v = cls(img, S, level, lo, rows, cols, delta, blood, _noise_sigma(f))
        mask = lo.copy()
        mask[rows[blood], cols[blood]] = False
        v.pieces = _pieces(S, mask, level, p)
        return v

    def with_blood(self, p: SegmentationParams) -> _View:
        v = _View(
            self.img,
            self.S,
            self.level,
            self.lo,
            self.rows,
            self.cols,
            self.delta,
            self.blood,
            self.sigma,
        )
        v.pieces = _pieces(self.S, self.lo, self.level, p)
        return v


def _select(
    views: list[_View], p: SegmentationParams, nearest_hue: bool = False
) -> tuple[list[np.ndarray] | None, float, float]:
    """Core thread pixels (H, W) bool of both views (None when a view has no piece), the
    salience (mean S x sqrt(length), summed over the views) of the chosen pieces, and the
    largest (over the views) cosine between the chroma contrast of the chosen piece and the
    mean one of the view's other blood-like pixels (its vessels; 1 when there are too few to
    tell: a lone blood-like line is taken for a vessel).

    ``nearest_hue`` (a blood-like thread among vessels): pieces and pixels join the thread only
    when their hue is nearer the thread's than the vessels'."""
    D = int(p.max_disparity_px)
    cands = [v.pieces[1] for v in views]
    partners = (_reach(cands[1], D, look_left=True), _reach(cands[0], D, look_left=False))
    out = []
    salience = 0.0
    cos_vessels = -1.0
    for v, partner in zip(views, partners, strict=True):
        labels, cand, means, length, ok = v.pieces
        lab = labels[v.rows, v.cols]  # piece of each lo pixel (0: none); sparse from here on
        use = lab > 0
        k = _consistent(lab[use], partner[v.rows[use], v.cols[use]], ok)
        n = len(k)
        area = np.maximum(np.bincount(lab[use], minlength=n), 1).astype(np.float64)
        delta = np.stack(
            [np.bincount(lab[use], weights=v.delta[use, j], minlength=n) / area
             for j in range(v.delta.shape[1])],
            1,
        )  # fmt: skip
        # Is it there at all: its mean contrast to the background stands out of the pixel noise.
        k &= np.linalg.norm(delta / v.sigma, axis=1) >= _MIN_SNR
        if not k.any():
            return None, 0.0, 1.0
        rank = np.where(k, means * np.sqrt(length), -1.0)
        best = int(np.argmax(rank))
        salience += float(rank[best])
        # The frame's vessel hue: mean contrast of its blood-like pixels off the chosen piece.
        vessel = v.blood & (lab != best)
        d_vessel = v.delta[vessel].mean(axis=0) if vessel.sum() >= _MIN_VESSEL_PX else None
        cos_vessels = max(
            cos_vessels, 1.0 if d_vessel is None else _cosine(d_vessel[1:], delta[best, 1:])
        )
        d_best = delta[best]
        # Other pieces of the same thread (split by an occluder or a crossing) share its dye.
        k = k & (means >= p.keep_ratio * means[best]) & (_same_dye(delta, d_best) >= _SAME_DYE_COS)
        if nearest_hue and d_vessel is not None:
            k &= _same_dye(delta, d_best) > _same_dye(delta, d_vessel)
        k[best] = True
        k[0] = False
        # Within a kept piece: not pixels far fainter than the piece (a branch touching it),
        # nor pixels of another colour (a vessel or fibre merged into the thread's piece).
        hue = _same_dye(v.delta, d_best)
        other = hue < _SAME_DYE_COS_PX
        if nearest_hue and d_vessel is not None:
            other |= hue <= _same_dye(v.delta, d_vessel)
        sel = use & k[lab] & ~other
        sel &= v.S[v.rows, v.cols] >= _CORE_FRACTION * means[lab]
        core = np.zeros(labels.shape, bool)
        core[v.rows[sel], v.cols[sel]] = True
        if not sel.any():
            core = labels == best
        out.append(core)
    return out, salience, cos_vessels


def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    """Cosine of the angle between two contrast vectors (C,)."""
    return float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-9)


def _noise_sigma(f: np.ndarray) -> np.ndarray:
    """(C,) robust pixel-noise sigma of each channel of ``f`` (H, W, C): the median absolute
    difference of horizontal neighbours on every 8th row (texture and edges are sparse there;
    the differences are symmetric about 0), as a Gaussian sigma; at least the uint8
    quantisation noise."""
    d = cv2.absdiff(f[::8, 1:], f[::8, :-1]).reshape(-1, f.shape[2])
    mad = np.median(d, axis=0)
    return np.maximum(1.4826 * mad / np.sqrt(2.0), _QUANT_SIGMA)


def _same_dye(delta: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Cosine between colour contrasts (M, C) and ``ref`` (C,): on the chroma channels (hue
    of the contrast, independent of its strength and of lighting) when there is colour, with
    -1 where the brightness contrast has the other sign; the brightness sign alone for grey."""
    sign = np.where(delta[:, 0] * ref[0] >= 0, 1.0, -1.0)
    if delta.shape[1] == 1:
        return sign
    d, r = delta[:, 1:], ref[1:]
    nr = float(np.linalg.norm(r))
    if nr < _GREY_CHROMA:  # a grey thread (black, white): chroma contrast must stay small too
        return np.where(np.linalg.norm(d, axis=1) < 2 * _GREY_CHROMA, sign, -1.0)
    cos = (d @ r) / np.maximum(np.linalg.norm(d, axis=1) * nr, 1e-9)
    return np.minimum(cos, sign)


def _instrument_mask(f: np.ndarray) -> np.ndarray:
    """(H, W) bool: large unsaturated regions (metal or plastic instruments), found at quarter
    resolution. A grey region survives an opening by a 5 x 5 disc there (~20 px): a white or
    black thread, a fibre or a glint is thinner and does not. When grey covers most of the
    view it is the scene itself (a flat grey background), and nothing is masked."""
    h, w = f.shape[:2]
    small = (max(w // 4, 1), max(h // 4, 1))
    chroma = cv2.resize(f, small, interpolation=cv2.INTER_AREA)[:, :, 1:]
    grey = (np.abs(chroma).max(axis=2) < _GREY_TOOL * _LOG_SCALE).astype(np.uint8)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    tool = cv2.dilate(cv2.morphologyEx(grey, cv2.MORPH_OPEN, disc), disc)
    if np.count_nonzero(tool) > 0.5 * tool.size:  # a grey scene (flat background), not a tool
        return np.zeros((h, w), bool)
    return cv2.resize(tool, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)


def _contrast(f: np.ndarray, lo: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(M, C) log-channel contrast of pixels (rows, cols) to the local background: the Gaussian
    average of the pixels away from ``lo`` at quarter resolution (normalised convolution)."""
    h, w, c = f.shape
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * _BAND_PX + 1, 2 * _BAND_PX + 1))
    free = 1 - cv2.dilate(lo.view(np.uint8), k)
    small = (max(w // 4, 1), max(h // 4, 1))
    num = cv2.resize(f * free[:, :, None], small, interpolation=cv2.INTER_AREA)
    den = cv2.resize(free.astype(np.float32), small, interpolation=cv2.INTER_AREA)
    s4 = _BG_SIGMA / 4.0
    num = cv2.GaussianBlur(num, (0, 0), s4).reshape(small[1], small[0], c)
    den = cv2.GaussianBlur(den, (0, 0), s4)
    bg = num / np.maximum(den, 1e-3)[:, :, None]
    return (
        f[rows, cols] - bg[np.minimum(rows // 4, small[1] - 1), np.minimum(cols // 4, small[0] - 1)]
    )


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
    return cv2.transform(logs, _LOG_MIX)


_LOG_LUT: Final = (_LOG_SCALE * np.log(np.arange(256, dtype=np.float64) + _LOG_OFFSET)).astype(
    np.float32
)
_LOG_MIX: Final = np.array(
    [[0.299, 0.587, 0.114], [1.0, -1.0, 0.0], [0.0, -1.0, 1.0]], np.float32
)  # (brightness, log R/G, log B/G) from (log R, log G, log B)


def _line_response(f: np.ndarray) -> np.ndarray:
    """(H, W) float32 multi-scale line strength of the (H, W, C) channels ``f``.

    The fine scale sees the grey channel only (a 1-2 px thread differs from tissue mostly in
    brightness); the coarse scale sees every channel at half resolution (pyrDown) and is
    upsampled: the same response for a quarter of the work.
    """
    h, w = f.shape[:2]
    fine = _line_at(np.ascontiguousarray(f[:, :, 0]), _SCALES[0], _SCALES[0])
    coarse = _line_at(cv2.pyrDown(f), 0.5 * _SCALES[1], _SCALES[1])
    return cv2.max(fine, cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR))


def _line_at(f: np.ndarray, sigma: float, norm: float) -> np.ndarray:
    """Line strength at Gaussian scale ``sigma`` px of this image, normalised as scale ``norm``.

    Written with cv2's in-place outputs: six buffers instead of fifteen fresh arrays (page
    faults on fresh memory cost more than the arithmetic here).
    """
    h, w = f.shape[:2]
    c = 1 if f.ndim == 2 else f.shape[2]
    g = cv2.GaussianBlur(f, (0, 0), sigma)
    shape = (h, w * c)
    r = sigma / norm  # derivatives per original pixel: a half-resolution pixel is 2 px
    bufs = [np.empty(shape, np.float32) for _ in range(5)]
    gx, gy, hxx, hyy, hxy = bufs
    for out, (dx, dy, scale) in zip(
        bufs,
        ((1, 0, 0.125 * r), (0, 1, 0.125 * r), (2, 0, 0.25 * r * r), (0, 2, 0.25 * r * r),
         (1, 1, 0.25 * r * r)),
        strict=True,
    ):  # fmt: skip
        cv2.Sobel(g, cv2.CV_32F, dx, dy, dst=out.reshape(g.shape), ksize=3, scale=scale)
    grad = cv2.magnitude(gx, gy, gx)
    a = cv2.addWeighted(hxx, 0.5, hyy, 0.5, 0.0, dst=gy)
    cv2.absdiff(a, 0.0, dst=a)  # |l1 + l2| / 2
    cv2.addWeighted(hxx, 0.5, hyy, -0.5, 0.0, dst=hxx)
    d = cv2.magnitude(hxx, hxy, hyy)  # |l1 - l2| / 2
    line = cv2.min(a, d, dst=a)
    cv2.addWeighted(line, 2.0 * norm * norm, grad, -_EDGE_K * norm, 0.0, dst=line)
    cv2.max(line, 0.0, dst=line)
    cv2.multiply(line, line, dst=line)
    sq = line.reshape(h, w, c)
    if c > 1:
        sq = cv2.transform(sq, np.ones((1, c), np.float32))
    return cv2.sqrt(sq.reshape(h, w))


def _robust_level(s: np.ndarray) -> float:
    """Typical response of the background: the 90th percentile (thread px are < 5 %)."""
    return max(float(np.percentile(s[::2, ::2], 90)), 1e-3)


def _pieces(s: np.ndarray, lo: np.ndarray, level: float, p: SegmentationParams) -> tuple:
    """Hysteresis pieces of the mask ``lo`` (S >= ridge_lo * level): labels, candidate mask,
    per-label mean S, length, shape ok."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(lo.view(np.uint8), connectivity=8)
    idx = np.flatnonzero(lo)
    lab = labels.ravel()[idx]
    sums = np.bincount(lab, weights=s.ravel()[idx], minlength=n)
    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    seeded = np.zeros(n, bool)
    seeded[lab[s.ravel()[idx] >= p.ridge_hi * level]] = True
    means = sums / np.maximum(area, 1.0)
    # Half-width of a piece: its largest distance to the outside; length: area / width (a loop
    # or a coil is long in a small box), at least the bounding box diagonal.
    dist = cv2.distanceTransform(lo.view(np.uint8), cv2.DIST_L2, 3)
    half = _label_max(lab, dist.ravel()[idx], n)
    diag = np.hypot(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    length = np.maximum(diag, area / np.maximum(2.0 * half, 1.0))
    ok = seeded & (length >= p.min_length_px) & (half <= _MAX_HALF_WIDTH_PX)
    ok[0] = False
    means[0] = 0.0
    cand = np.zeros(lo.shape, bool)
    cand.ravel()[idx[ok[lab]]] = True
    return labels, cand, means, length, ok


def _label_max(lab: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n,) largest value per label (0 where a label has none): one sort and a reduceat."""
    out = np.zeros(n)
    if lab.size == 0:
        return out
    order = np.argsort(lab, kind="stable")
    lab_s = lab[order]
    starts = np.flatnonzero(np.concatenate([[True], lab_s[1:] != lab_s[:-1]]))
    out[lab_s[starts]] = np.maximum.reduceat(values[order], starts)
    return out


def _reach(mask: np.ndarray, d: int, look_left: bool) -> np.ndarray:
    """Pixels (r, c) with a ``mask`` pixel at (r, c - j) (``look_left``) or (r, c + j), j <= d."""
    if d <= 0:
        return mask
    k = np.zeros((1, 2 * d + 1), np.uint8)  # dilate: out(c) = max_i mask(c + i - d) over k[i]
    if look_left:
        k[:, : d + 1] = 1
    else:
        k[:, d:] = 1
    return cv2.dilate(mask.view(np.uint8), k).astype(bool)


def _consistent(lab: np.ndarray, partner: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Shape-ok pieces with a stereo partner for at least half of their pixels; ``lab`` (M,)
    the piece of each labelled pixel, ``partner`` (M,) bool whether it has a partner."""
    n = len(ok)
    cand = ok[lab]
    lab = lab[cand]
    hits = np.bincount(lab, weights=partner[cand], minlength=n)
    area = np.bincount(lab, minlength=n).astype(np.float64)
    return ok & (hits >= 0.5 * np.maximum(area, 1.0))


def _grow_mask(img: np.ndarray, core: np.ndarray) -> np.ndarray:
    """Thread pixels near ``core``: coverage >= 0.5 of a linear blend thread over background.

    A pixel blending thread colour T over local background B with coverage c has
    I - B = c (T - B), so c^2 = |I - B|^2 / |T - B|^2; |T - B|^2 is the largest |I - B|^2 of a
    core pixel within the band radius (the thread's axis is there). Sparse: band pixels only.
    """
    h, w = core.shape
    a = img if img.ndim == 3 else img[:, :, None]
    a = a[:, :, :3]
    c = a.shape[2]
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * _BAND_PX + 1, 2 * _BAND_PX + 1))
    band = cv2.dilate(core.view(np.uint8), k)
    # Local background: thread-free average at quarter resolution (normalised convolution).
    small = (max(w // 4, 1), max(h // 4, 1))
    free = np.where(band[:, :, None] > 0, np.uint8(0), a).astype(np.float32)
    w_bg = cv2.resize((1 - band).astype(np.float32), small, interpolation=cv2.INTER_AREA)
    num = cv2.resize(free, small, interpolation=cv2.INTER_AREA).reshape(small[1], small[0], c)
    s4 = _BG_SIGMA / 4.0
    num = cv2.GaussianBlur(num, (0, 0), s4).reshape(small[1], small[0], c)
    den = cv2.GaussianBlur(w_bg, (0, 0), s4)
    bg = num / np.maximum(den, 1e-3)[:, :, None]
    rows, cols = np.nonzero(band)
    diff = (
        a[rows, cols].astype(np.float32)
        - bg[np.minimum(rows // 4, small[1] - 1), np.minimum(cols // 4, small[0] - 1)]
    )
    c2 = np.einsum("ij,ij->i", diff, diff)
    on_core = core[rows, cols]
    dense = np.zeros((h, w), np.float32)
    dense[rows[on_core], cols[on_core]] = c2[on_core]
    peak = cv2.dilate(dense, k)[rows, cols]
    out = np.zeros((h, w), bool)
    keep = (c2 >= 0.25 * peak) & (peak > 0)
    out[rows[keep], cols[keep]] = True
    return out


def _lift(grey: np.ndarray, P: np.ndarray, dilate_px: int) -> np.ndarray:
    """Eq. (1): keep the image on P (dilated by ``dilate_px``), 255 elsewhere."""
    if dilate_px > 0:
        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        P = cv2.dilate(P.astype(np.uint8), k).astype(bool)
    return np.where(P, grey, np.float32(LIFT_VALUE)).astype(np.float32)


def _background_level(grey: np.ndarray, p: SegmentationParams) -> float:
    if p.background is not None:
        return float(p.background)
    hist = cv2.calcHist([np.clip(grey, 0, 255).astype(np.uint8)], [0], None, [256], [0, 256])
    return float(np.argmax(hist))


def _drop_specks(mask: np.ndarray, min_px: int) -> np.ndarray:
    if min_px <= 1 or not mask.any():
        return mask
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_px
    keep[0] = False
    return keep[labels]
