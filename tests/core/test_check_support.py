"""The reliable matches under the curve (core/check_support.py): contradicted depth, contested
matches."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from threadrecon.core.check_support import contested, contradicted, reliable_rows, uncontested


def _matches(xy: list[tuple[int, int]], disp: list[float]):
    stereo = SimpleNamespace(
        pixels=np.array(xy, dtype=np.int64), disparity=np.array(disp, dtype=np.float64)
    )
    rel = SimpleNamespace(reliable=np.ones(len(xy), dtype=bool))
    return stereo, rel


def test_a_point_is_contradicted_only_when_every_match_under_it_disagrees() -> None:
    # Two strands crossing at (10, 10): one at disparity 30, one at 20.
    stereo, rel = _matches([(10, 10), (11, 10), (30, 30)], [30.0, 20.0, 25.0])
    uv = np.array([[10.0, 10.0], [10.2, 9.6], [10.0, 10.0], [50.0, 50.0], [31.4, 30.0]])
    d = np.array([30.4, 24.0, 19.5, 30.0, 10.0])
    got = contradicted(stereo, rel, uv, d, 1, 1.0)
    # 0: agrees with the strand at 30; 1: both matches differ by >= 4 px; 2: agrees with 20;
    # 3: no match near (unsupported, not contradicted); 4: the match 1 px away disagrees
    assert got.tolist() == [False, True, False, False, True]
    assert not contradicted(stereo, rel, uv, d, 0, 1.0)[4]  # the window is 1 px wide


def test_contradicted_handles_no_reliable_match_and_bad_points() -> None:
    stereo, rel = _matches([(5, 5)], [10.0])
    rel.reliable[:] = False
    uv = np.array([[5.0, 5.0], [np.nan, 1.0]])
    assert not contradicted(stereo, rel, uv, np.array([3.0, 3.0]), 1, 1.0).any()
    stereo, rel = _matches([(5, 5)], [10.0])
    assert not contradicted(stereo, rel, uv, np.array([3.0, 3.0]), 1, 1.0)[1]  # NaN point
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        contradicted(stereo, rel, np.zeros((3, 3)), np.zeros(3), 1, 1.0)


def _image(stereo, rel):  # noqa: ANN001, ANN202
    """The reliable pixels' disparities (float32) on their bounding box, NaN elsewhere."""
    sel = np.flatnonzero(rel.reliable)
    if sel.size == 0:
        return 0, 0, np.zeros((0, 0))
    xy = np.asarray(stereo.pixels)[sel].astype(np.int64)
    x0, y0 = int(xy[:, 0].min()), int(xy[:, 1].min())
    shape = (int(xy[:, 1].max()) - y0 + 1, int(xy[:, 0].max()) - x0 + 1)
    img = np.full(shape, np.nan, dtype=np.float32)
    img[xy[:, 1] - y0, xy[:, 0] - x0] = np.asarray(stereo.disparity, dtype=np.float32)[sel]
    return x0, y0, img


def _contradicted_numpy(stereo, rel, uv, disp, near, tol):  # noqa: ANN001, ANN202
    """contradicted as numpy ran it before the kernels: (N, K, K) windows gathered at once
    from an image of the reliable disparities."""
    x0, y0, img = _image(stereo, rel)
    n = len(uv)
    if img.size == 0 or n == 0:
        return np.zeros(n, dtype=bool)
    h, w = img.shape
    ok = np.all(np.isfinite(uv), axis=1) & np.isfinite(disp)
    q = np.rint(np.where(ok[:, None], uv, -1e6)).astype(np.int64) - [x0, y0]
    k = np.arange(-near, near + 1)
    xs = q[:, 0, None, None] + k[None, None, :]
    ys = q[:, 1, None, None] + k[None, :, None]
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    d = img[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]
    d = np.where(inside, d, np.nan).reshape(n, -1)
    seen = np.isfinite(d).any(axis=1)
    with np.errstate(invalid="ignore"):
        agrees = (np.abs(d - disp[:, None]) <= tol).any(axis=1)
    return ok & seen & ~agrees


