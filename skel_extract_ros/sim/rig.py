"""A skinned rig (libigl layout: mesh .obj, skeleton .tgf, weights .DMAT, key poses
-K.Tmat) blended smoothly between its rest pose and its key poses, as an AnimatedBody.

Rig facts (checked on a cow rig in this layout, see test/test_sim_sources.py):
a .Tmat holds, for every bone, a 4 x 3 matrix (3 x 3 linear part over a translation row)
applied to rest vertices as row vectors, v' = [v 1] @ T; stacked bone after bone. Bone i
is TGF edge i (parent joint -> child joint). Several bones may start at the same joint (the
cow's legs, neck and back all start at the withers): the bone with the most skinning
weight there is the root or the parent, the others hang from its start.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .animated import AnimatedBody, SkinnedSurface


class RigError(ValueError):
    """A rig directory that cannot be used; the message is one line naming the file."""


@dataclass
class Rig:
    """vertices (V, 3) and faces (T, 3) of the rest mesh (file units); joints (K, 3) rest
    joint positions; bones (B, 2) (start joint, end joint) 0-based; weights (V, B);
    poses: list of (B, 4, 4) absolute column-vector transforms (rest -> key pose)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    bones: np.ndarray
    weights: np.ndarray
    poses: list


def _read_obj(path: Path) -> tuple:
    """(vertices (V, 3), triangles (T, 3)) of an .obj, vertex order kept. Open3D splits
    vertices along texture seams (the cow's 11,666 become 46,656), which would break the
    per-vertex skinning weights, so the v and f lines are read here."""
    vertices, faces = [], []
    try:
        with open(path) as stream:
            for line in stream:
                if line.startswith('v '):
                    vertices.append(line.split()[1:4])
                elif line.startswith('f '):
                    corners = [int(token.split('/')[0]) for token in line.split()[1:]]
                    faces.extend([corners[0], corners[i], corners[i + 1]] for i in range(1, len(corners) - 1))
    except (OSError, ValueError, IndexError) as error:
        raise RigError(f'{path}: cannot read the mesh: {error}') from None
    if not vertices or not faces:
        raise RigError(f'{path}: no triangle mesh (v and f lines) found')
    vertices = np.array(vertices, dtype=float)
    faces = np.array(faces, dtype=np.int64)
    faces = np.where(faces > 0, faces - 1, faces + len(vertices))      # 1-based, negative = from the end
    return vertices, faces


def _numbers(path: Path) -> list:
    try:
        return path.read_text().split()
    except OSError as error:
        raise RigError(f'{path}: cannot read: {error}') from None


def load_rig(directory) -> Rig:
    """Read the rig in `directory` (<name>.obj, <name>.tgf, <name>.DMAT, <name>-K.Tmat)."""
    directory = Path(directory)
    if not directory.is_dir():
        raise RigError(f'{directory}: rig directory does not exist')
    tgfs = sorted(directory.glob('*.tgf'))
    if len(tgfs) != 1:
        raise RigError(f'{directory}: expected one .tgf skeleton, found {len(tgfs)}')
    name = tgfs[0].stem
    for suffix in ('.obj', '.DMAT'):
        if not (directory / f'{name}{suffix}').is_file():
            raise RigError(f'{directory}: {name}{suffix} is missing')
    vertices, faces = _read_obj(directory / f'{name}.obj')
    text = tgfs[0].read_text().split('#')
    if len(text) < 2:
        raise RigError(f'{tgfs[0]}: no "#" between joints and bones')
    try:
        joints = np.array([[float(v) for v in line.split()[1:4]] for line in text[0].strip().splitlines()])
        bones = np.array([[int(v) for v in line.split()[:2]] for line in text[1].strip().splitlines()]) - 1
    except (ValueError, IndexError) as error:
        raise RigError(f'{tgfs[0]}: malformed line: {error}') from None
    if joints.ndim != 2 or joints.shape[1] != 3 or bones.ndim != 2 or bones.min() < 0 or bones.max() >= len(joints):
        raise RigError(f'{tgfs[0]}: joints must be "index x y z" and bones pairs of joint indices')
    values = _numbers(directory / f'{name}.DMAT')
    try:
        columns, rows = int(values[0]), int(values[1])
        weights = np.array(values[2:], dtype=float).reshape(columns, rows).T     # column-major
    except (ValueError, IndexError) as error:
        raise RigError(f'{directory / (name + ".DMAT")}: malformed weights: {error}') from None
    if weights.shape != (len(vertices), len(bones)):
        raise RigError(f'{name}.DMAT: weights are {weights.shape[0]} x {weights.shape[1]}, the rig has '
                       f'{len(vertices)} vertices and {len(bones)} bones')
    poses = []
    for tmat in sorted(directory.glob(f'{name}-*.Tmat')):
        try:
            rows_4x3 = np.array(_numbers(tmat), dtype=float).reshape(len(bones), 4, 3)
        except ValueError:
            raise RigError(f'{tmat}: expected {len(bones)} bones x 4 x 3 numbers') from None
        absolute = np.tile(np.eye(4), (len(bones), 1, 1))
        absolute[:, :3, :3] = np.transpose(rows_4x3[:, :3], (0, 2, 1))   # row-vector -> column form
        absolute[:, :3, 3] = rows_4x3[:, 3]
        poses.append(absolute)
    if not poses:
        raise RigError(f'{directory}: no key pose ({name}-K.Tmat)')
    return Rig(name, vertices, faces, joints, bones, weights, poses)


