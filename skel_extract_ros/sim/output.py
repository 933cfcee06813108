"""Writing a simulated sequence to disk: a rosbag2 (mcap) directory with gt.npz inside."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..codecs.bag import DEFAULT_DEPTH_TOPIC, DEFAULT_TOPIC, write_cloud_bag, write_depth_bag
from .render import SimulatedSequence

GT_FILENAME = 'gt.npz'


def write_simulated_bag(sequence: SimulatedSequence, out: Path, topic: str | None = None,
                        depth_image: bool = False) -> Path:
    """Write `sequence` as the bag directory `out`, ground truth at `out/gt.npz`: organized
    PointCloud2 clouds, or with `depth_image` 16UC1 depth images (mm) with a CameraInfo
    each, as depth drivers publish by default. Returns the path of gt.npz."""
    out = Path(out)
    if depth_image:
        width, height, fx, fy, cx, cy = sequence.ground_truth['intrinsics']
        write_depth_bag(out, [cloud[..., 2] for cloud in sequence.clouds], sequence.stamps_ns,
                        sequence.frame_id, (fx, fy, cx, cy), topic or DEFAULT_DEPTH_TOPIC)
    else:
        write_cloud_bag(out, sequence.clouds, sequence.stamps_ns, sequence.frame_id, topic or DEFAULT_TOPIC)
    gt_path = out / GT_FILENAME
    np.savez_compressed(gt_path, **sequence.ground_truth)
    return gt_path
