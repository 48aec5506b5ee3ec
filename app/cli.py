"""``threadrecon``: reconstruct one pair, evaluate a dataset, benchmark the stages."""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from app.dataset import Frame, discover, frame_inputs, frame_rectification, load_frame
from app.evaluation import evaluate_frame, summarise, write_csv
from app.export import result_json
from app.io import load_calibration
from app.presets import resolve_preset, validate
from app.python_api import reconstruct
from core.pipeline import STAGES, Pipeline, ReconParams, Reconstruction, StageError
from core.tracking import TrackParams


class UserError(Exception):
    """A problem with the user's input: reported in one line, no traceback."""


def limit_blas_threads() -> None:
    """One BLAS thread: the core's matrices are small (tens of control points), and OpenBLAS's
    spinning worker threads, sharing two cores with a browser or another job, made a 10 ms
    spline re-run take 300 ms (scripts/bench_latency.py with Chromium on the same machine)."""
    threadpool_limits(limits=1, user_api="blas")


def main(argv: list[str] | None = None) -> int:
    limit_blas_threads()
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        return int(args.func(args))
    except (UserError, ValueError, OSError) as exc:
        print(f"threadrecon: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("threadrecon: interrupted", file=sys.stderr)
        return 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="threadrecon", description=__doc__)
    sub = parser.add_subparsers(dest="command")

    r = sub.add_parser(
        "reconstruct",
        help="reconstruct the thread of one stereo pair (raw pairs are rectified first)",
    )
    r.add_argument("--left", help="left image (rectified, or raw with its calibration)")
    r.add_argument("--right", help="right image")
    r.add_argument("--stereo", help="side-by-side composite (left half | right half)")
    r.add_argument("--mask", help="optional side-by-side thread mask")
    r.add_argument("--mask-left", help="optional left thread mask (with --mask-right)")
    r.add_argument("--mask-right", help="optional right thread mask")
    r.add_argument(
        "--calib",
        required=True,
        help="OpenCV FileStorage YAML (K1 D1 K2 D2 R T ImageSize), Kalibr camchain.yaml, "
        "or the left ROS camera_info YAML (with --calib-right)",
    )
    r.add_argument("--calib-right", help="the right ROS camera_info YAML")
    r.add_argument(
        "--units",
        choices=("mm", "cm", "m"),
        help="calibration length unit when the file does not say "
        "(default: mm for OpenCV files, m for ROS and Kalibr)",
    )
    r.add_argument(
        "--frame",
        choices=("left", "left_rectified"),
        default="left",
        help="frame of the output: the left camera's own (default) or the left rectified one",
    )
    r.add_argument("--config", help="preset name (configs/NAME.toml) or path")
    r.add_argument("--out", required=True, help="output JSON (docs/result.schema.json)")
    r.add_argument("--ply", help="also write the curve as a PLY polyline (vertices + edges)")
    r.set_defaults(func=cmd_reconstruct)

    e = sub.add_parser("evaluate", help="evaluate every frame of a dataset folder")
    e.add_argument("dataset", help="folder with simulated/ and/or real/")
    e.add_argument("--config", help="preset name or path")
    e.add_argument("--out", help="CSV with one row per frame")
    e.add_argument(
        "--save-predictions", metavar="DIR", help="write each frame's reconstruction JSON here"
    )
    e.set_defaults(func=cmd_evaluate)

    b = sub.add_parser(
        "bench", help="per-stage timings (median, p90) and peak memory over any data folder"
    )
    b.add_argument(
        "dataset",
        nargs="?",
        default=str(_sample_data()),
        help="dataset folder, or a folder of side-by-side pairs with a calibration.yaml "
        "(default: sample_data)",
    )
    b.add_argument("--config", help="preset name or path")
    b.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="STAGE.NAME=VALUE",
        help="override one parameter of the preset (repeatable), e.g. stereo.z_near_mm=40",
    )
    b.add_argument(
        "--repeat", type=int, default=3, help="runs per frame; a frame counts its median (>= 1)"
    )
    b.add_argument("--limit", type=int, default=None, help="at most this many frames")
    b.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="wall time (default), or this thread's CPU time: steadier on a loaded machine",
    )
    b.set_defaults(func=cmd_bench)

    v = sub.add_parser("serve", help="start the browser debugger on a data folder")
    v.add_argument(
        "dataset", nargs="?", default=str(_sample_data()), help="data folder (default: sample_data)"
    )
    v.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    v.add_argument("--port", type=int, default=8000, help="port of the page and API (default 8000)")
    v.add_argument(
        "--viser-port",
        type=int,
        default=None,
        help="port of the 3D view (default: --port + 1; the next free one if taken)",
    )
    v.add_argument(
        "--db", help="ratings and evaluations database (default: DATASET/threadrecon.sqlite3)"
    )
    v.add_argument(
        "--configs",
        help="folder of the user's presets (default: the platform's user data folder; "
        "the built-in presets are read-only)",
    )
    v.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="URL",
        help="also accept requests from this origin (http://host:port) and its host name; "
        "repeatable; '*' accepts any (default: loopback names only)",
    )
    v.add_argument(
        "--idle-timeout",
        type=float,
        default=600.0,
        metavar="S",
        help="close a session without a 3D view after S seconds unused (default 600)",
    )
    v.add_argument(
        "--max-body",
        type=int,
        default=4 * 1024 * 1024,
        metavar="BYTES",
        help="largest request body accepted (default 4 MiB; larger: 413)",
    )
    v.set_defaults(func=cmd_serve)

    t = sub.add_parser(
        "track",
        help="reconstruct and track the thread over a stereo video, image folder or ROS bag",
    )
    t.add_argument(
        "source",
        help="side-by-side video, left video (with --right), image folder, ROS1 .bag or ROS2 bag folder",
    )
    t.add_argument("--right", help="right-view video when SOURCE is the left one")
    t.add_argument(
        "--calib",
        help="OpenCV FileStorage YAML (default: the source's own: calibration.yaml in the "
        "folder, camera_info in a bag)",
    )
    t.add_argument(
        "--units", choices=("mm", "cm", "m"), help="calibration unit when the file has no Units key"
    )
    t.add_argument("--config", help="preset name (configs/NAME.toml) or path")
    t.add_argument("--out", required=True, help="folder: frames/<frame>.json and summary.csv")
    t.add_argument("--no-tracking", action="store_true", help="single-frame reconstructions only")
    t.add_argument("--left-topic", help="left image topic of a bag (default: the one named left)")
    t.add_argument("--right-topic", help="right image topic of a bag")
    t.add_argument("--limit", type=int, help="stop after this many frames")
    t.add_argument(
        "--record",
        metavar="FILE.html",
        help="also save the 3D view of the whole sequence as a recording that opens without a server",
    )
    t.set_defaults(func=cmd_track)

    try:
        from app import generate
    except ImportError:  # the generator ships with the synthetic-data module
        generate = None
    if generate is not None:
        generate.add_parser(sub)
    return parser


