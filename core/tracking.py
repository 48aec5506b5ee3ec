"""Tracking across frames: the previous frame's curve informs the next.

The single-frame pipeline (Section III of the paper) runs unchanged on every frame; tracking
adds, per frame t, with the previous tracked curve ``x_{t-1}`` and its velocity ``v_{t-1}``
(both (N, 3) samples uniform in arc length):

1. **Search range**: the stereo search range alpha of Eq. (3) is set from the predicted
   curve's largest disparity plus a margin (:func:`search_alpha`).
2. **Prediction** (motion prior): ``x_pred = x_{t-1} + v_{t-1}`` (constant velocity; ``v`` is
   the smoothed mean displacement of the observed curve normal to itself).
3. **Observed part**: an end of the single-frame curve that no stereo point of the frame
   supports (the spline ran on past its data) is trimmed; the prior fills it in (4.).
   **Start and direction**: the single-frame curve is reversed when that brings it closer to
   the prediction, so the curve's u = 0 end stays the same physical end.
4. **Hidden pieces**: the part of the prediction beyond the observed curve's ends (an end
   hidden by an instrument, or dropped by the ordering) is taken from the prediction, moved
   rigidly so that it joins the observed curve where the two meet, and pulled onto this frame's
   stereo points where it has some. A thread does not stretch: while the observation is
   shorter than the longest length seen since the track started, any predicted end beyond it
   is kept (so an end hidden a little more every frame is not lost bit by bit); otherwise only
   pieces longer than ``min_hidden_mm``.
5. **Temporal smoothness**: each sample moves towards its predicted position by
   ``smooth * exp(-(d / cover_mm)^2)``, d the distance between the two, so noise is damped and
   real disagreements are not.

6. **Gate** (:func:`gate_corrections`): when the single-frame curve of a frame is doubted, the
   segmentation's masks are cut to a band around the prediction reprojected into both views
   (widened by one frame's predicted motion): a piece of the masks far from where the thread
   can be (an instrument's shaft or jaws, a vessel) is a distractor. The band is a mask
   correction (``keep``, :mod:`core.corrections`), so the debugger shows what it removed.

A track (re)starts only from a curve the single-frame check calls "ok": a doubted first curve
(an instrument taken for thread) would otherwise be locked onto and gate the thread away.
A frame where the tracked and the single-frame curves differ by more than ``disagree_mm``
(Hausdorff distance) is flagged; the single-frame curve is always kept beside the tracked one.
Everything here is a pure function of arrays and frozen dataclasses; units are those of the
points (the calibration's unit, mm for the generator).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Final, Literal

import cv2
import numpy as np
from scipy.spatial import cKDTree

from threadrecon.core.corrections import MAX_RADIUS_PX, MAX_STROKE_POINTS, Correction
from threadrecon.core.numeric import distance_to_zero
from threadrecon.core.params import Params, param

MIN_ALPHA: Final = 8  # the smallest stereo search range tracking sets, px (Eq. (3) needs > 4)
MAX_ALPHA: Final = 512  # the largest the stereo stage accepts, px
_EPS: Final = 1e-9
_MIN_SUPPORTED: Final = 0.2  # share of a curve that must be supported before trimming its ends
_MIN_SUPPORTED_REJECTED: Final = 0.5  # share of a rejected curve that stereo must support
_SNAP_NEIGHBOURS: Final = 8  # stereo points averaged per sample when snapping a filled piece
_SNAP_SMOOTH: Final = 3.0  # std of the smoothing of snap offsets along a piece, samples
START_PIECES: Final = 3  # pieces tried one by one to start a track: a few pipeline runs a frame

Status = Literal["ok", "predicted", "lost"]


@dataclass(frozen=True)
class TrackParams(Params):
    enabled: bool = True
    """Track across frames (on by default for sequences); off: single-frame results only."""
    n_samples: int = param(200, lo=10, hi=5000, unit="points", label="track samples")
    """Samples of the tracked curve, uniform in arc length."""
    smooth: float = param(0.5, lo=0, hi=0.95, slider=(0.0, 0.95, 0.05), label="smoothness")
    """Weight lambda of the prediction in the temporal smoothness term (0: none)."""
    cover_mm: float = param(2.0, lo=1e-6, hi=1000, unit="calib. unit", label="cover distance")
    """An observed point within this distance explains a predicted one (calibration units)."""
    min_hidden_mm: float = param(4.0, lo=0, hi=1000, unit="calib. unit", label="min hidden piece")
    """An unexplained predicted end shorter than this is not filled in (calibration units)."""
    disagree_mm: float = param(8.0, lo=0, hi=1000, unit="calib. unit", label="disagreement flag")
    """Flag a frame whose tracked and single-frame curves differ by more (Hausdorff)."""
    min_overlap: float = param(0.3, lo=0, hi=1, label="min overlap")
    """Below this share of the prediction explained by the observation, the track restarts."""
    velocity_gain: float = param(0.5, lo=0, hi=1, label="velocity gain")
    """Exponential smoothing of the per-sample velocity (1: last displacement only)."""
    snap_mm: float = param(4.0, lo=0, hi=1000, unit="calib. unit", label="snap distance")
    """A filled piece is pulled onto this frame's stereo points within this distance."""
    support_mm: float = param(4.0, lo=0, hi=1000, unit="calib. unit", label="support distance")
    """An end of the single-frame curve farther than this from every stereo point of the frame
    was not observed (the spline ran on past its data): it is trimmed and taken from the prior."""
    max_coast: int = param(3, lo=0, hi=1000, unit="frames", label="max predicted frames")
    """Frames in a row the curve may be predicted without an observation before it is lost."""
    alpha_margin_px: float = param(10.0, lo=0, hi=512, unit="px", label="search margin")
    """Margin above the predicted largest disparity for the stereo search range, px."""
    gate_px: float = param(12.0, lo=0, hi=MAX_RADIUS_PX, unit="px", label="gate half-width")
    """Half-width of the band around the reprojected prediction that a doubted frame's masks
    are cut to, px, before one frame's predicted motion is added (0: no gate)."""
    thick_px: float = param(6.0, lo=0, hi=MAX_RADIUS_PX, unit="px", label="thicker than thread")
    """The gate also removes the parts of the band that a disk of this radius fits in: thicker
    than a thread (an instrument crossing it), px (0: keeps them)."""