def bone_tree(rig: Rig) -> np.ndarray:
    """(B,) parent bone of every bone, -1 for the root. A bone's parent is the bone that
    ends at its start joint; bones that start where no bone ends (several may) hang from
    the one among them with the most bones below it (the cow's back, not its heavy head
    or a leg), the root; skinning weight breaks ties."""
    n_bones = len(rig.bones)
    mass = rig.weights.sum(axis=0)
    parents = np.full(n_bones, -1)
    for b, (start, _end) in enumerate(rig.bones):
        ending = np.flatnonzero(rig.bones[:, 1] == start)
        if len(ending):
            parents[b] = int(ending[0])
    bones_below = np.ones(n_bones)
    for b in sorted(range(n_bones), key=lambda b: -_depth(parents, b)):   # leaves first
        if parents[b] >= 0:
            bones_below[parents[b]] += bones_below[b]
    orphans = np.flatnonzero(parents < 0)
    root = int(orphans[np.lexsort((mass[orphans], bones_below[orphans]))[-1]])
    parents[orphans[orphans != root]] = root
    return parents


def _skin(rig: Rig, transforms: np.ndarray) -> np.ndarray:
    """(F, V, 3) linear blend skinning of the rest vertices with (F, B, 4, 4) transforms."""
    moved = np.einsum('fbij,vj->fbvi', transforms[..., :3, :3], rig.vertices) + transforms[:, :, None, :3, 3]
    return np.einsum('vb,fbvi->fvi', rig.weights, moved)


