"""`skel-extract`: the command-line entry point.

Every command prints progress for long work and fails with exit code 2 and a single
`skel-extract: error: ...` line on bad input.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


class UserError(Exception):
    """An error caused by the user's input: reported as one line, no traceback."""


def _simulate_sequence(args):
    """The sequence `simulate` asked for: a built-in subject, a BVH clip, a rig or a mesh
    sequence (exactly one)."""
    from ..sim import NoiseModel, generate_sequence
    from ..sim import sources

    noise = NoiseModel.kinect() if args.noise == 'kinect' else NoiseModel.none()
    chosen = [name for name in ('subject', 'bvh', 'rig', 'mesh_sequence') if getattr(args, name)]
    if len(chosen) != 1:
        raise UserError('give exactly one of --subject, --bvh, --rig, --mesh-sequence')
    frames = args.frames if args.frames is not None else 90
    if frames < 2:
        raise UserError(f'--frames must be at least 2, got {frames}')
    if args.walk_in < 0:
        raise UserError(f'--walk-in must be 0 or more frames, got {args.walk_in}')
    options = dict(resolution=args.resolution, noise=noise, scene=args.scene, seed=args.seed,
                   enter_frames=args.walk_in, surface_samples=args.surface_samples)
    if args.one_limb_at_a_time and not args.subject:
        raise UserError('--one-limb-at-a-time applies to a built-in --subject (a clip, rig or mesh '
                        'sequence brings its own motion)')
    if args.subject:
        if args.start is not None or args.distance is not None or args.azimuth or args.treadmill:
            raise UserError('--start, --distance, --azimuth and --treadmill apply to --bvh, --rig and '
                            '--mesh-sequence; a built-in subject has its own camera')
        return generate_sequence(args.subject, frames, one_limb_at_a_time=args.one_limb_at_a_time, **options)
    view = dict(distance=args.distance if args.distance is not None else 3.0, azimuth=args.azimuth)
    if args.bvh:
        return sources.simulate_mocap(args.bvh, frames, args.start, units=args.units,
                                      treadmill=args.treadmill, **view, **options)
    if args.rig:
        return sources.simulate_rig(args.rig, frames, **view, **options)
    return sources.simulate_mesh_sequence(args.mesh_sequence, frames, args.start or 0, **view, **options)


def _cmd_simulate(args) -> int:
    from ..sim.output import write_simulated_bag

    out = Path(args.out)
    if out.exists():
        raise UserError(f'{out} already exists; choose a new --out or remove it')
    started = time.perf_counter()
    sequence = _simulate_sequence(args)
    generated = time.perf_counter() - started
    gt_path = write_simulated_bag(sequence, out, topic=args.topic, depth_image=args.depth_image)
    counts = sequence.points_per_frame()
    subject = sequence.ground_truth['subject_mask'].sum(axis=(1, 2))
    n_frames = len(sequence.clouds)
    start = sequence.ground_truth.get('source_start_frame')
    window = f' (source frames {int(start)}-{int(start) + n_frames - 1})' if start is not None else ''
    print(f'{sequence.name}: {n_frames} frames{window} at {args.resolution}, scene {args.scene} '
          f'({generated:.1f} s, {1000 * generated / n_frames:.0f} ms/frame); '
          f'valid points per frame {counts.min()}-{counts.max()} (median {int(np.median(counts))}), '
          f'subject {subject.min()}-{subject.max()}; '
          f'{len(sequence.ground_truth["joint_names"])} ground-truth joints')
    from ..codecs.bag import select_cloud_topic
    print(f'bag: {out}  topic: {select_cloud_topic(out)}  ground truth: {gt_path}')
    return 0


def _cmd_evaluate(args) -> int:
    from .evaluation import EvaluationError, GroundTruth, evaluate_outputs
    from .evaluation.report import score_lines
    if not args.pred and not args.registered:
        raise UserError('nothing to evaluate: give --pred and/or --registered')
    try:
        result = evaluate_outputs(GroundTruth.load(args.gt), args.pred, args.registered, args.threshold)
    except EvaluationError as error:
        raise UserError(str(error)) from None
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print('\n'.join(score_lines(result, per_joint=True)))
    return 0