@dataclass(frozen=True)
class TrackState:
    """What a frame hands to the next. ``points``: (N, 3) tracked curve, uniform in arc
    length; ``velocity``: (N, 3) per-sample displacement per frame (the same translation for
    every sample: the thread's motion normal to itself, the part an observation shows);
    ``coasted``: frames in a row predicted without an observation."""

    points: np.ndarray
    velocity: np.ndarray
    coasted: int = 0
    length_ref: float = math.nan
    """Longest observed length since the track started: a thread does not stretch, so an
    observation shorter than this has a hidden piece (calibration units)."""

    def __post_init__(self) -> None:
        for name in ("points", "velocity"):
            a = getattr(self, name)
            if a.ndim != 2 or a.shape[1] != 3 or len(a) < 2:
                raise ValueError(f"TrackState.{name} must be (N >= 2, 3), got {a.shape}")
        if self.points.shape != self.velocity.shape:
            raise ValueError(
                f"TrackState points {self.points.shape} and velocity {self.velocity.shape} differ"
            )

    @property
    def predicted(self) -> np.ndarray:
        """(N, 3) constant-velocity prediction of the next frame's curve."""
        return self.points + self.velocity


@dataclass(frozen=True)
class TrackResult:
    """One frame's tracked curve beside its single-frame curve.

    ``points``: (N, 3) tracked curve (None when lost); ``single``: (M, 3) single-frame curve
    (None when that failed); ``status``: "ok" (observation used), "predicted" (no usable
    observation: the motion prior alone) or "lost"; ``flagged`` with ``reason`` when tracking
    and single-frame disagree; ``disagreement``: their Hausdorff distance (NaN when either is
    missing); ``filled``: length taken from the motion prior (hidden pieces); ``reversed``:
    the single-frame curve was flipped to keep the start; ``restarted``: no usable prior.
    """

    points: np.ndarray | None
    single: np.ndarray | None
    status: Status
    flagged: bool
    reason: str
    disagreement: float
    filled: float
    reversed: bool
    restarted: bool

    @property
    def length(self) -> float:
        return math.nan if self.points is None else polyline_length(self.points)


