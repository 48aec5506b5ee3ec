"""Ratings, presets, whole-dataset evaluation and exports through the debugger's REST API."""

from __future__ import annotations

import csv
import io
import os
import shutil
import socket
import threading
import time
import urllib.parse
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from test_server import FLAT, SAMPLE, free_port, url

from threadrecon.app.cli import main as cli_main
from threadrecon.app.ratings import StoreError
from threadrecon.app.server import ServerConfig, create_app
from threadrecon.core.pipeline import STAGES

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.fixture()
def setup(tmp_path):
    """A writable data folder (sample_data's flat frames) and preset folder per test."""
    data = tmp_path / "data"
    shutil.copytree(SAMPLE / "simulated" / "flat", data / "simulated" / "flat")
    configs = tmp_path / "configs"
    shutil.copytree(CONFIGS, configs)
    return data, configs


def client_for(data: Path, configs: Path, db: Path | None = None) -> TestClient:
    config = ServerConfig(
        data_dir=data, viser_port=free_port(), open_first=False, configs_dir=configs, db_path=db
    )
    return TestClient(create_app(config), base_url="http://127.0.0.1")


# --- ratings ---------------------------------------------------------------------------------


def test_a_rating_survives_a_restart_and_keeps_its_history(setup):
    data, configs = setup
    with client_for(data, configs) as c:
        c.post(url(FLAT, "run"), json={"preset": "default"})
        r = c.put(url(FLAT, "rating"), json={"score": 4, "note": "tip slightly short"})
        assert r.status_code == 200, r.text
        first = r.json()["latest"]
        assert first["preset"] == "default" and len(first["params_hash"]) == 12
        c.put(url(FLAT, "rating"), json={"score": 2, "note": "re-rated"})
    with client_for(data, configs) as c:  # a new server on the same database
        got = c.get(url(FLAT, "rating")).json()
        assert got["latest"]["score"] == 2 and got["latest"]["note"] == "re-rated"
        assert [h["score"] for h in got["history"]] == [2, 4]
        frames = {f["id"]: f["rating"] for f in c.get("/api/frames").json()}
        assert frames[FLAT] == 2 and frames["simulated/flat/flat_2"] is None
    assert (data / "threadrecon.sqlite3").exists()


def test_ratings_csv_matches_what_was_stored(setup):
    data, configs = setup
    with client_for(data, configs) as c:
        notes = {FLAT: 'thread "hook", missed\nsecond line', "simulated/flat/flat_2": "fine"}
        for i, (frame, note) in enumerate(notes.items()):
            assert (
                c.put(url(frame, "rating"), json={"score": 3 + i, "note": note}).status_code == 200
            )
        r = c.get("/api/ratings.csv")
        assert r.headers["content-type"].startswith("text/csv")
        rows = list(csv.DictReader(io.StringIO(r.text)))
        assert {row["frame_id"]: row["note"] for row in rows} == notes
        for row in rows:
            stored = c.get(url(row["frame_id"], "rating")).json()["latest"]
            assert {k: str(v) for k, v in stored.items()} == row


@pytest.mark.parametrize("score", [0, 6, "x", 3.5, None, True])
def test_invalid_scores_give_422_and_store_nothing(setup, score):
    data, configs = setup
    with client_for(data, configs) as c:
        r = c.put(url(FLAT, "rating"), json={"score": score})
        assert r.status_code == 422 and "score" in r.json()["detail"]
        assert c.get(url(FLAT, "rating")).json()["history"] == []
        assert len(list(csv.reader(io.StringIO(c.get("/api/ratings.csv").text)))) == 1


def test_rating_an_unknown_frame_gives_404(setup):
    data, configs = setup
    with client_for(data, configs) as c:
        assert c.put(url("simulated/flat/nope", "rating"), json={"score": 3}).status_code == 404


