"""Closed triangle meshes of the primitive shapes, and even surface samples on them."""
from __future__ import annotations

import numpy as np
import open3d as o3d

from .subjects import Capsule, Ellipsoid

_SPHERE_RESOLUTION = 14


def _unit_sphere():
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=_SPHERE_RESOLUTION)
    return np.asarray(sphere.vertices).copy(), np.asarray(sphere.triangles).copy()


def _rotation_from_z(direction: np.ndarray) -> np.ndarray:
    """Rotation taking +z onto the unit vector `direction`."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, direction)
    c = float(np.dot(z, direction))
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def shape_mesh(shape) -> tuple:
    """(vertices (V, 3), triangles (T, 3)) of a Capsule or Ellipsoid, bone-local metres."""
    vertices, triangles = _unit_sphere()
    if isinstance(shape, Ellipsoid):
        return vertices * np.asarray(shape.radii) + np.asarray(shape.center), triangles
    if isinstance(shape, Capsule):
        start, end = np.asarray(shape.start, float), np.asarray(shape.end, float)
        axis = end - start
        length = float(np.linalg.norm(axis))
        # Stretch a sphere along z: the two hemispheres become the caps, the band of
        # triangles across the equator becomes the cylinder.
        vertices = vertices * shape.radius
        vertices[:, 2] += np.sign(np.round(vertices[:, 2], 12)) * length / 2.0
        rotation = _rotation_from_z(axis / length) if length > 0 else np.eye(3)
        return vertices @ rotation.T + (start + end) / 2.0, triangles
    raise TypeError(f'unsupported shape {shape!r}')


def capsule_mesh(start, end, radius: float) -> tuple:
    """(vertices (V, 3), triangles (T, 3)) of a capsule from `start` to `end`, metres."""
    return shape_mesh(Capsule(tuple(np.asarray(start, float)), tuple(np.asarray(end, float)), float(radius)))


def ellipsoid_mesh(center, axes: np.ndarray, radii) -> tuple:
    """(vertices, triangles) of an ellipsoid with semi-axes `radii` (3,) along the rows of
    `axes` (3, 3, orthonormal), centred at `center` (3,)."""
    vertices, triangles = _unit_sphere()
    return (vertices * np.asarray(radii, float)) @ np.asarray(axes, float) + np.asarray(center, float), triangles


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, count: int,
                   rng: np.random.Generator) -> np.ndarray:
    """(count, 3) points drawn uniformly by area over a triangle mesh."""
    corners = vertices[triangles]
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                          corners[:, 2] - corners[:, 0]), axis=1)
    chosen = rng.choice(len(triangles), size=count, p=areas / areas.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    a, b, c = 1.0 - s, s * (1.0 - r2), s * r2
    tri = corners[chosen]
    return a[:, None] * tri[:, 0] + b[:, None] * tri[:, 1] + c[:, None] * tri[:, 2]


def mesh_area(vertices: np.ndarray, triangles: np.ndarray) -> float:
    corners = vertices[triangles]
    return float(0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                               corners[:, 2] - corners[:, 0]), axis=1).sum())


def inside_any(points: np.ndarray, meshes) -> np.ndarray:
    """(N,) bool: which points lie inside at least one of the closed meshes."""
    if not meshes:
        return np.zeros(len(points), dtype=bool)
    scene = o3d.t.geometry.RaycastingScene()
    for vertices, triangles in meshes:
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                            o3d.core.Tensor(triangles.astype(np.uint32)))
    occupancy = scene.compute_occupancy(o3d.core.Tensor(points.astype(np.float32)))
    return occupancy.numpy() > 0.5
