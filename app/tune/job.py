"""A tune in a background thread, for the debugger page: started from the page's current
setting, followed trial by trial, cancelled, and its trials loaded or saved as presets.

:class:`TuneJob` is one run of :func:`app.tune.run.tune` (its store survives the server:
the same store resumes from the command line). :class:`Tuner` is the server's holder: one tune
at a time, stores in one folder, requests checked before anything runs.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from threadrecon.app.dataset import discover
from threadrecon.app.errors import Conflict, Invalid, NotFound
from threadrecon.app.export import json_safe
from threadrecon.app.jobs import FINAL_STATES, BackgroundJob
from threadrecon.app.presets import params_hash, save_preset
from threadrecon.app.tune.config import TrialResult, TuneConfig, check_config
from threadrecon.app.tune.results import results, trial_summary
from threadrecon.app.tune.run import target_trials, tune
from threadrecon.app.tune.space import Constraint, params_of, parse_space
from threadrecon.core.pipeline import ReconParams

MAX_TRIALS = 500  # a page tune is a look at a few settings; bigger ones belong to the CLI
MAX_DIMENSIONS = 8  # parameters varied at once: more than the page's plots can show
MAX_CONSTRAINTS = 8


class TuneJob(BackgroundJob):
    """``tune(cfg, store)`` in a daemon thread, frames in this process.

    ``state``: "running" once started, then "done" (target reached), "cancelled"
    (:meth:`cancel`, which takes effect before the next frame; the trial under way is
    dropped, the finished ones are kept) or "failed" (``error`` says why).
    """

    def __init__(self, cfg: TuneConfig, store: Path, job_id: str) -> None:
        super().__init__(f"tune-{job_id}")
        self.cfg = cfg
        self.store = store
        self.id = job_id
        self.target = target_trials(cfg)
        self._trials: list[TrialResult] = []
        self._frames = (0, 0, "")
        self._log: list[str] = []

    def _work(self) -> str:
        got = tune(
            self.cfg,
            self.store,
            None,
            log=self._say,
            progress=self._progress,
            on_trial=self._on_trial,
            stop=self._cancel.is_set,
        )
        with self._lock:  # resumed trials too, in the store's order
            self._trials = list(got.trials)
        return "cancelled" if got.stopped else "done"

    def _say(self, line: str) -> None:
        with self._lock:
            self._log.append(line)

    def _progress(self, done: int, total: int, frame: str) -> None:
        with self._lock:
            self._frames = (done, total, frame)

    def _on_trial(self, t: TrialResult) -> None:
        with self._lock:
            self._trials.append(t)

    def trials(self) -> list[TrialResult]:
        with self._lock:
            return list(self._trials)

    def trial(self, number: int) -> TrialResult:
        for t in self.trials():
            if t.number == number:
                return t
        raise NotFound(f"tune {self.id} has no finished trial {number}")

    def params(self, number: int) -> ReconParams:
        """The full setting of a trial: its values on top of the tune's base setting."""
        return params_of(self.trial(number).values, self.cfg.base)

    def snapshot(self, since: int = 0) -> dict[str, Any]:
        """State for polling; ``trials`` holds the finished trials from index ``since`` on."""
        if since < 0:
            raise Invalid(f"since must be >= 0, got {since}")
        with self._lock:
            done, total, frame = self._frames
            return json_safe(
                {
                    "id": self.id,
                    "state": self._state,
                    "store": str(self.store),
                    "mode": self.cfg.mode,
                    "objective": self.cfg.objectives[0],
                    "keys": self.cfg.space.keys(),
                    "target": self.target,
                    "done": len(self._trials),
                    "frames": {"done": done, "total": total, "current": frame},
                    "since": since,
                    "trials": [trial_summary(t) for t in self._trials[since:]],
                    "log": self._log[-20:],
                    "error": self._error,
                    "started_at": self._started_at,
                    "elapsed_s": round(self._elapsed(), 3),
                }
            )

    def results(self) -> dict[str, Any]:
        out = results(self.trials(), self.cfg)
        out["id"], out["state"] = self.id, self.state
        return json_safe(out)


class Tuner:
    """The server's tunes: one at a time, each in a new store under ``folder``."""

    def __init__(self, data_dir: Path, folder: Path, configs: Path) -> None:
        self.data_dir = data_dir
        self.folder = folder
        self.configs = configs
        self.job: TuneJob | None = None
        self._lock = threading.Lock()

    def config(
        self,
        space: dict[str, Any],
        base: ReconParams,
        *,
        objective: str = "e_S",
        constraints: Sequence[str] = (),
        mode: str = "search",
        trials: int | None = None,
        max_frames: int | None = None,
        seed: int = 0,
    ) -> TuneConfig:
        """A checked configuration from a page request; :class:`Invalid` names the problem."""
        try:
            parsed = parse_space(space)
        except ValueError as exc:
            raise Invalid(str(exc)) from None
        if len(parsed.dims) > MAX_DIMENSIONS:
            raise Invalid(
                f"vary at most {MAX_DIMENSIONS} parameters at once, got {len(parsed.dims)}"
            )
        if trials is not None and not 1 <= trials <= MAX_TRIALS:
            raise Invalid(f"trials must be in [1, {MAX_TRIALS}], got {trials}")
        if len(constraints) > MAX_CONSTRAINTS:
            raise Invalid(f"at most {MAX_CONSTRAINTS} constraints, got {len(constraints)}")
        try:
            cfg = TuneConfig(
                dataset=str(self.data_dir),
                space=parsed,
                objectives=(objective,),
                constraints=tuple(Constraint.parse(c) for c in constraints),
                mode=mode,
                trials=trials,
                seed=seed,
                base=base,
                max_frames=max_frames,
            )
            frames = discover(self.data_dir)
            if not frames:
                raise ValueError(f"no frames in {self.data_dir}")
            check_config(cfg, frames)
            target = target_trials(cfg)
        except ValueError as exc:
            raise Invalid(str(exc)) from None
        if target > MAX_TRIALS:
            raise Invalid(
                f"the grid has {target} points, more than {MAX_TRIALS}: coarsen a step or give trials"
            )
        return cfg

    def start(self, cfg: TuneConfig) -> TuneJob:
        with self._lock:
            if self.job is not None and self.job.state not in FINAL_STATES:
                raise Conflict("a tune is already running: cancel it first")
            job_id = datetime.now(UTC).strftime("%Y%m%d-%H%M%S-") + params_hash(cfg.base)[:6]
            store = self.folder / job_id
            if store.exists():  # two starts in one second with one base: a fresh folder still
                job_id += f"-{time.monotonic_ns() % 10**6}"
                store = self.folder / job_id
            self.job = TuneJob(cfg, store, job_id).start()
            return self.job

    def current(self) -> TuneJob:
        if self.job is None:
            raise NotFound("no tune was started since the server started")
        return self.job

    def save_trial(self, number: int, name: str) -> Path:
        """A trial's setting as a new user preset (never over an existing or built-in one)."""
        job = self.current()
        t = job.trial(number)
        header = f"threadrecon tune {job.id}: trial {t.number}; " + ", ".join(
            f"{k} {v:.4g}" for k, v in t.objectives.items() if isinstance(v, float)
        )
        return save_preset(job.params(number), name, self.configs, overwrite=False, header=header)

    def stop(self) -> None:
        if self.job is not None:
            self.job.cancel()
