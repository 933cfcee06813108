"""Registration scores: each registered point followed as the material point it started on."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ...core.point_sets import median_spacing
from .data import EvaluationError, GroundTruth, match_frames


def _material_trajectories(first: np.ndarray, gt: 'GroundTruth', gt_idx: np.ndarray, anchor: int = 0):
    """The material points under `first` (P, 3) at frame gt_idx[anchor]: their true
    trajectories (F, P, 3), each point's distance to the surface it is tied to beyond the
    ground truth's own sampling spacing (P,), and the bone each is tied to (P,), -1 where
    unknown."""
    surface = gt.surface_points[gt_idx]
    if gt.surface_faces is not None and len(gt.surface_faces):
        import open3d as o3d
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(surface[anchor].astype(np.float32)),
                            o3d.core.Tensor(gt.surface_faces.astype(np.uint32)))
        closest = scene.compute_closest_points(o3d.core.Tensor(first.astype(np.float32)))
        triangles = gt.surface_faces[closest['primitive_ids'].numpy().astype(np.int64)]
        uv = closest['primitive_uvs'].numpy().astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        on_surface = np.einsum('pk,pki->pi', bary, surface[anchor][triangles])
        offset = first - on_surface
        trajectories = np.einsum('pk,fpki->fpi', bary, surface[:, triangles]) + offset
        bones = (gt.surface_bone_ids[triangles[:, 0]] if gt.surface_bone_ids is not None
                 else np.full(len(first), -1))
        # the mesh is the exact surface: any distance from it is off the body
        return trajectories, np.linalg.norm(offset, axis=1), bones
    tree = cKDTree(surface[anchor])
    tie_distance, tie = tree.query(first)
    # samples are a few cm apart: a point on the surface between them is up to a spacing
    # from the nearest one, which is not an error
    spacing = float(np.median(tree.query(surface[anchor], k=2)[0][:, 1]))
    off_surface = np.maximum(tie_distance - spacing, 0.0)
    bones = gt.surface_bone_ids[tie] if gt.surface_bone_ids is not None else np.full(len(first), -1)
    if gt.bone_transforms is not None and gt.surface_bone_ids is not None:
        transforms = gt.bone_transforms[gt_idx].astype(np.float64)
        start = transforms[anchor, bones]                              # (P, 4, 4)
        local = np.einsum('pji,pj->pi', start[:, :3, :3], first - start[:, :3, 3])
        carried = transforms[:, bones]                                  # (F, P, 4, 4)
        trajectories = np.einsum('fpij,pj->fpi', carried[..., :3, :3], local) + carried[..., :3, 3]
        return trajectories, off_surface, bones
    return surface[:, tie], off_surface, bones


def evaluate_registration(points: np.ndarray, stamps: np.ndarray, gt: GroundTruth,
                          drift_frames=(30, 60, 90), rest_points: np.ndarray | None = None) -> dict:
    """Registration error of a corresponded point sequence (F, M, 3) against true motion.

    Scoring starts at the registration's first frame with finite points (frames before it,
    waiting for the subject, are counted in n_frames_before_start). Each point is tied to
    the true surface in the rest pose's frame: the scored frame whose points are closest to
    `rest_points` (M, 3) (the rest pose is built from one frame, and that frame registers
    onto it; the first frames may be registered backward from it), else the first scored
    frame; it is compared with that material point in every scored frame, plus how far off
    the surface it was when tied (beyond the ground truth's sampling spacing); a point that
    is not finite in another frame costs the subject's size.
    Returns, in metres: mean and 95th percentile error, the mean error per frame, the worst
    frame's mean and 95th percentile, the error at `drift_frames` (1-based from the first
    scored frame), the mean distance off the surface when tied; coverage: the share of the
    true surface within two sample spacings of a registered point where tied (tied_at_frame,
    an index into the frames given); per_part:
    for every bone with tied points, their
    mean error and the worst frame's mean; nonfinite_fraction and counts.
    """
    if gt.surface_points is None:
        raise EvaluationError('ground truth has no surface_points; cannot evaluate registration')
    reg_idx, gt_idx = match_frames(stamps, gt.stamps)
    if len(reg_idx) == 0:
        raise EvaluationError('no registered frame has a ground-truth frame with the same stamp')
    registered = points[reg_idx]
    started = np.flatnonzero(np.isfinite(registered).all(axis=2).any(axis=1))
    if len(started) == 0:
        raise EvaluationError('every registered point is NaN: nothing was registered')
    start = int(started[0])
    registered, gt_idx = registered[start:], gt_idx[start:]
    anchor = 0
    if rest_points is not None and rest_points.shape == registered.shape[1:]:
        with np.errstate(invalid='ignore'):
            distance = np.nanmean(np.linalg.norm(registered - rest_points, axis=2), axis=1)
        anchor = int(np.nanargmin(distance))
    first_valid = np.isfinite(registered[anchor]).all(axis=1)
    truth, off_surface, bones = _material_trajectories(registered[anchor][first_valid], gt, gt_idx, anchor)
    errors = np.linalg.norm(registered[:, first_valid] - truth, axis=-1) + off_surface    # (F, M')
    nonfinite = ~np.isfinite(errors)
    errors[nonfinite] = gt.subject_scale_m
    per_frame = errors.mean(axis=1)
    # How much of the body the registered points stand for at the start: the share of the
    # true surface samples with a registered point within two sample spacings. One depth
    # camera sees about half of the body; points collapsed onto one spot cover nothing.
    surface = gt.surface_points[gt_idx[anchor]]
    spacing = median_spacing(surface)
    near, _ = cKDTree(registered[anchor][first_valid]).query(surface, distance_upper_bound=2.0 * spacing)
    coverage = float(np.isfinite(near).mean())
    per_part = {}
    names = gt.bone_names
    for bone in np.unique(bones[bones >= 0]):   # loop over bones, not points
        part = errors[:, bones == bone]
        name = names[bone] if names is not None and bone < len(names) else f'bone_{bone}'
        per_part[name] = {'mean_error_m': float(part.mean()), 'worst_frame_error_m': float(part.mean(axis=1).max()),
                          'n_points': int(part.shape[1])}
    return {
        'mean_error_m': float(errors.mean()),
        'p95_error_m': float(np.percentile(errors, 95)),
        'per_frame_error_m': [float(e) for e in per_frame],
        'worst_frame_error_m': float(per_frame.max()),
        'worst_frame_p95_m': float(np.percentile(errors, 95, axis=1).max()),
        'drift_m': {str(f): float(per_frame[f - 1]) for f in drift_frames if f - 1 < len(per_frame)},
        'tie_distance_m': float(off_surface.mean()),
        'coverage': coverage,
        'nonfinite_fraction': float(nonfinite.mean()),
        'per_part': per_part,
        'n_frames': int(len(gt_idx)),
        'n_frames_before_start': start,
        'tied_at_frame': start + anchor,
        'n_points': int(first_valid.sum()),
    }


def registration_span(points: np.ndarray, stamps: np.ndarray) -> tuple:
    """(first, last) stamps (s) of the registration: its first frame with a finite point
    (None if none) and the last frame it was given."""
    started = np.flatnonzero(np.isfinite(points).all(axis=2).any(axis=1))
    return (float(stamps[started[0]]) if len(started) else None), float(stamps.max())
