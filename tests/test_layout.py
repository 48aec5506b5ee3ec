"""The house's shape as a checked contract: small app modules (the import layering itself is
checked by ``lint-imports`` in the test command, from pyproject.toml)."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_APP_MODULE_LINES = 400  # a module past this does several jobs: split it by subject


@pytest.mark.parametrize(
    "module", sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "app").rglob("*.py"))
)
def test_no_app_module_is_over_400_lines(module: str) -> None:
    lines = (ROOT / module).read_text(encoding="utf-8").count("\n")
    assert lines <= MAX_APP_MODULE_LINES, f"{module}: {lines} lines"
