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

A task is a *chunk* of frames (every k-th frame of the map, k tasks per worker), not one frame:
a frame takes some tens of milliseconds, about the scheduler's round trip, so one task per frame
spent much of a small cluster's time on scheduling. Each worker process keeps the frames it has
loaded (read-only, by path and modification time, up to :data:`FRAME_CACHE_BYTES`): a tune maps
the same frames once per trial, and reading and rectifying them again was a sixth of the work.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import astuple, replace
from typing import Any

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from threadrecon.app.dataset import Frame, load_frame
from threadrecon.app.evaluation import evaluate_frame
from threadrecon.core.pipeline import ReconParams, Reconstruction

Progress = Callable[[int, int, str], None]
TASKS_PER_WORKER = (
    4  # chunks per worker and map: fewer round trips, yet a slow chunk is 1/4 of a share
)
FRAME_CACHE_BYTES = 512 * 2**20  # loaded frames kept per process (a 1280x1024 pair is ~8 MB)

_cache: OrderedDict[tuple[Any, ...], tuple[Any, int]] = OrderedDict()
_cache_bytes = 0
_cache_lock = threading.Lock()


def machine_workers() -> int:
    """Worker processes of a default local cluster: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _frame_key(frame: Frame) -> tuple[Any, ...]:
    """The frame's files and their modification times (a rewritten file is a new key). The
    user's corrections are applied after loading, so they are not part of it: a frame loads
    once whatever its corrections."""
    frame = replace(frame, corrections=())
    stamps = []
    for p in astuple(frame):
        if isinstance(p, os.PathLike):
            try:
                stamps.append(os.stat(p).st_mtime_ns)
            except OSError:
                stamps.append(None)
    return (frame, tuple(stamps))


def _nbytes(loaded: tuple[Any, ...]) -> int:
    pair, _, gt = loaded
    arrays = [getattr(pair, n, None) for n in ("left", "right", "mask_left", "mask_right")]
    return sum(a.nbytes for a in (*arrays, gt) if isinstance(a, np.ndarray))


def _freeze(loaded: tuple[Any, ...]) -> None:
    """Shared by every trial: an in-place write by a stage would raise rather than leak."""
    pair, _, gt = loaded
    for a in (*(getattr(pair, n, None) for n in ("left", "right", "mask_left", "mask_right")), gt):
        if isinstance(a, np.ndarray):
            a.flags.writeable = False


def cached_frame(frame: Frame) -> tuple[Any, Any, Any] | None:
    """``load_frame(frame)`` from this process's cache (loaded on a miss); None when the
    frame cannot be loaded (:func:`evaluate_frame` then loads it again and reports why)."""
    global _cache_bytes
    key = _frame_key(frame)
    with _cache_lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
            return hit[0]
    try:
        loaded = load_frame(frame)
    except Exception:
        return None
    size = _nbytes(loaded)
    if size > FRAME_CACHE_BYTES:
        return loaded
    _freeze(loaded)
    with _cache_lock:
        _cache[key] = (loaded, size)
        _cache_bytes += size
        while _cache_bytes > FRAME_CACHE_BYTES:
            _, (_, old) = _cache.popitem(last=False)
            _cache_bytes -= old
    return loaded


def evaluate_task(
    frame: Frame, params: ReconParams, keep: bool = False
) -> tuple[dict[str, Any], Reconstruction | None]:
    """One frame's evaluation row (and its reconstruction with ``keep``), as run by a worker."""
    return evaluate_chunk([frame], params, keep)[0]


def evaluate_chunk(
    frames: Sequence[Frame], params: ReconParams, keep: bool = False
) -> list[tuple[dict[str, Any], Reconstruction | None]]:
    """:func:`evaluate_task` of each frame, in order, as one task."""
    cv_threads = cv2.getNumThreads()
    # one thread per task: the workers are the parallelism (OpenCV's own pool on every worker
    # oversubscribed the cores), and BLAS gives the same arithmetic on every worker
    cv2.setNumThreads(1)
    out = []
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            for frame in frames:
                row, rec = evaluate_frame(frame, params, cached_frame(frame))
                out.append((row, rec if keep else None))
    finally:
        cv2.setNumThreads(cv_threads)
    return out


def _chunks(n: int, workers: int) -> list[list[int]]:
    """Frame indices of each task: every k-th frame, so neighbouring (similar) frames spread
    over the tasks and the chunks take about as long as each other."""
    k = max(1, min(n, TASKS_PER_WORKER * max(1, workers)))
    return [list(range(j, n, k)) for j in range(k)]


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

    chunks = _chunks(n, sum(client.nthreads().values()))
    futures = client.map(
        evaluate_chunk, [[frames[i] for i in c] for c in chunks], params=params, keep=keep,
        pure=False,
    )  # fmt: skip
    index = {f.key: c for f, c in zip(futures, chunks, strict=True)}
    done = 0
    if progress:
        progress(0, n, "")
    try:
        for fut in as_completed(futures):
            got = fut.result()
            for i, (row, rec) in zip(index[fut.key], got, strict=True):
                done += 1
                if progress:
                    progress(done, n, row["frame"])
                yield i, row, rec
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
