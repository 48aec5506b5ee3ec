"""Tests of core/clustering.py: BFS clusters of reliable pixels and their centroids."""

from dataclasses import replace

import numpy as np
import pytest
from support import assert_close, synthetic_case

from threadrecon.core.clustering import ClusterParams, cluster_keypoints
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
