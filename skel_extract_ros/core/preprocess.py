"""Per-frame cleaning of depth point clouds: raw (N, 3) points in, subject points out.

Steps, in order, each switchable: drop NaN/inf; crop box; voxel downsampling to about
`target_points` (the voxel size adapts from frame to frame); removal of the dominant plane
(floor, table); keep the largest Euclidean cluster; statistical outlier removal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .parameters import parameter, validate
from .point_sets import finite_rows, ransac_plane, statistical_inliers, voxel_centroids


class PreprocessError(ValueError):
    """Input that cannot be preprocessed; the message says why in one line."""


@dataclass
class PreprocessParams:
    """Preprocessing parameters (the steps in the module docstring)."""

    crop_min: tuple | None = parameter(None, '[x, y, z] m, lower corner of an axis-aligned crop box in the '
                                       'cloud frame; [] = no crop', size=3)
    crop_max: tuple | None = parameter(None, '[x, y, z] m, upper corner of the crop box; [] = no crop', size=3)
    target_points: int = parameter(5000, 'voxel downsampling aims at about this many points per frame; '
                                   '0 = no downsampling', 0, 10_000_000)
    initial_voxel_size: float = parameter(0.01, 'first voxel size tried, m (later frames reuse the last, '
                                          'adapted one)', 1e-4, 1.0)
    max_input_points: int = parameter(400_000, 'larger clouds are randomly thinned to this many points first '
                                      '(bounded time for a runaway driver setting)', 1000, 100_000_000)
    remove_plane: bool = parameter(False, 'remove the largest plane (floor, wall, table) if it holds '
                                   'plane_min_fraction of the points')
    plane_distance: float = parameter(0.02, 'RANSAC plane inlier distance, m', 1e-4, 1.0)
    plane_min_fraction: float = parameter(0.2, 'only a plane holding this share of the points is removed, '
                                          'a fraction', 0.0, 1.0)
    keep_largest_cluster: bool = parameter(False, 'keep only the largest Euclidean (DBSCAN) cluster, the '
                                           'subject')
    cluster_eps: float = parameter(0.05, 'cluster neighbour distance, m', 1e-4, 10.0)
    cluster_min_points: int = parameter(10, 'smallest cluster, points', 1, 1_000_000)
    outlier_neighbours: int = parameter(16, 'statistical outlier removal neighbours, points; 0 = off', 0, 200)
    outlier_std_ratio: float = parameter(2.0, 'statistical outlier removal threshold, standard deviations',
                                         0.1, 100.0)
    seed: int = parameter(0, 'seed of the random thinning', 0, 2**31 - 1)

    def __post_init__(self):
        validate(self)


class Preprocessor:
    """Stateful per-frame preprocessing (keeps the adapted voxel size between frames)."""

    def __init__(self, params: PreprocessParams | None = None):
        self.params = params or PreprocessParams()
        self.voxel_size = self.params.initial_voxel_size
        self._rng = np.random.default_rng(self.params.seed)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) raw points (NaN allowed) -> (K, 3) float64 clean points; K may be 0."""
        p = self.params
        points = np.asarray(points)
        if points.ndim != 2 or points.shape[1] != 3:
            raise PreprocessError(f'points must be an (N, 3) array, got shape {points.shape}')
        points = points[finite_rows(points)].astype(np.float64, copy=False)
        if len(points) > p.max_input_points:
            points = points[self._rng.choice(len(points), p.max_input_points, replace=False)]
        if p.crop_min is not None or p.crop_max is not None:
            low = np.asarray(p.crop_min if p.crop_min is not None else (-np.inf,) * 3)
            high = np.asarray(p.crop_max if p.crop_max is not None else (np.inf,) * 3)
            points = points[np.all((points >= low) & (points <= high), axis=1)]
        if len(points) == 0:
            return points.reshape(0, 3)
        if p.target_points > 0 and len(points) > p.target_points:
            points = self._downsample(points)
        if p.remove_plane and len(points) >= 3 * 10:
            plane = ransac_plane(points, p.plane_distance, 200, self._rng)
            if plane is not None and len(plane[2]) >= p.plane_min_fraction * len(points):
                points = np.delete(points, plane[2], axis=0)
        if p.keep_largest_cluster and len(points) > p.cluster_min_points:
            import open3d as o3d  # lazy, and only for this option: 170 MB (core/point_sets.py)
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            labels = np.asarray(cloud.cluster_dbscan(p.cluster_eps, p.cluster_min_points))
            if (labels >= 0).any():
                points = points[labels == np.bincount(labels[labels >= 0]).argmax()]
        if p.outlier_neighbours > 0 and len(points) > p.outlier_neighbours:
            points = points[statistical_inliers(points, p.outlier_neighbours, p.outlier_std_ratio)]
        return points

    def _downsample(self, points: np.ndarray) -> np.ndarray:
        """Voxel-downsample (N, 3) points to within 25 % of target_points, adapting the voxel size.

        Points on a surface scale with 1 / voxel^2, so each retry rescales by sqrt(ratio).
        """
        target = self.params.target_points
        best = None
        for _ in range(4):
            best = voxel_centroids(points, self.voxel_size)
            ratio = len(best) / target
            if 0.8 <= ratio <= 1.25:
                break
            self.voxel_size = float(np.clip(self.voxel_size * np.sqrt(ratio), 1e-4, 1.0))
        return best
