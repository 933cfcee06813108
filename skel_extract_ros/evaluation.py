"""Accuracy metrics against simulated ground truth, made hard to game.

Joint accuracy follows the paper (Sec. 7): the Euclidean distance error over the *common
subset* of joints, with Helten et al.'s per-joint normalisation. Predicted and true joints
are paired one-to-one (Hungarian assignment on the mean distance over the frames), and a
pair farther apart than a threshold does not count as found. What each number cannot be
fooled by, with a test for each in test/test_evaluation.py:

- predicting many joints: each true joint takes at most one, and `precision` (matched /
  predicted) and `n_predicted` stand beside every recall (2,000 surface points given as
  "joints" score recall 1 but precision 0.01);
- predicting joints that never bend: `articulated_recall` counts only the true joints
  whose rotation relative to their parent bone spans >= ARTICULATION_MIN_DEG within the
  scored frames, the joints a motion-based method can find at all;
- NaN: a non-finite prediction in a frame costs MISS_PENALTY_FACTOR x the threshold in
  that frame (so a joint missing in most frames cannot match), and `nonfinite_fraction`
  says how much was missing; a registered point that is non-finite after the
  registration's first frame costs the subject's size;
- standing still: a static skeleton at each true joint's temporal mean has a small mean
  error but `motion_skill` 0 (1 - normalized error / the joint's own motion spread;
  ground truth 1);
- registration that collapses or drifts off the body: each registered point is tied at
  the registration's first frame to the true surface and followed as that material point
  (with the sample's bone transform in simulation, barycentric coordinates on a captured
  mesh), and it pays how far it was from the surface there beyond the ground truth's own
  sampling spacing, so points collapsed to the centroid score their distance to the
  surface instead of 0, and `coverage` (the share of the true surface near a registered
  point at the start: about half for one camera's view, 0 for a collapse) says how much
  of the body the points stand for.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from .core.point_sets import median_spacing

DEFAULT_MATCH_THRESHOLD_M = 0.15
# A joint that bends less than this within the scored frames cannot be told from its
# parent by motion; 25 degrees moves a 30 cm limb's end by 13 cm.
ARTICULATION_MIN_DEG = 25.0
# A frame where a predicted joint is not finite counts as this many thresholds away.
MISS_PENALTY_FACTOR = 2.0
# Subjects smaller than this (bounding-box diagonal, m) get a proportionally smaller
# threshold: 15 cm is a fair "same joint" radius for a person, not for a finger.
REFERENCE_SUBJECT_SIZE_M = 1.5


class EvaluationError(ValueError):
    """Unusable input to the evaluation; the message is one line for the user."""


@dataclass
class GroundTruth:
    """Arrays of a gt.npz (see skel_extract_ros.sim.sequence).

    stamps: (F,) s; joints: (F, G, 3) m; surface_points: (F, S, 3) m.
    """

    stamps: np.ndarray
    joints: np.ndarray
    joint_names: list
    joint_parents: np.ndarray
    surface_points: np.ndarray | None
    subject_scale_m: float
    surface_bone_ids: np.ndarray | None = None     # (S,) bone of each surface sample
    bone_transforms: np.ndarray | None = None      # (F, B, 4, 4) camera-from-bone
    surface_faces: np.ndarray | None = None        # (T, 3) triangles over surface_points
    bone_names: list | None = None                 # (B,)
    bone_parents: np.ndarray | None = None         # (B,) parent bone, -1 = root
    joint_bones: np.ndarray | None = None          # (G,) the bone whose origin each joint is

    @classmethod
    def load(cls, path) -> 'GroundTruth':
        path = Path(path)
        if not path.is_file():
            raise EvaluationError(f'ground truth {path} does not exist')
        try:
            data = np.load(path, allow_pickle=False)
        except Exception as error:
            raise EvaluationError(f'cannot read ground truth {path}: {error}') from error
        return cls.from_arrays(data, str(path))

    @classmethod
    def from_arrays(cls, data, source: str = 'ground truth') -> 'GroundTruth':
        """From the arrays of a gt.npz (a mapping, e.g. SimulatedSequence.ground_truth)."""
        missing = [k for k in ('stamps', 'joints', 'joint_names', 'joint_parents') if k not in data]
        if missing:
            raise EvaluationError(f'ground truth {source} lacks {", ".join(missing)}')
        joints = np.asarray(data['joints'], dtype=np.float64)
        stamps = np.asarray(data['stamps'], dtype=np.float64)
        if joints.ndim != 3 or joints.shape[2] != 3 or joints.shape[0] != stamps.shape[0]:
            raise EvaluationError(f'ground truth {source}: joints must be (F, G, 3) with F stamps')
        surface = np.asarray(data['surface_points'], dtype=np.float64) if 'surface_points' in data else None
        scale = float(data['subject_scale_m']) if 'subject_scale_m' in data else \
            float(np.linalg.norm(np.ptp(joints[0], axis=0)))
        optional = {key: np.asarray(data[key]) for key in ('surface_bone_ids', 'bone_transforms', 'surface_faces',
                                                            'bone_parents', 'joint_bones') if key in data}
        if 'bone_names' in data:
            optional['bone_names'] = [str(n) for n in data['bone_names']]
        return cls(stamps, joints, [str(n) for n in data['joint_names']],
                   np.asarray(data['joint_parents']), surface, scale, **optional)


@dataclass
class PredictedSkeleton:
    """A skeleton.json: stamps (F,) s, positions (F, J, 3) m."""

    joint_names: list
    parents: list
    stamps: np.ndarray
    positions: np.ndarray
    frame_id: str = ''

    @classmethod
    def load(cls, path) -> 'PredictedSkeleton':
        path = Path(path)
        if not path.is_file():
            raise EvaluationError(f'prediction {path} does not exist')
        try:
            doc = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise EvaluationError(f'{path} is not valid JSON: {error}') from error
        if not isinstance(doc, dict):
            raise EvaluationError(f'{path}: expected a JSON object with joint_names and frames')
        for key in ('joint_names', 'parents', 'frames'):
            if key not in doc:
                raise EvaluationError(f'{path} has no "{key}" (see the skeleton.json schema in docs/contract.md)')
        names, frames = doc['joint_names'], doc['frames']
        n_joints = len(names)
        if len(doc['parents']) != n_joints:
            raise EvaluationError(f'{path}: {len(doc["parents"])} parents for {n_joints} joints')
        if not frames:
            raise EvaluationError(f'{path} has no frames')
        try:
            stamps = np.array([float(f['stamp']) for f in frames])
            positions = np.array([f['positions'] for f in frames], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as error:
            raise EvaluationError(f'{path}: every frame needs "stamp" and "positions" '
                                  f'(J x 3 numbers): {error}') from error
        if positions.ndim != 3 or positions.shape[1:] != (n_joints, 3):
            raise EvaluationError(f'{path}: frame positions must be {n_joints} x 3, got '
                                  f'{positions.shape[1:]}')
        return cls(list(names), list(doc['parents']), stamps, positions, str(doc.get('frame_id', '')))


def match_frames(pred_stamps: np.ndarray, gt_stamps: np.ndarray, tolerance_s: float | None = None):
    """Pair frames by stamp: (pred indices, gt indices) of pairs within `tolerance_s`.

    The default tolerance is a quarter of the ground truth's median frame period.
    """
    if tolerance_s is None:
        period = float(np.median(np.diff(gt_stamps))) if len(gt_stamps) > 1 else 1.0
        tolerance_s = 0.25 * period
    order = np.argsort(gt_stamps)
    sorted_stamps = gt_stamps[order]
    right = np.clip(np.searchsorted(sorted_stamps, pred_stamps), 0, len(gt_stamps) - 1)
    left = np.clip(right - 1, 0, len(gt_stamps) - 1)
    nearest = np.where(np.abs(sorted_stamps[left] - pred_stamps) <= np.abs(sorted_stamps[right] - pred_stamps),
                       left, right)
    close = np.abs(sorted_stamps[nearest] - pred_stamps) <= tolerance_s
    return np.flatnonzero(close), order[nearest[close]]


def match_threshold(subject_scale_m: float, base_m: float = DEFAULT_MATCH_THRESHOLD_M) -> float:
    return base_m * min(1.0, subject_scale_m / REFERENCE_SUBJECT_SIZE_M)


@dataclass
class JointReport:
    """Joint scores (metres); see `evaluate_joints`."""

    mean_error_m: float
    normalized_error_m: float
    recall: float
    n_predicted: int
    n_ground_truth: int
    n_matched: int
    n_frames: int
    threshold_m: float
    precision: float = 0.0
    articulated_recall: float = float('nan')
    n_articulated: int = 0
    motion_skill: float = float('nan')
    nonfinite_fraction: float = 0.0
    missed_articulated: list = field(default_factory=list)
    per_joint: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def articulation_spans(gt: GroundTruth, gt_idx: np.ndarray) -> np.ndarray:
    """(G,) degrees: for each true joint, the largest angle between two of its bone's
    rotations relative to the parent bone over the frames `gt_idx` (0 for root joints,
    NaN for every joint when the ground truth has no bone transforms)."""
    n_joints = gt.joints.shape[1]
    if gt.bone_transforms is None or gt.joint_bones is None or gt.bone_parents is None:
        return np.full(n_joints, np.nan)
    rotations = gt.bone_transforms[gt_idx][..., :3, :3].astype(np.float64)     # (F, B, 3, 3)
    spans = np.zeros(n_joints)
    for g, bone in enumerate(np.asarray(gt.joint_bones, dtype=int)):   # loop over joints, not points
        parent = int(gt.bone_parents[bone])
        if parent < 0:
            continue
        relative = np.einsum('fji,fjk->fik', rotations[:, parent], rotations[:, bone])  # (F, 3, 3)
        # angle between every pair of frames: trace(R_a^T R_b) = 1 + 2 cos(angle); the
        # largest angle has the smallest trace
        traces = np.einsum('aji,bji->ab', relative, relative)
        spans[g] = np.degrees(np.arccos(np.clip((traces.min() - 1.0) / 2.0, -1.0, 1.0)))
    return spans


def evaluate_joints(pred: PredictedSkeleton, gt: GroundTruth, threshold_m: float | None = None) -> JointReport:
    """Joint accuracy of `pred` against `gt` over the frames both have (matched by stamp).

    mean_error_m: mean over matched joints of the mean distance over frames (m), a
    non-finite frame counting MISS_PENALTY_FACTOR thresholds; normalized_error_m: the same
    after removing each matched joint's mean offset (finite frames); recall: matched /
    ground-truth joints; precision: matched / predicted joints; articulated_recall over the
    n_articulated joints that bend >= ARTICULATION_MIN_DEG in these frames (NaN without bone
    transforms); motion_skill: 1 - mean normalized error / mean true motion spread (a joint's
    mean distance from its own temporal mean) over matched joints: 0 for a static skeleton,
    1 for the truth; nonfinite_fraction: share of predicted joint-frames that are NaN/inf.
    Read every error next to recall and precision: unmatched joints contribute no error.
    """
    pred_idx, gt_idx = match_frames(pred.stamps, gt.stamps)
    if len(pred_idx) == 0:
        raise EvaluationError('no predicted frame has a ground-truth frame with the same stamp '
                              f'(prediction {pred.stamps[0]:.3f}..{pred.stamps[-1]:.3f} s, '
                              f'ground truth {gt.stamps[0]:.3f}..{gt.stamps[-1]:.3f} s)')
    if gt.joints.shape[1] == 0:
        raise EvaluationError('the ground truth has no joints (a captured mesh sequence?): '
                              'only the registration can be scored')
    threshold = match_threshold(gt.subject_scale_m) if threshold_m is None else float(threshold_m)
    predicted = pred.positions[pred_idx]          # (F, J, 3)
    truth = gt.joints[gt_idx]                     # (F, G, 3)
    n_gt = truth.shape[1]
    n_pred = predicted.shape[1]
    spans = articulation_spans(gt, gt_idx)
    articulated = spans >= ARTICULATION_MIN_DEG
    report = JointReport(float('nan'), float('nan'), 0.0, n_pred, n_gt, 0, len(pred_idx), threshold,
                         n_articulated=int(articulated.sum()))
    if not np.isnan(spans).all():
        report.articulated_recall = 0.0 if articulated.any() else float('nan')
        report.missed_articulated = [gt.joint_names[g] for g in np.flatnonzero(articulated)]
    if n_pred == 0:
        return report
    finite = np.isfinite(predicted).all(axis=-1)                          # (F, J)
    report.nonfinite_fraction = float(1.0 - finite.mean())
    # (F, J, G) distances; a non-finite prediction is a miss in that frame
    distances = np.linalg.norm(predicted[:, :, None, :] - truth[:, None, :, :], axis=-1)
    distances = np.where(finite[:, :, None], distances, MISS_PENALTY_FACTOR * threshold)
    cost = distances.mean(axis=0)                                          # (J, G)
    rows, cols = linear_sum_assignment(cost)
    keep = cost[rows, cols] <= threshold
    rows, cols = rows[keep], cols[keep]
    report.precision = len(rows) / n_pred
    if len(rows) == 0:
        return report
    errors, normalized, spreads = [], [], []
    for r, c in zip(rows, cols):
        errors.append(float(cost[r, c]))
        offsets = (predicted[:, r] - truth[:, c])[finite[:, r]]
        normalized.append(float(np.linalg.norm(offsets - offsets.mean(axis=0), axis=1).mean()))
        spreads.append(float(np.linalg.norm(truth[:, c] - truth[:, c].mean(axis=0), axis=1).mean()))
        report.per_joint.append({'ground_truth': gt.joint_names[c], 'predicted': pred.joint_names[r],
                                 'error_m': errors[-1], 'normalized_error_m': normalized[-1],
                                 'articulated': bool(articulated[c]),
                                 'span_deg': float(spans[c]) if np.isfinite(spans[c]) else None})
    report.mean_error_m = float(np.mean(errors))
    report.normalized_error_m = float(np.mean(normalized))
    report.n_matched = len(rows)
    report.recall = len(rows) / n_gt
    report.motion_skill = float(1.0 - np.mean(normalized) / max(np.mean(spreads), 1e-9))
    if report.n_articulated:
        found = np.zeros(n_gt, dtype=bool)
        found[cols] = True
        report.articulated_recall = float(found[articulated].mean())
        report.missed_articulated = [gt.joint_names[g] for g in np.flatnonzero(articulated & ~found)]
    return report


def load_registered(path) -> tuple:
    """(points (F, M, 3), stamps (F,)) from a registered.npz."""
    path = Path(path)
    if not path.is_file():
        raise EvaluationError(f'registered points {path} do not exist')
    try:
        data = np.load(path, allow_pickle=False)
        points, stamps = np.asarray(data['points'], np.float64), np.asarray(data['stamps'], np.float64)
    except KeyError as error:
        raise EvaluationError(f'{path} needs arrays "points" (F x M x 3) and "stamps" (F)') from error
    except Exception as error:
        raise EvaluationError(f'cannot read {path}: {error}') from error
    if points.ndim != 3 or points.shape[2] != 3 or points.shape[0] != stamps.shape[0]:
        raise EvaluationError(f'{path}: points must be F x M x 3 with one stamp per frame, got '
                              f'{points.shape} and {stamps.shape}')
    return points, stamps


def _material_trajectories(first: np.ndarray, gt: 'GroundTruth', gt_idx: np.ndarray):
    """The material points under `first` (P, 3) at frame gt_idx[0]: their true trajectories
    (F, P, 3), each point's distance to the surface it is tied to beyond the ground truth's
    own sampling spacing (P,), and the bone each is tied to (P,), -1 where unknown."""
    surface = gt.surface_points[gt_idx]
    if gt.surface_faces is not None and len(gt.surface_faces):
        import open3d as o3d
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(surface[0].astype(np.float32)),
                            o3d.core.Tensor(gt.surface_faces.astype(np.uint32)))
        closest = scene.compute_closest_points(o3d.core.Tensor(first.astype(np.float32)))
        triangles = gt.surface_faces[closest['primitive_ids'].numpy().astype(np.int64)]
        uv = closest['primitive_uvs'].numpy().astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        on_surface = np.einsum('pk,pki->pi', bary, surface[0][triangles])
        offset = first - on_surface
        trajectories = np.einsum('pk,fpki->fpi', bary, surface[:, triangles]) + offset
        bones = (gt.surface_bone_ids[triangles[:, 0]] if gt.surface_bone_ids is not None
                 else np.full(len(first), -1))
        # the mesh is the exact surface: any distance from it is off the body
        return trajectories, np.linalg.norm(offset, axis=1), bones
    tree = cKDTree(surface[0])
    tie_distance, tie = tree.query(first)
    # samples are a few cm apart: a point on the surface between them is up to a spacing
    # from the nearest one, which is not an error
    spacing = float(np.median(tree.query(surface[0], k=2)[0][:, 1]))
    off_surface = np.maximum(tie_distance - spacing, 0.0)
    bones = gt.surface_bone_ids[tie] if gt.surface_bone_ids is not None else np.full(len(first), -1)
    if gt.bone_transforms is not None and gt.surface_bone_ids is not None:
        transforms = gt.bone_transforms[gt_idx].astype(np.float64)
        start = transforms[0, bones]                                   # (P, 4, 4)
        local = np.einsum('pji,pj->pi', start[:, :3, :3], first - start[:, :3, 3])
        carried = transforms[:, bones]                                  # (F, P, 4, 4)
        trajectories = np.einsum('fpij,pj->fpi', carried[..., :3, :3], local) + carried[..., :3, 3]
        return trajectories, off_surface, bones
    return surface[:, tie], off_surface, bones


def evaluate_registration(points: np.ndarray, stamps: np.ndarray, gt: GroundTruth,
                          drift_frames=(30, 60, 90)) -> dict:
    """Registration error of a corresponded point sequence (F, M, 3) against true motion.

    Scoring starts at the registration's first frame with finite points (frames before it,
    waiting for the subject, are counted in n_frames_before_start). Each point is tied there
    to the true surface and compared with that material point in every later frame, plus
    how far off the surface it was when tied (beyond the ground truth's sampling spacing);
    a point that is not finite in a later frame costs the subject's size.
    Returns, in metres: mean and 95th percentile error, the mean error per frame, the worst
    frame's mean and 95th percentile, the error at `drift_frames` (1-based from the first
    scored frame), the mean distance off the surface when tied; coverage: the share of the
    true surface within two sample spacings of a registered point at the start; per_part:
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
    first_valid = np.isfinite(registered[0]).all(axis=1)
    truth, off_surface, bones = _material_trajectories(registered[0][first_valid], gt, gt_idx)
    errors = np.linalg.norm(registered[:, first_valid] - truth, axis=-1) + off_surface    # (F, M')
    nonfinite = ~np.isfinite(errors)
    errors[nonfinite] = gt.subject_scale_m
    per_frame = errors.mean(axis=1)
    # How much of the body the registered points stand for at the start: the share of the
    # true surface samples with a registered point within two sample spacings. One depth
    # camera sees about half of the body; points collapsed onto one spot cover nothing.
    surface = gt.surface_points[gt_idx[0]]
    spacing = median_spacing(surface)
    near, _ = cKDTree(registered[0][first_valid]).query(surface, distance_upper_bound=2.0 * spacing)
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
        'n_points': int(first_valid.sum()),
    }
