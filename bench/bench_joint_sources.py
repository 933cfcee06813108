"""Where the joint error comes from: Steps 2 and 3 on the registration, and on a perfect one.

    python bench/bench_joint_sources.py [--only wave,run] [--scenes empty] [--frames 90] [--work DIR]
                                        [--params FILE] [--lost-frame-cm 6]

For each real clip (the subjects of bench_real_motion.py; the bags are simulated into --work
or reused from it), the registration runs once as `skel-extract run` runs it; then Steps 2
and 3 run twice on the same rest points and observed points: on the registered points, and
on the true trajectories of the material points they started on (each registered point
tied to the true surface in the rest pose's frame and carried by its bone: what a
perfect registration would give). Both are learned on all the frames (window_size larger
than the clip) and scored with the yardstick (skel_extract_ros.app.evaluation). The gap between
the two rows is what the registration costs the joints; what is left on the perfect row is
the structure's and the joint placement's. Two more rows split the gap: each skeleton
(bones, joints and weights) fitted frame by frame to the other's motion, as `run` fits a
learned skeleton to the frames after its window (core.live.LiveJointTracker on every
frame): *registered skeleton, perfect motion* is what the skeleton learned on the
registration costs; *perfect skeleton, registered motion* is what the registration's
frames cost a skeleton that is right. `--params FILE` (the parameter YAML `skel-extract run`
takes) runs every step with its values instead of the defaults (the growth window stays
the whole clip).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'bench'))

from bench_real_motion import half, simulate_and_run, subjects  # noqa: E402
from skel_extract_ros.codecs.bag import read_cloud_frames, select_cloud_topic  # noqa: E402
from skel_extract_ros.config import load_params_file, pipeline_params  # noqa: E402
from skel_extract_ros.core.growth import GrowthSchedule  # noqa: E402
from skel_extract_ros.core.live import LiveJointTracker  # noqa: E402
from skel_extract_ros.core.pipeline import SkeletonPipeline  # noqa: E402
from skel_extract_ros.app.evaluation import (GroundTruth, PredictedSkeleton, evaluate_joints,  # noqa: E402
                                         match_frames, registration_span)
from skel_extract_ros.app.evaluation.registration import _material_trajectories  # noqa: E402


SOURCES = ('registered', 'perfect', 'registered skeleton, perfect motion', 'perfect skeleton, registered motion',
           'lost frames made perfect')


def joint_scores(bag: Path, settings: dict | None = None, lost_frame_m: float = 0.06) -> tuple:
    """({source: JointReport} for one bag, the sources as SOURCES; the number of lost frames
    and of frames scored); settings: SkeletonPipeline's keyword arguments but the schedule
    (config.pipeline_params); lost_frame_m: a frame whose registered points' error has its
    95th percentile above this (m) is lost."""
    topic = select_cloud_topic(bag)
    frames = list(read_cloud_frames(bag, topic))
    stamps = np.array([f.stamp for f in frames])
    pipeline = SkeletonPipeline(schedule=GrowthSchedule(window_size=len(frames) + 1), **(settings or {}))
    registered = pipeline.register(f.points.reshape(f.height, f.width, 3) if f.height > 1 else f.points
                                   for f in frames)
    gt = GroundTruth.load(bag / 'gt.npz')
    first = int(np.flatnonzero(np.isfinite(registered).all(axis=(1, 2)))[0])
    _, gt_index = match_frames(stamps, gt.stamps)
    # tied in the rest pose's frame, where the registered points are the rest points: the
    # frames before it were registered backward from it and may have slid
    rest_frame = pipeline.registration.rest_frame_
    perfect = registered.astype(np.float64)
    perfect[first:], _, _ = _material_trajectories(perfect[rest_frame], gt, gt_index[first:],
                                                   anchor=rest_frame - first)
    span = registration_span(registered, stamps)

    def scored(result, positions):
        skeleton = PredictedSkeleton(result.model.joint_names, list(result.model.parents),
                                     stamps[result.frames], positions)
        return evaluate_joints(skeleton, gt, None, *span)

    error = np.linalg.norm(registered[first:] - perfect[first:], axis=2)
    lost = first + np.flatnonzero(np.percentile(error, 95, axis=1) > lost_frame_m)
    mended = registered.astype(np.float64)
    mended[lost] = perfect[lost]

    scores, results = {}, {}
    for name, points in (('registered', registered), ('perfect', perfect), ('lost frames made perfect', mended)):
        result = results[name] = pipeline.extract(points)
        scores[name] = scored(result, result.joint_positions)
    for learned_on, fitted_to, points in (('registered', 'perfect', perfect), ('perfect', 'registered', registered)):
        result = results[learned_on]
        fit = LiveJointTracker(result.model, pipeline.joint_params)
        positions = np.stack([fit.track(points[frame]) for frame in result.frames])
        scores[f'{learned_on} skeleton, {fitted_to} motion'] = scored(result, positions)
    return scores, len(lost), len(registered) - first


def _row(name: str, scene: str, source: str, report, label: str | None = None) -> str:
    found = [j for j in report.per_joint if j['found']]
    along = np.mean([j['offset_along_ray_m'] for j in found]) if found else float('nan')
    across = np.mean([j['offset_across_ray_m'] for j in found]) if found else float('nan')
    return (f'| {name} | {scene} | {half(name)} | {label or source} | {report.n_predicted} | '
            f'{report.articulated_recall:.2f} / {report.articulated_recall_10cm:.2f} / '
            f'{report.articulated_recall_5cm:.2f} | {report.precision:.2f} | {100 * report.mean_error_m:.1f} / '
            f'{100 * report.normalized_error_m:.1f} | {100 * along:.1f} / {100 * across:.1f} | '
            f'{report.moving_recall:.2f} | {report.tracking_skill:.2f} |')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--only', default='', help='comma-separated name fragments (e.g. wave,run)')
    parser.add_argument('--scenes', default='empty')
    parser.add_argument('--frames', type=int, default=90)
    parser.add_argument('--work', default=None, help='bags are simulated here, or reused when present')
    parser.add_argument('--params', default=None,
                        help="a parameter YAML for skel-extract run: its values instead of the defaults")
    parser.add_argument('--lost-frame-cm', type=float, default=6.0,
                        help="a frame is lost when the 95th percentile of its registered points' error is above "
                             'this (cm)')
    args = parser.parse_args()
    settings = pipeline_params(load_params_file(args.params)) if args.params else {}
    settings.pop('schedule', None)      # here the window is the whole clip
    chosen = [(n, a) for n, a in subjects([o for o in args.only.split(',') if o]) if n not in ('samba',)]
    if not chosen:
        print('no real-motion data; nothing to benchmark')
        return 0
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix='bench_sources_'))
    print('| subject | scene | half | registration | found | artic. recall 15 / 10 / 5 cm | precision | '
          'joint mean / offset removed (cm) | offset along / across the ray (cm) | moving recall | '
          'tracking skill |')
    print('|' + '---|' * 11)
    for name, source_args in chosen:
        for scene in args.scenes.split(','):
            bag = work / f'{name}_{scene}'
            if not (bag / 'gt.npz').is_file():
                simulate_and_run(name, source_args, scene, args.frames, work)
            scores, n_lost, n_frames = joint_scores(bag, settings, args.lost_frame_cm / 100.0)
            for source in SOURCES:
                label = f'{n_lost} of {n_frames} {source}' if source == SOURCES[-1] else None
                print(_row(name, scene, source, scores[source], label), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
