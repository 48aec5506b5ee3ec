"""Tests of core/compiled.py: ahead-of-time kernels, the same results as numba's JIT, checked
arguments, and a reconstruction that never imports numba."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from threadrecon.core import walk_kernel
from threadrecon.core.compiled import MODE_ENV, kernel

# One reconstruction of a synthetic frame in a fresh process; prints what it used and found.
_RUN = """
import hashlib, json, sys
import numpy as np
sys.path.insert(0, {tests!r})
from support import synthetic_case
from threadrecon.core import compiled
from threadrecon.core.pipeline import reconstruct
from threadrecon.core.segmentation import SegmentationParams, segment
pair, calib, _ = synthetic_case(1)
rec = reconstruct(pair, calib)
st = rec["stereo"]
raw = segment(pair, SegmentationParams(method="raw"))  # the raw segmentation's kernels
from threadrecon.core.instrument import thread_half_width
thread_half_width(np.eye(8, dtype=bool))  # the instrument width test's kernels
def h(*arrays):
    return hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)).hexdigest()
print(json.dumps({{
    "numba": "numba" in sys.modules,
    "backends": compiled.backends(),
    "status": rec.status,
    "stereo": h(st.d_min, st.d_next, st.E_min, st.E_next, st.disparity, st.energy),
    "clusters": h(rec["clustering"].labels),
    "order": h(np.asarray(rec["ordering"].order)),
    "curve": h(rec["camera"].points),
    "raw": h(raw.P_L, raw.P_R, raw.score_L, raw.score_R),
}}))
"""


def _run(env: dict[str, str]) -> dict:
    code = _RUN.format(tests=str(Path(__file__).resolve().parents[1]))
    out = subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=900,
        check=True,
    )
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "stderr": out.stderr}


@pytest.fixture(scope="module")
def aot_run() -> dict:
    _run({MODE_ENV: "aot"})  # builds the AOT modules if this checkout has none yet
    return _run({MODE_ENV: "aot"})


def test_a_reconstruction_loads_aot_kernels_without_numba(aot_run: dict) -> None:
    assert aot_run["backends"] == {
        "threadrecon.core.stereo": "aot",
        "threadrecon.core.clustering": "aot",
        "threadrecon.core.walk_kernel": "aot",
        "threadrecon.core.spline_kernel": "aot",
        "threadrecon.core.check_kernel": "aot",
        "threadrecon.core.check_fast_kernel": "aot",
        "threadrecon.core.ridge_kernel": "aot",
        "threadrecon.core.grow_kernel": "aot",
        "threadrecon.core.instrument_kernel": "aot",
        "threadrecon.core.segmentation": "aot",
        "threadrecon.core.refine_kernel": "aot",
    }
    assert not aot_run["numba"]


def test_aot_kernels_give_the_jit_kernels_results_bit_for_bit(aot_run: dict) -> None:
    jit = _run({MODE_ENV: "jit"})
    assert set(jit["backends"].values()) == {"jit"} and jit["numba"]
    for key in ("status", "stereo", "clusters", "order", "curve", "raw"):
        assert aot_run[key] == jit[key], key


def test_an_unbuildable_cache_falls_back_to_the_jit_with_a_warning(tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    run = _run({MODE_ENV: "aot", "THREADRECON_KERNEL_CACHE": str(blocker / "kernels")})
    assert set(run["backends"].values()) == {"jit"}
    assert "could not be built" in run["stderr"] and "using numba's JIT" in run["stderr"]


def test_an_array_of_another_dtype_is_a_type_error_naming_it() -> None:
    K = 3
    args = [
        np.zeros(K, np.int32),  # walk: int64 expected
        1, 1, np.zeros(K), -1, np.zeros(K, bool), np.zeros(K + 1, np.int64),
        np.zeros(0, np.int64), np.zeros((K, 2)), np.zeros(K), 1.0, 1.0, 0.0,
        np.zeros(K, np.int64), np.zeros(K, np.int64), np.zeros(K, np.int64), 0, 1,
    ]  # fmt: skip
    if walk_kernel.walk_on.backend == "aot":
        with pytest.raises(
            TypeError, match="walk must be a 1-D int64 C-contiguous array, got int32"
        ):
            walk_kernel.walk_on(*args)
    args[0] = np.zeros(K, np.int64)
    args[8] = np.zeros(2 * K)  # pos: 2-D expected
    if walk_kernel.walk_on.backend == "aot":
        with pytest.raises(TypeError, match="pos must be a 2-D float64 C-contiguous array"):
            walk_kernel.walk_on(*args)
    args[8] = np.zeros((K, 2))
    args[0] = np.zeros(2 * K, np.int64)[::2]  # walk: written in place, so no copy is made
    if walk_kernel.walk_on.backend == "aot":
        with pytest.raises(TypeError, match=r"walk must be .* C-contiguous array, got .* strided"):
            walk_kernel.walk_on(*args)


def test_a_signature_that_does_not_fit_the_function_is_refused() -> None:
    with pytest.raises(ValueError, match="2 arguments, the function 1"):

        @kernel("int64(int64[:], int64)")
        def one(a):  # noqa: ANN001, ANN202
            return a.size

    with pytest.raises(ValueError, match="unsupported type 'complex128'"):

        @kernel("int64(complex128[:])")
        def two(a):  # noqa: ANN001, ANN202
            return a.size


def test_the_kernels_go_to_the_user_cache_when_the_package_is_read_only(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from threadrecon.core import compiled

    module = compiled._module_of(walk_kernel.walk_on.fn)
    monkeypatch.delenv(compiled.CACHE_ENV, raising=False)
    assert module.cache_dir() == Path(walk_kernel.__file__).resolve().parent / "__pycache__"
    monkeypatch.setattr(compiled.os, "access", lambda *_: False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert module.cache_dir() == tmp_path / "threadrecon" / "kernels"
    monkeypatch.setenv(compiled.CACHE_ENV, str(tmp_path / "mine"))
    assert module.cache_dir() == tmp_path / "mine"


def test_the_default_mode_takes_only_aot_or_jit() -> None:
    from threadrecon.core import compiled

    before = compiled._default_mode  # "jit" when a test before this one built the server
    with pytest.raises(ValueError, match="'aot' or 'jit'"):
        compiled.set_default_mode("fast")
    assert compiled._default_mode == before in ("aot", "jit")  # a refused value changes nothing
