"""The tuner's run: the store, the sampler, the trials (see :mod:`app.tune`)."""

from __future__ import annotations

import fcntl
import itertools
import json
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app.dataset import Frame, discover
from threadrecon.app.distributed import Progress, evaluate_rows
from threadrecon.app.tune.config import (
    TrialResult,
    TuneConfig,
    TuneResult,
    _rung_order,
    check_config,
    split_frames,
)
from threadrecon.app.tune.report import _trial_line, _write_reports, pick_best
from threadrecon.app.tune.space import OBJECTIVES, Dimension, params_of
from threadrecon.core.pipeline import ReconParams

STUDY_NAME = "threadrecon"
INTERRUPTED = "interrupted; run again"  # the error of a trial cut short by a kill
_STORE_DB = "study.sqlite3"
_LOCK_WAIT_S = 120.0


@contextmanager
def _locked(store: Path) -> Iterator[None]:
    """One tuner per store: a second one gets a clear error (the lock dies with its process)."""
    store.mkdir(parents=True, exist_ok=True)
    with (store / "tune.lock").open("w") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise ValueError(f"{store}: another tuner is using this store") from None
        yield


def open_study(store: Path, cfg: TuneConfig, create: bool = True) -> Any:
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    directions = [OBJECTIVES[o].direction for o in cfg.objectives]
    # SQLite lets one writer in at a time; a reader (the debugger's tune page, a second process
    # reading the study) holds the lock briefly. Wait for it rather than fail the trial with
    # "database is locked" after sqlite's default 5 s on a loaded machine.
    # Only the tuner creates the schema: a reader creating it too (optuna's create_all, a check
    # then a CREATE) races the tuner's own on a new store ("table ... already exists"), and the
    # tuner dies. A reader of a store whose schema is not there yet gets an error instead.
    storage = optuna.storages.RDBStorage(
        f"sqlite:///{store / _STORE_DB}",
        engine_kwargs={"connect_args": {"timeout": _LOCK_WAIT_S}},
        skip_table_creation=not create,
    )
    if create:
        return optuna.create_study(
            storage=storage, study_name=STUDY_NAME, directions=directions, load_if_exists=True
        )
    return optuna.load_study(storage=storage, study_name=STUDY_NAME)


def _check_identity(store: Path, cfg: TuneConfig) -> None:
    path = store / "tune.json"
    ident = json.loads(json.dumps(cfg.identity()))  # tuples as the lists read back
    if path.exists():
        old = json.loads(path.read_text())
        # a key missing on one side reads as None (a store written before the key existed)
        diffs = [k for k in sorted(set(ident) | set(old)) if old.get(k) != ident.get(k)]
        if diffs:
            raise ValueError(
                f"{store} holds a different tune ({', '.join(diffs)} differ): give a new --store to start another"
            )
    else:
        path.write_text(json.dumps(ident, indent=1))


def _sampler(cfg: TuneConfig, n_finished: int) -> Any:
    import optuna

    seed = cfg.seed * 100_003 + n_finished  # the k-th finished trial's sampler, whatever ran before
    if cfg.mode == "grid":
        return optuna.samplers.RandomSampler(seed=seed)  # unused: every grid value is fixed
    return optuna.samplers.TPESampler(
        seed=seed,
        n_startup_trials=10,
        multivariate=True,
    )


def _finished(study: Any) -> list[Any]:
    from optuna.trial import TrialState

    return [
        t
        for t in study.get_trials(deepcopy=False)
        if t.state in (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
    ]


def _recover(study: Any, cfg: TuneConfig) -> int:
    """A trial left running by a killed tuner is marked failed (and left out of every report);
    a search queues its setting again, a grid finds the point still to do by itself. Returns
    how many there were."""
    from optuna.trial import TrialState

    stale = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.RUNNING]
    for t in stale:
        study._storage.set_trial_user_attr(t._trial_id, "error", INTERRUPTED)
        study._storage.set_trial_state_values(t._trial_id, TrialState.FAIL)
        # killed inside ask(), a trial may hold only some of its values: nothing to repeat
        if cfg.mode == "search" and set(t.params) == set(cfg.space.keys()):
            study.enqueue_trial(t.params, user_attrs={"requeued_from": t.number})
    return len(stale)


