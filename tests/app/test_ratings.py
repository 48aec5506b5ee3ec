"""The ratings store: round trips, history, CSV, validation, threads, and refusing bad files."""

from __future__ import annotations

import csv
import io
import math
import os
import sqlite3
import threading
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from threadrecon.app.ratings import CSV_COLUMNS, MAX_NOTE_CHARS, Rating, RatingStore, StoreError

NASTY_NOTE = 'thread frays, "badly", near the tip\nsecond line\r\nthird; 50% ok, = sum(1)'


@pytest.fixture
def store(tmp_path: Path) -> Iterator[RatingStore]:
    s = RatingStore(tmp_path / "ratings.db")
    yield s
    s.close()


def _same(a: object, b: object) -> bool:
    """Deep equality where NaN equals NaN."""
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def test_rating_round_trips_and_survives_reopening(tmp_path: Path) -> None:
    path = tmp_path / "r.db"
    with RatingStore(path) as s:
        r = s.add_rating("simulated/flat/flat_1", 4, "good", preset="default", params_hash="abc")
        assert isinstance(r, Rating) and r.score == 4 and r.id >= 1
        assert s.latest("simulated/flat/flat_1") == r
    with RatingStore(path) as s:
        assert s.latest("simulated/flat/flat_1") == r
        assert s.latest("simulated/flat/flat_2") is None
    d = r.to_dict()
    assert set(d) == set(CSV_COLUMNS) and d["note"] == "good" and d["preset"] == "default"
    assert datetime.fromisoformat(r.created_at).utcoffset().total_seconds() == 0


def test_rerating_appends_history_newest_first(store: RatingStore) -> None:
    a1 = store.add_rating("a", 2)
    b1 = store.add_rating("b", 5, "fine")
    a2 = store.add_rating("a", 3, "better after tuning")
    a3 = store.add_rating("a", 1)
    assert store.history("a") == [a3, a2, a1]
    assert store.history("b") == [b1]
    assert store.history("never") == []
    assert store.latest("a") == a3
    assert store.latest_all() == {"a": a3, "b": b1}


def test_csv_rows_match_the_stored_ratings(store: RatingStore) -> None:
    store.add_rating("x/1", 3, NASTY_NOTE, "p", "h1")
    store.add_rating("x/0", 5, "", "q", "h2")
    store.add_rating("x/1", 4, "ok, now")
    rows = list(csv.reader(io.StringIO(store.ratings_csv())))
    assert tuple(rows[0]) == CSV_COLUMNS
    stored = store.history("x/0")[::-1] + store.history("x/1")[::-1]
    assert rows[1:] == [[str(getattr(r, c)) for c in CSV_COLUMNS] for r in stored]
    assert rows[2][3] == NASTY_NOTE

    latest = list(csv.reader(io.StringIO(store.ratings_csv(include_history=False))))
    assert [r[1:3] for r in latest[1:]] == [["x/0", "5"], ["x/1", "4"]]


@pytest.mark.parametrize("score", [0, 6, -1, "x", "3", 3.5, 3.0, True, None])
def test_invalid_score_raises_and_stores_nothing(store: RatingStore, score: object) -> None:
    with pytest.raises(ValueError, match="score"):
        store.add_rating("f", score)  # type: ignore[arg-type]
    assert store.history("f") == []
    assert store.ratings_csv().strip() == ",".join(CSV_COLUMNS)


def test_invalid_note_or_frame_raises_and_stores_nothing(store: RatingStore) -> None:
    with pytest.raises(ValueError, match="note"):
        store.add_rating("f", 3, "n" * (MAX_NOTE_CHARS + 1))
    with pytest.raises(ValueError, match="note"):
        store.add_rating("f", 3, 42)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="frame_id"):
        store.add_rating("", 3)
    assert store.latest_all() == {}
    assert store.add_rating("f", 3, "n" * MAX_NOTE_CHARS).note == "n" * MAX_NOTE_CHARS


