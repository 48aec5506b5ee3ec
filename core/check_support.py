"""The check's look at the reliable matches right next to the curve: depth they contradict.

A curve point is *contradicted* when reliable pixels of P_L^R lie within ``near_px`` of its
left projection and none of them agrees with the curve's disparity within ``tol_px``: the
images measure another depth there (a wrong branch at a crossing runs at one strand's depth
over the other strand's pixels, or between them). The reliable pixels' disparities are kept as
a sparse image over their bounding box, built once per stereo result (``check_field.derived``);
each curve point reads the (2 near_px + 1)^2 window around it.
"""

from __future__ import annotations

import numpy as np

from threadrecon.core.check_field import derived
from threadrecon.core.check_kernel import window_contradicted
from threadrecon.core.reliability import ReliabilityResult
from threadrecon.core.stereo import StereoResult


def contradicted(
    stereo: StereoResult,
    rel: ReliabilityResult,
    uv_l: np.ndarray,
    disp_curve: np.ndarray,
    near_px: int,
    tol_px: float,
) -> np.ndarray:
    """(N,) bool: reliable pixels lie within ``near_px`` (a square window) of the curve point
    ``uv_l`` (N, 2) (x, y) left px, and none has a disparity within ``tol_px`` of
    ``disp_curve`` (N,) px."""
    uv_l = np.asarray(uv_l, dtype=np.float64)
    if uv_l.ndim != 2 or uv_l.shape[1] != 2 or len(disp_curve) != len(uv_l):
        raise ValueError(f"uv_l must be (N, 2) with N disparities, got {uv_l.shape}")
    x0, y0, img = derived(
        (stereo.pixels, stereo.disparity, rel.reliable), "reliable_image",
        lambda: _image(stereo, rel),
    )  # fmt: skip
    n = len(uv_l)
    if img.size == 0 or n == 0:
        return np.zeros(n, dtype=bool)
    ok = np.all(np.isfinite(uv_l), axis=1) & np.isfinite(disp_curve)
    q = np.rint(np.where(ok[:, None], uv_l, -1e6)).astype(np.int64) - [x0, y0]
    disp = np.ascontiguousarray(disp_curve, dtype=np.float64)
    # compiled: the window of each point read in place (numpy built (N, K, K) index arrays)
    return window_contradicted(q, ok, disp, img, int(near_px), float(tol_px))


def _image(stereo: StereoResult, rel: ReliabilityResult) -> tuple[int, int, np.ndarray]:
    """The reliable pixels' disparities on their bounding box (NaN elsewhere): x0, y0, image."""
    sel = np.flatnonzero(rel.reliable)
    if sel.size == 0:
        return 0, 0, np.zeros((0, 0))
    xy = np.asarray(stereo.pixels)[sel].astype(np.int64)
    x0, y0 = int(xy[:, 0].min()), int(xy[:, 1].min())
    # float32: a 1920x1080 thread's box is ~10 MB in float64, kept for a few frames; the
    # disparities are compared at tol_px (~1 px), far above float32's 1e-5 px at 200 px
    shape = (int(xy[:, 1].max()) - y0 + 1, int(xy[:, 0].max()) - x0 + 1)
    img = np.full(shape, np.nan, dtype=np.float32)
    img[xy[:, 1] - y0, xy[:, 0] - x0] = np.asarray(stereo.disparity, dtype=np.float32)[sel]
    img.setflags(write=False)
    return x0, y0, img
