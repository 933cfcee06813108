"""Motion capture clips (BVH) as per-frame joint transforms.

Parsing and forward kinematics are bvhio's (a maintained BVH library). Two things it does
badly for us are done here, both small: bvhio accepts a motion line with too many values
(silently ignoring the rest) and fails on a truncated MOTION block with an error that does
not name the problem, so the file is checked first (frame count, values per line); and
bvhio leaves units to the caller, so the clip is scaled to metres from the skeleton's size.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

# Length units a BVH may use, tried from the largest: the first that makes the skeleton's
# extent a plausible body size in metres wins (a person is ~1.7 m; a hand ~0.2 m).
_UNIT_SCALES = {'m': 1.0, 'cm': 0.01, 'mm': 0.001, 'in': 0.0254}
_MAX_PLAUSIBLE_EXTENT_M = 5.0


class BvhError(ValueError):
    """A BVH file that cannot be used; the message is one line naming the file."""


@dataclass
class MocapClip:
    """A BVH clip in metres.

    joint_names: (J,); parents: (J,) parent joint, -1 for the top.
    world_transforms: (F, J, 4, 4) world-from-joint in the BVH world (y up), metres. Each
        joint's frame is rigid with the segment from it to its children (bvhio orients it
        so the segment runs along local +y).
    end_sites: (J, 3) end-site offset in the joint's frame, m (zero where there is none).
    rest_transforms: (J, 4, 4) world-from-joint in the rest pose (every rotation channel
        zero, the pose the hierarchy's offsets describe), m.
    frame_time: s between frames; unit_scale: metres per file unit.
    """

    path: str
    joint_names: list
    parents: np.ndarray
    world_transforms: np.ndarray
    end_sites: np.ndarray
    rest_transforms: np.ndarray
    frame_time: float
    unit_scale: float

    @property
    def n_frames(self) -> int:
        return int(self.world_transforms.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """(F, J, 3) world joint positions, m."""
        return self.world_transforms[:, :, :3, 3]

    def children(self, joint: int) -> list:
        return [int(c) for c in np.flatnonzero(self.parents == joint)]

    def resampled(self, frame_time: float) -> 'MocapClip':
        """Every k-th frame so that frames are about `frame_time` apart (k >= 1)."""
        step = max(1, int(round(frame_time / self.frame_time)))
        if step == 1:
            return self
        return MocapClip(self.path, self.joint_names, self.parents, self.world_transforms[::step],
                         self.end_sites, self.rest_transforms, self.frame_time * step, self.unit_scale)


def _check_motion_block(path: Path, text: str) -> None:
    """Raise BvhError for what bvhio would misread: the frame count or values per line."""
    channels = sum(int(n) for n in re.findall(r'CHANNELS\s+(\d+)', text))
    head, found, motion = text.partition('MOTION')
    if not found:
        raise BvhError(f'{path}: no MOTION block')
    lines = [line.split() for line in motion.strip().splitlines()]
    lines = [tokens for tokens in lines if tokens]
    if len(lines) < 2 or lines[0][:1] != ['Frames:'] or lines[1][:2] != ['Frame', 'Time:']:
        raise BvhError(f'{path}: MOTION must start with "Frames: N" and "Frame Time: T"')
    try:
        n_frames = int(lines[0][1])
        frame_time = float(lines[1][2])
    except (IndexError, ValueError):
        raise BvhError(f'{path}: unreadable "Frames:" or "Frame Time:" line') from None
    if n_frames < 1 or not frame_time > 0.0:
        raise BvhError(f'{path}: {n_frames} frames of {frame_time} s; need at least one frame and a positive frame time')
    motion_lines = lines[2:]
    if len(motion_lines) < n_frames:
        raise BvhError(f'{path}: truncated MOTION block: {len(motion_lines)} of {n_frames} frames')
    counts = np.array([len(tokens) for tokens in motion_lines[:n_frames]])
    wrong = np.flatnonzero(counts != channels)
    if len(wrong):
        raise BvhError(f'{path}: frame {wrong[0] + 1} has {counts[wrong[0]]} values, the hierarchy '
                       f'declares {channels} channels')


def load_bvh(path, units: str = 'auto') -> MocapClip:
    """Read a BVH clip; `units` is one of m, cm, mm, in or auto (from the skeleton's size)."""
    import bvhio

    path = Path(path)
    if not path.is_file():
        raise BvhError(f'{path}: BVH file does not exist')
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise BvhError(f'{path}: cannot read: {error}') from None
    if not text.lstrip().startswith('HIERARCHY'):
        raise BvhError(f'{path}: not a BVH file (no HIERARCHY at the start)')
    _check_motion_block(path, text)
    try:
        container = bvhio.readAsBvh(str(path))
        root = bvhio.convertBvhToHierarchy(container.Root)
    except Exception as error:  # bvhio raises SyntaxError/IndexError/ValueError alike
        raise BvhError(f'{path}: malformed BVH: {error}') from None
    layout = root.layout()
    bvh_layout = container.Root.layout()
    names = [joint.Name for joint, _, _ in layout]
    index = {name: i for i, name in enumerate(names)}
    parents = np.array([index[j.Parent.Name] if j.Parent is not None else -1 for j, _, _ in layout])
    n_frames, n_joints = container.FrameCount, len(layout)
    positions = np.empty((n_frames, n_joints, 3))
    quaternions = np.empty((n_frames, n_joints, 4))
    for frame in range(n_frames):  # bvhio's forward kinematics, one pose at a time
        root.loadPose(frame)
        for i, (joint, _, _) in enumerate(layout):
            p, q = joint.PositionWorld, joint.RotationWorld
            positions[frame, i] = (p.x, p.y, p.z)
            quaternions[frame, i] = (q.x, q.y, q.z, q.w)
    rotations = Rotation.from_quat(quaternions.reshape(-1, 4)).as_matrix().reshape(n_frames, n_joints, 3, 3)
    # In the rest pose (every rotation channel zero) the file's joint axes are the world's,
    # so an end site lies at its joint plus the file offset; bvhio's re-oriented joint frame
    # at rest turns that into the joint-local offset used for every frame.
    root.loadRestPose()
    end_sites = np.zeros((n_joints, 3))
    rest_transforms = np.tile(np.eye(4), (n_joints, 1, 1))
    for i, ((joint, _, _), (bvh_joint, _, _)) in enumerate(zip(layout, bvh_layout)):
        p, q = joint.PositionWorld, joint.RotationWorld
        rest_rotation = Rotation.from_quat([q.x, q.y, q.z, q.w])
        rest_transforms[i, :3, :3] = rest_rotation.as_matrix()
        rest_transforms[i, :3, 3] = (p.x, p.y, p.z)
        if not bvh_joint.Children:
            end_sites[i] = rest_rotation.inv().apply(list(bvh_joint.EndSite))
    transforms = np.zeros((n_frames, n_joints, 4, 4))
    transforms[..., :3, :3] = rotations
    transforms[..., :3, 3] = positions
    transforms[..., 3, 3] = 1.0
    scale = _unit_scale(positions, body_joints(parents, positions, names), units, path)
    transforms[..., :3, 3] *= scale
    rest_transforms[:, :3, 3] *= scale
    return MocapClip(str(path), names, parents, transforms, end_sites * scale, rest_transforms,
                     float(container.FrameTime), scale)


def body_joints(parents: np.ndarray, positions: np.ndarray, names=None) -> np.ndarray:
    """Indices of the joints that belong to the body: all but a top node that only marks
    the ground origin (a single child, and either a name saying so or a child that moves
    relative to it: body segments are rigid).

    parents: (J,); positions: (F, J, 3) in any unit; names: (J,) joint names.
    """
    joints = np.arange(len(parents))
    children = np.flatnonzero(parents == 0)
    if len(children) != 1:
        return joints
    if names is not None and re.search(r'root|reference|world|origin|trajectory', str(names[0]).lower()):
        return joints[1:]
    length = np.linalg.norm(positions[:, children[0]] - positions[:, 0], axis=-1)
    size = np.linalg.norm(np.ptp(positions[0], axis=0))
    if positions.shape[0] > 1 and np.ptp(length) > 0.01 * size:
        return joints[1:]
    return joints


def _unit_scale(positions: np.ndarray, body: np.ndarray, units: str, path: Path) -> float:
    """Metres per file unit; `body` indexes the joints that belong to the body."""
    if units != 'auto':
        if units not in _UNIT_SCALES:
            raise BvhError(f'unknown BVH units {units!r}; choose auto, {", ".join(_UNIT_SCALES)}')
        return _UNIT_SCALES[units]
    # The body's extent in one frame (the body may travel metres over the clip, and a
    # top node that stays on the ground origin is not part of it).
    extent = float(np.median(np.linalg.norm(np.ptp(positions[:, body], axis=1), axis=-1)))
    if not extent > 0.0:
        raise BvhError(f'{path}: every joint is at the same place; cannot tell the units')
    # Inches are not guessed: a person in inches looks like a child in centimetres.
    for name in ('m', 'cm', 'mm'):
        if extent * _UNIT_SCALES[name] <= _MAX_PLAUSIBLE_EXTENT_M:
            return _UNIT_SCALES[name]
    return _UNIT_SCALES['mm']
