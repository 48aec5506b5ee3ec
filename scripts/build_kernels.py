"""Build the core's ahead-of-time kernels (core/compiled.py) with several processes at once.

The first process that calls a kernel module's kernel compiles the whole module (numba's AOT
compiler, single-threaded): on a fresh checkout ~95 s of CPU for the nine modules, one after
the other. The test command runs this first so that the build uses every core: each process
walks the module list in its own order (two processes: from opposite ends), a module is built
by whichever process reaches it first while another that reaches it meanwhile waits on the
module's file lock and then loads it (core/compiled.py). Built modules load in milliseconds.

    python scripts/build_kernels.py [--jobs N]
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import subprocess
import sys
import time


def kernel_modules() -> list[str]:
    """Names of the core modules that declare compiled kernels, sorted."""
    import threadrecon.core as core
    from threadrecon.core import compiled

    for info in pkgutil.iter_modules(core.__path__):
        importlib.import_module(f"threadrecon.core.{info.name}")
    return sorted(compiled.backends())


def build(names: list[str]) -> None:
    """Resolve one kernel of each module of ``names``, in that order (building what is missing)."""
    from threadrecon.core.compiled import Kernel

    for name in names:
        module = importlib.import_module(name)
        kernels = [v for v in vars(module).values() if isinstance(v, Kernel)]
        if not kernels:
            raise SystemExit(f"build_kernels: {name} declares no kernel")
        t0 = time.perf_counter()
        backend = kernels[0].backend  # resolves the module: loads or builds its extension
        print(f"  {name}: {backend} ({time.perf_counter() - t0:.1f} s)", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="processes (cores)")
    ap.add_argument("--part", type=int, default=None, help=argparse.SUPPRESS)  # a child's rotation
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs must be >= 1, got {args.jobs}")
    names = kernel_modules()
    if args.part is not None:  # a child: its own order through the list
        if args.part == 1:  # the second walks from the other end: the two meet once
            order = names[::-1]
        else:  # the first from the start, further ones from evenly spaced offsets
            k = len(names) * args.part // args.jobs
            order = names[k:] + names[:k]
        build(order)
        return 0
    if os.environ.get("THREADRECON_KERNELS", "").lower() == "jit":
        print("build_kernels: THREADRECON_KERNELS=jit: nothing to build ahead of time")
        return 0
    t0 = time.perf_counter()
    children = [
        subprocess.Popen([sys.executable, __file__, "--jobs", str(args.jobs), "--part", str(i)])
        for i in range(min(args.jobs, len(names)))
    ]
    codes = [c.wait() for c in children]
    print(f"build_kernels: {len(names)} kernel modules ready in {time.perf_counter() - t0:.1f} s")
    return max(codes, default=0)


if __name__ == "__main__":
    sys.exit(main())
