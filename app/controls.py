"""The debugger's controls: one per parameter of the core, grouped by stage.

Sliders get a range that covers sensible tuning (the presets' validation ranges in
``app.presets.RANGES`` are wider); booleans are checkboxes, choices are dropdowns, and any
other number is a number field. The list is built from :class:`core.pipeline.ReconParams`,
so a new parameter of the core shows up without touching this file.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, fields
from typing import Any, Literal

from app.presets import RANGES
from core.pipeline import STAGES, ReconParams

Kind = Literal["slider", "checkbox", "dropdown", "number"]

# (min, max, step, label) of the sliders; the step also fixes int vs float.
SLIDERS: dict[str, tuple[float, float, float, str]] = {
    "segment.seg_delta": (0, 60, 1, "seg threshold δ"),
    "segment.min_component_px": (0, 100, 1, "min component px"),
    "segment.lift_dilate_px": (0, 4, 1, "lift dilation px"),
    "stereo.alpha": (8, 200, 1, "α max disparity"),
    "stereo.window": (3, 21, 2, "window px"),
    "reliability.eps1": (0.0, 30.0, 0.1, "ε1"),
    "reliability.eps2": (0.1, 30.0, 0.1, "ε2"),
    "reliability.eps3": (-5.0, 5.0, 0.01, "ε3"),
    "reliability.threshold": (0.0, 0.99, 0.01, "threshold"),
    "clustering.radius": (1, 6, 1, "neighbour radius"),
    "clustering.min_size": (1, 100, 1, "min size"),
    "clustering.max_size": (1, 200, 1, "max size"),
    "ordering.solidify_radius": (0, 6, 1, "solidify radius"),
    "ordering.extension_min_px": (0, 60, 1, "extension min px"),
    "ordering.tip_px": (0.0, 10.0, 0.5, "tip px"),
    "ordering.bridge_px": (0.0, 300.0, 5.0, "bridge px"),
    "bounds.extra_px": (4, 100, 1, "extra point spacing px"),
    "bounds.r_k_frac": (0.0, 0.5, 0.01, "r_k = |K| ×"),
    "bounds.r_k_min": (1, 20, 1, "r_k min"),
    "bounds.bound_scale": (1.0, 5.0, 0.05, "bound scale"),
    "bounds.widen_px": (0.0, 3.0, 0.05, "widen threshold"),
    "spline.n_ctrl": (5, 40, 1, "control points m"),
    "spline.degree": (2, 5, 1, "degree"),
    "spline.max_iter": (1, 500, 1, "solver iterations"),
    "spline.quad_per_span": (1, 10, 1, "quadrature nodes / span"),
    "spline.bound_tol": (0.0, 0.5, 0.01, "bound tolerance"),
    "spline.data_weight": (0.0, 100.0, 0.5, "data weight"),
    "spline.xy_tol_px": (0.1, 5.0, 0.1, "x,y knot split tolerance px"),
    "camera.n_points": (200, 2000, 50, "dense points"),
}


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
        }


def controls() -> tuple[Control, ...]:
    """Every parameter of :class:`ReconParams` as a control, in stage order."""
    out: list[Control] = []
    defaults = ReconParams()
    for stage in STAGES:
        group = getattr(defaults, stage)
        hints = typing.get_type_hints(type(group))
        for f in fields(group):
            key = f"{stage}.{f.name}"
            hint = hints[f.name]
            args = typing.get_args(hint)
            if typing.get_origin(hint) is typing.Literal:
                out.append(Control(stage, f.name, f.name, "dropdown", options=tuple(args)))
            elif hint is bool:
                out.append(Control(stage, f.name, f.name, "checkbox"))
            elif type(None) in args:
                continue  # "auto" parameters (e.g. the estimated background) live in presets
            elif key in SLIDERS:
                lo, hi, step, label = SLIDERS[key]
                out.append(
                    Control(stage, f.name, label, "slider", lo, hi, step, integer=hint is int)
                )
            elif hint in (int, float):
                lo, hi = RANGES.get(key, (None, None))
                out.append(Control(stage, f.name, f.name, "number", lo, hi, integer=hint is int))
    return tuple(out)
