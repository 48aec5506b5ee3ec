"""SQLite store of the paper's 1-5 quality ratings of frames and of saved dataset evaluations.

One file holds three tables: ``meta`` (which program wrote the file, schema version),
``ratings`` (every rating ever given: re-rating a frame appends, the history is kept) and
``evaluations`` (a whole-dataset evaluation: parameters, one row per frame, summary lines).
The store refuses, on opening, any file it cannot safely use: not an SQLite database (or a
corrupt one), an SQLite database of another program, a newer schema, a read-only file or
folder, a file locked by another program. The error names the file and what to do; the file
is never deleted, truncated or overwritten. Opening writes one meta row inside a transaction,
so that a file that cannot be written fails at start, not at the first rating.
Threads: one connection (``check_same_thread=False``) guarded by a lock, in autocommit mode;
every write is one ``BEGIN IMMEDIATE`` ... ``COMMIT`` transaction, so that several stores (or
processes) on the same file wait for each other (``timeout``) instead of failing. The journal
is SQLite's default rollback journal, which needs write access to the file's folder.
Evaluation rows are stored as strict JSON: a NaN (a metric that does not apply, e.g. 3D error
of a real frame) is stored as ``null`` and read back as ``float("nan")``.
"""

from __future__ import annotations

import csv
import io
import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from threadrecon.app.errors import Unavailable
from threadrecon.app.store_rows import dumps, evaluation_from_row

APP_ID = "threadrecon-ratings"  # meta.app: tells our database from another program's
SCHEMA_VERSION = 1  # bump, with a migration in _open_schema, when a table changes
SQLITE_MAGIC = b"SQLite format 3\x00"  # the first 16 bytes of every SQLite 3 database
BUSY_TIMEOUT_S = 5.0  # wait this long for another writer before reporting the file locked
SCORE_MIN, SCORE_MAX = 1, 5  # the paper's quality scale
MAX_NOTE_CHARS = 4000  # a note is a remark on a frame, not a report
MAX_ID_CHARS = 1000  # frame ids are dataset-relative paths
ADVICE = "choose another file with --db"
CSV_COLUMNS = ("id", "frame_id", "score", "note", "created_at", "preset", "params_hash")

_TABLES = {
    "meta": "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "ratings": (
        "CREATE TABLE ratings ("
        " id INTEGER PRIMARY KEY AUTOINCREMENT,"
        " frame_id TEXT NOT NULL,"
        " score INTEGER NOT NULL CHECK (score BETWEEN 1 AND 5),"
        " note TEXT NOT NULL,"
        " created_at TEXT NOT NULL,"
        " preset TEXT NOT NULL,"
        " params_hash TEXT NOT NULL)"
    ),
    "evaluations": (
        "CREATE TABLE evaluations ("
        " id INTEGER PRIMARY KEY AUTOINCREMENT,"
        " created_at TEXT NOT NULL,"
        " preset TEXT NOT NULL,"
        " params_hash TEXT NOT NULL,"
        " n_frames INTEGER NOT NULL,"
        " params TEXT NOT NULL,"
        " rows TEXT NOT NULL,"
        " summary TEXT NOT NULL)"
    ),
}
_INDEXES = ("CREATE INDEX ratings_by_frame ON ratings (frame_id, id)",)
_RATING_SELECT = f"SELECT {', '.join(CSV_COLUMNS)} FROM ratings"
_EVAL_COLUMNS = "id, created_at, preset, params_hash, n_frames, params, rows, summary"


class StoreError(Unavailable, RuntimeError):
    """The database file cannot be used; the message names it and says what to do."""

    def __init__(self, path: Path, problem: str, advice: str = ADVICE) -> None:
        super().__init__(f"{path}: {problem}; {advice}")
        self.path = path
        self.problem = problem


