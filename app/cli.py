"""``threadrecon``: reconstruct one pair, evaluate a dataset, benchmark the stages."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable
from pathlib import Path

from threadpoolctl import threadpool_limits

from threadrecon.app.bench import cmd_bench
from threadrecon.app.errors import UserError
from threadrecon.app.export import software_version, write_json
from threadrecon.app.python_api import reconstruct
from threadrecon.app.resources import sample_data_dir


def main(argv: list[str] | None = None) -> int:
    # One BLAS thread for the whole process (each stage also limits itself): the matrices are
    # small, and OpenBLAS's spinning threads beside a browser made a 10 ms re-run take 300 ms.
    threadpool_limits(limits=1, user_api="blas")
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


def _lazy(module: str, name: str) -> Callable[[argparse.Namespace], int]:
    """The command ``module.name``, imported when it runs: the server (viser, FastAPI), the
    tuner (Optuna) and Dask load only for the commands that use them."""

    def command(args: argparse.Namespace) -> int:
        return getattr(importlib.import_module(module), name)(args)

    return command


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="threadrecon", description=__doc__)
    parser.add_argument("--version", action="version", version=f"threadrecon {software_version()}")
    sub = parser.add_subparsers(dest="command")

    r = sub.add_parser(
        "reconstruct",
        help="reconstruct the thread of one stereo pair (raw pairs are rectified first)",
        description="Reconstruct one pair and write its JSON (always, with status and reasons). "
        "Exit code: 0 ok, 1 failed, 3 suspect (the check stage doubts the curve), 2 bad input.",
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
    e.add_argument(
        "dataset",
        nargs="?",
        default=str(sample_data_dir()),
        help="data folder, any layout (default: the bundled sample)",
    )
    e.add_argument("--config", help="preset name or path")
    e.add_argument("--out", help="CSV with one row per frame")
    e.add_argument(
        "--save-predictions", metavar="DIR", help="write each frame's reconstruction JSON here"
    )
    _add_dask_arguments(e, default_help="default: in this process, one frame after another")
    e.add_argument(
        "--no-masks",
        action="store_true",
        help="withhold the *_mask.png files: segment every frame from its raw images",
    )
    e.add_argument(
        "--db",
        help="apply the user's mask corrections stored in this database (default: the one "
        "`serve` uses for DATASET, if it exists)",
    )
    e.add_argument(
        "--no-corrections", action="store_true", help="ignore the stored mask corrections"
    )
    e.set_defaults(func=_lazy("threadrecon.app.evaluate_command", "cmd_evaluate"))

    b = sub.add_parser(
        "bench", help="per-stage timings (median, p90) and peak memory over any data folder"
    )
    b.add_argument(
        "dataset",
        nargs="?",
        default=str(sample_data_dir()),
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

    t = sub.add_parser(
        "tune",
        help="grid or search (Optuna TPE) over parameters of the stage table, frames on Dask",
        description="Tune parameters on a dataset: every trial on every frame, kept in a store "
        "that survives a kill (run the same command again to resume).",
    )
    t.add_argument("dataset", help="folder with simulated/ and/or real/")
    t.add_argument(
        "--space", required=True, help="TOML: [stage] name = [choices] or {low, high[, step]}"
    )
    t.add_argument(
        "--objective",
        action="append",
        metavar="NAME",
        help="e_S, reprojection, coverage, failure_rate or time; repeat for several (the first "
        "picks the best trial; default e_S)",
    )
    t.add_argument(
        "--constraint",
        action="append",
        metavar="EXPR",
        help="e.g. 'failure_rate<=0.02' or 'time<=80'; repeatable (default: failure_rate<=0.02)",
    )
    t.add_argument("--grid", action="store_true", help="every point of the space's grid, in order")
    t.add_argument(
        "--trials", type=int, help="trials in the store when done (default: 50, grid: its size)"
    )
    t.add_argument(
        "--holdout",
        type=float,
        default=0.0,
        help="fraction of frames held back from tuning; best and base are compared on them",
    )
    t.add_argument("--seed", type=int, default=0, help="sampler and frame-order seed (default 0)")
    t.add_argument(
        "--rungs", type=int, default=4, help="parts of the frames after which a trial may be pruned"
    )
    t.add_argument("--no-prune", action="store_true", help="evaluate every trial on every frame")
    t.add_argument("--config", help="base preset the space varies (default: the defaults)")
    t.add_argument("--store", required=True, help="folder of the trial store (created; resumable)")
    t.add_argument("--save-preset", metavar="DIR", help="save the best setting as a preset here")
    t.add_argument("--preset-name", help="its name (default: tuned-<hash of the setting>)")
    t.add_argument("--force", action="store_true", help="replace an existing preset of that name")
    _add_dask_arguments(t, default_help="default: one process per CPU")
    t.set_defaults(func=_lazy("threadrecon.app.tune.command", "cmd_tune"))

    v = sub.add_parser("serve", help="start the browser debugger on a data folder")
    v.add_argument(
        "dataset",
        nargs="?",
        default=str(sample_data_dir()),
        help="data folder (default: sample_data)",
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
        "--db",
        help="ratings and evaluations database (default: DATASET/threadrecon.sqlite3; for the "
        "bundled sample, sample_data.sqlite3 in the user data folder)",
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
    v.set_defaults(func=_lazy("threadrecon.app.server", "cmd_serve"))

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
    t.add_argument(
        "--no-masks",
        action="store_true",
        help="withhold an image folder's *_mask.png files: segment every frame from its images",
    )
    t.add_argument("--left-topic", help="left image topic of a bag (default: the one named left)")
    t.add_argument("--right-topic", help="right image topic of a bag")
    t.add_argument("--limit", type=int, help="stop after this many frames")
    t.add_argument(
        "--record",
        metavar="FILE.html",
        help="also save the 3D view of the whole sequence as a recording that opens without a server",
    )
    t.set_defaults(func=_lazy("threadrecon.app.track_report", "cmd_track"))

    try:
        from threadrecon.app import generate
    except ImportError:  # the generator ships with the synthetic-data module
        generate = None
    if generate is not None:
        generate.add_parser(sub)
    return parser


# --- reconstruct -------------------------------------------------------------------------


EXIT_OK, EXIT_FAILED, EXIT_SUSPECT = 0, 1, 3  # reconstruct's exit code by check status


def cmd_reconstruct(args: argparse.Namespace) -> int:
    out = Path(args.out)
    try:
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
    except ValueError as exc:  # unreadable input or a pair that does not fit its calibration
        write_json(
            out, {"status": "failed", "reasons": [str(exc)], "error": str(exc), "points": None}
        )
        raise
    data = result.to_json()
    write_json(out, data)
    if args.ply and result.points is not None:
        ply = Path(args.ply)
        ply.parent.mkdir(parents=True, exist_ok=True)
        ply.write_bytes(result.to_ply())
    if result.status == "failed":
        print(
            f"threadrecon: reconstruction failed: {'; '.join(result.reasons)} -> {out}",
            file=sys.stderr,
        )
        return EXIT_FAILED
    summary = (
        f"{len(data['points'])} points, length {data['length']:.2f} {data['unit']}, "
        f"frame {data['frame']}, score {data['rating']:.2f}/5 (class {data['score']}), "
        f"{sum(result.timings_ms.values()):.0f} ms -> {out}"
    )
    if result.status == "suspect":
        print(f"suspect: {summary}", file=sys.stderr)
        for reason in result.reasons:
            print(f"  - {reason}", file=sys.stderr)
        return EXIT_SUSPECT
    print(f"ok: {summary}")
    return EXIT_OK


def _add_dask_arguments(p: argparse.ArgumentParser, default_help: str) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run frames on an existing Dask cluster (`dask scheduler`), e.g. tcp://host:8786",
    )
    g.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help=f"run frames on a local Dask cluster of N processes (0: in this process; {default_help})",
    )


if __name__ == "__main__":
    sys.exit(main())
