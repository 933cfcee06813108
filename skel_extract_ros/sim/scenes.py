"""What else a depth camera in a room sees, placed around a moving body so that none of it
touches or hides the body: a floor, walls, a table and a second still object.

Everything is built from the space the body moves through (all frames) and the camera's
position, so the same scene works for a person waving on the spot, a person walking across
the room, a hand or a cow.
"""
from __future__ import annotations

import numpy as np
import open3d as o3d

from .animated import AnimatedBody

SCENES = ('empty', 'floor', 'room')
_UP = np.array([0.0, 1.0, 0.0])


def _box(size, centre, axes) -> tuple:
    """(vertices, triangles) of a box with edge lengths `size` (3,) along the rows of `axes`
    (3, 3: right, up, towards the camera), centred at `centre` (3,)."""
    box = o3d.geometry.TriangleMesh.create_box(*size)
    vertices = np.asarray(box.vertices) - np.asarray(size) / 2.0
    return vertices @ np.asarray(axes) + np.asarray(centre), np.asarray(box.triangles).copy()


def _cylinder(radius, height, base, axes) -> tuple:
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius=radius, height=height, resolution=24)
    # Open3D's cylinder runs along z, centred at the origin: stand it up along `up`.
    vertices = np.asarray(mesh.vertices)[:, [0, 2, 1]] + [0.0, height / 2.0, 0.0]
    return vertices @ np.asarray(axes) + np.asarray(base), np.asarray(mesh.triangles)[:, [0, 2, 1]].copy()


def body_extent(body: AnimatedBody, stride: int = 3):
    """World (min (3,), max (3,)) of the body's surface over every `stride`-th frame, m."""
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    for f in range(0, body.n_frames, stride):
        vertices = np.concatenate([v for v, _ in body.world_meshes(f)])
        low, high = np.minimum(low, vertices.min(axis=0)), np.maximum(high, vertices.max(axis=0))
    return low, high


def view_axes(body_centre: np.ndarray, camera_from_world: np.ndarray) -> np.ndarray:
    """(3, 3) rows: right, up and towards the camera (horizontal), as seen from the camera."""
    eye = -camera_from_world[:3, :3].T @ camera_from_world[:3, 3]
    towards = (eye - body_centre) * [1.0, 0.0, 1.0]
    towards /= np.linalg.norm(towards)
    right = np.cross(_UP, towards)
    return np.stack([right, _UP, towards])


def scene_meshes(scene: str, body: AnimatedBody, camera_from_world: np.ndarray) -> list:
    """World meshes of `scene` ('empty', 'floor' or 'room') around `body`.

    floor: a floor under the lowest point the body reaches. room: the floor, a back wall
    0.7 m behind the body's farthest reach, a side wall on the right and a table on the
    left, each 1.0 m beside the body's reach, and a second still object (a standing lamp)
    0.5 m right of the body, level with it.
    """
    if scene == 'empty':
        return []
    low, high = body_extent(body)
    centre = (low + high) / 2.0
    axes = view_axes(centre, camera_from_world)
    right, _, towards = axes
    corners = np.array(np.meshgrid(*zip(low, high))).reshape(3, -1).T
    reach_right = float(((corners - centre) @ right).max())
    reach_back = float(-((corners - centre) @ towards).min())
    floor_y = float(low[1])
    size = 12.0
    floor_centre = np.array([centre[0], floor_y - 0.01, centre[2]])
    meshes = [_box((size, 0.02, size), floor_centre, axes)]
    if scene == 'floor':
        return meshes
    ground = centre * [1.0, 0.0, 1.0] + _UP * floor_y
    back = ground - towards * (reach_back + 0.7)
    meshes.append(_box((size, 3.0, 0.05), back + _UP * 1.5, axes))
    side = ground + right * (reach_right + 1.0)
    meshes.append(_box((0.05, 3.0, size), side + _UP * 1.5, axes))
    table = ground - right * (reach_right + 1.0) - towards * 0.2
    meshes.append(_box((1.0, 0.05, 0.6), table + _UP * 0.72, axes))            # top
    for dx in (-0.45, 0.45):
        for dz in (-0.25, 0.25):
            leg = table + right * dx + towards * dz + _UP * 0.35
            meshes.append(_box((0.05, 0.7, 0.05), leg, axes))
    lamp = ground + right * (reach_right + 0.5)
    meshes.append(_cylinder(0.15, 0.05, lamp, axes))                              # foot
    meshes.append(_cylinder(0.02, 1.5, lamp, axes))                               # pole
    meshes.append(_cylinder(0.18, 0.3, lamp + _UP * 1.45, axes))                  # shade
    return meshes


def entry_offsets(body: AnimatedBody, camera_from_world: np.ndarray, intrinsics,
                  enter_frames: int) -> np.ndarray:
    """(F, 3) world offsets that start the body outside the image on the right and bring it
    in sideways over `enter_frames` frames (smooth start and stop), 0 afterwards."""
    low, high = body_extent(body)
    centre = (low + high) / 2.0
    right = view_axes(centre, camera_from_world)[0]
    depth = float((camera_from_world[:3, :3] @ centre + camera_from_world[:3, 3])[2])
    half_view = depth * intrinsics.width / (2.0 * intrinsics.fx)
    corners = np.array(np.meshgrid(*zip(low, high))).reshape(3, -1).T
    half_body = float(np.abs((corners - centre) @ right).max())
    distance = half_view + half_body + 0.3
    progress = np.clip(np.arange(body.n_frames) / float(enter_frames), 0.0, 1.0)
    eased = progress * progress * (3.0 - 2.0 * progress)
    return (1.0 - eased)[:, None] * distance * right
