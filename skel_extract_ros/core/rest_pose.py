"""The rest pose Q (paper Sec. 4, end): a clean, evenly spread point set of one frame (the
paper's first; which frame: core.stream.FrameRegistrar).

A frame's points are noisy and unevenly spread (dense near the camera, holes,
flying pixels), so the paper reconstructs a surface and resamples it. Here: normals from
local PCA oriented towards the camera, Open3D screened Poisson reconstruction, the mesh
trimmed where Poisson invented surface far from the data (low density or far from every
input point: a single view gives an open surface that Poisson closes with a balloon), then
Poisson-disk resampling to exactly M points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .parameters import INF, parameter, validate
from .point_sets import finite_rows, median_spacing


class RestPoseError(ValueError):
    """The first frame cannot give a rest pose (too few points, degenerate surface)."""


@dataclass
class RestPoseParams:
    """Rest-pose parameters (the reconstruction in the module docstring)."""

    n_points: int = parameter(2000, 'M, the rest points = the registered points per frame', 100, 1_000_000)
    choice_frames: int = parameter(60, 'the rest pose is built from the most spread-out subject (RMS distance '
                                   'of its points from their centroid) among this many consecutive frames from '
                                   'the first one where it is wholly in view, and those frames are registered '
                                   'backward and forward from it; 1 = the first frame (the paper)', 1, 100_000)
    poisson_depth: int = parameter(8, 'octree depth of the Poisson reconstruction of the rest pose', 4, 12)
    density_quantile: float = parameter(0.05, 'Poisson vertices below this quantile of the Poisson density are '
                                        'trimmed, a fraction', 0.0, 1.0)
    max_distance_factor: float = parameter(2.0, 'surface farther than this many median input point spacings '
                                           'from every input point is trimmed, dimensionless', 0.0, INF)
    normal_neighbours: int = parameter(20, 'neighbours for normal estimation, points', 3, 200)
    camera_location: tuple = parameter((0.0, 0.0, 0.0), '[x, y, z] m, the sensor origin in the cloud frame '
                                       '(normals are oriented towards it)', size=3)
    poisson_threads: int = parameter(1, 'threads of the Poisson solver; 1 = repeatable rest pose, and so every '
                                     "later result (Open3D's multi-threaded solver is not deterministic), "
                                     '-1 = all cores', -1, 256)

    def __post_init__(self):
        validate(self)


def spread(points: np.ndarray) -> float:
    """RMS distance (m) of the points (N, 3) from their centroid (NaN rows ignored; 0 for
    none): how far the subject's parts are from one another. The deformation graph is
    built on the rest pose by distance, so parts touching there (an arm along the torso,
    the legs together) are tied, and the ties hold them together when they later part; of
    a few frames of a subject, the most spread-out has the fewest such contacts."""
    points = np.asarray(points, dtype=np.float64)
    points = points[finite_rows(points)]
    if len(points) == 0:
        return 0.0
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


@dataclass
class RestPose:
    """points: (M, 3) rest points Q (metres); mesh_vertices/mesh_triangles: trimmed surface."""

    points: np.ndarray
    mesh_vertices: np.ndarray
    mesh_triangles: np.ndarray

    @classmethod
    def from_points(cls, points: np.ndarray, params: RestPoseParams | None = None,
                    seed: int = 0) -> 'RestPose':
        """Reconstruct and resample the rest pose from one frame's cleaned points (N, 3)."""
        import open3d as o3d  # lazy: the accumulator and joint nodes never load it
        params = params or RestPoseParams()
        points = np.asarray(points, dtype=np.float64)
        points = points[finite_rows(points)]
        if len(points) < max(100, params.n_points // 10):
            raise RestPoseError(f'the frame has only {len(points)} usable points; '
                                'a rest pose needs at least a few hundred')
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(params.normal_neighbours))
        cloud.orient_normals_towards_camera_location(np.asarray(params.camera_location, dtype=np.float64))
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                cloud, depth=params.poisson_depth, n_threads=params.poisson_threads)
        densities = np.asarray(densities)
        vertices = np.asarray(mesh.vertices)
        spacing = median_spacing(points)
        distance, _ = cKDTree(points).query(vertices)
        remove = (densities < np.quantile(densities, params.density_quantile)) | \
                 (distance > params.max_distance_factor * max(spacing, 1e-6))
        mesh.remove_vertices_by_mask(remove)
        mesh.remove_degenerate_triangles()
        mesh.remove_unreferenced_vertices()
        if len(mesh.triangles) < 50:
            raise RestPoseError('the surface reconstructed from the frame is degenerate '
                                f'({len(mesh.triangles)} triangles left after trimming)')
        o3d.utility.random.seed(seed)
        sampled = mesh.sample_points_poisson_disk(params.n_points, init_factor=5)
        rest = np.asarray(sampled.points)
        if len(rest) != params.n_points:
            raise RestPoseError(f'resampling gave {len(rest)} points instead of {params.n_points}')
        return cls(rest, np.asarray(mesh.vertices), np.asarray(mesh.triangles))

    @classmethod
    def from_raw(cls, points: np.ndarray, n_points: int, seed: int = 0) -> 'RestPose':
        """Baseline without reconstruction: M points picked from the frame by farthest-point
        sampling (used to measure what the reconstruction buys)."""
        import open3d as o3d  # lazy: the accumulator and joint nodes never load it
        points = np.asarray(points, dtype=np.float64)
        points = points[finite_rows(points)]
        if len(points) < n_points:
            raise RestPoseError(f'the first frame has {len(points)} points, fewer than M = {n_points}')
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        rest = np.asarray(cloud.farthest_point_down_sample(n_points).points)
        return cls(rest, np.empty((0, 3)), np.empty((0, 3), dtype=np.int64))
