"""Keypoint selection via BFS clustering of the reliable pixels P_L^R (paper Sec. III-B).

Neighbours are reliable pixels within a Manhattan distance of ``radius`` (2 in the paper). A BFS
grows from a start pixel until its frontier is empty or it holds ``max_size`` pixels; explored
sets of at least ``min_size`` pixels become clusters; each cluster's centroid is a keypoint.

``mode="restart"`` is the paper's procedure: every BFS starts at the first unexplored pixel in
scan order. ``mode="wavefront"`` (default) starts each connected component's BFS at one of its
extremities and cuts the BFS order into consecutive runs of ``max_size`` pixels: the clusters are
then slices across the thread, in order along it, independent of the image scan order; its
BFS passes run in one compiled kernel (numba) over the neighbour graph (CSR), built vectorised.
"""

from __future__ import annotations

import functools
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp

from threadrecon.core.compiled import helper, kernel
from threadrecon.core.params import Params, param
from threadrecon.core.reliability import ReliabilityResult
from threadrecon.core.stereo import StereoResult


@dataclass(frozen=True)
class ClusterParams(Params):
    radius: int = param(2, lo=1, hi=10, unit="px", slider=(1, 6, 1), label="neighbour radius")
    """Neighbour radius, Manhattan distance in px (paper: 2)."""
    min_size: int = param(8, lo=1, hi=10000, unit="px", slider=(1, 100, 1), label="min size")
    """Smallest explored set that forms a cluster, px."""
    max_size: int = param(30, lo=1, hi=10000, unit="px", slider=(1, 200, 1), label="max size")
    """BFS stops growing a cluster at this many px."""
    mode: Literal["wavefront", "restart"] = "wavefront"
    """BFS start rule, see module docstring; "restart" is the paper's."""

    def _check(self) -> None:
        super()._check()
        if self.min_size > self.max_size:
            raise ValueError("clustering.min_size must not exceed clustering.max_size")


@dataclass(frozen=True)
class Clusters:
    """``labels``: (N,) int per pixel of P_L, cluster id or -1.
    ``keypoints``: (K, 3) cluster centroids in the left camera frame (the set K), calib units.
    ``keypoints_px``: (K, 3) (x, y, z): centroid in px and mean depth z, the spline's space.
    ``sizes``: (K,) pixels per cluster.
    """

    labels: np.ndarray
    keypoints: np.ndarray
    keypoints_px: np.ndarray
    sizes: np.ndarray

    @property
    def count(self) -> int:
        return int(self.sizes.size)


def cluster_keypoints(
    stereo: StereoResult, rel: ReliabilityResult, p: ClusterParams = ClusterParams()
) -> Clusters:
    """BFS clustering of P_L^R and cluster centroids (the keypoint set K)."""
    if p.radius < 1:
        raise ValueError(f"radius must be >= 1, got {p.radius}")
    if p.min_size < 1 or p.max_size < p.min_size:
        raise ValueError(f"need 1 <= min_size <= max_size, got {p.min_size}, {p.max_size}")
    rel_idx = np.flatnonzero(rel.reliable)
    labels = np.full(len(stereo.pixels), -1, dtype=np.int64)
    if rel_idx.size == 0:
        raise ValueError("no reliable pixels: lower the reliability threshold or check the pair")
    px = stereo.pixels[rel_idx]
    if p.mode == "wavefront":
        local = _wavefront_kernel(*_neighbour_lists(px, p.radius), p.min_size, p.max_size)
    elif p.mode == "restart":
        local = _restart_clusters(_neighbour_graph(px, p.radius), p.min_size, p.max_size)
    else:
        raise ValueError(f"mode must be 'wavefront' or 'restart', got {p.mode!r}")
    labels[rel_idx] = local
    k = int(local.max()) + 1 if local.size else 0
    if k == 0:
        raise ValueError(f"no cluster reaches min_size={p.min_size} px: no keypoints")
    sel = labels >= 0
    lab = labels[sel]
    sizes = np.bincount(lab, minlength=k)
    xyz = stereo.points[sel]
    keypoints = (
        np.stack([np.bincount(lab, weights=xyz[:, a], minlength=k) for a in range(3)], 1)
        / sizes[:, None]
    )
    px = stereo.pixels[sel].astype(np.float64)
    kx = np.bincount(lab, weights=px[:, 0], minlength=k) / sizes
    ky = np.bincount(lab, weights=px[:, 1], minlength=k) / sizes
    keypoints_px = np.stack([kx, ky, keypoints[:, 2]], axis=1)
    return Clusters(labels=labels, keypoints=keypoints, keypoints_px=keypoints_px, sizes=sizes)


