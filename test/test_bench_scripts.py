"""The benchmark scripts still run against the code they measure: each on one small
built-in subject and a few frames (their numbers are the benchmarks' business, in
bench/README.md; this catches a script the code moved under, as the growth window once
did to bench_skeleton.py), the skeleton bench with a parameter file too; the real-motion
bench's comparison of two runs adds up and its Steps 2-3 alone score as `run` does, and the
realtime bench's extra parameters merge over its window's."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED_DATA

REPO = Path(__file__).resolve().parents[1]


def _table_rows(script: str, *args) -> list:
    """The Markdown rows the script prints for the arm, as lists of cells."""
    done = subprocess.run([sys.executable, str(REPO / 'bench' / script), *args], capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return [[cell.strip() for cell in line.strip().strip('|').split('|')]
            for line in done.stdout.splitlines() if line.startswith('| arm |')]


def test_bench_skeleton_scores_steps_2_and_3():
    rows = _table_rows('bench_skeleton.py', '--frames', '24', '--subjects', 'arm', '--no-dem-bones', '--no-surface')
    assert [row[2] for row in rows] == ['step 2 (structure)', 'step 3 (Alg. 2)', '(registration, steps 0-1)']
    for row in rows[:2]:
        found, mean_error, recall = int(row[3]), float(row[4]), float(row[6])
        # the arm's two true joints are found, well within the arm's length
        assert found >= 2 and recall == 1.0 and mean_error < 0.1, row


def test_bench_skeleton_runs_with_a_parameter_file(tmp_path):
    # every cut is kept when a joint needs no evidence and no turn: the file's values reach Step 2
    params = tmp_path / 'params.yaml'
    params.write_text('accumulator_node:\n  ros__parameters:\n    motion_noise_factor: 0.0\n    min_turn_deg: 0.0\n')
    args = ('--frames', '24', '--subjects', 'arm', '--no-dem-bones', '--no-surface')
    default = _table_rows('bench_skeleton.py', *args)
    every_cut = _table_rows('bench_skeleton.py', *args, '--params', str(params))
    assert int(every_cut[0][3]) > int(default[0][3]), (every_cut[0], default[0])


def test_bench_registration_runs_the_registration_and_the_skeleton_tracker():
    rows = _table_rows('bench_registration.py', '--sequences', 'arm', '--frames', '36',
                       '--methods', 'ours,tracker,tracker_start,static')
    by_method = {row[2]: row for row in rows}
    assert set(by_method) == {'ours', 'tracker', 'tracker_start', 'static'}, rows
    mean = {method: float(row[3]) for method, row in by_method.items()}
    after_window = {method: float(row[7]) for method, row in by_method.items()}
    # all three follow the arm: far nearer the truth than the rest pose held still
    for method in ('ours', 'tracker', 'tracker_start'):
        assert mean[method] < 0.5 * mean['static'], mean
        assert after_window[method] < 0.5 * after_window['static'], after_window


def _bench_real_motion():
    """bench/bench_real_motion.py as a module (bench/ is not a package)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location('bench_real_motion', REPO / 'bench' / 'bench_real_motion.py')
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def _row(subject, scene, half, recall, skill, error_m, base_scene='empty'):
    return {'subject': subject, 'scene': scene, 'base_scene': base_scene, 'half': half, 'true_joints': 21,
            'articulated_recall': recall, 'tracking_skill': skill, 'mean_error_m': error_m}


def test_bench_real_motion_compares_each_half_and_seed_with_a_baseline():
    bench = _bench_real_motion()
    baseline = [_row('wave', 'empty', 'tuning', 0.5, 0.2, 0.08), _row('run', 'empty', 'tuning', 0.3, 0.0, 0.10),
                _row('wave', 'empty-seed1', 'tuning', 1.0, 0.4, 0.06), _row('cow', 'empty', 'check', 0.2, 0.0, 0.1),
                _row('samba', 'empty', 'check', None, None, None) | {'true_joints': 0}]
    rows = [_row('wave', 'empty', 'tuning', 1.0, 0.4, 0.06), _row('run', 'empty', 'tuning', 0.2, 0.1, 0.10),
            _row('wave', 'empty-seed1', 'tuning', 0.5, 0.2, 0.08), _row('cow', 'room', 'check', 0.9, 0.5, 0.05)]
    lines = bench.comparison_table(rows, baseline).splitlines()
    header = [cell.strip() for cell in lines[0].strip('|').split('|')]
    table = {(cells[0], cells[1]): dict(zip(header, cells))
             for cells in ([c.strip() for c in line.strip('|').split('|')] for line in lines[2:])}
    # seed 0 and seed 1 apart; the cow's room row has no baseline, the samba no joints: neither counts
    assert set(table) == {('tuning', 'seed0'), ('tuning', 'seed1')}, lines
    seed0 = table[('tuning', 'seed0')]
    assert seed0['rows'] == '2'
    assert seed0['artic. recall'] == '0.40 -> 0.60 (1 up, 1 down)'
    assert seed0['tracking skill'] == '0.10 -> 0.25 (2 up, 0 down)'
    assert seed0['joint mean (cm)'] == '9.0 -> 8.0 (0 up, 1 down)'
    assert table[('tuning', 'seed1')]['artic. recall'] == '1.00 -> 0.50 (0 up, 1 down)'


