"""The best trial, the reports of a store, the comparison on held-back frames, the preset."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from threadrecon.app.dataset import Frame
from threadrecon.app.distributed import Progress, evaluate_rows
from threadrecon.app.evaluation import write_csv
from threadrecon.app.presets import load_preset, params_hash, save_preset
from threadrecon.app.tune.config import (
    TrialResult,
    TuneConfig,
    TuneResult,
)
from threadrecon.app.tune.space import OBJECTIVES
from threadrecon.core.pipeline import ReconParams


def pick_best(trials: Sequence[TrialResult], cfg: TuneConfig) -> TrialResult | None:
    """The feasible complete trial best on the first objective (ties: the earlier trial)."""
    first = OBJECTIVES[cfg.objectives[0]]
    sign = 1.0 if first.direction == "minimize" else -1.0
    ok = [
        t
        for t in trials
        if t.state == "COMPLETE"
        and t.feasible
        and math.isfinite(t.objectives.get(first.name, math.nan))
    ]
    return min(ok, key=lambda t: (sign * t.objectives[first.name], t.number)) if ok else None


def _trial_line(t: TrialResult, cfg: TuneConfig) -> str:
    vals = ", ".join(f"{k}={_fmt(v)}" for k, v in t.values.items())
    objs = ", ".join(f"{o} {_fmt(t.objectives.get(o, math.nan))}" for o in cfg.objectives)
    extra = (
        "" if t.state == "COMPLETE" else f" [{t.state.lower()}{': ' + t.error if t.error else ''}]"
    )
    feas = "" if t.feasible or t.state != "COMPLETE" else " (infeasible)"
    fr = t.objectives.get("failure_rate", math.nan)
    return f"trial {t.number:3d}: {objs}, failures {fr:.1%}{feas}{extra}  <- {vals}"


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _write_reports(store: Path, trials: Sequence[TrialResult], cfg: TuneConfig) -> None:
    summary, per_frame = [], []
    for t in trials:
        summary.append(
            {
                "trial": t.number,
                "state": t.state,
                "feasible": t.feasible,
                **t.values,
                **{f"obj_{k}": v for k, v in t.objectives.items()},
                "error": t.error,
            }
        )
        per_frame += [{"trial": t.number, **r} for r in t.rows]
    if summary:
        write_csv(store / "trials.csv", summary)
    if per_frame:
        write_csv(store / "frames.csv", per_frame)


def compare_on(
    frames: Sequence[Frame],
    settings: dict[str, ReconParams],
    client: Any = None,
    progress: Progress | None = None,
) -> dict[str, dict[str, float]]:
    """Every objective of each named setting on ``frames`` (e.g. the held-back part)."""
    out = {}
    for name, params in settings.items():
        rows = evaluate_rows(client, frames, params, progress)
        out[name] = {o: OBJECTIVES[o].compute(rows) for o in OBJECTIVES}
    return out


def save_best(
    result: TuneResult, folder: Path, name: str | None = None, force: bool = False
) -> Path:
    """The best trial's setting as preset ``folder/name.toml`` (default name: tuned-<hash>).
    An existing preset of that name is replaced only with ``force`` or when it is identical."""
    if result.best is None or result.best_params is None:
        raise ValueError(
            "no feasible trial: nothing to save (relax --constraint or widen the space)"
        )
    name = name or f"tuned-{params_hash(result.best_params)}"
    path = folder / f"{name}.toml"
    same = path.exists() and load_preset(path) == result.best_params
    header = f"threadrecon tune: trial {result.best.number} of {result.store}\n" + ", ".join(
        f"{k} {_fmt(v)}" for k, v in result.best.objectives.items()
    )
    return save_preset(result.best_params, name, folder, overwrite=force or same, header=header)