def rig_body(rig: Rig, frames: int, seed: int = 0, frame_time: float = 1.0 / 30.0,
             length_m: float = 2.0) -> AnimatedBody:
    """The rig moving smoothly rest -> key pose -> rest -> next key pose ... (each leg of
    the path 24-36 frames, seeded, cosine-eased), scaled so its longest side is `length_m`
    and standing on y = 0. Bone rotations relative to the parent bone are interpolated
    (slerp) about each bone's start joint, so joints stay connected; the root also moves
    between its key positions.
    """
    rng = np.random.default_rng(seed)
    parents = bone_tree(rig)
    n_bones = len(rig.bones)
    starts = rig.joints[rig.bones[:, 0]]                                      # (B, 3)
    # waypoints of relative rotations (B,) and root displacement, rest first
    keys = [np.tile(np.eye(4), (n_bones, 1, 1))]
    order = list(rng.permutation(len(rig.poses)))
    while len(keys) < 2 * frames:
        keys += [rig.poses[order[len(keys) // 2 % len(order)]], keys[0]]
    relative, displacement = [], []
    for absolute in keys:
        rotation = absolute[:, :3, :3]
        rel = np.einsum('bji,bjk->bik', rotation[np.maximum(parents, 0)], rotation)
        rel[parents < 0] = rotation[parents < 0]
        relative.append(rel)
        displacement.append(absolute[:, :3, :3] @ starts[:, :, None] + absolute[:, :3, 3:] - starts[:, :, None])
    # path: each leg lasts 24-36 frames
    legs = rng.integers(24, 37, size=len(keys) - 1)
    ends = np.concatenate([[0], np.cumsum(legs)])
    times = np.arange(frames, dtype=float)
    leg = np.clip(np.searchsorted(ends, times, side='right') - 1, 0, len(legs) - 1)
    progress = np.clip((times - ends[leg]) / legs[leg], 0.0, 1.0)
    eased = 0.5 - 0.5 * np.cos(np.pi * progress)
    rotations = np.empty((frames, n_bones, 3, 3))
    for b in range(n_bones):   # loop over bones, not vertices
        key_rotations = Rotation.from_matrix(np.stack([r[b] for r in relative]))
        slerp = Slerp(np.arange(len(keys)), key_rotations)
        rotations[:, b] = slerp(leg + eased).as_matrix()
    root = int(np.flatnonzero(parents < 0)[0])
    root_shift = np.stack([d[root, :, 0] for d in displacement])               # (K, 3)
    shift = root_shift[leg] * (1 - eased)[:, None] + root_shift[leg + 1] * eased[:, None]
    # forward kinematics: each bone turns about its start joint, carried by its parent
    world_rotation = np.empty((frames, n_bones, 3, 3))
    origin = np.empty((frames, n_bones, 3))
    transforms = np.tile(np.eye(4), (frames, n_bones, 1, 1))                   # rest -> posed
    for b in _parents_first(parents):
        if parents[b] < 0:
            world_rotation[:, b] = rotations[:, b]
            origin[:, b] = starts[b] + shift
        else:
            p = parents[b]
            world_rotation[:, b] = world_rotation[:, p] @ rotations[:, b]
            origin[:, b] = np.einsum('fij,j->fi', transforms[:, p, :3, :3], starts[b]) + transforms[:, p, :3, 3]
        transforms[:, b, :3, :3] = world_rotation[:, b]
        transforms[:, b, :3, 3] = origin[:, b] - np.einsum('fij,j->fi', world_rotation[:, b], starts[b])
    vertices = _skin(rig, transforms)
    # scale to metres, feet on the floor, body over the origin
    scale = length_m / float(np.ptp(rig.vertices, axis=0).max())
    offset = -np.array([rig.vertices[:, 0].mean(), rig.vertices[:, 1].min(), rig.vertices[:, 2].mean()])
    vertices = (vertices + offset) * scale
    bone_transforms = np.tile(np.eye(4), (frames, n_bones, 1, 1))
    bone_transforms[..., :3, :3] = world_rotation
    bone_transforms[..., :3, 3] = (origin + offset) * scale
    # one ground-truth joint per distinct start joint: the bone with the most weight there
    mass = rig.weights.sum(axis=0)
    joint_bones = []
    for start in np.unique(rig.bones[:, 0]):
        candidates = np.flatnonzero(rig.bones[:, 0] == start)
        joint_bones.append(int(candidates[np.argmax(mass[candidates])]))
    joint_bones = np.array(sorted(joint_bones, key=lambda b: _depth(parents, b)))
    joint_of_start = {int(rig.bones[b, 0]): g for g, b in enumerate(joint_bones)}

    def joint_parent(bone: int) -> int:
        """The joint of the nearest ancestor bone that starts elsewhere (-1: none)."""
        ancestor = parents[bone]
        while ancestor >= 0 and rig.bones[ancestor, 0] == rig.bones[bone, 0]:
            ancestor = parents[ancestor]
        return joint_of_start[int(rig.bones[ancestor, 0])] if ancestor >= 0 else -1
    joint_parents = np.array([joint_parent(int(b)) for b in joint_bones])
    return AnimatedBody(rig.name, bone_transforms, [f'bone_{b}' for b in range(n_bones)], parents,
                        [f'joint_{rig.bones[b, 0] + 1}' for b in joint_bones], joint_parents, joint_bones,
                        skin=SkinnedSurface(vertices, rig.faces, rig.weights.argmax(axis=1)),
                        frame_time=frame_time, description=f'{rig.name} rig, {n_bones} bones')


def _depth(parents: np.ndarray, bone: int) -> int:
    depth = 0
    while parents[bone] >= 0:
        bone, depth = parents[bone], depth + 1
    return depth


def _parents_first(parents: np.ndarray) -> list:
    return sorted(range(len(parents)), key=lambda b: _depth(parents, b))
