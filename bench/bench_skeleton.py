#!/usr/bin/env python3
"""Skeleton benchmark: joints after Step 2, after Step 3, and with Dem Bones (SSDR) as peer.

    python bench/bench_skeleton.py [--frames 90] [--subjects human,upper_body,arm,hand,fish]
                                   [--n-clusters K] [--params FILE]

For each simulated subject (320x240, Kinect noise) the sequence is registered once (Step
0-1) and learned once on every registered frame (a growth window as long as the sequence);
then (a) the joints of the skeletal structure (Step 2, the paper's Fig. 5 situation), (b)
the joints after Alg. 2 (Step 3), and (c) Dem Bones' SSDR (py-dem-bones 0.13.1) run on Step
2's key frames of the same registered sequence, initialised with the Step 2 labels as hard
weights and the Step 2 bone transforms (its own initialisation needs mesh faces; a
nearest-neighbour triangle per point gives its weight smoothing an adjacency), its bone
transforms then turned into joints by the same joint solve (E_Joint); and (d) Steps 2 and 3
again on those key frames with the paper's joint anchors (the boundary centroid on the
visible surface, anchor_depth=surface) instead of the default medial anchors. The scores are
the real-motion yardstick's (`evaluate_joints`). Prints a Markdown table; `--json FILE`
keeps the raw numbers. `--params FILE` (the parameter YAML `skel-extract run` takes) runs
every step with its values instead of the defaults, so a variant measured on real motion
(`bench_real_motion.py --params`) is checked on these bodies with the same file. Needs the
`bench` extra.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from skel_extract_ros.config import load_params_file, pipeline_params  # noqa: E402
from skel_extract_ros.core.growth import GrowthSchedule  # noqa: E402
from skel_extract_ros.core.joints import JointEstimation  # noqa: E402
from skel_extract_ros.core.pipeline import SkeletonPipeline  # noqa: E402
from skel_extract_ros.core.joint_centres import joint_trajectories, solve_joints  # noqa: E402
from skel_extract_ros.core.structure import StructureParams, extract_structure  # noqa: E402
from skel_extract_ros.app.evaluation import GroundTruth, PredictedSkeleton, evaluate_joints  # noqa: E402
from skel_extract_ros.sim import generate_sequence  # noqa: E402


def dem_bones_joints(rest, registered, structure, eta: float):
    """SSDR from the Step 2 state, then joints from its bone transforms.

    Dem Bones smooths weights over the mesh; our points have no mesh, and without faces its
    weight update does nothing (measured: weights stay hard, transforms unchanged). Each
    rest point with its two nearest neighbours gives it the adjacency it needs.
    """
    from py_dem_bones._py_dem_bones import DemBones
    from scipy.spatial import cKDTree
    F, M, _ = registered.shape
    B = structure.n_bones
    solver = DemBones()
    solver.clear()
    solver.nV, solver.nF, solver.nS, solver.nB = M, F, 1, B
    solver.nnz = min(4, B)
    solver.nIters = 30
    solver.fStart = np.array([0, F], dtype=np.int32)
    solver.subjectID = np.zeros(F, dtype=np.int32)
    solver.u = np.ascontiguousarray(rest.T)
    solver.v = np.ascontiguousarray(registered.transpose(0, 2, 1).reshape(3 * F, M))
    _, nearest = cKDTree(rest).query(rest, k=3)
    solver.fv = nearest.astype(int).tolist()
    hard = np.zeros((B, M))
    hard[structure.labels, np.arange(M)] = 1.0
    solver.set_weights(hard)
    transforms = np.zeros((F, B, 4, 4))
    transforms[:, :, :3, :3] = structure.rotations
    transforms[:, :, :3, 3] = structure.translations
    transforms[:, :, 3, 3] = 1.0
    solver.m = np.ascontiguousarray(transforms.transpose(0, 2, 1, 3).reshape(4 * F, 4 * B))
    solver.compute()
    blocks = np.asarray(solver.m).reshape(F, 4, B, 4).transpose(0, 2, 1, 3)
    rotations, translations = blocks[:, :, :3, :3], blocks[:, :, :3, 3]
    joints = solve_joints(rotations, translations, structure.parents, structure.boundary_centroids, eta)
    return joint_trajectories(rotations, translations, joints, structure.parents)


def score(positions, parents, stamps, gt):
    pred = PredictedSkeleton([f'joint_{i}' for i in range(positions.shape[1])], list(parents), stamps, positions)
    return evaluate_joints(pred, gt, start_stamp=float(stamps[0]), end_stamp=float(stamps[-1]))


def _cell(value) -> str:
    """A score for the table: '-' where the subject has none (no bending or moving joint)."""
    return '-' if value is None or not np.isfinite(value) else f'{value:.2f}'


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--frames', type=int, default=90)
    parser.add_argument('--subjects', default='human,upper_body,arm,hand,fish')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--no-dem-bones', action='store_true')
    parser.add_argument('--no-surface', action='store_true',
                        help="skip Steps 2-3 with the paper's surface anchors (anchor_depth=surface)")
    parser.add_argument('--n-clusters', type=int, default=None,
                        help="Step 2's K-means clusters (default: StructureParams' default)")
    parser.add_argument('--params', default=None,
                        help="a parameter YAML for skel-extract run: its values instead of the defaults")
    parser.add_argument('--json', default=None)
    args = parser.parse_args()
    settings = pipeline_params(load_params_file(args.params)) if args.params else {}
    structure_params = settings.pop('structure', StructureParams())
    if args.n_clusters is not None:
        structure_params = dataclasses.replace(structure_params, n_clusters=args.n_clusters)
    settings.pop('schedule', None)      # here the window is the whole sequence
    rows = []
    print('| subject | true joints | method | joints found | mean_error_m | normalized_error_m | recall | '
          'precision | artic. recall | moving recall | tracking skill | seconds |')
    print('|---|---|---|---|---|---|---|---|---|---|---|---|')
    for subject in args.subjects.split(','):
        seq = generate_sequence(subject, args.frames, seed=args.seed, progress=False)
        g = seq.ground_truth
        gt = GroundTruth.from_arrays(g)
        # learned once, on every registered frame (a window as long as the sequence)
        pipeline = SkeletonPipeline(structure=structure_params, schedule=GrowthSchedule(window_size=args.frames),
                                    **settings)
        started = time.perf_counter()
        # organized clouds, as a camera gives them: the subject segmentation (on by
        # default) then finds the subject from the second frame on
        registered = pipeline.register(seq.clouds)
        register_seconds = time.perf_counter() - started
        result = pipeline.extract(registered)
        n_true = g['joints'].shape[1]
        entries = [('step 2 (structure)', result.step2_positions, result.structure.parents,
                    result.seconds['structure'], result.frames),
                   ('step 3 (Alg. 2)', result.joint_positions, result.model.parents, result.seconds['joints'],
                    result.frames)]
        # the peers start from what Step 2 learned on: its key frames
        key_frames = result.key_frames
        window = registered[key_frames].astype(np.float64)
        if not args.no_surface:
            # the paper's anchors (boundary centroids on the visible surface) on the same input
            rest = pipeline.registration.rest_pose_.points
            observed = [result.observed[i] for i in np.searchsorted(result.frames, key_frames)]
            started = time.perf_counter()
            surface = extract_structure(rest, window, dataclasses.replace(structure_params, anchor_depth='surface'))
            middle = time.perf_counter()
            estimate = JointEstimation(pipeline.joint_params).fit(rest, window, observed, surface)
            entries += [('step 2, surface anchors', surface.joint_trajectories(), surface.parents,
                         middle - started, key_frames),
                        ('step 3, surface anchors', estimate.joint_trajectories(), estimate.parents,
                         time.perf_counter() - middle, key_frames)]
        if not args.no_dem_bones:
            started = time.perf_counter()
            positions = dem_bones_joints(pipeline.registration.rest_pose_.points, window, result.structure, 1.0)
            entries.append(('Dem Bones SSDR', positions, result.structure.parents, time.perf_counter() - started,
                            key_frames))
        for method, positions, parents, seconds, frames in entries:
            report = score(positions, parents, g['stamps'][frames], gt)
            rows.append({'subject': subject, 'method': method, 'true_joints': n_true,
                         'joints': report.n_predicted, 'mean_error_m': report.mean_error_m,
                         'normalized_error_m': report.normalized_error_m, 'recall': report.recall,
                         'precision': report.precision, 'articulated_recall': report.articulated_recall,
                         'moving_recall': report.moving_recall, 'tracking_skill': report.tracking_skill,
                         'seconds': seconds, 'register_seconds': register_seconds})
            print(f'| {subject} | {n_true} | {method} | {report.n_predicted} | {report.mean_error_m:.4f} | '
                  f'{report.normalized_error_m:.4f} | {report.recall:.2f} | {_cell(report.precision)} | '
                  f'{_cell(report.articulated_recall)} | {_cell(report.moving_recall)} | '
                  f'{_cell(report.tracking_skill)} | {seconds:.1f} |', flush=True)
        print(f'| {subject} | | (registration, steps 0-1) | | | | | | | | | {register_seconds:.1f} |', flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
