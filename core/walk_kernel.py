"""Compiled kernels of the ordering (core/ordering.py): the walk (walk = "bending") and the
geodesic distances inside gaps (:func:`gap_distances`).

A walk step looks at a handful of keypoints, and a 1920x1080 frame tries up to ``MAX_WALKS``
walks of 500-800 steps: as numpy calls on arrays of one or two elements that is 10-60 us a
step, 100-300 ms a frame. This kernel takes the steps of tiers 0 and 1 of
:func:`threadrecon.core.ordering._continuations` (neighbours in A; the other strand of a
crossing) with the same cost, in the same floating-point operations, and hands the walk back
to Python when only a jump across a gap (tier 2, a few per walk) is left.

The graph A is CSR: ``indptr``, ``indices``, each keypoint's neighbours in the order of
``ordering._adjacency`` (the candidates' order breaks ties, as a stable sort does).
"""

from __future__ import annotations

import math

import numpy as np

from threadrecon.core.compiled import helper, kernel

WALK_END = 0  # the walk ends: no continuation, every one excluded, or the forced one missing
WALK_JUMP = 1  # tiers 0 and 1 are empty: the caller looks for a jump (tier 2)


@helper(inline="always")
def _before(a: float, b: float) -> bool:
    """a sorts before b (np.argsort: NaN last)."""
    return a < b or (math.isnan(b) and not math.isnan(a))


@helper(inline="always")
def _after(a: float, i: int, b: float, k: int) -> bool:
    """Candidate i of cost a sorts after candidate k of cost b (a stable argsort: by cost,
    NaN last, ties by candidate order)."""
    return _before(b, a) or (not _before(a, b) and i > k)


REF_KEYPOINTS = 3  # the walk's disparity reference: the mean of its last three keypoints ...
REF_LOOKBACK = 8  # ... that are not junctions, among its last eight (a crossing spans a few)


@helper()
def _ref_disparity(walk, n, disp, indptr):  # noqa: ANN001
    """Mean disparity of the last ``REF_KEYPOINTS`` keypoints of ``walk[:n]`` that are no
    junction (degree < 3 in A), looking back at most ``REF_LOOKBACK`` keypoints; of the last
    ``REF_KEYPOINTS`` keypoints where there is none. A crossing's keypoints carry the other
    strand's disparity (their pixels are both strands'), and would turn the walk onto the
    other strand at the crossing. Summed oldest first (the paper-era reference, bit for bit,
    where no junction is near)."""
    lo = n - REF_LOOKBACK if n >= REF_LOOKBACK else 0
    start = n
    c = 0
    while start > lo and c < REF_KEYPOINTS:
        start -= 1
        k = walk[start]
        if indptr[k + 1] - indptr[k] < 3:
            c += 1
    ref = 0.0
    if c == 0:
        start = n - REF_KEYPOINTS if n >= REF_KEYPOINTS else 0
        for i in range(start, n):
            ref += disp[walk[i]]
        return ref / (n - start)
    for i in range(start, n):
        k = walk[i]
        if indptr[k + 1] - indptr[k] < 3:
            ref += disp[k]
    return ref / c


@helper(inline="always")
def _is_split(v, indptr):  # noqa: ANN001
    """Keypoint v has degree 3 in A: with an adjacent one of degree 3, the two are a four-arm
    crossing split in two (a junction of higher degree is a knot of touching strands, whose
    arms are no continuation of each other)."""
    return indptr[v + 1] - indptr[v] == 3


@helper()
def _add_free(u, cur, visited, indptr, indices, cand, m):  # noqa: ANN001
    """Append the unvisited neighbours of u other than ``cur`` that ``cand[:m]`` does not hold
    yet to it; returns the new count."""
    for f in range(indptr[u], indptr[u + 1]):
        w = indices[f]
        if w == cur or visited[w]:
            continue
        seen = False
        for i in range(m):
            if cand[i] == w:
                seen = True
                break
        if not seen:
            cand[m] = w
            m += 1
    return m


