"""Synthetic depth sequences of the built-in articulated subjects, with exact ground truth."""
from __future__ import annotations

import numpy as np

from .animated import AnimatedBody, RigidPart
from .camera import Intrinsics, NoiseModel, look_at
from .meshes import shape_mesh
from .motion import bone_transforms, make_motion
from .render import FIRST_STAMP_NS, FRAME_ID, FRAME_RATE_HZ, SimulatedSequence, render_body
from .subjects import Subject, make_subject

__all__ = ['FIRST_STAMP_NS', 'FRAME_ID', 'FRAME_RATE_HZ', 'SimulatedSequence', 'generate_sequence',
           'subject_body']


def subject_body(subject: Subject, motion, placement: np.ndarray, frames: int) -> AnimatedBody:
    """A built-in subject in seeded motion as an AnimatedBody in the world (placed)."""
    parts = []
    for b, bone in enumerate(subject.bones):
        for shape in bone.shapes:
            vertices, triangles = shape_mesh(shape)
            parts.append(RigidPart(b, vertices, triangles))
    times = np.arange(frames) / FRAME_RATE_HZ
    world_transforms = placement @ bone_transforms(subject, motion, times)
    joint_bones = np.array([b for b, bone in enumerate(subject.bones) if bone.parent >= 0])
    joint_of_bone = {int(b): j for j, b in enumerate(joint_bones)}
    joint_parents = np.array([joint_of_bone.get(int(subject.bones[b].parent), -1)
                              for b in joint_bones], dtype=np.int64)
    return AnimatedBody(subject.name, world_transforms, subject.bone_names, subject.bone_parents,
                        [subject.bones[b].joint_name for b in joint_bones], joint_parents,
                        joint_bones, parts=parts, frame_time=1.0 / FRAME_RATE_HZ,
                        description=subject.description)


def _placement(subject: Subject, rng: np.random.Generator) -> np.ndarray:
    """(4, 4) seeded world placement: the subject is not always dead centre and square on."""
    d = subject.camera_distance
    yaw = rng.uniform(-0.35, 0.35)
    c, s = np.cos(yaw), np.sin(yaw)
    placement = np.eye(4)
    placement[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pivot = np.asarray(subject.camera_target, float)
    offset = np.array([rng.uniform(-0.08, 0.08) * d, 0.0, rng.uniform(-0.08, 0.08) * d])
    placement[:3, 3] = pivot - placement[:3, :3] @ pivot + offset
    return placement


def generate_sequence(subject_name: str, frames: int, resolution: str = '320x240',
                      noise: NoiseModel | None = None, scene: str = 'empty', seed: int = 0,
                      surface_samples: int = 4000, enter_frames: int = 0,
                      progress: bool = True, one_limb_at_a_time: bool = False) -> SimulatedSequence:
    """Render `frames` frames of a built-in subject in seeded motion through a virtual depth
    camera (see `render.render_body` for the ground truth); one_limb_at_a_time: the limbs
    take turns (motion.MotionSpec)."""
    if frames < 1:
        raise ValueError(f'frames must be at least 1, got {frames}')
    subject = make_subject(subject_name)
    intrinsics = Intrinsics.from_resolution(resolution)
    noise = NoiseModel.kinect() if noise is None else noise
    rng = np.random.default_rng(seed)
    motion = make_motion(subject, seed, one_limb_at_a_time)
    placement = _placement(subject, rng)
    body = subject_body(subject, motion, placement, frames)
    target = np.asarray(subject.camera_target, float)
    eye = target + np.array([0.0, subject.camera_height_offset, subject.camera_distance])
    camera_from_world = np.linalg.inv(look_at(eye, target))
    # Samples are drawn on the rest pose (every joint at zero angle), where no part is
    # folded into another.
    rest = np.tile(np.eye(4), (len(subject.bones), 1, 1))
    rest[:, :3, 3] = subject.rest_joint_positions
    return render_body(body, camera_from_world, intrinsics, noise, rng, scene=scene,
                       enter_frames=enter_frames, surface_samples=surface_samples,
                       reference_transforms=rest, progress=progress,
                       extra_ground_truth={'seed': np.int64(seed)})
