"""Parameter presets: TOML files with one table per stage (``[stereo]``, ``[spline]`` ...).

Unknown keys, wrong types and out-of-range values are rejected with the key's name; a parameter
a stage has retired (its Params' ``RETIRED``) is ignored with a warning, so that a preset saved
before still loads.

Storage: the built-in presets (the project's ``configs/``) are read-only. User presets live in
a user data folder (``serve --configs DIR``, else the platform's data dir, e.g.
``~/.local/share/threadrecon/presets``), never in the installed package. Writing never replaces
an existing preset unless asked to, never takes a built-in name, and goes through a temporary
file so that a crash cannot leave half a preset behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tempfile
import tomllib
import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, TypeVar

from threadrecon.app.errors import AlreadyExists, Forbidden, Invalid, NotFound
from threadrecon.app.resources import configs_dir, user_data_dir
from threadrecon.core.params import ParamSpec, specs
from threadrecon.core.pipeline import STAGE_BY_NAME, STAGES, ReconParams

NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # whole name only: use valid_name()
T = TypeVar("T")
HASH_HEX = 12  # 48 bits: no collision among the few hundred parameter sets of a study


def validate(data: dict[str, Any]) -> ReconParams:
    """``{stage: {name: value}}`` -> :class:`ReconParams`; errors name the offending key.

    Types, ranges and cross-field rules are the stages' own (``core.params``): this only turns
    TOML/JSON values into the declared types ("auto" for None, whole floats for ints).
    """
    if not isinstance(data, dict):
        raise ValueError("a preset must be a table of stage tables")
    params = ReconParams()
    for stage, values in data.items():
        if stage not in STAGE_BY_NAME:
            raise ValueError(f"unknown parameter group {stage!r} (known: {', '.join(STAGES)})")
        if not isinstance(values, dict):
            raise ValueError(f"{stage}: must be a table of parameters")
        cls = STAGE_BY_NAME[stage].params
        by_name = {spec.name: spec for spec in specs(cls)}
        clean: dict[str, Any] = {}
        for name, value in values.items():
            if name in cls.RETIRED:  # a preset saved before the parameter was retired
                warnings.warn(
                    f"{stage}.{name} is no longer a parameter ({cls.RETIRED[name]}): ignored",
                    stacklevel=2,
                )
                continue
            if name not in by_name:
                raise ValueError(f"unknown parameter {stage}.{name}")
            clean[name] = _coerce(by_name[name], value)
        try:
            group = replace(getattr(params, stage), **clean)
        except ValueError as exc:  # the stage's own check, named by stage rather than class
            raise ValueError(str(exc).replace(f"{cls.__name__}.", f"{stage}.")) from None
        params = replace(params, **{stage: group})
    return params


def _coerce(spec: ParamSpec, value: Any) -> Any:
    """A TOML/JSON value in the declared type where that is lossless; anything else is passed
    on unchanged for the Params check to reject with its own message."""
    if spec.optional and value == "auto":
        return None
    if spec.kind in ("slider", "number", "auto") and not isinstance(value, bool):
        if spec.integer and isinstance(value, float) and value.is_integer():
            return int(value)
        if not spec.integer and isinstance(value, int) and abs(value) < 2**53:
            return float(value)
    return value


def params_hash(params: ReconParams) -> str:
    """Short stable fingerprint of ``params``: the first 12 hex digits of the SHA-256 of the
    canonical JSON of :meth:`ReconParams.to_dict` (sorted keys, no whitespace, numbers as
    floats so that params equal under ``==``, e.g. ``seg_delta=6`` and ``6.0``, hash equally)."""
    numbers = {
        stage: {k: float(v) if type(v) is int else v for k, v in values.items()}
        for stage, values in params.to_dict().items()
    }
    canonical = json.dumps(numbers, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()[:HASH_HEX]


def read_toml(path: str | Path, what: str, parse: Callable[[dict[str, Any]], T]) -> T:
    """``parse`` of the TOML file at ``path``; every error is a ValueError naming the file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from None
    try:
        return parse(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def load_preset(path: str | Path) -> ReconParams:
    return read_toml(path, "preset", validate)


def valid_name(name: object) -> bool:
    """True for a preset name: letters, digits, '.', '_' or '-', at most 64, nothing else
    (``fullmatch``: a trailing newline is refused too)."""
    return isinstance(name, str) and NAME_RE.fullmatch(name) is not None


def default_configs_dir() -> Path:
    """The built-in presets (read-only)."""
    return configs_dir()


def user_configs_dir() -> Path:
    """The platform's folder for the user's presets (created on first save)."""
    return user_data_dir() / "presets"


def builtin_presets() -> list[str]:
    return sorted(p.stem for p in default_configs_dir().glob("*.toml") if valid_name(p.stem))


def find_preset(name: str, user_dir: Path | None = None) -> Path:
    """The file of preset ``name``: a built-in one, else one of ``user_dir``. Raises
    :class:`Invalid` for a bad name and :class:`NotFound` for an unknown one."""
    if not valid_name(name):
        raise Invalid(f"invalid preset name {name!r}")
    for folder in (default_configs_dir(), user_dir or user_configs_dir()):
        path = folder / f"{name}.toml"
        if path.is_file():
            return path
    raise NotFound(f"no preset {name!r} (presets: {', '.join(list_presets(user_dir))})")


def resolve_preset(name_or_path: str | None, configs_dir: Path | None = None) -> ReconParams:
    """A preset by file path, or by name (built-in, else in the user folder); None gives
    the defaults."""
    if name_or_path is None:
        return ReconParams()
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        return load_preset(p)
    try:
        return load_preset(find_preset(name_or_path, configs_dir))
    except LookupError as exc:
        raise ValueError(str(exc.args[0])) from None


def to_toml(params: ReconParams, header: str = "") -> str:
    lines = [f"# {line}" for line in header.splitlines()] if header else []
    for stage, values in params.to_dict().items():
        lines.append(f"\n[{stage}]")
        for name, value in values.items():
            if value is None:
                lines.append(f'{name} = "auto"')
            elif isinstance(value, bool):
                lines.append(f"{name} = {'true' if value else 'false'}")
            elif isinstance(value, str):
                lines.append(f'{name} = "{value}"')
            else:
                lines.append(f"{name} = {value!r}")
    return "\n".join(lines).lstrip("\n") + "\n"


def save_preset(
    params: ReconParams, name: str, folder: Path, overwrite: bool = False, header: str = ""
) -> Path:
    """Write ``folder/name.toml`` atomically; refuses an existing name unless ``overwrite``
    (:class:`Conflict`), a built-in name or the built-in folder (:class:`Forbidden`)."""
    if not valid_name(name):
        raise Invalid(f"invalid preset name {name!r}: letters, digits, '.', '_' or '-', at most 64")
    if name in builtin_presets():
        raise Forbidden(f"preset {name!r} is built in and read-only: save under another name")
    if folder.resolve() == default_configs_dir().resolve():
        raise Forbidden(f"{folder} holds the built-in presets: user presets go elsewhere")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.toml"
    if path.exists() and not overwrite:
        raise AlreadyExists(f"preset {name!r} exists: confirm to overwrite it")
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(to_toml(params, header))
    os.replace(tmp, path)
    return path


def diff(params: ReconParams, base: ReconParams | None = None) -> list[dict[str, Any]]:
    """The parameters whose value differs from ``base`` (default: the paper's defaults), as
    ``[{"key": "stage.name", "value": ..., "base": ...}]`` in stage order."""
    a, b = params.to_dict(), (base or ReconParams()).to_dict()
    return [
        {"key": f"{stage}.{name}", "value": value, "base": b[stage][name]}
        for stage, values in a.items()
        for name, value in values.items()
        if value != b[stage][name]
    ]


def list_presets(user_dir: Path | None = None) -> list[str]:
    """The built-in presets ("default" first), then the user's (a user file with a built-in
    name is ignored: built-ins cannot be shadowed)."""
    builtin = sorted(builtin_presets(), key=lambda n: n != "default")
    folder = user_dir or user_configs_dir()
    user = (
        sorted(p.stem for p in folder.glob("*.toml") if valid_name(p.stem))
        if folder.is_dir()
        else []
    )
    return builtin + [n for n in user if n not in builtin]
