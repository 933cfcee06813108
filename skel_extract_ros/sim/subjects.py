"""Articulated synthetic subjects: primitive shapes on a kinematic tree.

Conventions: the subject is modelled in a world frame with y up and the subject facing +z
(towards the camera). Each bone has its own frame whose origin is the joint that attaches
it to its parent; at rest every bone frame is axis-aligned with the world, so the shapes
and joint offsets below are simply rest-pose world coordinates relative to that joint.
All lengths are metres, all angles radians.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Capsule:
    """A cylinder with hemispherical caps from `start` to `end` (bone-local, metres)."""

    start: tuple
    end: tuple
    radius: float


@dataclass(frozen=True)
class Ellipsoid:
    """An axis-aligned ellipsoid (bone-local centre and semi-axes, metres)."""

    center: tuple
    radii: tuple


@dataclass(frozen=True)
class Bone:
    """One rigid part.

    `joint_position` is the rest-pose world position of the joint attaching this bone to its
    parent (for the root: the point the whole subject turns about). `dof_center` and
    `dof_amplitude` give, per local axis (x, y, z), the mean angle and the amplitude of the
    joint's rotation over the motion; an amplitude of 0 locks that axis.
    """

    name: str
    joint_name: str
    parent: int
    joint_position: tuple
    shapes: tuple
    dof_center: tuple = (0.0, 0.0, 0.0)
    dof_amplitude: tuple = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Subject:
    """A kinematic tree of bones plus where the camera should look at it from.

    `root_sway` is the amplitude of the root's own motion: translation (x, y, z) in metres
    and rotation (x, y, z) in radians. `camera_distance` and `camera_target` place the
    virtual camera in front of the subject (world frame).
    """

    name: str
    bones: tuple
    root_sway_translation: tuple
    root_sway_rotation: tuple
    camera_distance: float
    camera_target: tuple
    camera_height_offset: float = 0.0
    description: str = ''
    floor_height: float = field(default=None)

    def __post_init__(self):
        for index, bone in enumerate(self.bones):
            if not -1 <= bone.parent < index:
                raise ValueError(f'bone {bone.name!r} (index {index}) has parent {bone.parent}; '
                                 'bones must be listed parents first')

    @property
    def bone_parents(self) -> np.ndarray:
        return np.array([b.parent for b in self.bones], dtype=np.int64)

    @property
    def bone_names(self) -> list:
        return [b.name for b in self.bones]

    @property
    def rest_joint_positions(self) -> np.ndarray:
        """(B, 3) rest-pose world positions of every bone's joint, metres."""
        return np.array([b.joint_position for b in self.bones], dtype=np.float64)


def _mirror(x: float, side: str) -> float:
    return x if side == 'l' else -x


def _arm_bones(side: str, parent: int, first_index: int, shoulder: tuple, scale: float = 1.0,
               prefix: str = '') -> list:
    """Upper arm, forearm and hand of one side, hanging slightly abducted; `first_index` is
    the index the upper arm will have in the subject's bone list."""
    m = (lambda x: _mirror(x, side))
    sx, sy, sz = shoulder
    elbow = (sx + m(0.11 * scale), sy - 0.26 * scale, sz)
    wrist = (elbow[0] + m(0.09 * scale), elbow[1] - 0.24 * scale, sz)
    tip = (wrist[0] + m(0.03 * scale), wrist[1] - 0.16 * scale, sz)

    def rel(p, o):
        return tuple(float(a - b) for a, b in zip(p, o))

    s = 1.0 if side == 'l' else -1.0
    upper = Bone(f'{prefix}{side}_upper_arm', f'{side}_shoulder', parent, shoulder,
                 (Capsule((0, 0, 0), rel(elbow, shoulder), 0.048 * scale),),
                 dof_center=(-0.2, 0.0, s * 0.35), dof_amplitude=(0.7, 0.3, 0.4))
    fore = Bone(f'{prefix}{side}_forearm', f'{side}_elbow', first_index, elbow,
                (Capsule((0, 0, 0), rel(wrist, elbow), 0.040 * scale),),
                dof_center=(-0.8, 0.0, 0.0), dof_amplitude=(0.7, 0.25, 0.0))
    hand = Bone(f'{prefix}{side}_hand', f'{side}_wrist', first_index + 1, wrist,
                (Ellipsoid(rel(((wrist[0] + tip[0]) / 2, (wrist[1] + tip[1]) / 2, sz), wrist),
                           (0.035 * scale, 0.085 * scale, 0.022 * scale)),),
                dof_center=(0.0, 0.0, 0.0), dof_amplitude=(0.5, 0.0, s * 0.3))
    return [upper, fore, hand]


