"""Search spaces, objectives, constraints and the run's configuration (see :mod:`app.tune`)."""

from __future__ import annotations

import itertools
import math
import operator
import re
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app.presets import read_toml, validate
from threadrecon.core.params import ParamSpec, specs
from threadrecon.core.pipeline import STAGE_BY_NAME, STAGES, ReconParams

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
    return read_toml(path, "space", parse_space)


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
