"""The extracted skeleton as a BVH motion file (`skeleton.bvh`), for Blender, motion
retargeting and learning-from-demonstration tools. No ROS import.

Hierarchy. One BVH joint per joint of the skeleton (names: the skeleton's joint names).
Joint b sits between bone b and its parent bone, so the BVH rotation of JOINT b, which
turns the offsets of b's children, is the rotation of bone b. The ROOT is the root joint
(the root bone's centre) with 6 channels; its OFFSET is 0 0 0 and its position channels
hold its absolute position (BVH readers disagree on whether a root's position channels
add to its OFFSET; with a zero OFFSET both readings agree). A JOINT's OFFSET is
rest_joints[b] - rest_joints[parent]; every leaf ends in an `End Site` at its bone's far
end: the farthest of the bone's rest points along the direction from the joint to the
bone's centroid (the bone's main axis when the centroid is at the joint).

Frames. Per frame, the world rotation W_b of every bone is the rotation that best carries
the rest offsets of b's child joints onto their offsets in that frame (Kabsch); the file
holds the local rotations W_parent^T W_b (the root: W_root) and the root position. Of the
rotations that carry the child offsets equally well (the twist of a joint with a single
child about that child, every rotation of a leaf) the one nearest the bone's rigid fit to
its registered points is taken; without those (no points given, or not finite in a
frame) the one nearest the parent's rotation (no twist relative to the parent; a leaf
turns with its parent). That twist moves no joint and is poorly determined for a thin limb
(on the sample bag the points' fit and Alg. 2's bone rotation differ by 20-35 deg about the
arms); it matters only for a mesh skinned to the BVH. So the rotations come from the joint
positions, the only thing `skel-extract replay` receives from the nodes besides the points,
and `run` and `replay` write their BVH the same way. The BVH's bones have the rest lengths, so the forward
kinematics reproduce the joint positions up to how much the estimated joints' distances
change from frame to frame (`BvhMotion.deviation`).

A frame with a non-finite joint position repeats the pose of the frame before it (the
first finite frame for the leading ones); with no finite frame at all every frame is the
rest pose. No frames give a valid file with `Frames: 0` (the skeleton only).

Conventions: lengths in metres (Blender's importer reads them at true size with its
default scale 1.0; for tools that expect centimetres, scale by 100 on import), in the
skeleton's frame (skeleton.json's `frame_id`, for a depth camera its optical frame: x
right, y down, z away from the camera; import into Blender with Forward -Z, Up -Y to see
the subject upright). Rotation channels `Zrotation Xrotation Yrotation` in degrees:
R = Rz(z) Rx(x) Ry(y) (intrinsic, the usual BVH reading; Blender and bvhio read it so),
each channel unwrapped over time. Frame Time is the median interval of the stamps (1/30 s
with fewer than two).

The text is written here rather than with bvhio's writer (bvhio is used to read it back
in the tests and by the simulator): bvhio's writer converts to Euler angles in float32 and
drops two of the three angles at gimbal lock (x = +-90 deg), which moved a joint 21 cm in
a check, and writes offsets like 0.300000012.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.bone_rotations import bone_rotations, children_of, depth_first, point_fit_rotations

ROTATION_CHANNELS = ('Zrotation', 'Xrotation', 'Yrotation')
_EULER_ORDER = 'ZXY'            # intrinsic: R = Rz Rx Ry, the channel order above
DEFAULT_FRAME_TIME = 1.0 / 30.0


@dataclass
class BvhMotion:
    """A skeleton's BVH: names (J,), parents (J,), order (J,) joint indices in file order
    (depth first from the root), offsets (J, 3) m (root: 0), end_sites (J, 3) m (zero for
    joints with children), root_positions (F, 3) m, local_rotations (F, J, 3, 3),
    frame_time s, held (F,) frames that repeat an earlier pose (non-finite joints),
    deviation (F, J) m between the BVH's forward kinematics and the joint positions given
    (NaN on held frames)."""

    names: list
    parents: np.ndarray
    order: np.ndarray
    offsets: np.ndarray
    end_sites: np.ndarray
    root_positions: np.ndarray
    local_rotations: np.ndarray
    frame_time: float
    held: np.ndarray
    deviation: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.root_positions)

    def forward_kinematics(self) -> np.ndarray:
        """(F, J, 3) world joint positions of the BVH pose, m."""
        return forward_kinematics(self.parents, self.offsets, self.root_positions, self.local_rotations)

    def text(self) -> str:
        """The BVH file."""
        lines = ['HIERARCHY']
        children = children_of(self.parents)

        def joint(b, depth):
            indent = '\t' * depth
            root = self.parents[b] < 0
            lines.append(f'{indent}{"ROOT" if root else "JOINT"} {self.names[b]}')
            lines.append(f'{indent}{{')
            lines.append(f'{indent}\tOFFSET {_numbers(self.offsets[b])}')
            channels = (('Xposition', 'Yposition', 'Zposition') if root else ()) + ROTATION_CHANNELS
            lines.append(f'{indent}\tCHANNELS {len(channels)} {" ".join(channels)}')
            for child in children[b]:
                joint(child, depth + 1)
            if not children[b]:
                lines.extend([f'{indent}\tEnd Site', f'{indent}\t{{',
                              f'{indent}\t\tOFFSET {_numbers(self.end_sites[b])}', f'{indent}\t}}'])
            lines.append(f'{indent}}}')

        joint(int(self.order[0]), 0)
        lines += ['MOTION', f'Frames: {self.n_frames}', f'Frame Time: {self.frame_time:.9g}']
        if self.n_frames:
            angles = euler_channels(self.local_rotations[:, self.order])              # (F, J, 3)
            values = np.concatenate([self.root_positions, angles.reshape(self.n_frames, -1)], axis=1)
            lines += [_numbers(row) for row in values]
        return '\n'.join(lines) + '\n'


def _numbers(values) -> str:
    return ' '.join(f'{v:.6f}' for v in np.asarray(values, dtype=np.float64))


def euler_channels(rotations) -> np.ndarray:
    """(F, J, 3) degrees [z, x, y] of rotations (F, J, 3, 3), R = Rz Rx Ry, each channel
    unwrapped over the frames (adding 360 deg to one angle keeps the rotation)."""
    F, J = rotations.shape[:2]
    if F == 0:
        return np.zeros((0, J, 3))
    with warnings.catch_warnings():     # gimbal lock: scipy sets the third angle to 0, exactly
        warnings.simplefilter('ignore', UserWarning)
        angles = Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_euler(_EULER_ORDER, degrees=True)
    return np.unwrap(angles.reshape(F, J, 3), period=360.0, axis=0)


def forward_kinematics(parents, offsets, root_positions, local_rotations) -> np.ndarray:
    """(F, J, 3) world joint positions from the BVH's parts (see BvhMotion)."""
    parents = np.asarray(parents)
    F, J = local_rotations.shape[:2]
    world = np.empty((F, J, 3, 3))
    positions = np.empty((F, J, 3))
    for b in depth_first(parents):   # loop over joints, vectorised over frames
        p = parents[b]
        if p < 0:
            world[:, b] = local_rotations[:, b]
            positions[:, b] = root_positions
        else:
            world[:, b] = world[:, p] @ local_rotations[:, b]
            positions[:, b] = positions[:, p] + world[:, p] @ offsets[b]
    return positions


