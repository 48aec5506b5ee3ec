"""The debugger's REST API, through FastAPI's test client (the lifespan starts viser too)."""

from __future__ import annotations

import shutil
import socket
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from threadrecon.app.server import ServerConfig, create_app
from threadrecon.core.pipeline import STAGES

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"
FLAT = "simulated/flat/flat_1"
TISSUE = "simulated/tissue/tissue_1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_client(data_dir: Path) -> TestClient:
    config = ServerConfig(data_dir=data_dir, viser_port=free_port(), open_first=False)
    return TestClient(create_app(config), base_url="http://127.0.0.1")


@pytest.fixture(scope="module")
def client():
    with make_client(SAMPLE) as c:
        yield c


def url(frame_id: str, rest: str) -> str:
    return f"/api/frames/{frame_id}/{rest}"


def run(client: TestClient, frame_id: str = FLAT, **body) -> dict:
    r = client.post(url(frame_id, "run"), json=body)
    assert r.status_code == 200, r.text
    return r.json()


def test_frames_lists_the_sample_data(client):
    frames = client.get("/api/frames").json()
    assert len(frames) == 14  # flat 4, tissue 4, crossing 2, raw 4 (no masks)
    assert {f["kind"] for f in frames} == {"simulated"}
    assert all({"id", "kind", "has_ground_truth", "name", "status"} <= set(f) for f in frames)
    assert any(f["id"] == FLAT for f in frames)


def test_images_are_the_rectified_pair(client):
    for side in ("left", "right"):
        r = client.get(url(FLAT, f"images/{side}"))
        assert r.status_code == 200
        img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
        assert img.shape == (480, 640, 3)
    assert client.get(url(FLAT, "images/middle")).status_code == 404


def test_run_reconstructs_every_stage(client):
    st = run(client, params={}, preset="default")
    assert st["status"] == "ok", st["error"]
    assert [s["stage"] for s in st["stages"]] == list(STAGES)
    assert all(s["status"] in ("done", "cached") for s in st["stages"])
    assert st["metrics"]["e_S_mm"] < 0.5
    cam = client.get(url(FLAT, "stages/camera")).json()["result"]
    assert len(cam["points"]) >= 200 and len(cam["points"][0]) == 3


def test_reliability_threshold_changes_the_reliable_pixels(client):
    # the clean flat frames have R = 1 everywhere; the tissue frames have doubtful pixels
    run(client, TISSUE, preset="default")
    loose = client.get(url(TISSUE, "stages/reliability")).json()["result"]["count"]
    run(client, TISSUE, params={"reliability": {"threshold": 0.999}})
    strict = client.get(url(TISSUE, "stages/reliability")).json()["result"]["count"]
    assert 0 < strict < loose


def test_spline_parameter_reruns_only_the_spline_and_camera(client):
    run(client, preset="default")
    st = run(client, params={"spline": {"n_ctrl": 12}})
    status = {s["stage"]: s["status"] for s in st["stages"]}
    assert all(status[s] == "cached" for s in STAGES[:6])
    assert status["spline"] == "done" and status["camera"] == "done"
    assert st["params"]["spline"]["n_ctrl"] == 12
    assert st["preset"] == "custom"


@pytest.mark.parametrize(
    ("path", "method"),
    [
        (url("simulated/flat/nope", "run"), "post"),
        (url("simulated/flat/nope", "images/left"), "get"),
        (url("simulated/flat/nope", "stages/stereo"), "get"),
        ("/api/sessions/nope", "get"),
        (url(FLAT, "stages/nope"), "get"),
    ],
)
def test_unknown_ids_give_404(client, path, method):
    r = getattr(client, method)(path, **({"json": {}} if method == "post" else {}))
    assert r.status_code == 404
    assert "nope" in r.json()["detail"]


@pytest.mark.parametrize(
    ("params", "name"),
    [
        ({"reliability": {"threshold": 2.0}}, "reliability.threshold"),
        ({"stereo": {"alpha": -3}}, "stereo.alpha"),
        ({"spline": {"n_ctrl": "many"}}, "spline.n_ctrl"),
        ({"spline": {"wiggle": 1}}, "spline.wiggle"),
        ({"clustering": {"min_size": 50, "max_size": 10}}, "clustering.min_size"),
        ({"nonsense": {}}, "nonsense"),
    ],
)
def test_out_of_range_parameters_give_422_naming_them(client, params, name):
    before = run(client, preset="default")["params"]
    r = client.post(url(FLAT, "run"), json={"params": params})
    assert r.status_code == 422
    assert name in r.json()["detail"]
    sid = client.post("/api/sessions").json()["session"]
    r = client.patch(f"/api/sessions/{sid}/params", json=params)
    assert r.status_code == 422 and name in r.json()["detail"]
    assert client.get("/api/sessions/api").json()["params"] == before  # nothing applied


