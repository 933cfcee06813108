"""The extracted skeleton: bone tree, joints and LBS model, and its skeleton.json form.

Joint b is the joint between bone b and its parent bone; the root bone's joint is its
centre (the paper's root joint). So the joint tree has the bone tree's parents.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SkeletonModel:
    """rest_points (M, 3), labels (M,), parents (B,), rest_joints (B, 3), all metres in the
    rest frame (the cloud frame of the rest-pose frame); LBS influences/weights (M, k)."""

    rest_points: np.ndarray
    labels: np.ndarray
    parents: np.ndarray
    rest_joints: np.ndarray
    influences: np.ndarray
    weights: np.ndarray

    @property
    def n_joints(self) -> int:
        return len(self.parents)

    @property
    def joint_names(self) -> list:
        return [f'joint_{i}' for i in range(self.n_joints)]

    def to_json(self, stamps, positions, frame_id: str) -> dict:
        """The skeleton.json document (DESIGN.md): stamps (F,) s, positions (F, J, 3) m."""
        positions = np.asarray(positions, dtype=np.float64)
        frames = [{'stamp': float(stamp),
                   'positions': [[None if not np.isfinite(v) else round(float(v), 6) for v in joint]
                                 for joint in frame]}
                  for stamp, frame in zip(stamps, positions)]
        return {
            'frame_id': frame_id,
            'joint_names': self.joint_names,
            'parents': [int(p) for p in self.parents],
            'rest_positions': np.round(self.rest_joints, 6).tolist(),
            'frames': frames,
        }
