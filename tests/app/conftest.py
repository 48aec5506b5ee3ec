"""Fixtures of the app tests: one headless chromium shared by consecutive browser tests.

Launching chromium costs ~1.5 s of CPU; a test gets its isolation from a new browser context
(its own cookies, storage and downloads), not from a browser process of its own. The browser
is closed after the last test of a run of tests that use it: playwright's sync API leaves its
event loop marked running in the thread while it is open, which would break a later test that
calls ``asyncio.run`` (e.g. tests/app/test_session.py).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from browser_support import browser, missing_browser


class SharedChromium:
    """The shared browser: launched on the first ``new_context``, closed by ``close``."""

    def __init__(self) -> None:
        self._cm: Any = None
        self._browser: Any = None

    def new_context(self, **options: Any) -> Any:
        """A new context (playwright ``BrowserContext``) of the running browser."""
        if self._browser is None:
            cm = browser()
            self._browser = cm.__enter__()
            self._cm = cm
        return self._browser.new_context(**options)

    def close(self) -> None:
        cm, self._cm, self._browser = self._cm, None, None
        if cm is not None:
            cm.__exit__(None, None, None)


_SHARED = SharedChromium()


@pytest.fixture(scope="session")
def chromium() -> SharedChromium:
    """The shared headless system chromium; skips when it is missing."""
    reason = missing_browser()
    if reason is not None:
        pytest.skip(reason)
    return _SHARED


@pytest.fixture()
def new_context(chromium: SharedChromium) -> Iterator[Any]:
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


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Close the shared chromium once the next test does not use it (after this test's
    fixtures, module-scoped contexts included, are finalised)."""
    yield
    if nextitem is None or "chromium" not in getattr(nextitem, "fixturenames", ()):
        _SHARED.close()
