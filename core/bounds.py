"""Extra points H between sparse keypoints and the depth bounds of Eq. (7).

Extra points: between consecutive keypoints whose linking gap holds more than ``extra_px``
segmented pixels, the gap pixels are ordered by their geodesic position between the two
clusters (``Ordering.pixel_t``; the paper orders "based on their location between these
keypoints", the published code by projection on the chord, which drops loops and curled tails)
and cut into runs of ``extra_px`` pixels; each run gives one point of H (centroid in
the image, median stereo depth). Together with the keypoints they form H with order phi^H.

Bounds: for each ordered keypoint k_i the depths of the points of H between k_{i-r_k} and
k_{i+r_k} are fitted with a least-squares line L_{k_i} (depth against 2D arc length along H);
Eq. (7) puts the bounds at k_{i,z} -+ ``bound_scale`` * |L_{k_i}(k_i) - k_{i,z}|. Between keypoints
the bounds are interpolated linearly. A half-width below ``widen_px`` pixels of disparity, i.e.
``widen_px * Z^2 / (f B)`` in depth, is widened to it: a unit-free threshold that follows the
depth resolution of the rig (the paper leaves this threshold unstated).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from threadrecon.core import walk_kernel
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.continuity import (
    DISPARITY_SLACK_PX,
    DISPARITY_SLOPE,
    depth_of,
    disparity_of,
    disparity_room,
    second_match_subpixel,
)
from threadrecon.core.ends import fuse_end
from threadrecon.core.numeric import row_norms
from threadrecon.core.ordering import OUTLIER_PX, Ordering
from threadrecon.core.params import Params, param
from threadrecon.core.stereo import StereoResult

T_TIE = 1e-12  # positions t this close are one (d_a / (d_a + d_b) from either end: ulps)
BORDER_PX = 2.0  # a left pixel within this of where its match leaves the right image: no depth


@dataclass(frozen=True)
class BoundsParams(Params):
    extra_px: int = param(
        24, lo=1, hi=10000, unit="px", slider=(4, 100, 1), label="extra point spacing px"
    )
    """Gap size (segmented px) per extra point; gaps larger than this get extra points."""
    r_k_frac: float = param(
        0.1, lo=0, hi=1, symbol="r_k/|K|", slider=(0.0, 0.5, 0.01), label="r_k = |K| ×"
    )
    """r_k = r_k_frac * |K| (paper: |K| / 10), at least ``r_k_min``."""
    r_k_min: int = param(2, lo=1, hi=1000, unit="keypoints", slider=(1, 20, 1), label="r_k min")
    """Smallest r_k, keypoints."""
    bound_scale: float = param(1.5, lo=1e-06, hi=100, slider=(1.0, 5.0, 0.05), label="bound scale")
    """Scale of |L(k) - k_z| in Eq. (7)."""
    widen_px: float = param(
        0.25, lo=0, hi=100, unit="px", slider=(0.0, 3.0, 0.05), label="widen threshold"
    )
    """Smallest bound half-width, px of disparity."""
    depth_ratio: float = param(
        2.0, lo=0, hi=100, slider=(0.0, 5.0, 0.1), label="extra point depth ratio"
    )
    """Extra points deeper than this many times, or nearer than its inverse of, the keypoints'
    depth interpolated at them leave the window lines of Eq. (7) (0: off, the paper): another
    strand's match or none (docs/method.md, deviation 26)."""
    drop_outliers: bool = False
    """Leave extra points whose disparity lies > ``OUTLIER_PX`` from the keypoints' out of the
    window lines of Eq. (7) (docs/method.md, deviation 21; measured better on held-out
    generated frames, not yet the default: it changes the repair's test frames)."""
    second_matches: bool = param(
        True,
        label="gap pixels' second matches",
        doc="Gap pixels matched to a neighbouring strand take their second match where it "
        "continues the strand from its keypoints (docs/method.md, deviation 30; off: the paper).",
    )
    dead_end_others: bool = param(
        True,
        label="dead end's other matches",
        doc="A dead end's pixel (the thread's end beyond its last keypoint) whose match, followed "
        "out from that keypoint, breaks with the strand by more than the continuity bound plus "
        "OUTLIER_PX and whose second match does not continue it has no depth of the thread (an "
        "occluder's edge in its window): its extra point leaves it out (docs/method.md, "
        "deviation 64; off: the paper).",
    )


