"""Slider latency of the debugger on every frame of a data folder, with its breakdown.

Starts the debugger in this process and opens the page in headless Chromium (``--viewer
chromium``: the page and its embedded viser viewer, software WebGL on the same cores), then for
each frame changes a spline parameter, eps1, eps2, eps3 and the reliability threshold through
the path a slider takes (``Session.submit``). With Chromium the latency is the time from the
change until the page has the run's final state and has drawn its 2D overlays; the breakdown
gives, per slider, the session worker's compute and publish (3D layers to viser) ms, wall and
CPU, when the last layer was in the scene, when the page got the state, the page's overlay
fetches (ms, kB) and its drawing ms, and Chromium's CPU ms per change: its GPU process (the
viewer's software-WebGL frames) and its renderers (the page, the viewer's JavaScript). A probe
in the viewer also gives the ms until the 3D view has issued its first frame after the change's
scene message. Without Chromium (``socket``: a websocket client that
receives the 3D scene and renders nothing; ``none``) it is the server-side time until the last
layer is in the scene, and the overlay GET the page would make.

    .venv/bin/python scripts/bench_latency.py [DATA_DIR] [--repeat 3] [--viewer chromium]
        [--set stereo.z_near_mm=40 --set stereo.z_far_mm=250]   # e.g. 1920x1080 frames
        [--pause-ms 300]   # a pause after each change (default 0: back to back)
        [--user-priority]   # Chromium at nice 0, as for a user who is not root
        [--moves FILE.csv]   # one row per move: its latency and every part of it

HD frames: ``threadrecon generate DIR --size 1920x1080 --count 4 --seed 5601``.
Targets (issue #13, p90): 150 ms for eps1-3 / threshold and 80 ms for a spline slider at
640x480; 400 ms and 250 ms at 1920x1080 (sizes in between: 1920x1080's).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import gc
import os
import socket
import statistics
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402
import uvicorn  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from threadrecon.app import heap  # noqa: E402
from threadrecon.app.bench import parse_overrides  # noqa: E402
from threadrecon.app.errors import UserError  # noqa: E402
from threadrecon.app.library import merge_params  # noqa: E402
from threadrecon.app.server import ServerConfig, create_app  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
]  # fmt: skip
VIEWER_PROBE = """
(() => {  // in the viser viewer: when its worker hands over a message, when each frame is drawn
  if (!window.WebGL2RenderingContext || window.__viewerProbe) return;
  const P = window.__viewerProbe = { msgs: [], frames: [] };
  const W = window.Worker;
  if (W) {
    window.Worker = function (...a) {
      const w = new W(...a);
      w.addEventListener("message", () => P.msgs.push(Date.now()));
      return w;
    };
    window.Worker.prototype = W.prototype;
  }
  let tick = 0, last = -1;
  const loop = () => { tick++; requestAnimationFrame(loop); };
  requestAnimationFrame(loop);
  const C = WebGL2RenderingContext.prototype;
  for (const name of ["drawArrays", "drawElements", "drawArraysInstanced", "drawElementsInstanced"]) {
    const f = C[name];
    C[name] = function (...a) {
      const now = Date.now();
      if (tick !== last) { last = tick; P.frames.push([now, now]); } else P.frames[P.frames.length - 1][1] = now;
      return f.apply(this, a);
    };
  }
})();
"""  # the first frame drawn after a move's last scene message is when the 3D view shows it
TARGETS_MS = {  # p90, issue #13: by frame size (<= 640x480 pixels, else HD)
    "vga": {"spline": 80.0, "reliability": 150.0},
    "hd": {"spline": 250.0, "reliability": 400.0},
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def running_server(data: Path, db: Path):
    port = _free_port()
    config = ServerConfig(data_dir=data, port=port, viser_port=_free_port(), db_path=db)
    app = create_app(config)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    heap.settle()  # as `threadrecon serve` does once it has started
    try:
        yield f"http://127.0.0.1:{port}", app.state.core
    finally:
        server.should_exit = True
        thread.join(10)


@contextlib.contextmanager
def browser_page(url: str):
    """The real page in headless Chromium; its software WebGL shares the cores with the
    server, as it would on a laptop without a GPU."""
    if not CHROMIUM.exists():
        print("no /usr/bin/chromium: measuring without a viewer attached", file=sys.stderr)
        yield None
        return
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        context = browser.new_context(viewport={"width": 1200, "height": 800})
        context.add_init_script(VIEWER_PROBE)
        page = context.new_page()
        page.goto(url)
        page.wait_for_function("window.threadrecon && window.threadrecon.session")
        yield page
        browser.close()


@contextlib.contextmanager
def socket_viewer(viser_port: int, sid: str):
    """A minimal viser client: connects with the session's websocket path, reports a camera
    (viser then counts it as connected, and the session attaches its view) and receives every
    message the server sends. It renders nothing, so it costs the server what a browser on
    another machine costs it, without a software renderer on these two cores."""
    import asyncio

    import msgspec
    import viser
    import websockets

    stop = threading.Event()
    received = [0]

    async def run() -> None:
        uri = f"ws://127.0.0.1:{viser_port}/session/{sid}"
        async with websockets.connect(
            uri, subprotocols=[f"viser-v{viser.__version__}"], max_size=None
        ) as ws:
            camera = {
                "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0],
                "position": [0.0, 0.0, 0.0], "fov": 1.0, "near": 0.01, "far": 1000.0,
                "image_height": 800, "image_width": 1200, "look_at": [0.0, 0.0, 1.0],
                "up_direction": [0.0, -1.0, 0.0],
            }  # fmt: skip
            await ws.send(msgspec.msgpack.encode(camera))
            while not stop.is_set():
                try:
                    msg = await asyncio.wait_for(ws.recv(), 0.2)
                    received[0] += len(msg)
                except TimeoutError:
                    pass

    thread = threading.Thread(target=lambda: asyncio.run(run()), daemon=True)
    thread.start()
    try:
        yield received
    finally:
        stop.set()
        thread.join(5)


_PART_ORDER = [
    "compute", "compute cpu", "publish", "publish cpu", "metrics", "metrics cpu", "scene",
    "page state", "overlay GET", "overlay kB", "page draw", "gpu cpu", "renderers cpu",
]  # fmt: skip


def _add(part: dict[str, list[float]], key: str, value: float) -> None:
    part.setdefault(key, []).append(value)


def _page_shown(page, version: int, timeout_s: float = 120.0) -> dict[str, float]:
    """Wait until the page has drawn the 2D overlay of session version >= ``version``; when
    (epoch ms), how long its last overlay GET took and its size, and the drawing's ms."""
    page.wait_for_function(
        "v => { const s = window.threadrecon.overlayShown; return s && s.version >= v; }",
        arg=version,
        timeout=1000 * timeout_s,
        polling=20,
    )
    return page.evaluate(
        """() => {
          const S = window.threadrecon;
          const gets = performance.getEntriesByType("resource").filter((e) => e.name.includes("/overlay"));
          performance.clearResourceTimings();
          return { at: S.overlayShown.at, state_at: S.stateAt.at, draw_ms: S.drawMs || 0,
                   states: S.states || 0,
                   get_ms: gets.reduce((a, e) => a + e.duration, 0),
                   kB: gets.reduce((a, e) => a + e.encodedBodySize, 0) / 1e3 };
        }"""
    )