def _sample_data() -> Path:
    return Path(__file__).resolve().parent.parent / "sample_data"


# --- reconstruct -------------------------------------------------------------------------


def _write_json(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, allow_nan=False, default=_json_default))
    tmp.replace(path)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def cmd_reconstruct(args: argparse.Namespace) -> int:
    out = Path(args.out)
    result = reconstruct(
        args.left,
        args.right,
        args.calib,
        stereo=args.stereo,
        mask=args.mask,
        mask_left=args.mask_left,
        mask_right=args.mask_right,
        calib_right=args.calib_right,
        units=args.units,
        params=args.config,  # a preset name or path; None: the default preset
        frame=args.frame,
    )
    data = result.to_json()
    _write_json(out, data)
    if args.ply and result.points is not None:
        ply = Path(args.ply)
        ply.parent.mkdir(parents=True, exist_ok=True)
        ply.write_bytes(result.to_ply())
    if not result.ok:
        print(f"threadrecon: reconstruction failed: {'; '.join(result.reasons)}", file=sys.stderr)
        return 1
    print(
        f"ok: {len(data['points'])} points, length {data['length']:.2f} {data['unit']}, "
        f"frame {data['frame']}, {sum(result.timings_ms.values()):.0f} ms -> {out}"
    )
    return 0


# --- evaluate ----------------------------------------------------------------------------


