"""Corrections through the REST API and the store: a vessel clicked away and a missed piece
clicked in change the curve as they should; undo, redo, clear; corrections survive a restart
of the server on the same database; the corrected masks export as PNG; hostile input gets a
clear 4xx and never loses a stored correction."""

from __future__ import annotations

import socket
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pytest
from correction_support import Case, write_case
from fastapi.testclient import TestClient

from threadrecon.app.corrections import CorrectionStore
from threadrecon.app.errors import Conflict
from threadrecon.app.ratings import RatingStore, StoreError
from threadrecon.app.server import ServerConfig, create_app
from threadrecon.core.corrections import Correction

SEED = 13  # the given mask's vessel drags the curve off the thread (status "failed")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _client(root: Path, db: Path) -> TestClient:
    config = ServerConfig(data_dir=root, viser_port=_free_port(), open_first=False, db_path=db)
    return TestClient(create_app(config), base_url="http://127.0.0.1")


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> Case:
    return write_case(tmp_path_factory.mktemp("corrections"), SEED)


def _url(case: Case, rest: str = "corrections") -> str:
    return f"/api/frames/{case.frame_id}/{rest}"


def _click(client: TestClient, case: Case, op: str, view: str, xy: tuple[int, int], **kw) -> dict:
    r = client.post(_url(case), json={"op": op, "view": view, "points": [list(xy)], **kw})
    assert r.status_code == 200, r.text
    return r.json()


def _mask(client: TestClient, case: Case, view: str) -> np.ndarray:
    r = client.get(_url(case, f"mask.png?view={view}"))
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    return cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_GRAYSCALE) > 127


def test_clicks_fix_the_curve_and_survive_a_restart(case: Case, tmp_path: Path) -> None:
    db = tmp_path / "threadrecon.sqlite3"
    with _client(case.root, db) as client:
        r = client.post(_url(case, "run"), json={})
        given = r.json()
        assert given["status"] != "ok"  # the vessel drags the curve off the thread
        for view in ("left", "right"):
            out = _click(client, case, "remove", view, case.vessel[view])
        removed = out["state"]
        assert removed["status"] == "ok", removed["error"]
        # the vessel is gone, the curve lies on the thread but misses its last third
        assert removed["metrics"]["length_mm"] < 0.8 * case.length_mm
        for view in ("left", "right"):
            out = _click(client, case, "add", view, case.missed[view])
        fixed = out["state"]
        assert fixed["status"] == "ok", fixed["error"]
        assert abs(fixed["metrics"]["e_length_mm"]) < 2.0
        assert fixed["metrics"]["e_S_mm"] < 0.5
        assert [c["op"] for c in out["corrections"]] == ["remove", "remove", "add", "add"]
        masks = {v: _mask(client, case, v) for v in ("left", "right")}
        both = _mask(client, case, "both")
        assert np.array_equal(both, np.hstack([masks["left"], masks["right"]]))
        for view, true in case.true_masks.items():
            iou = (masks[view] & true).sum() / (masks[view] | true).sum()
            assert iou > 0.9, (view, iou)
    # a new server on the same database applies the corrections to its first run
    with _client(case.root, db) as client:
        listed = client.get(_url(case)).json()
        assert [c["op"] for c in listed["corrections"]] == ["remove", "remove", "add", "add"]
        again = client.post(_url(case, "run"), json={}).json()
        assert again["metrics"]["length_mm"] == pytest.approx(fixed["metrics"]["length_mm"])
        assert again["status"] == "ok"