def test_compiled_windows_equal_the_numpy_windows() -> None:
    """The compiled window test against the (N, K, K) numpy gather it replaced: random
    reliable pixels and disparities, points inside, at and beyond the box, NaN points and
    disparities, windows 0-3 px."""
    rng = np.random.default_rng(2)
    for _ in range(40):
        m = int(rng.integers(1, 300))
        flat = rng.choice(60 * 50, size=m, replace=False)  # P_L's pixels are distinct
        xy = np.column_stack([20 + flat % 60, 10 + flat // 60])
        stereo, rel = _matches([tuple(p) for p in xy], list(rng.uniform(5.0, 40.0, m)))
        stereo.disparity[rng.random(m) < 0.05] = np.nan  # a match without a disparity
        rel.reliable[:] = rng.random(m) < 0.8
        n = int(rng.integers(0, 200))
        uv = rng.uniform(0.0, 100.0, (n, 2))
        disp = rng.uniform(5.0, 40.0, n)
        if n > 4:
            uv[0, 1], disp[1] = np.nan, np.nan
        for near in range(4):
            tol = float(rng.uniform(0.2, 5.0))
            want = _contradicted_numpy(stereo, rel, uv, disp, near, tol)
            assert np.array_equal(contradicted(stereo, rel, uv, disp, near, tol), want)


def _rows(runs: list[tuple[int, int, int]], shape=(20, 80)) -> np.ndarray:
    """P_R with the row runs (y, x0, x1) set, x1 inclusive."""
    P = np.zeros(shape, dtype=bool)
    for y, x0, x1 in runs:
        P[y, x0 : x1 + 1] = True
    return P


def test_two_left_strands_matched_into_one_right_strand_are_contested() -> None:
    # Row 10: the thread at left 20-22 (disparity 10, right 10-12) and a distractor's piece at
    # left 27 matched into the same 3 px right run at disparity 16 (right 11): one right strand
    # cannot show both. The pixels farther than its width + 2 px from the piece are contested.
    stereo, rel = _matches([(20, 10), (21, 10), (22, 10), (27, 10)], [10.0, 10.0, 10.0, 16.0])
    P_R = _rows([(10, 10, 12)])
    assert contested(stereo, rel, P_R, 2.0).tolist() == [True, True, False, True]
    alone = SimpleNamespace(reliable=np.array([True, True, True, False]))
    assert not contested(stereo, alone, P_R, 2.0).any()  # the piece not reliable: no contest


def test_one_strand_and_two_strands_seen_apart_are_not_contested() -> None:
    # a strand along the row (left 20-49 at disparity 10 to 12: right 10-37, one 28 px run) and
    # two strands side by side in both views (left 20-22 and 40-42 at disparity 10)
    xs = list(range(20, 50))
    stereo, rel = _matches([(x, 5) for x in xs], list(np.linspace(10.0, 12.0, len(xs))))
    assert not contested(stereo, rel, _rows([(5, 10, 37)]), 2.0).any()
    stereo, rel = _matches([(20, 5), (21, 5), (22, 5), (40, 5), (41, 5), (42, 5)], [10.0] * 6)
    assert not contested(stereo, rel, _rows([(5, 10, 12), (5, 30, 32)]), 2.0).any()
    # the same left strands over an empty right row, or no reliable match: nothing contested
    assert not contested(stereo, rel, _rows([]), 2.0).any()
    rel.reliable[:] = False
    assert not contested(stereo, rel, _rows([(5, 10, 12), (5, 30, 32)]), 2.0).any()


def _contested_by_rows(stereo, rel, P_R: np.ndarray, slack: float) -> np.ndarray:
    """contested(), one match and one row at a time: the run of P_R's row holding the match's
    right position x - d (else a pixel next to it), and the farthest other match of that run."""
    H, W = P_R.shape
    runs = {}  # (y, x) of a run's pixel -> (run key, width)
    for y in range(H):
        x = 0
        while x < W:
            if P_R[y, x]:
                x1 = x
                while x1 + 1 < W and P_R[y, x1 + 1]:
                    x1 += 1
                for xx in range(x, x1 + 1):
                    runs[y, xx] = ((y, x), x1 - x + 1)
                x = x1 + 1
            else:
                x += 1
    member = {}
    for i in np.flatnonzero(rel.reliable):
        x, y = (int(v) for v in stereo.pixels[i])
        xr = float(np.rint(x - stereo.disparity[i]))
        if not np.isfinite(xr) or not 0 <= y < H:
            continue
        for o in (0, -1, 1):
            if (y, int(xr) + o) in runs:
                member[i] = runs[y, int(xr) + o]
                break
    out = np.zeros(len(stereo.pixels), dtype=bool)
    for i, (key, width) in member.items():
        xs = [int(stereo.pixels[j, 0]) for j, (k, _) in member.items() if k == key]
        out[i] = max(abs(v - int(stereo.pixels[i, 0])) for v in xs) > width + slack
    return out


@pytest.mark.parametrize("seed", range(6))
def test_contested_equals_the_row_by_row_reading(seed: int) -> None:
    rng = np.random.default_rng(seed)
    H, W, n = 12, 40, 60
    P_R = rng.random((H, W)) < 0.35
    xy = np.column_stack([rng.integers(0, W + 10, n), rng.integers(-1, H + 1, n)])
    disp = rng.uniform(-2.0, 14.0, n)
    disp[rng.random(n) < 0.1] = np.nan
    stereo, rel = _matches([tuple(p) for p in xy], list(disp))
    rel.reliable[rng.random(n) < 0.2] = False
    for slack in (0.0, 2.0, 5.0):
        want = _contested_by_rows(stereo, rel, P_R, slack)
        assert np.array_equal(contested(stereo, rel, P_R, slack), want)


def test_contested_reads_p_rs_row_runs_once_with_the_refine_stage_and_the_field(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """P_R is scanned once per segmentation: contested, the check's field (count and box)
    and the refine stage's runs all read refine.row_runs, cached with the mask."""
    from threadrecon.core import refine
    from threadrecon.core.check_field import clear_fields, mask_field

    scans = []

    def counted(mask: np.ndarray):
        scans.append(mask)
        return real(mask)

    real = refine._mask_runs
    monkeypatch.setattr(refine, "_mask_runs", counted)
    clear_fields()
    P_R = _rows([(5, 10, 12), (5, 30, 32)])
    stereo, rel = _matches([(11, 5), (31, 5), (40, 5)], [0.0, 0.0, 29.0])
    assert contested(stereo, rel, P_R, 2.0).tolist() == [True, False, True]
    assert len(scans) == 1 and scans[0] is P_R
    field = mask_field(P_R, 5.0)
    assert (field.total, field.bbox) == (6, (10, 5, 23, 1))
    refine._runs(P_R, np.zeros(P_R.shape, np.float32), 0.0)
    assert len(scans) == 1


def test_uncontested_is_one_cached_array_so_the_reliable_rows_are_built_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The reliable matches less the contested ones: the same read-only array on every run of
    the check (its reliable rows then come from the cache), None when nothing is contested
    (ck17: a new array per run rebuilt the rows each time)."""
    from threadrecon.core import check_support
    from threadrecon.core.check_field import clear_fields

    clear_fields()
    stereo, rel = _matches([(20, 10), (21, 10), (22, 10), (27, 10)], [10.0, 10.0, 10.0, 16.0])
    P_R = _rows([(10, 10, 12)])
    kept = uncontested(stereo, rel, P_R, 2.0)
    assert kept.tolist() == [False, False, True, False] and not kept.flags.writeable
    assert uncontested(stereo, rel, P_R, 2.0) is kept
    built = []
    real = check_support._rows
    monkeypatch.setattr(check_support, "_rows", lambda s, r: built.append(r) or real(s, r))
    for _ in range(3):  # the check's rel_s, replaced on each run around the one array
        rows = reliable_rows(stereo, SimpleNamespace(reliable=uncontested(stereo, rel, P_R, 2.0)))
    assert len(built) == 1 and rows[0].tolist() == [22]
    apart = _rows([(10, 10, 12), (10, 17, 19)])  # a right strand for each: no contest
    stereo2, rel2 = _matches([(20, 10), (27, 10)], [10.0, 10.0])
    assert uncontested(stereo2, rel2, apart, 2.0) is None
