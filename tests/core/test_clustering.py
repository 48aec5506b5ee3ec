"""Tests of core/clustering.py: BFS clusters of reliable pixels and their centroids."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse import csgraph
from scipy.spatial import cKDTree
from support import assert_close, synthetic_case

from threadrecon.core.clustering import (
    ClusterParams,
    _neighbour_graph,
    _neighbour_lists,
    _wavefront_kernel,
    cluster_keypoints,
)
from threadrecon.core.pipeline import Pipeline
from threadrecon.core.reliability import ReliabilityResult
from threadrecon.core.stereo import StereoResult

MODES = ("wavefront", "restart")


def _stereo_rel(seed: int) -> tuple[StereoResult, ReliabilityResult]:
    pair, calib, _ = synthetic_case(seed)
    rec = Pipeline(pair, calib).run(until="reliability")
    assert rec.status == "ok", rec.message
    return rec["stereo"], rec["reliability"]


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(("min_size", "max_size"), [(8, 30), (3, 12)])
def test_clusters_respect_size_limits(mode: str, seed: int, min_size: int, max_size: int) -> None:
    st, rel = _stereo_rel(seed)
    cl = cluster_keypoints(st, rel, ClusterParams(min_size=min_size, max_size=max_size, mode=mode))
    assert cl.count > 5
    assert np.all((cl.sizes >= min_size) & (cl.sizes <= max_size))
    assert_close(cl.sizes, np.bincount(cl.labels[cl.labels >= 0], minlength=cl.count))
    # Only reliable pixels are clustered, and every cluster id 0..K-1 is used.
    assert np.all(rel.reliable[cl.labels >= 0])
    assert set(np.unique(cl.labels[cl.labels >= 0])) == set(range(cl.count))


@pytest.mark.parametrize("mode", MODES)
def test_keypoints_are_centroids_of_their_clusters(mode: str) -> None:
    st, rel = _stereo_rel(0)
    cl = cluster_keypoints(st, rel, ClusterParams(mode=mode))
    assert cl.keypoints.shape == (cl.count, 3) and cl.keypoints_px.shape == (cl.count, 3)
    for k in range(cl.count):
        members = cl.labels == k
        assert_close(cl.keypoints[k], st.points[members].mean(axis=0), rtol=1e-12, atol=1e-12)
        assert_close(
            cl.keypoints_px[k, :2], st.pixels[members].mean(axis=0), rtol=1e-12, atol=1e-12
        )
        assert_close(cl.keypoints_px[k, 2], cl.keypoints[k, 2])


@pytest.mark.parametrize("mode", MODES)
def test_cluster_members_are_connected_within_radius(mode: str) -> None:
    """Every member of a cluster lies within ``radius`` (Manhattan) of another member."""
    st, rel = _stereo_rel(1)
    p = ClusterParams(mode=mode)
    cl = cluster_keypoints(st, rel, p)
    for k in range(cl.count):
        px = st.pixels[cl.labels == k]
        d = np.abs(px[:, None, :] - px[None, :, :]).sum(-1)
        np.fill_diagonal(d, 10**6)
        assert np.all(d.min(axis=1) <= p.radius)


def test_no_reliable_pixels_raises() -> None:
    st, rel = _stereo_rel(0)
    none = replace(rel, reliable=np.zeros_like(rel.reliable))
    with pytest.raises(ValueError, match="no reliable pixels"):
        cluster_keypoints(st, none)


def test_invalid_parameters_raise_on_construction() -> None:
    with pytest.raises(ValueError, match="radius"):
        ClusterParams(radius=0)
    with pytest.raises(ValueError, match="min_size"):
        ClusterParams(min_size=10, max_size=5)
    with pytest.raises(ValueError, match="mode"):
        ClusterParams(mode="dfs")  # type: ignore[arg-type]


def _reference_wavefront(graph: sp.csr_matrix, min_size: int, max_size: int) -> np.ndarray:
    """The wavefront clusters and their split into connected parts with scipy.sparse.csgraph
    (the kernel's specification)."""
    n = graph.shape[0]
    labels = np.full(n, -1, dtype=np.int64)
    n_comp, comp = csgraph.connected_components(graph, directed=False)
    sizes = np.bincount(comp, minlength=n_comp)
    first = np.full(n_comp, -1)
    first[comp[::-1]] = np.arange(n)[::-1]
    next_label = 0
    for c in np.flatnonzero(sizes >= min_size):
        far = csgraph.breadth_first_order(graph, first[c], return_predecessors=False)[-1]
        order = csgraph.breadth_first_order(graph, far, return_predecessors=False)
        for start in range(0, order.size, max_size):
            chunk = order[start : start + max_size]
            if chunk.size >= min_size:
                labels[chunk] = next_label
                next_label += 1
    coo = graph.tocoo()
    same = (labels[coo.row] == labels[coo.col]) & (labels[coo.row] >= 0)
    sub = sp.csr_matrix((np.ones(int(same.sum())), (coo.row[same], coo.col[same])), (n, n))
    _, part = csgraph.connected_components(sub, directed=False)
    part = np.where(labels >= 0, part, -1)
    psize = np.bincount(part[part >= 0], minlength=n)
    keep = (part >= 0) & (psize[np.maximum(part, 0)] >= min_size)
    out = np.full(n, -1, dtype=np.int64)
    out[keep] = np.unique(labels[keep] * (n + 1) + part[keep], return_inverse=True)[1]
    return out


@pytest.mark.parametrize("seed", range(12))
def test_compiled_wavefront_equals_the_csgraph_procedure(seed: int) -> None:
    # Random pixel sets (blobs, strands, specks) at several sizes and both real-frame pixels:
    # the kernel's labels must be those of the scipy procedure, exactly.
    rng = np.random.default_rng(seed)
    if seed < 3:
        st, rel = _stereo_rel(seed)
        pixels = st.pixels[rel.reliable]
    else:
        img = rng.random((60, 80)) < rng.uniform(0.1, 0.6)
        ys, xs = np.nonzero(img)
        pixels = np.stack([xs, ys], axis=1)
    radius = int(rng.integers(1, 4))
    min_size = int(rng.integers(1, 10))
    max_size = int(rng.integers(min_size, 40))
    graph = _neighbour_graph(pixels, radius)
    expected = _reference_wavefront(graph, min_size, max_size)
    labels = _wavefront_kernel(*_neighbour_lists(pixels, radius), min_size, max_size)
    np.testing.assert_array_equal(labels, expected)


@pytest.mark.parametrize("radius", [1, 2, 3])
def test_neighbour_graph_links_pixels_within_manhattan_radius(radius: int) -> None:
    rng = np.random.default_rng(radius)
    ys, xs = np.nonzero(rng.random((40, 50)) < 0.3)
    pixels = np.stack([xs, ys], axis=1) + [7, 3]  # row-major, off the origin
    graph = _neighbour_graph(pixels, radius)
    pairs = cKDTree(pixels).query_pairs(radius + 1e-9, p=1, output_type="ndarray")
    expected = sp.coo_matrix(
        (np.ones(2 * len(pairs)), (pairs.ravel(), pairs[:, ::-1].ravel())), shape=graph.shape
    ).tocsr()
    assert (graph != expected).nnz == 0
    assert np.all(np.diff(graph.indices[graph.indptr[0] : graph.indptr[1]]) > 0)  # sorted


@pytest.mark.parametrize("radius", [1, 2, 4])
def test_neighbour_lists_are_each_pixels_neighbours_in_ascending_order(radius: int) -> None:
    rng = np.random.default_rng(10 + radius)
    ys, xs = np.nonzero(rng.random((30, 45)) < 0.4)
    pixels = np.stack([xs, ys], axis=1)
    indptr, indices = _neighbour_lists(pixels, radius)
    for i, (x, y) in enumerate(pixels):
        dist = np.abs(pixels[:, 0] - x) + np.abs(pixels[:, 1] - y)
        expected = np.flatnonzero((dist <= radius) & (dist > 0))
        np.testing.assert_array_equal(indices[indptr[i] : indptr[i + 1]], expected)
