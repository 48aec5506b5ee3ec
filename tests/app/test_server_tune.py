"""Tuning through the REST API (app/api/routes_tune.py, app/tune/job.py): a small tune runs
from a session's setting, its results carry the best trials, importance and Pareto front, a
trial loads into the session or saves as a new user preset, and bad requests are clear 4xx."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from threadrecon.app.server import ServerConfig, create_app
from threadrecon.app.tune.results import pareto_front

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data"
SPACE = {"reliability": {"eps1": {"low": 3.0, "high": 12.0}}, "spline": {"n_ctrl": [10, 16]}}
BIG_GRID = {  # 55 x 20 x 11 points
    "spline": {"n_ctrl": {"low": 6, "high": 60}},
    "bounds": {"r_k_min": {"low": 1, "high": 20}},
    "ordering": {"tip_px": {"low": 0.0, "high": 5.0, "step": 0.5}},
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory):
    tmp = tmp_path_factory.mktemp("tune-server")
    config = ServerConfig(
        data_dir=SAMPLE,
        viser_port=free_port(),
        open_first=False,
        db_path=tmp / "db.sqlite3",
        configs_dir=tmp / "presets",
    )
    with TestClient(create_app(config), base_url="http://127.0.0.1") as c:
        yield c


def wait_done(client: TestClient, timeout: float = 120.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        snap = client.get("/api/tune/current").json()
        if snap["state"] != "running":
            return snap
        time.sleep(0.1)
    raise AssertionError("the tune did not finish in time")


def start(client: TestClient, **body: Any) -> Any:
    body = {"space": SPACE, "trials": 3, "max_frames": 2, "objective": "e_S", **body}
    return client.post("/api/tune", json=body)


@pytest.fixture(scope="module")
def finished(client: TestClient) -> dict[str, Any]:
    sid = client.post("/api/sessions").json()["session"]
    client.patch(f"/api/sessions/{sid}/params", json={"stereo": {"window": 7}})
    r = start(client, session=sid)
    assert r.status_code == 200, r.text
    assert r.json()["state"] == "running" and r.json()["target"] == 3
    snap = wait_done(client)
    assert snap["state"] == "done", snap
    return {"sid": sid, "snap": snap}


def test_a_tune_from_the_page_runs_its_trials_on_the_session_setting(client, finished):
    snap = finished["snap"]
    assert snap["done"] == 3 and len(snap["trials"]) == 3
    assert snap["frames"]["total"] == 2  # max_frames: two frames per trial
    assert [t["number"] for t in snap["trials"]] == [0, 1, 2]
    for t in snap["trials"]:
        assert set(t["values"]) == {"reliability.eps1", "spline.n_ctrl"}
        assert 3.0 <= t["values"]["reliability.eps1"] <= 12.0
        assert t["values"]["spline.n_ctrl"] in (10, 16)
    # polling from an index sends only the newer trials
    assert [t["number"] for t in client.get("/api/tune/current?since=2").json()["trials"]] == [2]
    # the trial's full setting keeps the session's own window
    r = client.post("/api/tune/current/trials/0/load", json={"session": finished["sid"]})
    assert r.status_code == 200, r.text
    params = r.json()["params"]
    assert params["stereo"]["window"] == 7
    t0 = snap["trials"][0]["values"]
    assert params["reliability"]["eps1"] == pytest.approx(t0["reliability.eps1"])
    assert params["spline"]["n_ctrl"] == t0["spline.n_ctrl"]


def test_results_hold_best_trials_importance_and_the_pareto_front(client, finished):
    res = client.get("/api/tune/current/results").json()
    assert res["objective"]["name"] == "e_S" and res["objective"]["direction"] == "minimize"
    assert {d["key"] for d in res["dimensions"]} == {"reliability.eps1", "spline.n_ctrl"}
    by_number = {t["number"]: t for t in res["trials"]}
    best = [by_number[n] for n in res["best"]]
    assert best, res
    feasible_first = [not t["feasible"] for t in best]
    assert feasible_first == sorted(feasible_first)
    e_s = [t["objectives"]["e_S"] for t in best if t["feasible"]]
    assert e_s == sorted(e_s)
    assert res["pareto"]["axes"] == ["e_S", "failure_rate", "time"]
    assert set(res["pareto"]["front"]) <= set(by_number) and res["pareto"]["front"]
    if res["importance"]:
        assert set(res["importance"]) <= {"reliability.eps1", "spline.n_ctrl"}
        assert sum(res["importance"].values()) == pytest.approx(1.0)
    else:
        assert res["importance_note"]


def test_a_trial_saves_as_a_new_user_preset_never_over_another(client, finished):
    r = client.post("/api/tune/current/trials/1/preset", json={"name": "tuned-one"})
    assert r.status_code == 200, r.text
    assert "tuned-one" in client.get("/api/presets").json()
    got = client.get("/api/presets/tuned-one").json()["params"]
    t1 = finished["snap"]["trials"][1]["values"]
    assert got["spline"]["n_ctrl"] == t1["spline.n_ctrl"]
    assert got["stereo"]["window"] == 7
    again = client.post("/api/tune/current/trials/0/preset", json={"name": "tuned-one"})
    assert again.status_code == 409
    assert client.get("/api/presets/tuned-one").json()["params"] == got
    builtin = client.post("/api/tune/current/trials/0/preset", json={"name": "default"})
    assert builtin.status_code == 403
    missing = client.post("/api/tune/current/trials/99/preset", json={"name": "x"})
    assert missing.status_code == 404


@pytest.mark.parametrize(
    ("body", "status", "message"),
    [
        ({"space": {"reliability": {"eps1": {"low": 3.0, "high": 1e9}}}}, 422, "reliability.eps1"),
        ({"space": {"reliability": {"nope": [1]}}}, 422, "unknown parameter reliability.nope"),
        ({"space": {}}, 422, "names no parameter"),
        ({"trials": 0}, 422, "trials"),
        ({"trials": 10**6}, 422, "trials"),
        ({"objective": "beauty"}, 422, "unknown objective"),
        ({"constraints": ["failure_rate<0.1"]}, 422, "expected METRIC<=VALUE"),
        ({"mode": "grid", "trials": None}, 422, "a grid needs choices or a step"),
        (
            {"mode": "grid", "trials": None, "space": BIG_GRID},
            422,
            "points",
        ),
        ({"session": "nope"}, 404, "nope"),
    ],
)
def test_bad_tune_requests_are_clear_4xx(client, finished, body, status, message):
    r = start(client, **body)
    assert r.status_code == status, r.text
    assert message in r.text


def test_one_tune_at_a_time_and_cancel_keeps_the_finished_trials(client, finished):
    r = start(client, trials=40, max_frames=None)
    assert r.status_code == 200, r.text
    assert start(client).status_code == 409
    deadline = time.monotonic() + 60
    while client.get("/api/tune/current").json()["done"] < 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    snap = client.post("/api/tune/current/cancel").json()
    assert snap["state"] == "cancelled", snap
    assert 1 <= snap["done"] < 40
    assert [t["number"] for t in snap["trials"]] == list(range(snap["done"]))
    assert start(client).status_code == 200  # the next one may start
    assert wait_done(client)["state"] == "done"


def test_pareto_front_keeps_exactly_the_non_dominated_points():
    pts = np.array([[1, 5, 1], [2, 2, 2], [3, 3, 3], [1, 5, 2], [np.nan, 0, 0], [5, 1, 9]])
    assert pareto_front(pts).tolist() == [0, 1, 5]
    rng = np.random.default_rng(7)
    for _ in range(20):
        p = rng.integers(0, 4, size=(15, 3)).astype(float)
        front = set(pareto_front(p).tolist())
        for i in range(len(p)):
            dominated = any((p[j] <= p[i]).all() and (p[j] < p[i]).any() for j in range(len(p)))
            assert (i in front) == (not dominated)
