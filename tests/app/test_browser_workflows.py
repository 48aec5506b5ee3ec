"""Rating and presets in a real browser, across a server restart: rate a frame with the
page's buttons and keys, save the slider values as a preset, restart the server, reload the
page, find the rating, load the preset and see every changed slider of the viser panel
restored; an existing preset name is not overwritten when the confirmation is dismissed."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import pytest
from browser_support import (
    TISSUE,
    VIEWPORT,
    Server,
    missing_browser,
    send_json,
    wait_idle,
)

pytestmark = pytest.mark.browser

_reason = missing_browser()
if _reason is not None:
    pytest.skip(_reason, allow_module_level=True)

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
CHANGED = {  # viser folder -> (slider index in the folder, value) set through the REST API
    "3. reliability": (0, 6.5),  # eps1
    "7. spline": (0, 18),  # n_ctrl
}


def open_page(new_context: Any, server: Server) -> Any:
    page = new_context(viewport=VIEWPORT).new_page()
    errors: list[str] = []
    notes: list[str] = []  # the viser client's messages and the server's log, on failure only
    viser = f":{server.viser_port}"

    def on_error(exc: Any) -> None:
        (notes if viser in (getattr(exc, "stack", "") or "") else errors).append(str(exc))

    def on_console(msg: Any) -> None:
        if msg.type in ("error", "warning"):
            notes.append(f"{msg.type} at {(msg.location or {}).get('url', '')}: {msg.text}")

    page.on("pageerror", on_error)
    page.on("console", on_console)
    page.goto(server.url + "/")
    page.wait_for_function("window.threadrecon && window.threadrecon.state", timeout=60_000)
    page.errors, page.notes, page.server = errors, notes, server
    return page


def select(page: Any, frame_id: str) -> None:
    page.locator(f'#frames tr[data-id="{frame_id}"]').click()
    wait_idle(page, frame_id)


def slider_value(page: Any, folder: str, index: int) -> float:
    header = page.frame_locator("#viewer").get_by_text(folder, exact=True)
    try:
        header.wait_for(timeout=60_000)
    except Exception as exc:  # say what the viser client and the server reported
        raise AssertionError(
            f"the viser panel shows no folder {folder!r}: {exc}\nviser client and page:\n"
            + "\n".join(page.notes[-30:])
            + f"\nserver log:\n{page.server.log()}"
        ) from None
    sliders = header.locator("xpath=..").get_by_role("slider")
    if sliders.count() == 0:
        header.click()
        sliders.first.wait_for(timeout=30_000)
    return float(sliders.nth(index).get_attribute("aria-valuenow"))


def wait_slider(page: Any, folder: str, index: int, value: float, timeout: float = 15.0) -> None:
    """Wait until the viser panel shows ``value`` on the slider (updates arrive async)."""
    deadline = time.monotonic() + timeout
    got = None
    while time.monotonic() < deadline:
        got = slider_value(page, folder, index)
        if got == pytest.approx(value):
            return
        page.wait_for_timeout(200)
    raise AssertionError(f"{folder} slider {index} shows {got}, expected {value}")


def test_rating_and_preset_survive_a_restart(tmp_path, new_context):
    db = tmp_path / "ratings.sqlite3"
    configs = tmp_path / "configs"
    shutil.copytree(CONFIGS, configs)
    args = ("--configs", str(configs))
    with Server(db=db, extra_args=args) as server:
        page = open_page(new_context, server)
        select(page, TISSUE)
        page.locator("#rating-note").fill("tip a little short")
        page.locator('.star[data-score="4"]').click()
        page.wait_for_selector('#rating-latest[data-score="4"]', state="attached")
        page.locator("#stepper").click()  # focus out of the note: keys rate
        page.keyboard.press("3")
        page.wait_for_selector('#rating-latest[data-score="3"]', state="attached")
        got = server.api(f"/api/frames/{TISSUE}/rating")
        assert [h["score"] for h in got["history"]] == [3, 4]
        assert got["latest"]["note"] == "tip a little short"

        sid = page.evaluate("window.threadrecon.session")
        patch = {"reliability": {"eps1": 6.5}, "spline": {"n_ctrl": 18}}
        send_json("PATCH", f"{server.url}/api/sessions/{sid}/params?wait=true", patch)
        for folder, (index, value) in CHANGED.items():  # the panel follows the API
            wait_slider(page, folder, index, value)
        page.locator("#preset-name").fill("browser-1")
        page.locator("#preset-save").click()
        page.wait_for_selector("#preset-msg:has-text('saved browser-1')")
        saved = (configs / "browser-1.toml").read_text()
        assert "eps1 = 6.5" in saved and "n_ctrl = 18" in saved
        assert not page.errors

    with Server(db=db, extra_args=args) as server:  # restart, same database and presets
        page = open_page(new_context, server)
        row = page.locator(f'#frames tr[data-id="{TISSUE}"] td.rating')
        assert row.inner_text() == "★★★"
        select(page, TISSUE)
        page.wait_for_selector('#rating-latest[data-score="3"]', state="attached")
        for folder, (index, value) in CHANGED.items():
            assert slider_value(page, folder, index) != pytest.approx(value)
        page.locator("#preset-select").select_option("browser-1")
        page.locator("#preset-load").click()
        page.wait_for_function(
            "() => window.threadrecon.state.preset === 'browser-1'", timeout=30_000
        )
        for folder, (index, value) in CHANGED.items():
            wait_slider(page, folder, index, value)
        diff = page.locator("#preset-diff").inner_text()
        assert "reliability.eps1" in diff and "spline.n_ctrl" in diff

        before = (configs / "browser-1.toml").read_text()
        page.on("dialog", lambda d: d.dismiss())  # "overwrite?" -> no
        sid = page.evaluate("window.threadrecon.session")
        send_json(
            "PATCH",
            f"{server.url}/api/sessions/{sid}/params?wait=true",
            {"spline": {"n_ctrl": 9}},
        )
        page.locator("#preset-name").fill("browser-1")
        page.locator("#preset-save").click()
        page.wait_for_selector("#preset-msg:has-text('not saved')")
        assert (configs / "browser-1.toml").read_text() == before
        assert not page.errors
