"""Live joints without registration: the learned skeleton fitted to every camera frame's
observed subject points (core.live.CameraTracker), against the offline joints, as the
joint node does it (live_frames camera).

    python bench/bench_live.py [--only wave,punch] [--scenes empty,room] [--frames 90]
                               [--iterations 3] [--sweeps 1] [--lag 30] [--schemes chain,reach,bones]
                               [--work DIR]

For each real clip ($SKEL_SHARED_DATA, as bench_real_motion.py): simulate the bag (kept in
--work and reused), learn the skeleton as `skel-extract run` does (SkeletonPipeline:
registration, Steps 2-3 on the key frames; kept in --work too: empty it after changing
those). Then the node's live
scheme: the registration takes every `--lag`-th frame and answers `--lag` frames later
(30: a registration a second at 30 Hz, as the node once tracking; 3 was this bench's
cadence before); every camera frame is fitted from its observed points alone, started
from the model's fit of the newest registered frame it has. Schemes: `chain` (the node's
default, `live_chain`: each frame also fitted from the pose served for the frame before,
each of the two fits on half the points of one, the fit with the higher mean confidence
served; here with no deadline), `reach` (`live_chain: false`: from the registered pose
only, on all the points, the whole-body move and the joint weight ramp in each EM
iteration, the registered pose for a diverged fit) and `bones` (the node before that:
bone-by-bone updates at Alg. 2's joint weight only, the registered pose for a frame with
a bone without data). `--sweeps 1` is the node's camera-frame fit. `--limb-poses on` (the
node's `live_limb_poses`) starts the fit from the registered pose with each limb the frame
shows elsewhere put in a key frame's pose (core.limb_poses): a frame after the learned
window has every key frame's, as in the node; a frame of the window, fitted here though the
node has no skeleton yet, only those of the key frames its registered start had.
Printed per row: live vs offline joints on the same frames (median, p95, on Alg. 2's key
frames and on all), the same on the frames after the learned window alone (the frames the
node fits live; with their tracking skill, offline and live), the same for holding the
registered pose's joints (what waiting for the registration gives), the ground-truth scores
(articulated recall and joint mean of the offline and the live joints; moving recall and
tracking skill of the offline, the live and the held joints, each over the same scored
frames: what the live fit adds to the joints that move; the share of those frames the live
joints answered), the frames whose start had a limb re-posed, the frames that got the
registered pose and the per-frame fit time (median, p95; nothing else may run while timing).
"""
from __future__ import annotations

import argparse
import itertools
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'bench'))

from bench_real_motion import CLI, subjects  # noqa: E402

from skel_extract_ros.codecs.bag import read_cloud_frames, select_cloud_topic  # noqa: E402
from skel_extract_ros.core.limb_poses import LimbPoses  # noqa: E402
from skel_extract_ros.core.live import CameraTracker, LiveJointTracker  # noqa: E402
from skel_extract_ros.core.pipeline import SkeletonPipeline  # noqa: E402
from skel_extract_ros.app.evaluation import GroundTruth, PredictedSkeleton, evaluate_joints  # noqa: E402


def simulated_bag(name, source_args, scene, frames, work: Path) -> Path:
    bag = work / f'{name}_{scene}'
    if not (bag / 'gt.npz').is_file():
        done = subprocess.run([CLI, 'simulate', *source_args, '--frames', str(frames), '--scene', scene,
                               '--out', str(bag)], capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f'simulate {name}: {done.stderr.strip()[-300:]}')
    return bag


def learned(bag: Path) -> tuple:
    """(registered (F, M, 3), PipelineResult, observed [(N_t, 3)], JointParams, stamps) of
    `skel-extract run` on the bag; kept beside the bag (pickle) for the next scheme or run."""
    cache = bag.parent / f'{bag.name}_learned.pkl'
    if cache.is_file():
        return pickle.loads(cache.read_bytes())
    topic = select_cloud_topic(bag, None)
    stamps, clouds = [], []
    for frame in read_cloud_frames(bag, topic):
        stamps.append(frame.stamp)
        clouds.append(frame.points.reshape(frame.height, frame.width, 3) if frame.height > 1 else frame.points)
    pipeline = SkeletonPipeline()
    registered = pipeline.register(clouds)
    result = pipeline.extract(registered)
    value = (registered, result, pipeline.registration.observed_, pipeline.joint_params, stamps)
    cache.write_bytes(pickle.dumps(value))
    return value


