"""Score the live joints of a `skel-extract replay --realtime [--loop N]` against the bag's
ground truth, repeated for each pass of the loop.

    python bench/score_realtime.py BAG OUT [--from-pass K] [--bounce]

BAG: the simulated bag (its gt.npz); OUT: the replay's --out directory (its output.mcap).
The live joints, one PoseArray per camera frame, are read from skeleton/joints in
output.mcap, with the newest skeleton/description's joint names (skeleton.json has the
same frames, but `evaluate` matches stamps to the bag's ground truth, which covers the
first pass of a loop only). Printed: the evaluate scores over every frame with
joints and over the passes from K on (by default the first pass that starts after the
newest skeleton's first live joints: every frame of it is one the nodes could answer, and
a frame they leave unanswered is a miss), the distance of
every live joint to its nearest true joint (median, p95): meaningful where the scores
match no joint, the registration's error (registered.npz against the repeated ground
truth's material points, evaluate_registration), over all and from pass K on, and the joint
node's camera frames by the start their joints came from (its last /diagnostics: from the
registered pose, from the frame before with `live_chain`, the second fits left out for
time, with `live_limb_poses` the starts that had a limb re-posed, and the frames the live
fit had no time for, answered between two fitted ones).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message
from std_msgs.msg import String

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from skel_extract_ros.app.evaluation import (GroundTruth, PredictedSkeleton, evaluate_joints,  # noqa: E402
                                         evaluate_registration, load_registered, match_frames)
from skel_extract_ros.app.replay import looped_stamp  # noqa: E402


# the joint node's diagnostics keys that count its camera frames' fits (README.md, Diagnostics),
# and those a recording made before them lacks (the frames whose start had a limb re-posed, the
# frames answered between two fitted ones)
LIVE_FIT_KEYS = ('live_fitted', 'live_chained', 'live_chain_skipped')
LIVE_FIT_OPTIONAL = ('live_reposed', 'live_interpolated')


def read_recording(recording: Path) -> tuple:
    """One pass over a replay's output.mcap (hundreds of MB: read once): (the live joints,
    a PredictedSkeleton of every skeleton/joints message with the newest description's
    joint count, in stamp order; the joint node's last /diagnostics counts of its camera
    frames' fits, {key: int} for LIVE_FIT_KEYS and those of LIVE_FIT_OPTIONAL it has,
    cumulative over the recording, or None without such a status; the stamp (s) of the
    first camera frame answered live by a skeleton of that joint count, `live_start_stamp`)."""
    stamps, logged, positions, descriptions, fits = [], [], [], [], None
    with open(recording, 'rb') as stream:
        for _schema, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            if channel.topic.endswith('skeleton/description'):
                descriptions.append((message.log_time * 1e-9,
                                     json.loads(deserialize_message(message.data, String).data)))
            elif channel.topic.endswith('skeleton/joints'):
                msg = deserialize_message(message.data, PoseArray)
                stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
                logged.append(message.log_time * 1e-9)
                positions.append([[p.position.x, p.position.y, p.position.z] for p in msg.poses])
            elif channel.topic == '/diagnostics':
                for status in deserialize_message(message.data, DiagnosticArray).status:
                    values = {value.key: value.value for value in status.values}
                    if all(key in values for key in LIVE_FIT_KEYS):
                        fits = {key: int(values[key]) for key in LIVE_FIT_KEYS + LIVE_FIT_OPTIONAL
                                if key in values}
    if not descriptions:
        raise SystemExit(f'{recording}: no skeleton/description recorded')
    description = descriptions[-1][1]
    n_joints = len(description['joint_names'])
    keep = [i for i, p in enumerate(positions) if len(p) == n_joints]
    kept_stamps = np.array(stamps)[keep]
    learned_at = min(log_s for log_s, entry in descriptions if len(entry['joint_names']) == n_joints)
    order = np.argsort(kept_stamps, kind='stable')
    skeleton = PredictedSkeleton(description['joint_names'], description['parents'], kept_stamps[order],
                                 np.array([positions[i] for i in keep])[order])
    return skeleton, fits, live_start_stamp(kept_stamps, np.array(logged)[keep], learned_at)


def live_start_stamp(stamps: np.ndarray, logged: np.ndarray, learned_at: float) -> float:
    """The stamp (s) of the first camera frame a skeleton learned at log time `learned_at`
    (s) answers live, from its joints messages' stamps (J,) and log times (J,) s.

    When the skeleton is learned the node also publishes the joints of the frames it was
    learned on, stamped with those frames, seconds before the log time; from then on each
    camera frame is answered a latency after its stamp. That latency is the median over
    the joints logged since (the newer half at most), and the first live frame is the one
    the learning's log time, less it, reaches."""
    since = logged >= learned_at
    if not since.any():
        return float(stamps.min(initial=np.inf))
    lag = np.median((logged - stamps)[since][-max(1, since.sum() // 2):])
    return float(learned_at - lag)


def looped(gt: GroundTruth, until_s: float, bounce: bool = False) -> tuple:
    """(the ground truth repeated until `until_s`, one pass in s), stamps moved on by a pass
    each time as `replay --loop` moves them (with `bounce`, every odd pass backwards, its
    stamps mirrored: replay.looped_stamp)."""
    n = len(gt.stamps)
    pass_s = (gt.stamps[-1] - gt.stamps[0]) * n / (n - 1)
    mirror_s = gt.stamps[0] + gt.stamps[-1]
    passes = int(np.ceil((until_s - gt.stamps[0]) / pass_s)) + 1
    order = [slice(None, None, -1) if bounce and k % 2 else slice(None) for k in range(passes)]
    fields = {}
    for field in dataclasses.fields(gt):
        value = getattr(gt, field.name)
        if field.name == 'stamps':
            fields['stamps'] = np.concatenate([looped_stamp(value[order[k]], k, pass_s, mirror_s, bounce)
                                               for k in range(passes)])
        elif isinstance(value, np.ndarray) and value.ndim and len(value) == n and field.name != 'surface_bone_ids':
            fields[field.name] = np.concatenate([value[order[k]] for k in range(passes)])
    return dataclasses.replace(gt, **fields), pass_s


def first_full_pass(first_stamp: float, start_stamp: float, pass_s: float) -> int:
    """The index of the first pass of a loop that starts at or after `first_stamp` (s), the
    loop starting at `start_stamp` (s), each pass `pass_s` long."""
    # a hundredth of a pass: the stamps of a pass's first frame and of the joints answering
    # it are the same number written by two programs
    if not np.isfinite(first_stamp):
        return 0
    return max(0, int(np.ceil((first_stamp - start_stamp) / pass_s - 0.01)))


def score(bag: Path, out: Path, from_pass: int | None = None, bounce: bool = False) -> dict:
    """The live joints and registered frames of a replay in `out` against the bag's ground
    truth, repeated for each pass: {'all' / 'later': JointReport or None (every frame with
    joints / from pass `from_pass` on; None: the first pass that starts after the newest
    skeleton's first live joints, read_recording's), 'from_pass': that pass, 'nearest_cm':
    (median, p95) of each live joint's distance to its nearest true joint, 'registration':
    (frames, frames from the pass, mean cm, mean cm from the pass), 'live_fits':
    read_recording's counts or None}."""
    pred, fits, live_from = read_recording(out / 'output.mcap')
    gt, pass_s = looped(GroundTruth.load(bag / 'gt.npz'), float(pred.stamps.max()), bounce)
    if from_pass is None:
        from_pass = first_full_pass(live_from, float(gt.stamps[0]), pass_s)
    later = pred.stamps >= gt.stamps[0] + from_pass * pass_s
    result = {}
    for name, chosen in (('all', np.ones(len(pred.stamps), bool)), ('later', later)):
        part = dataclasses.replace(pred, stamps=pred.stamps[chosen], positions=pred.positions[chosen])
        # scored from the first live joints (or the pass) to the last: a camera frame without
        # joints in between is a miss
        start = gt.stamps[0] + from_pass * pass_s if name == 'later' else float(part.stamps.min(initial=np.inf))
        result[name] = ((len(part.stamps), evaluate_joints(part, gt, start_stamp=start,
                                                           end_stamp=float(pred.stamps.max())))
                        if chosen.any() else None)
    _, gt_index = match_frames(pred.stamps, gt.stamps)
    nearest = np.linalg.norm(pred.positions[:, :, None, :] - gt.joints[gt_index][:, None, :, :], axis=-1).min(axis=2)
    result['nearest_cm'] = (100 * float(np.median(nearest)), 100 * float(np.percentile(nearest, 95)))
    points, stamps, rest_points = load_registered(out / 'registered.npz')
    tracking = stamps >= gt.stamps[0] + from_pass * pass_s
    scores = evaluate_registration(points, stamps, gt, rest_points=rest_points)
    per_frame = np.asarray(scores['per_frame_error_m'])
    result['registration'] = (len(per_frame), int(tracking.sum()), 100 * scores['mean_error_m'],
                              100 * per_frame[-tracking.sum():].mean() if tracking.any() else float('nan'))
    result['live_fits'] = fits
    result['from_pass'] = from_pass
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('bag', type=Path)
    parser.add_argument('out', type=Path)
    parser.add_argument('--from-pass', type=int, default=None,
                        help="score from this pass of the loop on (default: the first that starts after the newest "
                             "skeleton's first live joints)")
    parser.add_argument('--bounce', action='store_true', help='the replay ran with --bounce')
    args = parser.parse_args(argv)
    result = score(args.bag, args.out, args.from_pass, args.bounce)
    from_pass = result['from_pass']
    for key, name in (('all', 'every frame with joints'), ('later', f'from pass {from_pass}')):
        if result[key] is None:
            print(f'{name}: no frame')
            continue
        frames, report = result[key]
        print(f'{name}: {frames} frames, {report.n_predicted} joints, {report.n_matched} matched, recall '
              f'{report.recall:.2f}, articulated recall {report.articulated_recall:.2f} of {report.n_articulated}, '
              f'precision {report.precision:.2f}, mean {100 * report.mean_error_m:.1f} cm')
    median, p95 = result['nearest_cm']
    print(f'distance of each live joint to its nearest true joint: median {median:.1f} cm, p95 {p95:.1f} cm')
    frames, later_frames, mean, later_mean = result['registration']
    print(f'registration: {frames} frames ({later_frames} from pass {from_pass}), mean '
          f'{mean:.1f} cm, from pass {from_pass} mean {later_mean:.1f} cm')
    fits = result['live_fits']
    if fits is not None:
        print(f"camera frames' joints: {fits['live_fitted']} from the registered pose, {fits['live_chained']} from "
              f"the frame before; second fits left out for time: {fits['live_chain_skipped']}; starts with a "
              f"limb re-posed: {fits.get('live_reposed', '-')}; frames the fit had no time for, interpolated: "
              f"{fits.get('live_interpolated', '-')}")
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