@dataclass(frozen=True)
class Bounds:
    """Points of H in the order phi^H, all (P,) or (P, 3).

    ``H``: (x px, y px, z depth) with the stereo depth for extra points.
    ``is_key``: True for keypoints (incl. extension keypoints).
    ``s``: 2D arc length along H, px.
    ``centre``, ``lower``, ``upper``: depth bounds (calib units), Eq. (7) + interpolation.
    ``end_values``, ``end_slopes``: L_{k_1}, L_{k_n} at the end keypoints and their slopes
    d depth / d s (calib units per px), for the endpoint constraints of Eq. (8).
    ``r_k``: the window half-size used, keypoints.
    """

    H: np.ndarray
    is_key: np.ndarray
    s: np.ndarray
    centre: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    end_values: tuple[float, float]
    end_slopes: tuple[float, float]
    r_k: int
    line_ends: tuple[float, float, float, float] | None = None
    """(L_{k_1}, its slope, L_{k_n}, its slope) of the window lines alone (the paper's end
    constraints) when a tip matched in both views moved ``end_values`` (deviation 23), else
    None; the spline falls back to them when the tips' make Eq. (8) infeasible."""


def depth_bounds(
    stereo: StereoResult,
    ordering: Ordering,
    calib: StereoCalibration,
    p: BoundsParams = BoundsParams(),
) -> Bounds:
    """Build H and the lower/upper depth bounds."""
    if p.extra_px < 1:
        raise ValueError(f"extra_px must be >= 1, got {p.extra_px}")
    if p.bound_scale <= 0 or p.widen_px < 0 or p.r_k_frac < 0:
        raise ValueError("bound_scale must be > 0, widen_px and r_k_frac >= 0")
    path = ordering.path_px
    M = len(path)
    if M < 2:
        raise ValueError(f"need at least 2 ordered keypoints for a curve, got {M}")
    fB = calib.focal * calib.baseline
    path = _border_depths(path, fB)
    H, is_key = _extra_points(
        stereo, ordering, path, p.extra_px, fB, p.second_matches, p.dead_end_others
    )
    seg = row_norms(np.diff(H[:, :2], axis=0))
    s = np.concatenate([[0.0], np.cumsum(seg)])
    key_idx = np.flatnonzero(is_key)
    z_key = H[key_idx, 2]

    n_kp = int(np.sum(ordering.order >= 0))
    r_k = max(p.r_k_min, int(round(p.r_k_frac * n_kp)))
    z_rel = _fit_depths(H, is_key, s, key_idx, fB)  # extra points matched elsewhere: NaN
    z_fit = _off_by_ratio(H, is_key, s, key_idx, p.depth_ratio)
    z_fit = np.where(np.isnan(z_rel), np.nan, z_fit) if p.drop_outliers else z_fit
    line_at_key, slopes = _window_line_fits(s, z_fit, key_idx, r_k)
    paper_ends = (line_at_key[0], slopes[0], line_at_key[-1], slopes[-1])
    line_at_key, slopes = _tip_ends(
        line_at_key, slopes, ordering.end_disparity, s, z_rel, key_idx, r_k, fB
    )
    tipped = (line_at_key[0], slopes[0], line_at_key[-1], slopes[-1]) != paper_ends
    half = p.bound_scale * np.abs(line_at_key - z_key)  # Eq. (7)
    min_half = p.widen_px * z_key**2 / (calib.focal * calib.baseline)
    half = np.maximum(half, min_half)
    centre = np.interp(s, s[key_idx], z_key)
    half_all = np.interp(s, s[key_idx], half)
    return Bounds(
        H=H,
        is_key=is_key,
        s=s,
        centre=centre,
        lower=centre - half_all,
        upper=centre + half_all,
        end_values=(float(line_at_key[0]), float(line_at_key[-1])),
        end_slopes=(float(slopes[0]), float(slopes[-1])),
        r_k=r_k,
        line_ends=tuple(float(v) for v in paper_ends) if tipped else None,  # type: ignore[arg-type]
    )


