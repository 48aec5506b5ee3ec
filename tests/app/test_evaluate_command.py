"""``threadrecon evaluate`` and the page's evaluation job apply the user's stored mask
corrections, as the debugger's runs do; ``--no-corrections`` ignores them; a ``--db`` that does
not exist is a clear error; the database is never written by an evaluation."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from correction_support import Case, write_case

from threadrecon.app.cli import main
from threadrecon.app.corrections import CorrectionStore, with_corrections
from threadrecon.app.dataset import discover
from threadrecon.app.jobs import EvaluationJob
from threadrecon.app.ratings import RatingStore
from threadrecon.app.resources import default_db
from threadrecon.core.corrections import Correction
from threadrecon.core.pipeline import ReconParams

SEED = 13  # the given mask's vessel drags the curve off the thread (see test_server_corrections)


@pytest.fixture(scope="module")
def case(tmp_path_factory: pytest.TempPathFactory) -> Case:
    case = write_case(tmp_path_factory.mktemp("evaluate"), SEED)
    store = RatingStore(default_db(case.root))
    corrections = CorrectionStore(store)
    for view in ("left", "right"):
        corrections.add(case.frame_id, Correction("remove", view, (case.vessel[view],)))
    for view in ("left", "right"):
        corrections.add(case.frame_id, Correction("add", view, (case.missed[view],)))
    store.close()
    return case


def _rows(case: Case, tmp_path: Path, *extra: str) -> tuple[int, list[dict[str, str]]]:
    out = tmp_path / "rows.csv"
    code = main(["evaluate", str(case.root), "--out", str(out), *extra])
    with out.open() as fh:
        return code, list(csv.DictReader(fh))


def test_evaluate_applies_the_stored_corrections(case: Case, tmp_path: Path) -> None:
    db = default_db(case.root)
    before = db.stat().st_mtime_ns
    code, (row,) = _rows(case, tmp_path)
    assert code == 0 and row["status"] == "ok", row["error"]
    assert row["corrections"] == "4"
    assert float(row["e_length_mm"]) < 2.0 and float(row["e_S_mm"]) < 0.5
    assert db.stat().st_mtime_ns == before  # read, never written


def test_no_corrections_judges_the_given_masks(case: Case, tmp_path: Path) -> None:
    code, (row,) = _rows(case, tmp_path, "--no-corrections")
    assert row["corrections"] == "0"
    assert row["status"] != "ok"  # the vessel in the given mask drags the curve off the thread


def test_a_missing_db_is_a_clear_error(
    case: Case, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["evaluate", str(case.root), "--db", str(tmp_path / "nope.sqlite3")]) == 2
    assert "nope.sqlite3: no such database file" in capsys.readouterr().err


def test_the_page_job_applies_the_stored_corrections(case: Case) -> None:
    store = RatingStore(default_db(case.root))
    try:
        frames = with_corrections(discover(case.root), CorrectionStore(store).active)
    finally:
        store.close()
    job = EvaluationJob(frames, ReconParams(), "default").start()
    assert job.wait(120)
    (row,) = job.rows
    assert row["corrections"] == 4 and row["status"] == "ok", row["error"]


def test_a_db_that_is_not_a_database_is_a_clear_error(
    case: Case, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    junk = tmp_path / "junk.sqlite3"
    junk.write_bytes(b"not a database, just bytes" * 100)
    assert main(["evaluate", str(case.root), "--db", str(junk)]) == 2
    err = capsys.readouterr().err
    assert "junk.sqlite3" in err and "cannot be read" in err
    assert junk.read_bytes() == b"not a database, just bytes" * 100