@dataclass(frozen=True)
class Rating:
    """One quality rating of one frame."""

    id: int
    frame_id: str  # dataset-relative frame id (``Frame.id``)
    score: int  # quality score, 1 (unusable) .. 5 (perfect), the paper's scale
    note: str
    created_at: str  # ISO-8601 UTC time of the rating
    preset: str  # preset name in use when rating ("" if none)
    params_hash: str
    """:func:`app.presets.params_hash` of the parameters in use ("" if unknown)."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class RatingStore:
    """Ratings and evaluations in one SQLite file; see the module docstring."""

    def __init__(self, path: str | Path, timeout: float = BUSY_TIMEOUT_S) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._check_path()
        try:
            conn = sqlite3.connect(
                self.path, timeout=timeout, isolation_level=None, check_same_thread=False
            )
        except sqlite3.Error as exc:
            raise self._error(exc) from None
        self._conn: sqlite3.Connection | None = conn
        try:
            self._open_schema()
        except BaseException:
            conn.close()
            self._conn = None
            raise

    # --- opening -----------------------------------------------------------------------

    def _check_path(self) -> None:
        """Refuse, before SQLite touches it, a path it would fail on or damage."""
        path = self.path
        if path.is_dir():
            raise StoreError(path, "is a folder, not a database file", "give a file path with --db")
        if not path.parent.is_dir():
            raise StoreError(path, f"folder {path.parent} does not exist", f"create it or {ADVICE}")
        if path.exists():
            if not path.is_file():
                raise StoreError(path, "is not a regular file")
            try:
                with path.open("rb") as fh:
                    head = fh.read(len(SQLITE_MAGIC))
            except OSError as exc:
                raise StoreError(path, f"cannot be read ({exc.strerror or exc})") from None
            if head and head != SQLITE_MAGIC:  # an empty file is an empty database
                raise StoreError(
                    path,
                    "is not an SQLite database (another kind of file, or corrupt); left untouched",
                )
            if not os.access(path, os.W_OK):
                raise StoreError(path, "is read-only")
        if not os.access(path.parent, os.W_OK):
            raise StoreError(
                path, f"folder {path.parent} is read-only (SQLite writes its journal there)"
            )

    def _open_schema(self) -> None:
        """Create our tables in an empty database, or check that the tables are ours; then
        write one meta row, which proves the file writable."""
        now = _now()
        with self._write() as cur:
            tables = {
                r[0] for r in cur.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
            }
            tables.discard("sqlite_sequence")
            if not tables:
                for sql in (*_TABLES.values(), *_INDEXES):
                    cur.execute(sql)
                cur.executemany(
                    "INSERT INTO meta (key, value) VALUES (?, ?)",
                    [("app", APP_ID), ("schema_version", str(SCHEMA_VERSION)), ("created_at", now)],
                )
            else:
                self._check_ours(cur, tables)
            cur.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('opened_at', ?)", (now,))

    def _check_ours(self, cur: sqlite3.Cursor, tables: set[str]) -> None:
        listed = ", ".join(sorted(tables))
        if "meta" not in tables:
            raise StoreError(
                self.path, f"is an SQLite database of another program (tables: {listed})"
            )
        meta = dict(cur.execute("SELECT key, value FROM meta").fetchall())
        if meta.get("app") != APP_ID:
            raise StoreError(
                self.path,
                f"is an SQLite database of another program (meta app={meta.get('app')!r})",
            )
        try:
            version = int(meta.get("schema_version", ""))
        except ValueError:
            raise StoreError(
                self.path, f"has an unreadable schema version {meta.get('schema_version')!r}"
            ) from None
        if version > SCHEMA_VERSION:
            raise StoreError(
                self.path,
                f"was written by a newer threadrecon (schema {version}, this one reads "
                f"up to {SCHEMA_VERSION})",
                f"upgrade threadrecon or {ADVICE}",
            )
        missing = set(_TABLES) - tables
        if missing:
            raise StoreError(self.path, f"lacks the table(s) {', '.join(sorted(missing))}")

    # --- transactions --------------------------------------------------------------------

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Cursor]:
        """One ``BEGIN IMMEDIATE`` transaction: committed on success, rolled back otherwise."""
        with self._lock:
            conn = self._connection()
            try:
                conn.execute("BEGIN IMMEDIATE")
            except sqlite3.Error as exc:
                raise self._error(exc) from None
            try:
                yield conn.cursor()
                conn.execute("COMMIT")
            except BaseException as exc:
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                if isinstance(exc, sqlite3.Error):
                    raise self._error(exc) from None
                raise

    def _read(self, sql: str, args: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        with self._lock:
            try:
                return self._connection().execute(sql, args).fetchall()
            except sqlite3.Error as exc:
                raise self._error(exc) from None

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise StoreError(self.path, "the store is closed", "open a new RatingStore")
        return self._conn

    def _error(self, exc: sqlite3.Error) -> StoreError:
        msg = str(exc)
        low = msg.lower()
        if "readonly" in low or "read-only" in low:
            return StoreError(self.path, f"is read-only ({msg})")
        if "locked" in low or "busy" in low:
            return StoreError(
                self.path,
                f"is locked by another program ({msg})",
                f"close that program, or {ADVICE}",
            )
        if "not a database" in low or "malformed" in low or "corrupt" in low:
            return StoreError(self.path, f"is a corrupt SQLite database ({msg}); left untouched")
        if "unable to open" in low:
            return StoreError(self.path, f"cannot be opened or created ({msg})")
        return StoreError(self.path, f"database error ({msg})")

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> RatingStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- ratings -------------------------------------------------------------------------

    def add_rating(
        self,
        frame_id: str,
        score: int,
        note: str = "",
        preset: str = "",
        params_hash: str = "",
    ) -> Rating:
        """Append a rating of ``frame_id`` (earlier ratings stay in the history)."""
        _check_text("frame_id", frame_id, MAX_ID_CHARS, empty=False)
        if isinstance(score, bool) or not isinstance(score, int):
            raise ValueError(
                f"score must be a whole number from {SCORE_MIN} to {SCORE_MAX}, got {score!r}"
            )
        if not SCORE_MIN <= score <= SCORE_MAX:
            raise ValueError(f"score must be from {SCORE_MIN} to {SCORE_MAX}, got {score}")
        _check_text("note", note, MAX_NOTE_CHARS)
        _check_text("preset", preset, MAX_ID_CHARS)
        _check_text("params_hash", params_hash, MAX_ID_CHARS)
        created_at = _now()
        with self._write() as cur:
            cur.execute(
                "INSERT INTO ratings (frame_id, score, note, created_at, preset, params_hash)"
                " VALUES (?, ?, ?, ?, ?, ?)",
                (frame_id, score, note, created_at, preset, params_hash),
            )
            rid = cur.lastrowid
        assert rid is not None
        return Rating(rid, frame_id, score, note, created_at, preset, params_hash)

    def latest(self, frame_id: str) -> Rating | None:
        """The newest rating of ``frame_id``, or None when it was never rated."""
        rows = self._read(
            f"{_RATING_SELECT} WHERE frame_id = ? ORDER BY id DESC LIMIT 1", (frame_id,)
        )
        return Rating(*rows[0]) if rows else None

    def history(self, frame_id: str) -> list[Rating]:
        """Every rating of ``frame_id``, newest first."""
        rows = self._read(f"{_RATING_SELECT} WHERE frame_id = ? ORDER BY id DESC", (frame_id,))
        return [Rating(*r) for r in rows]

    def latest_all(self) -> dict[str, Rating]:
        """The newest rating of every rated frame, by frame id."""
        rows = self._read(
            f"{_RATING_SELECT} WHERE id IN (SELECT MAX(id) FROM ratings GROUP BY frame_id)"
            " ORDER BY frame_id"
        )
        return {r[1]: Rating(*r) for r in rows}

    def ratings_csv(self, include_history: bool = True) -> str:
        """CSV of the ratings (header ``CSV_COLUMNS``), by frame id then oldest first; only
        each frame's newest rating when ``include_history`` is False."""
        if include_history:
            rows = self._read(f"{_RATING_SELECT} ORDER BY frame_id, id")
        else:
            rows = [_astuple(r) for r in self.latest_all().values()]
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(CSV_COLUMNS)
        writer.writerows(rows)
        return buf.getvalue()

    # --- evaluations ---------------------------------------------------------------------

    def save_evaluation(
        self,
        preset: str,
        params_hash: str,
        params: dict[str, Any],
        rows: list[dict[str, Any]],
        summary: list[str],
    ) -> int:
        """Store a whole-dataset evaluation; returns its id."""
        _check_text("preset", preset, MAX_ID_CHARS)
        _check_text("params_hash", params_hash, MAX_ID_CHARS)
        if not isinstance(params, dict):
            raise ValueError(f"params must be a dict, got {type(params).__name__}")
        if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
            raise ValueError("rows must be a list of dicts (one per frame)")
        if not isinstance(summary, list) or not all(isinstance(s, str) for s in summary):
            raise ValueError("summary must be a list of str")
        blobs = (dumps("params", params), dumps("rows", rows), dumps("summary", summary))
        with self._write() as cur:
            cur.execute(
                "INSERT INTO evaluations"
                " (created_at, preset, params_hash, n_frames, params, rows, summary)"
                " VALUES (?, ?, ?, ?, ?, ?, ?)",
                (_now(), preset, params_hash, len(rows), *blobs),
            )
            eid = cur.lastrowid
        assert eid is not None
        return eid

    def last_evaluation(
        self, preset: str | None = None, params_hash: str | None = None
    ) -> dict[str, Any] | None:
        """The newest evaluation (of ``preset`` / ``params_hash`` when given), or None."""
        where = [
            (c, v) for c, v in (("preset", preset), ("params_hash", params_hash)) if v is not None
        ]
        sql = " AND ".join(f"{c} = ?" for c, _ in where)
        rows = self._read(
            f"SELECT {_EVAL_COLUMNS} FROM evaluations {'WHERE ' + sql if sql else ''}"
            " ORDER BY id DESC LIMIT 1",
            tuple(v for _, v in where),
        )
        return evaluation_from_row(rows[0]) if rows else None

    def evaluation(self, eid: int) -> dict[str, Any] | None:
        """The evaluation with id ``eid``, or None."""
        rows = self._read(f"SELECT {_EVAL_COLUMNS} FROM evaluations WHERE id = ?", (eid,))
        return evaluation_from_row(rows[0]) if rows else None

    def evaluations(self) -> list[dict[str, Any]]:
        """Id, created_at, preset, params_hash and n_frames of every evaluation, newest first."""
        keys = ("id", "created_at", "preset", "params_hash", "n_frames")
        rows = self._read(f"SELECT {', '.join(keys)} FROM evaluations ORDER BY id DESC")
        return [dict(zip(keys, r, strict=True)) for r in rows]


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="microseconds")


def _astuple(r: Rating) -> tuple[Any, ...]:
    return tuple(getattr(r, c) for c in CSV_COLUMNS)


def _check_text(name: str, value: object, max_chars: int, empty: bool = True) -> None:
    if not isinstance(value, str):
        raise ValueError(f"{name} must be a str, got {type(value).__name__}")
    if len(value) > max_chars:
        raise ValueError(f"{name} is {len(value)} characters long, at most {max_chars} allowed")
    if not empty and not value:
        raise ValueError(f"{name} must not be empty")