def _joint(name, found, nearest_m=None, answers=None):
    return {'ground_truth': name, 'articulated': True, 'found': found, 'nearest_m': nearest_m,
            'nearest_answers': answers}


def test_bench_real_motion_tells_a_joint_that_flips_by_structure_from_one_that_flips_by_placement():
    """Over three noise seeds: the elbow is missed once with a joint of its own 20 cm off
    (placement); the wrist once because its nearest joint answers the elbow (the skeleton
    has one joint for two: structure); the knee once with no joint within 30 cm
    (structure); the shoulder is found every time and the hip never (neither flips)."""
    bench = _bench_real_motion()
    always = [_joint('shoulder', True), _joint('hip', False, 0.5)]
    variants = [[_joint('elbow', False, 0.20), _joint('wrist', True), _joint('knee', True)],
                [_joint('elbow', True), _joint('wrist', False, 0.12, 'elbow'), _joint('knee', True)],
                [_joint('elbow', True), _joint('wrist', True), _joint('knee', False, 0.40)]]
    rows = [_row('wave', scene, 'tuning', 0.5, 0.2, 0.08) | {'threshold_m': 0.15, 'per_joint': always + joints}
            for scene, joints in zip(('empty', 'empty-seed1', 'empty-seed2'), variants)]
    assert bench.flipping_joints(rows) == (2, 1)
    line = bench.stability_table(rows).splitlines()[-1]
    assert line.startswith('| wave | empty | 3 | 0.50-0.50 |') and line.endswith('| 2 / 1 |'), line


def test_bench_realtime_applies_extra_parameters_over_the_window():
    sys.path.insert(0, str(REPO / 'bench'))
    from bench_realtime import merged_params
    window = {'accumulator_node': {'window_size': 10},
              'registration_node': {'rest_pose': {'choice_frames': 10}}}
    extra = {'accumulator_node': {'sliding': True, 'window_size': 20},
             'registration_node': {'rest_pose': {'mode': 'first'}},
             'joint_estimation_node': {'zeta': 10.0}}
    merged = merged_params(window, extra)
    assert merged['accumulator_node'] == {'window_size': 20, 'sliding': True}
    # a nested section keeps the window's keys it does not name
    assert merged['registration_node']['rest_pose'] == {'choice_frames': 10, 'mode': 'first'}
    assert merged['joint_estimation_node'] == extra['joint_estimation_node']
    # the window's own parameters are not changed in place
    assert window['accumulator_node'] == {'window_size': 10}


def test_bench_real_motion_relearns_steps_2_and_3_on_a_kept_registration(tmp_path):
    """`--relearn` scores what `run` scores on the same bag, to the digit, and runs Steps 2
    and 3 again with a parameter file on the registration it kept, unchanged."""
    if not (SHARED_DATA / 'mocap').is_dir():
        pytest.skip(f'no real motion data under {SHARED_DATA}')

    env = os.environ | {'SKEL_SHARED_DATA': str(SHARED_DATA)}

    def rows(*args) -> dict:
        out = tmp_path / f'rows{len(list(tmp_path.glob("rows*")))}.json'
        done = subprocess.run([sys.executable, str(REPO / 'bench' / 'bench_real_motion.py'), '--only',
                               'wave-left-hand', '--scenes', 'empty', '--frames', '30', '--work',
                               str(tmp_path / 'work'), '--json', str(out), *args],
                              capture_output=True, text=True, timeout=600, env=env)
        assert done.returncode == 0, done.stderr[-3000:]
        (row,) = json.loads(out.read_text())
        return row

    keys = ('n_predicted', 'articulated_recall', 'precision', 'tracking_skill', 'mean_error_m', 'reg_mean_m')
    run = rows()
    relearned = rows('--relearn')
    assert {k: relearned[k] for k in keys} == {k: run[k] for k in keys}
    kept = tmp_path / 'work' / 'registrations' / 'wave-left-hand_normal_empty.pkl'
    made = kept.stat().st_mtime_ns
    # every cut kept: no evidence and no turn asked of a joint
    params = tmp_path / 'params.yaml'
    params.write_text('accumulator_node:\n  ros__parameters:\n    motion_noise_factor: 0.0\n    min_turn_deg: 0.0\n')
    every_cut = rows('--relearn', '--params', str(params))
    assert every_cut['n_predicted'] > run['n_predicted']
    assert every_cut['reg_mean_m'] == run['reg_mean_m'] and kept.stat().st_mtime_ns == made