def _chromium_pids() -> list[int]:
    """This process's Chromium descendants (Linux /proc)."""
    parent: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
    mine, todo = set(), [os.getpid()]
    while todo:
        pid = todo.pop()
        kids = [c for c, pp in parent.items() if pp == pid]
        mine.update(kids)
        todo.extend(kids)
    out = []
    for pid in mine:
        with contextlib.suppress(OSError):
            if b"chrom" in Path(f"/proc/{pid}/cmdline").read_bytes():
                out.append(pid)
    return out


def _user_priority() -> int:
    """Put Chromium's threads back to nice 0 where they run higher: as root, Chromium raises
    its GPU process (the software-WebGL frames) and browser threads to nice -8, which a user
    without CAP_SYS_NICE cannot, and they would then pre-empt the server. Returns how many."""
    n = 0
    for pid in _chromium_pids():
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{pid}/task").iterdir():
                with contextlib.suppress(OSError, ValueError, IndexError):
                    tid = int(task.name)
                    if int((task / "stat").read_text().rsplit(")", 1)[1].split()[16]) < 0:
                        os.setpriority(os.PRIO_PROCESS, tid, 0)
                        n += 1
    return n


def _chromium_cpu_ms() -> dict[str, float]:
    """CPU ms so far of this process's Chromium descendants (Linux /proc): its GPU process
    (software WebGL: the viewer's frames) and its renderers (the page, the viewer's page)."""
    out = {"gpu": 0.0, "renderers": 0.0}
    tick = os.sysconf("SC_CLK_TCK")
    for pid in _chromium_pids():
        with contextlib.suppress(OSError, IndexError, ValueError):
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
            f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            ms = 1000.0 * (int(f[11]) + int(f[12])) / tick  # utime + stime
            key = "gpu" if b"--type=gpu-process" in cmd else "renderers"
            if b"--type=" in cmd or key == "gpu":
                out[key] += ms
    return out


