"""Writing a simulated sequence to disk: a rosbag2 (mcap) directory with gt.npz inside."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..bag import DEFAULT_TOPIC, write_cloud_bag
from .sequence import SimulatedSequence

GT_FILENAME = 'gt.npz'


def write_simulated_bag(sequence: SimulatedSequence, out: Path, topic: str = DEFAULT_TOPIC) -> Path:
    """Write `sequence` as the bag directory `out`, ground truth at `out/gt.npz`.

    Returns the path of gt.npz.
    """
    out = Path(out)
    write_cloud_bag(out, sequence.clouds, sequence.stamps_ns, sequence.frame_id, topic)
    gt_path = out / GT_FILENAME
    np.savez_compressed(gt_path, **sequence.ground_truth)
    return gt_path
