"""Stages B (voxel means) and C (clusters on the voxel grid) against brute force."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest
from hapticloud.core.errors import ConfigError, InputError
from hapticloud.core.perception.cluster import (
    ClusterConfig,
    ClusterResult,
    cluster_voxels,
    connected_voxels,
)
from hapticloud.core.perception.voxel import VoxelConfig, VoxelResult, voxel_downsample
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

ORIGIN = np.array([0.1, -0.2, 1.1])


def brute_voxels(points: np.ndarray, origin: np.ndarray, size: float):
    """{(i, j, k): (mean, count)} with a plain Python dict."""
    acc: dict[tuple[int, int, int], list] = defaultdict(lambda: [np.zeros(3), 0])
    for p in np.asarray(points, dtype=np.float64):
        if not np.isfinite(p).all():
            continue
        # Same arithmetic as the implementation (multiply by 1/size): on a voxel boundary the
        # two roundings of p / size may fall on either side.
        key = tuple(int(v) for v in np.floor((p - origin) * (1.0 / size)))
        acc[key][0] = acc[key][0] + (p - origin)
        acc[key][1] += 1
    return {k: (s / n + origin, n) for k, (s, n) in acc.items()}


def as_dict(res: VoxelResult):
    return {
        tuple(int(v) for v in ijk): (p, c)
        for ijk, p, c in zip(res.ijk, res.points, res.counts, strict=True)
    }


def check_against_brute(points, origin, size) -> VoxelResult:
    res = voxel_downsample(points, origin, VoxelConfig(voxel_size_m=size))
    ref = brute_voxels(points, np.asarray(origin, float), size)
    got = as_dict(res)
    assert got.keys() == ref.keys()
    for key, (mean, count) in ref.items():
        assert got[key][1] == count
        np.testing.assert_allclose(got[key][0], mean, rtol=0, atol=1e-12)
    return res


# ----- B: voxel ----------------------------------------------------------------------------------


def test_voxel_config() -> None:
    assert 0.003 <= VoxelConfig().voxel_size_m <= 0.004
    with pytest.raises(ConfigError, match="voxel_size_m"):
        VoxelConfig(voxel_size_m=0.0)
    with pytest.raises(ConfigError, match="voxel_size_m"):
        VoxelConfig(voxel_size_m=1.0)


def test_voxel_means_counts_and_coordinates() -> None:
    rng = np.random.default_rng(0)
    pts = ORIGIN + rng.normal(0, 0.03, (3000, 3))
    res = check_against_brute(pts, ORIGIN, 0.0035)
    assert res.points.dtype == np.float64 and res.ijk.dtype == np.int32
    assert res.counts.sum() == 3000 and res.n_input == 3000 and res.n_dropped == 0
    assert len(res) == res.points.shape[0] == res.ijk.shape[0]
    # Each mean lies in its voxel; the output is sorted by voxel (x-major).
    lo = ORIGIN + res.ijk * 0.0035
    assert np.all(res.points >= lo - 1e-12) and np.all(res.points <= lo + 0.0035 + 1e-12)
    keys = [tuple(r) for r in res.ijk]
    assert keys == sorted(keys)
    np.testing.assert_array_equal(res.origin, ORIGIN)


def test_voxel_sparse_path_far_apart_groups() -> None:
    # Two blobs 50 m apart: the bounding grid is huge, the sort-based grouping takes over.
    rng = np.random.default_rng(1)
    pts = np.vstack(
        [rng.normal(0, 0.01, (500, 3)), np.array([50.0, 0, 0]) + rng.normal(0, 0.01, (500, 3))]
    )
    check_against_brute(pts, np.zeros(3), 0.004)
    # Kilometres apart on every axis at a fine voxel: flat keys would overflow int64.
    corners = np.array([[-3000.0, -3000.0, -3000.0], [3000.0, 3000.0, 3000.0], [0.0, 0.0, 0.0]])
    pts = np.vstack([corners, corners + 1e-4])
    res = check_against_brute(pts, np.zeros(3), 0.0005)
    assert len(res) == 3 and cluster_voxels(res, None).n_clusters == 3


def test_voxel_points_on_voxel_faces_use_floor() -> None:
    # 1/16 m is exact in binary: a point on a face belongs to the voxel above it.
    cfg = VoxelConfig(voxel_size_m=0.03125)
    pts = np.array([[0.0, 0.0, 0.0], [0.03125, 0.0, 0.0], [-0.03125, 0.0, 0.0], [0.03, 0.0, 0.0]])
    res = voxel_downsample(pts, np.zeros(3), cfg)
    assert res.ijk[:, 0].tolist() == [-1, 0, 1]
    assert res.counts.tolist() == [1, 2, 1]


def test_voxel_float32_nan_and_far_rows() -> None:
    rng = np.random.default_rng(2)
    pts = (ORIGIN + rng.normal(0, 0.02, (500, 3))).astype(np.float32)
    res32 = voxel_downsample(pts, ORIGIN)
    ref = brute_voxels(pts.astype(np.float64), ORIGIN, VoxelConfig().voxel_size_m)
    assert as_dict(res32).keys() == ref.keys()
    bad = pts.astype(np.float64)
    bad[::10, 0] = np.nan
    bad[1] = [np.inf, 0, 0]
    bad[2] = [1e300, 0, 0]  # would overflow the integer voxel index
    res = voxel_downsample(bad, ORIGIN)
    assert res.n_dropped == 50 + 2 and res.counts.sum() == 500 - res.n_dropped
    assert np.isfinite(res.points).all()


@pytest.mark.parametrize(
    "points",
    [np.empty((0, 3)), np.empty(0), np.full((7, 3), np.nan)],
    ids=["empty", "empty-1d", "all-nan"],
)
def test_voxel_degenerate_inputs(points) -> None:
    res = voxel_downsample(points, ORIGIN)
    assert res.points.shape == (0, 3) and res.ijk.shape == (0, 3) and res.counts.shape == (0,)
    assert cluster_voxels(res, ORIGIN).points.shape == (0, 3)


def test_voxel_single_point_and_errors() -> None:
    res = voxel_downsample([ORIGIN + 0.001], ORIGIN)
    np.testing.assert_allclose(res.points, [ORIGIN + 0.001])
    assert res.ijk.tolist() == [[0, 0, 0]]
    with pytest.raises(ValueError, match="points"):
        voxel_downsample(np.zeros((3, 4)), ORIGIN)
    with pytest.raises(InputError, match="origin"):
        voxel_downsample(np.zeros((3, 3)), [0.0, 0.0])
    with pytest.raises(InputError, match="origin"):
        voxel_downsample(np.zeros((3, 3)), [0.0, 0.0, np.inf])


@settings(max_examples=100, deadline=None)
@given(
    points=hnp.arrays(
        np.float64,
        st.tuples(st.integers(0, 80), st.just(3)),
        elements=st.one_of(st.floats(-0.05, 0.05), st.just(np.nan), st.sampled_from([0.0, 0.01])),
    ),
    size=st.sampled_from([0.001, 0.0035, 0.01]),
)
def test_voxel_properties(points, size) -> None:
    check_against_brute(points, np.zeros(3), size)


# ----- C: cluster --------------------------------------------------------------------------------


def blobs(seed: int = 0) -> np.ndarray:
    """A large surface patch, a smaller separate one and a few isolated outliers (voxel 3.5 mm)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-0.05, 0.05, (6000, 2))
    big = np.c_[u, 0.002 * np.sin(20 * u[:, 0])]
    small = [0.0, 0.0, 0.03] + np.c_[rng.uniform(-0.01, 0.01, (400, 2)), np.zeros(400)]
    outliers = np.array([[0.0, 0.0, 0.06], [0.02, 0.02, 0.08], [-0.03, 0.0, -0.05]])
    return ORIGIN + np.vstack([big, small, outliers])


