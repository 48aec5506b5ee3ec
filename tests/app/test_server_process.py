"""``threadrecon serve`` as a process: long polls hold no thread, Ctrl-C is quick and the port
can be taken again at once, and closed sessions give their memory back.

The figures (latency, shutdown and restart times, RSS) are printed for the closing note:
``pytest tests/app/test_server_process.py -s``.
"""

from __future__ import annotations

import json
import signal
import statistics
import subprocess
import sys
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
from browser_support import READY_LINE, ROOT, SAMPLE, Server, free_port, get_json

FRAMES = [f"simulated/{g}/{g}_{i}" for g in ("flat", "tissue") for i in (1, 2)]


def _post(url: str, body: dict, timeout: float = 120.0) -> dict:
    req = urllib.request.Request(
        url, data=json.dumps(body).encode(), method="POST",
        headers={"Content-Type": "application/json"},
    )  # fmt: skip
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def _latency_ms(url: str, n: int = 7) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        get_json(url, timeout=30)
        times.append(1000 * (time.perf_counter() - t0))
    return statistics.median(times)


def _interrupt(server: Server) -> float:
    """Ctrl-C the server; seconds until it exited."""
    t0 = time.perf_counter()
    server.proc.send_signal(signal.SIGINT)
    server.proc.wait(30)
    return time.perf_counter() - t0


def test_45_long_polls_leave_the_api_responsive_and_ctrl_c_is_quick(tmp_path):
    with Server(SAMPLE, extra_args=("--configs", str(tmp_path))) as server:
        sid = _post(server.url + "/api/sessions", {})["session"]
        state = get_json(f"{server.url}/api/sessions/{sid}")
        idle_ms = _latency_ms(server.url + "/api/info")
        done: list[float] = []

        def long_poll() -> None:
            t0 = time.perf_counter()
            v = state["version"] + 10**6  # never reached: each poll waits its full timeout
            get_json(f"{server.url}/api/sessions/{sid}?since={v}&timeout=20", timeout=60)
            done.append(time.perf_counter() - t0)

        threads = [threading.Thread(target=long_poll, daemon=True) for _ in range(45)]
        for t in threads:
            t.start()
        time.sleep(1.5)  # every poll is waiting in the server now
        busy_ms = _latency_ms(server.url + "/api/info")
        assert not done, "a long poll answered early"
        shutdown_s = _interrupt(server)
        print(f"\n/api/info median: {idle_ms:.1f} ms idle, {busy_ms:.1f} ms under 45 long polls; "
              f"Ctrl-C to exit with 45 open polls: {shutdown_s:.2f} s")  # fmt: skip
        assert busy_ms < 200
        assert shutdown_s < 5


def test_the_port_can_be_taken_again_right_after_ctrl_c(tmp_path):
    port, viser_port = free_port(), free_port()
    args = ("--configs", str(tmp_path))
    server = Server(SAMPLE, port=port, viser_port=viser_port, extra_args=args)
    try:
        for _ in range(5):  # connections the server closes first: TIME_WAIT on its side
            get_json(server.url + "/api/frames")
        _post(server.url + "/api/sessions", {})
        shutdown_s = _interrupt(server)
    finally:
        server.stop()
    t0 = time.perf_counter()
    with Server(SAMPLE, port=port, viser_port=viser_port, extra_args=args) as again:
        ready_s = time.perf_counter() - t0
        assert get_json(again.url + "/api/info")["stages"]
    print(
        f"\nCtrl-C to exit: {shutdown_s:.2f} s; restart on the same port ready after {ready_s:.2f} s"
    )


def test_closed_sessions_give_their_memory_back(tmp_path):
    idle = 20.0  # longer than opening the 50 sessions takes, so that all 50 live at once
    args = ("--configs", str(tmp_path), "--idle-timeout", str(idle))
    with Server(SAMPLE, extra_args=args) as server:
        pid = server.proc.pid
        warm = _post(server.url + "/api/sessions", {})["session"]
        for frame in FRAMES:  # decoded frames (shared by every session) and code paths warm
            _post(f"{server.url}/api/frames/{frame}/run", {"session": warm})
        _post(f"{server.url}/api/frames/{FRAMES[0]}/run", {})  # the shared API session
        req = urllib.request.Request(f"{server.url}/api/sessions/{warm}", method="DELETE")
        urllib.request.urlopen(req, timeout=30).close()
        start = _rss_mb(pid)
        t0 = time.monotonic()
        sids = []
        for i in range(50):  # a tab opens, shows a frame, and goes away
            sids.append(_post(server.url + "/api/sessions", {})["session"])
            _post(f"{server.url}/api/frames/{FRAMES[i % len(FRAMES)]}/run", {"session": sids[-1]})
        peak = _rss_mb(pid)
        opened_s = time.monotonic() - t0
        for sid in sids[-25:]:  # half closed by the page (pagehide), half left to expire
            req = urllib.request.Request(f"{server.url}/api/sessions/{sid}", method="DELETE")
            urllib.request.urlopen(req, timeout=30).close()
        deadline = time.monotonic() + idle + 60
        while time.monotonic() < deadline:
            try:
                get_json(f"{server.url}/api/sessions/{sids[24]}")
            except urllib.error.HTTPError as exc:
                assert exc.code == 404
                break
            time.sleep(0.5)
        time.sleep(1.0)
        end = _rss_mb(pid)
        print(f"\nRSS: {start:.0f} MB at start, {peak:.0f} MB with 50 sessions (opened in "
              f"{opened_s:.0f} s), {end:.0f} MB after they closed ({100 * (end / start - 1):+.1f} %)")  # fmt: skip
        assert end <= 1.2 * start


@pytest.mark.parametrize("bad", [["--idle-timeout", "0"], ["--allow-origin", "evil.example"]])
def test_bad_serve_options_are_one_line_errors(bad):
    r = subprocess.run(
        [sys.executable, "-m", "threadrecon.app.cli", "serve", str(SAMPLE), "--port", str(free_port()), *bad],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode != 0 and READY_LINE not in r.stdout
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
