"""Parameter sweeps and searches (app/tune.py) and frames on Dask (app/distributed.py): the
space file is checked against the parameter declarations, a grid runs every point once, the
store keeps every finished trial through a kill, and rows do not depend on who computed them."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from threadrecon.app import generate
from threadrecon.app.dataset import discover
from threadrecon.app.distributed import connect, evaluate_rows
from threadrecon.app.presets import load_preset
from threadrecon.app.tune import (
    OBJECTIVES,
    Constraint,
    TuneConfig,
    check_config,
    load_space,
    open_study,
    params_of,
    parse_space,
    pick_best,
    save_best,
    split_frames,
    tune,
)
from threadrecon.core.pipeline import ReconParams

ROOT = Path(__file__).resolve().parents[2]
GRID_SPACE = {"reliability": {"threshold": [0.6, 0.9]}, "spline": {"n_ctrl": [8, 12, 15]}}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("tune-set")
    assert generate.main([str(root), "--count", "3", "--seed", "4242", "--noise", "2"]) == 0
    return root


def _timeless(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """A row without its timings, NaN as a string so that equal rows compare equal."""
    return [
        {
            k: ("nan" if isinstance(v, float) and math.isnan(v) else v)
            for k, v in r.items()
            if not k.startswith("ms_")
        }
        for r in rows
    ]


# --- space ---------------------------------------------------------------------------------


def test_space_reads_ranges_and_choices_in_the_declared_types(tmp_path: Path) -> None:
    path = tmp_path / "space.toml"
    path.write_text(
        "[reliability]\neps1 = { low = 2, high = 20 }\nthreshold = { low = 0.5, high = 0.9, step = 0.1 }\n"
        "[stereo]\nwindow = [5, 7.0, 9]\n[spline]\nn_ctrl = { low = 8, high = 12, step = 2 }\n"
        'xy_knots = ["uniform", "adaptive"]\n[segment]\nbackground = ["auto", 40]\n'
    )
    space = load_space(path)
    by_key = {d.key: d for d in space.dims}
    assert by_key["reliability.eps1"].low == 2.0 and isinstance(
        by_key["reliability.eps1"].low, float
    )
    assert by_key["stereo.window"].choices == (5, 7, 9)
    assert all(type(v) is int for v in by_key["stereo.window"].choices)
    assert by_key["reliability.threshold"].grid() == [0.5, 0.6, 0.7, 0.8, 0.9]
    assert by_key["spline.n_ctrl"].grid() == [8, 10, 12]
    assert by_key["segment.background"].choices == ("auto", 40.0)
    assert params_of({"segment.background": "auto"}).segment.background is None


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"nope": {"x": [1]}}, "unknown parameter group 'nope'"),
        ({"stereo": {"nope": [1]}}, "unknown parameter stereo.nope"),
        ({"reliability": {"threshold": {"low": 0.5, "high": 1.5}}}, "reliability.threshold"),
        ({"stereo": {"window": {"low": 3, "high": 9, "step": 0.5}}}, "step must be a whole number"),
        ({"stereo": {"window": {"low": 3.5, "high": 9}}}, "whole number"),
        ({"spline": {"xy_knots": {"low": 0, "high": 1}}}, "give a list of choices"),
        ({"spline": {"xy_knots": ["uniform", "cubic"]}}, "spline.xy_knots"),
        ({"stereo": {"window": []}}, "empty list"),
        ({"stereo": {"window": [5, 5]}}, "repeated choice"),
        ({"reliability": {"eps1": {"low": 9, "high": 3}}}, "low must be below high"),
        ({"reliability": {"eps1": {"low": 1, "high": 2, "step": 0.3}}}, "multiple of step"),
        ({"reliability": {"eps1": {"low": 1, "hi": 2}}}, "unknown key(s) hi"),
        ({"reliability": {"eps1": {"low": 1}}}, "needs both low and high"),
        ({"reliability": {"eps3": {"low": -1, "high": 2, "log": True}}}, "low > 0"),
        ({}, "names no parameter"),
    ],
)
def test_space_errors_name_the_parameter(data: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=None) as info:
        parse_space(data)
    assert message in str(info.value)


def test_grid_is_the_product_with_the_last_dimension_fastest() -> None:
    space = parse_space(GRID_SPACE)
    assert space.grid() == [
        {"reliability.threshold": t, "spline.n_ctrl": n} for t in (0.6, 0.9) for n in (8, 12, 15)
    ]
    with pytest.raises(ValueError, match="a grid needs choices or a step"):
        parse_space({"reliability": {"eps1": {"low": 1.0, "high": 2.0}}}).grid()


# --- objectives, constraints, split ----------------------------------------------------


def _row(status: str, e: float, kind: str = "simulated", ms: float = 10.0) -> dict[str, Any]:
    return {
        "frame": "f", "kind": kind, "status": status, "e_S_mm": e, "left_mean_px": 1.0,
        "right_mean_px": 3.0, "coverage_left": 0.5, "coverage_right": 1.0, "ms_total": ms,
    }  # fmt: skip


def test_objectives_ignore_failed_frames_except_failure_rate_and_coverage() -> None:
    rows = [_row("ok", 0.2, ms=10), _row("ok", 0.4, ms=30), _row("failed", math.nan, ms=20)]
    m = {name: o.compute(rows) for name, o in OBJECTIVES.items()}
    assert m["e_S"] == pytest.approx(0.3)
    assert m["reprojection"] == pytest.approx(2.0)
    assert m["failure_rate"] == pytest.approx(1 / 3)
    assert m["coverage"] == pytest.approx(0.75 * 2 / 3)
    assert m["time"] == 20


def test_constraints_parse_and_judge() -> None:
    c = Constraint.parse(" failure_rate <= 2% ")
    assert (c.metric, c.op, c.bound) == ("failure_rate", "<=", 0.02)
    assert c.violation(0.01) < 0 < c.violation(0.03)
    assert c.violation(math.nan) == math.inf
    assert Constraint.parse("coverage>=0.9").violation(0.95) < 0
    for bad in ("failure_rate<0.02", "speed<=3", "time<=fast"):
        with pytest.raises(ValueError, match="constraint"):
            Constraint.parse(bad)


def test_holdout_split_depends_on_the_frame_not_on_the_order(dataset: Path) -> None:
    frames = discover(dataset)
    tune_a, held_a = split_frames(frames, 0.34)
    tune_b, held_b = split_frames(frames[::-1], 0.34)
    assert len(held_a) == 1 and {f.id for f in held_a} == {f.id for f in held_b}
    assert {f.id for f in tune_a} | {f.id for f in held_a} == {f.id for f in frames}
    assert {f.id for f in tune_a} == {f.id for f in tune_b}


# --- runs ------------------------------------------------------------------------------


def _grid_cfg(dataset: Path, **kw: Any) -> TuneConfig:
    return TuneConfig(
        dataset=str(dataset),
        space=parse_space(GRID_SPACE),
        mode="grid",
        constraints=(Constraint.parse("failure_rate<=0.5"),),
        prune=False,
        **kw,
    )


def test_grid_runs_every_point_once_and_saves_the_best_as_a_preset(
    dataset: Path, tmp_path: Path
) -> None:
    cfg = _grid_cfg(dataset)
    result = tune(cfg, tmp_path / "store", log=lambda _: None)
    assert sorted(tuple(t.values.values()) for t in result.trials) == sorted(
        tuple(p.values()) for p in cfg.space.grid()
    )
    assert all(len(t.rows) == 3 for t in result.trials)
    best = result.best
    assert best is not None and best is pick_best(result.trials, cfg)
    assert best.objectives["e_S"] == min(t.objectives["e_S"] for t in result.trials if t.feasible)
    path = save_best(result, tmp_path / "presets", "best")
    assert load_preset(path) == params_of(best.values) == result.best_params
    assert save_best(result, tmp_path / "presets", "best") == path  # same setting: no clash
    with pytest.raises(FileExistsError):
        other = params_of({"spline.n_ctrl": 33})
        result.best_params = other
        save_best(result, tmp_path / "presets", "best")
    # the same command again runs nothing new and reports the same trials
    again = tune(cfg, tmp_path / "store", log=lambda _: None)
    assert [(t.number, t.objectives) for t in again.trials] == [
        (t.number, t.objectives) for t in result.trials
    ]
    assert (tmp_path / "store" / "frames.csv").read_text().count("\n") == 1 + 6 * 3


def test_a_store_refuses_a_different_tune(dataset: Path, tmp_path: Path) -> None:
    tune(_grid_cfg(dataset, trials=1), tmp_path / "store", log=lambda _: None)
    with pytest.raises(ValueError, match="different tune.*space"):
        cfg = TuneConfig(
            dataset=str(dataset), space=parse_space({"spline": {"n_ctrl": [8, 9]}}), mode="grid"
        )
        tune(cfg, tmp_path / "store", log=lambda _: None)


def test_objective_without_ground_truth_is_a_clear_error(dataset: Path) -> None:
    frames = discover(dataset)
    real = [replace(f, kind="real", ground_truth=None) for f in frames]
    cfg = TuneConfig(dataset=str(dataset), space=parse_space(GRID_SPACE))
    check_config(cfg, frames)
    with pytest.raises(ValueError, match="needs frames with ground truth"):
        check_config(cfg, real)
    check_config(replace(cfg, objectives=("reprojection", "coverage")), real)
    with pytest.raises(ValueError, match="unknown objective 'speed'"):
        check_config(replace(cfg, objectives=("speed",)), frames)
    with pytest.raises(ValueError, match="a grid needs"):
        spaced = parse_space({"reliability": {"eps1": {"low": 1.0, "high": 2.0}}})
        check_config(replace(cfg, mode="grid", space=spaced), frames)


def test_search_starts_from_the_base_setting_and_is_repeatable(
    dataset: Path, tmp_path: Path
) -> None:
    space = parse_space(
        {
            "reliability": {"eps1": {"low": 4.0, "high": 12.0}},
            "spline": {"n_ctrl": {"low": 10, "high": 20}},
        }
    )
    cfg = TuneConfig(dataset=str(dataset), space=space, trials=3, rungs=1)
    a = tune(cfg, tmp_path / "a", log=lambda _: None)
    b = tune(cfg, tmp_path / "b", log=lambda _: None)
    assert a.trials[0].values == {"reliability.eps1": 8.0, "spline.n_ctrl": 15}  # the defaults
    assert [t.values for t in a.trials] == [t.values for t in b.trials]
    assert [_timeless(t.rows) for t in a.trials] == [_timeless(t.rows) for t in b.trials]


def test_rows_are_identical_in_process_and_on_a_dask_cluster(dataset: Path) -> None:
    frames = discover(dataset)
    params = params_of({"spline.n_ctrl": 12})
    with connect(workers=0) as none:
        local = evaluate_rows(none, frames, params)
    from distributed import Client

    with Client(
        processes=False, n_workers=2, threads_per_worker=1, dashboard_address="127.0.0.1:0"
    ) as c:
        remote = evaluate_rows(c, frames, params)
    assert [r["frame"] for r in remote] == [f.id for f in frames]
    assert _timeless(local) == _timeless(remote)


def test_connect_rejects_both_a_scheduler_and_workers_and_names_an_unreachable_scheduler() -> None:
    with pytest.raises(ValueError, match="either --scheduler"), connect("tcp://127.0.0.1:1", 2):
        pass
    with (
        pytest.raises(OSError, match="cannot reach the Dask scheduler"),
        connect("tcp://127.0.0.1:1", timeout=1),
    ):
        pass


def test_killing_the_tuner_mid_run_loses_no_finished_trial(dataset: Path, tmp_path: Path) -> None:
    space = tmp_path / "space.toml"
    space.write_text(
        "[reliability]\nthreshold = [0.6, 0.75, 0.9]\n[spline]\nn_ctrl = [8, 10, 12, 15]\n"
    )  # 12 trials: time to be killed
    store = tmp_path / "store"
    argv = [sys.executable, "-m", "threadrecon.app.cli", "tune", str(dataset), "--space", str(space),
            "--grid", "--workers", "0", "--no-prune", "--constraint", "failure_rate<=0.5",
            "--store", str(store)]  # fmt: skip
    cfg = replace(_grid_cfg(dataset), space=load_space(space))
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    before: dict[int, Any] = {}
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            if (store / "study.sqlite3").exists():
                try:
                    done = [
                        t
                        for t in open_study(store, cfg, create=False).get_trials()
                        if t.state.is_finished()
                    ]
                except Exception:  # the study is still being created
                    done = []
                if len(done) >= 2:
                    before = {t.number: (t.params, t.values, t.user_attrs["rows"]) for t in done}
                    break
            time.sleep(0.05)
        if proc.poll() is not None:
            err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
            pytest.fail(
                f"the tuner ended (exit {proc.returncode}) before it could be killed:\n{err}"
            )
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    assert 2 <= len(before) < 12
    result = tune(cfg, store, log=lambda _: None)
    after = {t.number: t for t in result.trials}
    for number, (params, values, rows) in before.items():  # every finished trial, unchanged
        assert after[number].values == params
        assert [after[number].objectives["e_S"]] == values
        assert after[number].rows == rows
    assert sorted(tuple(t.values.values()) for t in result.trials) == sorted(
        tuple(p.values()) for p in cfg.space.grid()
    )  # each grid point exactly once: the interrupted one ran again, none twice


def test_evaluate_cli_maps_frames_over_dask_with_the_same_rows(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from threadrecon.app.cli import main

    assert main(["evaluate", str(dataset), "--out", str(tmp_path / "a.csv")]) == 0
    assert main(["evaluate", str(dataset), "--workers", "1", "--out", str(tmp_path / "b.csv")]) == 0
    strip = lambda p: [  # noqa: E731
        {k: v for k, v in zip(head, line, strict=True) if not k.startswith("ms_")}
        for head, *lines in [[row.split(",") for row in p.read_text().splitlines()]]
        for line in lines
    ]
    assert strip(tmp_path / "a.csv") == strip(tmp_path / "b.csv")
    capsys.readouterr()
    assert main(["evaluate", str(dataset), "--workers", "-1"]) == 2
    assert "--workers must be >= 0" in capsys.readouterr().err


def test_default_params_are_the_base_of_every_trial() -> None:
    assert params_of({}) == ReconParams()
    p = params_of({"stereo.window": 7}, base=params_of({"spline.n_ctrl": 9}))
    assert (p.stereo.window, p.spline.n_ctrl) == (7, 9)


def test_several_objectives_are_kept_per_trial_and_the_first_picks_the_best(
    dataset: Path, tmp_path: Path
) -> None:
    cfg = replace(_grid_cfg(dataset, trials=2), objectives=("reprojection", "coverage"), prune=True)
    result = tune(cfg, tmp_path / "store", log=lambda _: None)
    study = open_study(tmp_path / "store", cfg, create=False)
    assert [d.name for d in study.directions] == ["MINIMIZE", "MAXIMIZE"]
    assert [t.values for t in study.trials] == [
        [t.objectives["reprojection"], t.objectives["coverage"]] for t in result.trials
    ]
    assert result.best is min(result.trials, key=lambda t: t.objectives["reprojection"])


def test_a_reader_never_creates_the_schema_the_tuner_creates(dataset: Path, tmp_path: Path) -> None:
    # A reader that opened a new store while the tuner was starting used to create the tables
    # too: two processes' CREATE TABLE raced and the tuner died ("table ... already exists").
    import sqlite3

    cfg = _grid_cfg(dataset, trials=1)
    store = tmp_path / "store"
    store.mkdir()
    with pytest.raises(Exception):  # noqa: B017 - optuna/sqlalchemy: no schema, no study
        open_study(store, cfg, create=False)
    db = store / "study.sqlite3"
    tables = sqlite3.connect(db).execute("SELECT name FROM sqlite_master").fetchall()
    assert tables == [], tables  # the reader left the schema to the tuner
    tune(cfg, store, log=lambda _: None)  # which creates it without a clash
    assert len(open_study(store, cfg, create=False).get_trials()) == 1


def test_a_trial_cut_short_inside_ask_leaves_no_duplicate_grid_point(
    dataset: Path, tmp_path: Path
) -> None:
    cfg = _grid_cfg(dataset, trials=3)
    store = tmp_path / "store"
    tune(replace(cfg, trials=1), store, log=lambda _: None)
    study = open_study(store, cfg)
    study.ask()  # a kill inside ask(): a running trial without its values
    study.ask({"reliability.threshold": cfg.space.dims[0].distribution()})  # with some of them
    lines: list[str] = []
    result = tune(cfg, store, log=lines.append)
    assert "resuming: 2 interrupted trial(s) will run again" in lines
    assert [t.values for t in result.trials] == cfg.space.grid()[:3]


def test_a_reader_holding_the_study_lock_delays_a_trial_instead_of_failing_it(
    dataset: Path, tmp_path: Path
) -> None:
    import sqlite3
    import threading

    store = tmp_path / "store"
    store.mkdir()
    study = open_study(store, _grid_cfg(dataset))
    holder = sqlite3.connect(store / "study.sqlite3", check_same_thread=False)
    holder.execute("BEGIN EXCLUSIVE")  # another process reading/writing the study, for 6 s
    release = threading.Timer(6.0, holder.rollback)  # longer than sqlite's default 5 s wait
    release.start()
    try:
        t0 = time.monotonic()
        trial = study.ask()  # a write: must wait for the lock, not raise "database is locked"
        assert time.monotonic() - t0 >= 5.0
        assert trial.number == 0
    finally:
        release.join()
        holder.close()
