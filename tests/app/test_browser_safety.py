"""Stored XSS and the rating form, in a real browser (headless system chromium).

A rating note and a data file name that hold HTML must show as text; a note typed on one
frame is never saved with another frame's score after ``n``.
"""

from __future__ import annotations

import shutil
import urllib.parse

import pytest
from browser_support import SAMPLE, Server, get_json, missing_browser, send_json, wait_idle

pytestmark = pytest.mark.browser

_reason = missing_browser()
if _reason is not None:
    pytest.skip(_reason, allow_module_level=True)

PAYLOAD = "<img src=x onerror=window.__xss=1>"
A, B = "simulated/flat/flat_1", "simulated/flat/flat_2"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("xss") / "data"
    group = data / "simulated" / "flat"
    shutil.copytree(SAMPLE / "simulated" / "flat", group)
    for ext in (".png", ".npy"):  # a side-by-side frame whose file name is HTML
        shutil.copy(group / f"flat_3{ext}", group / f"{PAYLOAD}{ext}")
    presets = tmp_path_factory.mktemp("presets")
    with Server(data, extra_args=("--configs", str(presets))) as s:
        yield s


@pytest.fixture()
def page(server, new_context):
    page = new_context().new_page()
    dialogs: list[str] = []
    page.on("dialog", lambda d: (dialogs.append(d.message), d.dismiss()))
    page.goto(server.url + "/", wait_until="load")
    page.wait_for_function("window.threadrecon && window.threadrecon.state", timeout=60_000)
    page.dialogs = dialogs  # type: ignore[attr-defined]
    return page


def _rating(server: Server, frame_id: str) -> dict:
    return get_json(f"{server.url}/api/frames/{urllib.parse.quote(frame_id)}/rating")


def test_html_in_a_file_name_and_a_note_shows_as_text(server, page):
    evil_id = next(f["id"] for f in get_json(server.url + "/api/frames") if "<img" in f["id"])
    send_json(
        "PUT",
        f"{server.url}/api/frames/{urllib.parse.quote(A)}/rating",
        {"score": 2, "note": PAYLOAD},
    )
    send_json(
        "PUT",
        f"{server.url}/api/frames/{urllib.parse.quote(evil_id)}/rating",
        {"score": 4, "note": PAYLOAD},
    )
    page.reload(wait_until="load")
    page.wait_for_function("window.threadrecon && window.threadrecon.state", timeout=60_000)
    names = page.locator("#frames td").all_text_contents()
    assert any(PAYLOAD in n for n in names), names
    page.click("#evaluation-section summary")
    page.click("#ratings-refresh")
    page.wait_for_selector("#ratings-table tbody tr", timeout=30_000)
    notes = page.locator("#ratings-table td.col-note").all_text_contents()
    frames = page.locator("#ratings-table tbody tr td:first-child").all_text_contents()
    assert notes == [PAYLOAD, PAYLOAD] and evil_id in frames
    page.wait_for_timeout(500)  # an injected <img src=x> would have fired onerror by now
    assert page.evaluate("window.__xss") is None
    assert page.locator("#frames img, #ratings-table img, #eval-table img").count() == 0
    assert page.dialogs == []  # type: ignore[attr-defined]


def test_a_note_stays_with_the_frame_it_was_typed_on(server, page):
    page.locator(f'#frames tr[data-id="{A}"]').click()
    wait_idle(page, A)
    page.fill("#rating-note", "only about flat_1")
    page.click("h1")  # leave the note box, as a user would before pressing n
    page.keyboard.press("n")
    wait_idle(page, B)
    assert page.input_value("#rating-note") != "only about flat_1"
    page.keyboard.press("5")
    page.wait_for_function(
        "document.querySelector('#rating-latest').dataset.score === '5'", timeout=30_000
    )
    got = _rating(server, B)["latest"]
    assert got["score"] == 5 and got["note"] != "only about flat_1"
    page.keyboard.press("p")
    wait_idle(page, A)
    assert page.input_value("#rating-note") == "only about flat_1"  # the draft came back
    page.keyboard.press("3")
    page.wait_for_function(
        "document.querySelector('#rating-latest').dataset.score === '3'", timeout=30_000
    )
    assert _rating(server, A)["latest"]["note"] == "only about flat_1"


def test_the_api_docs_render_with_no_request_leaving_the_machine(server, new_context):
    page = new_context().new_page()
    hosts: list[str] = []
    page.on("request", lambda r: hosts.append(urllib.parse.urlsplit(r.url).hostname or ""))
    page.goto(server.url + "/docs", wait_until="networkidle")
    page.wait_for_selector(".swagger-ui .opblock", timeout=30_000)
    assert page.locator(".swagger-ui .opblock").count() > 20
    assert hosts and set(hosts) <= {"127.0.0.1"}, sorted(set(hosts))
