"""The debugger in a real browser: headless system chromium (playwright) on a ``threadrecon
serve`` subprocess. The tests share one server and one tab and run in file order:

1. the viser iframe renders the 3D scene (coloured thread layers on its WebGL canvas);
2. the reliability threshold slider *of the viser GUI* changes the reliable-pixel layer
   (page overlay count, REST count, session params);
3. "Next step" reveals the stages one by one, "Run all" reveals them all;
4. a click on a thread pixel of the left image shows its energy curve;
5. a second tab changes its own parameters without disturbing the first tab.

Uncaught errors and console errors of the page fail the test that was running.
"""

from __future__ import annotations

import re
import time
import warnings
from typing import Any

import cv2
import numpy as np
import pytest
from browser_support import (
    TISSUE,
    VIEWPORT,
    Server,
    missing_browser,
    png_stats,
    wait_idle,
)

from threadrecon.core.pipeline import STAGES

pytestmark = pytest.mark.browser

_reason = missing_browser()
if _reason is not None:
    pytest.skip(_reason, allow_module_level=True)

RELIABILITY_FOLDER = "3. reliability"
THRESHOLD_SLIDER = 3  # ε1, ε2, ε3, threshold


class Tab:
    """One browser tab on the debugger, with the errors it reported."""

    def __init__(self, context: Any, server: Server) -> None:
        self.server = server
        self.page = context.new_page()
        self.errors: list[str] = []
        self.notes: list[str] = []  # messages of the viser client, reported on failure only
        self.warnings: list[str] = []  # failed requests of the page
        self.page.on("pageerror", self._on_pageerror)
        self.page.on("console", self._on_console)
        self.page.goto(server.url + "/", wait_until="load")
        self.page.wait_for_function(
            "window.threadrecon && window.threadrecon.session && window.threadrecon.state",
            timeout=60_000,
        )
        self.viewer = self.page.frame_locator("#viewer")

    def _own(self, url: str) -> bool:
        return url.startswith(self.server.url)

    def _on_pageerror(self, exc: Any) -> None:
        stack = getattr(exc, "stack", "") or ""
        if f":{self.server.viser_port}" in stack and self.server.url not in stack:
            self.notes.append(f"viser pageerror: {exc}")
        else:
            self.errors.append(f"pageerror: {exc}\n{stack}")

    def _on_console(self, msg: Any) -> None:
        if msg.type != "error":
            return
        url = (msg.location or {}).get("url", "")
        if not self._own(url):
            self.notes.append(f"console error (viser) at {url}: {msg.text}")
        elif msg.text.startswith("Failed to load resource"):
            # An API answer >= 400 that the page handles (e.g. "nothing yet"): reported only.
            self.warnings.append(f"{url}: {msg.text}")
        else:
            self.errors.append(f"console error at {url}: {msg.text}")

    # --- state --------------------------------------------------------------------------------

    @property
    def sid(self) -> str:
        return self.page.evaluate("window.threadrecon.session")

    @property
    def frame_id(self) -> str:
        """The frame the tab's session shows (a new tab opens the first frame of the list)."""
        return self.page.evaluate("window.threadrecon.state.frame_id")

    def api_state(self) -> dict[str, Any]:
        return self.server.api(f"/api/sessions/{self.sid}")

    def api_count(self) -> int:
        return self.server.api(f"/api/sessions/{self.sid}/stages/reliability")["result"]["count"]

    def wait_overlay(self, frame_id: str) -> None:
        """Wait until the 2D overlays belong to the session's newest state of ``frame_id``."""
        self.page.wait_for_function(
            """(fid) => {
                const S = window.threadrecon;
                return S.state && !S.state.busy && S.overlay && S.overlay.frame_id === fid
                    && S.overlayVersion === S.version && S.overlay.reliable;
            }""",
            arg=frame_id, timeout=60_000,
        )  # fmt: skip

    def page_count(self) -> int:
        text = self.page.locator('[data-count="reliable"]').inner_text()
        m = re.fullmatch(r"\((\d+)\)", text.strip())
        assert m, f"the reliable count shows {text!r}"
        return int(m.group(1))

    def select(self, frame_id: str) -> None:
        self.page.locator(f'#frames tr[data-id="{frame_id}"]').click()
        wait_idle(self.page, frame_id)
        self.wait_overlay(frame_id)

    # --- viser GUI ----------------------------------------------------------------------------

    def viser_sliders(self, folder: str) -> Any:
        """Expand the viser GUI folder ``folder`` and return the locator of its slider thumbs."""
        header = self.viewer.get_by_text(folder, exact=True)
        header.wait_for(timeout=60_000)
        sliders = header.locator("xpath=..").get_by_role("slider")
        if sliders.count() == 0:  # collapsed: its content is inert, hence not in the a11y tree
            header.click()
            sliders.first.wait_for(timeout=30_000)
        return sliders

    def check_errors(self) -> None:
        errors, self.errors = self.errors, []
        warned, self.warnings = sorted(set(self.warnings)), []
        for w in warned:
            warnings.warn(f"failed request in the page: {w}", stacklevel=2)
        notes = "\n".join(["", "viser client:", *self.notes]) if self.notes else ""
        assert not errors, "errors in the page:\n" + "\n".join(errors) + notes


