"""The files `skel-extract run` and `skel-extract replay` write (docs/contract.md), written
here for both, so they hold the same keys: registered.npz, skeleton.json, skeleton.bvh and
skeleton.png."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

# registered.npz's per-frame arrays beyond points, stamps and status, and what a frame
# without the value holds (replay receives only the registered points from the nodes)
REGISTRATION_DETAILS = {'sigma2': np.nan, 'recaptured': -1, 'landmarks': -1, 'subject_points': -1,
                        'background_fraction': np.nan, 'segmentation': ''}


def write_registered(out: Path, points: np.ndarray, stamps: np.ndarray, status: np.ndarray,
                     rest_points: np.ndarray | None, frame_id: str, **details) -> None:
    """registered.npz: points (F, M, 3) m, stamps (F,) s, status (F,), rest_points (M, 3),
    frame_id, and each of REGISTRATION_DETAILS (F,): the one given, else its unknown value."""
    n_frames = len(stamps)
    unknown = set(details) - set(REGISTRATION_DETAILS)
    if unknown:
        raise ValueError(f'unknown registered.npz arrays: {", ".join(sorted(unknown))}')
    arrays = {name: np.asarray(details[name]) if name in details else np.full(n_frames, missing)
              for name, missing in REGISTRATION_DETAILS.items()}
    np.savez_compressed(out / 'registered.npz', points=points, stamps=stamps, status=np.asarray(status),
                        rest_points=(np.empty((0, 3)) if rest_points is None else rest_points).astype(np.float32),
                        frame_id=np.array(frame_id), **arrays)


def write_skeleton(out: Path, joint_names: list, parents, rest_joints, frame_id: str, stamps: np.ndarray,
                   positions: np.ndarray, confidence, rest_points: np.ndarray, labels: np.ndarray,
                   registered: dict, observed: dict, scene: dict | None = None, pivot: dict | None = None,
                   interpolated=None) -> None:
    """skeleton.json for every frame with joints (stamps (F,) s, positions (F, J, 3) m,
    confidence (F, J) or a list with None where unknown, or None; pivot: the joints' pivot
    evidence, core.skeleton_model.pivot_document; interpolated (F,) bool or None: the
    frames whose joints the live path interpolated), and skeleton.bvh and
    skeleton.png for those of them with registered points: registered / observed / scene
    map a frame's row in stamps to its registered (M, 3), observed (N, 3) and whole-view
    (K, 3) points; rest_points (M, 3) and labels (M,) the model's."""
    from .bvh_export import write_skeleton_bvh
    from ..core.skeleton_model import skeleton_document
    from .visualization import draw_skeleton_png

    document = skeleton_document(joint_names, parents, rest_joints, stamps, positions, frame_id, confidence, pivot,
                                 interpolated)
    (out / 'skeleton.json').write_text(json.dumps(document))
    rows = [row for row in range(len(stamps)) if row in registered]
    with_points = np.stack([registered[row] for row in rows])
    write_skeleton_bvh(out / 'skeleton.bvh', joint_names, parents, rest_joints, stamps[rows], positions[rows],
                       rest_points, labels, with_points)
    draw_skeleton_png(out / 'skeleton.png', [observed.get(row, np.empty((0, 3))) for row in rows], with_points,
                      labels, positions[rows], np.asarray(parents), stamps[rows],
                      scene=None if scene is None else [scene[row] for row in rows])
