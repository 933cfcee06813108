"""`skel-extract replay`: the three node processes over real DDS, on the sample bag and
driven like a camera at 30 Hz."""
import json
import re

import numpy as np
import pytest

from skel_extract_ros.codecs.bag import topic_counts

from conftest import SHARED_DATA, check_bvh_joints, check_sample_scores, run_cli, run_cli_private_domain


def test_replay_sample_bag_records_every_topic_and_matches_run(tmp_path, sample_bag, sample_run):
    done = run_cli_private_domain(50, 'replay', sample_bag, '--out', tmp_path / 'out', '--rate', '0')
    out = tmp_path / 'out'
    assert done.returncode == 0, done.stderr[-2000:]
    assert 'latency registration' in done.stdout
    # every output topic recorded, one message per input frame where one is due
    # one self-contained MCAP file, as Foxglove and `ros2 bag play` open it
    assert (out / 'output.mcap').is_file() and not (out / '.recording').exists()
    counts = topic_counts(out / 'output.mcap')
    # every depth image gives a filtered cloud (empty while nobody has moved); frames from
    # the rest pose on (frame 1) are registered and get joints
    assert counts['/filtered_points'] == 60, counts
    for topic in ('/registered_points', '/skeleton/joints', '/skeleton/markers'):
        assert counts[topic] == 59, counts
    for topic in ('/rest_points', '/skeleton/structure', '/skeleton/description'):
        assert counts[topic] >= 1, counts
    assert counts['/diagnostics'] >= 3, counts      # each node reports once a second
    # the nodes shut down cleanly on SIGINT
    for name in ('registration_node', 'accumulator_node', 'joint_estimation_node'):
        assert 'Traceback' not in (out / 'logs' / f'{name}.log').read_text()
    # the same skeleton as `skel-extract run` (same frames, same deterministic steps)
    run_done, run_out = sample_run
    assert run_done.returncode == 0, run_done.stderr
    replayed = json.loads((out / 'skeleton.json').read_text())
    offline = json.loads((run_out / 'skeleton.json').read_text())
    assert replayed['parents'] == offline['parents']
    assert [f['stamp'] for f in replayed['frames']] == [f['stamp'] for f in offline['frames']]
    np.testing.assert_allclose([f['positions'] for f in replayed['frames']],
                               [f['positions'] for f in offline['frames']], atol=1e-3)
    # and every frame's per-joint confidence (skeleton/confidence, core/confidence.py)
    confidence = np.array([f['confidence'] for f in offline['frames']])
    assert confidence.shape == (59, len(offline['joint_names'])) and 0.0 <= confidence.min() <= confidence.max() <= 1.0
    np.testing.assert_allclose([f['confidence'] for f in replayed['frames']], confidence, atol=5e-3)
    # and each joint's pivot evidence (skeleton/description's pivot, core.joint_centres)
    assert replayed['pivot']['fixed'] == offline['pivot']['fixed']
    assert sum(bool(f) for f in offline['pivot']['fixed']) >= 1
    np.testing.assert_allclose([r or 0.0 for r in replayed['pivot']['residual_m']],
                               [r or 0.0 for r in offline['pivot']['residual_m']], atol=1e-4)
    # run keeps every input frame (frame 0, before the rest pose, NaN); the nodes publish
    # only registered frames
    offline_points = np.load(run_out / 'registered.npz')
    np.testing.assert_allclose(np.load(out / 'registered.npz')['points'],
                               offline_points['points'][offline_points['status'] == 'ok'], atol=1e-4)
    # scored like `run`
    done = run_cli('evaluate', '--gt', sample_bag / 'gt.npz', '--pred', out / 'skeleton.json',
                   '--registered', out / 'registered.npz', '--json')
    check_sample_scores(json.loads(done.stdout))
    assert (out / 'skeleton.png').stat().st_size > 10_000
    # skeleton.bvh beside it, written as `run` writes it (test_bvh_export.py), read back by
    # the simulator's BVH loader (bvhio): the same joints, as run's, up to the bones' length
    # changes a BVH cannot hold
    from skel_extract_ros.sim.bvh import load_bvh
    clip = load_bvh(out / 'skeleton.bvh')
    order = [clip.joint_names.index(name) for name in replayed['joint_names']]
    check_bvh_joints(clip.positions[:, order], replayed)


