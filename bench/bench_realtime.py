"""The installed nodes driven like a camera on real motion in the room: the live targets of
the camera-rate issue (rate, latency, first skeleton) and the live joints' accuracy, end to end.

    python bench/bench_realtime.py [--only walk_normal,cow,human] [--loop 10] [--bounce]
                                   [--window 10] [--runs 1] [--work DIR] [--params FILE]

For each clip (default: the five of bench/README.md's node tables: walk_normal, run_normal,
cow, wave-both-hands_active, wave-left-hand_normal; `--only` picks among every clip of
$SKEL_SHARED_DATA as bench_real_motion.py does) 90 frames in the room, rendered as 320x240 depth
images at 30 Hz (`simulate --scene room --depth-image`, kept in --work); then `skel-extract
replay --realtime --loop N` as a user runs it, with the accumulator's `window_size` and the
rest pose's `choice_frames` set to `--window` (a 3 s bag played N times: a 60-frame window
would leave a short tracking time).
`human` in `--only` is the built-in human in the room as 1.2 MB clouds, 300 frames (10 s),
on the defaults (the 60-frame window), played `--loop` times.
`--params FILE` (a ROS 2 parameter YAML, e.g. the accumulator's `sliding: true`) is
applied on top: over the clips' window parameters, and alone for the human.

Printed per run: joints once tracking (Hz, of the camera's), latency cloud -> joints median
/ p95 (ms), the first skeleton (s after the first camera frame), the pass scored from (the
first that starts after the newest skeleton's first live joints: every frame of it a miss
unless answered), the frames registered from it on and the registration's error on them
(cm), each live joint's distance to its nearest true joint over every frame with joints
(median / p95, cm) and the live joints' articulated recall, moving recall and tracking
skill from that pass on, as bench/score_realtime.py scores them, and the joint node's
camera frames by the start of their joints (from the registered pose / from the frame
before, `live_chain`) with the second fits it left out for time, the starts that had a
limb re-posed (`live_limb_poses`) and the frames the live fit had no time for, answered
between two fitted ones (its last /diagnostics, counted over the whole replay).
The walker jumps back to the start of the walk at each pass; with `--bounce` every other
pass plays the bag backwards (`replay --bounce`) and the motion stays continuous. Nothing
else may run while it measures: every number is a time on a shared 2-core machine. The
nodes join the ROS domain of the environment: give the bench one of its own
(ROS_DOMAIN_ID, and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'bench'))

from bench_live import simulated_bag  # noqa: E402
from bench_real_motion import CLI, subjects  # noqa: E402
from score_realtime import LIVE_FIT_KEYS, LIVE_FIT_OPTIONAL, score  # noqa: E402
from skel_extract_ros.config import load_params_file  # noqa: E402

DEFAULT_CLIPS = ('walk_normal', 'run_normal', 'cow', 'wave-both-hands_active', 'wave-left-hand_normal')
LINES = {
    'first_s': re.compile(r'first skeleton ([\d.]+) s after the first camera frame'),
    'latency': re.compile(r'latency cloud -> joints median (\d+) ms, p95 (\d+) ms'),
    'tracking': re.compile(r'once tracking \(([\d.]+) s\): (\d+) of (\d+) camera frames got joints '
                           r'\(([\d.]+) Hz of ([\d.]+) Hz\)'),
}


def merged_params(base: dict, extra: dict) -> dict:
    """Parameters `extra` applied over `base` (both {node: {name: value}}, as
    config.load_params_file reads them): nested mappings merged key by key, any other value
    of `extra` replacing `base`'s."""
    merged = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merged_params(merged[key], value)
        else:
            merged[key] = value
    return merged


def _params_document(nodes: dict) -> str:
    """A ROS 2 parameter file's text for {node: {name: value}}."""
    return yaml.safe_dump({node: {'ros__parameters': params} for node, params in nodes.items()})


