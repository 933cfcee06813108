"""A moving body in a world frame, whatever drives it: the built-in subjects, motion
capture (BVH) on a body of capsules, a skinned rig blended between key poses, or a captured
mesh sequence. `render.render_body` turns one into depth clouds and ground truth.

World convention: metres, y up, the body facing +z (towards a camera placed on +z).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RigidPart:
    """One closed triangle mesh fixed to a bone: vertices (V, 3) in the bone's frame (m),
    triangles (T, 3)."""

    bone: int
    vertices: np.ndarray
    triangles: np.ndarray


@dataclass
class SkinnedSurface:
    """A deforming closed mesh: vertices (F, V, 3) in the world frame (m), faces (T, 3),
    and the bone that moves each vertex most (V,) (-1 where there are no bones)."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_bones: np.ndarray


@dataclass
class AnimatedBody:
    """What a renderer needs to see a body move, and the ground truth it carries.

    bone_transforms: (F, B, 4, 4) world-from-bone. A bone's origin is the joint attaching it
        to its parent; the joint's rotation is the bone's rotation relative to its parent.
    bone_names: (B,) names; bone_parents: (B,) parent bone, -1 for the root.
    joint_names / joint_parents: (G,) the ground-truth joints and their tree (-1 = root).
    joint_bones: (G,) the bone whose origin each joint is (joint g sits at
        bone_transforms[:, joint_bones[g], :3, 3]).
    Exactly one of `parts` (rigid meshes on bones) and `skin` (a deforming mesh) is set.
    frame_time: seconds between frames.
    """

    name: str
    bone_transforms: np.ndarray
    bone_names: list
    bone_parents: np.ndarray
    joint_names: list
    joint_parents: np.ndarray
    joint_bones: np.ndarray
    parts: list | None = None
    skin: SkinnedSurface | None = None
    frame_time: float = 1.0 / 30.0
    description: str = ''

    def __post_init__(self):
        if (self.parts is None) == (self.skin is None):
            raise ValueError('an AnimatedBody has either rigid parts or a skinned surface')
        n_frames, n_bones = self.bone_transforms.shape[:2]
        if len(self.bone_names) != n_bones or len(self.bone_parents) != n_bones:
            raise ValueError(f'{n_bones} bone transforms but {len(self.bone_names)} names and '
                             f'{len(self.bone_parents)} parents')
        if not len(self.joint_names) == len(self.joint_parents) == len(self.joint_bones):
            raise ValueError('joint_names, joint_parents and joint_bones differ in length')
        if self.skin is not None and self.skin.vertices.shape[0] != n_frames:
            raise ValueError(f'{self.skin.vertices.shape[0]} skin frames for {n_frames} bone frames')

    @property
    def n_frames(self) -> int:
        return int(self.bone_transforms.shape[0])

    @property
    def joints(self) -> np.ndarray:
        """(F, G, 3) world joint positions, m."""
        return self.bone_transforms[:, self.joint_bones][..., :3, 3]

    def key_points(self) -> np.ndarray:
        """(F, K, 3) world points that show where the body is: its joints, or for a body
        without joints a spread of its surface vertices."""
        if len(self.joint_bones):
            return self.joints
        step = max(1, self.skin.vertices.shape[1] // 500)
        return self.skin.vertices[:, ::step]

    def world_meshes(self, frame: int) -> list:
        """The body at `frame` as a list of (vertices (V, 3), triangles (T, 3)) in the world."""
        if self.skin is not None:
            return [(self.skin.vertices[frame], self.skin.faces)]
        transforms = self.bone_transforms[frame]
        return [(part.vertices @ transforms[part.bone, :3, :3].T + transforms[part.bone, :3, 3],
                 part.triangles) for part in self.parts]

    def window(self, start: int, stop: int) -> 'AnimatedBody':
        """The frames [start, stop) as a body of their own."""
        skin = None if self.skin is None else SkinnedSurface(
            self.skin.vertices[start:stop], self.skin.faces, self.skin.vertex_bones)
        return AnimatedBody(self.name, self.bone_transforms[start:stop], self.bone_names,
                            self.bone_parents, self.joint_names, self.joint_parents,
                            self.joint_bones, self.parts, skin, self.frame_time, self.description)
