"""Keypoint selection via BFS clustering of the reliable pixels P_L^R (paper Sec. III-B).

Neighbours are reliable pixels within a Manhattan distance of ``radius`` (2 in the paper). A BFS
grows from a start pixel until its frontier is empty or it holds ``max_size`` pixels; explored
sets of at least ``min_size`` pixels become clusters; each cluster's centroid is a keypoint.

``mode="restart"`` is the paper's procedure: every BFS starts at the first unexplored pixel in
scan order. ``mode="wavefront"`` (default) starts each connected component's BFS at one of its
extremities and cuts the BFS order into consecutive runs of ``max_size`` pixels: the clusters are
then slices across the thread, in order along it, independent of the image scan order, and the
whole stage is vectorised (scipy.sparse.csgraph) instead of a Python loop over pixels.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

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
    graph = _neighbour_graph(stereo.pixels[rel_idx], stereo.shape, p.radius)
    if p.mode == "wavefront":
        local = _wavefront_clusters(graph, p.min_size, p.max_size)
    elif p.mode == "restart":
        local = _restart_clusters(graph, p.min_size, p.max_size)
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


def _neighbour_graph(pixels: np.ndarray, shape: tuple[int, int], radius: int) -> sp.csr_matrix:
    """Symmetric adjacency of pixels within Manhattan distance ``radius`` (excluding self).
    The index image covers the pixels' bounding box only (the thread, not the image)."""
    n = len(pixels)
    x0, y0 = pixels.min(axis=0) if n else (0, 0)
    x1, y1 = pixels.max(axis=0) if n else (0, 0)
    idx = np.full((y1 - y0 + 1 + 2 * radius, x1 - x0 + 1 + 2 * radius), -1, dtype=np.int32)
    x, y = pixels[:, 0] - x0 + radius, pixels[:, 1] - y0 + radius
    idx[y, x] = np.arange(n, dtype=np.int32)
    offsets = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]
    offsets = [o for o in offsets if 0 < abs(o[0]) + abs(o[1]) <= radius]
    dy = np.array([o[0] for o in offsets])
    dx = np.array([o[1] for o in offsets])
    nb = idx[y[:, None] + dy[None, :], x[:, None] + dx[None, :]]  # (n, offsets), row = i
    ok = nb >= 0
    indptr = np.concatenate([[0], np.cumsum(ok.sum(axis=1))])
    data = np.ones(int(indptr[-1]), dtype=np.int8)
    return sp.csr_matrix((data, nb[ok], indptr), shape=(n, n))


def _wavefront_clusters(graph: sp.csr_matrix, min_size: int, max_size: int) -> np.ndarray:
    n = graph.shape[0]
    labels = np.full(n, -1, dtype=np.int64)
    # The graph is symmetric: directed traversals visit exactly what undirected ones do, in
    # the same order, without scipy building the transpose (graph + graph.T) on every call.
    n_comp, comp = csgraph.connected_components(graph, directed=True, connection="weak")
    sizes = np.bincount(comp, minlength=n_comp)
    first = np.full(n_comp, -1)
    first[comp[::-1]] = np.arange(n)[::-1]  # lowest pixel index of each component
    next_label = 0
    for c in np.flatnonzero(sizes >= min_size):
        # Two BFS: the last pixel reached from any pixel is an extremity of the component.
        far = csgraph.breadth_first_order(
            graph, first[c], directed=True, return_predecessors=False
        )[-1]
        order = csgraph.breadth_first_order(graph, far, directed=True, return_predecessors=False)
        for start in range(0, order.size, max_size):
            chunk = order[start : start + max_size]
            if chunk.size >= min_size:
                labels[chunk] = next_label
                next_label += 1
    return _split_disconnected(graph, labels, min_size)


def _split_disconnected(graph: sp.csr_matrix, labels: np.ndarray, min_size: int) -> np.ndarray:
    """Each cluster becomes its connected parts (parts < ``min_size`` px are unclustered).

    Where the thread crosses itself a BFS slice holds both fronts that leave the crossing; its
    centroid would lie between the strands."""
    coo = graph.tocoo()
    same = (labels[coo.row] == labels[coo.col]) & (labels[coo.row] >= 0)
    n = graph.shape[0]
    sub = sp.csr_matrix((np.ones(int(same.sum()), np.int8), (coo.row[same], coo.col[same])), (n, n))
    _, part = csgraph.connected_components(sub, directed=False)
    part = np.where(labels >= 0, part, -1)
    sizes = np.bincount(part[part >= 0], minlength=n)
    part = np.where((part >= 0) & (sizes[np.maximum(part, 0)] >= min_size), part, -1)
    # Renumber in the order of the original labels (slices along the thread stay in order).
    keep = part >= 0
    key = labels[keep].astype(np.int64) * (n + 1) + part[keep]
    _, new = np.unique(key, return_inverse=True)
    out = np.full(n, -1, dtype=np.int64)
    out[keep] = new
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