def _neighbour_graph(pixels: np.ndarray, radius: int) -> sp.csr_matrix:
    """Symmetric adjacency of pixels within Manhattan distance ``radius`` (excluding self), as
    CSR with each row's neighbours in ascending order (:func:`_neighbour_lists`)."""
    indptr, indices = _neighbour_lists(pixels, radius)
    n = len(pixels)
    return sp.csr_matrix((np.ones(indices.size, dtype=np.int8), indices, indptr), shape=(n, n))


def _neighbour_lists(pixels: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(indptr, indices) of the neighbour graph of ``pixels`` ((N, 2) int (x, y), row-major
    order). The index image covers the pixels' bounding box only (the thread, not the image)."""
    n = len(pixels)
    if n == 0:
        return np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    xs, ys = pixels[:, 0], pixels[:, 1]  # per column: 4x faster than axis=0 on (N, 2)
    x0, y0, x1, y1 = xs.min(), ys.min(), xs.max(), ys.max()
    idx = np.full((y1 - y0 + 1 + 2 * radius, x1 - x0 + 1 + 2 * radius), -1, dtype=np.int32)
    x, y = pixels[:, 0] - x0 + radius, pixels[:, 1] - y0 + radius
    idx[y, x] = np.arange(n, dtype=np.int32)
    dy, dx = _offsets(radius)
    return _gather_kernel(idx, y.astype(np.int64), x.astype(np.int64), dy, dx)


@functools.lru_cache(maxsize=16)
def _offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(dy, dx) int64 of the offsets within Manhattan distance ``radius`` (self excluded), in
    row-major order; built once per radius (read-only: the cached arrays are shared)."""
    offsets = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]
    offsets = [o for o in offsets if 0 < abs(o[0]) + abs(o[1]) <= radius]
    dy = np.array([o[0] for o in offsets], dtype=np.int64)
    dx = np.array([o[1] for o in offsets], dtype=np.int64)
    dy.flags.writeable = dx.flags.writeable = False
    return dy, dx


# --- compiled kernels ------------------------------------------------------------------------
# Compiled ahead of time once per machine, loaded without numba (core/compiled.py).


@kernel(
    "Tuple((int64[::1], int64[::1]))(int32[:, ::1], int64[::1], int64[::1], int64[::1], int64[::1])"
)
def _gather_kernel(idx, y, x, dy, dx):  # noqa: ANN001
    """CSR of the pixels at offsets (dy, dx) from each pixel (y, x) in the index image ``idx``
    (-1 where none), in offset order: the order of a (n, offsets) gather and a row-wise mask."""
    n = y.size
    indptr = np.zeros(n + 1, dtype=np.int64)
    indices = np.empty(n * dy.size, dtype=np.int64)
    k = 0
    for i in range(n):
        for o in range(dy.size):
            j = idx[y[i] + dy[o], x[i] + dx[o]]
            if j >= 0:
                indices[k] = j
                k += 1
        indptr[i + 1] = k
    return indptr, indices[:k].copy()


@helper()
def _bfs(indptr, indices, start, seen, mark, order):  # noqa: ANN001
    """BFS from ``start`` over nodes whose ``seen`` differs from ``mark`` (sets it to ``mark``),
    neighbours in CSR order (as csgraph.breadth_first_order): the visit order in ``order``;
    returns how many were visited."""
    order[0] = start
    seen[start] = mark
    head, tail = 0, 1
    while head < tail:
        u = order[head]
        head += 1
        for e in range(indptr[u], indptr[u + 1]):
            v = indices[e]
            if seen[v] != mark:
                seen[v] = mark
                order[tail] = v
                tail += 1
    return tail


@kernel("int64[::1](int64[::1], int64[::1], int64, int64)")
def _wavefront_kernel(indptr, indices, min_size, max_size):  # noqa: ANN001
    """Per connected component of >= ``min_size`` px (in the order of their lowest pixel): a BFS
    from its lowest pixel finds an extremity (the last pixel reached), a BFS from there orders
    the component, consecutive runs of ``max_size`` px of that order are clusters (a run under
    ``min_size`` is not). Then every cluster becomes its connected parts (graph restricted to the
    cluster; parts under ``min_size`` px are unclustered): where the thread crosses itself a
    run holds both fronts that leave the crossing, and its centroid would lie between them.
    Labels: by cluster, then by the part's lowest pixel."""
    n = indptr.size - 1
    labels = np.full(n, -1, dtype=np.int64)
    seen = np.zeros(n, dtype=np.int64)  # BFS marks: 1 component search, 2 ordering BFS
    order = np.empty(n, dtype=np.int64)
    comp = np.empty(n, dtype=np.int64)
    next_label = 0
    for s in range(n):
        if seen[s] != 0:
            continue
        m = _bfs(indptr, indices, s, seen, 1, comp)  # from the component's lowest pixel
        if m < min_size:
            continue
        _bfs(indptr, indices, comp[m - 1], seen, 2, order)  # from the last pixel it reached
        for start in range(0, m, max_size):
            stop = min(start + max_size, m)
            if stop - start >= min_size:
                for i in range(start, stop):
                    labels[order[i]] = next_label
                next_label += 1
    # Connected parts of each cluster: BFS inside the cluster from its parts' lowest pixels.
    part = np.full(n, -1, dtype=np.int64)  # lowest pixel of the part
    size = np.zeros(n, dtype=np.int64)
    for s in range(n):
        if labels[s] < 0 or part[s] >= 0:
            continue
        part[s] = s
        order[0] = s
        head, tail = 0, 1
        while head < tail:
            u = order[head]
            head += 1
            for e in range(indptr[u], indptr[u + 1]):
                v = indices[e]
                if part[v] < 0 and labels[v] == labels[s]:
                    part[v] = s
                    order[tail] = v
                    tail += 1
        size[s] = tail
    keys = np.empty(n, dtype=np.int64)
    k = 0
    for s in range(n):
        if part[s] == s and size[s] >= min_size:
            keys[k] = labels[s] * (n + 1) + s
            k += 1
    rank = np.full(n, -1, dtype=np.int64)
    srt = np.sort(keys[:k])
    for i in range(k):
        rank[srt[i] % (n + 1)] = i
    out = np.full(n, -1, dtype=np.int64)
    for v in range(n):
        if part[v] >= 0:
            out[v] = rank[part[v]]
    return out


def _restart_clusters(graph: sp.csr_matrix, min_size: int, max_size: int) -> np.ndarray:
    """The paper's BFS: restart at the first unexplored pixel until none is left."""
    n = graph.shape[0]
    indptr, indices = graph.indptr, graph.indices
    labels = np.full(n, -1, dtype=np.int64)
    explored = np.zeros(n, dtype=bool)
    next_label = 0
    for s in range(n):
        if explored[s]:
            continue
        explored[s] = True
        members = [s]
        frontier = deque([s])
        while frontier and len(members) < max_size:
            u = frontier.popleft()
            for v in indices[indptr[u] : indptr[u + 1]]:
                if not explored[v] and len(members) < max_size:
                    explored[v] = True
                    members.append(v)
                    frontier.append(v)
        if len(members) >= min_size:
            labels[members] = next_label
            next_label += 1
    return labels
