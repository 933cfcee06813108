"""The extracted skeleton: bone tree, joints and LBS model (Eq. 8), and its skeleton.json form.

Joint b is the joint between bone b and its parent bone; the root bone's joint is its
centre (the paper's root joint). So the joint tree has the bone tree's parents.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .joint_centres import PivotEvidence


@dataclass
class SkeletonModel:
    """rest_points (M, 3), labels (M,), parents (B,), rest_joints (B, 3), all metres in the
    rest frame (the cloud frame of the rest-pose frame); LBS influences/weights (M, k);
    joint_ids (B,): stable ids that name the joints across updates of a growing skeleton
    (core.growth; None: 0..B-1); pivot: how far the motion it was learned on fixed each
    joint (None: not known); noise_m: the RMS distance (m) of the observed points to the
    skeleton's fit on the frames it was learned on (core.confidence judges a frame's fit
    against it; None: not known)."""

    rest_points: np.ndarray
    labels: np.ndarray
    parents: np.ndarray
    rest_joints: np.ndarray
    influences: np.ndarray
    weights: np.ndarray
    joint_ids: np.ndarray | None = None
    pivot: PivotEvidence | None = None
    noise_m: float | None = None

    @property
    def n_joints(self) -> int:
        return len(self.parents)

    @property
    def ids(self) -> list:
        """(J,) the stable joint ids as ints (0..J-1 without joint_ids)."""
        return [int(i) for i in (range(self.n_joints) if self.joint_ids is None else self.joint_ids)]

    @property
    def joint_names(self) -> list:
        return [f'joint_{i}' for i in self.ids]

    def to_json(self, stamps, positions, frame_id: str, confidence=None) -> dict:
        """The skeleton.json document (docs/contract.md): stamps (F,) s, positions (F, J, 3)
        m, confidence (F, J) in [0, 1] or None."""
        return skeleton_document(self.joint_names, self.parents, self.rest_joints, stamps, positions, frame_id,
                                 confidence, pivot_document(self.pivot))


def pivot_document(pivot: PivotEvidence | None) -> dict | None:
    """The `pivot` block of skeleton.json and skeleton/description: per joint `fixed` (the
    motion fixed its pivot across its axis: a ball joint or a hinge), `fixed_directions`
    (0-3), `confidence` ([0, 1], the share of the anchor's uncertainty the motion removed)
    and `residual_m` (the RMS pivot gap, m); null for the root joint (a bone centre, not a
    pivot). None without evidence."""
    if pivot is None:
        return None
    root = ~np.isfinite(pivot.residual_m)

    def per_joint(values, convert):
        return [None if r else convert(v) for v, r in zip(values, root)]
    return {'fixed': per_joint(pivot.fixed, bool),
            'fixed_directions': per_joint(pivot.fixed_directions, int),
            'confidence': per_joint(pivot.confidence, lambda v: round(float(v), 4)),
            'residual_m': per_joint(pivot.residual_m, lambda v: round(float(v), 6))}


def skeleton_document(joint_names, parents, rest_positions, stamps, positions, frame_id: str,
                      confidence=None, pivot: dict | None = None, interpolated=None) -> dict:
    """skeleton.json: names (J,), parents (J,), rest_positions (J, 3) m, stamps (F,) s,
    positions (F, J, 3) m in the input frame (non-finite values become null), per frame
    the joints' confidence (F, J) in [0, 1] (core.confidence) when given (a frame whose
    confidence is unknown: None, left out), the joints' pivot evidence (pivot_document;
    None: null), and interpolated (F,) bool or None: the frames whose joints the live path
    interpolated between fitted frames (the nodes' live camera frames it had no time for)
    are marked `"interpolated": true`; the others carry no mark."""
    positions = np.asarray(positions, dtype=np.float64)
    frames = [{'stamp': float(stamp),
               'positions': [[None if not np.isfinite(v) else round(float(v), 6) for v in joint]
                             for joint in frame]}
              for stamp, frame in zip(stamps, positions)]
    for frame, values in zip(frames, confidence if confidence is not None else []):
        if values is not None:
            frame['confidence'] = [round(float(c), 4) for c in values]
    for frame, flag in zip(frames, interpolated if interpolated is not None else []):
        if flag:
            frame['interpolated'] = True
    return {
        'frame_id': frame_id,
        'joint_names': list(joint_names),
        'parents': [int(p) for p in parents],
        'rest_positions': np.round(np.asarray(rest_positions, dtype=np.float64), 6).tolist(),
        'pivot': pivot,
        'frames': frames,
    }
