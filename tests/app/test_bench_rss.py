"""The bench's peak RSS line says when it includes compiling the kernels or numba's JIT."""

from __future__ import annotations

import pytest

from threadrecon.app import bench


@pytest.mark.parametrize(
    ("built", "backends", "note"),
    [
        ([], {"threadrecon.core.stereo": "aot"}, ""),
        (["threadrecon.core.stereo"], {"threadrecon.core.stereo": "aot"}, "compiling the kernels"),
        ([], {"threadrecon.core.stereo": "jit"}, "numba's JIT"),
    ],
)
def test_peak_rss_line_names_what_else_it_includes(
    monkeypatch: pytest.MonkeyPatch, built: list[str], backends: dict[str, str], note: str
) -> None:
    monkeypatch.setattr(bench, "built_here", lambda: built)
    monkeypatch.setattr(bench, "backends", lambda: backends)
    text = bench._kernel_note()
    assert (note in text) if note else text == ""