@pytest.fixture(scope="module")
def server():
    with Server() as srv:
        yield srv


@pytest.fixture(scope="module")
def context(server, chromium):
    ctx = chromium.new_context(viewport=VIEWPORT)
    ctx.set_default_timeout(60_000)
    yield ctx
    ctx.close()


@pytest.fixture(scope="module")
def tab(context, server):
    t = Tab(context, server)
    yield t
    t.page.close()


@pytest.fixture(autouse=True)
def _no_page_errors(request, server):
    yield
    if "tab" in request.fixturenames:
        request.getfixturevalue("tab").check_errors()


def coloured_pixels(png: bytes, masks: list[tuple[int, int, int, int]]) -> int:
    """Pixels of a screenshot with a clear hue (thread layers, frustums), outside ``masks``
    (x, y, w, h boxes of the GUI drawn over the canvas)."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.int16)
    keep = np.ones(img.shape[:2], bool)
    for x, y, w, h in masks:
        keep[max(0, y) : max(0, y + h), max(0, x) : max(0, x + w)] = False
    chroma = img.max(axis=2) - img.min(axis=2)
    return int(((chroma > 60) & keep).sum())


def test_viewer_renders_the_scene(tab):
    page, viewer = tab.page, tab.viewer
    wait_idle(page, tab.frame_id)
    canvas = viewer.locator("canvas").first
    canvas.wait_for(timeout=60_000)
    # The viewer's GUI panel and notifications sit on the canvas: mask them out.
    frame_box = page.locator("#viewer").bounding_box()
    viewer.get_by_text("Connected", exact=True).wait_for(timeout=60_000)
    masks = []
    for sel in ("[data-dock-group]", ".mantine-Notification-root"):
        for i in range(viewer.locator(sel).count()):
            b = viewer.locator(sel).nth(i).bounding_box()
            if b:
                masks.append(
                    (int(b["x"] - frame_box["x"]) - 4, int(b["y"] - frame_box["y"]) - 4,
                     int(b["width"]) + 8, int(b["height"]) + 8)
                )  # fmt: skip
    assert masks, "the viser control panel was not found"
    # The scene arrives over the websocket after the canvas exists: give it a few frames.
    n, deadline = 0, time.monotonic() + 45
    while time.monotonic() < deadline:
        png = page.locator("#viewer").screenshot()
        std, colours = png_stats(png)
        n = coloured_pixels(png, masks)
        if n > 300 and std > 5 and colours > 50:
            break
        time.sleep(1.0)
    assert n > 300, f"the 3D view shows no thread ({n} coloured pixels, std {std:.1f})"


def test_viser_threshold_slider_changes_reliable_pixels(tab):
    page = tab.page
    tab.select(TISSUE)
    before_page, before_api = tab.page_count(), tab.api_count()
    assert before_page == before_api > 0
    assert tab.api_state()["params"]["reliability"]["threshold"] == pytest.approx(0.9)

    sliders = tab.viser_sliders(RELIABILITY_FOLDER)
    assert sliders.count() == 4, "expected ε1, ε2, ε3, threshold in the reliability folder"
    thumb = sliders.nth(THRESHOLD_SLIDER)
    assert float(thumb.get_attribute("aria-valuemax")) == pytest.approx(0.99)
    thumb.focus()
    thumb.press("End")  # -> 0.99: fewer pixels pass R > threshold
    page.wait_for_function(
        "() => window.threadrecon.state.params.reliability.threshold > 0.985", timeout=30_000
    )
    wait_idle(page, TISSUE)
    tab.wait_overlay(TISSUE)
    high_page, high_api = tab.page_count(), tab.api_count()
    assert high_page == high_api
    assert high_api < before_api, f"threshold 0.99 kept {high_api} of {before_api} pixels"
    st = tab.api_state()
    assert st["params"]["reliability"]["threshold"] == pytest.approx(0.99)
    assert st["preset"] == "custom"
    assert st["frame_id"] == TISSUE

    # The number field next to the slider: a lower threshold keeps more pixels.
    field = thumb.locator(
        "xpath=ancestor::div[contains(@class,'mantine-Slider-root')]/following-sibling::div//input"
    )
    field.fill("0.5")
    field.press("Enter")
    page.wait_for_function(
        "() => Math.abs(window.threadrecon.state.params.reliability.threshold - 0.5) < 1e-9",
        timeout=30_000,
    )
    wait_idle(page, TISSUE)
    tab.wait_overlay(TISSUE)
    low_page, low_api = tab.page_count(), tab.api_count()
    assert low_page == low_api >= before_api
    assert float(thumb.get_attribute("aria-valuenow")) == pytest.approx(0.5)


def test_overlay_toggles_come_from_the_server(tab):
    page = tab.page
    info = tab.server.api("/api/info")
    keys = page.locator("#overlay-toggles input").evaluate_all("els => els.map(e => e.dataset.ov)")
    assert keys == [o["key"] for o in info["overlays"]]
    checked = page.locator("#overlay-toggles input").evaluate_all("els => els.map(e => e.checked)")
    assert checked == [o["on"] for o in info["overlays"]]


def test_next_step_reveals_stages_in_order(tab):
    page = tab.page
    if tab.api_state()["frame_id"] != TISSUE:
        tab.select(TISSUE)
    wait_idle(page, TISSUE)
    for k in range(1, len(STAGES) + 1):
        page.locator("#btn-next").click()
        stage = STAGES[k - 1]
        page.wait_for_function(
            """([k, stage]) => {
                const shown = [...document.querySelectorAll('#stepper li:not(.hidden)')];
                const li = document.querySelector(`#stepper li[data-stage="${stage}"]`);
                return shown.length === k && li && !li.classList.contains('hidden')
                    && ['done', 'cached'].includes(li.dataset.status)
                    && !window.threadrecon.state.busy;
            }""",
            arg=[k, stage], timeout=30_000,
        )  # fmt: skip
        shown = page.locator("#stepper li:not(.hidden)").evaluate_all(
            "els => els.map(e => e.dataset.stage)"
        )
        assert shown == list(STAGES[:k])
        hidden = page.locator("#stepper li.hidden").evaluate_all(
            "els => els.map(e => [e.dataset.stage, e.dataset.status])"
        )
        assert [s for s, _ in hidden] == list(STAGES[k:])
        assert all(status == "pending" for _, status in hidden), hidden
        assert tab.api_state()["reveal"] == k
    # One more "Next step" starts over at the first stage; "Run all" reveals every stage.
    page.locator("#btn-next").click()
    page.wait_for_function(
        "() => document.querySelectorAll('#stepper li:not(.hidden)').length === 1"
    )
    page.locator("#btn-all").click()
    wait_idle(page, TISSUE)
    assert page.locator("#stepper li:not(.hidden)").count() == len(STAGES)
    statuses = page.locator("#stepper li").evaluate_all("els => els.map(e => e.dataset.status)")
    assert all(s in ("done", "cached", "fallback") for s in statuses), statuses


def test_pixel_inspector_shows_the_energy_curve(tab):
    page = tab.page
    wait_idle(page, TISSUE)
    tab.wait_overlay(TISSUE)
    reliable = page.evaluate("window.threadrecon.overlay.reliable.left")
    assert len(reliable) >= 2
    i = (len(reliable) // 4) & ~1  # a pixel a quarter along the list
    x, y = reliable[i], reliable[i + 1]
    canvas = page.locator("#img-left")
    canvas.scroll_into_view_if_needed()
    size = canvas.evaluate("c => [c.width, c.height]")
    box = canvas.bounding_box()
    canvas.click(
        position={
            "x": (x + 0.5) * box["width"] / size[0],
            "y": (y + 0.5) * box["height"] / size[1],
        }
    )
    energy = page.locator("#energy")
    page.wait_for_function("() => document.querySelector('#energy').dataset.pixel", timeout=30_000)
    # The image is drawn smaller than its size and mouse positions are whole CSS pixels, so the
    # click lands within a pixel or two of (x, y); the server snaps it to a thread pixel.
    px, py = (int(v) for v in energy.get_attribute("data-pixel").split(","))
    assert abs(px - x) <= 3 and abs(py - y) <= 3, f"inspected ({px}, {py}), clicked ({x}, {y})"
    info = page.locator("#pixel-info").inner_text()
    assert f"pixel ({px}, {py})" in info and "E_min" in info and "E_next" in info, info
    assert "reliable" in info, info
    std, colours = png_stats(energy.screenshot())
    assert std > 3 and colours > 5, f"the energy plot looks blank (std {std:.1f})"
    # The session knows the inspected pixel (the 3D view marks it).
    st = tab.api_state()
    assert (st["inspect"]["x"], st["inspect"]["y"]) == (px, py)
    assert {"d_min", "d_next", "E_min", "energy"} <= set(st["inspect"])


def test_second_tab_does_not_disturb_the_first(tab, context, server):
    first = tab.api_state()
    first_count = tab.api_count()
    first_slider = tab.viser_sliders(RELIABILITY_FOLDER).nth(THRESHOLD_SLIDER)
    first_value = first_slider.get_attribute("aria-valuenow")

    other = Tab(context, server)
    try:
        assert other.sid != tab.sid
        wait_idle(other.page, other.frame_id)
        thumb = other.viser_sliders(RELIABILITY_FOLDER).nth(THRESHOLD_SLIDER)
        thumb.focus()
        thumb.press("Home")  # threshold 0 in the second tab only
        other.page.wait_for_function(
            "() => window.threadrecon.state.params.reliability.threshold === 0", timeout=30_000
        )
        wait_idle(other.page, other.frame_id)
        assert other.api_state()["params"]["reliability"]["threshold"] == 0
        other.check_errors()
    finally:
        other.page.close()

    now = tab.api_state()
    for key in ("params", "frame_id", "status", "reveal", "preset", "stages"):
        assert now[key] == first[key], f"the second tab changed the first tab's {key}"
    assert now["version"] == first["version"]
    assert tab.api_count() == first_count
    assert tab.page_count() == first_count
    assert first_slider.get_attribute("aria-valuenow") == first_value


def test_ordering_graph_overlay_draws_its_costs_when_toggled(tab):
    # A generic overlay of kind "segments": its toggle draws the pieces and the labelled
    # continuations on the left image; the badge counts the cost labels the server sent.
    # Off when the page opens, it is neither built nor sent until it is turned on.
    page = tab.page
    tab.select(TISSUE)
    box = page.locator('[data-ov="ordering_graph"]')
    assert not box.is_checked()  # off when the page opens
    held = page.evaluate(
        "(() => { const o = window.threadrecon.overlay;"
        " return [Boolean(o.ordering_graph), o._later]; })()"
    )
    assert held[0] is False and "ordering_graph" in held[1]
    before = page.evaluate("document.querySelector('#img-left').toDataURL()")
    box.check()
    page.wait_for_function(
        "() => { const o = window.threadrecon.overlay; return o && o.ordering_graph; }",
        timeout=30_000,
    )
    payload = page.evaluate("window.threadrecon.overlay.ordering_graph.left")
    assert len(payload["segments"]) == len(payload["colors"]) > 0
    badge = page.locator('[data-count="ordering_graph"]').inner_text().strip()
    assert badge == f"({len(payload['labels'])})"
    after = page.evaluate("document.querySelector('#img-left').toDataURL()")
    assert after != before
    box.uncheck()
    assert page.evaluate("document.querySelector('#img-left').toDataURL()") == before
