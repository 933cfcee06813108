"""Accuracy metrics against simulated ground truth.

Joint accuracy follows the paper (Sec. 7): the Euclidean distance error over the *common
subset* of joints, with Helten et al.'s per-joint normalisation. To keep it honest,
predicted and true joints are paired one-to-one (Hungarian assignment on the mean distance
over the sequence), and a pair farther apart than a threshold does not count as found: a
method cannot score well by predicting few joints (recall drops) or many (each true joint
takes at most one).

Registration accuracy ties each registered point, at the first frame, to its nearest true
surface sample and follows the material point it sits on through the sequence: with the
sample's bone transform when the ground truth has bones (simulation), with barycentric
coordinates on the nearest triangle when it has a mesh (captured mesh sequences), else with
the sample itself. Carrying the point's own first-frame position, rather than the sample,
keeps the metric free of the sample spacing (a 2 cm grid would put a 1 cm floor under every
method); the tie distance is reported beside it.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

DEFAULT_MATCH_THRESHOLD_M = 0.15
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
        optional = {key: np.asarray(data[key]) for key in ('surface_bone_ids', 'bone_transforms', 'surface_faces')
                    if key in data}
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
                raise EvaluationError(f'{path} has no "{key}" (see the skeleton.json schema in DESIGN.md)')
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
    mean_error_m: float
    normalized_error_m: float
    recall: float
    n_predicted: int
    n_ground_truth: int
    n_matched: int
    n_frames: int
    threshold_m: float
    per_joint: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def evaluate_joints(pred: PredictedSkeleton, gt: GroundTruth, threshold_m: float | None = None) -> JointReport:
    """Joint accuracy of `pred` against `gt` over the frames both have (matched by stamp).

    mean_error_m: mean over matched joints of the mean distance over frames (m);
    normalized_error_m: the same after removing each matched joint's mean offset;
    recall: matched / ground-truth joints. Unmatched joints contribute no error, which is
    why recall must always be read next to the error.
    """
    pred_idx, gt_idx = match_frames(pred.stamps, gt.stamps)
    if len(pred_idx) == 0:
        raise EvaluationError('no predicted frame has a ground-truth frame with the same stamp '
                              f'(prediction {pred.stamps[0]:.3f}..{pred.stamps[-1]:.3f} s, '
                              f'ground truth {gt.stamps[0]:.3f}..{gt.stamps[-1]:.3f} s)')
    threshold = match_threshold(gt.subject_scale_m) if threshold_m is None else float(threshold_m)
    predicted = pred.positions[pred_idx]          # (F, J, 3)
    truth = gt.joints[gt_idx]                     # (F, G, 3)
    n_gt = truth.shape[1]
    n_pred = predicted.shape[1]
    report = JointReport(float('nan'), float('nan'), 0.0, n_pred, n_gt, 0, len(pred_idx), threshold)
    if n_pred == 0:
        return report
    # (J, G) mean distance over frames; frames where a predicted joint is NaN are skipped.
    distances = np.linalg.norm(predicted[:, :, None, :] - truth[:, None, :, :], axis=-1)
    cost = np.nanmean(distances, axis=0)
    cost = np.where(np.isfinite(cost), cost, 1e6)
    rows, cols = linear_sum_assignment(cost)
    keep = cost[rows, cols] <= threshold
    rows, cols = rows[keep], cols[keep]
    if len(rows) == 0:
        return report
    errors, normalized = [], []
    for r, c in zip(rows, cols):
        offsets = predicted[:, r] - truth[:, c]
        valid = np.isfinite(offsets).all(axis=1)
        offsets = offsets[valid]
        errors.append(float(np.linalg.norm(offsets, axis=1).mean()))
        normalized.append(float(np.linalg.norm(offsets - offsets.mean(axis=0), axis=1).mean()))
        report.per_joint.append({'ground_truth': gt.joint_names[c], 'predicted': pred.joint_names[r],
                                 'error_m': errors[-1], 'normalized_error_m': normalized[-1]})
    report.mean_error_m = float(np.mean(errors))
    report.normalized_error_m = float(np.mean(normalized))
    report.n_matched = len(rows)
    report.recall = len(rows) / n_gt
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
    """True trajectories (F, P, 3) of the material points under `first` (P, 3) at frame
    gt_idx[0], and the distance from each point to the sample or surface it is tied to."""
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
        return trajectories, np.linalg.norm(offset, axis=1)
    tie_distance, tie = cKDTree(surface[0]).query(first)
    if gt.bone_transforms is not None and gt.surface_bone_ids is not None:
        transforms = gt.bone_transforms[gt_idx].astype(np.float64)
        bones = gt.surface_bone_ids[tie]
        start = transforms[0, bones]                                   # (P, 4, 4)
        local = np.einsum('pji,pj->pi', start[:, :3, :3], first - start[:, :3, 3])
        carried = transforms[:, bones]                                  # (F, P, 4, 4)
        trajectories = np.einsum('fpij,pj->fpi', carried[..., :3, :3], local) + carried[..., :3, 3]
        return trajectories, tie_distance
    return surface[:, tie], tie_distance


def evaluate_registration(points: np.ndarray, stamps: np.ndarray, gt: GroundTruth,
                          drift_frames=(30, 60, 90)) -> dict:
    """Registration error of a corresponded point sequence (F, M, 3) against true motion.

    Each point is tied at its first frame to the true surface (see the module docstring)
    and compared with that material point in every later frame. Returns mean and 95th
    percentile error (m), the mean error per frame, the error at `drift_frames` (1-based
    frame numbers from the first evaluated frame, where present) and the mean tie distance.
    """
    if gt.surface_points is None:
        raise EvaluationError('ground truth has no surface_points; cannot evaluate registration')
    reg_idx, gt_idx = match_frames(stamps, gt.stamps)
    if len(reg_idx) == 0:
        raise EvaluationError('no registered frame has a ground-truth frame with the same stamp')
    registered = points[reg_idx]
    first_valid = np.isfinite(registered[0]).all(axis=1)
    truth, tie_distance = _material_trajectories(registered[0][first_valid], gt, gt_idx)
    errors = np.linalg.norm(registered[:, first_valid] - truth, axis=-1)  # (F, M')
    per_frame = np.nanmean(errors, axis=1)
    return {
        'mean_error_m': float(np.nanmean(errors)),
        'p95_error_m': float(np.nanpercentile(errors, 95)),
        'per_frame_error_m': [float(e) for e in per_frame],
        'drift_m': {str(f): float(per_frame[f - 1]) for f in drift_frames if f - 1 < len(per_frame)},
        'tie_distance_m': float(tie_distance.mean()),
        'n_frames': int(len(reg_idx)),
        'n_points': int(first_valid.sum()),
    }
