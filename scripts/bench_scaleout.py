"""Scale-out of ``threadrecon tune`` on a Dask cluster started as separate processes: the same
grid on ``dask scheduler`` + 1 ``dask worker`` and on ``dask scheduler`` + N workers, runs
interleaved, each timed from the tune's start to its end (clusters are started and their workers
registered before the clock starts); the per-frame rows (timings aside) of every run are
compared with an in-process run of the same grid.

    PYTHONPATH=... python scripts/bench_scaleout.py DATASET --space grid.toml --repeats 3

Prints one line per run, the median wall time per cluster size and the speed-up.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from threadrecon.app.distributed import connect
from threadrecon.app.tune import TuneConfig, load_space, tune

DASK = str(Path(sys.executable).with_name("dask"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def cluster(workers: int) -> Iterator[str]:
    """``dask scheduler`` and ``workers`` x ``dask worker`` (one thread each) as processes."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)  # the package under test
    common = {"env": env, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [
        subprocess.Popen(
            [DASK, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            start_new_session=True, **common,
        )
    ]  # fmt: skip
    try:
        time.sleep(2.0)
        for _ in range(workers):
            procs.append(
                subprocess.Popen(
                    [DASK, "worker", address, "--nthreads", "1", "--nworkers", "1",
                     "--no-dashboard", "--host", "127.0.0.1"],
                    start_new_session=True, **common,
                )
            )  # fmt: skip
        from distributed import Client

        with Client(address, timeout="30s") as c:
            c.wait_for_workers(workers, timeout=120)
        yield address
    finally:
        for p in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)


def rows_of(result: Any) -> list[tuple[int, list[dict[str, Any]]]]:
    """Every trial's per-frame rows without timings, NaN as a string (so equal rows compare
    equal)."""
    out = []
    for t in sorted(result.trials, key=lambda t: t.number):
        rows = [
            {
                k: ("nan" if isinstance(v, float) and math.isnan(v) else v)
                for k, v in r.items()
                if not k.startswith("ms_")
            }
            for r in t.rows
        ]
        out.append((t.number, rows))
    return out


def timed_tune(cfg: TuneConfig, scheduler: str | None, workers: int | None) -> tuple[float, Any]:
    store = Path(tempfile.mkdtemp(prefix="bench-scaleout-"))
    try:
        with connect(scheduler, workers) as client:
            t0 = time.perf_counter()
            result = tune(cfg, store, client, log=lambda _: None)
            return time.perf_counter() - t0, result
    finally:
        shutil.rmtree(store, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--space", required=True)
    ap.add_argument("--workers", type=int, default=2, help="workers of the scale-out cluster")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-prune", action="store_true")
    ap.add_argument("--no-reference", action="store_true", help="skip the in-process run")
    args = ap.parse_args(argv)
    cfg = TuneConfig(
        dataset=args.dataset, space=load_space(args.space), mode="grid", prune=not args.no_prune
    )
    reference = None
    if not args.no_reference:
        wall, res = timed_tune(cfg, None, 0)
        reference = rows_of(res)
        n_rows = sum(len(r) for _, r in reference)
        print(f"in-process: {wall:7.1f} s, {len(reference)} trials, {n_rows} frame rows")
    times: dict[int, list[float]] = {1: [], args.workers: []}
    identical = True
    for rep in range(args.repeats):
        for n in (1, args.workers) if rep % 2 == 0 else (args.workers, 1):
            with cluster(n) as address:
                wall, res = timed_tune(cfg, address, None)
            rows = rows_of(res)
            if reference is None:
                reference = rows
            same = rows == reference
            identical &= same
            times[n].append(wall)
            load = os.getloadavg()[0]
            print(
                f"run {rep + 1}, {n} worker(s): {wall:7.1f} s, rows identical: {same}, load {load:.1f}"
            )
    m1, mn = statistics.median(times[1]), statistics.median(times[args.workers])
    print(
        f"median wall: 1 worker {m1:.1f} s, {args.workers} workers {mn:.1f} s, "
        f"speed-up {m1 / mn:.2f}x (runs: {', '.join(f'{a / b:.2f}' for a, b in zip(times[1], times[args.workers], strict=True))})"
    )
    print(f"per-frame rows identical in every run: {identical}")
    return 0 if identical else 1


if __name__ == "__main__":
    sys.exit(main())