def live_row(bag: Path, iterations: int, sweeps: int, lag: int, scheme: str, limb_poses: bool = True) -> dict:
    registered, result, observed, params, stamps = learned(bag)
    model, frames = result.model, result.frames
    registered_fit = LiveJointTracker(model, params)
    poses = {}

    def pose(frame):
        if frame not in poses:
            poses[frame] = registered_fit.fit(registered[frame])
        return poses[frame]
    # the node's cadence: the registration takes every `lag`-th frame and answers `lag`
    # frames later (at 30 Hz, lag 30 is a registration a second, as the node once tracking)
    scored = frames[(frames >= frames[0] + lag) & np.array([len(observed[f]) > 0 for f in frames])]
    if len(scored) == 0:
        raise ValueError(f'no frame to score: the clip has {len(frames)} registered frames, the lag is {lag}')
    seeds = frames[0] + ((scored - lag - frames[0]) // lag) * lag
    live = np.full((len(scored), model.n_joints, 3), np.nan)
    held = np.full_like(live, np.nan)
    seconds, lost = [], 0
    # chain and reach: the joint node's schemes (core.live.CameraTracker, with and without
    # live_chain); bones: the node before (no reach, the registered pose for any frame the
    # fit reports lost)
    camera = CameraTracker.for_model(model, params, registered_fit, iterations, chain=scheme == 'chain', sweeps=sweeps,
                                     reach=scheme != 'bones')
    tracker = camera.tracker
    # the limbs' key poses (live_limb_poses): the node learns the skeleton on every key frame
    # before it fits a frame live, so a frame after the window has them all; a frame of the
    # window, fitted here too, has those its registered start had (never its own or later)
    key_frames = np.asarray(result.key_frames)
    seen = None
    for row, (index, seed) in enumerate(zip(scored, seeds)):
        held[row] = registered_fit.joints_of(*pose(seed))
        known = key_frames <= (index if index > key_frames[-1] else seed)
        if limb_poses and scheme != 'bones' and np.count_nonzero(known) != seen:
            seen = np.count_nonzero(known)
            camera.limb_poses = LimbPoses(model, result.joints.rotations[known],
                                          result.joints.translations[known]) if seen else None
        started = time.perf_counter()
        if scheme != 'bones':
            camera.registered(int(seed), registered[seed])
            live[row], outcome = camera.track(int(index), observed[index])
            lost += outcome == 'lost'
        else:
            tracker.seed(*pose(seed))
            live[row] = tracker.track(observed[index])
            if tracker.lost:
                live[row], lost = held[row], lost + 1
        seconds.append(time.perf_counter() - started)
    offline = result.joint_positions[np.searchsorted(frames, scored)]
    gap = np.linalg.norm(live - offline, axis=2)                                # (F, J)
    hold_gap = np.linalg.norm(held - offline, axis=2)
    key = np.isin(scored, result.key_frames)
    after = scored > np.max(result.key_frames)     # the frames after the learned window: the node's live frames
    gt = GroundTruth.load(bag / 'gt.npz')
    stamp_array = np.asarray(stamps)[scored]

    def report(positions, frames=slice(None)):
        stamps = stamp_array[frames]
        skeleton = PredictedSkeleton(model.joint_names, list(model.parents), stamps, positions[frames])
        return evaluate_joints(skeleton, gt, start_stamp=float(stamps[0]), end_stamp=float(stamps[-1]))

    return {'joints': model.n_joints, 'frames': len(scored), 'points': int(np.median([len(o) for o in observed])),
            'gap_key_median_cm': 100 * float(np.nanmedian(gap[key])) if key.any() else float('nan'),
            'gap_median_cm': 100 * float(np.nanmedian(gap)), 'gap_p95_cm': 100 * float(np.nanpercentile(gap, 95)),
            'gap_after_median_cm': 100 * float(np.nanmedian(gap[after])) if after.any() else float('nan'),
            'gap_after_p95_cm': 100 * float(np.nanpercentile(gap[after], 95)) if after.any() else float('nan'),
            'hold_median_cm': 100 * float(np.median(hold_gap)), 'hold_p95_cm': 100 * float(np.percentile(hold_gap, 95)),
            'offline': report(offline), 'live': report(live), 'held': report(held), 'lost': lost,
            'offline_after': report(offline, after) if after.any() else None,
            'live_after': report(live, after) if after.any() else None,
            'reposed': camera.counts['reposed'],
            'ms_median': 1000 * float(np.median(seconds)), 'ms_p95': 1000 * float(np.percentile(seconds, 95))}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--only', default='')
    parser.add_argument('--scenes', default='empty,room')
    parser.add_argument('--frames', type=int, default=90)
    parser.add_argument('--iterations', type=int, default=3)
    parser.add_argument('--sweeps', type=int, default=1)
    parser.add_argument('--lag', type=int, default=30)
    parser.add_argument('--schemes', default='chain,reach',
                        help='chain: the joint node\'s default, live_chain (core.live.CameraTracker: also fitted '
                             'from the last served pose, each fit on half the points, the better supported fit '
                             'served); reach: live_chain false, from the registered pose only (whole-body move and '
                             'joint weight ramp, the registered pose when the fit diverges); bones: the node before '
                             '(bone-by-bone updates at Alg. 2\'s joint weight, the registered pose when a bone has '
                             'no data)')
    parser.add_argument('--limb-poses', default='on',
                        help='on: the node\'s default, live_limb_poses (core.limb_poses: the fit from the registered '
                             'pose starts each limb the frame shows elsewhere in the key frames\' pose that explains '
                             'it best); off: the registered pose as it is; on,off: both, row by row')
    parser.add_argument('--work', type=Path)
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix='bench_live_'))
    work.mkdir(parents=True, exist_ok=True)
    rows = [(n, a, s) for (n, a), s in itertools.product(subjects([o for o in args.only.split(',') if o]),
                                                        args.scenes.split(',')) if n != 'samba']
    print(f'iterations {args.iterations}, sweeps {args.sweeps}, registration lag {args.lag} frames\n')
    print('| subject_scene | scheme | limb poses | joints | points '
          '| live - offline, key frames / all: median, p95 (cm) '
          '| after the window: live - offline median, p95 (cm); tracking skill offline / live '
          '| held - offline: median, p95 (cm) | offline: artic. recall / mean (cm) '
          '| live: artic. recall / mean (cm) | moving recall: offline / live / held '
          '| tracking skill: offline / live / held | live frame coverage '
          '| frames a limb re-posed | lost (registered joints published) | fit ms median / p95 |')
    print('|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|')
    for (name, source_args, scene), scheme, limbs in itertools.product(rows, args.schemes.split(','),
                                                                       args.limb_poses.split(',')):
        try:
            row = live_row(simulated_bag(name, source_args, scene, args.frames, work), args.iterations, args.sweeps,
                           args.lag, scheme, limbs == 'on')
        except Exception as error:  # a row that fails is reported, the others still run
            print(f'| {name}_{scene} | {scheme} | {limbs} | failed: {type(error).__name__}: {error} ||||||||||||||')
            continue
        off, live, held = row['offline'], row['live'], row['held']
        after_skill = '-' if row['live_after'] is None else \
            f"{row['offline_after'].tracking_skill:.2f} / {row['live_after'].tracking_skill:.2f}"
        print(f"| {name}_{scene} | {scheme} | {limbs} | {row['joints']} | {row['points']} "
              f"| {row['gap_key_median_cm']:.1f} / {row['gap_median_cm']:.1f}, {row['gap_p95_cm']:.1f} "
              f"| {row['gap_after_median_cm']:.1f}, {row['gap_after_p95_cm']:.1f}; {after_skill} "
              f"| {row['hold_median_cm']:.1f}, "
              f"{row['hold_p95_cm']:.1f} | {off.articulated_recall:.2f} / "
              f"{100 * off.mean_error_m:.1f} | {live.articulated_recall:.2f} / {100 * live.mean_error_m:.1f} "
              f"| {off.moving_recall:.2f} / {live.moving_recall:.2f} / {held.moving_recall:.2f} "
              f"| {off.tracking_skill:.2f} / {live.tracking_skill:.2f} / {held.tracking_skill:.2f} "
              f"| {live.frame_coverage:.2f} | {row['reposed']} "
              f"| {row['lost']} / {row['frames']} | {row['ms_median']:.0f} / {row['ms_p95']:.0f} |", flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