@kernel(
    "UniTuple(int64, 2)(int64[::1], int64, boolean[::1], int64[::1], int64[::1], "
    "float64[:, ::1], float64[::1], float64, float64, float64, int64[::1], float64[::1], "
    "float64[::1])"
)
def step_costs(
    walk, n, visited, indptr, indices, pos, disp, bend_w, disp_w, cos_max, cand, cost, cos_t
):  # noqa: ANN001
    """Candidates of tiers 0 and 1 of ``_continuations`` for the walk ``walk[:n]``, their
    costs and the cosines of their turns, written to ``cand``, ``cost``, ``cos_t``; returns
    (count, tier). Count 0: neither tier has one (tier 2 is the caller's). Cost = dist (1 +
    bend_w (1 - cos turn)) + disp_w |disparity change from :func:`_ref_disparity`|; at tier 1
    a turn with cos < ``cos_max`` is inf unless every candidate turns that much.

    Tier 0: the unvisited neighbours of the current keypoint and, when it has degree 3, the
    unvisited neighbours of its unvisited neighbours of degree 3: the clusters of a
    crossing often split it into two adjacent three-way junctions, each holding one arm of
    either strand, and the strand goes on from the other one's arm (the junction passed over
    stays for the second strand). Tier 1: the unvisited neighbours of the visited neighbours,
    and through a visited one of degree 3 those of its neighbours of degree 3 too (the other
    half of a split crossing)."""
    cur = walk[n - 1]
    back = walk[n - 3] if n >= 3 else walk[0]
    hx = pos[cur, 0] - pos[back, 0]
    hy = pos[cur, 1] - pos[back, 1]
    hn = math.hypot(hx, hy)
    ref = _ref_disparity(walk, n, disp, indptr)
    m = 0
    for e in range(indptr[cur], indptr[cur + 1]):
        v = indices[e]
        if not visited[v]:
            cand[m] = v
            m += 1
    if _is_split(cur, indptr):  # a crossing split over two adjacent three-way junctions
        for i in range(m):
            if _is_split(cand[i], indptr):
                m = _add_free(cand[i], cur, visited, indptr, indices, cand, m)
    tier = 0
    if m == 0:
        tier = 1
        for e in range(indptr[cur], indptr[cur + 1]):
            u = indices[e]
            if not visited[u]:
                continue
            m = _add_free(u, cur, visited, indptr, indices, cand, m)
            if _is_split(u, indptr):  # the other junction of a split crossing
                for f in range(indptr[u], indptr[u + 1]):
                    w = indices[f]
                    if w != cur and _is_split(w, indptr):
                        m = _add_free(w, cur, visited, indptr, indices, cand, m)
        cand[:m].sort()
    if m == 0:
        return 0, 2
    any_ok = False
    for i in range(m):
        v = cand[i]
        cx = pos[v, 0] - pos[cur, 0]
        cy = pos[v, 1] - pos[cur, 1]
        dist = math.sqrt(cx * cx + cy * cy)
        if dist < 1e-9:
            dist = 1e-9
        cos_t[i] = (cx * (hx / hn) + cy * (hy / hn)) / dist if hn > 0 else 1.0
        cost[i] = dist * (1.0 + bend_w * (1.0 - cos_t[i])) + disp_w * abs(disp[v] - ref)
        any_ok |= cos_t[i] >= cos_max
    if tier == 1 and any_ok:  # else a touching turn: the sharpest continuation is all that is left
        for i in range(m):
            if not cos_t[i] >= cos_max:
                cost[i] = np.inf
    return m, tier