def _progress(i: int, n: int, label: str) -> None:
    if not sys.stderr.isatty():  # logs get no carriage-return bar
        return
    width = 30
    done = int(width * i / max(n, 1))
    sys.stderr.write(f"\r[{'#' * done}{'.' * (width - done)}] {i}/{n} {label[:40]:<40}")
    if i == n:
        sys.stderr.write("\n")
    sys.stderr.flush()


def cmd_evaluate(args: argparse.Namespace) -> int:
    params = resolve_preset(args.config)
    frames = discover(args.dataset)
    rows = []
    for i, frame in enumerate(frames):
        _progress(i, len(frames), frame.id)
        row, rec = evaluate_frame(frame, params)
        rows.append(row)
        if args.save_predictions and rec is not None:
            pred = result_json(
                rec, frame_rectification(frame), "left", args.config or "default",
                frame_inputs(frame),
            )  # fmt: skip
            _write_json(Path(args.save_predictions) / f"{frame.id}.json", pred)
    _progress(len(frames), len(frames), "done")
    if args.out:
        write_csv(Path(args.out), rows)
    for line in summarise(rows):
        print(line)
    failed = sum(r["status"] != "ok" for r in rows)
    if failed:
        print(f"threadrecon: {failed} of {len(rows)} frames failed", file=sys.stderr)
        return 1
    return 0


# --- track -------------------------------------------------------------------------------


def cmd_track(args: argparse.Namespace) -> int:
    from app.sequence import SequenceError, open_sequence, track_sequence
    from app.track_report import frame_row, recorded_frame, summary_lines, tracked_json

    params = resolve_preset(args.config)
    if args.limit is not None and args.limit < 1:
        raise UserError(f"--limit must be >= 1, got {args.limit}")
    try:
        seq = open_sequence(args.source, args.right, args.left_topic, args.right_topic)
    except SequenceError as exc:
        raise UserError(str(exc)) from None
    if args.calib is not None:
        calib = load_calibration(args.calib, unit=args.units)
    elif seq.calibration is not None:
        calib = seq.calibration
    else:
        raise UserError(f"{args.source} carries no calibration: give --calib")
    out = Path(args.out)
    track = TrackParams(enabled=not args.no_tracking)
    n = seq.count if args.limit is None else min(seq.count or args.limit, args.limit)
    rows: list[dict[str, Any]] = []
    recorded: list[Any] = []
    previous = None
    t0 = time.perf_counter()
    for k, tf in enumerate(track_sequence(seq, calib, params, track), start=1):
        row = frame_row(tf, calib, previous)
        rows.append(row)
        previous = tf
        data = result_json(tf.single)
        data.update(tracked_json(tf, row))
        _write_json(out / "frames" / f"{tf.frame.name}.json", data)
        if args.record:
            recorded.append(recorded_frame(tf))
        rate = k / (time.perf_counter() - t0)
        _track_progress(k, n, tf.frame.name, rate)
        if args.limit is not None and k >= args.limit:
            break
    if not rows:
        raise UserError(f"{args.source}: no frames")
    elapsed = time.perf_counter() - t0
    write_csv(out / "summary.csv", rows)
    for line in summary_lines(rows, elapsed):
        print(line)
    if args.record:
        from app.recording import save_recording

        save_recording(recorded, args.record, baseline=calib.baseline)
        print(f"recording of {len(recorded)} frames -> {args.record} (opens without a server)")
    lost = sum(r["curve"] == "none" for r in rows)
    if lost:
        print(f"threadrecon: {lost} of {len(rows)} frames have no curve", file=sys.stderr)
        return 1
    return 0


def _track_progress(k: int, n: int | None, name: str, rate: float) -> None:
    total = f"/{n}" if n else ""
    if sys.stderr.isatty():
        sys.stderr.write(f"\r[{k}{total}] {name[:30]:<30} {rate:6.2f} frames/s")
        if n is not None and k == n:
            sys.stderr.write("\n")
    elif k == 1 or k % 10 == 0 or k == n:
        sys.stderr.write(f"[{k}{total}] {name} {rate:.2f} frames/s\n")
    sys.stderr.flush()


# --- serve -------------------------------------------------------------------------------


