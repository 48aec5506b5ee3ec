"""Fixtures of the app tests: one headless chromium for every browser test of the run.

Launching chromium costs ~1.5 s of CPU; a test gets its isolation from a new browser context
(its own cookies, storage and downloads), not from a browser process of its own.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from browser_support import browser, missing_browser


@pytest.fixture(scope="session")
def chromium() -> Iterator[Any]:
    """The run's headless system chromium (a playwright ``Browser``); skips when missing."""
    reason = missing_browser()
    if reason is not None:
        pytest.skip(reason)
    with browser() as b:
        yield b


@pytest.fixture()
def new_context(chromium: Any) -> Iterator[Any]:
    """``new_context(**options)``: a fresh context of the shared chromium; every context made
    through it is closed after the test (its pages would otherwise go on polling)."""
    made: list[Any] = []

    def new(**options: Any) -> Any:
        ctx = chromium.new_context(**options)
        made.append(ctx)
        return ctx

    yield new
    for ctx in made:
        ctx.close()