def replay_row(bag: Path, out: Path, loop: int, params: Path | None, bounce: bool = False) -> dict:
    """`replay --realtime --loop` on `bag` into `out` (replaced), its printed figures and the scores."""
    shutil.rmtree(out, ignore_errors=True)
    command = [CLI, 'replay', str(bag), '--out', str(out), '--realtime', '--loop', str(loop)] + \
        (['--bounce'] if bounce else [])
    if params is not None:
        command += ['--params', str(params)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f'replay {bag.name}: {done.stderr.strip().splitlines()[-1]}')
    found = {key: pattern.search(done.stdout) for key, pattern in LINES.items()}
    if found['tracking'] is None:
        raise RuntimeError(f'replay {bag.name}: no skeleton was tracked\n{done.stdout[-600:]}')
    scores = score(bag, out, bounce=bounce)
    return {'first_s': float(found['first_s'][1]),
            'latency_ms': (int(found['latency'][1]), int(found['latency'][2])),
            'joints_hz': float(found['tracking'][4]), 'camera_hz': float(found['tracking'][5]),
            'from_pass': scores['from_pass'], 'registered_later': scores['registration'][1],
            'registration_cm': scores['registration'][3],
            'nearest_cm': scores['nearest_cm'], 'live_fits': scores['live_fits'],
            'later': None if scores['later'] is None else scores['later'][1]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--only', default=','.join(DEFAULT_CLIPS),
                        help='clips (substrings of their names), human: the built-in human as clouds '
                             '(default: %(default)s)')
    parser.add_argument('--loop', type=int, default=10, help='passes over each bag')
    parser.add_argument('--bounce', action='store_true', help='every other pass backwards (replay --bounce)')
    parser.add_argument('--window', type=int, default=10, help="the accumulator's window_size for the clips")
    parser.add_argument('--runs', type=int, default=1, help='runs of each bag')
    parser.add_argument('--work', type=Path)
    parser.add_argument('--params', type=Path, default=None,
                        help='ROS 2 parameter YAML applied over the clips\' window parameters and to the human')
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix='bench_realtime_'))
    work.mkdir(parents=True, exist_ok=True)
    # read (and checked) before minutes of simulation, as the replay will read it
    extra = load_params_file(args.params) if args.params else {}
    window = work / f'window_{args.window}.yaml'
    # the rest pose chosen within the window too (choice_frames 60 by default: the window's)
    window_params = {'accumulator_node': {'window_size': args.window},
                     'registration_node': {'rest_pose': {'choice_frames': args.window}}}
    window.write_text(_params_document(merged_params(window_params, extra)))
    human_params = None
    if extra:
        human_params = work / 'human_params.yaml'
        human_params.write_text(_params_document(extra))
    clips = [name for name in args.only.split(',') if name and name != 'human']
    rows = [(name, source_args, window, False) for name, source_args in (subjects(clips) if clips else [])
            if name != 'samba']                                  # a mesh sequence: no joints to track
    if 'human' in args.only.split(','):
        rows.append(('human', ['--subject', 'human'], human_params, True))
    print(f'replay --realtime --loop {args.loop}{" --bounce" if args.bounce else ""}; clips: depth images, '
          f'window_size {args.window}{f"; parameters from {args.params}" if extra else ""}; work {work}\n')
    print('| bag | run | joints once tracking (Hz of camera) | latency median / p95 (ms) | first skeleton (s) '
          '| scored from pass | registered from it | registration error from it (cm) | live joint to nearest true '
          'joint: median / p95 (cm) | live joints from it: artic. recall / moving recall / tracking skill '
          '| camera frames from the registered pose / from the frame before / second fit left out / start with a '
          'limb re-posed / interpolated |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    for name, source_args, params, human in rows:
        for run in range(1, args.runs + 1):
            try:
                # the clips as depth images (90 frames), the human as clouds (300), kept in work
                bag = (simulated_bag(f'{name}_clouds', source_args, 'room', 300, work) if human else
                       simulated_bag(f'{name}_depth', [*source_args, '--depth-image'], 'room', 90, work))
                row = replay_row(bag, work / f'{bag.name}_out', args.loop, params, args.bounce)
            except Exception as error:  # a row that fails is reported, the others still run
                print(f'| {name} | {run} | failed: {type(error).__name__}: {error} |||||||||', flush=True)
                continue
            fits, later = row['live_fits'], row['later']
            counts = '-' if fits is None else ' / '.join(str(fits.get(key, '-'))
                                                         for key in LIVE_FIT_KEYS + LIVE_FIT_OPTIONAL)
            moving = '-' if later is None else \
                f'{later.articulated_recall:.2f} / {later.moving_recall:.2f} / {later.tracking_skill:.2f}'
            print(f"| {name} | {run} | {row['joints_hz']:.1f} of {row['camera_hz']:.1f} "
                  f"| {row['latency_ms'][0]} / {row['latency_ms'][1]} | {row['first_s']:.1f} "
                  f"| {row['from_pass']} of {args.loop} | {row['registered_later']} | {row['registration_cm']:.1f} "
                  f"| {row['nearest_cm'][0]:.1f} / {row['nearest_cm'][1]:.1f} | {moving} "
                  f"| {counts} |", flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
