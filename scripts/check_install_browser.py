"""``threadrecon serve`` of an installed package, driven in the system chromium: the page
computes the bundled sample's first frame and the 3D view (viser iframe) draws the thread.

    python scripts/check_install_browser.py THREADRECON_EXECUTABLE SCREENSHOT_DIR

Writes page.png and viewer.png; exits non-zero when the page or the 3D view fails.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "app"))
from browser_support import CHROMIUM, CHROMIUM_ARGS, READY_LINE, VIEWPORT, free_port  # noqa: E402

COLOURED_PX = 300  # pixels of clear hue that make a drawn thread (test_browser's figure)


def main() -> None:
    exe, out = sys.argv[1], Path(sys.argv[2])
    out.mkdir(parents=True, exist_ok=True)
    port = free_port()
    proc = subprocess.Popen(
        [exe, "serve", "--port", str(port), "--viser-port", str(free_port())],
        cwd=tempfile.mkdtemp(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            print("server:", line.rstrip())
            if READY_LINE in line:
                break
        else:
            sys.exit("the server stopped before it was ready")
        n = _drive(f"http://127.0.0.1:{port}/", out)
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
    if n <= COLOURED_PX:
        sys.exit(f"the 3D view shows no thread ({n} coloured pixels)")


def _drive(url: str, out: Path) -> int:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        page = browser.new_page(viewport=VIEWPORT)
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url, timeout=120_000)
        page.wait_for_selector(
            '#stepper li[data-stage="camera"]:is([data-status="done"], [data-status="cached"])',
            state="attached", timeout=600_000,
        )  # fmt: skip
        viewer = page.frame_locator("#viewer")
        viewer.locator("canvas").first.wait_for(timeout=120_000)
        viewer.get_by_text("Connected", exact=True).wait_for(timeout=120_000)
        n, png = 0, b""
        for _ in range(60):  # the scene arrives over the websocket after the canvas
            png = page.locator("#viewer").screenshot()
            img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.int16)
            n = int(((img.max(axis=2) - img.min(axis=2)) > 60).sum())
            if n > COLOURED_PX:
                break
            time.sleep(1.0)
        page.screenshot(path=str(out / "page.png"))
        (out / "viewer.png").write_bytes(png)
        browser.close()
    print(f"page '{url}': camera stage done, page errors {errors}; 3D view: {n} coloured pixels")
    if errors:
        sys.exit(f"page errors: {errors}")
    return n


if __name__ == "__main__":
    main()
