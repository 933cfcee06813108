"""The point-set operations of the per-frame path, in numpy / scipy: voxel-grid centroids,
statistical outlier removal, a RANSAC plane, the k nearest neighbours within a radius,
and the strided subsets the per-frame steps sample their points with.

Open3D does each of them well, but importing it costs a process about 170 MB resident,
and the registration node needs these three for every camera frame, for as long as it
runs. Written here to give the same results as Open3D's `voxel_down_sample`,
`remove_statistical_outlier` and `segment_plane` (same definitions, tested against
them), so that Open3D is loaded only where nothing else will do: the Poisson rest pose
(built in a short-lived process by the node), DBSCAN for unorganized clouds and the
non-default preprocessing options.
"""
from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree


def finite_rows(points: np.ndarray) -> np.ndarray:
    """(N,) bool: the rows of points (N, 3) whose three coordinates are finite. The sum of
    the columns is finite exactly then (NaN and inf propagate; only a sum beyond the
    float's range, coordinates of 1e38 m, would also count as not finite), and is much
    faster than `np.isfinite(points).all(axis=1)`, which reduces along the short axis."""
    points = np.asarray(points)
    return np.isfinite(points[:, 0] + points[:, 1] + points[:, 2])


def subset_stride(count: int, at_most: int) -> int:
    """The smallest stride (>= 1) that leaves at most `at_most` of `count` rows: the cap on
    the points a per-frame step samples. A stride keeps every region's share, because the
    model's and the camera's points come in no spatial order that one would bias."""
    return max(1, -(-int(count) // max(1, int(at_most))))


def strided_subset(rows: np.ndarray, at_most: int) -> np.ndarray:
    """rows (N, ...) taken at `subset_stride`: at most `at_most` of them, evenly spread."""
    return rows[::subset_stride(len(rows), at_most)]


def nearest_within(queries: np.ndarray, points: np.ndarray, k: int, radius: float = np.inf) -> tuple:
    """Each query's k nearest points within `radius` (m): (distances (N, k') m, inf where
    none; indices (N, k') int64, M where none), k' = min(k, M), for queries (N, 3) and points
    (M, 3). The k-d tree is over `points` and built per call.

    pykdtree, not scipy's cKDTree: the same neighbours (M and inf where none, as scipy)
    built and queried in less time, and this runs in every EM iteration and every live
    frame. Its OpenMP team uses every core unless limited; the nodes keep it to one thread
    (nodes/__init__.py)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    queries = np.ascontiguousarray(queries, dtype=np.float64)
    count, K = len(queries), min(int(k), len(points))
    distances, indices = KDTree(points).query(queries, k=K, distance_upper_bound=radius)
    return distances.reshape(count, K), indices.reshape(count, K).astype(np.int64)


def median_spacing(points: np.ndarray) -> float:
    """Median distance (m) from each of the points (N, 3) to its nearest other point: the
    sampling scale of a point set, which thresholds across the method are measured in."""
    distances, _ = cKDTree(points).query(points, k=2)
    return float(np.median(distances[:, 1]))


def voxel_centroids(points: np.ndarray, size: float) -> np.ndarray:
    """(N, 3) points -> (K, 3) the mean of the points in each occupied cube of edge `size` m
    (the grid starts half a cube below the points' minimum, as Open3D's), in the order of
    the cubes' indices."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return points.reshape(0, 3)
    origin = points.min(axis=0) - 0.5 * size
    cells = np.floor((points - origin) / size).astype(np.int64)
    keys = np.ravel_multi_index(cells.T, tuple(cells.max(axis=0) + 1))
    _, cube, counts = np.unique(keys, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(cube, weights=points[:, axis], minlength=len(counts)) for axis in range(3)],
                    axis=1)
    return sums / counts[:, None]


def statistical_inliers(points: np.ndarray, neighbours: int, std_ratio: float) -> np.ndarray:
    """(N,) bool: the points (N, 3) whose mean distance to their `neighbours` nearest points
    (the point itself among them, as in Open3D and PCL) is below the mean of those
    distances over the cloud plus `std_ratio` standard deviations."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) <= neighbours:
        return np.ones(len(points), dtype=bool)
    # pykdtree, not scipy's cKDTree: the same distances in less time on the one thread the
    # nodes give it, and this runs for every camera frame
    distances, _ = KDTree(points).query(points, k=neighbours)
    mean = distances.mean(axis=1)
    threshold = mean.mean() + std_ratio * mean.std(ddof=1)
    return (mean > 0.0) & (mean < threshold)


def ransac_plane(points: np.ndarray, distance: float, iterations: int, rng: np.random.Generator,
                 score_points: int = 4000, rerank: int = 20) -> tuple:
    """The plane with the most points (K, 3) within `distance` m: (normal (3,) unit, d, inlier
    indices) with normal . x + d = 0, or None for fewer than 3 points.

    `iterations` planes through three random points are scored on `score_points` of the
    points at most (a random subset), the `rerank` best of them on all points (the subset's
    winner alone can be another plane than the full count's, and so change the
    segmentation); the inliers are the best plane's among all points, and the plane returned
    is the least-squares fit to them, as Open3D does. The inliers are not counted again
    with the refined plane: a floor refitted to them takes in the subject's feet.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        return None
    triples = points[rng.integers(0, len(points), size=(iterations, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    usable = lengths > 1e-12
    if not usable.any():
        return None
    normals = normals[usable] / lengths[usable, None]
    offsets = -np.einsum('ij,ij->i', normals, triples[usable, 0])
    scored = points if len(points) <= score_points else points[rng.choice(len(points), score_points,
                                                                         replace=False)]
    counts = (np.abs(scored @ normals.T + offsets) < distance).sum(axis=0)
    # the leaders on the subset are counted again on every point: the winner is then the
    # plane the full count would choose (unless it ranked below them on the subset)
    leaders = np.argsort(counts)[-min(rerank, len(counts)):]
    full_counts = (np.abs(points @ normals[leaders].T + offsets[leaders]) < distance).sum(axis=0)
    best = int(leaders[np.argmax(full_counts)])
    normal, offset = normals[best], offsets[best]
    inliers = np.flatnonzero(np.abs(points @ normal + offset) < distance)
    if len(inliers) >= 3:
        centroid = points[inliers].mean(axis=0)
        normal = np.linalg.svd(points[inliers] - centroid, full_matrices=False)[2][2]
        offset = -float(normal @ centroid)
    return normal, float(offset), inliers
