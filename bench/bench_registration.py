#!/usr/bin/env python3
"""Registration benchmark: this method vs the paper's Alg. 1 vs Coherent Point Drift vs
not moving at all.

    python bench/bench_registration.py [--frames 90] [--sequences human,hand,fish,samba,swing]
                                       [--real] [--scenes empty,room] [--only wave,cow]
                                       [--methods ours,paper,tracker,tracker_start,rustcpd,static]

Methods: `ours` (the defaults: robust smoothness, recapture), `ours_visibility` (and the
visibility test), `paper` (the registration before the real-motion issue: Eq. 4 as written,
beta_smooth = 1e5, no recapture, our translations/rotations M-step), `paper_per_node` (the
paper's Alg. 1 node by node), `tracker` (issue "one articulated tracker": `ours` on the
first `window_size` frames of the default growth schedule, or the first half of a shorter
clip; the skeleton learned on them as the nodes learn it (Steps 2 and 3); then every later
frame fitted by that skeleton alone, the ArticulatedTracker chained from frame to frame and
seeded once from the window's last registered frame, its LBS pose of every rest point
scored; its ms/frame are the tracked frames'), `tracker_start` (`ours`, the same window and
skeleton as `tracker`, then every later frame's EM started from that skeleton's fit of the
frame itself: the ArticulatedTracker seeded from the last registered frame, as the nodes'
`live_start` starts the registration from the live fit; its ms/frame are those frames', fit
and EM), `rustcpd` / `pycpd` (CPD frame
to frame, Y_t = CPD(V_t, Y_{t-1})), `static` (the rest pose, never moved). Every method sees the same
preprocessed subject points and starts from the same rest set. Each runs in its own
process so its peak memory (max RSS) is its own. Needs the `bench` extra:
pip install -e .[bench]. Prints a Markdown table; `--json FILE` keeps the raw numbers.

Sequences: the built-in subjects; `swing` (sim/stress.py: an arm hanging beside the torso
swings up at 22 cm a frame, then across in front of it); the real captured samba mesh
sequence ($SKEL_SHARED_DATA/samba_mesh_sequence.npz, Vlasic et al. 2008) through the same
virtual Kinect, its true vertex motion the ground truth. `--real` adds every motion-capture
clip in $SKEL_SHARED_DATA/mocap/ and the cow rig, in each of `--scenes`, rendered as
bench_real_motion.py renders them and segmented by the pipeline's segmentation (the rest
pose is the first frame the subject is wholly in view; frames before it are not scored).
Absent data is skipped. Columns: mean and p95 error over all points and frames, the worst
frame's p95, drift (mean error) at frames 30 / 60 / 90, the mean error over the frames the
`tracker` method tracks (after its window, for every method), median ms per frame.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from skel_extract_ros.core.growth import GrowthSchedule, SkeletonGrowth  # noqa: E402
from skel_extract_ros.core.live import ArticulatedTracker, LiveJointTracker  # noqa: E402
from skel_extract_ros.core.preprocess import Preprocessor  # noqa: E402
from skel_extract_ros.core.registration import NonRigidRegistration, RegistrationParams  # noqa: E402
from skel_extract_ros.core.rest_pose import RestPose, RestPoseParams  # noqa: E402
from skel_extract_ros.core.sequence import SequenceRegistration  # noqa: E402
from skel_extract_ros.app.evaluation import GroundTruth, evaluate_registration  # noqa: E402
from skel_extract_ros.sim import DepthCamera, Intrinsics, NoiseModel, generate_sequence  # noqa: E402
from skel_extract_ros.sim.camera import look_at  # noqa: E402
from skel_extract_ros.sim.sources import simulate_swing  # noqa: E402

DATA = Path(os.environ.get('SKEL_SHARED_DATA', REPO.parent / 'shared' / 'data'))
SAMBA = Path(os.environ.get('SKEL_SAMBA', DATA / 'samba_mesh_sequence.npz'))
METHODS = ('ours', 'ours_visibility', 'paper', 'paper_per_node', 'tracker', 'tracker_start', 'rustcpd', 'pycpd',
           'static')
METHOD_PARAMS = {'ours': {}, 'ours_visibility': {'visibility': True},
                 'paper': {'smoothness': 'paper', 'recapture': False},
                 'paper_per_node': {'smoothness': 'paper', 'recapture': False, 'm_step': 'per_node'}}


def render_samba(frames: int, seed: int = 0):
    """The samba mesh sequence through the virtual 320x240 Kinect, performer facing it."""
    data = np.load(SAMBA)
    vertices = data['vertices'][:frames].astype(np.float64)
    faces = data['faces']
    # y is up and the performer faces +x (toes point that way): camera 2.5 m out on +x.
    centre = vertices[0].mean(axis=0)
    target = np.array([centre[0], 0.95, centre[2]])
    camera_from_world = np.linalg.inv(look_at(target + [2.5, 0.1, 0.0], target))
    in_camera = vertices @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    camera = DepthCamera(Intrinsics.from_resolution('320x240'))
    noise = NoiseModel.kinect()
    rng = np.random.default_rng(seed)
    clouds = [camera.back_project(noise.apply(camera.render_depth([(v, faces)]), rng)) for v in in_camera]
    stamps = np.arange(len(clouds)) / float(data['fps'])
    gt = GroundTruth(stamps, np.zeros((len(clouds), 0, 3)), [], np.zeros(0), in_camera, 1.8,
                     surface_faces=faces)
    return clouds, gt


def simulated(subject: str, frames: int):
    seq = generate_sequence(subject, frames, seed=1, progress=False)
    return seq.clouds, GroundTruth.from_arrays(seq.ground_truth)


def real_sequences(scenes: list, only: list) -> list:
    """(name, simulate function, keyword arguments) for every real clip and the cow."""
    from skel_extract_ros.sim.sources import simulate_mocap, simulate_rig
    found = []
    for clip in sorted((DATA / 'mocap').glob('*.bvh')):
        name = clip.stem.replace('dataset-2_', '').replace('_001', '')
        found.append((name, simulate_mocap, {'path': clip, 'treadmill': name.startswith('run')}))
    if (DATA / 'rigs' / 'cow' / 'cow.obj').is_file():
        found.append(('cow', simulate_rig, {'directory': DATA / 'rigs' / 'cow'}))
    if only:
        found = [row for row in found if any(o in row[0] for o in only)]
    return [(f'{name}_{scene}', function, {**kwargs, 'scene': scene})
            for name, function, kwargs in found for scene in scenes]


def segmented(simulate, kwargs: dict, frames: int):
    """A real-motion sequence through the pipeline's segmentation and preprocessing:
    (observed frames, rest points, index of the rest frame, ground truth)."""
    sequence = simulate(frames=frames, progress=False, **kwargs)
    # the rest pose from the first frame the subject is wholly in view (choice_frames 1):
    # every method registers forward from it, so a rest pose chosen later in the clip
    # would be registered onto the first frames from another pose
    registration = SequenceRegistration(RegistrationParams(max_iterations=1), RestPoseParams(choice_frames=1),
                                        keep_observed=True)
    registration.register(list(sequence.clouds))
    if registration.rest_pose_ is None:
        raise RuntimeError('the segmentation never found the subject')
    start = registration.rest_frame_
    return registration.observed_, registration.rest_pose_.points, start, GroundTruth.from_arrays(sequence.ground_truth)


def prepare(name: str, frames: int, cache: Path, real: dict):
    start = 0
    if name in real:
        observed, rest, start, gt = segmented(*real[name], frames)
    else:
        if name == 'samba':
            clouds, gt = render_samba(frames)
        elif name == 'swing':
            sequence = simulate_swing(min(frames, 40), progress=False)
            clouds, gt = sequence.clouds, GroundTruth.from_arrays(sequence.ground_truth)
        else:
            clouds, gt = simulated(name, frames)
        preprocess = Preprocessor()
        observed = [preprocess(c.reshape(-1, 3)) for c in clouds]
        rest = RestPose.from_points(observed[0]).points
    np.savez(cache / f'{name}.npz', rest=rest, start=start, offsets=np.cumsum([0] + [len(o) for o in observed]),
             observed=np.concatenate(observed))
    return gt, int(np.median([len(o) for o in observed[start:]]))


def worker(name: str, method: str, cache: Path) -> None:
    """Runs in a child process: registers the cached sequence, writes points and timings."""
    data = np.load(cache / f'{name}.npz')
    rest, offsets, observed, start = data['rest'], data['offsets'], data['observed'], int(data['start'])
    frames = [observed[a:b].astype(np.float64) for a, b in zip(offsets[:-1], offsets[1:])][start:]
    registered, times = [], []
    if method in METHOD_PARAMS:
        registration = NonRigidRegistration(rest, RegistrationParams(**METHOD_PARAMS[method]))
        for frame in frames:
            started = time.perf_counter()
            registered.append(registration.register_frame(frame).points)
            times.append(time.perf_counter() - started)
    elif method in ('tracker', 'tracker_start'):
        registered, times = track_with_skeleton(rest, frames, method == 'tracker_start')
    elif method == 'static':
        registered = [rest] * len(frames)
        times = [0.0] * len(frames)
    elif method == 'rustcpd':
        import rustcpd
        current = rest
        for frame in frames:
            started = time.perf_counter()
            # standard CPD settings (alpha = beta = 2 on normalised data); rustcpd's default
            # rank-300 kernel approximation
            current = np.asarray(rustcpd.register_deformable(frame, current, normalize=True).points)
            times.append(time.perf_counter() - started)
            registered.append(current)
    elif method == 'pycpd':
        from pycpd import DeformableRegistration
        current = rest
        for frame in frames:
            started = time.perf_counter()
            # pycpd does not normalise: do what CPD prescribes, then map back. Its tolerance
            # is absolute on sigma2 (normalised units), so keep it small.
            centre, scale = frame.mean(axis=0), frame.std()
            fit = DeformableRegistration(X=(frame - centre) / scale, Y=(current - centre) / scale,
                                         alpha=2.0, beta=2.0, tolerance=1e-6, max_iterations=100)
            moved, _ = fit.register()
            current = moved * scale + centre
            times.append(time.perf_counter() - started)
            registered.append(current)
    # frames before the rest pose (the subject not yet wholly in view) are not registered
    points = np.concatenate([np.full((start, len(rest), 3), np.nan), np.array(registered)])
    np.savez(cache / f'{name}_{method}_out.npz', points=points, times=np.array(times))


def tracker_window(n_frames: int) -> int:
    """Frames the `tracker` method registers and learns on before it tracks: the default
    growth schedule's window, or the first half of a clip shorter than two windows."""
    return min(GrowthSchedule().window_size, n_frames // 2)


def track_with_skeleton(rest: np.ndarray, frames: list, start_registration: bool = False) -> tuple:
    """The `tracker` method, or with start_registration the `tracker_start` method: (registered
    points per frame, seconds per frame after the window): the times are the tracker's own
    (and the registration's it starts), without the learning (Steps 2 and 3, once) or the
    window's registration."""
    registration = NonRigidRegistration(rest, RegistrationParams())
    window = tracker_window(len(frames))
    registered = [registration.register_frame(frame).points for frame in frames[:window]]
    times = []
    model = SkeletonGrowth(rest).update(np.arange(window), np.array(registered), frames[:window]).model
    if model is None:
        raise RuntimeError(f'no skeleton learned on the first {window} frames')
    pose = LiveJointTracker(model)                  # every model point, in the registered order
    tracker = ArticulatedTracker(model)
    tracker.seed(*pose.fit(registered[-1]))
    for frame in frames[window:]:
        started = time.perf_counter()
        if start_registration:
            # as the registration node with live_start: the live fit, seeded from the newest
            # registered frame, gives the pose Alg. 1 starts from (none when it diverged)
            tracker.seed(*pose.fit(registered[-1]))
        posed = pose.deform(*tracker.fit(frame))
        if start_registration:
            posed = registration.register_frame(frame, None if tracker.diverged else posed).points
        registered.append(posed)
        times.append(time.perf_counter() - started)
    return registered, times


def run_method(name: str, method: str, cache: Path):
    process = subprocess.Popen([sys.executable, __file__, '--worker', name, method, str(cache)])
    _, status, usage = os.wait4(process.pid, 0)
    if status != 0:
        raise RuntimeError(f'{method} on {name} failed (status {status})')
    out = np.load(cache / f'{name}_{method}_out.npz')
    return out['points'], out['times'], usage.ru_maxrss / 1024.0  # MiB


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--frames', type=int, default=90)
    parser.add_argument('--sequences', default='human,hand,fish,samba,swing',
                        help="built-in, samba and swing sequences ('' for none)")
    parser.add_argument('--real', action='store_true', help='add every real clip and the cow (shared data)')
    parser.add_argument('--scenes', default='empty,room', help='scenes of the real clips')
    parser.add_argument('--only', default='', help='real clips whose name contains one of these (comma list)')
    parser.add_argument('--methods', default=','.join(METHODS))
    parser.add_argument('--json', default=None, help='write the raw results here')
    parser.add_argument('--worker', nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker[0], args.worker[1], Path(args.worker[2]))
        return 0
    methods = args.methods.split(',')
    unknown = set(methods) - set(METHODS)
    if unknown:
        parser.error(f'unknown method(s) {", ".join(sorted(unknown))}')
    rows = []
    real = {}
    if args.real:
        real = {name: (function, kwargs) for name, function, kwargs in
                real_sequences(args.scenes.split(','), [o for o in args.only.split(',') if o])}
    sequences = [name for name in args.sequences.split(',') if name] + list(real)
    print('| sequence | points/frame | method | mean (cm) | p95 (cm) | worst frame p95 (cm) | drift @30 / @60 / @90 (cm) '
          '| mean after the window (cm) | median ms/frame | peak memory (MiB) |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp)
        for name in sequences:
            if name == 'samba' and not SAMBA.is_file():
                print(f'(samba skipped: {SAMBA} not found)', file=sys.stderr)
                continue
            gt, points_per_frame = prepare(name, args.frames, cache, real)
            for method in methods:
                try:
                    registered, times, memory = run_method(name, method, cache)
                except RuntimeError as error:      # one method failing on one sequence
                    print(f'| {name} | {points_per_frame} | {method} | failed: {error} | | | | | | |', flush=True)
                    continue
                result = evaluate_registration(registered, gt.stamps[:len(registered)], gt)
                drift = ' / '.join(f'{100 * result["drift_m"][k]:.1f}' for k in ('30', '60', '90')
                                   if k in result['drift_m'])
                per_frame = np.array(result['per_frame_error_m'])
                # the frames the `tracker` method tracks (track_with_skeleton's window), for every method
                after = 100 * float(per_frame[tracker_window(len(per_frame)):].mean())
                row = {'sequence': name, 'method': method, 'points_per_frame': points_per_frame,
                       'mean_cm': 100 * result['mean_error_m'], 'p95_cm': 100 * result['p95_error_m'],
                       'worst_frame_p95_cm': 100 * result['worst_frame_p95_m'],
                       'drift_cm': {k: 100 * v for k, v in result['drift_m'].items()},
                       'mean_after_window_cm': after,
                       'median_ms': 1000 * float(np.median(times)), 'peak_mib': memory}
                rows.append(row)
                print(f'| {name} | {points_per_frame} | {method} | {row["mean_cm"]:.2f} | {row["p95_cm"]:.2f} | '
                      f'{row["worst_frame_p95_cm"]:.1f} | {drift} | {after:.2f} | {row["median_ms"]:.0f} | '
                      f'{memory:.0f} |', flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
