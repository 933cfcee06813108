"""Clouds without a pixel grid: planes, DBSCAN regions and nearest-neighbour motion on a
voxel grid."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..point_sets import voxel_centroids
from .params import STATUS_NOBODY, STATUS_SUBJECT, Segmentation


class UnorganizedSegmentation:
    """Mixin of SubjectSegmenter for unorganized clouds."""

    def _unorganized(self, points: np.ndarray, valid: np.ndarray) -> Segmentation:
        """Planes, DBSCAN regions and nearest-neighbour motion on a voxel grid."""
        import open3d as o3d  # lazy, for DBSCAN: organized clouds never load it (core/point_sets.py)
        p = self.params
        finite = points[valid]
        if len(finite) < p.min_subject_points:
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        extent = float(np.linalg.norm(np.ptp(finite, axis=0)))
        voxel = max(extent / 150.0, 0.01)
        down = voxel_centroids(finite, voxel)
        c = self._update_noise(None)
        sigma = c * down[:, 2] ** 2
        if self._frames_since_planes is None or self._frames_since_planes >= p.plane_refresh:
            self._planes, noise = self._fit_planes(down)
            self._update_noise(noise)
            self._frames_since_planes = 0
        self._frames_since_planes += 1
        keep = ~self._on_planes(down, sigma)
        candidates = down[keep]
        if len(candidates) < 10:
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        labels = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidates))
                            .cluster_dbscan(eps=3.0 * voxel, min_points=4))
        moved = np.zeros(len(candidates), dtype=bool)
        if self._previous_points is not None and len(self._previous_points):
            distance, _ = cKDTree(self._previous_points).query(candidates)
            moved = distance > max(p.noise_sigmas * float(np.median(sigma)), 1.5 * voxel)
        near_subject = np.zeros(len(candidates), dtype=bool)
        if self._previous_subject is not None and len(self._previous_subject):
            distance, _ = cKDTree(self._previous_subject).query(candidates)
            near_subject = distance <= 2.0 * voxel
        self._previous_points = down
        n_regions = int(labels.max()) + 1 if len(labels) else 0
        if n_regions == 0:
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        in_region = labels >= 0
        sizes = np.bincount(labels[in_region], minlength=n_regions)
        motion = np.bincount(labels[in_region], weights=moved[in_region], minlength=n_regions)
        overlap = np.bincount(labels[in_region], weights=near_subject[in_region], minlength=n_regions)
        moving = motion >= np.maximum(5.0, 0.05 * sizes)
        eligible = moving | (overlap >= 0.3 * sizes)
        if not eligible.any():
            self._previous_subject = None
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        primary = int(np.argmax(np.where(eligible, motion + 10.0 * overlap, -1.0)))
        subject_down = candidates[labels == primary]
        self._previous_subject = subject_down
        # every input point takes the label of its nearest subsampled candidate
        distance, _ = cKDTree(subject_down).query(finite, distance_upper_bound=1.5 * voxel)
        mask = np.zeros(len(points), dtype=bool)
        mask[np.flatnonzero(valid)[np.isfinite(distance)]] = True
        if mask.sum() < p.min_subject_points:
            return Segmentation(np.zeros(len(points), bool), STATUS_NOBODY, int(valid.sum()))
        n_moving = int(moving.sum())
        return Segmentation(mask, STATUS_SUBJECT, int(valid.sum()), n_moving, False, c, len(self._planes))
