"""Figures of the check stage (issue 11) on dataset folders with 3D ground truth.

    python scripts/check_figures.py DATASET [DATASET ...] [--csv rows.csv] [--params preset]

For every frame: the check's status against the truth ("wrong": |length error| > 20 mm or
max curve error > 20 mm), the rank correlation of per-point confidence with the true 3D error
of each point, the grasp point's true error, the score against e_S (its integer class and the
continuous rating, the score the product reports), and the check's time.
Frames without ground truth (real) only count towards the status table. Each flagged frame's
reasons are tallied by kind, on wrong and on right frames. Errors are ``metrics.frame_errors``
(the one metric of ``evaluate``: a thread leaving the view is judged on the part both views
see). The check's CPU time is given on a new segmentation (its distance fields computed, as
for every new frame) and with the segmentation cached (a slider move of a later stage).

The suites of issue 11's figures (seed S, 6 frames per group; add --no-mask for raw frames):

    G="python -m threadrecon.app.cli generate DIR --count 6"
    T="--background tissue --noise 2 --blur 0.5"
    $G --seed S --group flat
    $G --seed S+1 $T --group tissue;          $G --seed S+2 $T --crossing --group crossing
    $G --seed S+3 $T --occlusion --group occlusion
    $G --seed S+4 $T --leaves-image --group leaving
    $G --seed S+5 $T --hairpin --group hairpin; $G --seed S+6 $T --instrument --group instrument
    $G --seed S+7 --crossing --group crossing-flat; $G --seed S+8 $T --distractors 6 --group distractors
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from threadrecon.app.dataset import discover, load_frame  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402
from threadrecon.core.check import check_curve  # noqa: E402
from threadrecon.core.check_field import clear_fields  # noqa: E402
from threadrecon.core.metrics import frame_errors, resample, visible_part  # noqa: E402
from threadrecon.core.pipeline import Pipeline  # noqa: E402

WRONG_MM = 20.0  # the "wrong": length or max curve error above 2 cm


def frame_rows(root: str, params, point_sets: list) -> list[dict]:
    rows = []
    for frame in discover(root):
        row: dict = {"dataset": root, "frame": frame.id, "kind": frame.kind}
        try:
            pair, calib, gt = load_frame(frame)
            rec = Pipeline(pair, calib).run(params)
        except Exception as exc:  # noqa: BLE001 - a frame that cannot load is reported
            row.update(status="failed", reasons=f"load: {exc}", wrong=True, has_curve=False)
            rows.append(row)
            continue
        row.update(status=rec.status, reasons=rec.message or "")
        row["has_curve"] = "check" in rec.runs
        if "check" in rec.runs:
            chk = rec["check"]
            row.update(
                score=chk.score,
                rating=chk.rating,
                ms_check=rec.runs["check"].ms,
                **_flat(chk.evidence()),
            )
            row["cpu_ms_check"], row["cpu_ms_check_cached"] = _cpu_ms(rec, calib, params)
            e_mm = np.minimum(chk.expected_error_mm, 1e6)
            row.update(exp_mean=float(e_mm.mean()), exp_p90=float(np.percentile(e_mm, 90)))
            row["exp_max"] = float(e_mm.max())
        if gt is None:
            row["wrong"] = math.nan
            rows.append(row)
            continue
        if not row["has_curve"] or not np.all(np.isfinite(rec["camera"].points)):
            row.update(wrong=True, e_S=math.inf, e_S_max=math.inf, e_length=math.inf)
            rows.append(row)
            continue
        mm = calib.mm_per_unit
        pts = rec["camera"].points * mm
        e = frame_errors(rec["camera"].points, gt, calib)  # on the part both views see
        row.update(e_S=e.e_S, e_S_max=e.e_S_max, e_length=e.e_length)
        row["wrong"] = bool(e.e_length > WRONG_MM or e.e_S_max > WRONG_MM)
        seen = visible_part(gt, calib.P1, calib.P2, calib.image_size) * mm
        tree = cKDTree(resample(seen, 20000))
        err_pts = tree.query(pts)[0]
        chk = rec["check"]
        point_sets.append((frame.id, chk.confidence, err_pts, root))
        if chk.grasp is not None:
            row["grasp_error_mm"] = float(tree.query(chk.grasp.point * mm)[0])
            row["grasp_conf"] = chk.grasp.confidence
        rho = spearmanr(chk.confidence, err_pts)[0]
        row["conf_rho"] = float(rho) if np.isfinite(rho) else math.nan
        rows.append(row)
    return rows


def _cpu_ms(rec, calib, params) -> tuple[float, float]:
    """CPU time of the check stage (best of 3), ms: on a new segmentation (its distance
    fields computed, as for every new frame) and again on the same one (fields cached, as
    after a slider move of a later stage). Wall time is meaningless on a loaded machine."""
    args = [rec[s] for s in ("segment", "stereo", "reliability", "ordering", "bounds")]
    best = [math.inf, math.inf]
    for _ in range(3):
        for k in (0, 1):
            if k == 0:
                clear_fields()
            t0 = time.thread_time()
            check_curve(*args, rec["refine"], rec["camera"], calib, params.check)
            best[k] = min(best[k], time.thread_time() - t0)
    return 1000.0 * best[0], 1000.0 * best[1]


def _flat(ev: dict) -> dict:
    out = {}
    for k, v in ev.items():
        if isinstance(v, list) and len(v) == 2 and all(isinstance(x, float) for x in v):
            out[f"{k}_lo"], out[f"{k}_hi"] = v
        elif isinstance(v, list):
            out[k] = " ".join(map(str, v))
        else:
            out[k] = v
    return out


REASON_KINDS = {  # a keyword of each kind of reason (core/check.py) -> a short name
    "not finite": "non-finite",
    "behind a": "behind camera",
    "disparity search allows": "depth range",
    "projection lies": "reprojection",
    "the curve lies outside the": "off image",
    "depth is not observed": "one view",
    "covers": "coverage",
    "image border": "border",
    "is implausible": "length",
    "solver": "solver",
    "run over another": "overlap",
    "off the thread pixels": "overshoot",
    "bridges": "bridge",
    "bare background in both views": "bridge over background",
    "a loop, not a continuation": "bridge loop",
    "deg at its": "bridge turn",
    "depth travels": "unsupported depth",
    "order or depth may be mixed": "crossing ambiguity",
    "give another depth": "contradicted depth",
    "depth bounds by": "bounds",
    "stops short": "piece beyond an end",
    "cut by an occluder": "cut end",
    "runs twice over": "fold",
    "last knot span": "end depth change",
    "runs into an occluder": "occluded end",
    "turns back by": "turn back",
}


def _reason_kinds(reasons: str) -> list[str]:
    kinds = [k for key, k in REASON_KINDS.items() if key in reasons]
    return kinds or ["other"]


def report(rows: list[dict], point_sets: list, label: str) -> None:
    gt_rows = [r for r in rows if r.get("wrong") in (True, False)]
    n = len(rows)
    by = {s: sum(r["status"] == s for r in rows) for s in ("ok", "suspect", "failed")}
    ok_wrong = [r for r in gt_rows if r["status"] == "ok" and r["wrong"]]
    flagged = [r for r in gt_rows if r["status"] != "ok"]
    flagged_wrong = [r for r in flagged if r["wrong"]]
    wrong = [r for r in gt_rows if r["wrong"]]
    print(f"== {label}: {n} frames ({len(gt_rows)} with ground truth)")
    print(f"  status: ok {by['ok']}, suspect {by['suspect']}, failed {by['failed']}")
    print(f"  wrong (|e_l| or e_S_max > {WRONG_MM:g} mm): {len(wrong)}")
    print(f"  ok and wrong: {len(ok_wrong)}  {[r['frame'] for r in ok_wrong]}")
    prec = len(flagged_wrong) / len(flagged) if flagged else math.nan
    print(
        f"  flagged (suspect/failed) with ground truth: {len(flagged)}, really wrong "
        f"{len(flagged_wrong)} ({100 * prec:.0f} %)"
    )
    tally = {}
    for r in flagged:
        for kind in _reason_kinds(r["reasons"]):
            right_wrong = tally.setdefault(kind, [0, 0])
            right_wrong[bool(r["wrong"])] += 1
    for kind, (right, wrong_n) in sorted(tally.items(), key=lambda kv: -sum(kv[1])):
        print(f"    reason {kind!r}: on {wrong_n} wrong and {right} right frames")
    for r in flagged:
        if not r["wrong"]:
            print(
                f"    flagged but right: {r['frame']} e_l {r.get('e_length', math.nan):.1f} "
                f"e_S_max {r.get('e_S_max', math.nan):.1f}: {r['reasons']}"
            )
    sets = [s for s in point_sets if s[3] in {r["dataset"] for r in rows}]
    if sets:
        conf = np.concatenate([s[1] for s in sets])
        err = np.concatenate([s[2] for s in sets])
        ok_ids = {r["frame"] for r in gt_rows if r["status"] == "ok"}
        ok_sets = [s for s in sets if s[0] in ok_ids]
        per = [r["conf_rho"] for r in gt_rows if np.isfinite(r.get("conf_rho", math.nan))]
        print(
            f"  confidence vs point error, Spearman: pooled {spearmanr(conf, err)[0]:.3f}, "
            f"median per frame {np.median(per):.3f}"
        )
        if ok_sets:
            c2 = np.concatenate([s[1] for s in ok_sets])
            e2 = np.concatenate([s[2] for s in ok_sets])
            print(f"    pooled over ok frames only: {spearmanr(c2, e2)[0]:.3f}")
    g = np.array([r["grasp_error_mm"] for r in gt_rows if "grasp_error_mm" in r])
    g_ok = np.array(
        [r["grasp_error_mm"] for r in gt_rows if "grasp_error_mm" in r and r["status"] == "ok"]
    )
    if g.size:
        print(
            f"  grasp point true error mm: median {np.median(g):.2f} (all), "
            f"{np.median(g_ok) if g_ok.size else math.nan:.2f} (ok frames), p90 "
            f"{np.percentile(g, 90):.2f}"
        )
    sc = [(r["score"], r["rating"], r["e_S"]) for r in gt_rows if "score" in r]
    if len(sc) > 2:
        s, x, e = np.array(sc, dtype=float).T
        e = np.where(np.isfinite(e), e, 1e9)
        hist = np.bincount(s.astype(int), minlength=6)[1:].tolist()
        print(
            f"  score vs e_S, Spearman: {spearmanr(s, e)[0]:.3f} (negative = agrees; integer classes "
            f"1-5: {hist}); continuous rating (the score reported): {spearmanr(x, e)[0]:.3f}"
        )
    _per_suite(gt_rows, sets)
    ms = [r["ms_check"] for r in rows if "ms_check" in r]
    cpu = [r["cpu_ms_check"] for r in rows if "cpu_ms_check" in r]
    cached = [r["cpu_ms_check_cached"] for r in rows if "cpu_ms_check_cached" in r]
    if ms:
        print(
            f"  check stage: CPU ms median {np.median(cpu):.2f}, p90 {np.percentile(cpu, 90):.2f}, "
            f"max {np.max(cpu):.2f} (new segmentation); median {np.median(cached):.2f} "
            f"(segmentation cached); wall ms median {np.median(ms):.2f}"
        )


def _suite(frame_id: str) -> str:
    """The generator group of a frame id ("simulated/flat/flat_3" -> "flat")."""
    parts = frame_id.split("/")
    return parts[-2] if len(parts) >= 2 else parts[0]


def _per_suite(gt_rows: list[dict], sets: list) -> None:
    """Issue 11's Spearman figures per generator group (8-odd frames each): pooled confidence
    vs point error, score and rating vs e_S. The pooled figures above mix the groups; a group
    whose frames are all right spans a narrow e_S range and ranks by differences of hundredths
    of a mm, so its figure says how finely the score ranks, not whether it tells good from bad."""
    groups: dict[str, list[dict]] = {}
    for r in gt_rows:
        groups.setdefault(_suite(r["frame"]), []).append(r)
    if len(groups) < 2:
        return
    print("  per suite: confidence / score / rating Spearman (score, rating: positive = agrees)")
    for name, rs in sorted(groups.items()):
        ids = {(r["dataset"], r["frame"]) for r in rs}
        pts = [s for s in sets if (s[3], s[0]) in ids]
        conf = (
            spearmanr(np.concatenate([s[1] for s in pts]), np.concatenate([s[2] for s in pts]))[0]
            if pts
            else math.nan
        )
        sc = np.array([(r["score"], r["rating"], r["e_S"]) for r in rs if "score" in r], float)
        sr = ra = math.nan
        if len(sc) > 2:
            e = np.where(np.isfinite(sc[:, 2]), sc[:, 2], 1e9)
            with warnings.catch_warnings():  # one score for all frames: no rank correlation
                warnings.simplefilter("ignore")
                sr, ra = -spearmanr(sc[:, 0], e)[0], -spearmanr(sc[:, 1], e)[0]
        print(f"    {name:16s} {len(rs):3d} frames  {conf:6.3f} / {sr:6.3f} / {ra:6.3f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--config", default=None, help="preset name or path")
    ap.add_argument("--csv", default=None, help="write one row per frame")
    args = ap.parse_args()
    params = resolve_preset(args.config)
    all_rows: list[dict] = []
    point_sets: list = []
    for root in args.datasets:
        rows = frame_rows(root, params, point_sets)
        report(rows, point_sets, root)
        all_rows += rows
    if len(args.datasets) > 1:
        report(all_rows, point_sets, "all")
    if args.csv:
        keys: list[str] = []
        for r in all_rows:
            keys += [k for k in r if k not in keys]
        with open(args.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            w.writerows(all_rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
