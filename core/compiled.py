"""Compiled kernels that run without numba in the process.

The core's loops over pixels and keypoints (the threshold segmentation's histogram, the raw
segmentation's filters and pieces in ``ridge_kernel`` and its mask growth in
``grow_kernel``, stereo and its continuity set-up,
clustering, the ordering walk and its gap geodesics in ``walk_kernel``, the spline's basis in
``spline_kernel``, the two-view refinement's runs and rounds in ``refine_kernel``, the check's
``check_kernel``, a raw rig's resampling in ``remap_kernel``) are numba functions. Loading numba costs more than the rest of a 1920x1080 reconstruction: importing it
maps llvmlite (~62 MB of resident memory) and the first call of a cached kernel builds its
typing and target contexts and the LLVM JIT (~42 MB, 0.5-1.3 s), against ~40 MB for a
frame's images and ~37 MB for its lifted pair (issue #13, "peak RSS <= 300 MB").

So each kernel module's kernels are compiled ahead of time, once per machine, into one small
extension module (numba's AOT compiler, ``numba.pycc``; ~1 MB, no numba needed to load it),
kept in the module's ``__pycache__`` (else the user's cache folder; ``$THREADRECON_KERNEL_CACHE``
overrides both) under a name that hashes the module's source, the signatures and the Python
and numpy versions: an edit of the module builds anew (so a kernel reads no other module's
globals: they come in as arguments). The first process builds it (numba imported then, as
numba's own cache compiles on first use); later processes load it. Where it cannot be built (no C compiler, a numba without ``pycc``)
or with ``THREADRECON_KERNELS=jit`` every kernel is the numba JIT function of the same source,
``cache=True, nogil=True``, as before.

A kernel declares its signature (numba's syntax): the AOT function takes exactly those types
and would read memory wrongly given others, so every call checks the dtype, the dimensions
and (for ``::1``) the C order of each array argument first (a ``TypeError`` naming the
argument; ~2 us a call). The JIT compiles for the layout it is given: declare arrays that are
always C-contiguous ``[::1]`` / ``[:, ::1]``, or the AOT code indexes them with strides (10-20 %
slower).
Functions that kernels call (helpers) are declared with :func:`helper`; in the JIT they are
``numba.njit`` functions with the same options.

Difference from the JIT: an AOT function holds the GIL while it runs (``nogil`` is a JIT
option only), so two pipelines in two threads of one process do not run their kernels at
the same time.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import inspect
import os
import re
import sys
import sysconfig
import tempfile
import threading
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

MODE_ENV = "THREADRECON_KERNELS"  # "jit": numba's JIT only (e.g. to compare with the AOT build)
CACHE_ENV = "THREADRECON_KERNEL_CACHE"  # where the AOT modules go instead of __pycache__

_DTYPES = {
    "int64": np.dtype(np.int64),
    "int32": np.dtype(np.int32),
    "float64": np.dtype(np.float64),
    "float32": np.dtype(np.float32),
    "boolean": np.dtype(np.bool_),
    "uint8": np.dtype(np.uint8),
}
_ARG = re.compile(r"\s*(\w+)\s*(\[[^\]]*\])?\s*(?:,|$)")

_lock = threading.RLock()
_modules: dict[str, _KernelModule] = {}
_default_mode = "aot"


def set_default_mode(mode: str) -> None:
    """The kernels' backend when ``$THREADRECON_KERNELS`` is unset: "aot" (default) or "jit"
    (numba's, ~100 MB more, but its kernels release the GIL: a server whose threads run
    pipelines while others serve requests). Takes effect for modules not resolved yet."""
    global _default_mode
    if mode not in ("aot", "jit"):
        raise ValueError(f"kernel mode must be 'aot' or 'jit', got {mode!r}")
    _default_mode = mode


def kernel(signature: str) -> Callable[[Callable[..., Any]], Kernel]:
    """Declare ``fn`` a compiled kernel of signature ``"ret(arg, ...)"`` (numba's syntax, e.g.
    ``"UniTuple(int64, 2)(int64[:], float64)"``); arrays are checked on every call."""

    def wrap(fn: Callable[..., Any]) -> Kernel:
        k = Kernel(fn, signature)
        _module_of(fn).kernels.append(k)
        return k

    return wrap


def helper(**options: Any) -> Callable[[Callable[..., Any]], Helper]:
    """Declare ``fn`` a function that kernels call (``numba.njit(**options)`` when compiled,
    e.g. ``inline="always"``); it is not called from Python."""

    def wrap(fn: Callable[..., Any]) -> Helper:
        h = Helper(fn, options)
        _module_of(fn).helpers.append(h)
        return h

    return wrap


class Helper:
    """A function that compiled kernels call; only compiled with them."""

    def __init__(self, fn: Callable[..., Any], options: dict[str, Any]) -> None:
        self.fn = fn
        self.options = options
        self.name = fn.__name__
        self.__doc__ = fn.__doc__

    def __call__(self, *args: Any) -> Any:
        raise TypeError(f"{self.name} is a helper of compiled kernels, not callable from Python")


class Kernel:
    """A compiled function: the AOT build's, else numba's JIT; resolved on the first call."""

    def __init__(self, fn: Callable[..., Any], signature: str) -> None:
        self.fn = fn
        self.name = fn.__name__
        self.signature = signature
        self.__doc__ = fn.__doc__
        self.__wrapped__ = fn
        self._arrays = _array_args(signature, fn)
        self._call: Callable[..., Any] | None = None

    def __call__(self, *args: Any) -> Any:
        call = self._call
        if call is None:
            call = self._resolve()
        return call(*args)

    @property
    def backend(self) -> str:
        """ "aot" or "jit" once resolved (resolves it)."""
        self._call or self._resolve()
        return _module_of(self.fn).backend  # type: ignore[return-value]

    def _resolve(self) -> Callable[..., Any]:
        with _lock:
            if self._call is None:
                _module_of(self.fn).load()
            return self._call  # type: ignore[return-value]

    def _checked(self, compiled: Callable[..., Any]) -> Callable[..., Any]:
        arrays, name = self._arrays, self.name
        ndarray = np.ndarray

        def call(*args: Any) -> Any:
            for i, arg_name, dtype, ndim, contiguous in arrays:
                a = args[i]
                # the common case first: a plain array of the builtin dtype (numpy's one
                # instance of it), tested by identity (~2 us a call less on the check's ~24
                # calls a run); anything else takes the full test below
                if (
                    a.__class__ is ndarray
                    and a.dtype is dtype
                    and a.ndim == ndim
                    and (not contiguous or a.flags.c_contiguous)
                ):
                    continue
                if (
                    not isinstance(a, np.ndarray)
                    or a.dtype != dtype
                    or a.ndim != ndim
                    or (contiguous and not a.flags.c_contiguous)
                ):
                    got = (
                        f"{a.dtype} {a.shape}{'' if a.flags.c_contiguous else ' strided'}"
                        if isinstance(a, np.ndarray)
                        else type(a).__name__
                    )
                    want = f"{ndim}-D {dtype}{' C-contiguous' if contiguous else ''} array"
                    raise TypeError(f"{name}: {arg_name} must be a {want}, got {got}")
            return compiled(*args)

        return call


def _array_args(
    signature: str, fn: Callable[..., Any]
) -> list[tuple[int, str, np.dtype, int, bool]]:
    """(position, name, dtype, ndim, C-contiguous) of each array argument of ``signature``
    (``[:, ::1]``: C-contiguous, which compiles to faster indexing than ``[:, :]``)."""
    names = list(inspect.signature(fn).parameters)
    inner = signature[signature.rindex("(") + 1 : signature.rindex(")")]
    args = [(m.group(1), m.group(2)) for m in _ARG.finditer(inner) if m.group(1)]
    if len(args) != len(names):
        raise ValueError(
            f"{fn.__name__}: the signature has {len(args)} arguments, the function {len(names)}"
        )
    out = []
    for i, (type_name, dims) in enumerate(args):
        if type_name not in _DTYPES:
            raise ValueError(f"{fn.__name__}: unsupported type {type_name!r} in the signature")
        if dims is not None:
            out.append((i, names[i], _DTYPES[type_name], dims.count(",") + 1, "::1" in dims))
    return out


def _module_of(fn: Callable[..., Any]) -> _KernelModule:
    name = fn.__module__
    with _lock:
        if name not in _modules:
            _modules[name] = _KernelModule(name)
        return _modules[name]


class _KernelModule:
    """The kernels and helpers of one Python module, built into one AOT extension."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.kernels: list[Kernel] = []
        self.helpers: list[Helper] = []
        self.backend: str | None = None
        self.built = False
        """The AOT module was compiled in this process (numba imported, ~450 MB at the peak)."""

    def key(self) -> str:
        """Hash of what the AOT module is built from: the module's whole source (a kernel reads
        its module's constants too), the signatures, the Python and numpy versions."""
        h = hashlib.sha256()
        for part in (sys.version, np.__version__, sysconfig.get_config_var("EXT_SUFFIX") or ""):
            h.update(part.encode())
        h.update(Path(sys.modules[self.name].__file__).read_bytes())  # type: ignore[arg-type]
        for k in self.kernels:
            h.update(f"{k.name}:{k.signature}".encode())
        for hp in self.helpers:
            h.update(f"{hp.name}:{sorted(hp.options.items())}".encode())
        return h.hexdigest()[:16]

    def aot_name(self) -> str:
        return f"{self.name.rsplit('.', 1)[-1]}_aot_{self.key()}"

    def cache_dir(self) -> Path:
        """``$THREADRECON_KERNEL_CACHE``, else the module's ``__pycache__`` where it can be
        written, else the user's cache folder (an installation the user cannot write to)."""
        env = os.environ.get(CACHE_ENV)
        if env:
            return Path(env)
        here = Path(sys.modules[self.name].__file__).resolve().parent  # type: ignore[arg-type]
        pycache = here / "__pycache__"
        if os.access(pycache if pycache.is_dir() else here, os.W_OK):
            return pycache
        user = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        return Path(user) / "threadrecon" / "kernels"

    def load(self) -> None:
        """Bind every kernel to its AOT function (building the extension if missing), or to
        numba's JIT."""
        mode = os.environ.get(MODE_ENV, _default_mode).lower()
        if mode not in ("aot", "jit"):
            raise ValueError(f"{MODE_ENV} must be 'aot' or 'jit', got {mode!r}")
        if mode == "aot":
            try:
                ext = self._load_or_build()
            except Exception as exc:  # no compiler, no numba.pycc, unwritable cache: the JIT
                warnings.warn(
                    f"{self.name}: the ahead-of-time kernels could not be built ({exc}); "
                    "using numba's JIT",
                    RuntimeWarning,
                    stacklevel=4,
                )
            else:
                for k in self.kernels:
                    k._call = k._checked(getattr(ext, k.name))
                self.backend = "aot"
                return
        jitted = self._jit()
        for k in self.kernels:
            k._call = jitted[k.name]
        self.backend = "jit"

    def _load_or_build(self) -> Any:
        name = self.aot_name()
        suffix = sysconfig.get_config_var("EXT_SUFFIX") or ".so"
        path = self.cache_dir() / f"{name}{suffix}"
        if not path.exists():
            with _file_lock(path.parent / f"{name}.lock"):  # one process builds, the others wait
                if not path.exists():
                    self._build(name, path)
                    self.built = True
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            raise ImportError(f"cannot load {path}")
        ext = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(ext)
        return ext

    def _jit(self, cache: bool = True) -> dict[str, Any]:
        """numba dispatchers of the helpers and kernels; the module's globals name them while
        numba compiles (a kernel reads the functions it calls from there)."""
        import numba

        g = sys.modules[self.name].__dict__
        out: dict[str, Any] = {}
        for hp in self.helpers:
            out[hp.name] = numba.njit(cache=cache, nogil=True, **hp.options)(hp.fn)
        for k in self.kernels:
            out[k.name] = numba.njit(cache=cache, nogil=True)(k.fn)
        g.update(out)  # a kernel calling another (or a helper) finds its dispatcher
        return out

    def _build(self, name: str, path: Path) -> None:
        """Compile every kernel of the module into the extension ``path`` (atomically: a
        process that loads it meanwhile sees the old file or the complete new one)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numba.pycc is pending deprecation
            from numba.pycc import CC

        g = sys.modules[self.name].__dict__
        saved = {f.name: g[f.name] for f in [*self.helpers, *self.kernels]}
        try:
            self._jit(cache=False)
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=path.parent, prefix=".build-") as tmp:
                cc = CC(name)
                cc.output_dir = tmp
                cc.target_cpu = "host"  # built on the machine that runs it
                cc.verbose = False
                for k in self.kernels:
                    cc.export(k.name, k.signature)(k.fn)
                cc.compile()
                os.replace(Path(tmp) / path.name, path)
        finally:
            g.update(saved)
        prefix = name.rsplit("_", 1)[0] + "_"
        for old in path.parent.glob(f"{prefix}*"):  # builds (and locks) of earlier sources
            if old.is_file() and not old.name.startswith(name):
                old.unlink(missing_ok=True)


@contextlib.contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    """An exclusive lock on ``path`` across processes (POSIX ``flock``; none elsewhere)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        try:
            import fcntl
        except ImportError:  # pragma: no cover - Windows: concurrent builds replace atomically
            yield
            return
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def backends() -> dict[str, str | None]:
    """Module name -> "aot", "jit" or None (not used yet) of every kernel module."""
    with _lock:
        return {name: m.backend for name, m in _modules.items()}


def built_here() -> list[str]:
    """The kernel modules whose AOT extension this process compiled (its memory and time
    count in this process's figures)."""
    with _lock:
        return [name for name, m in _modules.items() if m.built]
