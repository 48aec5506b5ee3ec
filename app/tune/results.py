"""What the page shows of a tune: the best trials, parameter importance, the points of the
objective-vs-parameter plots and the Pareto front of accuracy vs failure rate vs time.

Everything is computed from the trials (:class:`TrialResult`) and the configuration, so a
running tune and a finished one read the same way, and no second copy of a figure exists: the
objectives are the ones the tuner stored.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from threadrecon.app.tune.config import TrialResult, TuneConfig
from threadrecon.app.tune.space import OBJECTIVES

BEST_ROWS = 10  # rows of the best-trials table: the page shows a short list, not the store
PARETO_AXES = ("failure_rate", "time")  # minimised with the accuracy metric


def trial_summary(t: TrialResult) -> dict[str, Any]:
    """A trial without its per-frame rows (what a poll sends)."""
    return {
        "number": t.number,
        "state": t.state,
        "values": dict(t.values),
        "objectives": dict(t.objectives),
        "constraints": dict(t.constraints),
        "feasible": t.feasible,
        "error": t.error,
    }


def accuracy_metric(cfg: TuneConfig, trials: Sequence[TrialResult]) -> str:
    """The accuracy axis of the Pareto front: the first objective when it is e_S or the
    reprojection error, otherwise e_S where some trial has it, otherwise reprojection."""
    first = cfg.objectives[0]
    if first in ("e_S", "reprojection"):
        return first
    has_e_s = any(math.isfinite(t.objectives.get("e_S", math.nan)) for t in trials)
    return "e_S" if has_e_s else "reprojection"


def best_trials(
    trials: Sequence[TrialResult], cfg: TuneConfig, n: int = BEST_ROWS
) -> list[TrialResult]:
    """Complete trials with a finite first objective, feasible ones first, best first (ties:
    the earlier trial): the order of :func:`app.tune.report.pick_best`."""
    first = OBJECTIVES[cfg.objectives[0]]
    sign = 1.0 if first.direction == "minimize" else -1.0
    ok = [
        t
        for t in trials
        if t.state == "COMPLETE" and math.isfinite(t.objectives.get(first.name, math.nan))
    ]
    ok.sort(key=lambda t: (not t.feasible, sign * t.objectives[first.name], t.number))
    return ok[:n]


def pareto_front(points: np.ndarray) -> np.ndarray:
    """Indices of the non-dominated rows of ``points`` ((N, M) float, every column minimised):
    no other row is <= on every column and < on one. Rows with a NaN are never on the front."""
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2:
        raise ValueError(f"points must be (N, M), got shape {pts.shape}")
    finite = np.isfinite(pts).all(axis=1)
    # dominated[i, j]: row j dominates row i (N is a few hundred trials at most)
    le = (pts[None, :, :] <= pts[:, None, :]).all(axis=2)
    lt = (pts[None, :, :] < pts[:, None, :]).any(axis=2)
    dominated = (le & lt & finite[None, :]).any(axis=1)
    return np.flatnonzero(finite & ~dominated)


def pareto_trials(trials: Sequence[TrialResult], metric: str) -> list[int]:
    """Numbers of the complete trials on the front of (``metric``, failure rate, time)."""
    done = [t for t in trials if t.state == "COMPLETE"]
    if not done:
        return []
    axes = (metric, *PARETO_AXES)
    pts = np.array([[t.objectives.get(a, math.nan) for a in axes] for t in done], dtype=float)
    for j, a in enumerate(axes):
        if OBJECTIVES[a].direction == "maximize":
            pts[:, j] = -pts[:, j]
    return [done[i].number for i in pareto_front(pts)]


def importance(trials: Sequence[TrialResult], cfg: TuneConfig) -> tuple[dict[str, float], str]:
    """(importance of each varying parameter for the first objective, a note): Optuna's
    PED-ANOVA evaluator (deterministic, no scikit-learn, unlike its fANOVA) on the complete
    trials. The note says why there is none."""
    first = cfg.objectives[0]
    done = [
        t
        for t in trials
        if t.state == "COMPLETE" and math.isfinite(t.objectives.get(first, math.nan))
    ]
    if len(done) < 2:
        return {}, "parameter importance needs at least 2 complete trials"
    values = {t.objectives[first] for t in done}
    if len(values) < 2:
        return {}, f"every complete trial has the same {first}: no parameter matters so far"
    import optuna

    dists = {d.key: d.distribution() for d in cfg.space.dims}
    study = optuna.create_study(direction=OBJECTIVES[first].direction)
    for t in done:
        if set(t.values) != set(dists):
            continue
        study.add_trial(
            optuna.trial.create_trial(
                params=t.values, distributions=dists, value=t.objectives[first]
            )
        )
    sign = 1.0 if OBJECTIVES[first].direction == "minimize" else -1.0
    try:  # PED-ANOVA assumes "lower is better": a maximised objective is negated
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # its reminder of that, on every call
            got = optuna.importance.get_param_importances(
                study,
                evaluator=optuna.importance.PedAnovaImportanceEvaluator(),
                target=lambda t: sign * t.value,
            )
    except (ValueError, RuntimeError) as exc:
        return {}, f"no parameter importance: {exc}"
    return {k: float(v) for k, v in got.items()}, ""


def dimensions(cfg: TuneConfig) -> list[dict[str, Any]]:
    """The varying parameters as the plots need them (range or choices)."""
    return [
        {
            "key": d.key,
            "choices": list(d.choices),
            "low": d.low,
            "high": d.high,
            "log": d.log,
        }
        for d in cfg.space.dims
    ]


def results(trials: Sequence[TrialResult], cfg: TuneConfig) -> dict[str, Any]:
    """Everything the results view draws, JSON-ready apart from NaN (see ``json_safe``)."""
    metric = accuracy_metric(cfg, trials)
    imp, note = importance(trials, cfg)
    return {
        "objective": {
            "name": cfg.objectives[0],
            "direction": OBJECTIVES[cfg.objectives[0]].direction,
            "doc": OBJECTIVES[cfg.objectives[0]].doc,
        },
        "constraints": [str(c) for c in cfg.constraints],
        "dimensions": dimensions(cfg),
        "trials": [trial_summary(t) for t in trials],
        "best": [t.number for t in best_trials(trials, cfg)],
        "importance": imp,
        "importance_note": note,
        "pareto": {"axes": [metric, *PARETO_AXES], "front": pareto_trials(trials, metric)},
    }