@kernel(
    "UniTuple(int64, 3)(int64[::1], int64, int64, float64[::1], int64, boolean[::1], "
    "int64[::1], int64[::1], float64[:, ::1], float64[::1], float64, float64, float64, "
    "int64[::1], int64[::1], int64[::1], int64, int64)"
)
def walk_on(
    walk,
    n,
    n_prefix,
    steps,
    forced,
    visited,
    indptr,
    indices,
    pos,
    disp,
    bend_w,
    disp_w,
    cos_max,
    alt_at,
    alt_kp,
    alt_rank,
    n_alt,
    runners,
):  # noqa: ANN001
    """Extend ``walk[:n]`` (``steps[:n-1]`` the cost of each step so far) by the cheapest
    continuation of tier 0 or 1 until none is left; at the first step after the prefix
    (``n == n_prefix``) the step goes to ``forced`` when it is >= 0. The ``runners`` next
    cheapest continuations of each step with a finite cost (the runner-up, rank 1, then the
    third, rank 2, ...) are appended to ``alt_at`` (walk index) / ``alt_kp`` / ``alt_rank``
    (buffers of at least ``runners`` entries per keypoint).
    Returns (n, n_alt, WALK_END or WALK_JUMP)."""
    K = visited.size
    cand = np.empty(K, dtype=np.int64)
    cost = np.empty(K)
    cos_t = np.empty(K)
    while True:
        m, _ = step_costs(
            walk, n, visited, indptr, indices, pos, disp, bend_w, disp_w, cos_max, cand, cost, cos_t
        )
        if m == 0:
            return n, n_alt, WALK_JUMP
        j = 0
        for i in range(1, m):
            if _before(cost[i], cost[j]):
                j = i
        if forced >= 0 and n == n_prefix:
            j = -1
            for i in range(m):
                if cand[i] == forced:
                    j = i
                    break
            if j < 0:
                return n, n_alt, WALK_END
        elif m > 1:
            prev = j  # each runner sorts after the one before it (ties: candidate order)
            for rank in range(1, min(runners, m - 1) + 1):
                r = -1
                for i in range(m):
                    if i == j or not _after(cost[i], i, cost[prev], prev):
                        continue
                    if r < 0 or _after(cost[r], r, cost[i], i):
                        r = i
                if r < 0 or not math.isfinite(cost[r]):
                    break
                alt_at[n_alt] = n - 1
                alt_kp[n_alt] = cand[r]
                alt_rank[n_alt] = rank
                n_alt += 1
                prev = r
        if not math.isfinite(cost[j]):
            return n, n_alt, WALK_END
        v = cand[j]
        visited[v] = True
        walk[n] = v
        steps[n - 1] = cost[j]
        n += 1


@kernel("float64[::1](int32[:, ::1], int64[::1], int64, float64[::1], int64[::1])")
def gap_distances(nb, node, K, step, src):  # noqa: ANN001
    """(N,) geodesic distances from the pixels ``src`` (distance 0) over the gap graph, inf
    where unreachable: Dijkstra with a binary heap. Pixel i steps to its neighbour nb[i, k]
    (-1: none) at cost step[k] when both lie in the same gap (``node`` equal and >= K).

    Every correct Dijkstra computes the same distances to the last bit: d[v] is the minimum over
    v's neighbours u of d[u] + w (a float64 sum, monotone in d[u], and > d[u] for w > 0), a
    fixed point that is unique given the sources; so these equal scipy's csgraph.dijkstra on
    the same graph, whatever the order in which ties are taken off the heap."""
    n = node.size
    dist = np.full(n, np.inf)
    cap = 8 * n + src.size + 1  # pushes: one per source and at most one per edge
    hk = np.empty(cap)  # heap keys (distances) and values (pixels)
    hv = np.empty(cap, dtype=np.int64)
    size = 0
    for s in src:
        if dist[s] > 0.0:
            dist[s] = 0.0
            size = _push(hk, hv, size, 0.0, s)
    while size > 0:
        d, u = hk[0], hv[0]
        size = _pop(hk, hv, size)
        if d > dist[u]:
            continue  # a stale entry: u was reached more cheaply since
        g = node[u]
        if g < K:
            continue  # a source on a cluster's pixel: no gap edge leaves it
        for k in range(nb.shape[1]):
            v = nb[u, k]
            if v < 0 or node[v] != g:
                continue
            nd = d + step[k]
            if nd < dist[v]:
                dist[v] = nd
                size = _push(hk, hv, size, nd, v)
    return dist


