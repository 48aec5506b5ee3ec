"""Agreement of the automatic quality score with a person's ratings (issue 11).

The check stage scores every frame on the paper's 1-5 scale (``CheckResult.score``, stored in
each evaluation row as ``auto_score``); where a person has rated frames (the ratings store),
this module puts the two side by side: a 5x5 confusion table (rows: the person's rating,
columns: the automatic score), the Spearman rank correlation, and the shares of exact and
within-one agreement, so a lab can calibrate the score to its own ratings. The table compares
integers (the score's class, ``auto_score``); the rank correlation reads the continuous score
(``auto_rating``) where the evaluation stored it, so frames of one class still rank by their
expected error.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import spearmanr

SCORES = (1, 2, 3, 4, 5)  # the paper's rating scale
MIN_PAIRS_RHO = 3  # a rank correlation of fewer pairs says nothing


@dataclass(frozen=True)
class Agreement:
    """``confusion[h - 1][a - 1]``: frames the person rated h and the check scored a.
    ``spearman``: rank correlation of the pairs (None with fewer than MIN_PAIRS_RHO pairs or
    when either side is constant; ``spearman_note`` says why). ``exact``, ``within_one``:
    shares of pairs with a == h and |a - h| <= 1; ``mean_difference``: mean of a - h."""

    n: int
    confusion: tuple[tuple[int, ...], ...]
    spearman: float | None
    spearman_note: str
    exact: float | None
    within_one: float | None
    mean_difference: float | None

    def to_dict(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "scores": list(SCORES),
            "confusion": [list(r) for r in self.confusion],
            "spearman": self.spearman,
            "spearman_note": self.spearman_note,
            "exact": self.exact,
            "within_one": self.within_one,
            "mean_difference": self.mean_difference,
        }


def agreement(
    pairs: Iterable[tuple[int, int]], ratings: Iterable[float] | None = None
) -> Agreement:
    """The agreement of ``(automatic, human)`` score pairs, each an integer 1-5. ``ratings``:
    the continuous automatic score of each pair (1-5), ranked in the Spearman correlation
    instead of the integer classes when given.

    Raises ValueError naming the first pair that is not two integers in 1..5, or when
    ``ratings`` does not give one finite value per pair."""
    a_list, h_list = [], []
    for i, pair in enumerate(pairs):
        try:
            a, h = pair
        except (TypeError, ValueError):
            raise ValueError(f"pair {i} must be (automatic, human), got {pair!r}") from None
        for name, v in (("automatic", a), ("human", h)):
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v not in SCORES:
                raise ValueError(f"pair {i}: the {name} score must be an integer 1-5, got {v!r}")
        a_list.append(int(a))
        h_list.append(int(h))
    auto, human = np.array(a_list, dtype=int), np.array(h_list, dtype=int)
    n = len(auto)
    ranked = auto.astype(float)
    if ratings is not None:
        ranked = np.array(list(ratings), dtype=float)
        if ranked.shape != (n,) or not np.all(np.isfinite(ranked)):
            raise ValueError(f"ratings must be {n} finite values, one per pair, got {ranked}")
    confusion = np.zeros((5, 5), dtype=int)
    np.add.at(confusion, (human - 1, auto - 1), 1)
    rho, note = None, ""
    if n < MIN_PAIRS_RHO:
        note = f"needs at least {MIN_PAIRS_RHO} rated frames with a score, got {n}"
    elif len(set(ranked.tolist())) == 1 or len(set(h_list)) == 1:
        side = "automatic score" if len(set(ranked.tolist())) == 1 else "rating"
        note = f"every {side} is the same: no ranking to compare"
    else:
        rho = float(spearmanr(ranked, human)[0])
    diff = auto - human
    return Agreement(
        n=n,
        confusion=tuple(tuple(int(v) for v in row) for row in confusion),
        spearman=rho,
        spearman_note=note,
        exact=float(np.mean(diff == 0)) if n else None,
        within_one=float(np.mean(np.abs(diff) <= 1)) if n else None,
        mean_difference=float(np.mean(diff)) if n else None,
    )


def _automatic(row: Mapping[str, Any], key: str) -> float | None:
    """An evaluation row's finite number under ``key``; 1 for a frame that failed before the
    check could score it (the check's score of a failed curve); None when the row has none."""
    v = row.get(key)
    if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    if row.get("status") == "failed" and key in row:
        return 1.0
    return None


def automatic_score(row: Mapping[str, Any]) -> int | None:
    """The automatic score of an evaluation row: its ``auto_score``; a frame that failed
    before the check could score it (no score, status failed) scores 1, the check's score of
    a failed curve; None when the row has no score (an evaluation older than the score)."""
    v = _automatic(row, "auto_score")
    return None if v is None else int(v)


def automatic_rating(row: Mapping[str, Any]) -> float | None:
    """The continuous automatic score of an evaluation row: its ``auto_rating``; 1.0 for a
    frame that failed before the check (as its score); None when the row has none (an
    evaluation older than the continuous score)."""
    return _automatic(row, "auto_rating")


def rated_pairs(
    ratings: Mapping[str, int], rows: Iterable[Mapping[str, Any]]
) -> tuple[list[dict[str, Any]], list[str]]:
    """Join the latest rating per frame (``frame id -> score``) with the evaluation rows.

    Returns the joined frames (``frame``, ``human``, ``auto``, ``auto_rating`` (None when the
    row has no continuous score), ``status``) in frame order and
    the rated frames that have no automatic score in ``rows`` (not evaluated, or evaluated
    before the score existed)."""
    by_frame = {r.get("frame"): r for r in rows}
    joined, missing = [], []
    for frame_id in sorted(ratings):
        row = by_frame.get(frame_id)
        auto = automatic_score(row) if row is not None else None
        if auto is None:
            missing.append(frame_id)
            continue
        joined.append(
            {"frame": frame_id, "human": int(ratings[frame_id]), "auto": auto,
             "auto_rating": automatic_rating(row) if row is not None else None,
             "status": row.get("status") if row is not None else None}
        )  # fmt: skip
    return joined, missing