def _tip_ends(
    line_at_key: np.ndarray,
    slopes: np.ndarray,
    end_disparity: np.ndarray,
    s: np.ndarray,
    z: np.ndarray,
    key_idx: np.ndarray,
    r_k: int,
    fB: float,
) -> tuple[np.ndarray, np.ndarray]:
    """L_{k_1}, L_{k_n} (Eq. (8)'s end values, and Eq. (7)'s lines at the end keypoints) fused
    with the depth of the tip matched in both views (``Ordering.end_disparity``, core/ends.py),
    each weighted by its inverse variance: the line's from its window's residuals and its
    distance from the end keypoint's depth, the tip's from its match. The end's slope is then the window's least-squares line through the fused
    end value (the line's own slope belongs to its own end value). The other keypoints' lines
    and slopes are returned unchanged."""
    out, out_slope = line_at_key.copy(), slopes.copy()
    M = len(key_idx)
    for row, i in ((0, 0), (1, M - 1)):
        d, var_d = end_disparity[row]
        if not (np.isfinite(d) and d > 0 and np.isfinite(var_d)):
            continue
        z_tip = fB / d
        var_tip = var_d * (z_tip * z_tip / fB) ** 2  # dz = z^2 / (f B) dd
        lo = key_idx[max(0, i - r_k)]
        hi = key_idx[min(M - 1, i + r_k)] + 1
        s_end = s[key_idx[i]]
        # The line's variance: its fit's, plus Eq. (7)'s own measure of doubt at a keypoint,
        # the line's distance from the keypoint's depth (an extra point matched elsewhere
        # pulls an extrapolated line by metres while its residuals stay moderate).
        doubt = float(line_at_key[i] - z[key_idx[i]])
        var_line = _line_variance(s[lo:hi], z[lo:hi], s_end) + doubt * doubt
        out[i] = fuse_end(float(line_at_key[i]), var_line, z_tip, var_tip)[0]
        ds, dz = s[lo:hi] - s_end, z[lo:hi] - out[i]
        ok = np.isfinite(dz)
        sxx = float(ds[ok] @ ds[ok])
        if sxx > 0:
            out_slope[i] = float(ds[ok] @ dz[ok]) / sxx
    return out, out_slope


def _line_variance(s: np.ndarray, z: np.ndarray, s_at: float) -> float:
    """Variance of a least-squares line z = a + b s through the finite (s, z), evaluated at
    ``s_at``, from its residuals (inf with fewer than 3 points: no residual to judge by)."""
    ok = np.isfinite(z)
    s, z = s[ok], z[ok]
    n = len(s)
    if n < 3:
        return float("inf")
    sc = s - s.mean()
    sxx = float(sc @ sc)
    if sxx <= 0:
        return float("inf")
    b = float(sc @ (z - z.mean())) / sxx
    res = z - z.mean() - b * sc
    sigma2 = float(res @ res) / (n - 2)
    return sigma2 * (1.0 / n + (s_at - s.mean()) ** 2 / sxx)


