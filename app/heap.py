"""The server process's heap and the garbage collector's full collections.

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
"""

from __future__ import annotations

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
