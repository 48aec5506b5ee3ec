"""Screenshots of the debugger page, stage by stage, in headless chromium.

    .venv/bin/python scripts/screenshots.py [--out docs/screenshots] [--frame ID]

Starts ``threadrecon serve sample_data`` on free ports (with a throw-away ratings database),
opens the page on a tissue frame and saves ``01-segment.png`` ... ``08-camera.png`` (the
"Next step" button reveals one stage after the other), ``09-full-result.png`` ("Run all") and
``10-pixel-inspector.png`` (the energy curve of a reliable thread pixel). Uses the system
chromium (/usr/bin/chromium), never a playwright browser download.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "app"))

from browser_support import (  # noqa: E402
    SAMPLE,
    TISSUE,
    VIEWPORT,
    Server,
    browser,
    missing_browser,
    wait_idle,
)

from threadrecon.core.pipeline import STAGES  # noqa: E402

RENDER_S = 2.0  # time the software-rendered 3D view gets to draw the new layers


def wait_overlay(page, frame_id: str) -> None:
    page.wait_for_function(
        """(fid) => {
            const S = window.threadrecon;
            return S.state && !S.state.busy && S.overlay && S.overlay.frame_id === fid
                && S.overlayVersion === S.version;
        }""",
        arg=frame_id, timeout=60_000,
    )  # fmt: skip


def close_notifications(page) -> None:
    """Close viser's "Software WebGL rendering detected" notice (it covers the 3D view)."""
    viewer = page.frame_locator("#viewer")
    with contextlib.suppress(Exception):
        viewer.locator(".mantine-Notification-root").first.wait_for(timeout=5_000)
    notes = viewer.locator(".mantine-Notification-root button")
    for _ in range(notes.count()):
        with contextlib.suppress(Exception):
            notes.first.click(timeout=2_000)
            time.sleep(0.4)


def shoot(page, path: Path) -> None:
    time.sleep(RENDER_S)
    page.screenshot(path=str(path))
    print(f"  {path}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "screenshots"), help="output folder")
    ap.add_argument("--frame", default=TISSUE, help=f"frame id (default {TISSUE})")
    ap.add_argument("--data", default=str(SAMPLE), help="data folder (default sample_data)")
    args = ap.parse_args(argv)
    reason = missing_browser()
    if reason:
        print(f"screenshots: {reason}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    with Server(Path(args.data)) as server, browser() as b:
        page = b.new_page(viewport=VIEWPORT)
        page.set_default_timeout(60_000)
        page.on("pageerror", lambda e: print(f"  page error: {e}", file=sys.stderr))
        page.goto(server.url + "/")
        page.wait_for_function("window.threadrecon && window.threadrecon.state")
        page.frame_locator("#viewer").locator("canvas").first.wait_for()
        close_notifications(page)
        page.locator(f'#frames tr[data-id="{args.frame}"]').click()
        wait_idle(page, args.frame)
        print(f"{args.frame} on {server.url}")
        for k, stage in enumerate(STAGES, start=1):
            page.locator("#btn-next").click()  # all revealed -> 1, then one more each time
            page.wait_for_function(
                """([k, stage]) => {
                    const li = document.querySelector(`#stepper li[data-stage="${stage}"]`);
                    return document.querySelectorAll('#stepper li:not(.hidden)').length === k
                        && li && ['done', 'cached', 'fallback', 'failed'].includes(li.dataset.status)
                        && !window.threadrecon.state.busy;
                }""",
                arg=[k, stage],
            )  # fmt: skip
            wait_overlay(page, args.frame)
            shoot(page, out / f"{k:02d}-{stage}.png")
        page.locator("#btn-all").click()
        wait_idle(page, args.frame)
        wait_overlay(page, args.frame)
        shoot(page, out / "09-full-result.png")
        reliable = page.evaluate("window.threadrecon.overlay.reliable || []")
        if len(reliable) >= 2:
            i = (len(reliable) // 4) & ~1
            x, y = reliable[i], reliable[i + 1]
            canvas = page.locator("#img-left")
            canvas.scroll_into_view_if_needed()
            w, h = canvas.evaluate("c => [c.width, c.height]")
            box = canvas.bounding_box()
            canvas.click(
                position={"x": (x + 0.5) * box["width"] / w, "y": (y + 0.5) * box["height"] / h}
            )
            page.wait_for_function("() => document.querySelector('#energy').dataset.pixel")
            page.locator("#energy").scroll_into_view_if_needed()
            shoot(page, out / "10-pixel-inspector.png")
        else:
            print("  no reliable pixel: no pixel-inspector screenshot", file=sys.stderr)
    print(f"done in {time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
