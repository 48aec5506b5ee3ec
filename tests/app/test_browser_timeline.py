"""The sequence timeline in a real browser: a generated sequence is one entry of the frame
list; moving the slider runs the new frame in the session (every stage layer follows: the
spline overlay changes); the timeline plot fills in, and clicking a point jumps to its frame;
play steps through the frames; the sequence saved as a recording from the page opens in
Chromium with the server stopped and shows the tracked curve."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from browser_support import VIEWPORT, Server, missing_browser, wait_for_magenta, wait_idle

from threadrecon.app.cli import main

pytestmark = pytest.mark.browser

_reason = missing_browser()
if _reason is not None:
    pytest.skip(_reason, allow_module_level=True)

N_FRAMES = 6
SEQ = "sequences/drag"
PLOT_PAD_L, PLOT_PAD_R = 44, 8  # the plot's margins in static/js/timeline.js (PAD)


def _spline(page: Any, frame_id: str) -> list:
    """The final spline of the left image as the page's overlay holds it for ``frame_id``."""
    page.wait_for_function(
        "(fid) => { const o = window.threadrecon.overlay; return o && o.frame_id === fid && o.spline; }",
        arg=frame_id, timeout=60_000,
    )  # fmt: skip
    return page.evaluate("() => window.threadrecon.overlay.spline.left")


def test_slider_and_plot_move_through_a_generated_sequence(tmp_path, new_context):
    data = tmp_path / "data"
    assert main(["generate", str(data), "--count", "1", "--seed", "3"]) == 0
    assert main(["generate", str(data), "--sequence", str(N_FRAMES), "--motion", "drag",
                 "--seed", "23", "--speed-mm", "2.0"]) == 0  # fmt: skip
    recording = tmp_path / "recording.html"
    with Server(data_dir=data) as server:
        _walk_the_timeline(new_context, server, recording)
    # The recording saved from the page opens with the server stopped and shows the curve.
    page = new_context(viewport=VIEWPORT).new_page()
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    page.goto(recording.as_uri())
    magenta = wait_for_magenta(page, tries=60)
    assert magenta > 150, "the tracked curve (magenta) is not drawn"
    assert not [u for u in requests if u.startswith(("http://", "https://", "ws://"))]


def _walk_the_timeline(new_context: Any, server: Server, recording: Path) -> None:
    """Open the sequence, move the slider, click the plot, play, save the recording."""
    page = new_context(viewport=VIEWPORT, accept_downloads=True).new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(server.url + "/")
    page.wait_for_function("window.threadrecon && window.threadrecon.state", timeout=60_000)

    row = page.locator(f'#frames tr[data-id="{SEQ}"]')
    assert row.count() == 1, "the sequence is one entry of the frame list"
    assert page.locator('#frames tr[data-id^="sequences/"]').count() == 1
    row.click()
    wait_idle(page, f"{SEQ}@0")
    assert page.locator("#timeline").is_visible()
    first = _spline(page, f"{SEQ}@0")

    page.locator("#tl-slider").fill("4")
    wait_idle(page, f"{SEQ}@4")
    moved = _spline(page, f"{SEQ}@4")
    assert moved != first, "the spline layer follows the slider"
    assert page.locator("#tl-frame").text_content() == f"5 / {N_FRAMES}"

    # The timeline fills in (computed on the server, tracked) and plots every frame.
    page.wait_for_function(
        "(n) => { const t = window.threadrecon.timeline; return t.done && t.rows.length === n; }",
        arg=N_FRAMES, timeout=120_000,
    )  # fmt: skip
    rows = page.evaluate("() => window.threadrecon.timeline.rows")
    assert [r["frame"] for r in rows] == list(range(N_FRAMES))
    assert all(r["track_status"] == "ok" for r in rows)
    page.wait_for_function("() => window.threadrecon.timeline.curvesFor === 4", timeout=30_000)
    tracked4 = page.evaluate("() => window.threadrecon.timeline.curves.tracked")

    # Click the plot at frame 1's x: the page jumps there, and the curves follow.
    box = page.locator("#tl-plot").bounding_box()
    assert box is not None
    x = PLOT_PAD_L + (box["width"] - PLOT_PAD_L - PLOT_PAD_R) * 1 / (N_FRAMES - 1)
    page.locator("#tl-plot").click(position={"x": x, "y": box["height"] / 2})
    wait_idle(page, f"{SEQ}@1")
    assert page.evaluate("() => document.querySelector('#tl-slider').value") == "1"
    assert _spline(page, f"{SEQ}@1") not in (first, moved)
    page.wait_for_function("() => window.threadrecon.timeline.curvesFor === 1", timeout=30_000)
    assert page.evaluate("() => window.threadrecon.timeline.curves.tracked") != tracked4

    # Play runs to the last frame and stops there.
    page.locator("#tl-play").click()
    wait_idle(page, f"{SEQ}@{N_FRAMES - 1}")
    page.wait_for_function("() => !window.threadrecon.timeline.playing", timeout=30_000)

    # Save the whole sequence as a recording from the page's link.
    with page.expect_download(timeout=60_000) as dl:
        page.locator("#tl-rec-seq").click()
    dl.value.save_as(recording)
    assert recording.stat().st_size > 1000
    assert not errors, errors
