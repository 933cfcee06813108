"""Synthetic depth sequences of articulated subjects, with exact ground truth."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from ..progress import progress_bar
from .camera import DepthCamera, Intrinsics, NoiseModel, look_at
from .meshes import inside_any, mesh_area, sample_surface, shape_mesh
from .motion import bone_transforms, make_motion
from .subjects import Subject, make_subject

FRAME_ID = 'camera_depth_optical_frame'
FRAME_RATE_HZ = 30.0
FIRST_STAMP_NS = 1_700_000_000 * 10**9


@dataclass
class SimulatedSequence:
    """A rendered sequence.

    clouds: list of F organized clouds, each (H, W, 3) float32 metres in the camera optical
        frame, NaN where the camera saw nothing.
    stamps_ns: (F,) int64 header stamps.
    ground_truth: the arrays written to gt.npz (see `ground_truth_arrays`).
    """

    subject: Subject
    clouds: list
    stamps_ns: np.ndarray
    ground_truth: dict
    frame_id: str = FRAME_ID

    def points_per_frame(self) -> np.ndarray:
        return np.array([int(np.isfinite(c[..., 2]).sum()) for c in self.clouds])


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


def _clutter_meshes(subject: Subject, surface_rest: np.ndarray) -> list:
    """Floor below the subject and a wall behind it, as (vertices, triangles) in world."""
    lowest = float(surface_rest[:, 1].min())
    floor_y = subject.floor_height if subject.floor_height is not None else lowest - 0.05
    d = subject.camera_distance
    size = 4.0 * d
    floor = o3d.geometry.TriangleMesh.create_box(size, 0.02, size)
    floor.translate((-size / 2, floor_y - 0.02, -size / 2))
    wall_z = float(surface_rest[:, 2].min()) - 0.6 * d
    wall = o3d.geometry.TriangleMesh.create_box(size, size, 0.02)
    wall.translate((-size / 2, floor_y - 0.02, wall_z - 0.02))
    return [(np.asarray(m.vertices), np.asarray(m.triangles)) for m in (floor, wall)]


def generate_sequence(subject_name: str, frames: int, resolution: str = '320x240',
                      noise: NoiseModel | None = None, clutter: bool = False, seed: int = 0,
                      surface_samples: int = 4000, progress: bool = True) -> SimulatedSequence:
    """Render `frames` frames of a subject in seeded motion through a virtual depth camera.

    Returns organized clouds and the ground truth: joints, bone transforms and dense
    surface samples with their bone ids, all in the camera optical frame (metres).
    """
    if frames < 1:
        raise ValueError(f'frames must be at least 1, got {frames}')
    subject = make_subject(subject_name)
    intrinsics = Intrinsics.from_resolution(resolution)
    noise = NoiseModel.kinect() if noise is None else noise
    rng = np.random.default_rng(seed)
    motion = make_motion(subject, seed)
    placement = _placement(subject, rng)

    target = np.asarray(subject.camera_target, float)
    eye = target + np.array([0.0, subject.camera_height_offset, subject.camera_distance])
    camera_from_world = np.linalg.inv(look_at(eye, target)) @ placement

    # Shape meshes (bone-local) and surface samples that are not buried in another shape.
    shape_meshes, shape_bones = [], []
    for b, bone in enumerate(subject.bones):
        for shape in bone.shapes:
            shape_meshes.append(shape_mesh(shape))
            shape_bones.append(b)
    rest_joints = subject.rest_joint_positions
    rest_meshes = [(v + rest_joints[b], t) for (v, t), b in zip(shape_meshes, shape_bones)]
    areas = np.array([mesh_area(v, t) for v, t in rest_meshes])
    counts = np.maximum(1, np.round(surface_samples * areas / areas.sum()).astype(int))
    local_samples, sample_bones = [], []
    for i, ((vertices, triangles), b, count) in enumerate(zip(shape_meshes, shape_bones, counts)):
        samples = sample_surface(vertices, triangles, int(count), rng)
        others = [m for j, m in enumerate(rest_meshes) if j != i]
        keep = ~inside_any(samples + rest_joints[b], others)
        local_samples.append(samples[keep])
        sample_bones.append(np.full(int(keep.sum()), b))
    local_samples = np.concatenate(local_samples)
    sample_bones = np.concatenate(sample_bones)

    clutter_world = _clutter_meshes(subject, local_samples + rest_joints[sample_bones]) if clutter else []
    clutter_camera = [(v @ camera_from_world[:3, :3].T + camera_from_world[:3, 3], t)
                      for v, t in clutter_world]

    times = np.arange(frames) / FRAME_RATE_HZ
    world_transforms = bone_transforms(subject, motion, times)
    transforms = camera_from_world @ world_transforms  # (F, B, 4, 4) camera from bone
    camera = DepthCamera(intrinsics)

    clouds = []
    surface = np.empty((frames, len(local_samples), 3), dtype=np.float32)
    bar = progress_bar(total=frames, desc=f'simulate {subject_name}', unit='frame', disable=not progress)
    for f in range(frames):
        rotations, origins = transforms[f, :, :3, :3], transforms[f, :, :3, 3]
        meshes = [(v @ rotations[b].T + origins[b], t)
                  for (v, t), b in zip(shape_meshes, shape_bones)]
        depth = camera.render_depth(meshes + clutter_camera)
        clouds.append(camera.back_project(noise.apply(depth, rng)))
        surface[f] = np.einsum('sij,sj->si', rotations[sample_bones], local_samples) + origins[sample_bones]
        bar.update()

    bar.close()
    joint_bones = np.array([b for b, bone in enumerate(subject.bones) if bone.parent >= 0])
    joint_of_bone = {int(b): j for j, b in enumerate(joint_bones)}
    joint_parents = np.array([joint_of_bone.get(int(subject.bones[b].parent), -1)
                              for b in joint_bones], dtype=np.int64)
    stamps_ns = FIRST_STAMP_NS + np.round(np.arange(frames) * 1e9 / FRAME_RATE_HZ).astype(np.int64)
    rest_surface = surface[0]
    ground_truth = {
        'subject': np.array(subject.name),
        'frame_id': np.array(FRAME_ID),
        'stamps': stamps_ns.astype(np.float64) * 1e-9,
        'stamps_ns': stamps_ns,
        'joints': transforms[:, joint_bones][:, :, :3, 3].astype(np.float32),
        'joint_names': np.array([subject.bones[b].joint_name for b in joint_bones]),
        'joint_parents': joint_parents,
        'joint_bones': joint_bones,
        'bone_names': np.array(subject.bone_names),
        'bone_parents': subject.bone_parents,
        'bone_transforms': transforms.astype(np.float32),
        'surface_points': surface,
        'surface_bone_ids': sample_bones.astype(np.int64),
        'subject_scale_m': np.float64(np.linalg.norm(np.ptp(rest_surface, axis=0))),
        'intrinsics': np.array([intrinsics.width, intrinsics.height, intrinsics.fx,
                                intrinsics.fy, intrinsics.cx, intrinsics.cy]),
        'seed': np.int64(seed),
    }
    return SimulatedSequence(subject, clouds, stamps_ns, ground_truth)
