"""The user's mask corrections per frame, stored in the rating store's SQLite file.

One table, ``corrections``, beside ``ratings`` and ``evaluations`` in the file of
:class:`app.ratings.RatingStore` (created on first use; a file written by an older threadrecon
gains it, and older versions ignore it). Every correction ever made is a row: ``state`` is
``active`` (applied, in ``id`` order), ``undone`` (the redo stack) or ``dropped`` (undone, then
superseded by a new correction: kept as history, never applied). Undo marks the newest active
row undone; redo re-activates the oldest undone one; a new correction drops the undone rows,
as in any editor. "Clear" is a correction too (:class:`core.corrections.Correction` "clear"),
so that it can be undone: no row is ever deleted.

Every write is one transaction of the rating store's connection (its lock and its
``BEGIN IMMEDIATE``), so that corrections and ratings never interleave half-written.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from threadrecon.app.dataset import Frame
from threadrecon.app.errors import Conflict, Invalid
from threadrecon.app.ratings import MAX_ID_CHARS, RatingStore, StoreError
from threadrecon.core.corrections import Correction

_TABLE = (
    "CREATE TABLE IF NOT EXISTS corrections ("
    " id INTEGER PRIMARY KEY AUTOINCREMENT,"
    " frame_id TEXT NOT NULL,"
    " op TEXT NOT NULL,"
    " view TEXT NOT NULL,"
    " points TEXT NOT NULL,"
    " radius REAL NOT NULL,"
    " stereo INTEGER NOT NULL DEFAULT 0,"
    " state TEXT NOT NULL CHECK (state IN ('active', 'undone', 'dropped')),"
    " created_at TEXT NOT NULL)"
)
_INDEX = "CREATE INDEX IF NOT EXISTS corrections_by_frame ON corrections (frame_id, state, id)"
_COLUMNS = "id, op, view, points, radius, stereo, state, created_at"
_ADDED_COLUMNS = {"stereo": "INTEGER NOT NULL DEFAULT 0"}  # since the table's first version


@dataclass(frozen=True)
class StoredCorrection:
    """One stored correction: its row id, the correction and when it was made."""

    id: int
    correction: Correction
    state: str
    created_at: str

    def to_dict(self) -> dict[str, Any]:
        c = self.correction
        return {
            "id": self.id,
            "op": c.op,
            "view": c.view,
            "points": [list(p) for p in c.points],
            "radius": c.radius,
            "stereo": c.stereo,
            "state": self.state,
            "created_at": self.created_at,
        }


class CorrectionStore:
    """Corrections per frame in the rating store's database file (see the module docstring)."""

    def __init__(self, store: RatingStore) -> None:
        self.store = store
        with store._write() as cur:
            cur.execute(_TABLE)
            columns = {r[1] for r in cur.execute("PRAGMA table_info(corrections)")}
            for name, sql in _ADDED_COLUMNS.items():  # a table of an earlier version
                if name not in columns:
                    cur.execute(f"ALTER TABLE corrections ADD COLUMN {name} {sql}")
                    columns.add(name)
            missing = set(_COLUMNS.split(", ")) - columns
            if missing:
                raise StoreError(
                    store.path,
                    f"has a corrections table without the column(s) {', '.join(sorted(missing))}",
                )
            cur.execute(_INDEX)

    def active(self, frame_id: str) -> tuple[Correction, ...]:
        """The corrections applied to ``frame_id``, oldest first (what a run uses)."""
        return tuple(s.correction for s in self._rows(frame_id, "state = 'active'"))

    def history(self, frame_id: str) -> list[StoredCorrection]:
        """Every correction of ``frame_id`` ever made, oldest first."""
        return self._rows(frame_id)

    def summary(self, frame_id: str) -> dict[str, Any]:
        """What the page shows: the active corrections, and whether undo and redo can act."""
        rows = self._rows(frame_id, "state IN ('active', 'undone')")
        active = [r.to_dict() for r in rows if r.state == "active"]
        return {
            "frame_id": frame_id,
            "corrections": active,
            "can_undo": bool(active),
            "can_redo": any(r.state == "undone" for r in rows),
        }

    def add(self, frame_id: str, correction: Correction) -> StoredCorrection:
        """Append ``correction`` to the frame's list (the redo stack is dropped)."""
        _check_frame_id(frame_id)
        if not isinstance(correction, Correction):
            raise Invalid(f"not a correction: {type(correction).__name__}")
        now = _now()
        points = json.dumps([list(p) for p in correction.points], separators=(",", ":"))
        with self.store._write() as cur:
            cur.execute(
                "UPDATE corrections SET state = 'dropped' WHERE frame_id = ? AND state = 'undone'",
                (frame_id,),
            )
            cur.execute(
                "INSERT INTO corrections"
                " (frame_id, op, view, points, radius, stereo, state, created_at)"
                " VALUES (?, ?, ?, ?, ?, ?, 'active', ?)",
                (
                    frame_id,
                    correction.op,
                    correction.view,
                    points,
                    float(correction.radius),
                    int(correction.stereo),
                    now,
                ),  # fmt: skip
            )
            rid = cur.lastrowid
        assert rid is not None
        return StoredCorrection(rid, correction, "active", now)

    def undo(self, frame_id: str) -> StoredCorrection:
        """Undo the newest active correction; :class:`Conflict` when there is none."""
        return self._move(frame_id, "active", "undone", "DESC", "nothing to undo")

    def redo(self, frame_id: str) -> StoredCorrection:
        """Re-apply the correction undone last; :class:`Conflict` when there is none."""
        return self._move(frame_id, "undone", "active", "ASC", "nothing to redo")

    def _move(self, frame_id: str, old: str, new: str, order: str, none: str) -> StoredCorrection:
        with self.store._write() as cur:
            # the newest active row (undo) or the oldest undone row (redo: the last undone)
            row = cur.execute(
                f"SELECT {_COLUMNS} FROM corrections WHERE frame_id = ? AND state = ?"
                f" ORDER BY id {order} LIMIT 1",
                (frame_id, old),
            ).fetchone()
            if row is None:
                raise Conflict(f"{none} on frame {frame_id}")
            cur.execute("UPDATE corrections SET state = ? WHERE id = ?", (new, row[0]))
        stored = _from_row(row)
        return StoredCorrection(stored.id, stored.correction, new, stored.created_at)

    def _rows(self, frame_id: str, where: str = "1") -> list[StoredCorrection]:
        rows = self.store._read(
            f"SELECT {_COLUMNS} FROM corrections WHERE frame_id = ? AND {where} ORDER BY id",
            (frame_id,),
        )
        return [_from_row(r) for r in rows]


