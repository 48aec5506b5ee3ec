"""The debugger's controls: one per parameter of the core, grouped by stage.

Everything here is read from the parameters' own declarations (``core.params.param``
metadata on each stage's Params): a parameter with a ``slider`` range is a slider, booleans are
checkboxes, choices are dropdowns, "auto" parameters (None = estimated per frame) live in presets
only, and any other number is a number field bounded by its valid range. A new parameter or a
new stage of the core shows up without touching this file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from threadrecon.core.params import specs
from threadrecon.core.pipeline import STAGE_TABLE

Kind = Literal["slider", "checkbox", "dropdown", "number"]


@dataclass(frozen=True)
class Control:
    stage: str
    name: str
    label: str
    kind: Kind
    min: float | None = None
    max: float | None = None
    step: float | None = None
    options: tuple[str, ...] = ()
    integer: bool = False
    unit: str = ""
    symbol: str = ""

    @property
    def key(self) -> str:
        return f"{self.stage}.{self.name}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "key": self.key,
            "stage": self.stage,
            "name": self.name,
            "label": self.label,
            "kind": self.kind,
            "min": self.min,
            "max": self.max,
            "step": self.step,
            "options": list(self.options),
            "integer": self.integer,
            "unit": self.unit,
            "symbol": self.symbol,
        }


def controls() -> tuple[Control, ...]:
    """Every parameter of :class:`ReconParams` as a control, in stage order."""
    out: list[Control] = []
    for stage in STAGE_TABLE:
        for spec in specs(stage.params):
            label = spec.label or spec.name
            extra = {"unit": spec.unit, "symbol": spec.symbol}
            if spec.kind == "auto":
                continue
            if spec.kind == "slider" and spec.slider is not None:
                lo, hi, step = spec.slider
                out.append(
                    Control(
                        stage.name,
                        spec.name,
                        label,
                        "slider",
                        lo,
                        hi,
                        step,
                        integer=spec.integer,
                        **extra,
                    )
                )
            elif spec.kind == "number":
                out.append(
                    Control(
                        stage.name,
                        spec.name,
                        label,
                        "number",
                        spec.lo,
                        spec.hi,
                        integer=spec.integer,
                        **extra,
                    )
                )
            elif spec.kind == "dropdown":
                out.append(
                    Control(stage.name, spec.name, label, "dropdown", options=spec.options, **extra)
                )
            else:
                out.append(Control(stage.name, spec.name, label, "checkbox", **extra))
    return tuple(out)
