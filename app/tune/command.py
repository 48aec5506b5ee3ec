"""``threadrecon tune``: a sweep or a search over the stage table's parameters (see :mod:`app.tune`)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from threadrecon.app.dataset import discover
from threadrecon.app.distributed import connect, describe
from threadrecon.app.presets import resolve_preset
from threadrecon.app.tune.config import TuneConfig, split_frames
from threadrecon.app.tune.report import compare_on, save_best
from threadrecon.app.tune.run import tune
from threadrecon.app.tune.space import DEFAULT_CONSTRAINTS, Constraint, load_space


def cmd_tune(args: argparse.Namespace) -> int:
    cfg = TuneConfig(
        dataset=args.dataset,
        space=load_space(args.space),
        objectives=tuple(args.objective or ("e_S",)),
        constraints=tuple(Constraint.parse(c) for c in (args.constraint or DEFAULT_CONSTRAINTS)),
        mode="grid" if args.grid else "search",
        trials=args.trials,
        holdout=args.holdout,
        seed=args.seed,
        rungs=args.rungs,
        prune=not args.no_prune,
        base=resolve_preset(args.config),
    )
    with connect(args.scheduler, args.workers) as client:
        print(f"threadrecon tune: {describe(client)}")
        t0 = time.perf_counter()
        result = tune(cfg, args.store, client)
        wall = time.perf_counter() - t0
        n = len(result.trials)
        print(f"{n} trials in {args.store} ({wall:.1f} s of trials in this run)")
        if result.best is None:
            print("threadrecon: no feasible trial", file=sys.stderr)
            return 1
        print(
            f"best: trial {result.best.number}: "
            + ", ".join(f"{k}={v}" for k, v in result.best.values.items())
        )
        _print_metrics({"best (tuning frames)": result.best.objectives})
        _, held = split_frames(discover(args.dataset), args.holdout)
        if held:
            cmp = compare_on(held, {"base": cfg.base, "best": result.best_params}, client)
            print(f"held-back frames ({len(held)}):")
            _print_metrics(cmp)
    if args.save_preset:
        path = save_best(result, Path(args.save_preset), args.preset_name, args.force)
        print(f"preset -> {path}")
    return 0


def _print_metrics(table: dict[str, dict[str, float]]) -> None:
    names = ("e_S", "reprojection", "coverage", "failure_rate", "time")
    print(f"  {'':<22}" + "".join(f"{n:>14}" for n in names))
    for label, m in table.items():
        print(f"  {label:<22}" + "".join(f"{m.get(n, math.nan):14.4g}" for n in names))
