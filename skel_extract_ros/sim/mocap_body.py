"""A body of capsules and ellipsoids on a motion-capture skeleton, and the stretch of a clip
with the most limb motion.

Each segment gets a shape by the body part its joint's name says it is (head, upper arm,
thigh, ...), with human proportions scaled to the skeleton's size; a name that says nothing
gets a plain limb capsule, so any BVH renders. Leaf joints (head, hands, toes) whose end
site has no length get a shape continuing their parent segment, as the hand continues the
forearm.
"""
from __future__ import annotations

import re

import numpy as np

from .animated import AnimatedBody, RigidPart
from .bvh import MocapClip, body_joints
from .meshes import capsule_mesh, ellipsoid_mesh

# Body parts by joint name (lower case, prefixes such as "mixamorig:" dropped); the first
# pattern that matches wins, so the more specific ones come first.
_PART_PATTERNS = (
    ('head', r'head'),
    ('neck', r'neck'),
    ('toe', r'toe'),
    ('foot', r'foot|ankle'),
    ('hand', r'hand|wrist|finger|thumb|palm'),
    ('forearm', r'forearm|lowerarm|elbow'),
    ('clavicle', r'shoulder|clavicle|collar'),
    ('upper_arm', r'arm|humerus'),
    ('thigh', r'upperleg|upleg|thigh|femur|hipjoint|hip$'),
    ('shin', r'leg|shin|calf|knee|tibia'),
    ('pelvis', r'hips|pelvis'),
    ('chest', r'chest|thorax|spine[_-]?[1-9]|upperback'),
    ('spine', r'spine|abdomen|back|waist|torso'),
)

# Shapes of a reference adult (sum of segment lengths 3.74 m, about 1.7 m tall), m:
# capsule radii, and ellipsoid semi-axes (lateral, along the segment, front-back).
_REFERENCE_SEGMENT_SUM_M = 3.74
_CAPSULE_RADIUS = {'neck': 0.05, 'clavicle': 0.05, 'upper_arm': 0.048, 'forearm': 0.040,
                   'thigh': 0.075, 'shin': 0.055, 'foot': 0.042, 'toe': 0.03, 'limb': 0.035}
_TORSO_RADII = {'pelvis': (0.16, 0.11, 0.11), 'spine': (0.15, None, 0.10),
                'chest': (0.17, None, 0.11)}
_TORSO_OVERLAP_M = 0.05            # torso ellipsoids reach this far past their segment
_HEAD_RADII = (0.085, 0.11, 0.095)
_HEAD_CENTRE_M = 0.10              # along the neck direction, from the head joint
_HAND_RADII = (0.045, 0.085, 0.025)
_TOE_LENGTH_M = 0.05


def body_part(name: str) -> str:
    """The body part a joint name describes ('limb' when the name says nothing)."""
    key = name.lower().rsplit(':', 1)[-1]
    key = re.sub(r'[^a-z0-9_]', '', key)
    for part, pattern in _PART_PATTERNS:
        if re.search(pattern, key):
            return part
    return 'limb'


def _segment_sum(clip: MocapClip, body: np.ndarray) -> float:
    """Sum of the body's segment lengths up to the hands and feet (fingers excluded), m."""
    rest = clip.rest_transforms[:, :3, 3]
    total = 0.0
    for j in body:
        parent = int(clip.parents[j])
        if parent in body and body_part(clip.joint_names[parent]) not in ('hand', 'toe'):
            total += float(np.linalg.norm(rest[j] - rest[parent]))
    return total