def end_sites(parents, rest_joints, rest_points=None, labels=None) -> np.ndarray:
    """(J, 3) End Site offsets (m, rest frame) of the leaves, zero elsewhere: the farthest
    rest point of the bone along the direction from its joint to its centroid (the main
    axis of its points when the centroid is at the joint). Without points: the leaf
    continues the direction from its parent joint by the same length."""
    parents = np.asarray(parents)
    rest_joints = np.asarray(rest_joints, dtype=np.float64)
    children = children_of(parents)
    result = np.zeros((len(parents), 3))
    for b in (b for b in range(len(parents)) if not children[b]):
        points = (np.asarray(rest_points, dtype=np.float64)[np.asarray(labels) == b]
                  if rest_points is not None and labels is not None else np.empty((0, 3)))
        if len(points):
            relative = points - rest_joints[b]
            direction = relative.mean(axis=0)
            extent = np.linalg.norm(np.ptp(points, axis=0))
            if np.linalg.norm(direction) <= 1e-3 * extent and len(points) > 1:
                direction = np.linalg.svd(relative - relative.mean(axis=0), full_matrices=False)[2][0]
            norm = np.linalg.norm(direction)
            if norm > 0:
                direction = direction / norm
                result[b] = direction * max(float(np.max(relative @ direction)), 0.0)
                continue
        if parents[b] >= 0:
            result[b] = rest_joints[b] - rest_joints[parents[b]]
    return result


