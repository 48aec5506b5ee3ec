"""Parameter declarations shared by every stage: a field's range, unit, paper symbol and slider
are metadata on the field itself, and :class:`Params` checks them on construction.

A stage's parameters are declared once, as a frozen dataclass deriving from :class:`Params`::

    @dataclass(frozen=True)
    class StereoParams(Params):
        alpha: int = param(80, lo=4, hi=512, unit="px", symbol="alpha", slider=(8, 200, 1),
                           label="α max disparity", doc="Maximum disparity of Eq. (3).")

Presets, the debugger's sliders, the REST API's validation and the exports read this metadata
(:func:`specs`); nothing else keeps a copy of a range or a label.
"""

from __future__ import annotations

import math
import typing
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, Literal

Kind = Literal["slider", "checkbox", "dropdown", "number", "auto"]


@dataclass(frozen=True)
class ParamSpec:
    """Everything a user interface or a validator needs to know about one parameter."""

    name: str
    kind: Kind
    default: Any
    lo: float | None = None
    """Smallest valid value (inclusive); None is unbounded."""
    hi: float | None = None
    """Largest valid value (inclusive); None is unbounded."""
    unit: str = ""
    symbol: str = ""
    """The paper's symbol, e.g. "eps1" or "alpha"; "" when the paper has none."""
    label: str = ""
    doc: str = ""
    slider: tuple[float, float, float] | None = None
    """(min, max, step) of the debugger's slider: the range worth tuning, inside [lo, hi]."""
    integer: bool = False
    options: tuple[Any, ...] = ()
    optional: bool = False
    """None is a valid value ("auto": estimated per frame)."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "default": self.default,
            "min": self.lo,
            "max": self.hi,
            "unit": self.unit,
            "symbol": self.symbol,
            "label": self.label or self.name,
            "doc": self.doc,
            "slider": list(self.slider) if self.slider else None,
            "integer": self.integer,
            "options": list(self.options),
            "optional": self.optional,
        }


def param(
    default: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    unit: str = "",
    symbol: str = "",
    label: str = "",
    doc: str = "",
    slider: tuple[float, float, float] | None = None,
) -> Any:
    """A dataclass field carrying a parameter's metadata (see :class:`ParamSpec`)."""
    if slider is not None:
        s_lo, s_hi, step = slider
        if not (step > 0 and s_lo <= s_hi):
            raise ValueError(f"bad slider {slider}")
        if (lo is not None and s_lo < lo) or (hi is not None and s_hi > hi):
            raise ValueError(f"slider {slider} leaves the valid range [{lo}, {hi}]")
    meta = {
        "lo": lo,
        "hi": hi,
        "unit": unit,
        "symbol": symbol,
        "label": label,
        "doc": doc,
        "slider": slider,
    }
    return field(default=default, metadata={"param": meta})


class Params:
    """Base of every stage's frozen parameter dataclass: checks each field against its
    declared type and range on construction, so that no stage ever sees an invalid value.

    Subclasses add cross-field checks by overriding :meth:`_check` (call ``super()._check()``).
    """

    RETIRED: ClassVar[dict[str, str]] = {}
    """Parameters the stage no longer has, each with why: a preset saved before (every saved
    preset lists every parameter) still loads, the retired value ignored (``app.presets``)."""

    def __post_init__(self) -> None:
        self._check()

    def _check(self) -> None:
        for spec in specs(type(self)):
            _check_value(type(self).__name__, spec, getattr(self, spec.name))


def specs(cls: type) -> tuple[ParamSpec, ...]:
    """The :class:`ParamSpec` of every field of a Params dataclass, in declaration order."""
    cached = _SPECS.get(cls)
    if cached is not None:
        return cached
    hints = typing.get_type_hints(cls)
    out = []
    for f in fields(cls):
        meta = dict(f.metadata.get("param", {}))
        default = f.default if f.default is not MISSING else None
        out.append(_spec(f.name, hints[f.name], default, meta))
    result = tuple(out)
    _SPECS[cls] = result
    return result


_SPECS: dict[type, tuple[ParamSpec, ...]] = {}


def _spec(name: str, hint: Any, default: Any, meta: dict[str, Any]) -> ParamSpec:
    args = typing.get_args(hint)
    if typing.get_origin(hint) is Literal:
        return ParamSpec(name, "dropdown", default, options=args, **_text(meta))
    optional = type(None) in args
    base = next((a for a in args if a is not type(None)), hint) if args else hint
    if base is bool:
        return ParamSpec(name, "checkbox", default, **_text(meta))
    if base in (int, float):
        kind: Kind = "auto" if optional else ("slider" if meta.get("slider") else "number")
        return ParamSpec(
            name,
            kind,
            default,
            lo=meta.get("lo"),
            hi=meta.get("hi"),
            slider=meta.get("slider"),
            integer=base is int,
            optional=optional,
            **_text(meta),
        )
    raise TypeError(f"parameter {name}: unsupported type {hint!r}")


def _text(meta: dict[str, Any]) -> dict[str, str]:
    return {k: meta.get(k, "") for k in ("unit", "symbol", "label", "doc")}


def _check_value(owner: str, spec: ParamSpec, value: Any) -> None:
    where = f"{owner}.{spec.name}"
    if value is None:
        if spec.optional:
            return
        raise ValueError(f"{where} must not be empty")
    if spec.kind == "dropdown":
        if value not in spec.options:
            opts = ", ".join(map(repr, spec.options))
            raise ValueError(f"{where} must be one of {opts}, got {value!r}")
        return
    if spec.kind == "checkbox":
        if not isinstance(value, bool):
            raise ValueError(f"{where} must be true or false, got {value!r}")
        return
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{where} must be a number, got {value!r}")
    if spec.integer and not isinstance(value, int):
        raise ValueError(f"{where} must be a whole number, got {value!r}")
    try:
        finite = math.isfinite(value)
    except OverflowError:  # an int beyond float range
        finite = False
    if not finite:
        raise ValueError(f"{where} must be a finite number in range, got {value!r:.40}")
    lo = -math.inf if spec.lo is None else spec.lo
    hi = math.inf if spec.hi is None else spec.hi
    if not lo <= value <= hi:
        raise ValueError(f"{where} must be in [{lo:g}, {hi:g}], got {value!r}")
