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

from core.calibration import StereoCalibration
from core.ordering import Ordering
from core.stereo import StereoResult

BORDER_PX = 2.0  # a left pixel within this of where its match leaves the right image: no depth


@dataclass(frozen=True)
class BoundsParams:
    extra_px: int = 24
    """Gap size (segmented px) per extra point; gaps larger than this get extra points."""
    r_k_frac: float = 0.1
    """r_k = r_k_frac * |K| (paper: |K| / 10), at least ``r_k_min``."""
    r_k_min: int = 2
    """Smallest r_k, keypoints."""
    bound_scale: float = 1.5
    """Scale of |L(k) - k_z| in Eq. (7)."""
    widen_px: float = 0.25
    """Smallest bound half-width, px of disparity."""


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
    H, is_key = _extra_points(stereo, ordering, path, p.extra_px, fB)
    seg = np.linalg.norm(np.diff(H[:, :2], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    key_idx = np.flatnonzero(is_key)
    z_key = H[key_idx, 2]

    n_kp = int(np.sum(ordering.order >= 0))
    r_k = max(p.r_k_min, int(round(p.r_k_frac * n_kp)))
    line_at_key = np.empty(M)
    slopes = np.empty(M)
    for i in range(M):
        lo, hi = key_idx[max(0, i - r_k)], key_idx[min(M - 1, i + r_k)]
        ss, zz = s[lo : hi + 1], H[lo : hi + 1, 2]
        ok = np.isfinite(zz)
        a, b = _line_fit(ss[ok], zz[ok], fallback=z_key[i])
        line_at_key[i] = a + b * s[key_idx[i]]
        slopes[i] = b
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
    )


def _line_fit(s: np.ndarray, z: np.ndarray, fallback: float) -> tuple[float, float]:
    """Least-squares z = a + b s; a constant when fewer than 2 distinct s."""
    if s.size == 0:
        return fallback, 0.0
    if s.size < 2 or np.ptp(s) <= 0:
        return float(np.mean(z)), 0.0
    b, a = np.polyfit(s, z, 1)
    return float(a), float(b)


def _border_depths(path: np.ndarray, fB: float) -> np.ndarray:
    """Keypoints whose match would lie left of the right image take the depth of the nearest
    keypoint along the path that lies safely inside it (x >= 2 d + ``BORDER_PX``): the search
    was cut at the border there, and its depth is meaningless (metres on generated frames)."""
    x, z = path[:, 0], path[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(z > 0, fB / z, np.inf)
    safe = np.flatnonzero(x >= 2 * d + BORDER_PX)
    if safe.size == 0 or safe.size == len(path):
        return path
    i = np.arange(len(path))
    pos = np.clip(np.searchsorted(safe, i), 1, safe.size) - 1
    nxt = np.minimum(pos + 1, safe.size - 1)
    near = np.where(np.abs(safe[nxt] - i) < np.abs(safe[pos] - i), safe[nxt], safe[pos])
    bad = x < d[near] + BORDER_PX
    if not bad.any():
        return path
    out = path.copy()
    out[bad, 2] = z[near[bad]]
    return out


def _extra_points(
    stereo: StereoResult, ordering: Ordering, path: np.ndarray, extra_px: int, fB: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points of H between keypoints. A gap pixel whose match would lie left of the right
    image (x < the disparity of its link's keypoints + ``BORDER_PX``: the thread leaves the
    right view there) has no stereo depth and gives none."""
    rows: list[np.ndarray] = [path[:1]]
    keys: list[bool] = [True]
    for i in range(len(path) - 1):
        sel = np.flatnonzero((ordering.pixel_link == i) & np.isfinite(ordering.pixel_t))
        sel = sel[(ordering.pixel_t[sel] > 0) & (ordering.pixel_t[sel] < 1)]
        z_ends = path[i : i + 2, 2]
        d_ref = fB / np.min(z_ends[z_ends > 0]) if np.any(z_ends > 0) else 0.0
        sel = sel[stereo.pixels[sel, 0] >= d_ref + BORDER_PX]
        n_extra = sel.size // extra_px
        if n_extra > 0:
            xy = stereo.pixels[sel].astype(np.float64)
            depth = stereo.depth[sel]
            for run in np.array_split(np.argsort(ordering.pixel_t[sel], kind="stable"), n_extra):
                d = depth[run]
                d = d[np.isfinite(d)]
                if d.size:
                    rows.append(np.array([[*xy[run].mean(axis=0), np.median(d)]]))
                    keys.append(False)
        elif sel.size == 0:
            fill = _bridge(path, i, extra_px)
            rows.extend(fill[j : j + 1] for j in range(len(fill)))
            keys.extend([False] * len(fill))
        rows.append(path[i + 1 : i + 2])
        keys.append(True)
    return np.concatenate(rows), np.array(keys)


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
