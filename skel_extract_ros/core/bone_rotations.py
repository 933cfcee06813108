"""Each bone's rotation (rest -> frame) from the joint positions, for the outputs that carry
rotations (skeleton.bvh, skeleton/trajectory, the joints' PoseArray orientations).

Per frame, the world rotation W_b of bone b is the rotation that best carries the rest
offsets of b's child joints onto their offsets in that frame (Kabsch). The twist the child
offsets leave open (one child, or none) is taken nearest a hint: the bone's rigid fit to
its registered points where known (point_fit_rotations), else the parent's rotation.
"""
from __future__ import annotations

import numpy as np

from .rigid import fit_rigid_segments, rotations_from_h

_HINT_WEIGHT = 1e-9             # the twist hint decides only what the child offsets leave open


def children_of(parents) -> list:
    """[the child bones of each bone] of a bone tree given as parents (B,), -1 at the root."""
    return [[int(c) for c in np.flatnonzero(parents == b)] for b in range(len(parents))]


def depth_first(parents) -> np.ndarray:
    """(B,) the bones parents first (depth first from the one root); ValueError when the
    tree has several roots or is not connected."""
    roots = np.flatnonzero(parents < 0)
    if len(roots) != 1:
        raise ValueError(f'the joint tree must have exactly one root, has {len(roots)}')
    children, order, stack = children_of(parents), [], [int(roots[0])]
    while stack:
        b = stack.pop()
        order.append(b)
        stack.extend(reversed(children[b]))
    if len(order) != len(parents):
        raise ValueError('the joint tree is not connected (a parent index loops or is out of range)')
    return np.array(order)


def point_fit_rotations(rest_points, labels, registered, n_bones: int) -> np.ndarray:
    """(F, B, 3, 3) each bone's rigid fit (Kabsch) of its rest points (M, 3), labels (M,),
    onto its registered points (F, M, 3); NaN for frames with non-finite points and for
    bones without points."""
    registered = np.asarray(registered, dtype=np.float64)
    result = np.full((len(registered), n_bones, 3, 3), np.nan)
    finite = np.isfinite(registered).all(axis=(1, 2))
    if finite.any():
        result[finite] = fit_rigid_segments(np.asarray(rest_points, dtype=np.float64), registered[finite],
                                             labels, n_bones)[0]
    result[:, np.bincount(labels, minlength=n_bones)[:n_bones] == 0] = np.nan
    return result


def bone_rotations(parents, rest_joints, positions, hints=None) -> np.ndarray:
    """(F, J, 3, 3) world rotation (rest -> frame) of every bone from the joint positions
    (F, J, 3): the Kabsch fit of the rest offsets of its child joints onto the frame's, the
    twist left open (one child, or none) taken nearest `hints` (F, J, 3, 3; NaN where
    unknown) or else the parent's rotation. Frames must be finite."""
    parents = np.asarray(parents)
    rest_joints = np.asarray(rest_joints, dtype=np.float64)
    F, J = positions.shape[:2]
    children = children_of(parents)
    world = np.empty((F, J, 3, 3))
    for b in depth_first(parents):   # parents first
        p = parents[b]
        hint = np.broadcast_to(np.eye(3), (F, 3, 3)).copy() if p < 0 else world[:, p].copy()
        if hints is not None:
            known = np.isfinite(hints[:, b]).all(axis=(1, 2))
            hint[known] = hints[known, b]
        H = np.zeros((F, 3, 3))
        scale = np.zeros(F)
        for c in children[b]:
            rest = rest_joints[c] - rest_joints[b]
            now = positions[:, c] - positions[:, b]
            H += rest[None, :, None] * now[:, None, :]                     # tr(R u v^T) = v . R u
            scale += np.linalg.norm(rest) * np.linalg.norm(now, axis=1)
        weight = np.where(scale > 0, _HINT_WEIGHT * scale, 1.0)
        H += weight[:, None, None] * np.transpose(hint, (0, 2, 1))          # tr(R W^T) = <R, W>
        world[:, b] = rotations_from_h(H)
    return world