def _lateral_axis(clip: MocapClip, joint: int, body: np.ndarray, frame: int) -> np.ndarray:
    """World direction across the torso at `joint`: between its two children farthest apart
    (legs at the hips, shoulders at the chest), else that of the nearest torso relative."""
    positions = clip.positions[frame]
    order = [joint]
    ancestor = int(clip.parents[joint])
    while ancestor >= 0:
        order.append(ancestor)
        ancestor = int(clip.parents[ancestor])
    stack = clip.children(joint)
    while stack:
        child = stack.pop(0)
        order.insert(1, child)
        stack.extend(clip.children(child))
    for candidate in order:
        children = [c for c in clip.children(candidate) if c in body]
        if len(children) < 2:
            continue
        points = positions[children]
        gaps = np.linalg.norm(points[:, None] - points[None], axis=-1)
        a, b = np.unravel_index(np.argmax(gaps), gaps.shape)
        if gaps[a, b] > 1e-6:
            return (points[a] - points[b]) / gaps[a, b]
    return np.array([1.0, 0.0, 0.0])


def _segment_direction(clip: MocapClip, joint: int) -> np.ndarray:
    """Unit direction, in the joint's own frame, in which its segment leaves it; a leaf
    continues its parent's segment as it lies in the rest pose."""
    children = clip.children(joint)
    rest = clip.rest_transforms
    if children:
        tip = np.mean([rest[c, :3, 3] for c in children], axis=0) - rest[joint, :3, 3]
        local = rest[joint, :3, :3].T @ tip
    elif np.linalg.norm(clip.end_sites[joint]) > 1e-9:
        local = clip.end_sites[joint]
    else:
        parent = int(clip.parents[joint])
        along = rest[joint, :3, 3] - rest[parent, :3, 3] if parent >= 0 else np.array([0.0, 1.0, 0.0])
        local = rest[joint, :3, :3].T @ along
    norm = np.linalg.norm(local)
    return local / norm if norm > 1e-9 else np.array([0.0, 1.0, 0.0])


def _parts_of_joint(clip: MocapClip, joint: int, body: np.ndarray, scale: float, frame: int) -> list:
    """The rigid parts (joint-local meshes) of the segment(s) starting at `joint`."""
    part = body_part(clip.joint_names[joint])
    rest = clip.rest_transforms
    origin = np.zeros(3)
    children = [c for c in clip.children(joint) if c in body]
    direction = _segment_direction(clip, joint)
    meshes = []
    if part in _TORSO_RADII:
        lateral_world = _lateral_axis(clip, joint, body, frame)
        rotation = clip.world_transforms[frame, joint, :3, :3]
        lateral = rotation.T @ lateral_world
        lateral -= direction * float(lateral @ direction)
        lateral /= max(np.linalg.norm(lateral), 1e-9)
        depth = np.cross(lateral, direction)
        lateral_r, along_r, depth_r = _TORSO_RADII[part]
        centre = origin
        if along_r is not None:                 # the pelvis: a block around its joint
            along_r *= scale
        elif children:                          # spine and chest: their segment, overlapping
            tip = np.mean([rest[joint, :3, :3].T @ (rest[c, :3, 3] - rest[joint, :3, 3])
                           for c in children], axis=0)
            length = float(np.linalg.norm(tip))
            along_r = length / 2.0 + _TORSO_OVERLAP_M * scale
            centre = direction * length / 2.0
        else:
            along_r = 2.0 * _TORSO_OVERLAP_M * scale
        radii = np.array([lateral_r * scale, along_r, depth_r * scale])
        meshes.append(ellipsoid_mesh(centre, np.stack([lateral, direction, depth]), radii))
        return meshes
    if part == 'head' and not children:
        axes = _orthonormal_axes(direction)
        meshes.append(ellipsoid_mesh(direction * _HEAD_CENTRE_M * scale, axes,
                                     np.array(_HEAD_RADII) * scale))
        return meshes
    if part == 'hand' and not children:
        axes = _orthonormal_axes(direction)
        meshes.append(ellipsoid_mesh(direction * _HAND_RADII[1] * scale, axes,
                                     np.array(_HAND_RADII) * scale))
        return meshes
    radius = _CAPSULE_RADIUS.get(part, _CAPSULE_RADIUS['limb']) * scale
    if part == 'head':
        radius = _CAPSULE_RADIUS['neck'] * scale
    if not children:
        meshes.append(capsule_mesh(origin, direction * _TOE_LENGTH_M * scale, radius))
        return meshes
    for child in children:
        end = rest[joint, :3, :3].T @ (rest[child, :3, 3] - rest[joint, :3, 3])
        if np.linalg.norm(end) < 1e-6:
            continue
        if body_part(clip.joint_names[child]) in _TORSO_RADII:
            continue  # a limb ending in a torso part: the torso's own shape covers it
        meshes.append(capsule_mesh(origin, end, radius))
    return meshes


