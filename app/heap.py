"""The process's heap: the garbage collector's full collections, and freed pages handed back.

A full collection stops every thread (a slider move's run, the page's answer, the 3D views)
while it scans every object the collector tracks. The server's start makes ~130k of them
(the imports, viser, the app) and compiling the kernels (``jit`` mode, the first run) ~160k
more, kept for the process's life: a full collection then took 0.3-0.6 s at load 16 on this
machine, 1.2 s after the kernels compiled, and caught one or two of every 200 slider moves.
:func:`settle` puts the objects alive now out of its reach (``gc.freeze``), so that it scans
only what has been made since; the server settles once started and, from then on, again after
a run on a new frame that left more than ``SETTLE_ABOVE`` objects to scan (new kernels
compiled). Frozen objects are still freed by their reference counts (a closed session releases
its frames and results); a reference cycle among them is not. A process that never settled
(the tests, the Python API) is left as it is.

:func:`trim` hands glibc's free heap pages back to the OS: the server after closing sessions
(:func:`release_memory`), ``threadrecon bench`` between frames (:func:`release_memory`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import threading

SETTLE_ABOVE = 20_000  # objects a full collection may scan before the heap is settled again
_lock = threading.Lock()
_settled = False  # this process has settled its heap once (a server)


def settle() -> None:
    """Collect, then freeze what is left (alive): full collections skip it from now on."""
    global _settled
    with _lock:
        gc.collect()
        gc.freeze()
        _settled = True


def settle_if_grown(limit: int = SETTLE_ABOVE) -> bool:
    """In a process that has settled once, :func:`settle` again when the collector tracks
    more than ``limit`` objects not frozen (listing them costs ~1 ms a 10k). True when it
    settled."""
    if not _settled or len(gc.get_objects()) <= limit:
        return False
    settle()
    return True


def _malloc_trim() -> ctypes._CFuncPtr | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):  # not glibc
        return None


_TRIM = _malloc_trim()


def trim() -> None:
    """Hand the heap's free pages back to the OS (glibc keeps them otherwise: after a few
    1920x1080 frames a process holds ~25 MB more than one frame needs; 1-3 ms a call)."""
    if _TRIM is not None:
        _TRIM(0)


def release_memory() -> None:
    """Collect, then :func:`trim` (the RSS of a server that closed 50 sessions would otherwise
    stay at its peak)."""
    gc.collect()
    trim()
