"""Parameter presets: built-in ones (read-only) and the user's (a user data folder)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from threadrecon.app.api import schemas
from threadrecon.app.api.deps import State, answer
from threadrecon.app.errors import Unavailable
from threadrecon.app.presets import builtin_presets, diff, list_presets, params_hash, save_preset

router = APIRouter(prefix="/api/presets", tags=["presets"])


@router.get("")
def presets(state: State) -> list[str]:
    """Names of the presets: the built-in ones ("default" first), then the user's."""
    return list_presets(state.config.configs)


@router.get("/{name}")
def preset(state: State, name: str) -> JSONResponse:
    """A preset's values and its difference from the defaults; 422 names a bad key."""
    params = state.preset(name)
    return answer(
        {
            "name": name,
            "builtin": name in builtin_presets(),
            "params": params.to_dict(),
            "diff": diff(params),
        }
    )


@router.post("")
def save(state: State, body: schemas.SavePresetBody) -> schemas.SavedPreset:
    """Save the session's current parameters as a user preset. A built-in name is refused
    (403); an existing user preset (409) unless ``overwrite`` is true."""
    s = state.session(body.session)
    try:
        path = save_preset(
            s.params, body.name, state.config.configs, overwrite=body.overwrite,
            header=f"saved from the debugger; params hash {params_hash(s.params)}",
        )  # fmt: skip
    except OSError as exc:
        if isinstance(exc, FileExistsError):
            raise
        raise Unavailable(f"cannot write preset {body.name!r}: {exc}") from None
    s.rename_preset(body.name)
    return schemas.SavedPreset(name=body.name, path=str(path))