def test_two_sessions_do_not_disturb_each_other(client):
    a = client.post("/api/sessions", params={"frame_id": FLAT}).json()["session"]
    b = client.post("/api/sessions", params={"frame_id": TISSUE}).json()["session"]
    errors: list[str] = []

    def hammer(sid: str, frame: str, threshold: float) -> None:
        for _ in range(3):
            r = client.post(
                url(frame, "run"),
                json={"session": sid, "params": {"reliability": {"threshold": threshold}}},
            )
            if r.status_code != 200:
                errors.append(r.text)

    ta = threading.Thread(target=hammer, args=(a, FLAT, 0.97))
    tb = threading.Thread(target=hammer, args=(b, TISSUE, 0.8))
    ta.start(), tb.start()
    ta.join(), tb.join()
    assert not errors
    sa, sb = (client.get(f"/api/sessions/{s}").json() for s in (a, b))
    assert (sa["frame_id"], sa["shown_frame"]) == (FLAT, FLAT)
    assert (sb["frame_id"], sb["shown_frame"]) == (TISSUE, TISSUE)
    assert sa["params"]["reliability"]["threshold"] == 0.97
    assert sb["params"]["reliability"]["threshold"] == 0.8
    assert sa["status"] == sb["status"] == "ok"
    ra = client.get(f"/api/sessions/{a}/stages/reliability").json()["result"]["count"]
    ra_direct = client.get(url(FLAT, "stages/reliability"), params={"session": a}).json()
    assert ra == ra_direct["result"]["count"]


def test_latest_parameter_wins_when_changes_come_fast(client):
    sid = client.post("/api/sessions", params={"frame_id": FLAT}).json()["session"]
    for n in (10, 11, 12, 13, 14):
        r = client.patch(f"/api/sessions/{sid}/params", json={"spline": {"n_ctrl": n}})
        assert r.status_code == 200
    st = client.get(f"/api/sessions/{sid}/stages/spline")
    client.get(f"/api/sessions/{sid}", params={"since": 0, "timeout": 1})
    from_state = client.post(url(FLAT, "run"), json={"session": sid}).json()
    assert from_state["params"]["spline"]["n_ctrl"] == 14
    ctrl = client.get(f"/api/sessions/{sid}/stages/spline").json()["result"]["ctrl"]
    assert len(ctrl) == 14
    assert st.status_code in (200, 409)


def test_stepper_reveals_one_stage_at_a_time(client):
    sid = client.post("/api/sessions", params={"frame_id": FLAT}).json()["session"]
    client.post(url(FLAT, "run"), json={"session": sid})
    revealed = []
    for _ in range(3):
        st = client.post(
            f"/api/sessions/{sid}/step", params={"wait": True}, json={"action": "next"}
        )
        revealed.append(sum(s["revealed"] for s in st.json()["stages"]))
    assert revealed == [1, 2, 3]
    st = client.get(f"/api/sessions/{sid}").json()
    assert [s["status"] for s in st["stages"][:3]] != ["pending"] * 3
    assert all(s["status"] == "pending" for s in st["stages"][3:])
    assert client.get(f"/api/sessions/{sid}/stages/bounds").status_code == 409
    st = client.post(f"/api/sessions/{sid}/step", params={"wait": True}, json={"action": "all"})
    assert all(s["revealed"] for s in st.json()["stages"]) and st.json()["status"] == "ok"
    bad = client.post(f"/api/sessions/{sid}/step", json={"action": "jump"})
    assert bad.status_code == 422


