"""Seeded smooth joint motion and forward kinematics for synthetic subjects."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .subjects import Subject


@dataclass(frozen=True)
class MotionSpec:
    """Per-axis sum-of-two-sines angle trajectories.

    Arrays are (B, 3, 2): bone, local axis, harmonic. Frequencies are in Hz, phases in
    radians. `root_*` arrays are (3, 2) for the root's sway in translation and rotation.
    one_limb_at_a_time: the limbs (see `limb_groups`) take turns: the sequence is cut into
    as many equal slots as there are limbs and in each only one limb moves (the root keeps
    swaying), the way a person waves one arm, then the other, then steps.
    """

    frequencies: np.ndarray
    phases: np.ndarray
    root_frequencies: np.ndarray
    root_phases: np.ndarray
    one_limb_at_a_time: bool = False


def make_motion(subject: Subject, seed: int, one_limb_at_a_time: bool = False) -> MotionSpec:
    """Draw a repeatable motion for `subject`.

    Frequencies lie in 0.5-1.0 Hz so that even a 1 s window sees every joint move a
    sizeable fraction of its range; the two harmonics keep the motion from being periodic.
    """
    rng = np.random.default_rng(seed)
    n_bones = len(subject.bones)
    frequencies = rng.uniform(0.5, 1.0, size=(n_bones, 3, 2))
    phases = rng.uniform(0.0, 2.0 * np.pi, size=(n_bones, 3, 2))
    root_frequencies = rng.uniform(0.2, 0.5, size=(2, 3, 2))
    root_phases = rng.uniform(0.0, 2.0 * np.pi, size=(2, 3, 2))
    return MotionSpec(frequencies, phases, root_frequencies, root_phases, one_limb_at_a_time)


def _two_sines(times: np.ndarray, frequencies: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """(F,) times x (..., 2) harmonics -> (F, ...) signal in [-1, 1]."""
    arg = 2.0 * np.pi * times.reshape((-1,) + (1,) * frequencies.ndim) * frequencies + phases
    return 0.7 * np.sin(arg[..., 0]) + 0.3 * np.sin(arg[..., 1])


def limb_groups(subject: Subject) -> np.ndarray:
    """(B,) the limb of each bone: the bone below the nearest branching of the tree above it
    (an arm hangs on the chest with the head beside it: arm and head are limbs; a chain
    without branches is one limb); -1 for the root."""
    parents = np.array([b.parent for b in subject.bones])
    children = np.bincount(parents[parents >= 0], minlength=len(parents))
    groups = np.full(len(parents), -1)
    for b in range(len(parents)):    # a loop over bones (tens)
        top = b
        while parents[top] >= 0 and parents[parents[top]] >= 0 and children[parents[top]] < 2:
            top = parents[top]
        groups[b] = -1 if parents[b] < 0 else top
    return groups


def limb_activity(subject: Subject, times: np.ndarray) -> np.ndarray:
    """(F, B) in [0, 1]: how much each bone moves at `times` when the limbs take turns (each
    limb's slot fades in and out over a tenth of it; the root always moves)."""
    groups = limb_groups(subject)
    limbs = np.unique(groups[groups >= 0])
    activity = np.ones((len(times), len(groups)))
    if not len(limbs):
        return activity
    span = max(float(times[-1] - times[0]), 1e-9) * (1.0 + 1.0 / max(len(times) - 1, 1))
    slot = span / len(limbs)
    position = (times - times[0])[:, None] / slot - np.arange(len(limbs))[None, :]   # (F, L), 0..1 in its slot
    ramp = np.clip(np.minimum(position, 1.0 - position) / 0.1, 0.0, 1.0)
    envelope = ramp * ramp * (3.0 - 2.0 * ramp)
    for index, limb in enumerate(limbs):   # a loop over limbs
        activity[:, groups == limb] = envelope[:, index:index + 1]
    return activity


def joint_angles(subject: Subject, motion: MotionSpec, times: np.ndarray) -> np.ndarray:
    """(F, B, 3) local rotation angles (radians, about bone-local x, y, z) at `times` (s)."""
    center = np.array([b.dof_center for b in subject.bones], dtype=np.float64)
    amplitude = np.array([b.dof_amplitude for b in subject.bones], dtype=np.float64)
    motion_part = amplitude * _two_sines(times, motion.frequencies, motion.phases)
    if motion.one_limb_at_a_time:
        motion_part = motion_part * limb_activity(subject, times)[:, :, None]
    return center + motion_part


def bone_transforms(subject: Subject, motion: MotionSpec, times: np.ndarray) -> np.ndarray:
    """(F, B, 4, 4) world transforms of every bone frame at `times` (s).

    A bone frame's origin is its joint and at rest it is world-aligned, so a point p given
    relative to the joint (as the shapes are) is at R p + o with R = T[f, b, :3, :3] and
    o = T[f, b, :3, 3]. The root additionally sways (translation and rotation about its
    joint).
    """
    times = np.asarray(times, dtype=np.float64)
    n_frames = times.shape[0]
    n_bones = len(subject.bones)
    angles = joint_angles(subject, motion, times)
    # Rest-pose angles: joints at their mean angle would not be a neutral pose, so the rest
    # pose (zero angles) is what the shapes are modelled in, and motion is relative to it.
    local_rotations = Rotation.from_euler('xyz', angles.reshape(-1, 3)).as_matrix().reshape(
        n_frames, n_bones, 3, 3)

    rest_joints = subject.rest_joint_positions
    sway = _two_sines(times, motion.root_frequencies, motion.root_phases)  # (F, 2, 3)
    root_translation = sway[:, 0, :] * np.asarray(subject.root_sway_translation)
    root_rotation = Rotation.from_euler(
        'xyz', sway[:, 1, :] * np.asarray(subject.root_sway_rotation)).as_matrix()

    transforms = np.zeros((n_frames, n_bones, 4, 4))
    transforms[:, :, 3, 3] = 1.0
    for b, bone in enumerate(subject.bones):  # loop over bones (tree order), not points
        if bone.parent < 0:
            rotation = root_rotation @ local_rotations[:, b]
            origin = rest_joints[b] + root_translation
        else:
            parent = transforms[:, bone.parent]
            offset = rest_joints[b] - rest_joints[bone.parent]
            rotation = parent[:, :3, :3] @ local_rotations[:, b]
            origin = parent[:, :3, 3] + parent[:, :3, :3] @ offset
        transforms[:, b, :3, :3] = rotation
        transforms[:, b, :3, 3] = origin
    return transforms


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (N, 3) points."""
    return points @ transform[:3, :3].T + transform[:3, 3]