def _from_row(r: tuple[Any, ...]) -> StoredCorrection:
    rid, op, view, points, radius, stereo, state, created_at = r
    try:
        pts = tuple((int(x), int(y)) for x, y in json.loads(points))
        c = Correction(op, view, pts, radius, bool(stereo))
    except (ValueError, TypeError) as exc:  # a row edited by hand: name it, never skip it
        raise Invalid(f"stored correction {rid} is unreadable: {exc}") from None
    return StoredCorrection(rid, c, state, created_at)


def _check_frame_id(frame_id: object) -> None:
    if not isinstance(frame_id, str) or not frame_id or len(frame_id) > MAX_ID_CHARS:
        raise Invalid(f"frame id must be 1 to {MAX_ID_CHARS} characters")


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="microseconds")


def with_corrections(
    frames: Iterable[Frame], active: Callable[[str], tuple[Correction, ...]]
) -> list[Frame]:
    """``frames``, each carrying its active corrections (``active(frame_id)``, e.g.
    :meth:`CorrectionStore.active`): an evaluation then judges the masks the user made, as the
    debugger's runs do."""
    return [replace(f, corrections=active(f.id)) for f in frames]


def read_active(path: Path) -> dict[str, tuple[Correction, ...]]:
    """Every frame's active corrections in the database file ``path``, opened read-only (an
    evaluation never writes the user's file); none when it has no corrections table."""
    try:
        conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise StoreError(path, f"cannot be opened: {exc}") from None
    try:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if "corrections" not in tables:
            return {}
        rows = conn.execute(
            f"SELECT frame_id, {_COLUMNS} FROM corrections WHERE state = 'active' ORDER BY id"
        ).fetchall()
    except sqlite3.Error as exc:
        raise StoreError(path, f"cannot be read: {exc}") from None
    finally:
        conn.close()
    out: dict[str, list[Correction]] = {}
    for frame_id, *row in rows:
        out.setdefault(frame_id, []).append(_from_row(tuple(row)).correction)
    return {k: tuple(v) for k, v in out.items()}
