"""Two processes that start at once on an empty kernel cache (a fresh installation, e.g. two
workers of a server or of ``evaluate --workers 2``): one builds the ahead-of-time module, the
other waits for it and loads it; neither falls back to the JIT or sees a half-written file."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

from threadrecon.core.compiled import CACHE_ENV, MODE_ENV

# A kernel module of its own (a small build), imported from the test's folder.
_MODULE = """
import numpy as np
from threadrecon.core.compiled import kernel


@kernel("int64(int64[::1])")
def total(a):
    s = 0
    for v in a:
        s += v
    return s
"""

_RUN = """
import json, sys, warnings
sys.path.insert(0, {folder!r})
warnings.simplefilter("always")
import numpy as np
import kmod_concurrency as m
from threadrecon.core import compiled
value = int(m.total(np.arange(100, dtype=np.int64)))
print(json.dumps({{"value": value, "backend": m.total.backend, "built": compiled.built_here()}}))
"""


def test_two_processes_starting_at_once_build_the_kernels_once(tmp_path: Path) -> None:
    (tmp_path / "kmod_concurrency.py").write_text(textwrap.dedent(_MODULE))
    cache = tmp_path / "cache"
    env = {**os.environ, CACHE_ENV: str(cache), MODE_ENV: "aot"}
    code = _RUN.format(folder=str(tmp_path))
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err
        assert "could not be built" not in err, err  # no fall-back to the JIT
    results = [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
    assert [r["value"] for r in results] == [4950, 4950]
    assert [r["backend"] for r in results] == ["aot", "aot"]
    # one process compiled the module, the other waited on the lock and loaded it
    assert sorted(len(r["built"]) for r in results) == [0, 1]
    built = [f for f in cache.iterdir() if f.name.startswith("kmod_concurrency_aot_")]
    assert len([f for f in built if not f.name.endswith(".lock")]) == 1
    assert not [f for f in cache.iterdir() if f.name.startswith(".build-")]  # no leftovers
