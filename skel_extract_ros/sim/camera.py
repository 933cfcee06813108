"""A virtual single depth camera with a Kinect-like noise model.

The camera renders triangle meshes with Open3D's RaycastingScene into an organized depth
image and back-projects it to an organized point cloud in the optical frame (x right,
y down, z forward), invalid pixels NaN, the way OpenNI-style drivers publish it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

RESOLUTIONS = {
    # Kinect v1 style intrinsics: 525 px focal length at 640x480, halved at 320x240.
    '640x480': (640, 480, 525.0, 525.0, 319.5, 239.5),
    '320x240': (320, 240, 262.5, 262.5, 159.5, 119.5),
}


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (pixels)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_resolution(cls, resolution: str) -> 'Intrinsics':
        try:
            return cls(*RESOLUTIONS[resolution])
        except KeyError:
            raise ValueError(f'unknown resolution {resolution!r}; choose one of '
                             f'{", ".join(RESOLUTIONS)}') from None


@dataclass(frozen=True)
class NoiseModel:
    """Kinect-like depth corruption; every part can be switched off on its own.

    - axial: Gaussian depth noise with std 1.2 mm + 1.9 mm * (z - 0.4 m)^2 / m^2
      (Nguyen, Izadi and Lovell 2012).
    - quantization_disparity: step of depth quantisation in inverse depth (1/m); 0.00285
      gives the Kinect v1 step of 2.85 mm at 1 m and 1.8 cm at 2.5 m.
    - flying_pixel_probability: chance that a pixel on a depth edge takes a depth between
      foreground and background (mixed pixels).
    - outlier_fraction: fraction of valid pixels given a random wrong depth.
    - dropout_fraction: fraction of valid pixels lost (NaN).
    """

    axial: bool = True
    quantization_disparity: float = 0.00285
    flying_pixel_probability: float = 0.5
    edge_threshold_m: float = 0.05
    outlier_fraction: float = 0.002
    dropout_fraction: float = 0.01

    @classmethod
    def kinect(cls) -> 'NoiseModel':
        return cls()

    @classmethod
    def none(cls) -> 'NoiseModel':
        return cls(axial=False, quantization_disparity=0.0, flying_pixel_probability=0.0,
                   outlier_fraction=0.0, dropout_fraction=0.0)

    def tolerance(self, depth: np.ndarray) -> np.ndarray:
        """Depth error (m) this model gives a pixel at `depth` (m) without flying pixels and
        outliers: 4 axial deviations plus one quantisation step."""
        axial = 0.0012 + 0.0019 * (depth - 0.4) ** 2 if self.axial else 0.0
        return 4.0 * axial + self.quantization_disparity * depth ** 2 + 1e-6

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Corrupt an (H, W) depth image in metres (NaN = no return); returns a new image."""
        depth = depth.copy()
        valid = np.isfinite(depth)
        if self.flying_pixel_probability > 0.0:
            depth = self._flying_pixels(depth, valid, rng)
            valid = np.isfinite(depth)
        if self.axial:
            z = depth[valid]
            depth[valid] = z + rng.normal(size=z.shape) * (0.0012 + 0.0019 * (z - 0.4) ** 2)
        if self.outlier_fraction > 0.0:
            hit = valid & (rng.random(depth.shape) < self.outlier_fraction)
            depth[hit] *= rng.uniform(0.6, 1.4, size=int(hit.sum()))
        if self.quantization_disparity > 0.0:
            z = depth[valid]
            disparity = np.round((1.0 / np.maximum(z, 1e-3)) / self.quantization_disparity)
            depth[valid] = 1.0 / (np.maximum(disparity, 1.0) * self.quantization_disparity)
        if self.dropout_fraction > 0.0:
            depth[valid & (rng.random(depth.shape) < self.dropout_fraction)] = np.nan
        return depth

    def _flying_pixels(self, depth: np.ndarray, valid: np.ndarray,
                       rng: np.random.Generator) -> np.ndarray:
        """Mix foreground pixels on a depth edge with the background behind them."""
        # Farthest 4-neighbour depth; a missing neighbour (no surface) counts as far away.
        far = np.where(valid, depth, np.inf)
        padded = np.pad(far, 1, constant_values=np.inf)
        neighbour_max = np.max(np.stack([padded[:-2, 1:-1], padded[2:, 1:-1],
                                         padded[1:-1, :-2], padded[1:-1, 2:]]), axis=0)
        edge = valid & (neighbour_max - np.where(valid, depth, 0.0) > self.edge_threshold_m)
        chosen = edge & (rng.random(depth.shape) < self.flying_pixel_probability)
        background = neighbour_max[chosen]
        foreground = depth[chosen]
        # Against empty space there is no background return: smear up to 0.3 m behind.
        background = np.where(np.isfinite(background), background, foreground + 0.3)
        mix = rng.uniform(0.1, 0.9, size=foreground.shape)
        depth[chosen] = foreground + mix * (background - foreground)
        return depth


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(4, 4) world-from-camera transform of an optical frame at `eye` looking at `target`."""
    z_axis = np.asarray(target, float) - np.asarray(eye, float)
    z_axis /= np.linalg.norm(z_axis)
    x_axis = np.cross(z_axis, np.asarray(up, float))
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x_axis, y_axis, z_axis, eye
    return pose


class DepthCamera:
    """Renders triangle meshes given in the camera optical frame into depth and points."""

    def __init__(self, intrinsics: Intrinsics):
        self.intrinsics = intrinsics
        u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
        # Ray directions with unit z, so the hit distance along a ray is the depth itself.
        self._rays_xy = np.stack([(u - intrinsics.cx) / intrinsics.fx,
                                  (v - intrinsics.cy) / intrinsics.fy], axis=-1)
        directions = np.concatenate([self._rays_xy, np.ones(u.shape + (1,))], axis=-1)
        rays = np.concatenate([np.zeros_like(directions), directions], axis=-1)
        self._rays = o3d.core.Tensor(rays.reshape(-1, 6).astype(np.float32))

    def render_depth(self, meshes) -> np.ndarray:
        """(H, W) depth in metres from a list of (vertices (V, 3), triangles (T, 3)) in the
        optical frame; NaN where no surface is hit."""
        return self.render(meshes, [])[0]

    def render(self, subject_meshes, scene_meshes) -> tuple:
        """(depth (H, W) m, NaN where nothing is hit; subject (H, W) bool: the first surface
        hit is one of `subject_meshes`) for meshes given as (vertices, triangles) in the
        optical frame."""
        scene = o3d.t.geometry.RaycastingScene()
        for vertices, triangles in list(subject_meshes) + list(scene_meshes):
            scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                                o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
        hits = scene.cast_rays(self._rays)
        shape = (self.intrinsics.height, self.intrinsics.width)
        depth = hits['t_hit'].numpy().reshape(shape).astype(np.float64)
        depth[~np.isfinite(depth)] = np.nan
        # Geometry ids are given in the order added, so the subject's come first.
        ids = hits['geometry_ids'].numpy().reshape(shape).astype(np.int64)
        subject = np.isfinite(depth) & (ids < len(subject_meshes))
        return depth, subject

    def back_project(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) depth -> (H, W, 3) float32 organized cloud, NaN where depth is NaN."""
        points = np.concatenate([self._rays_xy * depth[..., None], depth[..., None]], axis=-1)
        return points.astype(np.float32)