def test_live_at_camera_rate_on_a_room_bag(tmp_path):
    """The installed nodes on defaults, a 30 Hz best-effort depth camera (a 3 s room bag of
    depth images played 15 times over, every other pass backwards, the stamps moving on), a
    short learning window so that most of the 45 s is tracking: joints come, for the frames
    the segmentation passes on, at a rate a person-following robot can use. Depth images,
    as a live camera is best run (input:=depth_image: 150 kB a frame against a 1.2 MB
    cloud)."""
    bag = tmp_path / 'arm_room'
    run_cli('simulate', '--subject', 'arm', '--frames', '90', '--scene', 'room', '--depth-image', '--out', bag)
    params = tmp_path / 'window.yaml'
    params.write_text('accumulator_node:\n  ros__parameters:\n    window_size: 10\n')
    done = run_cli_private_domain(51, 'replay', bag, '--out', tmp_path / 'out', '--realtime', '--loop', '15',
                                  '--bounce', '--params', params)
    assert done.returncode == 0, done.stderr[-2000:]
    tracking = re.search(r'once tracking \(([\d.]+) s\): (\d+) of (\d+) camera frames got joints '
                         r'\(([\d.]+) Hz of ([\d.]+) Hz\), (\d+) passed the segmentation', done.stdout)
    assert tracking, done.stdout
    seconds, with_joints, _published, joints_hz, camera_hz, _filtered = map(float, tracking.groups())
    # tracking counts from the first skeleton/description: learning (rest pose, 10 frames
    # registered in order, Alg. 1 and 2) took 13-18 s on this machine with one or both cores
    # kept busy by another process; a fresh-clone CI run was slower still
    assert seconds > 10.0 and abs(camera_hz - 30.0) < 1.5
    # the first skeleton's time, from the first camera frame: learning, then tracking to the
    # last of the 1 350 frames (45 s at 30 Hz)
    first = re.search(r'first skeleton ([\d.]+) s after the first camera frame', done.stdout)
    assert first and float(first[1]) > 1.0, done.stdout
    assert abs(float(first[1]) + seconds - 1349 / 30) < 1.5, done.stdout     # 2.4 + 42.6 s measured
    # joints for a third of the camera frames at least, two orders of magnitude above the
    # registration's rate once tracking (well under 1 Hz): the live path does not wait for it.
    # 29.0 Hz of 30 with one core kept busy by another process, 24.2 Hz with both (6-10
    # joints: the window is whichever 10 frames the camera stage passed on); the issue's
    # 5.6 Hz before the live fit. The share of segmented frames that get joints is not
    # asserted: the live fit keeps only the newest frame when it falls behind, and that
    # share moves with the load
    assert joints_hz >= 10.0 and with_joints > 0, done.stdout
    # skeleton.json holds what a camera user got: every answered frame, the live ones too
    # (not only the ~1 Hz registered frames), in stamp order
    frames = json.loads((tmp_path / 'out' / 'skeleton.json').read_text())['frames']
    registered = np.load(tmp_path / 'out' / 'registered.npz')['stamps']
    stamps = [frame['stamp'] for frame in frames]
    assert len(frames) >= with_joints > 2 * len(registered) and stamps == sorted(set(stamps))
    registration_log = (tmp_path / 'out' / 'logs' / 'registration_node.log').read_text()
    assert 'the skeleton is learned: registration runs at nice' in registration_log
    # --bounce: every other pass backwards, the stamps moving on all the same (never a new
    # rest pose for stamps going back)
    assert 'stamps went back' not in registration_log and registration_log.count('rest pose built') == 1
    for name in ('registration_node', 'accumulator_node', 'joint_estimation_node'):
        assert 'Traceback' not in (tmp_path / 'out' / 'logs' / f'{name}.log').read_text()


def test_replay_bad_input_is_one_line(tmp_path, sample_bag):
    done = run_cli('replay', tmp_path / 'missing', '--out', tmp_path / 'o')
    assert done.returncode == 2 and done.stderr.count('\n') == 1 and 'does not exist' in done.stderr
    done = run_cli('replay', sample_bag, '--out', tmp_path / 'o', '--loop', '3')
    assert done.returncode == 2 and done.stderr.count('\n') == 1 and 'needs --realtime' in done.stderr