def _viewer_frame(page):
    """The viewer's frame (iframe) of the page, when it has the probe."""
    if page is None:
        return None
    for f in page.frames:
        if f != page.main_frame and f.evaluate("Boolean(window.__viewerProbe)"):
            return f
    return None


def _viewer_latencies(
    viewer, moves: list[tuple[float, str]], frames_out: list[tuple[int, float]] | None = None
) -> list[tuple[str, float]]:
    """Per change (epoch ms, label): ms until the viewer finished issuing the first frame that
    began after the last message it received before the next change (the scene batch). Waits
    for the last change's frame; clears the probe's records. ``frames_out`` gets, per change,
    the frames the viewer drew until the next change and their ms of draw calls."""
    time.sleep(0.5)  # the last change's frame
    msgs, frames = viewer.evaluate(
        "() => { const P = window.__viewerProbe; const out = [P.msgs, P.frames];"
        " P.msgs = []; P.frames = []; return out; }"
    )
    out = []
    ends = [t for t, _ in moves[1:]] + [float("inf")]
    for (t0, label), t1 in zip(moves, ends, strict=True):
        got = [m for m in msgs if t0 <= m < t1]
        if frames_out is not None:
            drawn = [f for f in frames if t0 <= f[0] < min(t1, t0 + 5000.0)]
            frames_out.append((len(drawn), sum(b - a for a, b in drawn)))
        if not got:
            continue
        frame = next((f for f in frames if f[0] >= got[-1]), None)
        if frame is not None:
            out.append((label, frame[1] - t0))
    return out


