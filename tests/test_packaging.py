"""The built wheel: one import package ``threadrecon`` holding the core, the app, the page, the
built-in presets and the sample set; nothing else at the top level."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import threadrecon
from threadrecon.app import resources

REPO = Path(__file__).resolve().parent.parent
# what a checkout holds besides its source (the venv, caches, compiled kernels, builds, stores)
LOCAL_ONLY = (".venv", ".git", "build", "out", "__pycache__", "*.egg-info", ".*_cache", "*.sqlite3")


@pytest.fixture(scope="module")
def wheel_names(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    out = tmp_path_factory.mktemp("wheel")
    # built from a copy of the source: setuptools leaves a build/ folder where it builds, and a
    # stale one in the checkout would put deleted modules back into later wheels
    src = tmp_path_factory.mktemp("src") / "threadrecon"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(*LOCAL_ONLY))
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(out), str(src)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = out.glob("threadrecon-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        return zf.namelist()


def test_the_wheel_holds_one_package_with_its_data(wheel_names: list[str]) -> None:
    tops = {n.split("/", 1)[0] for n in wheel_names}
    assert tops == {"threadrecon", f"threadrecon-{threadrecon.__version__}.dist-info"}
    for needed in (
        "threadrecon/__init__.py",
        "threadrecon/py.typed",
        "threadrecon/core/pipeline.py",
        "threadrecon/app/cli.py",
        "threadrecon/app/views/__init__.py",
        "threadrecon/static/index.html",
        "threadrecon/configs/default.toml",
        "threadrecon/configs/paper-real.toml",
        "threadrecon/sample_data/README.md",
        "threadrecon/docs/result.schema.json",  # the result JSON's schema, for installed users
    ):
        assert needed in wheel_names, needed
    assert any(n.startswith("threadrecon/sample_data/simulated/") for n in wheel_names)
    assert not any(n.endswith(".sqlite3") or "__pycache__" in n for n in wheel_names)
    assert not any(n.startswith(("threadrecon/tests/", "threadrecon/.venv/")) for n in wheel_names)


def test_package_data_is_found_through_importlib_resources() -> None:
    assert (resources.static_dir() / "index.html").is_file()
    assert (resources.configs_dir() / "default.toml").is_file()
    assert (resources.sample_data_dir() / "simulated").is_dir()


def test_version_and_the_python_api_at_the_top() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "threadrecon.app.cli", "--version"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0 and proc.stdout.strip() == f"threadrecon {threadrecon.__version__}"
    from threadrecon import ThreadResult, reconstruct

    assert callable(reconstruct) and ThreadResult.__name__ == "ThreadResult"
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        _ = threadrecon.nothing
