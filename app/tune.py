"""Parameter sweeps and searches: a grid or an Optuna TPE search over any parameters of the
stage table, every trial evaluated on every frame of a dataset (frames on Dask, see
:mod:`app.distributed`), every trial kept in a store that survives a kill.

A *space* file (TOML) names the parameters that vary, one table per stage::

    [reliability]
    eps1 = { low = 2.0, high = 20.0 }               # a range (float: continuous)
    threshold = { low = 0.5, high = 0.95, step = 0.05 }
    [stereo]
    window = [5, 7, 9, 11]                          # choices
    [spline]
    n_ctrl = { low = 8, high = 30 }                 # an integer parameter: integers
    xy_knots = ["uniform", "adaptive"]

Every bound and choice is checked against the parameter's declaration (``core.params``). A grid
needs choices or a ``step`` on every float range (integer ranges step by 1 unless told).

Objectives (:data:`OBJECTIVES`) are computed from the per-frame rows of
:func:`app.evaluation.evaluate_frame`; constraints such as ``failure_rate<=0.02`` select the
feasible trials. The store is a folder: ``study.sqlite3`` (Optuna's RDB storage: each trial's
parameters, per-frame rows, objectives and constraint values), ``tune.json`` (what the run
is; a resume must match it), ``trials.csv`` and ``frames.csv`` (written at the end). Running the
same command again resumes: finished trials are kept, a trial cut short by a kill is run again.

Trials run one after another, each on all frames at once, and the TPE sampler is seeded from
``--seed`` and the number of finished trials: the sequence of trials depends only on the store,
never on how many workers ran them.
"""

from __future__ import annotations

import fcntl
import hashlib
import itertools
import json
import math
import operator
import re
import tomllib
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.dataset import Frame, discover
from app.distributed import Progress, evaluate_rows
from app.evaluation import write_csv
from app.presets import load_preset, params_hash, save_preset, validate
from core.params import ParamSpec, specs
from core.pipeline import STAGE_BY_NAME, STAGES, ReconParams

# --- search space ------------------------------------------------------------------------

RANGE_KEYS = {"low", "high", "step", "log"}
GRID_DIGITS = 12  # grid values rounded to 12 significant digits: 0.1 * 3 is 0.3, not 0.30...04


@dataclass(frozen=True)
class Dimension:
    """One varying parameter ``stage.name``: ``choices``, or a range ``low..high``."""

    stage: str
    name: str
    choices: tuple[Any, ...] = ()
    low: float | None = None
    high: float | None = None
    step: float | None = None
    log: bool = False
    integer: bool = False

    @property
    def key(self) -> str:
        return f"{self.stage}.{self.name}"

    def distribution(self) -> Any:
        import optuna.distributions as od

        if self.choices:
            return od.CategoricalDistribution(self.choices)
        if self.integer:
            return od.IntDistribution(
                int(self.low), int(self.high), log=self.log, step=int(self.step or 1)
            )
        return od.FloatDistribution(self.low, self.high, log=self.log, step=self.step)

    def grid(self) -> list[Any]:
        """The values of a grid along this dimension, in order."""
        if self.choices:
            return list(self.choices)
        if self.integer:
            return list(range(int(self.low), int(self.high) + 1, int(self.step or 1)))
        if self.step is None:
            raise ValueError(f"{self.key}: a grid needs choices or a step for a float range")
        n = round((self.high - self.low) / self.step)
        return [float(f"{self.low + i * self.step:.{GRID_DIGITS}g}") for i in range(n + 1)]

    def contains(self, value: Any) -> bool:
        if self.choices:
            return value in self.choices
        if value is None or isinstance(value, bool) or not self.low <= value <= self.high:
            return False
        if self.step is None:
            return True
        k = (value - self.low) / self.step
        return abs(k - round(k)) < 1e-9


@dataclass(frozen=True)
class Space:
    dims: tuple[Dimension, ...]

    def keys(self) -> list[str]:
        return [d.key for d in self.dims]

    def grid(self) -> list[dict[str, Any]]:
        """Every point of the grid, the last dimension varying fastest."""
        values = [d.grid() for d in self.dims]
        return [dict(zip(self.keys(), combo, strict=True)) for combo in itertools.product(*values)]

    def to_dict(self) -> dict[str, Any]:
        return {
            d.key: {k: v for k, v in asdict(d).items() if k not in ("stage", "name")}
            for d in self.dims
        }