def test_undo_redo_and_clear(case: Case, tmp_path: Path) -> None:
    with _client(case.root, tmp_path / "db.sqlite3") as client:
        assert client.post(_url(case, "corrections/undo")).status_code == 409
        assert client.post(_url(case, "corrections/clear")).status_code == 409
        first = client.post(_url(case, "run"), json={}).json()["metrics"]["length_mm"]
        for view in ("left", "right"):
            _click(client, case, "remove", view, case.vessel[view])
        fixed = client.get("/api/sessions/api").json()["metrics"]["length_mm"]
        assert fixed != pytest.approx(first)
        r = client.post(_url(case, "corrections/undo"), json={})
        assert r.status_code == 200 and r.json()["undone"]["view"] == "right"
        assert r.json()["can_redo"] and len(r.json()["corrections"]) == 1
        r = client.post(_url(case, "corrections/redo"), json={})
        assert r.status_code == 200 and r.json()["redone"]["view"] == "right"
        assert r.json()["state"]["metrics"]["length_mm"] == pytest.approx(fixed)
        assert client.post(_url(case, "corrections/redo")).status_code == 409
        r = client.post(_url(case, "corrections/clear"), json={})
        assert r.status_code == 200
        assert r.json()["state"]["metrics"]["length_mm"] == pytest.approx(first)
        r = client.post(_url(case, "corrections/undo"), json={})  # clear is undoable
        assert r.json()["undone"]["op"] == "clear"
        assert r.json()["state"]["metrics"]["length_mm"] == pytest.approx(fixed)


def test_one_stereo_click_removes_the_vessel_from_both_views(case: Case, tmp_path: Path) -> None:
    with _client(case.root, tmp_path / "db.sqlite3") as client:
        client.post(_url(case, "run"), json={})
        out = _click(client, case, "remove", "right", case.vessel["right"], stereo=True)
        assert out["corrections"][0]["stereo"] is True
        assert out["state"]["status"] == "ok", out["state"]["error"]
        for view in ("left", "right"):
            x, y = case.vessel[view]
            assert not _mask(client, case, view)[y - 3 : y + 4, x - 3 : x + 4].any()
        r = client.post(
            _url(case), json={"op": "add", "view": "left", "points": [[5, 5]], "stereo": True}
        )
        assert r.status_code == 422 and "remove only" in r.text


@pytest.mark.parametrize(
    ("body", "status", "message"),
    [
        ({"op": "remove", "view": "left", "points": [[100000, 5]]}, 422, "outside"),
        ({"op": "remove", "view": "left", "points": [[-1, 5]]}, 422, "outside"),
        ({"op": "erase", "view": "left", "points": [[5, 5]], "radius": 1e6}, 422, "radius"),
        ({"op": "erase", "view": "left", "points": [[5, 5]], "radius": -2}, 422, ""),
        ({"op": "add", "view": "left", "points": [[1.5, 5]]}, 422, ""),
        ({"op": "add", "view": "top", "points": [[1, 5]]}, 422, ""),
        ({"op": "explode", "view": "left", "points": [[1, 5]]}, 422, ""),
        ({"op": "add", "view": "left", "points": []}, 422, ""),
        ({"op": "remove", "view": "left", "points": [[1, 5], [2, 5]]}, 422, "one click"),
        ({"op": "erase", "view": "left", "points": [[0, 0]] * 6000}, 422, ""),
        ({"op": "remove", "view": "left", "points": [[10**400, 5]]}, 422, ""),
    ],
)
def test_hostile_corrections_are_refused_and_nothing_is_stored(
    case: Case, tmp_path: Path, body: dict, status: int, message: str
) -> None:
    with _client(case.root, tmp_path / "db.sqlite3") as client:
        r = client.post(_url(case), json=body)
        assert r.status_code == status, r.text
        assert message in r.text
        assert client.get(_url(case)).json()["corrections"] == []


def test_a_correction_that_changes_nothing_or_empties_a_view_is_refused(
    case: Case, tmp_path: Path
) -> None:
    with _client(case.root, tmp_path / "db.sqlite3") as client:
        client.post(_url(case, "run"), json={})
        r = client.post(_url(case), json={"op": "remove", "view": "left", "points": [[3, 3]]})
        assert r.status_code == 422 and "no segmented piece within 8 px of (3, 3)" in r.text
        wipe = [[x, y] for y in range(0, 480, 150) for x in range(0, 640, 150)]
        r = client.post(
            _url(case), json={"op": "erase", "view": "right", "points": wipe, "radius": 200}
        )
        assert r.status_code == 422 and "no thread pixel in the right view" in r.text
        assert client.get(_url(case)).json()["corrections"] == []
        _click(client, case, "remove", "left", case.vessel["left"])
        # the stored correction outlives a refused one
        r = client.post(_url(case), json={"op": "remove", "view": "left", "points": [[3, 3]]})
        assert r.status_code == 422
        assert len(client.get(_url(case)).json()["corrections"]) == 1


