"""Recordings (app/recording.py): a saved sequence opens in Chromium from a file, no server."""

from __future__ import annotations

import numpy as np
import pytest
from browser_support import wait_for_magenta

from threadrecon.app.recording import RecordedFrame, save_recording


def _curve(k: int) -> np.ndarray:
    t = np.linspace(0, 1, 120)
    return np.column_stack([100 * t - 50 + k, 15 * np.sin(np.pi * t), 100 + 5 * t])


def test_a_recording_is_one_self_contained_html_file(tmp_path):
    path = tmp_path / "rec.html"
    frames = [RecordedFrame({"tracked": _curve(k), "truth": _curve(k) + 2}) for k in range(5)]
    assert save_recording(frames, path, baseline=5.0) == 5
    html = path.read_text()
    assert "__VISER_EMBED_DATA__" in html
    assert "ws://" not in html.split("__VISER_EMBED_DATA__")[1][:200]
    with pytest.raises(ValueError, match="no frames"):
        save_recording([], tmp_path / "empty.html")
    with pytest.raises(ValueError, match=r"curve 'tracked' must be \(N >= 2, 3\)"):
        save_recording([RecordedFrame({"tracked": np.zeros((4, 2))})], tmp_path / "bad.html")


@pytest.mark.browser
def test_a_saved_recording_shows_the_curve_in_chromium_without_a_server(tmp_path, new_context):
    path = tmp_path / "rec.html"
    save_recording([RecordedFrame({"tracked": _curve(k)}) for k in range(3)], path, baseline=5.0)
    page = new_context(viewport={"width": 1000, "height": 700}).new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    page.goto(path.as_uri())
    magenta = wait_for_magenta(page, tries=40)
    assert not errors
    assert magenta > 150, "the tracked curve (magenta) is not drawn"
    assert not [u for u in requests if u.startswith(("http://", "https://", "ws://"))]
