"""Files that ship inside the package: the page's static files, the built-in presets and the
sample set. Read through ``importlib.resources`` so a wheel install and a checkout agree."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def package_dir(name: str) -> Path:
    """The folder ``name`` of the installed ``threadrecon`` package (``static``, ``configs`` or
    ``sample_data``), as a file-system path (the package is never installed zipped)."""
    return Path(str(resources.files("threadrecon").joinpath(name)))


def static_dir() -> Path:
    return package_dir("static")


def configs_dir() -> Path:
    return package_dir("configs")


def sample_data_dir() -> Path:
    return package_dir("sample_data")


def user_data_dir() -> Path:
    """The platform's folder for what the user makes (presets, the bundled sample's ratings):
    never inside the installed package, which an upgrade replaces."""
    import platformdirs

    return Path(platformdirs.user_data_dir("threadrecon", appauthor=False))


DB_NAME = "threadrecon.sqlite3"


def default_db(data_dir: Path) -> Path:
    """Where ratings, evaluations and corrections of ``data_dir`` are kept unless ``--db`` says:
    ``<data_dir>/threadrecon.sqlite3``, or ``sample_data.sqlite3`` in the user data folder for
    the bundled sample (never inside the package). The folder may not exist yet."""
    if Path(data_dir).resolve() == sample_data_dir().resolve():
        return user_data_dir() / "sample_data.sqlite3"
    return Path(data_dir) / DB_NAME