def main() -> int:
    threadpool_limits(limits=1, user_api="blas")  # as `threadrecon serve` does
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=str(ROOT / "sample_data"))
    ap.add_argument("--repeat", type=int, default=3, help="changes per parameter and frame")
    ap.add_argument(
        "--viewer",
        choices=("socket", "chromium", "none"),
        default="socket",
        help="socket: a websocket client that receives everything and renders nothing "
        "(default); chromium: the real page, its software WebGL on the same cores",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="STAGE.NAME=VALUE",
        help="parameter on top of the default preset for every frame, e.g. "
        "stereo.z_near_mm=40 (repeatable)",
    )
    ap.add_argument(
        "--user-priority",
        action="store_true",
        help="put Chromium's threads that run at nice -8 (it raises its GPU process and "
        "browser so when run as root) back to 0, as for a user who is not root",
    )
    ap.add_argument(
        "--pause-ms",
        type=float,
        default=0.0,
        help="pause after each change before the next (0: back to back, as a dragged slider)",
    )
    ap.add_argument(
        "--moves",
        metavar="FILE.csv",
        help="write one row per move (frame, slider, ms, and every part of the breakdown, "
        "with this process's garbage-collection pauses and the page's state answers): what "
        "the slow moves do that the fast ones don't",
    )
    args = ap.parse_args()
    try:
        overrides = parse_overrides(args.set)
    except UserError as exc:
        ap.error(str(exc))
    db = Path("/tmp") / f"threadrecon-bench-{time.time_ns()}.sqlite3"
    changes = {  # (label, stage, name, values): each value is one slider move
        "spline.n_ctrl": ("spline", "n_ctrl", [14, 16, 15]),
        "reliability.eps1": ("reliability", "eps1", [7.0, 9.0, 8.0]),
        "reliability.eps2": ("reliability", "eps2", [4.0, 6.0, 5.0]),
        "reliability.eps3": ("reliability", "eps3", [0.7, 0.9, 0.8]),
        "reliability.threshold": ("reliability", "threshold", [0.85, 0.95, 0.9]),
    }
    results: dict[str, list[float]] = {k: [] for k in changes}
    shown3d: dict[str, list[float]] = {k: [] for k in changes}  # the viewer's first new frame
    frames3d: list[tuple[int, float]] = []  # per move: the viewer's frames and their draw ms
    parts: dict[str, dict[str, list[float]]] = {k: {} for k in changes}
    sizes: set[tuple[int, int]] = set()
    rows: list[dict[str, object]] = []  # --moves
    gc_ms = [0.0, 0]  # this process's (the server's) collection pauses: ms, generation-2 count
    gc_t0 = [0.0]

    def on_gc(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            gc_t0[0] = time.perf_counter()
        else:
            gc_ms[0] += 1000.0 * (time.perf_counter() - gc_t0[0])
            gc_ms[1] += info.get("generation") == 2

    gc.callbacks.append(on_gc)
    with (
        running_server(Path(args.data), db) as (url, state),
        browser_page(url) if args.viewer == "chromium" else contextlib.nullcontext() as page,
    ):
        http = httpx.Client(base_url=url, timeout=120)
        if page is not None:
            sid = page.evaluate("window.threadrecon.session")
            deadline = time.monotonic() + 60
            session = state.sessions.get(sid)
            while not session.views and time.monotonic() < deadline:
                time.sleep(0.1)  # the viser client connects after the page loads
            if not session.views:
                print("the viewer did not connect: measuring without it", file=sys.stderr)
        else:
            sid = http.post("/api/sessions").json()["session"]
            session = state.sessions.get(sid)
        viewer = (
            socket_viewer(state.viser_port, sid)
            if args.viewer == "socket"
            else contextlib.nullcontext([0])
        )
        stack = contextlib.ExitStack()
        received = stack.enter_context(viewer)
        deadline = time.monotonic() + 30
        while args.viewer != "none" and not session.views and time.monotonic() < deadline:
            time.sleep(0.05)
        frames = [f["id"] for f in http.get("/api/frames").json()]
        tags: dict[str, int] = {}  # overlay payloads held, as the page holds them
        probe = _viewer_frame(page)
        reniced = 0
        for frame in frames:
            if page is not None and args.user_priority:
                reniced += _user_priority()  # new threads come and go
            moves: list[tuple[float, str]] = []  # (epoch ms of the change, label)
            http.post(f"/api/frames/{frame}/run", json={"session": sid, "preset": "default"})
            if overrides:
                session.wait(session.submit(params=merge_params(session.params, overrides)), 120)
            if session.loaded is not None:
                sizes.add(session.loaded.calib.image_size)
            if page is not None:
                _page_shown(page, session.version)
            for label, (stage, name, values) in changes.items():
                cpu0 = _chromium_cpu_ms() if page is not None else None
                for value in values[: args.repeat]:
                    params = merge_params(session.params, {stage: {name: value}})
                    gc0 = list(gc_ms)
                    states0 = page.evaluate("window.threadrecon.states || 0") if page else 0
                    t_submit = time.time()
                    seq = session.submit(params=params)  # what a slider callback does
                    session.wait(seq, 120)
                    st = session.state()
                    if "camera" not in st["latency_ms"]:
                        continue
                    part = parts[label]
                    if page is not None:  # the page has the final state and drew its overlay
                        moves.append((1000.0 * t_submit, label))
                        shown = _page_shown(page, st["version"])
                        results[label].append(shown["at"] - 1000.0 * t_submit)
                        _add(part, "scene", st["latency_ms"]["shown"])
                        _add(part, "page state", shown["state_at"] - 1000.0 * t_submit)
                        _add(part, "overlay GET", shown["get_ms"])
                        _add(part, "overlay kB", shown["kB"])
                        _add(part, "page draw", shown["draw_ms"])
                    else:
                        results[label].append(st["latency_ms"]["shown"])
                        t0 = time.perf_counter()  # the page fetches the 2D overlay next
                        known = ",".join(str(t) for t in tags.values())
                        ov = http.get(f"/api/sessions/{sid}/overlay", params={"known": known})
                        _add(part, "overlay GET", 1000 * (time.perf_counter() - t0))
                        _add(part, "overlay kB", len(ov.content) / 1e3)
                        tags = ov.json().get("_tags", {})
                    for key, ms in st["timing"].items():
                        _add(part, key.removesuffix("_ms").replace("_", " "), ms)
                    row = {"frame": frame, "change": label, "value": value}
                    if page is not None:
                        row |= {
                            "ms": shown["at"] - 1000.0 * t_submit,
                            "page_state_ms": shown["state_at"] - 1000.0 * t_submit,
                            "overlay_get_ms": shown["get_ms"],
                            "page_draw_ms": shown["draw_ms"],
                            "states": shown["states"] - states0,
                        }
                    lat = st["latency_ms"]
                    row |= {"final_ms": lat.get("final"), "answered_ms": lat.get("answered")}
                    row |= {"scene_ms": lat["shown"], **st["timing"]}
                    row |= {"gc_ms": gc_ms[0] - gc0[0], "gc2": gc_ms[1] - gc0[1]}
                    rows.append(row)
                    if args.pause_ms:
                        time.sleep(args.pause_ms / 1000.0)
                if cpu0 is not None and args.repeat:  # per change, spilling into the next few
                    cpu1 = _chromium_cpu_ms()
                    for key, ms in cpu1.items():
                        _add(parts[label], f"{key} cpu", (ms - cpu0[key]) / args.repeat)
            if probe is not None and moves:
                for label, ms in _viewer_latencies(probe, moves, frames3d):
                    shown3d[label].append(ms)
        viewers = len(session.views)
        stack.close()
    gc.callbacks.remove(on_gc)
    with contextlib.suppress(OSError):
        db.unlink()
    if args.moves and rows:
        with open(args.moves, "w", newline="") as fh:
            out = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
            out.writeheader()
            out.writerows(rows)
    print(
        f"{len(frames)} frames of {args.data}, {viewers} viewer(s) attached ({args.viewer}), "
        f"{received[0] / 1e6:.1f} MB sent to the socket viewer"
    )
    if args.user_priority:
        print(f"Chromium threads put back from nice -8 to 0 (as a user who is not root): {reniced}")
    what = (
        "until the page has the final state and has drawn its 2D overlay"
        if args.viewer == "chromium"
        else "until the new spline (last layer) is in the scene, server side"
    )
    print(f"ms from the parameter change {what}")
    ok = True
    hd = any(h * w > 640 * 480 for h, w in sizes)
    targets = TARGETS_MS["hd" if hd else "vga"]
    print(f"frame sizes: {', '.join(f'{w}x{h}' for h, w in sorted(sizes))}; p90 targets")
    print(f"{'change':<24}{'n':>4}{'median':>10}{'p90':>10}{'max':>10}{'p90 max':>10}")
    for label, values in results.items():
        if not values:
            continue
        values.sort()
        p90 = values[min(len(values) - 1, int(0.9 * len(values)))]
        target = targets["spline" if label.startswith("spline") else "reliability"]
        ok &= p90 <= target
        print(
            f"{label:<24}{len(values):>4}{statistics.median(values):>10.1f}{p90:>10.1f}"
            f"{values[-1]:>10.1f}{target:>10.0f}"
        )
    if any(shown3d.values()):
        print("\nms from the change until the 3D viewer has drawn its first frame with the update")
        for label, values in shown3d.items():
            if values:
                values.sort()
                p90 = values[min(len(values) - 1, int(0.9 * len(values)))]
                print(
                    f"{label:<24}{len(values):>4}{statistics.median(values):>10.1f}{p90:>10.1f}"
                    f"{values[-1]:>10.1f}"
                )
    if frames3d:
        n3 = sorted(n for n, _ in frames3d)
        ms3 = sorted(ms for _, ms in frames3d)
        print(
            f"the viewer's frames per move (until the next): median {statistics.median(n3):.0f}, "
            f"max {n3[-1]}; their draw calls' ms per move: median {statistics.median(ms3):.1f}, "
            f"max {ms3[-1]:.1f}"
        )
    print("\nbreakdown, medians (ms unless said): compute / publish / metrics = the session worker")
    print("computing the stages / drawing their 3D layers and sending them to viser / the frame's")
    print("metrics (wall and CPU of its thread); scene = request -> last layer sent; page state =")
    print("request -> the page has the final state; overlay GET = the page's own fetches of the 2D")
    print("overlays (0 when they came with the state); page draw = redrawing the two images")
    keys = sorted({k for p in parts.values() for k in p}, key=_PART_ORDER.index)
    print(f"{'change':<24}" + "".join(f"{k:>15}" for k in keys))
    for label, part in parts.items():
        if part:
            cells = (statistics.median(part[k]) if part.get(k) else float("nan") for k in keys)
            print(f"{label:<24}" + "".join(f"{c:>15.1f}" for c in cells))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