def brute_components(ijk: np.ndarray, radius: float) -> np.ndarray:
    tree = cKDTree(ijk.astype(float))
    pairs = tree.query_pairs(radius + 1e-9, output_type="ndarray")
    n = len(ijk)
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    pairs = set(zip(a.tolist(), b.tolist(), strict=True))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


def test_cluster_config() -> None:
    cfg = ClusterConfig()
    assert cfg.keep == "all_large" and cfg.neighbour_radius_voxels >= np.sqrt(3)
    with pytest.raises(ConfigError, match="keep"):
        ClusterConfig(keep="biggest")
    with pytest.raises(ConfigError, match="min_cluster_points"):
        ClusterConfig(min_cluster_points=0)
    with pytest.raises(ConfigError, match="neighbour_radius_voxels"):
        ClusterConfig(neighbour_radius_voxels=0.5)


def test_cluster_keeps_large_and_rejects_small() -> None:
    vox = voxel_downsample(blobs(), ORIGIN)
    res = cluster_voxels(vox, ORIGIN, ClusterConfig(min_cluster_points=10))
    assert isinstance(res, ClusterResult)
    assert res.n_clusters == 5
    assert list(res.cluster_sizes[2:]) == [1, 1, 1]
    assert res.cluster_sizes[0] > res.cluster_sizes[1] > 10
    assert res.kept_clusters == (0, 1)
    assert len(res.points) == res.cluster_sizes[:2].sum() and len(res.rejected) == 3
    assert res.kept.sum() == len(res.points) and len(res.labels) == len(vox)
    np.testing.assert_array_equal(res.points, vox.points[res.kept])
    np.testing.assert_array_equal(res.rejected, vox.points[~res.kept])
    np.testing.assert_array_equal(np.bincount(res.labels), res.cluster_sizes)