def test_pixel_inspector_explains_a_pixel(client):
    run(client, preset="default")
    rel = client.get(url(FLAT, "stages/reliability")).json()["result"]
    stereo = client.get(url(FLAT, "stages/stereo")).json()["result"]
    i = rel["reliable"].index(True)
    x, y = stereo["pixels"][i]
    info = client.get("/api/sessions/api/pixel", params={"x": x, "y": y}).json()
    assert info["segmented"] and (info["x"], info["y"]) == (x, y)
    energy = np.array(info["energy"], dtype=float)
    assert energy.shape == (81,)
    assert info["d_min"] == int(np.nanargmin(energy))
    assert abs(info["d_next"] - info["d_min"]) > 2
    assert info["reliable"] is True and info["R"] >= 0.9
    assert client.get("/api/sessions/api").json()["inspect"]["x"] == x
    off = client.get("/api/sessions/api/pixel", params={"x": 2, "y": 2}).json()
    assert off["segmented"] is False
    outside = client.get("/api/sessions/api/pixel", params={"x": 5000, "y": 2})
    assert outside.status_code == 422 and "outside" in outside.json()["detail"]


def test_overlay_projects_the_spline_into_both_images(client):
    st = run(client, preset="default")
    ov = client.get("/api/sessions/api/overlay").json()
    assert ov["frame_id"] == FLAT
    for side in ("left", "right"):
        assert ov["spline"][side]["mean_px"] == pytest.approx(
            st["metrics"][f"{side}_mean_px"], abs=0.05
        )
        assert len(ov["spline"][side]["points"]) > 100
    assert len(ov["reliable"]["left"]) % 2 == 0 and len(ov["reliable"]["left"]) > 0
    assert len(ov["keypoints"]["left"]) > 3


@pytest.fixture(scope="module")
def broken_data(tmp_path_factory):
    """A copy of two sample frames plus an empty frame (no thread) and a corrupt image."""
    root = tmp_path_factory.mktemp("broken")
    group = root / "simulated" / "flat"
    group.mkdir(parents=True)
    src = SAMPLE / "simulated" / "flat"
    shutil.copy(src / "calibration.yaml", group)
    for name in ("flat_1.png", "flat_1.npy"):
        shutil.copy(src / name, group)
    img = cv2.imread(str(src / "flat_1.png"))
    cv2.imwrite(str(group / "blank.png"), np.full_like(img, 200))
    np.save(group / "blank.npy", np.load(src / "flat_1.npy"))
    (group / "corrupt.png").write_bytes(b"not a png at all")
    return root


def test_a_failing_frame_shows_its_stage_and_the_server_keeps_serving(broken_data):
    with make_client(broken_data) as c:
        st = c.post(url("simulated/flat/blank", "run"), json={}).json()
        assert st["status"] == "failed"
        assert st["failed_stage"] == "segment"
        assert "segment" in st["error"]
        statuses = {s["stage"]: s["status"] for s in st["stages"]}
        assert statuses["segment"] == "failed" and statuses["stereo"] == "pending"
        r = c.get(url("simulated/flat/blank", "stages/stereo"))
        assert r.status_code == 409 and "failed at segment" in r.json()["detail"]
        st = c.post(url("simulated/flat/corrupt", "run"), json={}).json()
        assert st["status"] == "failed" and st["failed_stage"] == "load"
        assert "corrupt" in st["error"]
        assert c.get(url("simulated/flat/corrupt", "images/left")).status_code == 422
        st = c.post(url("simulated/flat/flat_1", "run"), json={}).json()
        assert st["status"] == "ok"
        frames = {f["id"]: f["status"] for f in c.get("/api/frames").json()}
        assert frames["simulated/flat/blank"] == "failed"
        assert frames["simulated/flat/flat_1"] == "ok"


def test_page_and_docs_are_served(client):
    page = client.get("/")
    assert page.status_code == 200 and "threadrecon" in page.text
    for asset in ("js/main.js", "js/core.js", "style.css"):
        assert client.get(f"/static/{asset}").status_code == 200
    assert client.get("/docs").status_code == 200
    spec = client.get("/openapi.json").json()
    assert "/api/frames" in spec["paths"]
    info = client.get("/api/info").json()
    assert info["viser_port"] > 0 and info["stages"] == list(STAGES)
    keys = {c["key"] for c in info["controls"]}
    for key in ("reliability.eps1", "reliability.threshold", "spline.n_ctrl", "bounds.bound_scale"):
        assert key in keys


def test_session_and_run_answers_are_declared_response_models(client):
    spec = client.get("/openapi.json").json()

    def ref(path: str, method: str) -> str:
        content = spec["paths"][path][method]["responses"]["200"]["content"]
        return content["application/json"]["schema"]["$ref"].rsplit("/", 1)[-1]

    for path, method in (
        ("/api/sessions/{sid}", "get"),
        ("/api/sessions/{sid}/params", "patch"),
        ("/api/sessions/{sid}/step", "post"),
        ("/api/frames/{frame_id}/run", "post"),
    ):
        assert ref(path, method) == "SessionState", path
    assert ref("/api/sessions/{sid}/stages/{stage}", "get") == "StageAnswer"
    assert ref("/api/info", "get") == "Info"
    state = run(client, preset="default")
    assert set(state) == set(spec["components"]["schemas"]["SessionState"]["properties"])
    assert state["status"] in ("ok", "suspect") and isinstance(state["reasons"], list)
    assert all(s["status"] in ("done", "cached") for s in state["stages"])