def test_score_realtime_counts_the_joint_nodes_camera_fits_from_its_last_diagnostics(tmp_path):
    """In the one pass over the recording that reads the live joints, the counts come from the
    last status that has them (the joint node's; the other nodes' statuses are passed over);
    a recording without one gives None."""
    sys.path.insert(0, str(REPO / 'bench'))
    from rosbags.rosbag2 import StoragePlugin, Writer
    from score_realtime import read_recording
    from skel_extract_ros.codecs.bag import typestore
    store = typestore()
    Array, Status, Pair = (store.types[f'diagnostic_msgs/msg/{name}'] for name in
                           ('DiagnosticArray', 'DiagnosticStatus', 'KeyValue'))
    Header, Time = store.types['std_msgs/msg/Header'], store.types['builtin_interfaces/msg/Time']
    Text, Poses, Pose = (store.types[name] for name in ('std_msgs/msg/String', 'geometry_msgs/msg/PoseArray',
                                                        'geometry_msgs/msg/Pose'))
    Point, Quaternion = store.types['geometry_msgs/msg/Point'], store.types['geometry_msgs/msg/Quaternion']

    def status(name, **values):
        return Status(level=0, name=name, message='tracking', hardware_id='',
                      values=[Pair(key=key, value=str(value)) for key, value in values.items()])

    def header(second):
        return Header(stamp=Time(sec=second, nanosec=0), frame_id='camera')

    def recording(path, statuses):
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        with writer:
            topics = {topic: writer.add_connection(topic, kind, typestore=store) for topic, kind in
                      (('/skeleton/description', 'std_msgs/msg/String'),
                       ('/skeleton/joints', 'geometry_msgs/msg/PoseArray'),
                       ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray'))}
            description = Text(data=json.dumps({'joint_names': ['joint_0', 'joint_1'], 'parents': [-1, 0]}))
            writer.write(topics['/skeleton/description'], 10**9,
                         store.serialize_cdr(description, 'std_msgs/msg/String'))
            for second, entry in enumerate(statuses, start=1):
                poses = Poses(header=header(second), poses=[
                    Pose(position=Point(x=0.1 * second, y=0.0, z=float(joint)),
                         orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)) for joint in range(2)])
                writer.write(topics['/skeleton/joints'], second * 10**9,
                             store.serialize_cdr(poses, 'geometry_msgs/msg/PoseArray'))
                message = Array(header=header(second), status=[entry])
                writer.write(topics['/diagnostics'], second * 10**9,
                             store.serialize_cdr(message, 'diagnostic_msgs/msg/DiagnosticArray'))
        return next(path.glob('*.mcap'))

    joint = '/joint_estimation_node'
    statuses = [status(joint, live_fitted=5, live_chained=0, live_chain_skipped=1),
                status('/accumulator_node', rate_in_hz=30.0),
                status(joint, live_fitted=12, live_chained=30, live_chain_skipped=7),
                status('/registration_node', rate_in_hz=1.0)]
    skeleton, fits, _ = read_recording(recording(tmp_path / 'both', statuses))
    assert fits == {'live_fitted': 12, 'live_chained': 30, 'live_chain_skipped': 7}
    np.testing.assert_allclose(skeleton.stamps, [1.0, 2.0, 3.0, 4.0])
    np.testing.assert_allclose(skeleton.positions[:, 1], [[0.1 * s, 0.0, 1.0] for s in range(1, 5)])
    assert read_recording(recording(tmp_path / 'none', statuses[1:2]))[1] is None


def test_score_realtime_scores_from_the_first_pass_the_live_joints_cover_whole():
    """The scored passes start at the first pass that begins at or after the first live
    joints, so a skeleton learned late in a pass leaves no unanswerable frame in them (and
    joints stamped with a pass's first frame start at that pass)."""
    sys.path.insert(0, str(REPO / 'bench'))
    from score_realtime import first_full_pass
    pass_s = 3.0
    assert first_full_pass(100.0, 100.0, pass_s) == 0
    assert first_full_pass(100.0 + 2 * pass_s, 100.0, pass_s) == 2          # the pass's first frame
    assert first_full_pass(100.0 + 2 * pass_s + 0.033, 100.0, pass_s) == 3
    assert first_full_pass(100.0 + 8.9, 100.0, pass_s) == 3
    assert first_full_pass(99.0, 100.0, pass_s) == 0


def test_score_realtime_finds_the_first_live_frame_past_the_windows_joints():
    """When a skeleton is learned the node publishes its window's joints at once, stamped
    with frames seconds old; the live joints then follow each frame a latency after its
    stamp. The first live frame is the learning's log time less that latency, not the
    oldest stamp published."""
    sys.path.insert(0, str(REPO / 'bench'))
    from score_realtime import live_start_stamp
    learned_at, latency = 110.0, 0.05
    window = np.arange(100.0, 102.0, 1 / 30)                   # the window's frames, published at 110.0
    live = np.arange(110.0 - latency, 120.0, 1 / 30)          # each answered `latency` after its stamp
    stamps = np.concatenate([window, live])
    logged = np.concatenate([np.full(len(window), learned_at), live + latency])
    assert live_start_stamp(stamps, logged, learned_at) == pytest.approx(110.0 - latency, abs=1e-6)
    # nothing logged since the learning: the oldest stamp
    assert live_start_stamp(window, np.full(len(window), 105.0), learned_at) == window[0]
