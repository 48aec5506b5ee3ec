"""``threadrecon``: reconstruct one pair, evaluate a dataset, benchmark the stages."""

from __future__ import annotations

import argparse
import json
import math
import socket
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from app.dataset import discover, load_frame
from app.evaluation import evaluate_frame, summarise, write_csv
from app.io import load_calibration, load_pair
from app.presets import resolve_preset
from core.pipeline import STAGES, Pipeline, Reconstruction


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

    r = sub.add_parser("reconstruct", help="reconstruct the thread of one rectified stereo pair")
    r.add_argument("--left", help="left rectified image")
    r.add_argument("--right", help="right rectified image")
    r.add_argument("--stereo", help="side-by-side composite (left half | right half)")
    r.add_argument("--mask", help="optional side-by-side thread mask")
    r.add_argument(
        "--calib", required=True, help="OpenCV FileStorage YAML (K1 D1 K2 D2 R T ImageSize)"
    )
    r.add_argument(
        "--units", choices=("mm", "cm", "m"), help="calibration unit when the file has no Units key"
    )
    r.add_argument("--config", help="preset name (configs/NAME.toml) or path")
    r.add_argument("--out", required=True, help="output JSON")
    r.set_defaults(func=cmd_reconstruct)

    e = sub.add_parser("evaluate", help="evaluate every frame of a dataset folder")
    e.add_argument("dataset", help="folder with simulated/ and/or real/")
    e.add_argument("--config", help="preset name or path")
    e.add_argument("--out", help="CSV with one row per frame")
    e.add_argument(
        "--save-predictions", metavar="DIR", help="write each frame's reconstruction JSON here"
    )
    e.add_argument(
        "--no-masks",
        action="store_true",
        help="withhold the *_mask.png files: segment every frame from its raw images",
    )
    e.set_defaults(func=cmd_evaluate)

    b = sub.add_parser("bench", help="per-stage timings (median, p90) over a dataset")
    b.add_argument(
        "dataset",
        nargs="?",
        default=str(_sample_data()),
        help="dataset folder (default: sample_data)",
    )
    b.add_argument("--config", help="preset name or path")
    b.add_argument("--repeat", type=int, default=3, help="runs per frame (the fastest counts)")
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
    v.add_argument("--configs", help="preset folder (default: the project's configs/)")
    v.set_defaults(func=cmd_serve)

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


def reconstruction_json(rec: Reconstruction) -> dict[str, Any]:
    out: dict[str, Any] = {
        "status": rec.status,
        "error": rec.message,
        "failed_stage": rec.failed_stage,
    }
    out["timings_ms"] = {k: round(v, 3) for k, v in rec.timings_ms.items()}
    if "camera" in rec.runs:
        cam = rec["camera"]
        spline = rec["spline"]
        out.update(
            unit=cam.unit,
            points=cam.points.tolist(),
            control_points=cam.ctrl.tolist(),
            knots=cam.knots.tolist(),
            degree=cam.degree,
            length=cam.length,
            spline_status=spline.status,
            fallback=not spline.ok,
        )
    else:
        out.update(points=None, control_points=None, knots=None, degree=None)
    if "clustering" in rec.runs:
        out["n_keypoints"] = rec["clustering"].count
    if "reliability" in rec.runs:
        out["n_reliable"] = rec["reliability"].count
    return out


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
    params = resolve_preset(args.config)
    pair = load_pair(left=args.left, right=args.right, stereo=args.stereo, mask=args.mask)
    calib = load_calibration(args.calib, unit=args.units)
    out = Path(args.out)
    try:
        rec = Pipeline(pair, calib).run(params)
    except ValueError as exc:  # a pair that does not fit its calibration
        _write_json(out, {"status": "failed", "error": str(exc), "points": None})
        raise
    data = reconstruction_json(rec)
    _write_json(out, data)
    if rec.status != "ok":
        print(f"threadrecon: reconstruction failed: {rec.message}", file=sys.stderr)
        return 1
    print(
        f"ok: {len(data['points'])} points, length {data['length']:.2f} {data['unit']}, "
        f"{sum(rec.timings_ms.values()):.0f} ms -> {out}"
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
    if getattr(args, "no_masks", False):
        frames = [replace(f, mask=None) for f in frames]
    rows = []
    for i, frame in enumerate(frames):
        _progress(i, len(frames), frame.id)
        row, rec = evaluate_frame(frame, params)
        rows.append(row)
        if args.save_predictions and rec is not None:
            _write_json(Path(args.save_predictions) / f"{frame.id}.json", reconstruction_json(rec))
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
    with socket.socket() as probe:  # a taken port is a one-line error, not uvicorn's exit
        try:
            probe.bind((args.host, args.port))
        except OSError as exc:
            raise UserError(
                f"cannot listen on {args.host}:{args.port} ({exc.strerror}): choose another --port"
            ) from None
    config = ServerConfig(
        data_dir=root,
        host=args.host,
        port=args.port,
        viser_port=viser_port,
        db_path=Path(args.db) if args.db else None,
        configs_dir=Path(args.configs) if args.configs else None,
    )
    try:
        serve(config)
    except StoreError as exc:  # an unusable database stops the start, and nothing is written
        raise UserError(str(exc)) from None
    return 0


# --- bench -------------------------------------------------------------------------------


def cmd_bench(args: argparse.Namespace) -> int:
    params = resolve_preset(args.config)
    frames = discover(args.dataset)
    if args.repeat < 1:
        raise UserError("--repeat must be >= 1")
    per_stage: dict[str, list[float]] = {s: [] for s in STAGES}
    totals, reruns = [], []
    changed = replace(params, spline=replace(params.spline, n_ctrl=params.spline.n_ctrl - 1))
    for frame in frames:
        pair, calib, _ = load_frame(frame)
        best: dict[str, float] | None = None
        best_rerun = math.inf
        for _ in range(args.repeat):
            pipe = Pipeline(pair, calib)
            rec = pipe.run(params)
            if rec.failed_stage:
                break
            t = rec.timings_ms
            if best is None or sum(t.values()) < sum(best.values()):
                best = t
            t0 = time.perf_counter()
            pipe.run(changed)  # only the spline and camera stages re-run
            best_rerun = min(best_rerun, 1000 * (time.perf_counter() - t0))
        if best is None:
            print(f"skipped {frame.id}: {rec.message}", file=sys.stderr)
            continue
        for s in STAGES:
            per_stage[s].append(best.get(s, 0.0))
        totals.append(sum(best.values()))
        reruns.append(best_rerun)
    if not totals:
        raise UserError("no frame could be reconstructed")
    print(f"{len(totals)} frames of {args.dataset}, best of {args.repeat} runs each, ms per frame")
    print(f"{'stage':<14}{'median':>10}{'p90':>10}")
    for s in STAGES:
        v = np.array(per_stage[s])
        print(f"{s:<14}{np.median(v):10.2f}{np.percentile(v, 90):10.2f}")
    print(f"{'total':<14}{np.median(totals):10.2f}{np.percentile(totals, 90):10.2f}")
    print(
        f"{'spline rerun':<14}{np.median(reruns):10.2f}{np.percentile(reruns, 90):10.2f}"
        "   (n_ctrl changed: spline + camera stages only)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
