"""Result fields computed on their first read.

A stage result may hold a field that no later stage reads (the threshold path's score maps,
the ordering's explanation graph): the debugger shows it, the pipeline does not need it. Such
a field is declared ``name: T = LazyField()`` on the frozen dataclass and may be given a
:class:`Deferred` instead of its value: the value is computed on the first read and kept.
Everything else about the field stays as it was: the generated ``__init__`` takes it by name
(dataclasses' descriptor-typed fields store through :meth:`LazyField.__set__`, also on a
frozen class), ``dataclasses.fields``, ``replace`` and ``asdict`` read it, and assigning to it
raises ``FrozenInstanceError``. Threads that read a deferred field at once compute it once:
the debugger's page answer and its 3D views read the ordering's graph concurrently (~90 ms at
1920x1080, which each used to compute).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

_NO_DEFAULT = object()
_COMPUTING = threading.RLock()  # one deferred value computed at a time (re-entrant: a
# deferred function may read another lazy field); reads of computed values never take it


class Deferred:
    """A field value computed on its first read: ``fn(*args)``."""

    __slots__ = ("args", "fn")

    def __init__(self, fn: Callable[..., Any], *args: Any) -> None:
        self.fn, self.args = fn, args


class LazyField:
    """A dataclass field whose value may be given as a :class:`Deferred` (module docstring).
    ``default``: the field's default value; none when not given."""

    def __init__(self, default: Any = _NO_DEFAULT) -> None:
        self.default = default

    def __set_name__(self, owner: type, name: str) -> None:
        self.slot = "_lazy_" + name

    def __get__(self, obj: object, owner: type | None = None) -> Any:
        if obj is None:  # the class's access: dataclasses asks for the default here
            if self.default is _NO_DEFAULT:
                raise AttributeError("no default")
            return self.default
        value = obj.__dict__[self.slot]
        if isinstance(value, Deferred):
            with _COMPUTING:
                value = obj.__dict__[self.slot]  # another thread may have computed it meanwhile
                if isinstance(value, Deferred):
                    value = value.fn(*value.args)
                    obj.__dict__[self.slot] = value
        return value

    def __set__(self, obj: object, value: Any) -> None:
        obj.__dict__[self.slot] = value