def load_space(path: str | Path) -> Space:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"{path}: cannot read space ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from None
    try:
        return parse_space(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def parse_space(data: dict[str, Any]) -> Space:
    """``{stage: {name: [choices] | {low, high[, step][, log]}}}`` -> :class:`Space`; every
    error names the parameter."""
    dims = []
    for stage, table in data.items():
        if stage not in STAGE_BY_NAME:
            raise ValueError(f"unknown parameter group {stage!r} (known: {', '.join(STAGES)})")
        if not isinstance(table, dict):
            raise ValueError(f"{stage}: must be a table of parameters")
        by_name = {s.name: s for s in specs(STAGE_BY_NAME[stage].params)}
        for name, entry in table.items():
            if name not in by_name:
                raise ValueError(f"unknown parameter {stage}.{name}")
            dims.append(_dimension(stage, by_name[name], entry))
    if not dims:
        raise ValueError("the space names no parameter")
    return Space(tuple(dims))


def _check_value(stage: str, name: str, value: Any) -> Any:
    """``value`` as the parameter's declared type, or the declaration's own error."""
    try:
        params = validate({stage: {name: value}})
    except ValueError as exc:
        raise ValueError(
            f"{stage}.{name}: {exc}".replace(f"{stage}.{name}: {stage}.{name}", f"{stage}.{name}")
        ) from None
    got = getattr(getattr(params, stage), name)
    return "auto" if got is None else got


def _dimension(stage: str, spec: ParamSpec, entry: Any) -> Dimension:
    key = f"{stage}.{spec.name}"
    if isinstance(entry, list):
        if not entry:
            raise ValueError(f"{key}: empty list of choices")
        choices = tuple(_check_value(stage, spec.name, v) for v in entry)
        if len(set(map(repr, choices))) != len(choices):
            raise ValueError(f"{key}: repeated choice in {entry}")
        return Dimension(stage, spec.name, choices=choices)
    if not isinstance(entry, dict):
        raise ValueError(
            f"{key}: give a list of choices or a table {{low, high[, step][, log]}}, got {entry!r}"
        )
    unknown = set(entry) - RANGE_KEYS
    if unknown:
        raise ValueError(
            f"{key}: unknown key(s) {', '.join(sorted(unknown))} (known: low, high, step, log)"
        )
    if spec.kind not in ("slider", "number", "auto"):
        raise ValueError(f"{key} is a {spec.kind}: give a list of choices, not a range")
    if "low" not in entry or "high" not in entry:
        raise ValueError(f"{key}: a range needs both low and high")
    low, high = (_check_value(stage, spec.name, entry[k]) for k in ("low", "high"))
    if low == "auto" or high == "auto":
        raise ValueError(
            f'{key}: a range\'s bounds must be numbers; put "auto" in a list of choices'
        )
    if not low < high:
        raise ValueError(f"{key}: low must be below high, got {low} and {high}")
    log = entry.get("log", False)
    if not isinstance(log, bool):
        raise ValueError(f"{key}: log must be true or false, got {log!r}")
    step = entry.get("step")
    if step is not None:
        if isinstance(step, bool) or not isinstance(step, int | float) or not step > 0:
            raise ValueError(f"{key}: step must be a positive number, got {step!r}")
        if spec.integer and not float(step).is_integer():
            raise ValueError(f"{key} is an integer: step must be a whole number, got {step!r}")
        n = (high - low) / step
        if abs(n - round(n)) > 1e-9:
            raise ValueError(
                f"{key}: high - low ({high - low:g}) must be a multiple of step ({step:g})"
            )
        if log:
            raise ValueError(f"{key}: a log range takes no step")
        step = int(step) if spec.integer else float(step)
    if log and not low > 0:
        raise ValueError(f"{key}: a log range needs low > 0, got {low}")
    return Dimension(stage, spec.name, low=low, high=high, step=step, log=log, integer=spec.integer)


def params_of(values: dict[str, Any], base: ReconParams | None = None) -> ReconParams:
    """Trial values ``{"stage.name": value}`` on top of ``base`` (default: the defaults)."""
    data = (base or ReconParams()).to_dict()
    for key, value in values.items():
        stage, name = key.split(".", 1)
        data[stage][name] = value
    data = {
        s: {k: ("auto" if v is None else v) for k, v in vals.items()} for s, vals in data.items()
    }
    return validate(data)


# --- objectives and constraints ----------------------------------------------------------


def _ok(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in rows if r["status"] == "ok"]


def _mean(values: Sequence[float]) -> float:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else math.nan


def _e_s(rows: Sequence[dict[str, Any]]) -> float:
    return _mean([r["e_S_mm"] for r in _ok(rows) if r["kind"] == "simulated"])


def _reprojection(rows: Sequence[dict[str, Any]]) -> float:
    return _mean([(r["left_mean_px"] + r["right_mean_px"]) / 2 for r in _ok(rows)])


def _coverage(rows: Sequence[dict[str, Any]]) -> float:
    # a failed frame covers nothing
    return _mean(
        [
            (r["coverage_left"] + r["coverage_right"]) / 2 if r["status"] == "ok" else 0.0
            for r in rows
        ]
    )


def _failure_rate(rows: Sequence[dict[str, Any]]) -> float:
    return sum(r["status"] != "ok" for r in rows) / len(rows) if rows else math.nan


def _time(rows: Sequence[dict[str, Any]]) -> float:
    v = [r["ms_total"] for r in rows if math.isfinite(r.get("ms_total", math.nan))]
    return float(np.median(v)) if v else math.nan


@dataclass(frozen=True)
class Objective:
    name: str
    direction: str
    """"minimize" or "maximize" (Optuna's words)."""
    compute: Callable[[Sequence[dict[str, Any]]], float]
    doc: str


OBJECTIVES: dict[str, Objective] = {
    o.name: o
    for o in (
        Objective(
            "e_S", "minimize", _e_s, "mean e_S (mm) of the reconstructed frames with ground truth"
        ),
        Objective(
            "reprojection",
            "minimize",
            _reprojection,
            "mean reprojection error (px, left and right) of the reconstructed frames",
        ),
        Objective(
            "coverage",
            "maximize",
            _coverage,
            "mean coverage of the segmented thread (failed frames cover 0)",
        ),
        Objective("failure_rate", "minimize", _failure_rate, "fraction of frames that failed"),
        Objective("time", "minimize", _time, "median pipeline time per frame (ms)"),
    )
}
_CONSTRAINT_RE = re.compile(
    r"^\s*(\w+)\s*(<=|>=)\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(%?)\s*$"
)
DEFAULT_CONSTRAINTS = ("failure_rate<=0.02",)


@dataclass(frozen=True)
class Constraint:
    metric: str
    op: str
    bound: float

    @staticmethod
    def parse(text: str) -> Constraint:
        m = _CONSTRAINT_RE.match(text)
        if not m:
            raise ValueError(
                f"constraint {text!r}: expected METRIC<=VALUE or METRIC>=VALUE, e.g. failure_rate<=0.02"
            )
        metric, op, value, pct = m.groups()
        if metric not in OBJECTIVES:
            raise ValueError(
                f"constraint {text!r}: unknown metric {metric!r} (known: {', '.join(OBJECTIVES)})"
            )
        return Constraint(metric, op, float(value) / (100 if pct else 1))

    def __str__(self) -> str:
        return f"{self.metric}{self.op}{self.bound:g}"

    def violation(self, value: float) -> float:
        """<= 0 when satisfied (Optuna's convention); a NaN metric violates."""
        if not math.isfinite(value):
            return math.inf
        return value - self.bound if self.op == "<=" else self.bound - value

    def satisfied(self, value: float) -> bool:
        return (operator.le if self.op == "<=" else operator.ge)(value, self.bound)


# --- the run -----------------------------------------------------------------------------


@dataclass(frozen=True)
class TuneConfig:
    dataset: str
    space: Space
    objectives: tuple[str, ...] = ("e_S",)
    constraints: tuple[Constraint, ...] = ()
    mode: str = "search"
    """"search" (Optuna TPE) or "grid" (every point, in order)."""
    trials: int | None = None
    """Trials in the store when done (default: a grid's size; 50 for a search)."""
    holdout: float = 0.0
    """Fraction of the frames held back from tuning, chosen by a hash of the frame id."""
    seed: int = 0
    rungs: int = 4
    """The frames are evaluated in this many parts; a trial may be pruned after each."""
    prune: bool = True
    base: ReconParams = field(default_factory=ReconParams)
    """The setting the space's parameters vary on (default: the defaults)."""

    def identity(self) -> dict[str, Any]:
        """What a resume must match (the number of trials may grow)."""
        return {
            "dataset": str(Path(self.dataset).resolve()),
            "space": self.space.to_dict(),
            "objectives": list(self.objectives),
            "constraints": [str(c) for c in self.constraints],
            "mode": self.mode,
            "holdout": self.holdout,
            "seed": self.seed,
            "rungs": self.rungs,
            "prune": self.prune,
            "base": params_hash(self.base),
        }


def check_config(cfg: TuneConfig, frames: Sequence[Frame]) -> None:
    if not cfg.objectives:
        raise ValueError("give at least one --objective")
    for name in cfg.objectives:
        if name not in OBJECTIVES:
            raise ValueError(f"unknown objective {name!r} (known: {', '.join(OBJECTIVES)})")
    if len(set(cfg.objectives)) != len(cfg.objectives):
        raise ValueError("an objective is named twice")
    if "e_S" in cfg.objectives and not any(f.has_ground_truth for f in frames):
        raise ValueError(
            "objective e_S needs frames with ground truth; this dataset has none (try reprojection or coverage)"
        )
    if cfg.mode not in ("search", "grid"):
        raise ValueError(f"mode must be search or grid, got {cfg.mode!r}")
    if not 0 <= cfg.holdout < 1:
        raise ValueError(f"--holdout must be in [0, 1), got {cfg.holdout}")
    if cfg.trials is not None and cfg.trials < 1:
        raise ValueError(f"--trials must be >= 1, got {cfg.trials}")
    if cfg.rungs < 1:
        raise ValueError(f"--rungs must be >= 1, got {cfg.rungs}")
    if cfg.mode == "grid":
        cfg.space.grid()  # a float range without a step is an error here


def split_frames(frames: Sequence[Frame], holdout: float) -> tuple[list[Frame], list[Frame]]:
    """(tuning, held back): the held-back frames are those with the smallest SHA-256 of their
    id, so a frame's side does not depend on the others or on their order."""
    ranked = sorted(frames, key=lambda f: hashlib.sha256(f.id.encode()).hexdigest())
    n_hold = round(holdout * len(frames))
    held = {f.id for f in ranked[:n_hold]}
    tune = [f for f in frames if f.id not in held]
    if not tune:
        raise ValueError(f"--holdout {holdout} leaves no frame to tune on ({len(frames)} frames)")
    return tune, [f for f in frames if f.id in held]


def _rung_order(frames: Sequence[Frame], seed: int) -> list[Frame]:
    """The tuning frames in a seeded shuffled order, so each part of a trial is a sample of all
    groups rather than the first group only."""
    order = np.random.default_rng(seed).permutation(len(frames))
    return [frames[i] for i in order]


@dataclass
class TrialResult:
    number: int
    state: str
    values: dict[str, Any]
    objectives: dict[str, float]
    constraints: dict[str, float]
    feasible: bool
    rows: list[dict[str, Any]]
    error: str = ""


@dataclass
class TuneResult:
    trials: list[TrialResult]
    best: TrialResult | None
    best_params: ReconParams | None
    store: Path


STUDY_NAME = "threadrecon"
INTERRUPTED = "interrupted; run again"  # the error of a trial cut short by a kill
_STORE_DB = "study.sqlite3"


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
    storage = optuna.storages.RDBStorage(f"sqlite:///{store / _STORE_DB}")
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
        diffs = [k for k in ident if old.get(k) != ident[k]]
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
) -> TuneResult:
    """Run (or resume) the tune described by ``cfg`` in ``store`` on ``client`` (a Dask client;
    None runs frames in this process)."""
    from optuna.trial import TrialState

    store = Path(store)
    frames = discover(cfg.dataset)
    check_config(cfg, frames)
    tune_frames, _ = split_frames(frames, cfg.holdout)
    ordered = _rung_order(tune_frames, cfg.seed)
    parts = (
        min(cfg.rungs, len(ordered)) if cfg.prune else 1
    )  # one map per part: no parts to wait for
    bounds = np.linspace(0, len(ordered), parts + 1).round().astype(int)
    dists = {d.key: d.distribution() for d in cfg.space.dims}
    grid = cfg.space.grid() if cfg.mode == "grid" else []
    target = cfg.trials or (len(grid) if grid else 50)
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
            if grid:
                seen = [t.params for t in done]
                todo = [p for p in grid if p not in seen]
                if not todo:
                    break
                if not _has_waiting(study):
                    study.enqueue_trial(todo[0])
            study.sampler = _sampler(cfg, len(done))
            trial = study.ask(dists)
            result = _run_trial(trial, cfg, ordered, bounds, client, single, progress)
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
        out = TuneResult(trials, best, params_of(best.values, cfg.base) if best else None, store)
        _write_reports(store, trials, cfg)
    return out


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
        rows += evaluate_rows(client, frames[a:b], params, progress)
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
