"""The page's layout in a real browser at a laptop's size: every control of the centre
column (overlay toggles, correction tools) can be scrolled to and receives the click, i.e.
no panel (the evaluation and tune bars at the bottom) is drawn over it."""

from __future__ import annotations

import shutil

import pytest
from browser_support import SAMPLE, Server, missing_browser

pytestmark = pytest.mark.browser

_reason = missing_browser()
if _reason is not None:
    pytest.skip(_reason, allow_module_level=True)

_COVERED = """(sel) => [...document.querySelectorAll(sel)].filter((el) => {
    el.scrollIntoView({block: "nearest"});
    const r = el.getBoundingClientRect();
    const hit = document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2);
    return !(hit && (hit === el || el.contains(hit) || hit.contains(el)));
}).map((el) => el.id || el.textContent.trim() || el.outerHTML.slice(0, 60))"""


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """One server for the module: the tests only look at the page it serves."""
    data = tmp_path_factory.mktemp("layout") / "data"
    shutil.copytree(SAMPLE / "simulated" / "flat", data / "simulated" / "flat")
    with Server(data_dir=data) as s:
        yield s


@pytest.mark.parametrize("size", [(1280, 720), (1400, 900)])
def test_centre_controls_are_not_covered_by_the_bottom_bars(server, new_context, size):
    page = new_context(viewport={"width": size[0], "height": size[1]}).new_page()
    page.goto(server.url + "/")
    page.wait_for_function("window.threadrecon && window.threadrecon.state", timeout=60_000)
    page.wait_for_selector("#overlay-toggles input", timeout=60_000)
    page.wait_for_selector("#correct-tools button", timeout=60_000)
    for sel in ("#overlay-toggles input", "#correct-tools button"):
        assert page.locator(sel).count() > 0
        assert page.evaluate(_COVERED, sel) == [], f"{sel} covered at {size}"


_BOX = "(sel) => { const r = document.querySelector(sel).getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; }"


def _overlap(a: list[float], b: list[float]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def test_correction_toolbar_is_clear_of_the_bottom_bars_at_1280x720_without_scrolling(
    server, new_context
):
    page = new_context(viewport={"width": 1280, "height": 720}).new_page()
    page.goto(server.url + "/")
    page.wait_for_function("window.threadrecon && window.threadrecon.state", timeout=60_000)
    page.wait_for_selector("#correct-tools button", timeout=60_000)
    page.wait_for_function(  # the images are in: the centre column has its full height
        "() => document.querySelector('#img-left').height > 0", timeout=60_000
    )
    tools = page.evaluate(_BOX, "#correct-tools")
    for bar in ("#tune-section", "#evaluation-section"):
        assert not _overlap(tools, page.evaluate(_BOX, bar)), (bar, tools)
    assert tools[1] >= 0 and tools[3] <= page.evaluate(_BOX, "#evaluation-section")[1]
    for name in ("Undo", "Redo", "Clear"):  # visible where they are: no scrolling
        hit = page.evaluate(
            """(name) => { const b = [...document.querySelectorAll('#correct-tools button')]
                .find((x) => x.textContent.trim() === name);
              const r = b.getBoundingClientRect();
              return document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2) === b; }""",
            name,
        )
        assert hit, f"{name} is covered at 1280x720"