def test_cluster_keep_policies() -> None:
    vox = voxel_downsample(blobs(), ORIGIN)
    largest = cluster_voxels(vox, None, ClusterConfig(keep="largest"))
    assert largest.kept_clusters == (0,)
    # The small patch sits at z = +3 cm: a HIP above it picks it, a HIP below the big one that.
    above = cluster_voxels(
        vox, ORIGIN + np.array([0.0, 0.0, 0.045]), ClusterConfig(keep="nearest_to_hip")
    )
    assert above.kept_clusters == (1,)
    below = cluster_voxels(
        vox, ORIGIN + np.array([0.0, 0.0, -0.02]), ClusterConfig(keep="nearest_to_hip")
    )
    assert below.kept_clusters == (0,)
    # Outliers nearer the HIP than any large cluster are not chosen.
    near_outlier = cluster_voxels(
        vox, ORIGIN + np.array([0.0, 0.0, 0.061]), ClusterConfig(keep="nearest_to_hip")
    )
    assert near_outlier.kept_clusters == (1,)
    with pytest.raises(InputError, match="hip"):
        cluster_voxels(vox, None, ClusterConfig(keep="nearest_to_hip"))


def test_cluster_nothing_large_enough() -> None:
    vox = voxel_downsample(blobs(), ORIGIN)
    res = cluster_voxels(vox, ORIGIN, ClusterConfig(min_cluster_points=1_000_000))
    assert res.points.shape == (0, 3) and len(res.rejected) == len(vox) and res.kept_clusters == ()


@pytest.mark.parametrize(("radius", "expected"), [(1.0, 3), (1.5, 2), (1.75, 1)])
def test_cluster_neighbour_radius_sets_connectivity(radius, expected) -> None:
    # (0,0,0)-(1,1,0) touch by an edge, (1,1,0)-(2,2,1)... by a corner.
    ijk = np.array([[0, 0, 0], [1, 1, 0], [2, 2, 1]], dtype=np.int32)
    n, labels = connected_voxels(ijk, radius)
    assert n == expected and labels.shape == (3,)


def test_cluster_degenerate_and_errors() -> None:
    one = voxel_downsample([ORIGIN], ORIGIN)
    res = cluster_voxels(one, ORIGIN, ClusterConfig(min_cluster_points=1))
    assert len(res.points) == 1 and res.n_clusters == 1
    res = cluster_voxels(one, ORIGIN)  # default minimum > 1
    assert len(res.points) == 0 and len(res.rejected) == 1
    with pytest.raises(InputError, match="voxels"):
        cluster_voxels(np.zeros((3, 3)), ORIGIN)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="hip"):
        cluster_voxels(one, [0.0, 1.0])
    assert connected_voxels(np.empty((0, 3), dtype=np.int32))[0] == 0


def test_cluster_spread_out_voxels_use_sorted_lookup() -> None:
    # A handful of voxels spanning millions of cells: the sorted-key path.
    ijk = np.array([[0, 0, 0], [1, 0, 0], [5000, 0, 0], [5000, 1, 1], [0, 4000, 9000]])
    n, labels = connected_voxels(ijk, 1.75)
    assert n == 3 and labels[0] == labels[1] and labels[2] == labels[3] != labels[0]
    # Spans whose flat keys would overflow int64 (~2**30 voxels on every axis).
    big = 2**29
    ijk = np.array([[-big, -big, -big], [-big + 1, -big, -big], [big, big, big], [0, 0, 0]])
    n, labels = connected_voxels(ijk, 1.75)
    assert n == 3 and labels[0] == labels[1] and len(set(labels[1:].tolist())) == 3
    with pytest.raises(InputError, match="ijk"):
        connected_voxels(np.zeros((3, 2), dtype=int))
    with pytest.raises(InputError, match="ijk"):
        connected_voxels(np.zeros((3, 3)))
    with pytest.raises(InputError, match="radius_voxels"):
        connected_voxels(ijk, 0.5)


@settings(max_examples=100, deadline=None)
@given(
    cells=hnp.arrays(
        np.int32, st.tuples(st.integers(1, 60), st.just(3)), elements=st.integers(-6, 6)
    ),
    radius=st.sampled_from([1.0, 1.5, 1.75, 2.0, 2.5, 3.2]),
    far=st.booleans(),
)
def test_connected_voxels_matches_kdtree(cells, radius, far) -> None:
    ijk = np.unique(cells, axis=0)
    if far:  # push one voxel far away to exercise the sparse path
        ijk[0] = [900_000, 0, 0]
    n, labels = connected_voxels(ijk, radius)
    ref = brute_components(ijk, radius)
    assert n == len(set(ref.tolist()))
    assert same_partition(labels, ref)
