"""Parameter declarations: metadata on the field, checked on construction, read by every view."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import pytest

from threadrecon.core.params import Params, param, specs
from threadrecon.core.pipeline import STAGE_TABLE, STAGES, ReconParams


@dataclass(frozen=True)
class _Demo(Params):
    gain: float = param(1.0, lo=0, hi=10, unit="px", symbol="eps1", slider=(0, 5, 0.5))
    count: int = param(3, lo=1, hi=9)
    level: float | None = param(None, lo=0, hi=255)
    mode: Literal["a", "b"] = "a"
    on: bool = True


def test_specs_carry_the_declared_metadata() -> None:
    by_name = {s.name: s for s in specs(_Demo)}
    g = by_name["gain"]
    assert (g.kind, g.lo, g.hi, g.unit, g.symbol, g.slider) == (
        "slider",
        0,
        10,
        "px",
        "eps1",
        (0, 5, 0.5),
    )
    assert by_name["count"].kind == "number" and by_name["count"].integer
    assert by_name["level"].kind == "auto" and by_name["level"].optional
    assert by_name["mode"].options == ("a", "b")
    assert by_name["on"].kind == "checkbox"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"gain": 11.0}, r"gain must be in \[0, 10\]"),
        ({"gain": math.nan}, "finite"),
        ({"gain": 10**400}, "finite"),
        ({"gain": "1"}, "must be a number"),
        ({"gain": True}, "must be a number"),
        ({"count": 2.5}, "whole number"),
        ({"level": -1.0}, "level"),
        ({"mode": "c"}, "one of"),
        ({"on": 1}, "true or false"),
    ],
)
def test_invalid_values_are_refused_on_construction(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _Demo(**kwargs)


def test_valid_values_and_auto_are_accepted() -> None:
    d = _Demo(gain=0.0, count=9, level=None, mode="b", on=False)
    assert replace(d, level=128.0).level == 128.0


def test_a_slider_outside_the_valid_range_is_a_declaration_error() -> None:
    with pytest.raises(ValueError, match="slider"):
        param(1.0, lo=0, hi=1, slider=(0, 2, 0.1))


def test_every_stage_declares_its_params_and_defaults_are_valid() -> None:
    assert tuple(s.name for s in STAGE_TABLE) == STAGES
    params = ReconParams()
    for stage in STAGE_TABLE:
        group = getattr(params, stage.name)
        assert type(group) is stage.params and isinstance(group, Params)
        for spec in specs(stage.params):
            if spec.slider is not None:
                lo, hi, _ = spec.slider
                assert lo <= getattr(group, spec.name) <= hi, f"{stage.name}.{spec.name}"
        for name in stage.inputs:
            assert name in ("pair", "calib") or STAGES.index(name) < STAGES.index(stage.name)