def test_looped_stamps_move_on_by_a_period_across_passes_and_bounce_mirrors():
    """replay --loop: each pass moved on by the bag's length and one period; with --bounce
    the odd passes run backwards, the stamps still one period apart across every seam."""
    from skel_extract_ros.app.replay import looped_stamp
    period = 33_333_333
    bag = 1_700_000_000_000_000_000 + period * np.arange(4)
    pass_ns, mirror_ns = 4 * period, int(bag[0] + bag[-1])
    for bounce in (False, True):
        passes = [bag[::-1] if bounce and k % 2 else bag for k in range(4)]
        stamps = np.concatenate([[looped_stamp(int(s), k, pass_ns, mirror_ns, bounce) for s in frames]
                                 for k, frames in enumerate(passes)])
        assert np.all(np.diff(stamps) == period), (bounce, np.diff(stamps))
    # the order of the content: forward, then the last frame again first, backwards
    assert looped_stamp(int(bag[-1]), 1, pass_ns, mirror_ns, True) == bag[-1] + period
    assert looped_stamp(int(bag[0]), 1, pass_ns, mirror_ns, False) == bag[-1] + period


def test_realtime_replay_waits_for_the_first_skeletons_frames_not_a_grown_ones_key_frames():
    """replay --realtime with a growing skeleton (sliding): the newest structure's key frames
    include camera frames the live fit skipped, which the joint node does not answer again;
    the replay waits for the frames of the first description (all answered), not for those,
    so it ends instead of waiting out its budget and failing. Lossless, every registered
    frame still counts."""
    from skel_extract_ros.app.replay import answered
    from skel_extract_ros.app.replay.recording import Received
    received = Received()
    received.registered = {stamp: None for stamp in range(1, 9)}
    received.structures = [{'window_stamps_ns': [1, 2, 3]}, {'window_stamps_ns': [1, 3, 5, 7]}]
    received.structure = received.structures[-1]
    assert not answered(received, realtime=True)            # no description yet
    received.descriptions = [{'window_stamps_ns': [1, 2, 3]}, {'window_stamps_ns': [1, 3, 5, 7]}]
    received.description = received.descriptions[-1]
    received.joints = {stamp: None for stamp in (1, 2, 3, 4, 6, 8)}     # 5 and 7 were skipped live
    assert answered(received, realtime=True)
    assert not answered(received, realtime=False)           # lossless: 5 and 7 are missing
    del received.joints[2]                                  # a frame of the first window without joints
    assert not answered(received, realtime=True)


def test_lossless_live_latency_counts_the_frames_registered_once_the_skeleton_existed():
    """Lossless replay's joint latency (registered -> joints) is timed over the frames
    registered after the first description came. The first window's frames and those
    registered while Steps 2-3 ran wait seconds for the skeleton, and a grown skeleton's
    window (sliding) does not mark them: timed, they would be the worst live latency."""
    from skel_extract_ros.app.replay.summary import _latencies
    from skel_extract_ros.app.replay.recording import Received
    received = Received()
    received.published_at = {stamp: float(stamp) for stamp in range(1, 9)}
    received.registered_at = {stamp: stamp + 0.05 for stamp in range(1, 9)}
    # frames 1-4 registered before the skeleton (at 5.0); 5-8 answered 20 ms after registration
    received.description_at = 5.0
    received.joints_at = {stamp: (6.0 if stamp < 5 else stamp + 0.07) for stamp in range(1, 9)}
    received.structures = [{'window_stamps_ns': [1, 2]}, {'window_stamps_ns': [5, 6, 7, 8]}]
    received.structure = received.structures[-1]
    latency = _latencies(received, realtime=False)
    assert latency['live_joints_ms']['n'] == 4
    assert latency['live_joints_ms']['worst'] == pytest.approx(20.0)
    assert latency['registration_ms']['n'] == 8
    assert 'live_joints_ms' not in _latencies(received, realtime=True)
    received.description_at = None                          # no skeleton: nothing live
    assert 'live_joints_ms' not in _latencies(received, realtime=False)


