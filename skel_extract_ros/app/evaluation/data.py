"""The files scored: a simulator's ground truth (gt.npz), a skeleton.json, a registered.npz;
frames paired by stamp."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np


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
    subject_in_view: np.ndarray | None = None      # (F,) bool: any of the subject measured

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
        if 'subject_measured' in data:
            optional['subject_in_view'] = np.asarray(data['subject_measured']).reshape(len(stamps), -1).any(axis=1)
        if 'bone_names' in data:
            optional['bone_names'] = [str(n) for n in data['bone_names']]
        return cls(stamps, joints, [str(n) for n in data['joint_names']],
                   np.asarray(data['joint_parents']), surface, scale, **optional)


@dataclass
class PredictedSkeleton:
    """A skeleton.json: stamps (F,) s, positions (F, J, 3) m; confidence (F, J) in [0, 1],
    NaN where a frame gives none (None: no frame does)."""

    joint_names: list
    parents: list
    stamps: np.ndarray
    positions: np.ndarray
    frame_id: str = ''
    confidence: np.ndarray | None = None

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
        return cls(list(names), list(doc['parents']), stamps, positions, str(doc.get('frame_id', '')),
                   _frame_confidence(frames, n_joints))


def _frame_confidence(frames: list, n_joints: int) -> np.ndarray | None:
    """(F, J) each frame's `confidence`, NaN where a frame has none or a malformed one (the
    field is optional: a prediction without it is scored without the confidence's rank)."""
    confidence = np.full((len(frames), n_joints), np.nan)
    for index, frame in enumerate(frames):
        values = frame.get('confidence')
        if isinstance(values, list) and len(values) == n_joints:
            confidence[index] = [np.nan if v is None else float(v) for v in values]
    return None if np.isnan(confidence).all() else confidence


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


def load_registered(path) -> tuple:
    """(points (F, M, 3), stamps (F,), rest points (M, 3) or None) from a registered.npz."""
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
    rest = np.asarray(data['rest_points'], np.float64) if 'rest_points' in data else None
    return points, stamps, rest
