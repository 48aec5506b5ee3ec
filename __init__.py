"""threadrecon: suture-thread 3D reconstruction from stereo endoscope images, with a browser debugger.

``threadrecon.core`` is the method (pure numpy/scipy/OpenCV, one module per stage) and
``threadrecon.app`` the command line, the debugger server and the Python API
(``threadrecon.app.python_api.reconstruct``).
"""

from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("threadrecon")
except _metadata.PackageNotFoundError:  # imported from a checkout that was never installed
    __version__ = "0+unknown"

__all__ = ["ThreadResult", "__version__", "reconstruct"]


def __getattr__(name: str) -> object:
    """``from threadrecon import reconstruct`` without importing the app for ``threadrecon.core``
    users (PEP 562)."""
    if name in ("reconstruct", "ThreadResult"):
        from threadrecon.app import python_api

        return getattr(python_api, name)
    raise AttributeError(f"module 'threadrecon' has no attribute {name!r}")