def tune(
    cfg: TuneConfig,
    store: str | Path,
    client: Any = None,
    log: Callable[[str], None] = print,
    progress: Progress | None = None,
    on_trial: Callable[[TrialResult], None] | None = None,
    stop: Callable[[], bool] | None = None,
) -> TuneResult:
    """Run (or resume) the tune described by ``cfg`` in ``store`` on ``client`` (a Dask client;
    None runs frames in this process).

    ``stop()`` is asked before each trial and each frame: once it answers True the trial under
    way is left as interrupted (a resume runs it again), the finished ones are reported and
    ``TuneResult.stopped`` is True."""
    from optuna.trial import TrialState

    store = Path(store)
    frames = discover(cfg.dataset)
    check_config(cfg, frames)
    tune_frames, _ = split_frames(frames, cfg.holdout)
    ordered = _rung_order(tune_frames, cfg.seed)[: cfg.max_frames]
    progress = _stoppable(progress, stop)
    stopped = False
    parts = (
        min(cfg.rungs, len(ordered)) if cfg.prune else 1
    )  # one map per part: no parts to wait for
    bounds = np.linspace(0, len(ordered), parts + 1).round().astype(int)
    dists = {d.key: d.distribution() for d in cfg.space.dims}
    grid = cfg.space.grid() if cfg.mode == "grid" else []
    target = target_trials(cfg)
    single = len(cfg.objectives) == 1

    with _locked(store):
        _check_identity(store, cfg)
        study = open_study(store, cfg)
        n_stale = _recover(study, cfg)
        if n_stale:
            log(f"resuming: {n_stale} interrupted trial(s) will run again")
        done = [t for t in _finished(study) if not _interrupted(t)]
        if done:
            log(f"resuming: {len(done)} finished trial(s) in {store}")
        if not done and not grid:
            default = {d.key: _value_of(cfg.base, d) for d in cfg.space.dims}
            if all(d.contains(default[d.key]) for d in cfg.space.dims):
                study.enqueue_trial(default, user_attrs={"baseline": True})
        while True:
            done = [t for t in _finished(study) if not _interrupted(t)]
            if len(done) >= target:
                break
            if stop is not None and stop():
                stopped = True
                break
            if grid:
                seen = [t.params for t in done]
                todo = [p for p in grid if p not in seen]
                if not todo:
                    break
                if not _has_waiting(study):
                    study.enqueue_trial(todo[0])
            study.sampler = _sampler(cfg, len(done))
            trial = study.ask(dists)
            try:
                result = _run_trial(trial, cfg, ordered, bounds, client, single, progress)
            except Stopped:
                _interrupt(study, trial, cfg)
                stopped = True
                break
            state = {
                "COMPLETE": TrialState.COMPLETE,
                "PRUNED": TrialState.PRUNED,
                "FAIL": TrialState.FAIL,
            }[result.state]
            for k, v in (
                ("rows", result.rows),
                ("objectives", result.objectives),
                ("constraints", result.constraints),
                ("feasible", result.feasible),
                ("error", result.error),
            ):
                trial.set_user_attr(k, v)
            for c in cfg.constraints:  # the sampler prefers settings that satisfy them
                trial.set_constraint(str(c), min(result.constraints.get(str(c), 1e300), 1e300))
            values = (
                [result.objectives[o] for o in cfg.objectives]
                if state == TrialState.COMPLETE
                else None
            )
            if state == TrialState.COMPLETE and not all(math.isfinite(v) for v in values):
                state, values = TrialState.FAIL, None
                result.state, result.error = (
                    "FAIL",
                    result.error or "objective not computable (no reconstructed frame)",
                )
                trial.set_user_attr("error", result.error)
            study.tell(trial, values=values, state=state)
            log(_trial_line(result, cfg))
            if on_trial:
                on_trial(result)

        trials = [_result_of(t) for t in _finished(study) if not _interrupted(t)]
        best = pick_best(trials, cfg)
        out = TuneResult(
            trials, best, params_of(best.values, cfg.base) if best else None, store, stopped
        )
        _write_reports(store, trials, cfg)
    return out