def _parse_frame_range(text: str | None):
    """'a:b' -> slice(a, b) over frame indices (either side may be empty)."""
    if not text:
        return slice(None)
    try:
        start, _, stop = text.partition(':')
        if not _:
            raise ValueError
        return slice(int(start) if start else None, int(stop) if stop else None)
    except ValueError:
        raise UserError(f'--frames must look like a:b (frame indices), got {text!r}') from None


def _cmd_run(args) -> int:
    import itertools

    from ..codecs.bag import BagError, cloud_topics, read_cloud_frames, select_cloud_topic
    from ..config import ParamsError, load_params_file, pipeline_params
    from ..core.pipeline import SkeletonPipeline
    from ..core.skeleton_model import pivot_document
    from ..core.structure import StructureError
    from .outputs import write_registered, write_skeleton
    from .progress import progress_bar

    out = Path(args.out)
    frames_slice = _parse_frame_range(args.frames)
    try:
        settings = pipeline_params(load_params_file(args.params)) if args.params else {}
        topic = select_cloud_topic(args.input, args.topic)
        n_messages = cloud_topics(args.input)[topic]
    except (BagError, ParamsError) as error:
        raise UserError(str(error)) from None
    start, stop, _ = frames_slice.indices(n_messages)
    n_frames = max(0, stop - start)
    if n_frames < 2:
        raise UserError(f'{args.input}: {n_frames} frame(s) selected on {topic}; at least 2 are needed')
    out.mkdir(parents=True, exist_ok=True)

    stamps, frame_ids, scenes = [], [], []

    def clouds():
        for frame in itertools.islice(read_cloud_frames(args.input, topic), start, stop):
            stamps.append(frame.stamp)
            frame_ids.append(frame.frame_id)
            # a thinned copy of the whole view, for skeleton.png (the subject over the room)
            finite = frame.points[np.isfinite(frame.points).all(axis=1)]
            scenes.append(finite[::max(1, len(finite) // 8000)])
            yield frame.points.reshape(frame.height, frame.width, 3) if frame.height > 1 else frame.points

    pipeline = SkeletonPipeline(**settings)
    progress = progress_bar(total=n_frames, desc='register', unit='frame')
    counts = {}

    def on_frame(_index, status):
        counts[status] = counts.get(status, 0) + 1
        progress.set_postfix(counts, refresh=False)
        progress.update()

    started = time.perf_counter()
    try:
        registered = pipeline.register(clouds(), on_frame=on_frame)
    except BagError as error:
        raise UserError(str(error)) from None
    finally:
        progress.close()
    registration = pipeline.registration
    if registration.rest_pose_ is None:
        found = sum(s.status == 'subject' for s in registration.segmentation_)
        raise UserError(f'{args.input}: no rest pose: the subject was found in {found} of '
                        f'{len(registration.segmentation_)} frames and never wholly in view with enough '
                        'points (nobody moved? check the segmentation and preprocessing parameters)')
    frame_id = frame_ids[0] if frame_ids else ''
    stamps = np.array(stamps)
    segments = registration.segmentation_
    subject_points = np.array([s.n_subject for s in segments])
    background = np.array([s.background_fraction for s in segments])
    write_registered(out, registered, stamps, registration.statuses_, registration.rest_pose_.points, frame_id,
                     sigma2=registration.sigma2_, recaptured=registration.recaptured_,
                     landmarks=registration.landmarks_, subject_points=subject_points, background_fraction=background,
                     segmentation=np.array([s.status for s in segments]))
    recaptures = int(registration.recaptured_.sum())
    with_landmarks = int((registration.landmarks_ > 0).sum())
    print(f'registered {len(registered)} frames of {registered.shape[1]} points -> {out / "registered.npz"}'
          f'  ({", ".join(f"{n} {status}" for status, n in sorted(counts.items()))}'
          f'{f"; {recaptures} lost parts recaptured" if recaptures else ""}'
          f'{f"; limb ends matched in {with_landmarks} frames" if with_landmarks else ""}; '
          f'rest pose from frame {registration.rest_frame_}, the most spread-out of up to '
          f'{registration.rest_params.choice_frames} from the first usable)')
    with_subject = subject_points > 0
    several = max((s.n_moving_regions for s in segments), default=0)
    print(f'subject found in {with_subject.sum()} of {len(segments)} frames'
          + (f' (first at frame {int(np.argmax(with_subject))})' if with_subject.any() else '')
          + (f', median {int(np.median(subject_points[with_subject]))} points, '
             f'{100 * np.median(background[with_subject]):.1f} % of the view removed as background'
             if with_subject.any() else '')
          + (f'; up to {several} moving regions seen, the one moving most followed' if several > 1 else ''))
    print('extracting the skeleton (steps 2 and 3) ...', file=sys.stderr)
    try:
        result = pipeline.extract(registered)
    except StructureError as error:
        raise UserError(f'{args.input}: {error}') from None
    model, frames = result.model, result.frames
    write_skeleton(out, model.joint_names, model.parents, model.rest_joints, frame_id, stamps[frames],
                   result.joint_positions, result.joint_confidence, model.rest_points, model.labels,
                   registered=dict(enumerate(registered[frames])), observed=dict(enumerate(result.observed)),
                   scene={row: scenes[i] for row, i in enumerate(frames)}, pivot=pivot_document(model.pivot))
    total = time.perf_counter() - started
    per_frame = np.array(registration.times_.per_frame_registration) * 1000.0
    seconds = result.seconds
    pivots = '' if model.pivot is None else f' ({int(model.pivot.fixed.sum())} pivots fixed by the motion)'
    print(f'skeleton: {result.model.n_joints} joints{pivots}, {result.structure.n_bones} bones '
          f'-> {out / "skeleton.json"}, {out / "skeleton.bvh"}, {out / "skeleton.png"}')
    print(step_times_line(seconds, float(np.median(per_frame)), total))
    _score_if_simulated(Path(args.input), out)
    return 0


def step_times_line(seconds: dict, per_frame_ms: float, total_s: float) -> str:
    """The `time:` line `run` prints (and bench/bench_real_motion.py reads): each step's
    seconds, the registration's median ms per frame, the total (s)."""
    return (f'time: segmentation {seconds["segmentation"]:.1f} s | '
            f'preprocess {seconds["preprocess"]:.1f} s | rest pose {seconds["rest_pose"]:.1f} s | '
            f'registration {seconds["registration"]:.1f} s (median {per_frame_ms:.0f} ms/frame) | '
            f'structure {seconds["structure"]:.1f} s | joints {seconds["joints"]:.1f} s | total {total_s:.1f} s')


def _score_if_simulated(bag: Path, out: Path) -> None:
    """A bag made by `simulate` carries its ground truth (gt.npz): say how `out` scores."""
    from .evaluation import EvaluationError, GroundTruth, evaluate_outputs
    from .evaluation.report import score_lines
    if not (bag / 'gt.npz').is_file():
        return
    try:
        gt = GroundTruth.load(bag / 'gt.npz')
        result = evaluate_outputs(gt, out / 'skeleton.json' if gt.joints.shape[1] else None,
                                  out / 'registered.npz')
    except EvaluationError as error:
        print(f'cannot score against {bag / "gt.npz"}: {error}', file=sys.stderr)
        return
    print(f'against the ground truth beside the bag ({bag / "gt.npz"}):')
    print('\n'.join(score_lines(result, per_joint=False)))


def _cmd_replay(args) -> int:
    from ..codecs.bag import BagError
    from ..config import ParamsError
    from .progress import progress_bar
    from .replay import ReplayError, replay

    bar = None

    def on_published(done, total):
        nonlocal bar
        if bar is None:
            bar = progress_bar(total=total, desc='replay', unit='cloud')
        bar.update(done - bar.n)

    out = Path(args.out)
    try:
        summary = replay(args.input, out, rate=args.rate, topic=args.topic, params_file=args.params,
                         namespace=args.namespace, progress=on_published, realtime=args.realtime,
                         loops=args.loop, bounce=args.bounce)
    except (BagError, ParamsError, ReplayError) as error:
        raise UserError(str(error)) from None
    finally:
        if bar is not None:
            bar.close()
    counts = ', '.join(f'{topic} {n}' for topic, n in sorted(summary['counts'].items()))
    print(f'replayed {summary["n_frames"]} registered frames ({summary["clouds_per_s"]:.1f} clouds/s sustained); '
          f'skeleton: {summary["n_joints"]} joints on {summary["n_frames_with_joints"]} frames')
    print(f'wrote {out / "output.mcap"} ({counts}), {out / "skeleton.json"}, {out / "skeleton.bvh"}, '
          f'{out / "registered.npz"}, {out / "skeleton.png"}; node logs in {out / "logs"}')
    if 'realtime' in summary:
        camera = summary['realtime']
        print(f'realtime: {camera["with_joints"]} of {camera["published"]} camera frames got joints '
              f'({camera["joints_hz"]:.1f} Hz), {camera["without_joints"]} without; latency cloud -> joints '
              f'median {camera["latency_ms_median"]:.0f} ms, p95 {camera["latency_ms_p95"]:.0f} ms '
              f'({camera["live_frames"]} live frames)')
        if not np.isnan(camera['first_skeleton_s']):
            print(f'first skeleton {camera["first_skeleton_s"]:.1f} s after the first camera frame')
        tracking = camera['tracking']
        if tracking is not None:
            print(f'once tracking ({tracking["seconds"]:.1f} s): {tracking["with_joints"]} of '
                  f'{tracking["published"]} camera frames got joints ({tracking["joints_hz"]:.1f} Hz of '
                  f'{tracking["camera_hz"]:.1f} Hz), {tracking["filtered"]} passed the segmentation')
    for name in ('registration_ms', 'live_joints_ms'):
        if name in summary:
            values = summary[name]
            print(f'latency {name[:-3]}: median {values["median"]:.0f} ms, worst {values["worst"]:.0f} ms '
                  f'({values["n"]} frames)')
    _score_if_simulated(Path(args.input), out)
    failed = {name: code for name, code in summary['exit_codes'].items() if code != 0}
    if failed:
        raise UserError(f'node(s) did not shut down cleanly: {failed} (see {out / "logs"}; a node killed '
                        'after ignoring Ctrl-C for 20 s, code -9, wrote its threads\' stacks there)')
    return 0


def _cmd_record(args) -> int:
    from .record import record
    out = Path(args.out)
    demonstration = record(out, args.topic, idle=args.idle, frames=args.frames, namespace=args.namespace,
                           started=lambda topic: print(f'recording {topic} (Ctrl-C ends)', flush=True))
    print(f'wrote {out / "demonstration.csv"}, {out / "demonstration.bvh"} ({len(demonstration)} frames)')
    return 0


def _cmd_info(args) -> int:
    from ..codecs.bag import BagError, read_cloud_frames, select_cloud_topic
    try:
        topic = select_cloud_topic(args.input, args.topic)
        counts, stamps, frame_ids, layout = [], [], set(), None
        for frame in read_cloud_frames(args.input, topic):
            counts.append(int(np.isfinite(frame.points).all(axis=1).sum()))
            stamps.append(frame.stamp)
            frame_ids.add(frame.frame_id)
            layout = (frame.height, frame.width)
    except BagError as error:
        raise UserError(str(error)) from None
    if not counts:
        raise UserError(f'{args.input}: topic {topic} has no messages')
    counts = np.array(counts)
    duration = stamps[-1] - stamps[0]
    print(f'{args.input}: {len(counts)} clouds on {topic} ({", ".join(sorted(frame_ids))}), '
          f'{layout[0]}x{layout[1]}, {duration:.2f} s, '
          f'valid points per frame {counts.min()}-{counts.max()} (median {int(np.median(counts))})')
    return 0


# what run, replay and info read from a bag
TOPIC_HELP = ('the bag\'s PointCloud2 topic, or its depth Image topic (16UC1 mm or 32FC1 m, its CameraInfo on '
              'the sibling camera_info topic, e.g. /camera/depth/image_raw as in the sample bag); default: the '
              'only one')


def build_parser() -> argparse.ArgumentParser:
    from ..sim import SUBJECTS
    from ..sim.camera import RESOLUTIONS

    parser = argparse.ArgumentParser(
        prog='skel-extract',
        description='Template-free articulated skeleton extraction from depth point cloud sequences.')
    commands = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')

    simulate = commands.add_parser(
        'simulate', help='render a sequence through a virtual depth camera, with ground truth',
        description='Render a subject through a virtual Kinect-like depth camera into a bag, with '
                    'its ground truth (gt.npz) beside it. The subject is one of: a built-in '
                    'synthetic subject, a motion-capture clip (BVH) on a body of capsules, a '
                    'skinned rig blended between its key poses, or a captured mesh sequence.')
    source = simulate.add_argument_group('subject (exactly one)')
    source.add_argument('--subject', choices=sorted(SUBJECTS), help='built-in synthetic subject')
    source.add_argument('--bvh', help='motion-capture clip (BVH) to put a body on')
    source.add_argument('--rig', help='rig directory (mesh .obj, skeleton .tgf, weights .DMAT, '
                                      'key poses -K.Tmat), blended between its key poses')
    source.add_argument('--mesh-sequence', help='captured mesh sequence (.npz: vertices F x V x 3, '
                                                'faces, fps)')
    simulate.add_argument('--frames', type=int, default=None, help='number of frames at 30 Hz (default 90)')
    simulate.add_argument('--start', type=int, default=None,
                          help='first source frame (default: the window with the most limb motion)')
    simulate.add_argument('--out', required=True, help='bag directory to create (gt.npz goes inside)')
    simulate.add_argument('--scene', default='empty', choices=['empty', 'floor', 'room'],
                          help='what else the camera sees: nothing, a floor, or a room (floor, back '
                               'and side walls, a table, a standing lamp)')
    simulate.add_argument('--one-limb-at-a-time', action='store_true',
                          help='built-in subject: the limbs take turns (one moves at a time, in equal '
                               'slots of the sequence), as a person waves one arm, then the other')
    simulate.add_argument('--walk-in', type=int, default=0, metavar='N',
                          help='start outside the view and come in sideways over the first N frames')
    simulate.add_argument('--distance', type=float, default=None,
                          help='camera distance in m (default 3; backs off until all motion is in view)')
    simulate.add_argument('--azimuth', type=float, default=0.0,
                          help='camera direction in degrees about the vertical, 0 = facing the subject')
    simulate.add_argument('--treadmill', action='store_true',
                          help='BVH: take out the horizontal travel (a run does not fit the view)')
    simulate.add_argument('--units', default='auto', choices=['auto', 'm', 'cm', 'mm', 'in'],
                          help='BVH length unit (auto: from the skeleton size)')
    simulate.add_argument('--resolution', default='320x240', choices=sorted(RESOLUTIONS))
    simulate.add_argument('--noise', default='kinect', choices=['kinect', 'none'])
    simulate.add_argument('--seed', type=int, default=0)
    simulate.add_argument('--topic', default=None,
                          help='topic (default /camera/depth/points, or /camera/depth/image_raw with --depth-image)')
    simulate.add_argument('--depth-image', action='store_true',
                          help='record 16UC1 depth images (mm) with camera_info, as drivers publish by '
                               'default, instead of PointCloud2')
    simulate.add_argument('--surface-samples', type=int, default=4000,
                          help='ground-truth surface samples (for registration error)')
    simulate.set_defaults(handler=_cmd_simulate)

    evaluate = commands.add_parser('evaluate', help='score a skeleton and/or registration against gt.npz')
    evaluate.add_argument('--pred', help='skeleton.json')
    evaluate.add_argument('--gt', required=True, help='gt.npz from `skel-extract simulate`')
    evaluate.add_argument('--registered', help='registered.npz')
    evaluate.add_argument('--threshold', type=float, default=None,
                          help='match distance in m (default 0.15, scaled down for small subjects)')
    evaluate.add_argument('--json', action='store_true', help='print the full report as JSON')
    evaluate.set_defaults(handler=_cmd_evaluate)

    run = commands.add_parser('run', help='run the pipeline on a bag and write the results to --out')
    run.add_argument('input', help='rosbag2 directory (mcap or sqlite3) or .mcap file')
    run.add_argument('--out', required=True, help='output directory (created if missing)')
    run.add_argument('--topic', default=None, help=TOPIC_HELP)
    run.add_argument('--params', default=None, help='ROS 2 parameter YAML (params/skel_extract.yaml)')
    run.add_argument('--frames', default=None, help='frame index range a:b (python slice)')
    run.set_defaults(handler=_cmd_run)

    replay_cmd = commands.add_parser('replay', help='run the three ROS nodes over DDS on a bag and record the output')
    replay_cmd.add_argument('input', help='rosbag2 directory (mcap or sqlite3) or .mcap file')
    replay_cmd.add_argument('--out', required=True, help='output directory (created if missing)')
    replay_cmd.add_argument('--rate', type=float, default=1.0,
                            help='playback speed factor (default 1); 0 = as fast as the nodes take it')
    replay_cmd.add_argument('--realtime', action='store_true',
                            help='publish like a camera: at the bag\'s pace (x --rate), best effort, never waiting '
                                 'for the nodes; report the joints rate, latency and frames without joints')
    replay_cmd.add_argument('--loop', type=int, default=1, metavar='N',
                            help='with --realtime: play the bag N times, the stamps moving on each pass '
                                 '(a long live run from a short bag)')
    replay_cmd.add_argument('--bounce', action='store_true',
                            help='with --loop: every other pass plays the bag backwards, so the motion stays '
                                 'continuous (a walker walks back instead of jumping to the start)')
    replay_cmd.add_argument('--topic', default=None, help=TOPIC_HELP)
    replay_cmd.add_argument('--params', default=None, help='ROS 2 parameter YAML for the nodes')
    replay_cmd.add_argument('--namespace', default=None, help='run the nodes and topics in this namespace')
    replay_cmd.set_defaults(handler=_cmd_replay)

    record_cmd = commands.add_parser(
        'record', help='record skeleton/trajectory into a demonstration file (CSV and BVH)',
        description='An example consumer: subscribes to skeleton/trajectory (standard messages only) and, on '
                    'Ctrl-C, writes OUT/demonstration.csv (named joint positions, rotations and velocities per '
                    'stamp) and OUT/demonstration.bvh.')
    record_cmd.add_argument('--out', required=True, help='output directory (created if missing)')
    record_cmd.add_argument('--topic', default='skeleton/trajectory', help='MultiDOFJointTrajectory topic')
    record_cmd.add_argument('--namespace', default=None, help='the nodes\' namespace')
    record_cmd.add_argument('--idle', type=float, default=None, metavar='S',
                            help='stop S seconds after the last message (default: only on Ctrl-C)')
    record_cmd.add_argument('--frames', type=int, default=None, metavar='N', help='stop after N messages')
    record_cmd.set_defaults(handler=_cmd_record)

    info = commands.add_parser('info', help='summarise the point clouds or depth images in a bag')
    info.add_argument('input', help='rosbag2 directory or .mcap file')
    info.add_argument('--topic', default=None, help=TOPIC_HELP)
    info.set_defaults(handler=_cmd_info)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.handler(args)
    except UserError as error:
        print(f'skel-extract: error: {error}', file=sys.stderr)
        return 2
    except ValueError as error:  # library input validation (unknown subject, bad sizes, ...)
        print(f'skel-extract: error: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print('skel-extract: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
