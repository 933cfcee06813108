"""`skel-extract record`, the example consumer: skeleton/trajectory only, over DDS, on the
sample bag replayed through the three node processes with a skeleton that grows."""
import csv
import os
import signal
import subprocess

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from skel_extract_ros.codecs.bag import _raw_messages, topic_counts
from skel_extract_ros.config import DEFAULT_PARAMS_FILE

from conftest import CLI, run_cli
from ros_domains import private_environment


def _descriptions(mcap):
    """Every skeleton/description the replay recorded, in order."""
    import json

    from rclpy.serialization import deserialize_message
    from std_msgs.msg import String
    return [json.loads(deserialize_message(bytes(raw), String).data)
            for _t, raw in _raw_messages(mcap, '/skeleton/description')]


def _last_accumulator_report(mcap) -> dict:
    """The accumulator node's last /diagnostics values the replay recorded."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.serialization import deserialize_message
    values = {}
    for _t, raw in _raw_messages(mcap, '/diagnostics'):
        for status in deserialize_message(bytes(raw), DiagnosticArray).status:
            if status.name.endswith('/accumulator_node'):
                values = {kv.key: kv.value for kv in status.values}
    return values


def _rows(path):
    """{stamp ns: {joint: (position (3,), quaternion (4,))}} of demonstration.csv, in stamp order."""
    frames = {}
    with open(path, newline='') as stream:
        for row in csv.DictReader(stream):
            frames.setdefault(int(row['stamp_ns']), {})[row['joint']] = (
                np.array([float(row[k]) for k in 'xyz']), np.array([float(row[k]) for k in ('qx', 'qy', 'qz', 'qw')]))
    return dict(sorted(frames.items()))


def _at(frames, stamp_s):
    """The recorded frame at skeleton.json's float stamp (s; a float second of a 2020s epoch
    stamp keeps about a quarter of a microsecond)."""
    stamps = np.array(list(frames))
    nearest = stamps[np.argmin(np.abs(stamps - round(stamp_s * 1e9)))]
    assert abs(int(nearest) - stamp_s * 1e9) < 1e3, stamp_s
    return frames[int(nearest)]


@pytest.fixture(scope='module')
def recorded(sample_bag, tmp_path_factory):
    """(replay output dir, recorder output dir) of the sample bag replayed with sliding
    windows (30 frames, every 5 after: the skeleton grows several times, faster than Alg. 2
    describes it, so the joint node skips structures and each description's changes must
    span them) while `skel-extract record` listens on the same private domain."""
    tmp = tmp_path_factory.mktemp('record')
    params = yaml.safe_load(DEFAULT_PARAMS_FILE.read_text())
    # Step 2 as it was before its least turn: on this bag those settings make a growth
    # update that adds and removes joints, which is what the names are tested across
    params['accumulator_node']['ros__parameters'].update(window_size=30, sliding=True, stride=5,
                                                         motion_noise_factor=5.0, min_turn_deg=0.0)
    # the rest pose from the first cloud: every cloud is registered while the replay goes
    # on, so the skeleton grows during it (with the default choice among 60 clouds, the
    # sample bag's 59 are all held and registered after the last one, and its skeleton did
    # not change on growth)
    params['registration_node']['ros__parameters']['rest_pose']['choice_frames'] = 1
    (tmp / 'grow.yaml').write_text(yaml.safe_dump(params))
    env = private_environment(60, PYTHONUNBUFFERED='1')
    recorder = subprocess.Popen([CLI, 'record', '--out', tmp / 'demo'], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env=env)
    try:
        assert 'recording /skeleton/trajectory' in recorder.stdout.readline()
        done = subprocess.run([CLI, 'replay', sample_bag, '--out', tmp / 'out', '--rate', '0',
                               '--params', tmp / 'grow.yaml'], capture_output=True, text=True, env=env, timeout=900)
        assert done.returncode == 0, done.stderr[-2000:]
    finally:
        recorder.send_signal(signal.SIGINT)          # Ctrl-C: it writes its files and ends
        said = recorder.communicate(timeout=60)[0]
    assert recorder.returncode == 0 and 'wrote' in said, said
    return tmp / 'out', tmp / 'demo'


def test_record_names_stay_stable_across_growth_and_positions_equal_skeleton_json(recorded):
    import json
    out, demo = recorded
    frames = _rows(demo / 'demonstration.csv')
    # one frame per trajectory message the nodes sent, every registered frame
    counts = topic_counts(out / 'output.mcap')
    assert len(frames) == counts['/skeleton/trajectory'] == counts['/registered_points'] == 59, counts
    # the skeleton grew while recording: each frame's names are one description's, in
    # order, and from one description to the next a name changes only as its `changes` say
    descriptions = _descriptions(out / 'output.mcap')
    assert len(descriptions) >= 2, 'no growth update: the test needs one'
    assert [d['version'] for d in descriptions] == list(range(1, len(descriptions) + 1))
    sets = []
    for joints in frames.values():
        if not sets or sets[-1] != set(joints):
            sets.append(set(joints))
    described = [set(d['joint_names']) for d in descriptions]
    assert len(sets) >= 2 and all(s in described for s in sets), (sets, described)
    # lossless, as `run`: every window that came due was learned (windows of 30, every 5
    # after: 59 frames give 6), and the replay ended once the newest structure was described
    accumulator = _last_accumulator_report(out / 'output.mcap')
    assert int(accumulator['extractions']) + int(accumulator['failed']) == 6, accumulator
    structures = [raw for _t, raw in _raw_messages(out / 'output.mcap', '/skeleton/structure')]
    from rclpy.serialization import deserialize_message
    from std_msgs.msg import String
    newest = json.loads(deserialize_message(bytes(structures[-1]), String).data)
    assert set(descriptions[-1]['window_stamps_ns']) == set(newest['window_stamps_ns'])
    for before, after in zip(descriptions, descriptions[1:]):
        changes = after['changes']
        assert set(after['joint_names']) == (set(before['joint_names']) - set(changes['removed'])) | set(changes['added'])
        kept = set(before['joint_names']) & set(after['joint_names'])
        assert kept, 'a growth update that renamed every joint'
    # the positions are skeleton.json's, by name, on every frame it has
    skeleton = json.loads((out / 'skeleton.json').read_text())
    assert skeleton['frames']
    for frame in skeleton['frames']:
        joints = _at(frames, frame['stamp'])
        assert sorted(joints) == sorted(skeleton['joint_names'])
        np.testing.assert_allclose([joints[n][0] for n in skeleton['joint_names']], frame['positions'], atol=2e-6)


def test_record_rotations_are_skeleton_bvhs_and_its_bvh_replays_the_positions(recorded):
    """The recorded rotations give skeleton.bvh's angles (local = W_parent^T W_b, parents
    from the description), and demonstration.bvh, read back by bvhio, the recorded poses."""
    import json

    import bvhio
    out, demo = recorded
    frames = _rows(demo / 'demonstration.csv')
    skeleton = json.loads((out / 'skeleton.json').read_text())
    names, parents = skeleton['joint_names'], skeleton['parents']
    world = np.array([[Rotation.from_quat(_at(frames, f['stamp'])[n][1]).as_matrix() for n in names]
                      for f in skeleton['frames']])
    local = world.copy()
    for b, p in enumerate(parents):
        if p >= 0:
            local[:, b] = np.transpose(world[:, p], (0, 2, 1)) @ world[:, b]
    from skel_extract_ros.app.bvh_export import euler_channels
    expected = euler_channels(local)                                        # (F, J, 3) z x y degrees
    text = (out / 'skeleton.bvh').read_text().split('MOTION')
    order = [line.split()[1] for line in text[0].splitlines() if line.strip().split()[:1] in (['ROOT'], ['JOINT'])]
    values = np.array([[float(v) for v in line.split()] for line in text[1].strip().splitlines()[2:]])
    angles = values[:, 3:].reshape(len(values), len(order), 3)[:, [order.index(n) for n in names]]
    difference = (angles - expected + 180.0) % 360.0 - 180.0
    assert np.abs(difference).max() < 0.05, np.abs(difference).max()
    # demonstration.bvh: a flat hierarchy (no tree on the topic), every joint's pose
    hierarchy = bvhio.readAsHierarchy(str(demo / 'demonstration.bvh'))
    recorded_names = sorted({n for joints in frames.values() for n in joints})
    joints = {j.Name: j for j, _i, _d in hierarchy.layout()}
    assert sorted(set(joints) - {hierarchy.Name}) == recorded_names
    last = list(frames)[-1]
    hierarchy.loadPose(len(frames) - 1)
    for name, (position, quaternion) in frames[last].items():
        np.testing.assert_allclose(np.array(joints[name].PositionWorld), position, atol=1e-4)
        turned = np.array(joints[name].RotationWorld)   # glm quat: w, x, y, z
        angle = (Rotation.from_quat([*turned[1:], turned[0]]) * Rotation.from_quat(quaternion).inv()).magnitude()
        assert np.degrees(angle) < 0.01