def _fit_depths(
    H: np.ndarray, is_key: np.ndarray, s: np.ndarray, key_idx: np.ndarray, fB: float
) -> np.ndarray:
    """(P,) depths of H for the window lines of Eq. (7): an extra point whose disparity lies
    more than ``OUTLIER_PX`` from the keypoints' disparity interpolated at it is another
    match (as in the ordering's clusters) and is left out (NaN). A run of gap pixels matched
    to another strand or to nothing (disparity 2 px instead of 42 px) otherwise dominates the
    least-squares line: bounds of +-750 mm and an end value of Eq. (8) 500 mm off."""
    z = H[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(z > 0, fB / z, np.nan)
        d_key = np.interp(s, s[key_idx], d[key_idx])
        other = ~is_key & ~(np.abs(d - d_key) <= OUTLIER_PX)
    return np.where(other, np.nan, z)


def _off_by_ratio(
    H: np.ndarray, is_key: np.ndarray, s: np.ndarray, key_idx: np.ndarray, ratio: float
) -> np.ndarray:
    """(P,) depths of H for the window lines of Eq. (7): an extra point deeper than ``ratio``
    times the keypoints' depth interpolated at it (in disparity, along s), or nearer than
    1 / ``ratio`` of it, is left out (NaN); ``ratio`` 0: none. Unlike :func:`_fit_depths`'
    fixed 2 px, a ratio keeps extra points that lie off the keypoints along a long link (their
    depth is the only one there: the development split's blend6_4 has links of 160 px whose
    extra points lie 15 px of disparity off the keypoints' line, and right), and leaves out
    a gap matched to nothing or to another strand (910 mm among 110 mm on generated crossing
    8114 #4: a window line metres off, bounds of +-200 mm, a curve 135 mm too long)."""
    z = H[:, 2]
    if ratio <= 0:
        return z
    if ratio < 1:
        raise ValueError(f"depth_ratio must be 0 (off) or >= 1, got {ratio}")
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(z > 0, 1.0 / z, np.nan)  # disparity / (f B)
        z_key = 1.0 / np.interp(s, s[key_idx], d[key_idx])
        off = ~is_key & np.isfinite(z_key) & ~((z <= ratio * z_key) & (z * ratio >= z_key))
    return np.where(off, np.nan, z)


def _window_line_fits(
    s: np.ndarray, z: np.ndarray, key_idx: np.ndarray, r_k: int
) -> tuple[np.ndarray, np.ndarray]:
    """For every keypoint i: the least-squares line z = a + b s through the finite points of H
    between keypoints i - r_k and i + r_k, evaluated at k_i, and its slope b. All windows at
    once from prefix sums of 1, s, z, s^2, s z (s centred at each window's keypoint, so that
    the sums do not cancel). A window with fewer than 2 distinct s gives its mean depth and
    slope 0; one with no finite depth gives k_i's own depth."""
    M = len(key_idx)
    i = np.arange(M)
    lo = key_idx[np.maximum(0, i - r_k)]
    hi = key_idx[np.minimum(M - 1, i + r_k)] + 1  # window: H[lo:hi]
    ok = np.isfinite(z)
    z0 = np.where(ok, z, 0.0)
    w = ok.astype(np.float64)
    s_ref = s[key_idx]  # centre of each window's fit

    def window_sum(v: np.ndarray) -> np.ndarray:
        c = np.concatenate([[0.0], np.cumsum(v)])
        return c[hi] - c[lo]

    # Sums over the window of powers of (s - s_ref): expand from the raw prefix sums of s^p
    # with a global shift first (s - s_mid is small), then re-centre per window exactly.
    shift = 0.5 * (s[0] + s[-1])
    t = s - shift
    n = window_sum(w)
    S1, S2 = window_sum(w * t), window_sum(w * t * t)
    Z, SZ = window_sum(z0), window_sum(w * t * z0)
    c = s_ref - shift  # t of each window's reference point
    Sx = S1 - n * c  # sum (s - s_ref)
    Sxx = S2 - 2 * c * S1 + n * c * c  # sum (s - s_ref)^2
    Sxz = SZ - c * Z  # sum (s - s_ref) z
    with np.errstate(divide="ignore", invalid="ignore"):
        var = Sxx - Sx * Sx / n  # n * variance of s in the window
        b = (Sxz - Sx * Z / n) / var
        a = (Z - b * Sx) / n  # the line at s_ref
        mean = Z / n
    z_key = z[key_idx]
    degenerate = ~(var > 1e-12 * np.maximum(Sxx, 1e-300)) | (n < 2)
    line = np.where(degenerate, mean, a)
    slope = np.where(degenerate, 0.0, b)
    empty = n == 0
    line = np.where(empty, z_key, line)
    slope = np.where(empty, 0.0, slope)
    return line, slope


def _extra_points(
    stereo: StereoResult,
    ordering: Ordering,
    path: np.ndarray,
    extra_px: int,
    fB: float,
    second_matches: bool = True,
    dead_end_others: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """H: the ordered keypoints ``path`` with, after keypoint i, the extra points of link i
    (grouped operations over all links at once: one sort, no loop over links or keypoints).

    A gap pixel whose match would lie left of the right image (x < the disparity of its
    link's keypoints + ``BORDER_PX``: the thread leaves the right view there) has no stereo
    depth and gives none; a link left with no pixel at all (a jump across an occlusion) gets
    points on a smooth bridge between its keypoints (:func:`_bridge`)."""
    M = len(path)
    t_all, link_all = ordering.pixel_t, ordering.pixel_link
    sel = np.flatnonzero((link_all >= 0) & (link_all < M - 1) & (t_all > 0) & (t_all < 1))
    z_link = np.where(path[:, 2] > 0, path[:, 2], np.inf)
    z_link = np.minimum(z_link[:-1], z_link[1:])  # nearest keypoint of each link
    d_ref = np.where(np.isfinite(z_link), fB / z_link, 0.0)
    sel = sel[stereo.pixels[sel, 0] >= d_ref[link_all[sel]] + BORDER_PX]
    link, t = link_all[sel], t_all[sel]
    order = np.lexsort((t, link))  # by link, then by position along it (stable on ties)
    sel, link = sel[order], link[order]
    count = np.bincount(link, minlength=M - 1)
    n_extra = count // extra_px
    # Runs the same from either end of the link (issue 12: the walk may start at either end):
    # pixel j of c goes to run floor((j + 1/2) n / c), pixels of equal t at their mean j, and
    # a pixel exactly on a run boundary (the middle of an odd link in 2 runs) to none. One
    # compiled pass over the sorted pixels: their runs (global ids, in the order of H) and
    # the runs' centroids (some forty numpy calls before).
    kept, group, cx, cy = walk_kernel.extra_runs(
        link, np.ascontiguousarray(t[order], dtype=np.float64),
        np.asarray(stereo.pixels, dtype=np.int64), count, n_extra, sel, T_TIE,
    )  # fmt: skip
    sel, link = sel[kept], link[kept]
    n_runs = int(n_extra.sum())
    # Median stereo depth of each run's finite depths.
    depth = _dead_end_depths(stereo, ordering, path, sel, link, second_matches, dead_end_others)
    med, has = walk_kernel.run_medians(group, np.ascontiguousarray(depth, dtype=np.float64), n_runs)
    run_link = np.repeat(np.arange(M - 1), n_extra)
    extras = np.column_stack([cx, cy, med])[has]
    extra_link = run_link[has]
    empty = np.flatnonzero(count == 0)
    # Most empty links join neighbouring keypoints, closer than extra_px: no bridge point.
    # Only links whose chord (to 0.1 %, far beyond rounding) reaches extra_px go to _bridge,
    # which measures the chord exactly and may still give none.
    chord = np.hypot(*(path[empty + 1, :2] - path[empty, :2]).T)
    empty = empty[chord >= 0.999 * extra_px]
    bridges = [_bridge(path, int(i), extra_px) for i in empty]
    if bridges:
        extras = np.concatenate([extras, *bridges])
        extra_link = np.concatenate([extra_link, np.repeat(empty, [len(b) for b in bridges])])
    # Keypoint i, then the extra points of link i: sort keys (i, 0) and (link, 1).
    rows = np.concatenate([path, extras])
    key_pos = np.concatenate([np.arange(M), extra_link])
    is_key = np.concatenate([np.ones(M, bool), np.zeros(len(extras), bool)])
    o = np.lexsort((~is_key, key_pos))  # stable: extras keep their run order
    return rows[o], is_key[o]


def _dead_end_depths(
    stereo: StereoResult,
    ordering: Ordering,
    path: np.ndarray,
    sel: np.ndarray,
    link: np.ndarray,
    second: bool = True,
    others: bool = False,
) -> np.ndarray:
    """Stereo depths of the gap pixels ``sel`` (on links ``link``), where the pixels of a dead
    end (the link to an extension keypoint) are followed from the end keypoint (their only
    anchor) outwards, in the order of ``pixel_t``, by :func:`_follow` (one pass serves both):

    - ``second`` (deviation 30's second matches): a pixel whose first match breaks continuity
      with the strand followed so far and whose second match does not takes its second. A tip
      whose depth drifts smoothly keeps every first match. A thin free end beside other
      strands (the inner end of a coil) is matched to its neighbours at every other pixel
      (generated spiral 8141 #11: 27, 11 and 44 px where the truth is 44 px, the second match
      then 44 px): the median of a run of them put the end 60 mm off. The links between two
      keypoints then follow (:func:`_interior_depths`).
    - ``others`` (deviation 64): a pixel whose first match lies beyond the strand's continuity
      bound by more than ``OUTLIER_PX`` and whose second match does not lie within it is
      another match (an occluder's edge): NaN, no depth for its extra point."""
    depth = stereo.depth[sel]
    if not (second or others):
        return depth
    for li, anchor, on, d_a in _dead_ends(stereo, ordering, path, sel, link):
        px = sel[on]
        first, d_next = stereo.disparity[px], stereo.d_next[px]
        swaps = second
        if swaps:  # a pixel whose second match the anchor's strand could reach, or none swaps
            bound = disparity_room(np.hypot(*(stereo.pixels[px] - path[anchor, :2]).T))
            swaps = bool(
                ((np.abs(first - d_a) > bound + OUTLIER_PX) & (np.abs(d_next - d_a) <= bound)).any()
            )
        if not (swaps or others):
            continue
        out, xy = _outwards(stereo, ordering, path, px, li, anchor)
        state = _follow(d_a, first[out], d_next[out], xy)
        if swaps and (state == SWAP).any():
            moved = on[out[state == SWAP]]
            depth[moved] = depth_of(stereo, second_match_subpixel(stereo, sel[moved]), px)
        if others:
            depth[on[out[state == OTHER]]] = np.nan
    return _interior_depths(stereo, ordering, path, sel, link, depth) if second else depth


def _interior_depths(
    stereo: StereoResult,
    ordering: Ordering,
    path: np.ndarray,
    sel: np.ndarray,
    link: np.ndarray,
    depth: np.ndarray,
) -> np.ndarray:
    """:func:`_dead_end_depths` for the links between two keypoints: a link whose pixels hold
    another match (beyond the continuity bound of its nearer keypoint by more than
    ``OUTLIER_PX``, the second match within it) is followed from each keypoint towards the
    other (:func:`_track`), and a pixel takes its second match where both followers take it.
    A gap along a coil's turn beside the next turn, matched to it (generated spiral 8149 #8:
    the window line of the first keypoint, extrapolated over such extra points, put the curve's
    start 35 mm off)."""
    M = len(path)
    a, b = ordering.mono
    lo = a + 1 if ordering.order[a] < 0 else a
    hi = M - 2 - b if ordering.order[M - 1 - b] < 0 else M - 1 - b
    cand = np.flatnonzero((link >= lo) & (link < hi))
    if not len(cand):
        return depth
    px, li = sel[cand], link[cand]
    d_path = disparity_of(stereo, path[:, 2], px)
    near = np.where(ordering.pixel_t[px] < 0.5, li, li + 1)
    bound = disparity_room(np.hypot(*(stereo.pixels[px] - path[near, :2]).T))
    first, second = stereo.disparity[px], stereo.d_next[px]
    with np.errstate(invalid="ignore"):
        gate = (np.abs(first - d_path[near]) > bound + OUTLIER_PX) & (
            np.abs(second - d_path[near]) <= bound
        )
    for k in np.unique(li[gate]).tolist():
        on = cand[li == k]
        p = sel[on]
        t = ordering.pixel_t[p]
        both = np.ones(len(on), dtype=bool)
        for anchor, order in (
            (k, np.argsort(t, kind="stable")),
            (k + 1, np.argsort(-t, kind="stable")),
        ):
            if not np.isfinite(d_path[anchor]):
                both[:] = False
                break
            xy = np.concatenate([path[anchor : anchor + 1, :2], stereo.pixels[p[order]]])
            taken = np.zeros(len(on), dtype=bool)
            taken[order] = _track(
                float(d_path[anchor]), stereo.disparity[p[order]], stereo.d_next[p[order]], xy
            )
            both &= taken
        if both.any():
            moved = on[both]
            depth[moved] = depth_of(stereo, second_match_subpixel(stereo, sel[moved]), p)
    return depth


TRACK_REF = 5  # pixels whose median disparity is the followed strand's (two wrong outvoted)


def _dead_ends(
    stereo: StereoResult, ordering: Ordering, path: np.ndarray, sel: np.ndarray, link: np.ndarray
):
    """Each dead end of the path (the link to an extension keypoint) that holds gap pixels and
    whose end keypoint has a depth: (its link li, the end keypoint ``anchor``, the indices
    ``on`` of its pixels in ``sel``, the end keypoint's disparity d_a). Points placed from the
    left view alone (``ordering.mono``) lie before a dead end's tip."""
    M = len(path)
    a, b = ordering.mono
    ends = [(a, a + 1)] if ordering.order[a] < 0 else []
    ends += [(M - 2 - b, M - 2 - b)] if ordering.order[M - 1 - b] < 0 and M - b > 2 else []
    for li, anchor in ends:
        on = np.flatnonzero(link == li)
        z_a = path[anchor, 2]
        if len(on) and np.isfinite(z_a) and z_a > 0:
            yield li, anchor, on, float(disparity_of(stereo, z_a, sel[on]))


def _outwards(
    stereo: StereoResult, ordering: Ordering, path: np.ndarray, px: np.ndarray, li: int, anchor: int
) -> tuple[np.ndarray, np.ndarray]:
    """The order of a dead end's pixels ``px`` (on link li) from its end keypoint ``anchor``
    outwards, and the positions to follow: the anchor's, then the pixels' in that order.
    ``pixel_t`` is 0 at keypoint li and 1 at li + 1, so a start's anchor (li + 1) reads it
    backwards and an end's (li) forwards."""
    t = ordering.pixel_t[px]
    out = np.argsort(-t if anchor == li + 1 else t, kind="stable")
    return out, np.concatenate([path[anchor : anchor + 1, :2], stereo.pixels[px[out]]])


def _track(d_a: float, first: np.ndarray, second: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(n,) bool over a gap's pixels (in order outwards from its anchor, disparity ``d_a``;
    ``xy``: (n + 1, 2), the anchor first): which take their second match. The strand's
    disparity is the median of the last ``TRACK_REF`` pixels taken (the anchor's at first); a
    pixel keeps its first match when it lies within the continuity bound of it (over the
    distance from the last pixel taken), else takes its second when that does and the first
    is another match (beyond the bound by more than ``OUTLIER_PX``, the ordering's rule: a tip
    that bends in depth keeps its own); otherwise it keeps its first, and the strand's
    disparity does not move (:func:`_follow`)."""
    return _follow(d_a, first, second, xy) == SWAP


FIRST, SWAP, KEPT, OTHER = 0, 1, 2, 3  # what _follow says a gap pixel does


def _follow(d_a: float, first: np.ndarray, second: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(n,) uint8 over a gap's pixels, :func:`_track`'s pass: FIRST (its first match taken),
    SWAP (its second taken), KEPT (its first kept, not taken: beyond the bound by at most
    ``OUTLIER_PX``) or OTHER (kept, not taken, beyond the bound by more: another match).
    Compiled (:func:`walk_kernel.track_strand`: a loop over the gap's pixels, thousands on a
    long link)."""
    return walk_kernel.track_strand(
        float(d_a),
        np.ascontiguousarray(first, dtype=np.float64),
        np.ascontiguousarray(second, dtype=np.float64),
        np.ascontiguousarray(xy, dtype=np.float64),
        DISPARITY_SLACK_PX,
        DISPARITY_SLOPE,
        OUTLIER_PX,
        TRACK_REF,
    )


def _border_depths(path: np.ndarray, fB: float) -> np.ndarray:
    """Keypoints whose match would lie left of the right image take the depth of the nearest
    keypoint along the path that lies safely inside it (the mean of the two when one before
    and one after are equally near: the same from either end; x >= 2 d + ``BORDER_PX``, and x >= the
    median disparity of such keypoints + ``BORDER_PX``): the search was cut at the border
    there, and its depth is meaningless (metres on generated frames). The second test catches
    a keypoint whose cut search found a tiny disparity (x = 3 px, d = 0.002 px: 2.9 km deep)."""
    x, z = path[:, 0], path[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(z > 0, fB / z, np.inf)
    first = x >= 2 * d + BORDER_PX
    d_ref = float(np.median(d[first])) if first.any() else 0.0
    safe = np.flatnonzero(first & (x >= d_ref + BORDER_PX))
    if safe.size == 0 or safe.size == len(path):
        return path
    i = np.arange(len(path))
    pos = np.clip(np.searchsorted(safe, i), 1, safe.size) - 1
    nxt = np.minimum(pos + 1, safe.size - 1)
    after, before = np.abs(safe[nxt] - i), np.abs(safe[pos] - i)
    near = np.where(after < before, safe[nxt], safe[pos])
    other = np.where(after == before, safe[nxt], near)  # equally near both: their mean
    bad = x < 0.5 * (d[near] + d[other]) + BORDER_PX
    if not bad.any():
        return path
    out = path.copy()
    out[bad, 2] = 0.5 * (z[near[bad]] + z[other[bad]])
    return out


def _bridge(path: np.ndarray, i: int, extra_px: int) -> np.ndarray:
    """Points every ``extra_px`` px on the cubic Hermite curve from keypoint i to i + 1 with the
    path's directions at both ends (a jump across an occlusion: no pixel lies between them),
    depth linear between the two keypoints. (n, 3), n = 0 for a short link."""
    p0, p1 = path[i, :2], path[i + 1, :2]
    chord = float(np.linalg.norm(p1 - p0))
    n = int(chord // extra_px)
    if n < 1:
        return np.zeros((0, 3))
    t0 = p0 - path[max(i - 1, 0), :2]
    t1 = path[min(i + 2, len(path) - 1), :2] - p1
    t0 = chord * t0 / max(float(np.linalg.norm(t0)), 1e-9)
    t1 = chord * t1 / max(float(np.linalg.norm(t1)), 1e-9)
    s = np.arange(1, n + 1)[:, None] / (n + 1)
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    xy = h00 * p0 + h10 * t0 + h01 * p1 + h11 * t1
    z = path[i, 2] + s[:, 0] * (path[i + 1, 2] - path[i, 2])
    return np.column_stack([xy, z])
