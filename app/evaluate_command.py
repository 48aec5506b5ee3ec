"""``threadrecon evaluate``: every frame of a dataset folder, with the user's corrections.

The rows and the summary are :mod:`app.evaluation`'s, computed in this process or on a Dask
cluster (:mod:`app.distributed`). The mask corrections the user made in the debugger are kept in
the dataset's database (the one ``serve`` uses, or ``--db``); every frame applies its own, as the
debugger's runs do, and its row says how many (``corrections``). ``--no-corrections`` ignores
them. A missing database is no error: then there are none. Nothing is written to it.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from threadrecon.app.corrections import read_active, with_corrections
from threadrecon.app.dataset import Frame, discover, frame_inputs, frame_rectification
from threadrecon.app.errors import UserError
from threadrecon.app.evaluation import summarise, write_csv
from threadrecon.app.export import result_json, write_json
from threadrecon.app.presets import resolve_preset
from threadrecon.app.ratings import StoreError
from threadrecon.app.resources import default_db


def _progress(i: int, n: int, label: str) -> None:
    if not sys.stderr.isatty():  # logs get no carriage-return bar
        return
    width = 30
    done = int(width * i / max(n, 1))
    sys.stderr.write(f"\r[{'#' * done}{'.' * (width - done)}] {i}/{n} {label[:40]:<40}")
    if i == n:
        sys.stderr.write("\n")
    sys.stderr.flush()


def corrected(frames: list[Frame], dataset: Path, db: str | None) -> list[Frame]:
    """``frames`` with their stored corrections from ``db`` (default: the dataset's database
    when it exists). A database named by ``--db`` must exist."""
    path = Path(db) if db else default_db(dataset)
    if not path.is_file():
        if db:
            raise FileNotFoundError(f"--db {db}: no such database file")
        return frames
    try:
        active = read_active(path)
    except StoreError as exc:  # a broken file: its problem, named, in one line
        raise UserError(str(exc)) from None
    return with_corrections(frames, lambda frame_id: active.get(frame_id, ()))


def cmd_evaluate(args: argparse.Namespace) -> int:
    params = resolve_preset(args.config)
    frames = discover(args.dataset)
    if args.no_masks:  # raw frames: every mask withheld, segmentation from the images
        frames = [replace(f, mask=None, mask_left=None, mask_right=None) for f in frames]
    if not args.no_corrections:
        frames = corrected(frames, Path(args.dataset), args.db)
    n_corrected = sum(bool(f.corrections) for f in frames)
    if n_corrected:
        print(f"threadrecon: {n_corrected} frame(s) with stored mask corrections", file=sys.stderr)
    workers = 0 if args.workers is None and args.scheduler is None else args.workers
    rows: list[dict[str, Any] | None] = [None] * len(frames)
    keep = bool(args.save_predictions)
    from threadrecon.app.distributed import connect, evaluate_frames

    with connect(args.scheduler, workers) as client:
        for i, row, rec in evaluate_frames(client, frames, params, keep, _progress):
            rows[i] = row
            if keep and rec is not None:
                path = Path(args.save_predictions) / f"{frames[i].id}.json"
                pred = result_json(
                    rec, frame_rectification(frames[i]), "left", args.config or "default",
                    frame_inputs(frames[i]),
                )  # fmt: skip
                write_json(path, pred)
    rows = [r for r in rows if r is not None]
    if args.out:
        write_csv(Path(args.out), rows)
    for line in summarise(rows):
        print(line)
    failed = sum(r["status"] == "failed" for r in rows)  # suspect frames are listed, not failed
    if failed:
        print(f"threadrecon: {failed} of {len(rows)} frames failed", file=sys.stderr)
        return 1
    return 0