def test_unknown_frame_is_404_everywhere(case: Case, tmp_path: Path) -> None:
    with _client(case.root, tmp_path / "db.sqlite3") as client:
        body = {"op": "remove", "view": "left", "points": [[3, 3]]}
        assert client.post("/api/frames/nope/corrections", json=body).status_code == 404
        assert client.get("/api/frames/nope/corrections").status_code == 404
        assert client.post("/api/frames/nope/corrections/undo").status_code == 404
        assert client.get("/api/frames/nope/mask.png").status_code == 404


def test_a_mask_of_the_wrong_shape_is_a_clear_error(tmp_path: Path) -> None:
    case = write_case(tmp_path / "data", SEED)
    mask = case.root / "case" / "vessel_mask.png"
    cv2.imwrite(str(mask), np.zeros((100, 300), np.uint8))
    with _client(case.root, tmp_path / "db.sqlite3") as client:
        st = client.post(_url(case, "run"), json={}).json()
        assert st["status"] == "failed" and "vessel_mask.png: the mask is 300x100 px" in st["error"]
        r = client.get(_url(case, "mask.png"))
        assert r.status_code == 409 and "mask" in r.text
        r = client.post(_url(case), json={"op": "remove", "view": "left", "points": [[3, 3]]})
        assert r.status_code == 422 and "cannot load frame" in r.text


def test_store_keeps_every_row_and_shares_the_rating_file(tmp_path: Path) -> None:
    path = tmp_path / "ratings.sqlite3"
    with RatingStore(path) as ratings:
        store = CorrectionStore(ratings)
        a = Correction("erase", "left", ((1, 2), (3, 4)), 5.0)
        b = Correction("remove", "right", ((7, 8),))
        store.add("f", a)
        store.add("f", b)
        store.undo("f")
        store.add("f", Correction("clear", "both"))  # drops the undone b from the redo stack
        with pytest.raises(Conflict, match="nothing to redo"):
            store.redo("f")
        assert store.active("f") == (a, Correction("clear", "both"))
        assert [r.state for r in store.history("f")] == ["active", "dropped", "active"]
        assert store.active("other") == ()
        ratings.add_rating("f", 4)
    # the same file opens again as a rating store, the corrections still there
    with RatingStore(path) as ratings:
        assert CorrectionStore(ratings).active("f") == (a, Correction("clear", "both"))
    tables = {r[0] for r in sqlite3.connect(path).execute("SELECT name FROM sqlite_master")}
    assert {"ratings", "corrections", "meta"} <= tables


def test_a_corrections_table_of_an_earlier_version_gains_its_columns(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite3"
    RatingStore(path).close()
    with sqlite3.connect(path) as conn:  # the first version had no stereo column
        conn.execute(
            "CREATE TABLE corrections (id INTEGER PRIMARY KEY AUTOINCREMENT, frame_id TEXT NOT"
            " NULL, op TEXT NOT NULL, view TEXT NOT NULL, points TEXT NOT NULL, radius REAL NOT"
            " NULL, state TEXT NOT NULL, created_at TEXT NOT NULL)"
        )
        conn.execute(
            "INSERT INTO corrections (frame_id, op, view, points, radius, state, created_at)"
            " VALUES ('f', 'remove', 'left', '[[3,4]]', 8.0, 'active', 'then')"
        )
    with RatingStore(path) as ratings:
        store = CorrectionStore(ratings)
        assert store.active("f") == (Correction("remove", "left", ((3, 4),)),)
        store.add("f", Correction("remove", "right", ((5, 6),), stereo=True))
        assert store.active("f")[-1].stereo


def test_a_foreign_corrections_table_stops_the_start_and_is_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / "other.sqlite3"
    RatingStore(path).close()
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE corrections (id INTEGER PRIMARY KEY, what TEXT)")
        conn.execute("INSERT INTO corrections (what) VALUES ('theirs')")
    with RatingStore(path) as ratings, pytest.raises(StoreError, match="corrections table"):
        CorrectionStore(ratings)
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT * FROM corrections").fetchall() == [
        (1, "theirs")
    ]  # no column added