def test_two_threads_rating_concurrently_keep_every_rating(store: RatingStore) -> None:
    n = 50

    def work(t: int) -> None:
        for i in range(n):
            store.add_rating(f"frame{i % 5}", 1 + (i + t) % 5, f"t{t} i{i}")

    threads = [threading.Thread(target=work, args=(t,)) for t in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    rows = list(csv.reader(io.StringIO(store.ratings_csv())))[1:]
    assert len(rows) == 2 * n
    assert sorted(r[3] for r in rows) == sorted(f"t{t} i{i}" for t in range(2) for i in range(n))
    assert len({r[0] for r in rows}) == 2 * n


def test_two_stores_on_one_file_writing_concurrently_keep_every_rating(tmp_path: Path) -> None:
    path = tmp_path / "shared.db"
    n = 50
    stores = [RatingStore(path), RatingStore(path)]
    errors: list[BaseException] = []

    def work(t: int) -> None:
        try:
            for i in range(n):
                stores[t].add_rating(f"s{t}", 1 + i % 5, str(i))
        except BaseException as exc:  # surfaced by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(t,)) for t in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert errors == []
    for s in stores:
        assert [len(s.history(f"s{t}")) for t in range(2)] == [n, n]
        s.close()


def test_corrupt_file_is_refused_and_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / "noise.db"
    data = np.random.default_rng(0).bytes(8192)
    path.write_bytes(data)
    with pytest.raises(StoreError, match="not an SQLite database") as info:
        RatingStore(path)
    assert str(path) in str(info.value) and "--db" in str(info.value)
    assert path.read_bytes() == data
    assert sorted(p.name for p in tmp_path.iterdir()) == ["noise.db"]


def test_damaged_sqlite_file_is_refused_and_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / "damaged.db"
    data = b"SQLite format 3\x00" + np.random.default_rng(1).bytes(4096)
    path.write_bytes(data)
    with pytest.raises(StoreError, match="corrupt") as info:
        RatingStore(path)
    assert str(path) in str(info.value)
    assert path.read_bytes() == data


def test_database_of_another_program_is_refused_and_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / "other.db"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE customers (name TEXT)")
        conn.execute("INSERT INTO customers VALUES ('ada')")
    conn.close()
    data = path.read_bytes()
    with pytest.raises(StoreError, match="another program.*customers"):
        RatingStore(path)
    assert path.read_bytes() == data


def test_meta_table_of_another_program_or_newer_schema_is_refused(tmp_path: Path) -> None:
    other = tmp_path / "other.db"
    with sqlite3.connect(other) as conn:
        conn.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        conn.execute("INSERT INTO meta VALUES ('app', 'somethingelse')")
    conn.close()
    with pytest.raises(StoreError, match="another program"):
        RatingStore(other)

    newer = tmp_path / "newer.db"
    RatingStore(newer).close()
    with sqlite3.connect(newer) as conn:
        conn.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    conn.close()
    with pytest.raises(StoreError, match="newer"):
        RatingStore(newer)


def test_folder_or_missing_folder_is_refused(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match="is a folder"):
        RatingStore(tmp_path)
    missing = tmp_path / "nope" / "r.db"
    with pytest.raises(StoreError, match="does not exist"):
        RatingStore(missing)
    assert not missing.parent.exists()


def test_file_locked_by_another_program_fails_on_opening(tmp_path: Path) -> None:
    path = tmp_path / "r.db"
    RatingStore(path).close()
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")
    try:
        with pytest.raises(StoreError, match="locked"):
            RatingStore(path, timeout=0.05)
    finally:
        other.execute("ROLLBACK")
        other.close()
    RatingStore(path).close()


def test_read_only_file_fails_on_opening_and_is_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / "r.db"
    with RatingStore(path) as s:
        s.add_rating("f", 2)
    data = path.read_bytes()
    path.chmod(0o444)
    try:
        try:
            with path.open("ab"):
                pass
        except PermissionError:
            pass
        else:
            pytest.skip(f"chmod 444 does not stop writes here (euid {os.geteuid()}, e.g. root)")
        with pytest.raises(StoreError, match="read-only") as info:
            RatingStore(path)
        assert str(path) in str(info.value)
        assert path.read_bytes() == data
    finally:
        path.chmod(0o644)


def test_closed_store_raises_store_error(tmp_path: Path) -> None:
    s = RatingStore(tmp_path / "r.db")
    s.close()
    with pytest.raises(StoreError, match="closed"):
        s.latest("f")


def test_evaluation_round_trips_with_nan(tmp_path: Path) -> None:
    path = tmp_path / "r.db"
    params = {"spline": {"n_ctrl": 15, "degree": 4}, "segment": {"background": None}}
    rows = [
        {"frame": "a", "kind": "simulated", "status": "ok", "e_S_mm": 0.25, "n_keypoints": 12},
        {"frame": "b", "kind": "real", "status": "failed", "e_S_mm": math.nan, "n_keypoints": 0},
        {"frame": "c", "kind": "real", "status": "ok", "e_S_mm": np.float64("nan"), "n": 3},
    ]
    summary = ["simulated: 1 frames, 0 failed", "FAILED b: stereo: empty"]
    with RatingStore(path) as s:
        e1 = s.save_evaluation("default", "h1", params, rows, summary)
        e2 = s.save_evaluation("tuned", "h2", params, rows[:1], [])
    with RatingStore(path) as s:
        got = s.evaluation(e1)
        assert got is not None
        assert _same(got["rows"], rows)
        assert got["params"] == params and got["summary"] == summary
        assert (got["id"], got["preset"], got["params_hash"]) == (e1, "default", "h1")
        assert s.last_evaluation()["id"] == e2
        assert s.last_evaluation("default")["id"] == e1
        assert s.last_evaluation("nobody") is None
        assert s.evaluation(e2 + 100) is None
        listing = s.evaluations()
        assert [(e["id"], e["preset"], e["n_frames"]) for e in listing] == [
            (e2, "tuned", 1),
            (e1, "default", 3),
        ]
        assert set(listing[0]) == {"id", "created_at", "preset", "params_hash", "n_frames"}


def test_evaluation_that_is_not_json_is_refused_and_not_stored(store: RatingStore) -> None:
    with pytest.raises(ValueError, match="rows"):
        store.save_evaluation("p", "h", {}, [{"frame": object()}], [])
    with pytest.raises(ValueError, match="summary"):
        store.save_evaluation("p", "h", {}, [], [1])  # type: ignore[list-item]
    assert store.evaluations() == []