def test_overlay_leaves_out_the_payloads_the_page_holds(client):
    run(client, preset="default")
    full = client.get("/api/sessions/api/overlay").json()
    tags = full["_tags"]
    assert set(tags) <= set(full) and len(set(tags.values())) == len(tags)
    held = ",".join(str(tags[k]) for k in ("mask", "reliable"))
    part = client.get("/api/sessions/api/overlay", params={"known": held}).json()
    assert "mask" not in part and "reliable" not in part and part["_tags"] == tags
    assert part["spline"] == full["spline"]
    bad = client.get("/api/sessions/api/overlay", params={"known": "1,x"})
    assert bad.status_code == 422 and "integer tags" in bad.json()["detail"]


def test_the_page_asks_for_a_process_apart_from_the_viewer(client):
    # the viewer's software WebGL frames must not hold up the page's main thread
    assert client.get("/static/index.html").headers["origin-agent-cluster"] == "?1"


def test_a_finished_run_state_brings_the_overlays_the_page_does_not_hold(client):
    run(client, preset="default")
    full = client.get("/api/sessions/api/overlay").json()
    st = client.get("/api/sessions/api", params={"overlay": ""}).json()
    assert not st["busy"] and st["overlay"]["spline"] == full["spline"]
    held = ",".join(str(t) for t in full["_tags"].values())
    st = client.get("/api/sessions/api", params={"overlay": held}).json()
    assert set(st["overlay"]) == {"shape", "_pixels", "_tags", "_later", "frame_id", "version"}
    assert "overlay" not in client.get("/api/sessions/api").json()  # only when asked


def test_a_state_brings_only_the_overlays_the_page_shows_and_names_the_others(client):
    run(client, preset="default")
    st = client.get("/api/sessions/api", params={"overlay": "", "keys": "spline,reliable"})
    ov = st.json()["overlay"]
    assert set(ov["_tags"]) == {"spline", "reliable"} and "ordering_graph" not in ov
    assert {"ordering_graph", "confidence", "spline_initial"} <= set(ov["_later"])
    held = ",".join(str(t) for t in ov["_tags"].values())
    got = client.get(
        "/api/sessions/api/overlay", params={"known": held, "keys": "spline,ordering_graph"}
    ).json()  # the page turned the ordering graph on: only it comes
    assert set(got["_tags"]) == {"spline", "ordering_graph"} and "spline" not in got
    assert got["ordering_graph"]["left"]["segments"]
    assert "reliable" in got["_later"] and "ordering_graph" not in got["_later"]


def test_serve_puts_the_start_up_heap_out_of_the_collectors_reach(monkeypatch, tmp_path):
    """Once started, the server freezes what its start made: a full garbage collection (which
    stops every thread, slider moves included) then scans only the objects made since."""
    import asyncio
    import gc

    import uvicorn

    from threadrecon.app import heap
    from threadrecon.app import server as server_module
    from threadrecon.app.api.state import AppState

    monkeypatch.setattr(heap, "_settled", False)  # restored after: this process is no server

    async def started(self, sockets=None):  # listening, the lifespan run: nothing here
        self.started = True

    monkeypatch.setattr(uvicorn.Server, "startup", started)
    monkeypatch.setattr(AppState, "viser_port", property(lambda self: 0))
    monkeypatch.setattr(
        uvicorn.Server, "run", lambda self, sockets=None: asyncio.run(self.startup())
    )
    config = ServerConfig(
        data_dir=SAMPLE, viser_port=free_port(), open_first=False, db_path=tmp_path / "db.sqlite3"
    )
    gc.unfreeze()
    try:
        server_module.serve(config)
        assert gc.get_freeze_count() > 10_000  # the imports, the app
        frozen = gc.get_freeze_count()
        made = [[] for _ in range(10)]  # made since: the collector still sees them
        assert gc.get_freeze_count() == frozen and any(gc.is_tracked(m) for m in made)
    finally:
        gc.unfreeze()