@helper(inline="always")
def _push(hk, hv, size, key, val):  # noqa: ANN001
    """Insert (key, val) into the binary min-heap hk[:size], hv[:size]; returns the new size."""
    i = size
    while i > 0:
        parent = (i - 1) // 2
        if hk[parent] <= key:
            break
        hk[i], hv[i] = hk[parent], hv[parent]
        i = parent
    hk[i], hv[i] = key, val
    return size + 1


@helper(inline="always")
def _pop(hk, hv, size):  # noqa: ANN001
    """Remove the root of the binary min-heap hk[:size], hv[:size]; returns the new size."""
    size -= 1
    key, val = hk[size], hv[size]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and hk[c + 1] < hk[c]:
            c += 1
        if hk[c] >= key:
            break
        hk[i], hv[i] = hk[c], hv[c]
        i = c
    if size > 0:
        hk[i], hv[i] = key, val
    return size


@kernel("int64[::1](int64[::1], int64[:, ::1], int64)")
def touching_keys(node, nb_node, m):  # noqa: ANN001
    """Keys lo * m + hi (lo < hi) of the pairs of different nodes >= 0 that are 8-neighbours
    (``node``: each pixel's, ``nb_node``: its neighbours', -1 for none; ``m`` > every node),
    with repeats, in pixel order."""
    n, k = nb_node.shape
    out = np.empty(n * k, dtype=np.int64)
    c = 0
    for i in range(n):
        a = node[i]
        if a < 0:
            continue
        for j in range(k):
            b = nb_node[i, j]
            if b >= 0 and b != a:
                out[c] = min(a, b) * m + max(a, b)
                c += 1
    return out[:c].copy()


