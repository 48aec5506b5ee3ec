"""The automatic score against a person's ratings: the confusion table and the rank
correlation, without HTTP and through the API; the evaluation rows carry the check's verdict."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
from scipy.stats import spearmanr
from test_server import FLAT, SAMPLE, url
from test_server_workflows import CONFIGS, _wait_job, client_for

from threadrecon.app.agreement import agreement, automatic_rating, automatic_score, rated_pairs
from threadrecon.app.dataset import discover
from threadrecon.app.evaluation import CHECK_COLUMNS, evaluate_frame, status_counts, summarise
from threadrecon.core.pipeline import ReconParams


def test_confusion_table_counts_each_pair_in_its_cell():
    pairs = [(5, 5), (4, 5), (4, 5), (1, 2), (3, 3), (2, 1)]
    got = agreement(pairs)
    assert got.n == 6
    table = np.array(got.confusion)
    assert table.shape == (5, 5) and table.sum() == 6
    assert table[4, 3] == 2  # rated 5, scored 4: twice
    assert table[1, 0] == 1 and table[0, 1] == 1 and table[4, 4] == 1 and table[2, 2] == 1
    auto, human = np.array(pairs).T
    assert got.spearman == pytest.approx(spearmanr(auto, human)[0])
    assert got.exact == pytest.approx(2 / 6) and got.within_one == 1.0
    assert got.mean_difference == pytest.approx(np.mean(auto - human))


def test_perfect_and_reversed_rankings_give_plus_and_minus_one():
    assert agreement([(s, s) for s in (1, 2, 3, 4, 5)]).spearman == pytest.approx(1.0)
    assert agreement([(s, 6 - s) for s in (1, 2, 3, 4, 5)]).spearman == pytest.approx(-1.0)


def test_the_rank_correlation_reads_the_continuous_score_the_table_its_classes():
    """Two frames of one class rank by their continuous score: a person who rated the worse
    one lower agrees fully, which the tied integers cannot show."""
    pairs = [(4, 5), (4, 4), (2, 2)]
    ties = agreement(pairs)
    got = agreement(pairs, [4.4, 3.6, 2.1])
    assert got.confusion == ties.confusion and got.exact == ties.exact
    assert got.spearman == pytest.approx(1.0) and ties.spearman < 0.9
    flat = agreement([(4, 1), (4, 4), (4, 5)], [4.0, 4.0, 4.0])
    assert flat.spearman is None and "automatic score is the same" in flat.spearman_note
    with pytest.raises(ValueError, match="one per pair"):
        agreement(pairs, [4.4, math.nan, 2.1])
    with pytest.raises(ValueError, match="one per pair"):
        agreement(pairs, [4.4])


def test_too_few_or_constant_pairs_give_no_correlation_and_say_why():
    few = agreement([(3, 4), (5, 5)])
    assert few.spearman is None and "at least 3" in few.spearman_note
    flat = agreement([(3, 1), (3, 4), (3, 5)])
    assert flat.spearman is None and "automatic score is the same" in flat.spearman_note
    empty = agreement([])
    assert empty.n == 0 and empty.exact is None and np.array(empty.confusion).sum() == 0


@pytest.mark.parametrize("pair", [(0, 3), (3, 6), (2.5, 3), ("4", 4), (True, 3), (3,)])
def test_a_score_outside_1_to_5_is_refused_with_its_value(pair):
    with pytest.raises(ValueError, match="pair 0"):
        agreement([pair])


def test_rows_without_a_score_are_missing_and_failed_frames_score_one():
    rows = [
        {"frame": "a", "status": "ok", "auto_score": 4},
        {"frame": "b", "status": "failed", "auto_score": math.nan},  # failed before the check
        {"frame": "c", "status": "ok"},  # an evaluation older than the score
        {"frame": "d", "status": "suspect", "auto_score": 2.0},
    ]
    assert automatic_score(rows[1]) == 1 and automatic_score(rows[2]) is None
    assert automatic_rating({"status": "ok", "auto_rating": 3.7}) == 3.7
    assert automatic_rating({"status": "failed", "auto_rating": math.nan}) == 1.0
    assert automatic_rating(rows[0]) is None  # an evaluation before the continuous score
    joined, missing = rated_pairs({"a": 5, "b": 1, "c": 3, "d": 2, "e": 4}, rows)
    assert [(j["frame"], j["auto"], j["human"]) for j in joined] == [
        ("a", 4, 5), ("b", 1, 1), ("d", 2, 2)
    ]  # fmt: skip
    assert missing == ["c", "e"]


def test_evaluation_rows_carry_status_reasons_and_score_and_the_summary_counts_them():
    frame = next(f for f in discover(SAMPLE) if f.id == FLAT)
    row, rec = evaluate_frame(frame, ReconParams())
    assert rec is not None and set(CHECK_COLUMNS) <= set(row)
    chk = rec["check"]
    assert row["check"] == chk.status and row["auto_score"] == chk.score
    assert row["auto_rating"] == chk.rating and abs(chk.rating - chk.score) <= 0.5
    assert row["reasons"] == "; ".join(chk.reasons)
    rows = [
        row,
        {"frame": "x", "kind": "simulated", "status": "suspect", "error": "r1; r2"},
        {"frame": "y", "kind": "simulated", "status": "failed", "error": "r3"},
    ]
    assert status_counts(rows) == {"ok": 1, "suspect": 1, "failed": 1}
    lines = summarise(rows)
    assert lines[0] == "simulated: 3 frames: 1 ok, 1 suspect, 1 failed"
    assert "SUSPECT x: r1; r2" in lines and "FAILED y: r3" in lines


def test_agreement_endpoint_joins_ratings_with_the_saved_scores(tmp_path):
    data = tmp_path / "data"
    shutil.copytree(SAMPLE / "simulated" / "flat", data / "simulated" / "flat")
    with client_for(data, CONFIGS) as c:
        got = c.get("/api/ratings/agreement").json()
        assert got["n"] == 0 and got["rated"] == 0 and got["evaluation"] is None
        ratings = {FLAT: 5, "simulated/flat/flat_2": 2, "simulated/flat/flat_3": 4}
        for frame, score in ratings.items():
            c.put(url(frame, "rating"), json={"score": score})
        got = c.get("/api/ratings/agreement").json()
        assert got["rated"] == 3 and got["n"] == 0 and len(got["missing"]) == 3  # no scores yet
        c.post("/api/evaluations", json={})
        _wait_job(c)
        got = c.get("/api/ratings/agreement").json()
        saved = {r["frame"]: r for r in c.get("/api/evaluations/last").json()["rows"]}
        assert got["n"] == 3 and got["missing"] == [] and got["evaluation"]["same_params"]
        pairs = [(saved[f]["auto_score"], h) for f, h in sorted(ratings.items())]
        assert [(f["auto"], f["human"]) for f in got["frames"]] == pairs
        assert got["confusion"] == agreement(pairs).to_dict()["confusion"]
        assert sum(map(sum, got["confusion"])) == 3
        continuous = [saved[f]["auto_rating"] for f in sorted(ratings)]
        assert [f["auto_rating"] for f in got["frames"]] == continuous
        assert got["spearman"] == agreement(pairs, continuous).spearman