def skeleton_motion(names, parents, rest_joints, stamps, positions, rest_points=None, labels=None,
                    registered=None) -> BvhMotion:
    """The BVH of a skeleton: names (J,), parents (J,), rest_joints (J, 3) m, stamps (F,) s,
    positions (F, J, 3) m (skeleton.json's), and optionally the rest points (M, 3), their
    bone labels (M,) and registered points (F, M, 3) for the End Sites and the twists
    (ignored when their sizes do not match)."""
    parents = np.asarray(parents, dtype=np.int64)
    rest_joints = np.asarray(rest_joints, dtype=np.float64).reshape(-1, 3)
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, len(parents), 3)
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    J, F = len(parents), len(positions)
    if len(names) != J or len(rest_joints) != J:
        raise ValueError(f'{len(names)} names and {len(rest_joints)} rest joints for {J} parents')
    if len(stamps) != F:
        raise ValueError(f'{len(stamps)} stamps for {F} frames of joint positions')
    order = depth_first(parents)
    names = [str(n).replace(' ', '_') or f'joint_{i}' for i, n in enumerate(names)]
    if len(set(names)) != J:
        raise ValueError(f'joint names must be unique: {names}')
    if rest_points is not None and labels is not None:
        labels = np.asarray(labels, dtype=np.int64)
        if len(labels) != len(rest_points) or (labels.size and not 0 <= labels.min() <= labels.max() < J):
            rest_points = labels = None
    else:
        rest_points = labels = None
    hints = None
    if rest_points is not None and registered is not None:
        registered = np.asarray(registered, dtype=np.float64)
        if registered.shape == (F, len(rest_points), 3):
            hints = point_fit_rotations(rest_points, labels, registered, J)

    offsets = rest_joints - rest_joints[np.maximum(parents, 0)]
    root = int(order[0])
    offsets[root] = 0.0
    good = np.flatnonzero(np.isfinite(positions).all(axis=(1, 2)))
    held = np.ones(F, dtype=bool)
    held[good] = False
    world = np.broadcast_to(np.eye(3), (F, J, 3, 3)).copy()
    root_positions = np.broadcast_to(rest_joints[root], (F, 3)).copy()
    if len(good):
        world[good] = bone_rotations(parents, rest_joints, positions[good],
                                     None if hints is None else hints[good])
        root_positions[good] = positions[good, root]
        source = good[np.maximum(np.searchsorted(good, np.arange(F), side='right') - 1, 0)]
        world, root_positions = world[source], root_positions[source]
    local = world.copy()
    child = parents >= 0
    local[:, child] = np.transpose(world[:, parents[child]], (0, 1, 3, 2)) @ world[:, child]
    steps = np.diff(stamps)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    frame_time = float(np.median(steps)) if len(steps) else DEFAULT_FRAME_TIME
    motion = BvhMotion(names, parents, order, offsets, end_sites(parents, rest_joints, rest_points, labels),
                       root_positions, local, frame_time, held, np.full((F, J), np.nan))
    deviation = np.linalg.norm(motion.forward_kinematics() - positions, axis=2)
    motion.deviation = np.where(held[:, None], np.nan, deviation)
    return motion


def write_skeleton_bvh(path, names, parents, rest_joints, stamps, positions, rest_points=None, labels=None,
                       registered=None) -> BvhMotion:
    """Write `path` (skeleton.bvh) for the skeleton (see skeleton_motion); returns its motion."""
    motion = skeleton_motion(names, parents, rest_joints, stamps, positions, rest_points, labels, registered)
    Path(path).write_text(motion.text())
    return motion