def cmd_serve(args: argparse.Namespace) -> int:
    from app.ratings import StoreError
    from app.server import ServerConfig, serve

    root = Path(args.dataset)
    discover(root)  # a wrong folder is a one-line error, before anything starts
    for name, port in (("--port", args.port), ("--viser-port", args.viser_port)):
        if port is not None and not 0 < port < 65536:
            raise UserError(f"{name} must be in 1..65535, got {port}")
    viser_port = args.viser_port if args.viser_port is not None else args.port + 1
    if not args.idle_timeout > 0:
        raise UserError(f"--idle-timeout must be > 0, got {args.idle_timeout}")
    if args.max_body < 1:
        raise UserError(f"--max-body must be >= 1, got {args.max_body}")
    family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    # SO_REUSEADDR: a restart right after Ctrl-C binds despite the old connections in
    # TIME_WAIT; the socket is handed to uvicorn, so a taken port is a one-line error here.
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.host, args.port))
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        raise UserError(
            f"cannot listen on {args.host}:{args.port} ({exc.strerror}): choose another --port"
        ) from None
    try:
        from app.api.guard import Policy

        Policy(args.allow_origin)
    except ValueError as exc:
        sock.close()
        raise UserError(str(exc)) from None
    config = ServerConfig(
        data_dir=root,
        host=args.host,
        port=args.port,
        viser_port=viser_port,
        db_path=Path(args.db) if args.db else None,
        configs_dir=Path(args.configs) if args.configs else None,
        allow_origins=tuple(args.allow_origin),
        idle_timeout_s=args.idle_timeout,
        max_body_bytes=args.max_body,
    )
    code = 0
    try:
        serve(config, sock)
    except StoreError as exc:  # an unusable database stops the start, and nothing is written
        raise UserError(str(exc)) from None
    except KeyboardInterrupt:  # uvicorn re-raises Ctrl-C once it has stopped cleanly
        print("threadrecon: interrupted", file=sys.stderr)
        code = 130
    # Stopped cleanly: the database is closed and viser stopped. Skip the interpreter's
    # teardown (seconds of freeing a large heap on a busy machine) so that Ctrl-C is quick.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


# --- bench -------------------------------------------------------------------------------


def cmd_bench(args: argparse.Namespace) -> int:
    params = _with_overrides(resolve_preset(args.config), args.set)
    frames = _bench_frames(Path(args.dataset))
    if args.limit is not None:
        if args.limit < 1:
            raise UserError("--limit must be >= 1")
        frames = frames[: args.limit]
    if args.repeat < 1:
        raise UserError("--repeat must be >= 1")
    per_stage: dict[str, list[float]] = {s: [] for s in STAGES}
    totals, reruns = [], []
    changed = replace(params, spline=replace(params.spline, n_ctrl=params.spline.n_ctrl - 1))
    sizes: set[str] = set()
    warmup_ms: float | None = None
    clock = time.thread_time if args.clock == "cpu" else time.perf_counter
    for frame in frames:
        pair, calib, _ = load_frame(frame)
        if warmup_ms is None:  # first call in the process: loads the compiled kernels
            t0 = time.perf_counter()
            Pipeline(pair, calib).run(params)
            warmup_ms = 1000 * (time.perf_counter() - t0)
        runs: list[dict[str, float]] = []
        frame_reruns: list[float] = []
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
        "   (n_ctrl changed: spline + camera stages only)"
    )
    print(f"first run in this process (loads compiled kernels): {warmup_ms:.0f} ms")
    print(f"peak RSS: {_peak_rss_mb():.0f} MB")
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


def _with_overrides(params: ReconParams, items: list[str]) -> ReconParams:
    """``STAGE.NAME=VALUE`` overrides on top of a preset, checked like a preset."""
    if not items:
        return params
    data = params.to_dict()
    for item in items:
        key, sep, text = item.partition("=")
        stage, dot, name = key.strip().partition(".")
        if not (sep and dot and name):
            raise UserError(f"--set expects STAGE.NAME=VALUE, got {item!r}")
        if stage not in data:
            raise UserError(f"--set {item!r}: unknown stage {stage!r}")
        data[stage][name] = _parse_value(text.strip())
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


def _peak_rss_mb() -> float:
    """Peak resident memory of this process, MB (Linux reports KB, macOS bytes)."""
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


if __name__ == "__main__":
    sys.exit(main())