@kernel("float64[::1](int64[::1], float64[::1], int64)")
def cluster_medians(labels, values, K):  # noqa: ANN001
    """(K,) median of the finite ``values`` of each cluster (``labels`` 0..K-1, < 0: none;
    NaN for a cluster with none): each cluster's values in pixel order, sorted by a stable
    insertion sort (clusters hold tens of pixels), the mean of the two middle ones. The same
    order as ``np.lexsort((values, labels))`` (ties in pixel order), so the same floats."""
    count = np.zeros(K + 1, dtype=np.int64)
    for i in range(labels.size):
        if labels[i] >= 0 and math.isfinite(values[i]):
            count[labels[i] + 1] += 1
    for c in range(K):
        count[c + 1] += count[c]  # count[c]: start of cluster c
    fill = count[:K].copy()
    buf = np.empty(count[K])
    for i in range(labels.size):
        c = labels[i]
        if c >= 0 and math.isfinite(values[i]):
            buf[fill[c]] = values[i]
            fill[c] += 1
    out = np.full(K, np.nan)
    for c in range(K):
        lo, hi = count[c], count[c + 1]
        for j in range(lo + 1, hi):  # stable: an equal value stays after the earlier one
            v = buf[j]
            i = j - 1
            while i >= lo and buf[i] > v:
                buf[i + 1] = buf[i]
                i -= 1
            buf[i + 1] = v
        n = hi - lo
        if n > 0:
            out[c] = 0.5 * (buf[lo + (n - 1) // 2] + buf[lo + n // 2])
    return out


@kernel("int64[::1](int32[:, ::1], boolean[::1])")
def member_components(nb, member):  # noqa: ANN001
    """(N,) label of the connected component (over the neighbour table ``nb``, -1: none) of
    each pixel where ``member``, numbered 1.. in the order of each component's first pixel, 0
    elsewhere: union-find over the pixel list (the components of P_L's gaps without an image of
    their bounding box)."""
    n = member.size
    parent = np.arange(n)
    for i in range(n):
        if not member[i]:
            continue
        for k in range(nb.shape[1]):
            j = nb[i, k]
            if j < 0 or not member[j]:
                continue
            a, b = i, j  # union(i, j): find both roots (path halving), link the larger id
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = parent[a]
            while parent[b] != b:
                parent[b] = parent[parent[b]]
                b = parent[b]
            if a != b:
                if a < b:
                    parent[b] = a
                else:
                    parent[a] = b
    label = np.zeros(n, dtype=np.int64)
    root_label = np.zeros(n, dtype=np.int64)
    count = 0
    for i in range(n):
        if not member[i]:
            continue
        r = i
        while parent[r] != r:
            r = parent[r]
        if root_label[r] == 0:
            count += 1
            root_label[r] = count
        label[i] = root_label[r]
    return label


@kernel("boolean[::1](int64[::1], int64[::1], boolean[:, :], int64, int64)")
def row_hits(x, y, P, tol, slack):  # noqa: ANN001
    """(N,) bool: a pixel of ``P`` (H, W) bool on a row ``y[i]`` +- ``slack`` (inside the image)
    and a column within ``tol`` of ``x[i]`` (the window clipped to the image): the test of
    :func:`threadrecon.core.ends.seen_in_right`, a few pixels read per point instead of prefix
    sums of whole image rows."""
    H, W = P.shape
    n = x.size
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        lo = min(max(x[i] - tol, 0), W)
        hi = min(max(x[i] + tol + 1, 0), W)
        for dy in range(-slack, slack + 1):
            yy = y[i] + dy
            if yy < 0 or yy >= H:
                continue
            for xx in range(lo, hi):
                if P[yy, xx]:
                    out[i] = True
                    break
            if out[i]:
                break
    return out


@kernel("int32[:, ::1](int32[:, ::1], int64[::1], int64[::1])")
def grid_neighbours(index, y, x):  # noqa: ANN001
    """(N, 8) ``index`` at the 8 neighbours of each pixel (``y``, ``x``: rows and columns in
    the index image, at least 1 px inside it), in the order of ``ordering._OFFSETS_8`` (rows
    -1, 0, 1, columns -1, 0, 1 within each, the pixel itself left out): one pass, where eight
    gathers and a stack were 0.1-0.3 ms a frame."""
    n = y.size
    out = np.empty((n, 8), dtype=np.int32)
    for i in range(n):
        k = 0
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                if dy != 0 or dx != 0:
                    out[i, k] = index[y[i] + dy, x[i] + dx]
                    k += 1
    return out


@helper(inline="always")
def _pairwise_block(a, lo, n):  # noqa: ANN001
    """numpy's pairwise sum of a block of n <= 128 values a[lo:lo + n]: fewer than 8 in turn;
    else 8 running sums combined as ((0 + 1) + (2 + 3)) + ((4 + 5) + (6 + 7)), then the rest
    in turn."""
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    m = n - n % 8
    for i in range(lo + 8, lo + m, 8):
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for i in range(lo + m, lo + n):
        res += a[i]
    return res


@helper(inline="always")
def _pairwise_half(n):  # noqa: ANN001
    """Where numpy's pairwise sum splits n > 128 values: half, rounded down to a multiple
    of 8."""
    n2 = n // 2
    return n2 - n2 % 8


@helper()
def _pairwise_sum(a, lo, n):  # noqa: ANN001
    """numpy's pairwise sum of a[lo:lo + n] (float64, contiguous), the same additions in the
    same order (what ``np.sum`` of a contiguous block does): blocks of at most 128 values
    (:func:`_pairwise_block`), a longer run split at :func:`_pairwise_half` and the two sums
    added, left + right. The split tree is walked with a stack (no recursion: the
    ahead-of-time build takes none)."""
    if n <= 128:
        return _pairwise_block(a, lo, n)
    n2 = _pairwise_half(n)
    if n - n2 <= 128:  # one split (up to ~256 values: a 15 x 15 window)
        return _pairwise_block(a, lo, n2) + _pairwise_block(a, lo + n2, n - n2)
    depth = 64  # splits halve n: far more levels than any array has
    s_lo = np.empty(depth, dtype=np.int64)
    s_n = np.empty(depth, dtype=np.int64)
    s_left = np.zeros(depth, dtype=np.bool_)  # the left half's sum is in s_val
    s_val = np.empty(depth)
    top = 0
    s_lo[0], s_n[0], s_left[0] = lo, n, False
    while True:
        if s_n[top] > 128:  # descend into the left half
            h = _pairwise_half(s_n[top])
            top += 1
            s_lo[top], s_n[top], s_left[top] = s_lo[top - 1], h, False
            continue
        v = _pairwise_block(a, s_lo[top], s_n[top])
        top -= 1
        while True:  # hand v up: a left half waits for its right one, a right one completes
            if top < 0:
                return v
            if not s_left[top]:
                s_left[top], s_val[top] = True, v
                h = _pairwise_half(s_n[top])
                top += 1
                s_lo[top], s_n[top], s_left[top] = s_lo[top - 1] + h, s_n[top - 1] - h, False
                break
            v = s_val[top] + v
            top -= 1


@kernel("float64[:, ::1](float64[:, ::1], float64[:, ::1], int64, int64, int64)")
def tip_costs(A, strip, radius, slack, shifts):  # noqa: ANN001
    """The SSD curves of :func:`threadrecon.core.ends.tip_disparity`: row t (the right row
    offset t - ``slack``), column k (the k-th of ``shifts`` shifts, the smallest first) is the
    mean of the squared differences between the left window ``A`` (n, n), n = 2 radius + 1,
    and the right window at rows t..t+n-1 and columns ``shifts`` - 1 - k .. ``shifts`` - 2 -
    k + n of ``strip`` (n + 2 slack, n + ``shifts`` - 1), summed as ``np.mean`` of the
    (shifts, n, n) block does: each shift's n^2 squares in one pairwise sum, then divided by
    n^2. Deviation 23's search has ``shifts`` = n; deviation 55's dead end a wider one."""
    n = 2 * radius + 1
    out = np.empty((2 * slack + 1, shifts))
    sq = np.empty(n * n)
    for t in range(2 * slack + 1):
        for k in range(shifts):
            c0 = shifts - 1 - k
            for r in range(n):
                for j in range(n):
                    v = A[r, j] - strip[t + r, c0 + j]
                    sq[r * n + j] = v * v
            out[t, k] = _pairwise_sum(sq, 0, n * n) / (n * n)
    return out


@kernel(
    "uint8[::1](float64, float64[::1], float64[::1], float64[:, ::1], float64, float64, float64, int64)"
)
def track_strand(d_a, first, second, xy, slack, slope, outlier, ref_n):  # noqa: ANN001
    """bounds._track compiled: (n,) uint8, what the pixels of a gap (in order outwards from its
    anchor of disparity ``d_a``; ``xy``: (n + 1, 2), the anchor first) do: 1 take their second
    match, 0 their first, 2 keep their first untaken, 3 the same with the first beyond the
    bound by more than ``outlier`` (another match: deviation 64 in bounds._dead_end_depths). The strand's
    disparity is the median of the last ``ref_n`` pixels taken (the anchor's at first); a
    pixel keeps its first match within ``slack + slope * step`` of it (step: distance from
    the last pixel taken), else takes its second when that lies within and the first lies
    beyond by more than ``outlier``; otherwise it keeps its first and the strand's disparity
    does not move."""
    n = first.size
    state = np.zeros(n, dtype=np.uint8)
    ring = np.empty(ref_n)
    buf = np.empty(ref_n)
    ring[0] = d_a
    taken = 1
    lx, ly = xy[0, 0], xy[0, 1]
    for i in range(n):
        k = min(taken, ref_n)
        for j in range(k):  # the last k taken, insertion-sorted: k <= ref_n (a handful)
            v = ring[(taken - k + j) % ref_n]
            m = j - 1
            while m >= 0 and buf[m] > v:
                buf[m + 1] = buf[m]
                m -= 1
            buf[m + 1] = v
        d_ref = 0.5 * (buf[(k - 1) // 2] + buf[k // 2])
        px, py = xy[i + 1, 0], xy[i + 1, 1]
        bound = slack + slope * math.hypot(px - lx, py - ly)
        e1 = abs(first[i] - d_ref)
        if e1 <= bound:
            v = first[i]
        elif abs(second[i] - d_ref) <= bound and e1 > bound + outlier:
            v = second[i]
            state[i] = 1
        else:
            state[i] = 3 if e1 > bound + outlier else 2
            continue
        ring[taken % ref_n] = v
        taken += 1
        lx, ly = px, py
    return state


@kernel(
    "float64[::1](float32[:, :], boolean[:, :], float64, float64, float64, float64, int64, "
    "float64, float64, int64, int64, float64)"
)
def occluded_share(grey, P, x0, y0, wx, wy, search, level, tol, disc, rim, tip):  # noqa: ANN001
    """ordering._occluded_share compiled: (3,) (found, share of all, share off the rim), found
    0 where that function gives None. The ray from (``x0``, ``y0``) along (``wx``, ``wy``) at
    steps 0..``search`` px, rounded as ``np.rint``; where it first leaves ``P`` (H, W) the disc
    of radius ``disc`` and its rim of ``rim`` px (the dilation of the thread pixels by a
    (2 rim + 1) square inside the patch, as cv2.dilate on the patch); pixels ``tip`` px ahead
    along the way. Shares as ``np.mean`` of bool arrays: count / n in float64. Where the
    numpy version took some 25 calls on a 15x15 patch (~100-200 us a ray), this takes a few."""
    H, W = P.shape
    out = np.zeros(3)
    cx, cy = -1, -1
    for s in range(search + 1):
        x = np.int64(np.rint(x0 + s * wx))
        y = np.int64(np.rint(y0 + s * wy))
        if x < 0 or y < 0 or x >= W or y >= H:
            return out  # the image border
        if not P[y, x]:
            cx, cy = x, y
            break
    if cx < 0:
        return out  # the thread goes on past the search
    r = disc + rim
    xa, xb, ya, yb = max(cx - r, 0), min(cx + r + 1, W), max(cy - r, 0), min(cy + r + 1, H)
    d2 = disc * disc
    n_disc = 0
    n_other = 0
    n_clean = 0
    n_clean_other = 0
    beside = False
    for yy in range(ya, yb):
        dy = yy - cy
        for xx in range(xa, xb):
            dx = xx - cx
            near = dx * dx + dy * dy <= d2
            if P[yy, xx]:
                if near and dx * wx + dy * wy > tip:
                    beside = True
                continue
            if not near:
                continue
            other = abs(np.float64(grey[yy, xx]) - level) > tol
            n_disc += 1
            n_other += other
            on_rim = False
            for ry in range(max(yy - rim, ya), min(yy + rim + 1, yb)):
                for rx in range(max(xx - rim, xa), min(xx + rim + 1, xb)):
                    if P[ry, rx]:
                        on_rim = True
            if not on_rim:
                n_clean += 1
                n_clean_other += other
    if n_disc == 0:
        return out  # the disc holds thread pixels only
    out[0] = 1.0
    out[1] = n_other / n_disc
    out[2] = n_clean_other / n_clean if n_clean > 0 else 0.0
    if beside:
        out[2] = 1.0
    return out


@kernel(
    "Tuple((int64[::1], int64[::1], float64[::1], float64[::1]))(int64[::1], float64[::1], "
    "int64[:, :], int64[::1], int64[::1], int64[::1], float64)"
)
def extra_runs(link, t, xy, count, n_extra, sel, tie):  # noqa: ANN001
    """The runs of bounds._extra_points in one pass over the gap pixels sorted by link, then
    by position ``t`` along it (``xy``: (N, 2) pixels; ``sel``: the sorted pixels' indices into
    it; ``count``: pixels per link; ``n_extra``: runs per link, ``count // extra_px``). A
    link's pixel j of c (its tie group, ``t`` within ``tie`` of the one before, at the group's
    mean j) goes to run floor((j + 1/2) n / c), a pixel exactly on a run boundary to none.
    Returns the kept pixels' positions in the sorted order, their global run ids (in the order
    of H) and the runs' centroids: their sums taken pixel by pixel in that order, as
    np.bincount's weights are, divided by max(size, 1)."""
    m = link.size
    n_links = count.size
    run_start = np.zeros(n_links + 1, dtype=np.int64)
    for k in range(n_links):
        run_start[k + 1] = run_start[k] + n_extra[k]
    n_runs = run_start[n_links]
    pos = np.empty(m, dtype=np.int64)
    group = np.empty(m, dtype=np.int64)
    sx = np.zeros(n_runs)
    sy = np.zeros(n_runs)
    size = np.zeros(n_runs, dtype=np.int64)
    out = 0
    i = 0
    while i < m:  # one link's pixels: i .. e - 1
        k = link[i]
        e = i
        while e < m and link[e] == k:
            e += 1
        n = n_extra[k]
        if n > 0:
            c = count[k]
            g = i
            while g < e:  # one tie group: g .. h - 1, at positions g - i .. h - 1 - i
                h = g + 1
                while h < e and not (t[h] - t[h - 1] > tie):
                    h += 1
                num = ((g - i) + (h - 1 - i) + 1) * n
                run = num // (2 * c)
                if not (num % (2 * c) == 0 and run > 0):
                    for q in range(g, h):
                        r = run_start[k] + run
                        pos[out] = q
                        group[out] = r
                        out += 1
                g = h
        i = e
    for q in range(out):  # the centroids, summed in the kept pixels' order
        r = group[q]
        s = sel[pos[q]]
        sx[r] += float(xy[s, 0])
        sy[r] += float(xy[s, 1])
        size[r] += 1
    for r in range(n_runs):
        d = float(max(size[r], 1))
        sx[r] /= d
        sy[r] /= d
    return pos[:out].copy(), group[:out].copy(), sx, sy


@kernel("Tuple((float64[::1], boolean[::1]))(int64[::1], float64[::1], int64)")
def run_medians(group, depth, n_runs):  # noqa: ANN001
    """(n_runs,) the median of each run's finite ``depth`` values (NaN: none) and whether it
    has one; ``group``: the run of each value. The mean of the two middle values of the sorted
    run (one value of an odd run twice), as bounds._extra_points took them."""
    n_f = np.zeros(n_runs + 1, dtype=np.int64)
    for q in range(group.size):
        if math.isfinite(depth[q]):
            n_f[group[q] + 1] += 1
    for r in range(n_runs):
        n_f[r + 1] += n_f[r]  # now the start of each run's values
    vals = np.empty(n_f[n_runs])
    fill = n_f[:n_runs].copy()
    for q in range(group.size):
        if math.isfinite(depth[q]):
            vals[fill[group[q]]] = depth[q]
            fill[group[q]] += 1
    med = np.full(n_runs, np.nan)
    has = np.zeros(n_runs, dtype=np.bool_)
    for r in range(n_runs):
        a, b = n_f[r], n_f[r + 1]
        if b > a:
            v = np.sort(vals[a:b])
            k = b - a
            med[r] = 0.5 * (v[(k - 1) // 2] + v[k // 2])
            has[r] = True
    return med, has
