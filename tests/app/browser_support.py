"""Helpers shared by the real-browser test (``tests/app/test_browser.py``) and
``scripts/screenshots.py``: start ``threadrecon serve`` on free ports, launch the system
chromium through playwright, and a few page probes (the viser GUI inside the iframe, PNG
checks).

Playwright's own browser downloads are never used: the Debian ``chromium`` package is.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_data"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    # software WebGL on a loaded 2-core machine: a GL call that takes seconds must not get the
    # GPU process killed by its watchdog, nor repeated restarts block WebGL for the page (the
    # viser client then never mounts its panel)
    "--disable-gpu-watchdog",
    "--disable-gpu-process-crash-limit",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
VIEWPORT = {"width": 1400, "height": 900}
TISSUE = "simulated/tissue/tissue_1"
READY_LINE = "threadrecon debugger: open"


def missing_browser() -> str | None:
    """Why the browser tests cannot run here, or None when they can."""
    if not Path(CHROMIUM).exists():
        return f"{CHROMIUM} is missing (apt-get install chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "python playwright is not installed (pip install -e '.[test]')"
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get_json(url: str, timeout: float = 30.0) -> Any:
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return json.loads(r.read())


def send_json(method: str, url: str, body: Any, timeout: float = 60.0) -> Any:
    req = urllib.request.Request(
        url, data=json.dumps(body).encode(), method=method,
        headers={"Content-Type": "application/json"},
    )  # fmt: skip
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())


class Server:
    """``threadrecon serve DATA_DIR`` as a subprocess on free ports; ``url`` is the page."""

    def __init__(
        self,
        data_dir: Path = SAMPLE,
        startup_timeout: float = 90.0,
        db: Path | None = None,
        extra_args: tuple[str, ...] = (),
        port: int | None = None,
        viser_port: int | None = None,
    ) -> None:
        self.data_dir = data_dir
        # Ratings and evaluations go to a throw-away database (unless ``db`` names one that
        # should outlive the server), not into the data folder.
        self._tmp = tempfile.TemporaryDirectory(prefix="threadrecon-browser-")
        db = db or Path(self._tmp.name) / "threadrecon.sqlite3"
        self.port = port or free_port()
        self.viser_port = viser_port or free_port()
        if "--configs" not in extra_args:  # user presets never go to the real user folder
            extra_args = (*extra_args, "--configs", str(Path(self._tmp.name) / "presets"))
        self.url = f"http://127.0.0.1:{self.port}"
        self.output: list[str] = []
        self._ready = threading.Event()
        cmd = [
            sys.executable, "-m", "threadrecon.app.cli", "serve", str(data_dir),
            "--host", "127.0.0.1", "--port", str(self.port),
            "--viser-port", str(self.viser_port),
            "--db", str(db), *extra_args,
        ]  # fmt: skip
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, start_new_session=True,
        )  # fmt: skip
        threading.Thread(target=self._read, daemon=True).start()
        try:
            self._wait_ready(startup_timeout)
        except BaseException:
            self.stop()
            raise

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line.rstrip("\n"))
            if READY_LINE in line:
                self._ready.set()

    def _wait_ready(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited ({self.proc.returncode}):\n{self.log()}")
            if self._ready.wait(0.2):
                with contextlib.suppress(OSError):
                    get_json(f"{self.url}/api/frames", timeout=10)
                    return
        raise TimeoutError(f"server not ready after {timeout:.0f} s:\n{self.log()}")

    def log(self) -> str:
        return "\n".join(self.output[-60:])

    def api(self, path: str) -> Any:
        return get_json(self.url + path)

    def stop(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self._tmp.cleanup()

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


@contextlib.contextmanager
def browser() -> Iterator[Any]:
    """A headless system chromium (playwright ``Browser``)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


# --- page probes ---------------------------------------------------------------------------


def wait_stage(page: Any, stage: str, timeout_ms: float = 90_000) -> None:
    """Wait until the stepper shows ``stage`` revealed and computed (done or cached)."""
    page.wait_for_selector(
        f'#stepper li[data-stage="{stage}"]:not(.hidden):is([data-status="done"], [data-status="cached"])',
        state="attached", timeout=timeout_ms,
    )  # fmt: skip


def wait_idle(page: Any, frame_id: str, stage: str = "camera", timeout_ms: float = 90_000) -> None:
    """Wait until the page's session shows ``frame_id`` with ``stage`` computed and not busy."""
    page.wait_for_function(
        """([fid, stage]) => {
            const st = window.threadrecon && window.threadrecon.state;
            if (!st || st.frame_id !== fid || st.shown_frame !== fid || st.busy) return false;
            const s = st.stages.find((x) => x.stage === stage);
            return s && (s.status === "done" || s.status === "cached");
        }""",
        arg=[frame_id, stage], timeout=timeout_ms,
    )  # fmt: skip
    wait_stage(page, stage, timeout_ms)


def png_stats(png: bytes) -> tuple[float, int]:
    """(standard deviation of the pixel values, number of distinct colours) of a PNG."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None, "not a PNG"
    colours = np.unique(img.reshape(-1, 3), axis=0)
    return float(img.std()), len(colours)


def wait_for_magenta(page: Any, tries: int = 60, at_least: int = 150) -> int:
    """Screenshot ``page`` every 250 ms until more than ``at_least`` pixels are magenta (the
    tracked curve's colour; a recording's viewer decodes its embedded scene, then draws) or
    ``tries`` run out; the last count."""
    magenta = 0
    for _ in range(tries):
        page.wait_for_timeout(250)
        img = cv2.imdecode(np.frombuffer(page.screenshot(), np.uint8), cv2.IMREAD_COLOR)
        b, g, r = (img[:, :, c].astype(int) for c in range(3))
        magenta = int(((r > 200) & (g < 120) & (b > 120)).sum())
        if magenta > at_least:
            break
    return magenta