def _leg_bones(side: str, parent: int, first_index: int) -> list:
    m = (lambda x: _mirror(x, side))
    hip = (m(0.095), 0.92, 0.0)
    knee = (m(0.105), 0.50, 0.0)
    ankle = (m(0.105), 0.09, 0.0)

    def rel(p, o):
        return tuple(float(a - b) for a, b in zip(p, o))

    s = 1.0 if side == 'l' else -1.0
    thigh = Bone(f'{side}_thigh', f'{side}_hip', parent, hip,
                 (Capsule((0, -0.02, 0), rel(knee, hip), 0.072),),
                 dof_center=(-0.25, 0.0, s * 0.05), dof_amplitude=(0.45, 0.2, 0.15))
    shin = Bone(f'{side}_shin', f'{side}_knee', first_index, knee,
                (Capsule((0, 0, 0), rel(ankle, knee), 0.052),),
                dof_center=(0.6, 0.0, 0.0), dof_amplitude=(0.5, 0.0, 0.0))
    foot = Bone(f'{side}_foot', f'{side}_ankle', first_index + 1, ankle,
                (Capsule((0, -0.04, -0.03), (0, -0.05, 0.14), 0.042),),
                dof_center=(0.0, 0.0, 0.0), dof_amplitude=(0.35, 0.15, 0.0))
    return [thigh, shin, foot]


def make_human() -> Subject:
    """Full body, 16 bones and 15 joints (spine base, mid spine, neck, shoulders, elbows,
    wrists, hips, knees, ankles)."""
    bones = [
        Bone('pelvis', 'root', -1, (0.0, 0.95, 0.0),
             (Ellipsoid((0.0, -0.01, 0.0), (0.165, 0.11, 0.105)),)),
        Bone('abdomen', 'spine_base', 0, (0.0, 1.04, 0.0),
             (Ellipsoid((0.0, 0.10, 0.0), (0.145, 0.12, 0.10)),),
             dof_center=(0.05, 0.0, 0.0), dof_amplitude=(0.2, 0.25, 0.12)),
        Bone('chest', 'spine_mid', 1, (0.0, 1.24, 0.0),
             (Ellipsoid((0.0, 0.12, 0.0), (0.175, 0.16, 0.11)),),
             dof_center=(0.0, 0.0, 0.0), dof_amplitude=(0.15, 0.25, 0.1)),
        Bone('head', 'neck', 2, (0.0, 1.49, 0.0),
             (Capsule((0, -0.02, 0), (0, 0.08, 0), 0.052),
              Ellipsoid((0.0, 0.17, 0.01), (0.085, 0.11, 0.095))),
             dof_center=(0.0, 0.0, 0.0), dof_amplitude=(0.35, 0.5, 0.2)),
    ]
    bones += _arm_bones('l', 2, len(bones), (0.20, 1.44, 0.0))
    bones += _arm_bones('r', 2, len(bones), (-0.20, 1.44, 0.0))
    bones += _leg_bones('l', 0, len(bones))
    bones += _leg_bones('r', 0, len(bones))
    return Subject('human', tuple(bones), root_sway_translation=(0.06, 0.02, 0.05),
                   root_sway_rotation=(0.05, 0.3, 0.05), camera_distance=2.3,
                   camera_target=(0.0, 0.9, 0.0), camera_height_offset=0.1,
                   description='full body, 16 bones, 15 joints', floor_height=0.0)


def make_upper_body() -> Subject:
    """Abdomen, chest, head and both arms: 9 bones, 8 joints."""
    bones = [
        Bone('abdomen', 'root', -1, (0.0, 1.04, 0.0),
             (Ellipsoid((0.0, 0.08, 0.0), (0.145, 0.12, 0.10)),)),
        Bone('chest', 'spine_mid', 0, (0.0, 1.24, 0.0),
             (Ellipsoid((0.0, 0.12, 0.0), (0.175, 0.16, 0.11)),),
             dof_center=(0.0, 0.0, 0.0), dof_amplitude=(0.2, 0.3, 0.12)),
        Bone('head', 'neck', 1, (0.0, 1.49, 0.0),
             (Capsule((0, -0.02, 0), (0, 0.08, 0), 0.052),
              Ellipsoid((0.0, 0.17, 0.01), (0.085, 0.11, 0.095))),
             dof_center=(0.0, 0.0, 0.0), dof_amplitude=(0.35, 0.5, 0.2)),
    ]
    bones += _arm_bones('l', 1, len(bones), (0.20, 1.44, 0.0))
    bones += _arm_bones('r', 1, len(bones), (-0.20, 1.44, 0.0))
    return Subject('upper_body', tuple(bones), root_sway_translation=(0.03, 0.01, 0.03),
                   root_sway_rotation=(0.05, 0.2, 0.05), camera_distance=1.5,
                   camera_target=(0.0, 1.25, 0.0), description='upper body, 9 bones, 8 joints')