def _orthonormal_axes(direction: np.ndarray) -> np.ndarray:
    """(3, 3) rows: a unit vector across `direction`, `direction`, and the third axis."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(direction[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    across = np.cross(direction, helper)
    across /= np.linalg.norm(across)
    return np.stack([np.cross(direction, across), direction, across])


def mocap_body(clip: MocapClip, name: str = 'mocap') -> AnimatedBody:
    """Put a body on every frame of `clip`.

    Bones are the body's joints (each carries the segment(s) leaving it); ground-truth joints
    are the same joints, the top body joint (the pelvis) being the root. Shapes are built in
    each joint's frame from the first frame (joint frames are rigid with their segments, so
    any frame gives the same shapes).
    """
    body = body_joints(clip.parents, clip.positions, clip.joint_names)
    index = {int(j): i for i, j in enumerate(body)}
    scale = _segment_sum(clip, body) / _REFERENCE_SEGMENT_SUM_M
    if not scale > 0.0:
        raise ValueError(f'{clip.path}: the skeleton has no segments with length')
    parts = []
    for j in body:
        for vertices, triangles in _parts_of_joint(clip, int(j), body, scale, frame=0):
            parts.append(RigidPart(index[int(j)], vertices, triangles))
    names = [clip.joint_names[j] for j in body]
    parents = np.array([index.get(int(clip.parents[j]), -1) for j in body], dtype=np.int64)
    transforms = clip.world_transforms[:, body]
    return AnimatedBody(name, transforms, names, parents, names, parents.copy(),
                        np.arange(len(body)), parts=parts, frame_time=clip.frame_time,
                        description=f'{len(body)} joints from {clip.path}')


def limb_motion(body: AnimatedBody) -> np.ndarray:
    """(F - 1,) how far the joints moved between consecutive frames relative to the root
    bone (sum over joints, m): walking or turning alone scores nothing, a waving arm does."""
    transforms = body.bone_transforms
    root = int(np.flatnonzero(body.bone_parents < 0)[0])
    rotation, origin = transforms[:, root, :3, :3], transforms[:, root, :3, 3]
    local = np.einsum('fji,fgj->fgi', rotation, body.joints - origin[:, None])
    return np.linalg.norm(np.diff(local, axis=0), axis=-1).sum(axis=1)


def most_active_start(body: AnimatedBody, frames: int) -> int:
    """Start of the `frames`-long window with the most limb motion (0 if the clip is short)."""
    if body.n_frames <= frames:
        return 0
    motion = np.concatenate([[0.0], np.cumsum(limb_motion(body))])
    # motion within [s, s + frames): the steps s -> s + frames - 1
    totals = motion[frames - 1:] - motion[:len(motion) - frames + 1]
    return int(np.argmax(totals))


def facing_direction(body: AnimatedBody) -> np.ndarray:
    """(3,) horizontal world direction the body faces on average: where its feet point (heel
    to toe), else +z."""
    feet = [g for g, name in enumerate(body.joint_names) if body_part(name) == 'foot']
    toes = {int(body.joint_parents[g]): g for g, name in enumerate(body.joint_names)
            if body_part(name) == 'toe'}
    pairs = [(f, toes[f]) for f in feet if f in toes]
    if not pairs:
        return np.array([0.0, 0.0, 1.0])
    joints = body.joints
    direction = sum((joints[:, t] - joints[:, f]).mean(axis=0) for f, t in pairs)
    direction = direction * np.array([1.0, 0.0, 1.0])
    norm = np.linalg.norm(direction)
    return direction / norm if norm > 1e-9 else np.array([0.0, 0.0, 1.0])
