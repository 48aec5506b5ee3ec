"""``threadrecon bench``: per-stage times (median and p90 over frames), peak memory."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app import heap
from threadrecon.app.dataset import Frame, discover, load_frame
from threadrecon.app.errors import UserError
from threadrecon.app.presets import resolve_preset, validate
from threadrecon.core.compiled import backends, built_here
from threadrecon.core.pipeline import STAGES, Pipeline, ReconParams, Reconstruction, StageError


def cmd_bench(args: argparse.Namespace) -> int:
    params = with_overrides(resolve_preset(args.config), args.set)
    frames = _bench_frames(Path(args.dataset))
    if args.limit is not None:
        if args.limit < 1:
            raise UserError("--limit must be >= 1")
        frames = frames[: args.limit]
    if args.repeat < 1:
        raise UserError("--repeat must be >= 1")
    per_stage: dict[str, list[float]] = {s: [] for s in STAGES}
    totals, reruns, solver_reruns = [], [], []
    changed = replace(params, spline=replace(params.spline, n_ctrl=params.spline.n_ctrl - 1))
    # a solver parameter (the knots, H and its bounds unchanged: the spline's set-up is reused)
    weighted = replace(
        params, spline=replace(params.spline, data_weight=params.spline.data_weight + 1.0)
    )
    sizes: set[str] = set()
    warmup_ms: float | None = None
    clock = time.thread_time if args.clock == "cpu" else time.perf_counter
    for frame in frames:
        heap.release_memory()  # the last frame's garbage freed and handed back: one frame's peak
        pair, calib, _ = load_frame(frame)
        if warmup_ms is None:  # first call in the process: loads the compiled kernels
            t0 = time.perf_counter()
            Pipeline(pair, calib).run(params)
            warmup_ms = 1000 * (time.perf_counter() - t0)
        runs: list[dict[str, float]] = []
        frame_reruns: list[float] = []
        frame_solver_reruns: list[float] = []
        rec = None
        for _ in range(args.repeat):
            pipe = rec = None  # free the previous run's results first: one frame in memory
            pipe = Pipeline(pair, calib)
            rec, timings = _timed_run(pipe, params, clock)
            if rec.failed_stage:
                break
            runs.append(timings)
            _, re_timings = _timed_run(pipe, changed, clock)  # spline and camera re-run
            frame_reruns.append(sum(re_timings.values()))
            _, re_timings = _timed_run(pipe, weighted, clock)
            frame_solver_reruns.append(sum(re_timings.values()))
        message = rec.message if rec else "no run"
        pipe = rec = None
        if not runs:
            print(f"skipped {frame.id}: {message}", file=sys.stderr)
            continue
        h, w = pair.shape
        sizes.add(f"{w}x{h}")
        for s in STAGES:
            per_stage[s].append(float(np.median([r.get(s, 0.0) for r in runs])))
        totals.append(float(np.median([sum(r.values()) for r in runs])))
        reruns.append(float(np.median(frame_reruns)))
        solver_reruns.append(float(np.median(frame_solver_reruns)))
    if not totals:
        raise UserError("no frame could be reconstructed")
    print(
        f"{len(totals)} frames ({', '.join(sorted(sizes))}) of {args.dataset}, "
        f"median of {args.repeat} runs per frame, {args.clock} ms; median and p90 over frames"
    )
    print(f"{'stage':<14}{'median':>10}{'p90':>10}")
    for s in STAGES:
        v = np.array(per_stage[s])
        print(f"{s:<14}{np.median(v):10.2f}{np.percentile(v, 90):10.2f}")
    print(f"{'total':<14}{np.median(totals):10.2f}{np.percentile(totals, 90):10.2f}")
    print(
        f"{'spline rerun':<14}{np.median(reruns):10.2f}{np.percentile(reruns, 90):10.2f}"
        "   (n_ctrl changed: the stages from spline on)"
    )
    print(
        f"{'solver rerun':<14}{np.median(solver_reruns):10.2f}"
        f"{np.percentile(solver_reruns, 90):10.2f}"
        "   (data_weight changed: the stages from spline on, the spline's set-up reused)"
    )
    print(f"first run in this process (loads compiled kernels): {warmup_ms:.0f} ms")
    print(f"peak RSS: {_peak_rss_mb():.0f} MB{_kernel_note()}")
    return 0


def _timed_run(
    pipe: Pipeline, params: ReconParams, clock: Callable[[], float]
) -> tuple[Reconstruction, dict[str, float]]:
    """One pipeline run, each stage timed with ``clock`` (cached stages count 0)."""
    timings: dict[str, float] = {}
    t0 = clock()
    try:
        for run in pipe.stages(params):
            t1 = clock()
            timings[run.stage] = 0.0 if run.cached else 1000 * (t1 - t0)
            t0 = t1
    except StageError:
        pass  # pipe.run below reports the failed stage
    return pipe.run(params), timings


def parse_overrides(items: list[str]) -> dict[str, dict[str, Any]]:
    """``STAGE.NAME=VALUE`` items (``--set``) as ``{stage: {name: value}}``; a malformed item
    or an unknown stage is a UserError naming it (the values are checked where they are used)."""
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        key, sep, text = item.partition("=")
        stage, dot, name = key.strip().partition(".")
        if not (sep and dot and name):
            raise UserError(f"--set expects STAGE.NAME=VALUE, got {item!r}")
        if stage not in STAGES:
            raise UserError(f"--set {item!r}: unknown stage {stage!r}")
        out.setdefault(stage, {})[name] = _parse_value(text.strip())
    return out


def with_overrides(params: ReconParams, items: list[str]) -> ReconParams:
    """``STAGE.NAME=VALUE`` overrides on top of a preset, checked like a preset."""
    if not items:
        return params
    data = params.to_dict()
    for stage, values in parse_overrides(items).items():
        data[stage].update(values)
    return validate(data)


def _parse_value(text: str) -> Any:
    if text.lower() in ("none", "null", ""):
        return None
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def _bench_frames(root: Path) -> list[Frame]:
    """Frames of a dataset folder, or else of a plain folder of side-by-side pairs next to one
    calibration YAML (e.g. one group folder written by ``generate``)."""
    if not root.is_dir():
        raise UserError(f"{root}: dataset folder not found")
    if (root / "simulated").is_dir() or (root / "real").is_dir():
        return discover(root)
    calibs = sorted(root.glob("*.yaml")) + sorted(root.glob("*.yml"))
    images = [
        p
        for p in sorted(root.iterdir())
        if p.suffix.lower() in (".png", ".jpg", ".jpeg") and not p.stem.endswith("_mask")
    ]
    if len(calibs) != 1 or not images:
        raise UserError(
            f"{root}: no dataset layout (simulated/, real/) and not a folder of side-by-side "
            "pairs with exactly one calibration .yaml"
        )
    return [
        Frame(
            id=p.stem,
            kind="real",
            calibration=calibs[0],
            stereo=p,
            mask=m if (m := p.with_name(p.stem + "_mask.png")).exists() else None,
        )
        for p in images
    ]


def _kernel_note() -> str:
    """What the peak RSS includes besides the runs: compiling the kernels, or numba's JIT."""
    if built_here():
        return " (includes compiling the kernels in this process: run again for the steady figure)"
    if "jit" in backends().values():
        return " (numba's JIT kernels, ~100 MB of it: core/compiled.py)"
    return ""


def _peak_rss_mb() -> float:
    """Peak resident memory of this process, MB (Linux reports KB, macOS bytes)."""
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024