def test_two_ratings_sent_at_once_from_two_clients_are_both_kept(setup):
    data, configs = setup
    app = create_app(
        ServerConfig(data_dir=data, viser_port=free_port(), open_first=False, configs_dir=configs)
    )
    with (
        TestClient(app, base_url="http://127.0.0.1") as c1,
        TestClient(app, base_url="http://127.0.0.1") as c2,
    ):
        barrier = threading.Barrier(2)
        codes: list[int] = []

        def rate(c: TestClient, score: int) -> None:
            barrier.wait()
            codes.append(c.put(url(FLAT, "rating"), json={"score": score}).status_code)

        threads = [threading.Thread(target=rate, args=(c, s)) for c, s in ((c1, 1), (c2, 5))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert codes == [200, 200]
        assert sorted(h["score"] for h in c1.get(url(FLAT, "rating")).json()["history"]) == [1, 5]


def test_a_corrupt_database_stops_the_start_and_is_left_untouched(setup, capsys):
    data, configs = setup
    db = data / "threadrecon.sqlite3"
    junk = os.urandom(4096)
    db.write_bytes(junk)
    with pytest.raises(StoreError, match="threadrecon.sqlite3"):
        create_app(ServerConfig(data_dir=data, viser_port=free_port(), configs_dir=configs))
    assert cli_main(["serve", str(data), "--port", str(free_port())]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "threadrecon.sqlite3" in err and "--db" in err
    assert db.read_bytes() == junk


def test_serve_on_a_taken_port_is_a_one_line_error(setup, capsys):
    data, _ = setup
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        assert cli_main(["serve", str(data), "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(port) in err and "--port" in err


def test_a_read_only_database_stops_the_start(setup):
    data, configs = setup
    db = data / "ratings.sqlite3"
    with client_for(data, configs, db) as c:
        c.put(url(FLAT, "rating"), json={"score": 4})
    before = db.read_bytes()
    db.chmod(0o444)
    try:
        if os.access(db, os.W_OK) and os.geteuid() == 0:
            pytest.skip("running as root: a read-only file is still writable")
        with pytest.raises(StoreError, match="read-only"):
            create_app(ServerConfig(data_dir=data, viser_port=free_port(), db_path=db))
    finally:
        db.chmod(0o644)
    assert db.read_bytes() == before


def test_ratings_summary_is_table_ii_with_the_failure_rate(setup):
    data, configs = setup
    with client_for(data, configs) as c:
        c.put(url(FLAT, "rating"), json={"score": 5})
        c.put(url("simulated/flat/flat_2", "rating"), json={"score": 2})
        c.put(url("simulated/flat/flat_2", "rating"), json={"score": 1})
        got = c.get("/api/ratings/summary").json()
        assert [r["frame"] for r in got["rows"]] == [FLAT, "simulated/flat/flat_2"]
        assert [r["score"] for r in got["rows"]] == [5, 1]
        assert got["summary"]["failure_rate"] == 0.5 and got["summary"]["rated"] == 2
        # Nothing is recomputed in the request: without a saved evaluation, no figures.
        assert got["evaluation"] is None
        assert all(r["left_mean_px"] is None for r in got["rows"])
        c.post("/api/evaluations", json={})
        _wait_job(c)
        got = c.get("/api/ratings/summary").json()
        assert got["evaluation"]["same_params"] is True
        saved = {r["frame"]: r for r in c.get("/api/evaluations/last").json()["rows"]}
        for r in got["rows"]:
            assert 0 <= r["left_mean_px"] < 1.0 and 0.9 <= r["coverage_right"] <= 1.0
            assert r["left_mean_px"] == saved[r["frame"]]["left_mean_px"]  # the stored figure
            assert r["same_params"] is True


# --- presets ---------------------------------------------------------------------------------


def test_saving_and_loading_a_preset_restores_every_parameter(setup):
    data, configs = setup
    with client_for(data, configs) as c:
        a = c.post("/api/sessions").json()["session"]
        change = {"reliability": {"threshold": 0.95, "eps1": 6.5}, "spline": {"n_ctrl": 18}}
        tuned = c.patch(f"/api/sessions/{a}/params", json=change).json()["params"]
        r = c.post("/api/presets", json={"name": "tuned-1", "session": a})
        assert r.status_code == 200, r.text
        assert "tuned-1" in c.get("/api/presets").json()
        diff = {d["key"]: d["value"] for d in c.get("/api/presets/tuned-1").json()["diff"]}
        assert diff == {"reliability.threshold": 0.95, "reliability.eps1": 6.5, "spline.n_ctrl": 18}
        b = c.post("/api/sessions").json()["session"]  # "reloading the page": a new session
        assert c.get(f"/api/sessions/{b}").json()["params"] != tuned
        st = c.post(f"/api/sessions/{b}/preset", json={"name": "tuned-1", "wait": True}).json()
        assert st["params"] == tuned and st["preset"] == "tuned-1"
        assert st["status"] == "ok"
        assert {d["key"] for d in st["diff"]} == set(diff)
    out = io.StringIO()
    with open(configs / "tuned-1.toml") as fh:
        out.write(fh.read())
    assert "threshold = 0.95" in out.getvalue()


def test_built_in_presets_are_read_only_and_user_presets_go_to_the_user_folder(setup):
    data, configs = setup
    tracked = CONFIGS / "default.toml"
    before = tracked.read_bytes()
    with client_for(data, configs) as c:
        sid = c.post("/api/sessions").json()["session"]
        c.patch(f"/api/sessions/{sid}/params", json={"spline": {"n_ctrl": 9}})
        for name in ("default", "paper-real"):
            for overwrite in (False, True):
                body = {"name": name, "session": sid, "overwrite": overwrite}
                r = c.post("/api/presets", json=body)
                assert r.status_code == 403 and "read-only" in r.json()["detail"]
        assert tracked.read_bytes() == before
        assert c.get("/api/presets/default").json()["params"]["spline"]["n_ctrl"] != 9
        assert c.get("/api/presets/default").json()["builtin"] is True
        r = c.post("/api/presets", json={"name": "mine", "session": sid})
        assert r.status_code == 200 and Path(r.json()["path"]).parent == configs
        assert (
            c.get("/api/presets").json()[0] == "default" and "mine" in c.get("/api/presets").json()
        )
    assert not (CONFIGS / "mine.toml").exists()


def test_an_existing_preset_is_not_overwritten_without_confirmation(setup):
    data, configs = setup
    with client_for(data, configs) as c:
        sid = c.post("/api/sessions").json()["session"]
        c.patch(f"/api/sessions/{sid}/params", json={"spline": {"n_ctrl": 9}})
        for bad in ("", "../evil", "a b", "x" * 80, "mine\n", "mine\n\n"):
            assert c.post("/api/presets", json={"name": bad, "session": sid}).status_code == 422
            path = "/api/presets/" + urllib.parse.quote(bad, safe="")
            assert not bad or c.get(path).status_code in (404, 422)
        r = c.post("/api/presets", json={"name": "mine", "session": sid})
        assert r.status_code == 200
        c.patch(f"/api/sessions/{sid}/params", json={"spline": {"n_ctrl": 10}})
        r = c.post("/api/presets", json={"name": "mine", "session": sid})
        assert r.status_code == 409 and "overwrite" in r.json()["detail"]
        assert c.get("/api/presets/mine").json()["params"]["spline"]["n_ctrl"] == 9
        c.patch(f"/api/sessions/{sid}/params", json={"spline": {"n_ctrl": 11}})
        r = c.post("/api/presets", json={"name": "mine", "session": sid, "overwrite": True})
        assert r.status_code == 200
        assert c.get("/api/presets/mine").json()["params"]["spline"]["n_ctrl"] == 11


def test_a_preset_that_fails_validation_is_refused_with_the_key(setup):
    data, configs = setup
    (configs / "broken.toml").write_text("[reliability]\nthreshold = 7.0\n")
    (configs / "typo.toml").write_text("[spline]\nn_crtl = 12\n")
    with client_for(data, configs) as c:
        sid = c.post("/api/sessions").json()["session"]
        before = c.get(f"/api/sessions/{sid}").json()["params"]
        for name, key in (("broken", "reliability.threshold"), ("typo", "spline.n_crtl")):
            r = c.post(f"/api/sessions/{sid}/preset", json={"name": name})
            assert r.status_code == 422 and key in r.json()["detail"]
            assert c.get(f"/api/presets/{name}").status_code == 422
        assert c.get(f"/api/sessions/{sid}").json()["params"] == before
        assert c.post(f"/api/sessions/{sid}/preset", json={"name": "nope"}).status_code == 404


# --- whole-dataset evaluation ----------------------------------------------------------------


def _wait_job(c: TestClient, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        snap = c.get("/api/evaluations/current").json()
        if snap["state"] not in ("pending", "running"):
            return snap
        time.sleep(0.05)
    raise AssertionError("evaluation did not finish")


def test_evaluation_from_the_page_agrees_with_the_cli_to_the_digit(tmp_path, capsys):
    with client_for(SAMPLE, CONFIGS, tmp_path / "db.sqlite3") as c:
        snap = c.post("/api/evaluations", json={"preset": "paper-simulated"}).json()
        assert snap["total"] == 14
        t0 = time.perf_counter()
        assert c.get("/api/frames").status_code == 200  # answered during the run
        answered_ms = 1000 * (time.perf_counter() - t0)
        running = c.get("/api/evaluations/current").json()
        snap = _wait_job(c)
        assert snap["state"] == "done" and snap["done"] == 14
        saved = c.get("/api/evaluations/last").json()
        assert saved["id"] == c.get("/api/evaluations/current").json()["saved_id"]
    assert running["state"] in ("running", "done") and answered_ms < 2000
    capsys.readouterr()
    code = cli_main(
        ["evaluate", str(SAMPLE), "--config", "paper-simulated", "--out", str(tmp_path / "cli.csv")]
    )
    n_failed = sum(r["status"] != "ok" for r in saved["rows"])
    assert code == (1 if n_failed else 0)  # evaluate exits 1 when any frame failed
    printed = capsys.readouterr().out.strip().splitlines()
    assert saved["summary"] == printed
    with open(tmp_path / "cli.csv") as fh:
        cli_rows = {r["frame"]: r for r in csv.DictReader(fh)}
    for row in saved["rows"]:
        ref = cli_rows[row["frame"]]
        for col in (
            "status",
            "e_S_mm",
            "e_S_max_mm",
            "e_length_mm",
            "left_mean_px",
            "coverage_right",
        ):
            mine = row[col]
            assert (f"{mine:.6g}" if isinstance(mine, float) else str(mine)) == ref[col], col


def test_evaluation_can_be_cancelled_and_two_presets_compared(setup):
    data, configs = setup
    with client_for(data, configs) as c:
        assert c.get("/api/evaluations/current").json() is None  # nothing yet: null, not 404
        assert c.get("/api/evaluations/last").json() is None
        c.post("/api/evaluations", json={"preset": "default"})
        assert c.post("/api/evaluations", json={"preset": "default"}).status_code in (200, 409)
        a = _wait_job(c)
        assert a["state"] == "done"
        c.post("/api/evaluations", json={"preset": "paper-strict"})
        b = _wait_job(c)
        ids = [e["id"] for e in c.get("/api/evaluations").json()]
        assert len(ids) == 2
        cmp = c.get("/api/evaluations/compare", params={"a": ids[1], "b": ids[0]}).json()
        assert cmp["a"]["preset"] == "default" and cmp["b"]["preset"] == "paper-strict"
        assert [r["frame"] for r in cmp["rows"]][-1] == "mean" and len(cmp["rows"]) == 5
        row = cmp["rows"][0]
        assert row["e_S_mm_diff"] == pytest.approx(row["e_S_mm_b"] - row["e_S_mm_a"])
        assert b["preset"] == "paper-strict"
        c.post("/api/evaluations", json={"preset": "default"})
        cancelled = c.post("/api/evaluations/current/cancel").json()
        assert cancelled["state"] in ("cancelled", "done")
        if cancelled["state"] == "cancelled":
            assert len(c.get("/api/evaluations").json()) == 2  # a cancelled run is not saved
        assert c.get("/api/evaluations/99").status_code == 404


# --- exports ---------------------------------------------------------------------------------


def test_exports_of_the_current_frame(setup):
    data, configs = setup
    with client_for(data, configs) as c:
        st = c.post(url(FLAT, "run"), json={}).json()
        sid = st["session"]
        spline = c.get(f"/api/sessions/{sid}/export/spline.json")
        assert "flat_1_spline.json" in spline.headers["content-disposition"]
        js = spline.json()
        cam = c.get(url(FLAT, "stages/camera")).json()["result"]
        np.testing.assert_allclose(js["points"], cam["points"])
        assert js["degree"] == cam["degree"] and len(js["knots"]) == len(cam["knots"])
        assert len(js["keypoints"]["reliability"]) == len(js["keypoints"]["points"])
        rows = list(csv.reader(io.StringIO(c.get(f"/api/sessions/{sid}/export/spline.csv").text)))
        assert len(rows) == len(cam["points"]) + 1
        ply = c.get(f"/api/sessions/{sid}/export/reliable.ply").content
        assert ply.startswith(b"ply\nformat binary_little_endian")
        assert c.get(f"/api/sessions/{sid}/export/bogus.ply").status_code == 404
        assert c.get("/api/sessions/nope/export/spline.json").status_code == 404
        assert set(STAGES) >= {"spline", "camera"}