def make_arm() -> Subject:
    """Upper arm, forearm and hand held out sideways: 3 bones, 2 joints."""
    shoulder = (0.0, 0.0, 0.0)
    elbow = (0.28, 0.0, 0.0)
    wrist = (0.53, 0.0, 0.0)
    bones = (
        Bone('upper_arm', 'shoulder', -1, shoulder, (Capsule(shoulder, elbow, 0.046),)),
        Bone('forearm', 'elbow', 0, elbow, (Capsule((0, 0, 0), (0.25, 0, 0), 0.038),),
             dof_center=(0.0, 0.5, 0.6), dof_amplitude=(0.3, 0.45, 0.6)),
        Bone('hand', 'wrist', 1, wrist, (Ellipsoid((0.085, 0, 0), (0.09, 0.045, 0.02)),),
             dof_center=(0.0, 0.0, 0.0), dof_amplitude=(0.4, 0.3, 0.5)),
    )
    return Subject('arm', bones, root_sway_translation=(0.02, 0.02, 0.02),
                   root_sway_rotation=(0.3, 0.25, 0.3), camera_distance=1.1,
                   camera_target=(0.35, 0.0, 0.0), description='arm, 3 bones, 2 joints')


def make_hand() -> Subject:
    """Palm facing the camera with five fingers of three segments: 16 bones, 15 joints."""
    bones = [Bone('palm', 'root', -1, (0.0, 0.0, 0.0),
                  (Ellipsoid((0.0, 0.045, 0.0), (0.045, 0.052, 0.016)),))]
    # (name, base x, base y, segment lengths, direction in the palm plane)
    fingers = [
        ('thumb', 0.042, 0.015, (0.040, 0.032, 0.026), (0.75, 0.66)),
        ('index', 0.030, 0.095, (0.042, 0.026, 0.021), (0.10, 1.0)),
        ('middle', 0.010, 0.100, (0.046, 0.029, 0.022), (0.0, 1.0)),
        ('ring', -0.011, 0.097, (0.043, 0.027, 0.021), (-0.07, 1.0)),
        ('little', -0.031, 0.088, (0.034, 0.021, 0.018), (-0.18, 1.0)),
    ]
    joint_suffixes = ('mcp', 'pip', 'dip')
    radii = (0.0095, 0.0085, 0.0075)
    for name, bx, by, lengths, direction in fingers:
        d = np.array([direction[0], direction[1], 0.0])
        d /= np.linalg.norm(d)
        position = np.array([bx, by, 0.0])
        parent = 0
        for seg, (length, suffix, radius) in enumerate(zip(lengths, joint_suffixes, radii)):
            end = d * length
            amp_z = 0.15 if seg == 0 else 0.0
            bones.append(Bone(f'{name}_{seg + 1}', f'{name}_{suffix}', parent,
                              tuple(float(v) for v in position),
                              (Capsule((0, 0, 0), tuple(float(v) for v in end), radius),),
                              dof_center=(0.55, 0.0, 0.0), dof_amplitude=(0.5, 0.0, amp_z)))
            parent = len(bones) - 1
            position = position + end
    return Subject('hand', tuple(bones), root_sway_translation=(0.01, 0.01, 0.01),
                   root_sway_rotation=(0.25, 0.3, 0.2), camera_distance=0.55,
                   camera_target=(0.0, 0.07, 0.0), description='hand, 16 bones, 15 joints')


def make_fish() -> Subject:
    """A swimming fish seen from above: head, four body segments and a tail fin, bending in
    a travelling wave: 6 bones, 5 joints."""
    lengths = (0.09, 0.075, 0.07, 0.06, 0.05)
    half_widths = (0.045, 0.05, 0.043, 0.034, 0.024)
    bones = [Bone('head', 'root', -1, (0.0, 0.0, 0.0),
                  (Ellipsoid((-0.045, 0.0, 0.0), (0.055, 0.04, 0.028)),))]
    x = 0.0
    for i, (length, half_width) in enumerate(zip(lengths, half_widths)):
        # The body extends towards -x; each joint bends about z (the camera axis) so the
        # wave is in the image plane, plus a little pitch about y.
        x_joint = x - (0.09 if i == 0 else lengths[i - 1])
        x = x_joint
        if i < len(lengths) - 1:
            shape = Ellipsoid((-length / 2, 0.0, 0.0), (length / 2 + 0.012, half_width, 0.026 * (1 - 0.15 * i)))
        else:
            shape = Ellipsoid((-length / 2 - 0.01, 0.0, 0.0), (length / 2 + 0.02, 0.05, 0.006))
        bones.append(Bone(f'segment_{i + 1}' if i < len(lengths) - 1 else 'tail',
                          f'joint_{i + 1}', i, (x_joint, 0.0, 0.0), (shape,),
                          dof_center=(0.0, 0.0, 0.0),
                          dof_amplitude=(0.0, 0.08, 0.18 + 0.07 * i)))
    return Subject('fish', tuple(bones), root_sway_translation=(0.02, 0.02, 0.01),
                   root_sway_rotation=(0.05, 0.05, 0.2), camera_distance=0.75,
                   camera_target=(-0.17, 0.0, 0.0), description='fish, 6 bones, 5 joints')


SUBJECTS = {
    'human': make_human,
    'upper_body': make_upper_body,
    'arm': make_arm,
    'hand': make_hand,
    'fish': make_fish,
}


def make_subject(name: str) -> Subject:
    """Build a subject by name; raises ValueError listing the valid names."""
    try:
        return SUBJECTS[name]()
    except KeyError:
        raise ValueError(f'unknown subject {name!r}; choose one of {", ".join(SUBJECTS)}') from None
