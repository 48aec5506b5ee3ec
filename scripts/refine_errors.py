"""Why the two-view refinement wins or loses: its observations against the generator's truth.

    python scripts/refine_errors.py --seed 7821 --count 10 [--suite plain ...]
        [--config PRESET] [--set stage.name=value ...]

Per generated frame (exact masks given; frame k of a suite is ``default_rng([seed, k])``, the
frames of ``scripts/hard_suites.py``), the refine stage's observations are compared with the
truth's projection. On every image row the true centreline crosses in the left view (the
rectified pair: the same 3D point lies on the same row in both views) the crossing gives the
true column x_L, x_R and the true disparity d = x_L - x_R. Reported, over those crossings
(RMS and mean, px):

- ``cL``, ``cR``: the row-run centre of each view (:class:`core.refine._Runs`) minus the true
  column, for the run nearest the crossing (within its half-length + 1 px);
- ``t``: the run-centre disparity cL - cR minus d (what ``two_view`` fits);
- ``mvs``, ``ref``: the disparity of the MVS curve (stage ``spline``) and of the refined curve
  (stage ``refine``, mode two_view) at the curve's point nearest the crossing in the left
  image, minus d: what the refinement started from and where it went;
- and e_S (mm) of both curves against the truth.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT.parent), str(ROOT / "scripts")]

from hard_suites import SUITES, _params  # noqa: E402

from threadrecon.core.metrics import curve_errors  # noqa: E402
from threadrecon.core.pipeline import Pipeline  # noqa: E402
from threadrecon.core.refine import _Runs  # noqa: E402
from threadrecon.core.segmentation import StereoPair  # noqa: E402
from threadrecon.core.synthetic import SyntheticParams, generate_frame  # noqa: E402


def true_crossings(ctrl: np.ndarray, cam) -> np.ndarray:
    """(M, 4) rows y, x_L, x_R, d where the true centreline crosses an integer image row."""
    from scipy.interpolate import BSpline

    n = len(ctrl)
    t = np.concatenate([np.zeros(3), np.linspace(0, 1, n - 2), np.ones(3)])
    p = BSpline(t, ctrl, 3)(np.linspace(0, 1, 20000))
    uvL, uvR = cam.project(p)
    y = uvL[:, 1]
    out = []
    for i in np.flatnonzero(np.floor(y[1:]) != np.floor(y[:-1])):
        r = np.floor(max(y[i], y[i + 1]))
        a = (r - y[i]) / (y[i + 1] - y[i])
        xl = uvL[i, 0] + a * (uvL[i + 1, 0] - uvL[i, 0])
        xr = uvR[i, 0] + a * (uvR[i + 1, 0] - uvR[i, 0])
        out.append((r, xl, xr, xl - xr))
    return np.array(out).reshape(-1, 4)


def curve_disparity(spline, fB: float, n: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    c = spline.curve(n)
    return c[:, :2], fB / c[:, 2]


def frame_stats(frame, params) -> dict:
    pair = StereoPair(frame.left, frame.right, frame.mask_left, frame.mask_right)
    calib = frame.camera.calibration()
    fB = calib.focal * calib.baseline
    pipe = Pipeline(pair, calib)
    rec_off = pipe.run(replace(params, refine=replace(params.refine, mode="off")))
    rec_on = pipe.run(replace(params, refine=replace(params.refine, mode="two_view")))
    if rec_off.failed_stage or rec_on.failed_stage:
        return {}
    lifted = rec_on["segment"]
    cr = true_crossings(frame.truth.control_points, frame.camera)
    rows = cr[:, 0].astype(np.int64)
    out = {}
    runs = {}
    for side, mask, grey, bg, col in (
        ("cL", lifted.P_L, lifted.grey_L, lifted.background[0], 1),
        ("cR", lifted.P_R, lifted.grey_R, lifted.background[1], 2),
    ):
        r = _Runs(mask, grey, bg)
        c, ln = r.nearest(rows, cr[:, col])
        ok = np.isfinite(c) & (np.abs(c - cr[:, col]) <= 0.5 * ln + 1.0)
        runs[side] = (c, ln, ok)
    (cL, lL, okL), (cR, lR, okR) = runs["cL"], runs["cR"]
    both = okL & okR
    # only rows with one run nearby in each view, and short runs (steep thread): clean cases
    out["n"] = int(both.sum())
    out["cL"] = cL[both] - cr[both, 1]
    out["cR"] = cR[both] - cr[both, 2]
    out["t"] = (cL[both] - cR[both]) - cr[both, 3]
    out["len"] = np.maximum(lL[both], lR[both])
    for key, rec in (("mvs", rec_off), ("ref", rec_on)):
        s = rec["refine"]
        xy, d = curve_disparity(s, fB)
        dist, j = cKDTree(xy).query(cr[:, [1, 0]])  # (x_L, y) of the crossings
        near = dist <= 1.5
        out[key] = np.where(near, d[j] - cr[:, 3], np.nan)[both]
        out["e_" + key] = curve_errors(rec["camera"].points, frame.truth.centerline).e_S
    out["d"] = cr[both, 3]
    return out


def rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--count", type=int, default=10)
    ap.add_argument("--suite", action="append", default=None, choices=sorted(SUITES))
    ap.add_argument("--config", default=None)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--frames", action="store_true", help="one line per frame")
    args = ap.parse_args()
    params = _params(args.config, args.set)
    head = "suite             n    cL rms/mean   cR rms/mean    t rms/mean  mvs rms/mean"
    print(head + "  ref rms/mean   e_S off / two_view")
    for name in args.suite or ["plain"]:
        _, thread, render = SUITES[name]
        syn = SyntheticParams(thread=thread, render=render)
        acc: dict[str, list] = {}
        for k in range(1, args.count + 1):
            frame = generate_frame(syn, np.random.default_rng([args.seed, k]))
            st = frame_stats(frame, params)
            if not st:
                continue
            for key, v in st.items():
                acc.setdefault(key, []).append(v)
            if args.frames:
                print(
                    f"  #{k:2d} n {st['n']:4d}  cL {rms(st['cL']):.3f} cR {rms(st['cR']):.3f} "
                    f"t {rms(st['t']):.3f} {np.nanmean(st['t']):+.3f}  mvs {rms(st['mvs']):.3f} "
                    f"ref {rms(st['ref']):.3f} {np.nanmean(st['ref']):+.3f}  "
                    f"e_S {st['e_mvs']:.3f} / {st['e_ref']:.3f}"
                )
        cat = {k: np.concatenate(v) for k, v in acc.items() if k not in ("n", "e_mvs", "e_ref")}
        cols = "".join(
            f"  {rms(cat[k]):5.3f}/{np.nanmean(cat[k]):+6.3f}"
            for k in ("cL", "cR", "t", "mvs", "ref")
        )
        print(
            f"{name:15s} {sum(acc['n']):5d}{cols}   {np.median(acc['e_mvs']):.3f} / "
            f"{np.median(acc['e_ref']):.3f} (median)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
