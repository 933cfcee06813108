"""The per-frame point-set operations give what Open3D gives (they replace it in the nodes
to keep its 170 MB out of the registration node)."""
import numpy as np
import open3d as o3d
import pytest

from scipy.spatial import cKDTree

from skel_extract_ros.core.point_sets import (finite_rows, nearest_within, ransac_plane, statistical_inliers,
                                              strided_subset, subset_stride, voxel_centroids)


def _surface_with_flying_pixels(seed=0, n=5000, flying=60):
    """A bent sheet 1.7 x 0.5 m at 2.5 m and `flying` points scattered in front of it."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(size=(n, 2))
    sheet = np.column_stack([0.5 * u[:, 0], 1.7 * u[:, 1], 2.5 + 0.05 * np.sin(6 * u[:, 0])])
    stray = rng.uniform([-0.2, -0.2, 1.5], [0.7, 1.9, 2.4], size=(flying, 3))
    return np.vstack([sheet + rng.normal(scale=0.002, size=sheet.shape), stray]), n


def _cloud(points):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


@pytest.mark.parametrize('size', [0.004, 0.013, 0.05])
def test_voxel_centroids_are_open3d_s(size):
    points, _ = _surface_with_flying_pixels()
    ours = voxel_centroids(points, size)
    theirs = np.asarray(_cloud(points).voxel_down_sample(size).points)
    assert len(ours) == len(theirs) and len(ours) < len(points)
    order = lambda p: p[np.lexsort(p.T)]                    # noqa: E731 (Open3D's order is its hash map's)
    np.testing.assert_allclose(order(ours), order(theirs), atol=1e-12)
    assert voxel_centroids(np.empty((0, 3)), size).shape == (0, 3)


def test_statistical_inliers_are_open3d_s_and_drop_the_flying_pixels():
    points, n_surface = _surface_with_flying_pixels()
    keep = statistical_inliers(points, 16, 2.0)
    _, kept = _cloud(points).remove_statistical_outlier(16, 2.0)
    np.testing.assert_array_equal(np.flatnonzero(keep), np.sort(np.asarray(kept)))
    assert keep[:n_surface].mean() > 0.99 and keep[n_surface:].mean() < 0.2
    assert statistical_inliers(points[:10], 16, 2.0).all()   # too few to judge: all kept


def test_ransac_plane_finds_the_floor_as_open3d_does():
    rng = np.random.default_rng(1)
    floor = np.column_stack([rng.uniform(-2, 2, 12000), np.full(12000, 1.2), rng.uniform(1, 5, 12000)])
    floor += rng.normal(scale=0.004, size=floor.shape)
    clutter = rng.uniform([-2, -1, 1], [2, 1.1, 5], size=(8000, 3))      # above the floor
    points = rng.permutation(np.vstack([floor, clutter]))
    normal, offset, inliers = ransac_plane(points, 0.02, 300, np.random.default_rng(0))
    assert abs(abs(normal[1]) - 1.0) < 1e-3 and abs(abs(offset) - 1.2) < 2e-3
    on_floor = np.abs(points[:, 1] - 1.2) < 0.02
    # the inliers are the RANSAC plane's, the plane their least-squares fit (as Open3D's)
    assert np.abs(points[inliers] @ normal + offset).max() < 0.03
    assert len(inliers) >= on_floor.sum() - 50
    _, theirs = _cloud(points).segment_plane(0.02, 3, 300)
    assert abs(len(inliers) - len(theirs)) <= 0.01 * len(theirs)
    assert ransac_plane(points[:2], 0.02, 10, np.random.default_rng(0)) is None


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_finite_rows_is_isfinite_all(dtype):
    rng = np.random.default_rng(3)
    points = rng.normal(size=(3000, 3)).astype(dtype)
    bad = rng.integers(0, 3000, size=(300, 2))
    points[bad[:, 0], bad[:, 1] % 3] = rng.choice([np.nan, np.inf, -np.inf], size=300)
    points[7] = [np.inf, -np.inf, 1.0]          # inf - inf: the sum is NaN, still not finite
    expected = np.isfinite(points).all(axis=1)
    assert not expected.all() and expected.any()
    np.testing.assert_array_equal(finite_rows(points), expected)
    assert finite_rows(points[:0]).shape == (0,)


@pytest.mark.parametrize('count', [0, 1, 999, 1000, 1001, 2999, 3000, 3001, 54321])
def test_strided_subset_keeps_at_most_the_cap_and_as_many_as_a_stride_allows(count):
    rows = np.arange(count)
    subset = strided_subset(rows, 1000)
    assert len(subset) <= 1000
    assert len(subset) == len(rows[::subset_stride(count, 1000)])
    # the smallest such stride: one less would keep more than the cap
    stride = subset_stride(count, 1000)
    assert stride == 1 or len(rows[::stride - 1]) > 1000
    np.testing.assert_array_equal(subset, rows[::stride])


@pytest.mark.parametrize('k, radius', [(1, np.inf), (8, 0.05), (8, np.inf), (50, 0.02)])
def test_nearest_within_is_scipys_query(k, radius):
    """The same neighbours as scipy's cKDTree, with its conventions: inf and M where fewer
    than k lie within the radius, and k capped at M (here 40 points)."""
    rng = np.random.default_rng(5)
    points, queries = rng.normal(scale=0.1, size=(40, 3)), rng.normal(scale=0.1, size=(300, 3))
    distances, indices = nearest_within(queries, points, k, radius)
    K = min(k, len(points))
    theirs_distances, theirs_indices = cKDTree(points).query(queries, k=K, distance_upper_bound=radius)
    assert distances.shape == indices.shape == (300, K) and indices.dtype == np.int64
    np.testing.assert_allclose(distances, theirs_distances.reshape(300, K))
    np.testing.assert_array_equal(indices, theirs_indices.reshape(300, K))
    assert radius == np.inf or (indices == len(points)).any()