def test_replays_skeleton_json_marks_the_frames_the_nodes_interpolated(tmp_path):
    """The confidence message's `interpolated` flag, as the recorder receives it, reaches the
    replay's skeleton.json: the frame the live fit had no time for says so, the fitted
    frames carry no mark."""
    import threading

    from rclpy.serialization import deserialize_message, serialize_message
    from std_msgs.msg import String
    from skel_extract_ros.app.replay.recording import Received, _Recorder
    from skel_extract_ros.app.replay.summary import _write_files
    from two_bone import two_bone_sequence
    rest, registered, labels, _, joints = two_bone_sequence(n_frames=3)
    names, stamps = ['joint_0', 'joint_1'], [10, 20, 30]
    received = Received(rest=rest, frame_id='camera')
    recorder = object.__new__(_Recorder)        # its message handler, without a ROS node
    recorder.received, recorder.condition = received, threading.Condition()
    recorder.writer = type('Writer', (), {'write': lambda *args: None})()
    recorder.connections, recorder._deserialize = {'skeleton/confidence': None}, deserialize_message
    for stamp, flag in zip(stamps, (False, True, False)):
        document = {'stamp_ns': stamp, 'frame_id': 'camera', 'version': 1, 'joint_names': names,
                    'confidence': [0.9, 0.8], 'interpolated': flag}
        recorder._on_message('skeleton/confidence', 'std_msgs/msg/String',
                             serialize_message(String(data=json.dumps(document))))
    assert received.interpolated == {20}
    received.joints = {stamp: np.stack([joints[k], joints[k] + 0.3]) for k, stamp in enumerate(stamps)}
    received.registered = {10: registered[0], 30: registered[2]}
    window = {'window_stamps_ns': [10, 30]}
    received.descriptions = [{**window, 'joint_names': names, 'parents': [-1, 0], 'frame_id': 'camera',
                              'rest_positions': [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]]}]
    received.structures = [{**window, 'labels': labels.tolist()}]
    received.description, received.structure = received.descriptions[0], received.structures[0]
    _write_files(received, tmp_path)
    frames = json.loads((tmp_path / 'skeleton.json').read_text())['frames']
    assert [frame.get('interpolated') for frame in frames] == [None, True, None]
    assert [frame['confidence'] for frame in frames] == [[0.9, 0.8]] * 3


def test_bounce_refuses_a_bag_larger_than_half_the_available_memory(sample_bag, monkeypatch):
    """--bounce holds the bag's messages; one that would not fit says so before any node starts."""
    from skel_extract_ros.app import replay as replay_module
    from skel_extract_ros.codecs.bag import select_cloud_topic
    topic = select_cloud_topic(sample_bag, None)
    assert len(replay_module._held_messages(sample_bag, topic)) == 60
    monkeypatch.setattr(replay_module, '_available_memory_bytes', lambda: 2_000_000)
    with pytest.raises(replay_module.ReplayError, match='--bounce holds the bag in memory'):
        replay_module._held_messages(sample_bag, topic)


def test_lossless_replay_of_a_real_clip_longer_than_the_window_gives_runs_skeleton(tmp_path):
    """90 frames of real motion (a left-hand wave): the nodes learn on the first window (60
    registered frames) and fit the learned skeleton to the frames after it; `run` follows
    the same growth schedule, so the two give the same joints (measured: identical to the
    micrometre the files keep; before, run learned on all 89 frames)."""
    clip = SHARED_DATA / 'mocap' / 'dataset-2_wave-left-hand_normal_001.bvh'
    if not clip.is_file():
        pytest.skip(f'real motion data absent ({clip})')
    bag = tmp_path / 'bag'
    done = run_cli('simulate', '--bvh', clip, '--frames', 90, '--out', bag)
    assert done.returncode == 0, done.stderr[-2000:]
    ran = run_cli('run', bag, '--out', tmp_path / 'run')
    assert ran.returncode == 0, ran.stderr[-2000:]
    replayed = run_cli_private_domain(53, 'replay', bag, '--out', tmp_path / 'replay', '--rate', '0')
    assert replayed.returncode == 0, replayed.stderr[-2000:]
    offline = json.loads((tmp_path / 'run' / 'skeleton.json').read_text())
    nodes = json.loads((tmp_path / 'replay' / 'skeleton.json').read_text())
    assert offline['joint_names'] == nodes['joint_names'] and offline['parents'] == nodes['parents']
    assert [f['stamp'] for f in offline['frames']] == [f['stamp'] for f in nodes['frames']]
    assert len(offline['frames']) > 60, 'the clip must outlast the learning window'
    np.testing.assert_allclose([f['positions'] for f in offline['frames']],
                               [f['positions'] for f in nodes['frames']], atol=1e-3)
