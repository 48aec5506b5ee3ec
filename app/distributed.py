"""Frames on Dask: one function maps a parameter set over frames, in this process or on a
cluster, for ``threadrecon evaluate`` and ``threadrecon tune`` alike.

``connect(scheduler=None, workers=None)`` gives a ``distributed.Client``:

- ``scheduler="tcp://host:8786"``: a cluster someone started with ``dask scheduler`` and
  ``dask worker`` (the workers must see the dataset under the same paths and import this
  package: start them from the project folder or with it on ``PYTHONPATH``);
- otherwise a ``LocalCluster`` on loopback, ``workers`` processes of one thread each (default:
  one per CPU this process may use);
- ``workers=0`` is no cluster at all: frames run one after another in this process.

Every task limits BLAS to one thread, so a frame's numbers do not depend on where it ran.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import cv2
from threadpoolctl import threadpool_limits

from threadrecon.app.dataset import Frame
from threadrecon.app.evaluation import evaluate_frame
from threadrecon.core.pipeline import ReconParams, Reconstruction

Progress = Callable[[int, int, str], None]


def machine_workers() -> int:
    """Worker processes of a default local cluster: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def evaluate_task(
    frame: Frame, params: ReconParams, keep: bool = False
) -> tuple[dict[str, Any], Reconstruction | None]:
    """One frame's evaluation row (and its reconstruction with ``keep``), as run by a worker."""
    cv_threads = cv2.getNumThreads()
    # one thread per task: the workers are the parallelism (OpenCV's own pool on every worker
    # oversubscribed the cores), and BLAS gives the same arithmetic on every worker
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            row, rec = evaluate_frame(frame, params)
    finally:
        cv2.setNumThreads(cv_threads)
    return row, (rec if keep else None)


@contextmanager
def connect(
    scheduler: str | None = None, workers: int | None = None, timeout: float = 10.0
) -> Iterator[Any]:
    """A Dask client (see the module docstring); None for ``workers=0`` (in-process)."""
    if scheduler is not None and workers is not None:
        raise ValueError("give either --scheduler (an existing cluster) or --workers, not both")
    if workers is not None and workers < 0:
        raise ValueError(f"--workers must be >= 0, got {workers}")
    if scheduler is None and workers == 0:
        yield None
        return
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=f"{timeout}s")
        except OSError as exc:
            raise OSError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        with client:
            if not client.scheduler_info(n_workers=-1).get("workers"):
                client.wait_for_workers(1, timeout=3 * timeout)
            yield client
        return
    n = machine_workers() if workers is None else workers
    with (
        LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address="127.0.0.1:0",  # any free port, loopback: not the shared 8787
            silence_logs=50,  # task errors reach the caller; shutdown chatter does not
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def describe(client: Any) -> str:
    if client is None:
        return "in this process"
    info = client.scheduler_info(n_workers=-1)
    n = len(info.get("workers", {}))
    return f"{n} Dask worker{'s' * (n != 1)} at {info.get('address', '?')}"


def evaluate_frames(
    client: Any,
    frames: Sequence[Frame],
    params: ReconParams,
    keep: bool = False,
    progress: Progress | None = None,
) -> Iterator[tuple[int, dict[str, Any], Reconstruction | None]]:
    """``(index, row, reconstruction or None)`` for every frame, in completion order; the rows
    are the same whichever client (or none) computed them, apart from the ``ms_*`` timings."""
    n = len(frames)
    if client is None:
        for i, frame in enumerate(frames):
            if progress:
                progress(i, n, frame.id)
            row, rec = evaluate_task(frame, params, keep)
            yield i, row, rec
        if progress:
            progress(n, n, "done")
        return
    from distributed import as_completed

    futures = client.map(evaluate_task, list(frames), params=params, keep=keep, pure=False)
    index = {f.key: i for i, f in enumerate(futures)}
    done = 0
    if progress:
        progress(0, n, "")
    try:
        for fut in as_completed(futures):
            row, rec = fut.result()
            done += 1
            if progress:
                progress(done, n, row["frame"])
            yield index[fut.key], row, rec
            fut.release()
    finally:
        for fut in futures:  # an interrupted caller leaves no work queued on the cluster
            fut.cancel()


def evaluate_rows(
    client: Any, frames: Sequence[Frame], params: ReconParams, progress: Progress | None = None
) -> list[dict[str, Any]]:
    """Rows of :func:`evaluate_frames` in frame order."""
    rows: list[dict[str, Any] | None] = [None] * len(frames)
    for i, row, _ in evaluate_frames(client, frames, params, progress=progress):
        rows[i] = row
    return [r for r in rows if r is not None]