class Stopped(Exception):
    """Raised between frames when the caller's ``stop()`` answers True."""


def _stoppable(progress: Progress | None, stop: Callable[[], bool] | None) -> Progress | None:
    if stop is None:
        return progress

    def check(done: int, total: int, frame: str) -> None:
        if stop():
            raise Stopped
        if progress is not None:
            progress(done, total, frame)

    return check


def _interrupt(study: Any, trial: Any, cfg: TuneConfig) -> None:
    """A trial stopped midway: failed as interrupted (out of every report), and a search queues
    its setting again, as after a kill (see :func:`_recover`)."""
    from optuna.trial import TrialState

    trial.set_user_attr("error", INTERRUPTED)
    study.tell(trial, state=TrialState.FAIL)
    if cfg.mode == "search":
        study.enqueue_trial(dict(trial.params), user_attrs={"requeued_from": trial.number})


def _offset(progress: Progress | None, start: int, total: int) -> Progress | None:
    """A part's progress (frames ``start`` on) as progress through all ``total`` frames."""
    if progress is None:
        return None
    return lambda done, _n, frame: progress(start + done, total, frame)


def target_trials(cfg: TuneConfig) -> int:
    """Trials in the store when the tune is done: ``cfg.trials``, else a grid's size, else 50."""
    return cfg.trials or (len(cfg.space.grid()) if cfg.mode == "grid" else 50)


def _interrupted(t: Any) -> bool:
    return t.user_attrs.get("error") == INTERRUPTED


def _has_waiting(study: Any) -> bool:
    from optuna.trial import TrialState

    return any(t.state == TrialState.WAITING for t in study.get_trials(deepcopy=False))


def _value_of(params: ReconParams, d: Dimension) -> Any:
    v = getattr(getattr(params, d.stage), d.name)
    return "auto" if v is None else v


def _run_trial(
    trial: Any,
    cfg: TuneConfig,
    frames: list[Frame],
    bounds: np.ndarray,
    client: Any,
    single: bool,
    progress: Progress | None,
) -> TrialResult:
    import optuna

    values = dict(trial.params)
    try:
        params = params_of(values, cfg.base)
    except ValueError as exc:  # e.g. clustering.min_size above max_size: no such setting
        return TrialResult(
            trial.number, "FAIL", values, {}, {}, False, [], f"invalid setting: {exc}"
        )
    pruner = (
        optuna.pruners.MedianPruner(n_startup_trials=5, n_warmup_steps=0)
        if cfg.prune and single
        else None
    )
    rows: list[dict[str, Any]] = []
    n = len(frames)
    state = "COMPLETE"
    for step, (a, b) in enumerate(itertools.pairwise(bounds)):
        rows += evaluate_rows(client, frames[a:b], params, _offset(progress, a, n))
        if b == n or not cfg.prune:
            continue
        failed = sum(r["status"] != "ok" for r in rows)
        # a failure constraint that the frames so far already break whatever the rest do
        if any(
            c.metric == "failure_rate" and c.op == "<=" and failed > c.bound * n
            for c in cfg.constraints
        ):
            state = "PRUNED"
            break
        if pruner is not None:
            value = OBJECTIVES[cfg.objectives[0]].compute(rows)
            if math.isfinite(value):
                trial.report(value, step)
                if pruner.prune(trial.study, trial.study._storage.get_trial(trial._trial_id)):
                    state = "PRUNED"
                    break
    objectives = {name: OBJECTIVES[name].compute(rows) for name in OBJECTIVES}
    constraints = {str(c): c.violation(objectives[c.metric]) for c in cfg.constraints}
    feasible = state == "COMPLETE" and all(v <= 0 for v in constraints.values())
    return TrialResult(trial.number, state, values, objectives, constraints, feasible, rows)


def _result_of(t: Any) -> TrialResult:
    a = t.user_attrs
    return TrialResult(
        t.number,
        t.state.name,
        dict(t.params),
        a.get("objectives", {}),
        a.get("constraints", {}),
        bool(a.get("feasible", False)),
        a.get("rows", []),
        a.get("error", ""),
    )