def polyline_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def resample(points: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) points uniform in arc length along the polyline ``points`` (M, 3)."""
    points = _check_curve(points, "points")
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    if s[-1] <= _EPS:
        return np.repeat(points[:1], n, axis=0)
    q = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(q, s, points[:, a]) for a in range(3)])


def search_alpha(
    state: TrackState | None, P1: np.ndarray, P2: np.ndarray, p: TrackParams
) -> int | None:
    """Stereo search range alpha (px) for the next frame from the predicted curve's largest
    disparity, Eq. (3); None without a prior (keep the configured alpha).

    ``P1``, ``P2``: (3, 4) rectified projection matrices of the left and right cameras.
    """
    if state is None or not p.enabled:
        return None
    x = state.predicted
    h = np.column_stack([x, np.ones(len(x))])
    uL, uR = h @ np.asarray(P1).T, h @ np.asarray(P2).T
    if np.any(uL[:, 2] <= _EPS):
        return None
    disparity = uL[:, 0] / uL[:, 2] - uR[:, 0] / uR[:, 2]
    if not np.all(np.isfinite(disparity)):
        return None
    return int(np.clip(math.ceil(disparity.max() + p.alpha_margin_px), MIN_ALPHA, MAX_ALPHA))


def gate_corrections(
    state: TrackState | None,
    P1: np.ndarray,
    P2: np.ndarray,
    shape: tuple[int, int],
    p: TrackParams,
    masks: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[Correction, ...]:
    """The tracker's gate on the next frame's masks P_L, P_R: per view, a ``keep`` correction,
    the band of half-width ``gate_px`` plus the predicted motion (px, the largest displacement
    of a sample between ``state.points`` and the prediction, reprojected) around the predicted
    curve projected with the rectified ``P1`` (left) and ``P2`` (right), (3, 4); then, given the
    segmented ``masks`` (P_L, P_R) (H, W) bool, ``erase`` corrections of the parts of the band
    thicker than a thread (the disks of radius ``thick_px`` that fit in the mask: an instrument
    where it crosses the thread, one stroke per row of disk centres). Samples outside the
    (H, W) ``shape`` are clamped to its border (the band follows the thread out of view).
    Empty without a prior, with tracking off, ``gate_px`` 0, or a prediction behind a camera."""
    if state is None or not p.enabled or p.gate_px <= 0:
        return ()
    if masks is not None and any(np.shape(m) != tuple(shape) for m in masks):
        raise ValueError(
            f"masks must be two {tuple(shape)} masks, got {[np.shape(m) for m in masks]}"
        )
    h, w = shape
    out = []
    for i, (view, P) in enumerate((("left", P1), ("right", P2))):
        uv_next = _project(state.predicted, P)
        uv_now = _project(state.points, P)
        if uv_next is None or uv_now is None:
            return ()
        motion = float(np.linalg.norm(uv_next - uv_now, axis=1).max())
        radius = min(p.gate_px + motion, MAX_RADIUS_PX)
        xy = np.rint(uv_next).astype(np.int64)
        xy[:, 0] = np.clip(xy[:, 0], 0, w - 1)
        xy[:, 1] = np.clip(xy[:, 1], 0, h - 1)
        keep = np.ones(len(xy), dtype=bool)
        keep[1:] = np.any(xy[1:] != xy[:-1], axis=1)  # no repeated pixel
        xy = xy[keep][:MAX_STROKE_POINTS]
        points = tuple((int(x), int(y)) for x, y in xy)
        out.append(Correction("keep", view, points, radius))  # type: ignore[arg-type]
        if masks is not None and p.thick_px > 0:
            near = _near_polyline(shape, xy, radius + p.thick_px)
            out += _thick_erasures(np.asarray(masks[i], bool), view, p.thick_px, near)
    return tuple(out)


def _thick_erasures(
    mask: np.ndarray, view: str, r: float, near: np.ndarray | None = None
) -> list[Correction]:
    """``erase`` strokes of radius ``r`` through every row run of the pixels of ``mask`` whose
    distance to its border is >= ``r`` (the centres of the disks that fit in it: their union is
    the mask's opening by that disk, what is thicker than a thread), restricted to ``near``
    (H, W) bool when given."""
    dist = distance_to_zero(mask.astype(np.uint8))
    centres = dist >= r
    if near is not None:
        centres &= near
    padded = np.pad(centres, ((0, 0), (1, 1))).astype(np.int8)
    rows, cols = np.nonzero(np.diff(padded, axis=1))  # run starts and (exclusive) ends per row
    bounds = zip(rows[0::2], cols[0::2], cols[1::2], strict=True)
    runs = [(int(y), int(a), int(b) - 1) for y, a, b in bounds]
    per_row = np.bincount([y for y, _, _ in runs], minlength=mask.shape[0]) if runs else None
    strokes: list[list[tuple[int, int]]] = []
    last: tuple[int, int, int] | None = None
    for y, a, b in runs:  # one stroke through consecutive rows of one overlapping run each
        alone = per_row is not None and per_row[y] == 1
        if alone and last is not None and last[0] == y - 1 and a <= last[2] and b >= last[1]:
            m = max(a, last[1])  # a column in both runs: the step down stays on disk centres
            strokes[-1] += [(m, y - 1), (m, y), (a, y), (b, y)]
        else:
            strokes.append([(a, y), (b, y)])
        last = (y, a, b) if alone else None
        if len(strokes[-1]) > MAX_STROKE_POINTS - 4:
            last = None
    return [Correction("erase", view, tuple(pts), float(r)) for pts in strokes]  # type: ignore[arg-type]


def _near_polyline(shape: tuple[int, int], xy: np.ndarray, distance: float) -> np.ndarray:
    """(H, W) bool: the pixels within ``distance`` of the polyline through ``xy`` (K, 2)."""
    line = np.ones(shape, np.uint8)
    cv2.polylines(line, [xy.astype(np.int32).reshape(-1, 1, 2)], False, 0, thickness=1)
    line[xy[0, 1], xy[0, 0]] = 0
    return distance_to_zero(line) <= distance


def start_corrections(
    P_L: np.ndarray,
    P_R: np.ndarray | None = None,
    thick_px: float = 0.0,
    pieces: int = START_PIECES,
) -> list[tuple[Correction, ...]]:
    """Hypotheses for starting a track when the frame's single-frame curve is doubted, in
    order: with ``thick_px`` > 0 and the right mask ``P_R``, the removal of what is thicker than
    a thread in both views (the disks of radius ``thick_px`` that fit in the masks: an
    instrument's shaft, also where it touches the thread); then for each of the ``pieces``
    largest 8-connected pieces of the left mask P_L (H, W) bool, the piece's removal in both
    views (``remove`` with its stereo partner, :mod:`core.corrections`), largest first (none
    when P_L has fewer than two pieces). The caller keeps the first hypothesis whose curve the
    check calls "ok"."""
    P_L = np.asarray(P_L)
    if P_L.ndim != 2:
        raise ValueError(f"P_L must be an (H, W) mask, got {P_L.shape}")
    out: list[tuple[Correction, ...]] = []
    if thick_px > 0 and P_R is not None:
        if np.shape(P_R) != P_L.shape:
            raise ValueError(f"P_R is {np.shape(P_R)}, P_L {P_L.shape}: masks of one pair differ")
        thick = (*_thick_erasures(P_L, "left", thick_px), *_thick_erasures(P_R, "right", thick_px))
        if thick:
            out.append(thick)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(P_L.astype(np.uint8), connectivity=8)
    if n < 3:  # background and at most one piece
        return out
    order = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA], kind="stable")[:pieces]
    for k in order:  # a handful of pieces
        rows, cols = np.nonzero(labels == k)
        click = ((int(cols[0]), int(rows[0])),)  # a pixel of the piece: it alone is removed
        out.append((Correction("remove", "left", click, 0.5, stereo=True),))
    return out


def _project(x: np.ndarray, P: np.ndarray) -> np.ndarray | None:
    """(N, 2) pixels (x, y) of the points ``x`` (N, 3) by the (3, 4) ``P``; None when a point
    is behind the camera or not finite."""
    u = np.column_stack([x, np.ones(len(x))]) @ np.asarray(P, dtype=np.float64).T
    if np.any(u[:, 2] <= _EPS) or not np.all(np.isfinite(u)):
        return None
    return u[:, :2] / u[:, 2:]


def track_step(
    single: np.ndarray | None,
    state: TrackState | None,
    p: TrackParams,
    cloud: np.ndarray | None = None,
    check: Literal["ok", "suspect", "failed"] = "ok",
    single_frame: np.ndarray | None | Literal["same"] = "same",
) -> tuple[TrackResult, TrackState | None]:
    """One frame of tracking: the single-frame curve ``single`` (M, 3) (None when the
    single-frame pipeline gave none), this frame's reliable stereo points ``cloud`` (K, 3)
    (optional: pieces filled from the prior are pulled onto them) and the previous state
    -> this frame's result and state.

    ``single_frame``: when the observation ``single`` comes from another run than the
    single-frame one (the masks with the tracker's corrections, :func:`gate_corrections`), the
    single-frame curve (M, 3) or None: the result keeps it and is flagged against it.

    ``check``: the single-frame check's verdict on the curve. Only an "ok" curve (re)starts a
    track. A doubted curve ("suspect" or "failed") is believed only where it also lies within
    ``disagree_mm`` of the prediction (the rest is trimmed at the ends or taken from the prior
    inside), and not at all when it explains less than ``min_overlap`` of the prediction (the
    frame is predicted). A "failed" curve is used only with a ``cloud``, when at least half of
    it is supported; it does not teach the thread's length."""
    res, new = _track_step(single, state, p, cloud, check)
    if isinstance(single_frame, str):
        return res, new
    return _against_single(res, single_frame, p), new


def _against_single(res: TrackResult, single: np.ndarray | None, p: TrackParams) -> TrackResult:
    """``res`` flagged against the single-frame curve ``single`` instead of its observation."""
    if single is not None:
        single = _check_curve(single, "single_frame")
    if res.points is None:
        return dataclasses.replace(res, single=single)
    d = math.nan if single is None else _hausdorff(res.points, single)
    parts = [r for r in res.reason.split("; ") if r and not r.startswith(_DIFFER)]
    flagged = not d <= p.disagree_mm  # NaN (no single-frame curve) is flagged too
    if flagged:
        parts.insert(0, f"{_DIFFER} by {d:.1f} (> {p.disagree_mm:g})" if single is not None
                     else "no single-frame curve")  # fmt: skip
    return dataclasses.replace(res, single=single, flagged=flagged, reason="; ".join(parts),
                               disagreement=d)  # fmt: skip


def _track_step(
    single: np.ndarray | None,
    state: TrackState | None,
    p: TrackParams,
    cloud: np.ndarray | None,
    check: Literal["ok", "suspect", "failed"],
) -> tuple[TrackResult, TrackState | None]:
    rejected = check == "failed"
    if cloud is not None:
        cloud = np.asarray(cloud, dtype=np.float64)
        if cloud.ndim != 2 or cloud.shape[1] != 3:
            raise ValueError(f"cloud must be (K, 3) points, got {cloud.shape}")
        cloud = cloud[np.all(np.isfinite(cloud), axis=1)]
    if single is not None:
        single = _check_curve(single, "single")
        if not np.all(np.isfinite(single)):
            single = None  # a non-finite curve is no observation
    n = p.n_samples
    if rejected and single is not None and not _usable_rejected(single, state, cloud, p):
        single = None
    if not p.enabled:
        return _restart(single, n, restarted=False)
    if state is None:
        if check != "ok" and single is not None:  # a track starts from an "ok" curve only
            reason = f"no track: the single-frame curve is {check}, a track starts from an ok one"
            return TrackResult(None, single, "lost", False, reason, *_NO_FIT), None
        return _restart(single, n, restarted=True)
    if len(state.points) != n:
        raise ValueError(f"state has {len(state.points)} samples, params say {n}")
    pred = state.predicted
    if single is None:
        if state.coasted >= p.max_coast:
            res = TrackResult(None, None, "lost", True, "no observation; track lost", *_NO_FIT)
            return res, None
        res = TrackResult(
            pred, None, "predicted", True, "single-frame failed; curve predicted", *_NO_FIT
        )
        return res, TrackState(pred, state.velocity, state.coasted + 1, state.length_ref)

    doubted = pred if check != "ok" else None  # a doubted curve must agree with the prior too
    obs = resample(_trim_unsupported(single, cloud, p, doubted), n)
    reversed_ = _closer_reversed(obs, pred)
    if reversed_:
        obs = obs[::-1]
    d_pred = cKDTree(obs).query(pred)[0]  # how well the observation explains each prediction
    explained = d_pred <= p.cover_mm
    if explained.mean() < p.min_overlap:
        if check != "ok":  # a doubted curve that disagrees with the prior is no observation
            return _track_step(None, state, p, cloud, "ok")
        res, new = _restart(single, n, restarted=True)
        reason = f"observation explains {100 * explained.mean():.0f}% of the prediction; restarted"
        return _replace_flag(res, reason, reversed_), new

    # The known length learns from what was seen: no gap filled from the prior, no rejected curve.
    length_seen = math.nan if rejected else polyline_length(obs)
    obs, gap_filled = _fill_hidden_gaps(obs, pred, cloud, p, doubted is not None)
    length_obs = polyline_length(obs)
    # A shorter observation than the thread's known length has a hidden piece: keep any predicted
    # end beyond it; otherwise only ends longer than min_hidden_mm (noise at the ends is no piece).
    hidden = length_obs < state.length_ref - p.cover_mm
    min_piece = 0.5 * p.cover_mm if hidden else p.min_hidden_mm
    # A thread does not stretch either: the ends filled in may add what the observation misses
    # of the known length, no more (a wrong piece of the prior is not carried on for ever).
    budget = state.length_ref - length_obs + p.cover_mm
    budget = math.inf if not math.isfinite(budget) else max(budget, 0.0)
    if cloud is not None and len(cloud):  # stereo points of the observed curve are not for snapping
        cloud = cloud[cKDTree(obs).query(cloud)[0] > p.cover_mm]
    curve, filled = _fill_hidden_ends(obs, pred, min_piece, cloud, p, budget)
    filled += gap_filled
    curve = resample(curve, n)
    # Temporal smoothness: pull towards the prediction where the two agree.
    pred_c = _match(curve, pred)
    d = np.linalg.norm(curve - pred_c, axis=1)
    w = p.smooth * np.exp(-((d / p.cover_mm) ** 2))
    curve = resample(curve + w[:, None] * (pred_c - curve), n)

    disagreement = _hausdorff(curve, single)
    flagged = disagreement > p.disagree_mm
    reason = f"{_DIFFER} by {disagreement:.1f} (> {p.disagree_mm:g})" if flagged else ""
    if filled > 0:
        reason = (reason + "; " if reason else "") + f"{filled:.1f} filled from the motion prior"
    # Velocity: mean displacement of the observed samples to the previous curve (normal motion;
    # motion along the thread is invisible), smoothed over frames.
    step = np.mean(obs - state.points[cKDTree(state.points).query(obs)[1]], axis=0)
    velocity = p.velocity_gain * step + (1 - p.velocity_gain) * state.velocity
    res = TrackResult(curve, single, "ok", flagged, reason, disagreement, filled, reversed_, False)
    return res, TrackState(curve, velocity, 0, float(np.fmax(state.length_ref, length_seen)))


# ----------------------------------------------------------------------------------------------

_NO_FIT = (math.nan, 0.0, False, False)  # disagreement, filled, reversed, restarted
_DIFFER = "tracked and single-frame curves differ"


def _check_curve(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2:
        raise ValueError(f"{name} must be (M >= 2, 3) points, got {points.shape}")
    return points


def _usable_rejected(
    single: np.ndarray, state: TrackState | None, cloud: np.ndarray | None, p: TrackParams
) -> bool:
    """A curve the single-frame check rejected may serve as an observation (see track_step)."""
    if state is None or not p.enabled or cloud is None or len(cloud) == 0:
        return False
    if not np.all(np.isfinite(single)):
        return False
    return bool(np.mean(cKDTree(cloud).query(single)[0] <= p.support_mm) >= _MIN_SUPPORTED_REJECTED)


def _supported(
    x: np.ndarray, cloud: np.ndarray | None, pred: np.ndarray | None, p: TrackParams
) -> np.ndarray:
    """(N,) bool: the samples of ``x`` with a stereo point within ``support_mm`` (all when there
    is no cloud) and, when ``pred`` is given (a doubted curve), within ``disagree_mm`` of it."""
    ok = np.ones(len(x), dtype=bool)
    if cloud is not None and len(cloud):
        ok &= cKDTree(cloud).query(x)[0] <= p.support_mm
    if pred is not None:
        ok &= cKDTree(pred).query(x)[0] <= p.disagree_mm
    return ok


def _trim_unsupported(
    single: np.ndarray, cloud: np.ndarray | None, p: TrackParams, pred: np.ndarray | None = None
) -> np.ndarray:
    """``single`` without the end runs that no stereo point of the frame supports (nor, for a
    doubted curve, the prediction ``pred``); kept whole when almost nothing would remain."""
    if (cloud is None or len(cloud) == 0) and pred is None:
        return single
    # Judged on the curve's own samples (even along the image): resampled in arc length, a run
    # off in depth would outweigh the observed part.
    supported = np.flatnonzero(_supported(single, cloud, pred, p))
    if supported.size < _MIN_SUPPORTED * len(single) or supported[-1] == supported[0]:
        return single
    return single[supported[0] : supported[-1] + 1]


def _restart(
    start: np.ndarray | None, n: int, restarted: bool, single: np.ndarray | None = None
) -> tuple[TrackResult, TrackState | None]:
    """A new track from the curve ``start`` (``single``: the single-frame curve it came from,
    when not ``start`` itself)."""
    if start is None:
        return TrackResult(None, None, "lost", False, "no observation", *_NO_FIT), None
    x = resample(start, n)
    single = start if single is None else single
    res = TrackResult(x, single, "ok", False, "", 0.0, 0.0, False, restarted)
    return res, TrackState(x, np.zeros_like(x), 0, polyline_length(x))


def _replace_flag(res: TrackResult, reason: str, reversed_: bool) -> TrackResult:
    return TrackResult(
        res.points, res.single, res.status, True, reason, 0.0, 0.0, reversed_, res.restarted
    )


def _closer_reversed(obs: np.ndarray, pred: np.ndarray) -> bool:
    """True when the reversed observation lies closer to the prediction, sample by sample
    (compared over the observation's ends, which carry the direction)."""
    k = max(2, len(obs) // 10)
    fwd = np.linalg.norm(obs[:k] - pred[:k], axis=1).sum()
    fwd += np.linalg.norm(obs[-k:] - pred[-k:], axis=1).sum()
    rev = np.linalg.norm(obs[::-1][:k] - pred[:k], axis=1).sum()
    rev += np.linalg.norm(obs[::-1][-k:] - pred[-k:], axis=1).sum()
    # Ends may be hidden: compare nearest-point positions along the prediction instead when
    # the observation is much shorter than the prediction.
    if polyline_length(obs) < 0.8 * polyline_length(pred):
        j = cKDTree(pred).query(obs[[0, -1]])[1]
        return bool(j[0] > j[1])
    return bool(rev < fwd)


def _fill_hidden_ends(
    obs: np.ndarray,
    pred: np.ndarray,
    min_piece: float,
    cloud: np.ndarray | None,
    p: TrackParams,
    budget: float = math.inf,
) -> tuple[np.ndarray, float]:
    """Prepend/append the predicted ends the observation does not explain: each is cut from the
    prediction where the observed end meets it, moved rigidly onto that end, then pulled onto
    this frame's stereo points ``cloud`` where it has some (hidden stretches keep the prior).
    Together the two ends add at most ``budget`` of length (each shortened in proportion)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pred, axis=0), axis=1))])
    s_ends = _arc_position(pred, s, obs[[0, -1]])
    head_len, tail_len = s_ends[0], s[-1] - s_ends[1]
    scale = min(1.0, budget / max(head_len + tail_len, _EPS))
    head_len, tail_len = scale * head_len, scale * tail_len
    parts = [obs]
    filled = 0.0
    if head_len > min_piece:
        keep = (s < s_ends[0]) & (s >= s_ends[0] - head_len)
        head = pred[keep] + (obs[0] - _at(pred, s, s_ends[0]))
        parts.insert(0, _snap(head, cloud, p, anchor_last=True))
        filled += head_len
    if tail_len > min_piece:
        keep = (s > s_ends[1]) & (s <= s_ends[1] + tail_len)
        tail = pred[keep] + (obs[-1] - _at(pred, s, s_ends[1]))
        parts.append(_snap(tail, cloud, p, anchor_last=False))
        filled += tail_len
    return np.vstack(parts), float(filled)


def _fill_hidden_gaps(
    obs: np.ndarray, pred: np.ndarray, cloud: np.ndarray | None, p: TrackParams, doubted: bool
) -> tuple[np.ndarray, float]:
    """Interior runs of the observation (N, 3) that no stereo point of the frame supports
    (farther than ``support_mm``: the spline bridged a piece hidden by an instrument) are taken
    from the prediction between the arc positions where the run's two supported neighbours meet
    it, moved to join both (offset blended linearly along the run); returns the curve and the
    length taken from the prior. A ``doubted`` curve's runs far from the prediction are too."""
    if (cloud is None or len(cloud) == 0) and not doubted:
        return obs, 0.0
    unsupported = ~_supported(obs, cloud, pred if doubted else None, p)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], unsupported.astype(np.int8), [0]])))
    runs = [(a, b) for a, b in zip(edges[0::2], edges[1::2], strict=True) if a > 0 and b < len(obs)]
    if not runs:
        return obs, 0.0
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pred, axis=0), axis=1))])
    out = obs.copy()
    filled = 0.0
    for a, b in runs:  # a handful of runs [a, b)
        if polyline_length(obs[a - 1 : b + 1]) <= p.min_hidden_mm:
            continue  # a short stretch without stereo points is no hidden piece
        sa, sb = _arc_position(pred, s, obs[[a - 1, b]])
        if sb <= sa:
            continue  # the prediction runs the other way here: no consistent prior
        t = np.linspace(0.0, 1.0, b - a + 2)[1:-1]
        piece = np.column_stack([np.interp(sa + t * (sb - sa), s, pred[:, k]) for k in range(3)])
        o0 = obs[a - 1] - _at(pred, s, sa)
        o1 = obs[b] - _at(pred, s, sb)
        out[a:b] = piece + (1 - t)[:, None] * o0 + t[:, None] * o1
        filled += polyline_length(out[a - 1 : b + 1])
    return out, float(filled)


