"""Preset fingerprints: equal parameters hash equally, every single change shows."""

from __future__ import annotations

import re
import typing
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from app.presets import load_preset, params_hash, save_preset, validate
from core.pipeline import STAGES, ReconParams


def _changed(hint: Any, value: Any) -> Any:
    """A different value of the same declared type."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) is typing.Literal:
        return next(a for a in args if a != value)
    if value is None:
        return 1.0
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    return value / 2 if 0 < value < 1 else value + 0.5  # a share stays inside [0, 1]


def test_params_hash_is_short_hex_and_equal_for_equal_params(tmp_path: Path) -> None:
    a = ReconParams()
    b = load_preset(save_preset(validate({"spline": {}}), "same", tmp_path))
    assert a == b and a is not b
    assert params_hash(a) == params_hash(b)
    assert re.fullmatch(r"[0-9a-f]{12}", params_hash(a))
    c = replace(a, segment=replace(a.segment, seg_delta=int(a.segment.seg_delta)))
    assert c == a and type(c.segment.seg_delta) is int
    assert params_hash(c) == params_hash(a)


def test_params_hash_changes_with_every_single_parameter() -> None:
    base = ReconParams()
    seen = {params_hash(base)}
    n = 0
    for stage in STAGES:
        group = getattr(base, stage)
        hints = typing.get_type_hints(type(group))
        for f in fields(group):
            new = _changed(hints[f.name], getattr(group, f.name))
            changed = replace(base, **{stage: replace(group, **{f.name: new})})
            h = params_hash(changed)
            assert h not in seen, f"{stage}.{f.name}: hash did not change"
            seen.add(h)
            n += 1
    assert n == sum(len(fields(getattr(base, s))) for s in STAGES) > 20


def test_params_hash_tells_close_floats_apart() -> None:
    a = validate({"reliability": {"threshold": 0.9}})
    b = validate({"reliability": {"threshold": 0.9000001}})
    assert params_hash(a) != params_hash(b)
