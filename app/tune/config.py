"""What a tuning run is: its configuration, frames and results (see :mod:`app.tune`)."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app.dataset import Frame
from threadrecon.app.presets import params_hash
from threadrecon.app.tune.space import OBJECTIVES, Constraint, Space
from threadrecon.core.pipeline import ReconParams


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
    max_frames: int | None = None
    """Tune on at most this many of the tuning frames (a quick look; default: all of them)."""

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
            "max_frames": self.max_frames,
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
    if cfg.max_frames is not None and cfg.max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {cfg.max_frames}")
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
    stopped: bool = False
    """The caller's ``stop()`` ended the run before its target number of trials."""
