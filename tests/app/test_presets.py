"""Preset fingerprints: equal parameters hash equally, every single change shows."""

from __future__ import annotations

import re
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import pytest

from threadrecon.app.presets import load_preset, params_hash, save_preset, validate
from threadrecon.core.check import CheckParams
from threadrecon.core.params import ParamSpec, specs
from threadrecon.core.pipeline import STAGES, ReconParams


def _changed(spec: ParamSpec, value: Any) -> Any:
    """A different valid value of the same declared type."""
    if spec.kind == "dropdown":
        return next(a for a in spec.options if a != value)
    if value is None:
        return 1.0
    if isinstance(value, bool):
        return not value
    step = 1 if spec.integer else 0.5 * ((spec.hi - value) if spec.hi is not None else 1.0)
    if step == 0:  # a default at its upper bound (ordering.hidden_turn_deg: 180 deg)
        step = 0.5 * (value - spec.lo) if spec.lo is not None else 1.0
    new = value + step
    return new if spec.hi is None or new <= spec.hi else value - step


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
        for spec in specs(type(group)):
            new = _changed(spec, getattr(group, spec.name))
            try:
                moved = replace(group, **{spec.name: new})
            except ValueError:  # a cross-field rule (e.g. an odd window): one step further
                moved = replace(group, **{spec.name: _changed(spec, new)})
            changed = replace(base, **{stage: moved})
            h = params_hash(changed)
            assert h not in seen, f"{stage}.{spec.name}: hash did not change"
            seen.add(h)
            n += 1
    assert n == sum(len(fields(getattr(base, s))) for s in STAGES) > 20


def test_params_hash_tells_close_floats_apart() -> None:
    a = validate({"reliability": {"threshold": 0.9}})
    b = validate({"reliability": {"threshold": 0.9000001}})
    assert params_hash(a) != params_hash(b)


def test_a_preset_saved_before_a_parameter_was_retired_still_loads(tmp_path: Path) -> None:
    """Every saved preset lists every parameter: one written while check.bridge_turn_deg and
    check.bridge_mm existed loads with the same values for every other parameter, the retired
    ones named in a warning; a key that never existed is still refused."""
    params = replace(ReconParams(), check=replace(ReconParams().check, max_bridge_mm=35.0))
    path = save_preset(params, "old", tmp_path)
    text = path.read_text().replace(
        "[check]\n", "[check]\nbridge_turn_deg = 60.0\nbridge_mm = 3.0\n"
    )
    path.write_text(text)
    assert set(CheckParams.RETIRED) == {"bridge_turn_deg", "bridge_mm"}
    with pytest.warns(UserWarning) as record:
        assert load_preset(path) == params
    assert sorted(str(w.message).split(" is ")[0] for w in record) == [
        "check.bridge_mm",
        "check.bridge_turn_deg",
    ]
    path.write_text(text.replace("bridge_mm = 3.0", "bridge_nm = 3.0"))
    with (
        pytest.raises(ValueError, match=r"unknown parameter check\.bridge_nm"),
        pytest.warns(UserWarning, match="bridge_turn_deg"),
    ):
        load_preset(path)
    # a retired name is a parameter of no stage: nothing of the current ones carries it
    assert not {s.name for s in specs(CheckParams)} & set(CheckParams.RETIRED)
