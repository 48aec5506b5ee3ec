"""Pytest configuration: its presence puts ``tests/`` on ``sys.path`` (rootdir import mode),
so test modules can ``from support import ...``."""

from collections.abc import Iterator
from pathlib import Path

import pytest


@pytest.fixture(autouse=True, scope="session")
def _user_data_elsewhere(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The user data folder (presets, the bundled sample's ratings and corrections) is a
    temporary one for the whole run, for this process and the servers it starts: the suite
    never writes into the home of whoever runs it."""
    home = tmp_path_factory.mktemp("user-data")
    patch = pytest.MonkeyPatch()
    patch.setenv("XDG_DATA_HOME", str(home))
    yield home
    patch.undo()
