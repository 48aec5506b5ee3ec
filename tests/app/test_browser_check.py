"""The check in a real browser: the status panel shows the verdict and every reason, the
confidence and grasp overlays are offered and drawn, the evaluation table counts frames per
status, and the agreement panel renders the 5x5 confusion table of score against ratings."""

from __future__ import annotations

import shutil
from typing import Any

import pytest
from browser_support import SAMPLE, VIEWPORT, Server, missing_browser, send_json

pytestmark = pytest.mark.browser

_reason = missing_browser()
if _reason is not None:
    pytest.skip(_reason, allow_module_level=True)

FLAT = "simulated/flat/flat_1"


def _wait_check(page: Any, frame_id: str) -> dict:
    """The check of ``frame_id`` once the session is idle (the state the page shows)."""
    handle = page.wait_for_function(
        """(fid) => { const st = window.threadrecon && window.threadrecon.state;
            return st && st.shown_frame === fid && !st.busy && st.check; }""",
        arg=frame_id, timeout=120_000,
    )  # fmt: skip
    return handle.json_value()


def _wait_text(page: Any, selector: str, text: str) -> None:
    page.wait_for_function(
        "([sel, text]) => document.querySelector(sel).textContent === text",
        arg=[selector, text], timeout=60_000,
    )  # fmt: skip


def test_status_panel_overlays_and_agreement_render(tmp_path, new_context):
    data = tmp_path / "data"
    shutil.copytree(SAMPLE / "simulated" / "flat", data / "simulated" / "flat")
    with Server(data_dir=data) as server:
        page = new_context(viewport=VIEWPORT).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(server.url + "/")
        page.wait_for_function("window.threadrecon && window.threadrecon.state", timeout=60_000)
        page.locator(f'#frames tr[data-id="{FLAT}"]').click()
        page.wait_for_function(
            """(fid) => { const st = window.threadrecon.state;
                return st && st.frame_id === fid && st.shown_frame === fid && !st.busy; }""",
            arg=FLAT, timeout=120_000,
        )  # fmt: skip
        sid = page.evaluate("window.threadrecon.session")
        send_json("POST", f"{server.url}/api/sessions/{sid}/step?wait=true", {"action": "all"})
        check = _wait_check(page, FLAT)
        page.wait_for_selector(f'#check-status[data-status="{check["status"]}"]', state="attached")
        _wait_text(page, "#check-status", check["status"])
        _wait_text(
            page,
            "#check-score",
            f"automatic score {check['rating']:.2f}/5 (class {check['score']})",
        )
        assert "grasp point: confidence" in page.locator("#check-grasp").text_content()
        assert page.locator("#check-reasons li").all_text_contents() == check["reasons"]
        for key in ("confidence", "grasp", "grasp_tangent"):
            assert page.locator(f'[data-ov="{key}"]').count() == 1, key

        # Suspect: thresholds no curve meets; every reason appears on the page.
        patch = {"check": {"reproj_mean_px": 0.0, "reproj_max_px": 0.0}}
        send_json("PATCH", f"{server.url}/api/sessions/{sid}/params?wait=true", patch)
        page.wait_for_selector('#check-status[data-status="suspect"]', state="attached",
                               timeout=120_000)  # fmt: skip
        check = _wait_check(page, FLAT)
        assert len(check["reasons"]) >= 2
        page.wait_for_function(
            "(n) => document.querySelectorAll('#check-reasons li').length === n",
            arg=len(check["reasons"]),
        )
        assert page.locator("#check-reasons li").all_text_contents() == check["reasons"]
        send_json("PATCH", f"{server.url}/api/sessions/{sid}/params?wait=true",
                  {"check": {"reproj_mean_px": 2.0, "reproj_max_px": 8.0}})  # fmt: skip

        for frame, score in ((FLAT, 5), ("simulated/flat/flat_2", 2), ("simulated/flat/flat_3", 4)):
            send_json("PUT", f"{server.url}/api/frames/{frame}/rating",
                      {"score": score, "note": "", "session": sid})  # fmt: skip
        page.locator("#evaluation-section > summary").click()
        page.locator("#eval-start").click()
        page.wait_for_selector('#eval-status[data-state="done"]', state="attached",
                               timeout=300_000)  # fmt: skip
        counts = page.locator("#eval-counts span").all_text_contents()
        assert [c.split()[0] for c in counts] == ["ok", "suspect", "failed"]
        assert sum(int(c.split()[1]) for c in counts) == 4
        page.locator("#agreement-refresh").click()
        page.wait_for_function("document.querySelector('#agreement-brief').textContent.length")
        brief = page.locator("#agreement-brief").text_content()
        assert brief.startswith("3 of 3 rated frames scored") and "Spearman" in brief, brief
        assert page.locator("#agreement-table tbody tr").count() == 5
        cells = page.locator("#agreement-table tbody td").all_text_contents()
        assert len(cells) == 25 and sum(int(c) for c in cells) == 3
        assert errors == []