def _arc_position(pred: np.ndarray, s: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Arc position along ``pred`` of the closest point to each of ``q`` (K, 3)."""
    a, ab = pred[:-1], np.diff(pred, axis=0)
    out = np.empty(len(q))
    for i, x in enumerate(q):  # a handful of query points
        t = np.clip(np.einsum("ij,ij->i", x - a, ab) / np.maximum((ab * ab).sum(1), _EPS), 0, 1)
        d = np.linalg.norm(a + t[:, None] * ab - x, axis=1)
        j = int(np.argmin(d))
        out[i] = s[j] + t[j] * (s[j + 1] - s[j])
    return out


def _at(pred: np.ndarray, s: np.ndarray, si: float) -> np.ndarray:
    return np.array([np.interp(si, s, pred[:, a]) for a in range(3)])


def _snap(piece: np.ndarray, cloud: np.ndarray | None, p: TrackParams, anchor_last: bool):
    """Move a predicted piece (K, 3) onto the stereo points near it: per sample the mean
    offset to the cloud points within ``snap_mm``, smoothed along the piece; samples with no
    point nearby take their neighbours' offsets; the end joined to the observation stays put."""
    if cloud is None or len(cloud) == 0 or len(piece) == 0:
        return piece
    tree = cKDTree(cloud)
    k = min(_SNAP_NEIGHBOURS, len(cloud))
    d, j = tree.query(piece, k=k, distance_upper_bound=p.snap_mm)
    d, j = d.reshape(len(piece), k), j.reshape(len(piece), k)
    hit = np.isfinite(d)
    count = hit.sum(1)
    has = count > 0
    if not has.any():
        return piece
    pts = np.where(hit[..., None], cloud[np.minimum(j, len(cloud) - 1)], 0.0)
    offset = np.zeros_like(piece)
    offset[has] = pts[has].sum(1) / count[has, None] - piece[has]
    i = np.arange(len(piece))
    anchor = len(piece) - 1 if anchor_last else 0
    known = has.copy()
    known[anchor] = True
    offset[anchor] = 0.0  # the junction with the observed curve does not move
    offset = np.column_stack([np.interp(i, i[known], offset[known, a]) for a in range(3)])
    kernel = np.exp(-0.5 * (np.arange(-3 * _SNAP_SMOOTH, 3 * _SNAP_SMOOTH + 1) / _SNAP_SMOOTH) ** 2)
    kernel /= kernel.sum()
    padded = np.pad(offset, ((len(kernel) // 2,) * 2, (0, 0)), mode="edge")
    offset = np.column_stack([np.convolve(padded[:, a], kernel, "valid") for a in range(3)])
    return piece + offset


def _match(curve: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """For each sample of ``curve``, the prediction at the same arc-length share measured from
    where the curve's start meets the prediction (handles a shorter or longer curve)."""
    tree = cKDTree(pred)
    j0, j1 = tree.query(curve[[0, -1]])[1]
    if j1 <= j0:
        return pred  # the curve does not run along the prediction: match by index
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pred, axis=0), axis=1))])
    t = np.linspace(s[j0], s[j1], len(curve))
    return np.column_stack([np.interp(t, s, pred[:, a]) for a in range(3)])


def _hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    a, b = resample(a, 400), resample(b, 400)
    return float(max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max()))


def motion_error(
    prev: np.ndarray, cur: np.ndarray, prev_gt: np.ndarray, cur_gt: np.ndarray, n: int = 200
) -> float:
    """Frame-to-frame jitter: mean over matched points i of
    ``|(cur_i - prev_i) - (cur_gt_i - prev_gt_i)|``, the error of the curve's motion between
    two frames. Each curve is resampled to ``n`` points uniform in arc length (point i of one
    frame is matched to point i of the next) and oriented like its ground truth, so a curve
    that flips its direction is not counted as motion."""
    curves = []
    for c, g in ((prev, prev_gt), (cur, cur_gt)):
        c, g = resample(c, n), resample(g, n)
        if _closer_reversed(c, g):
            c = c[::-1]
        curves.append((c, g))
    (a, ag), (b, bg) = curves
    return float(np.linalg.norm((b - a) - (bg - ag), axis=1).mean())
