"""The `skel-extract` command line, run as a user runs it."""
import json

import numpy as np
import pytest

from conftest import check_sample_scores, run_cli as run


def test_simulate_info_evaluate(tmp_path):
    bag = tmp_path / 'fish_bag'
    done = run('simulate', '--subject', 'fish', '--frames', '12', '--out', bag, '--seed', '4',
               '--resolution', '640x480', '--scene', 'room')
    assert done.returncode == 0, done.stderr
    assert 'valid points per frame' in done.stdout
    assert 'simulate fish' in done.stderr  # progress
    assert (bag / 'gt.npz').is_file() and (bag / 'metadata.yaml').is_file()
    info = run('info', bag)
    assert info.returncode == 0 and '12 clouds' in info.stdout and '480x640' in info.stdout

    gt = np.load(bag / 'gt.npz')
    skeleton = {'frame_id': 'camera_depth_optical_frame', 'joint_names': [str(n) for n in gt['joint_names']],
                'parents': gt['joint_parents'].tolist(), 'rest_positions': gt['joints'][0].tolist(),
                'frames': [{'stamp': float(s), 'positions': p.tolist()} for s, p in zip(gt['stamps'], gt['joints'])]}
    (tmp_path / 'skeleton.json').write_text(json.dumps(skeleton))
    np.savez(tmp_path / 'registered.npz', points=gt['surface_points'][:, ::3], stamps=gt['stamps'])
    done = run('evaluate', '--pred', tmp_path / 'skeleton.json', '--gt', bag / 'gt.npz',
               '--registered', tmp_path / 'registered.npz', '--json')
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report['joints']['recall'] == 1.0 and report['joints']['mean_error_m'] < 1e-6
    assert report['registration']['mean_error_m'] < 1e-6


@pytest.mark.parametrize('args, message', [
    (['info', '/nonexistent/bag'], 'does not exist'),
    (['evaluate', '--gt', '/nonexistent/gt.npz', '--pred', 'x.json'], 'does not exist'),
    (['simulate', '--subject', 'hand', '--frames', '1', '--out', '/tmp/unused_skel_bag'], 'at least 2'),
    (['simulate', '--frames', '5', '--out', '/tmp/unused_skel_bag'], 'exactly one of'),
    (['simulate', '--subject', 'arm', '--bvh', 'x.bvh', '--out', '/tmp/unused_skel_bag'], 'exactly one of'),
    (['simulate', '--subject', 'arm', '--azimuth', '30', '--out', '/tmp/unused_skel_bag'], 'own camera'),
    (['simulate', '--bvh', '/nonexistent/clip.bvh', '--out', '/tmp/unused_skel_bag'], 'does not exist'),
])
def test_bad_input_is_one_clear_line(args, message):
    done = run(*args)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('skel-extract: error:') and message in lines[0]


def test_existing_output_is_not_overwritten(tmp_path):
    (tmp_path / 'exists').mkdir()
    done = run('simulate', '--subject', 'arm', '--frames', '3', '--out', tmp_path / 'exists')
    assert done.returncode == 2 and 'already exists' in done.stderr


def test_run_on_the_sample_bag_end_to_end(sample_run, sample_bag):
    """The whole pipeline on the bundled bag (real motion in a room, depth images), scored
    by the evaluation metric (see conftest.check_sample_scores for the measured values)."""
    done, out = sample_run
    assert done.returncode == 0, done.stderr
    assert 'ms/frame' in done.stdout and 'joints' in done.stdout
    # the bag carries its ground truth: run scores itself
    assert 'against the ground truth' in done.stdout and 'tracking skill' in done.stdout
    assert 'subject found in 59 of 60 frames' in done.stdout and 'removed as background' in done.stdout
    assert 'register' in done.stderr  # progress
    data = np.load(out / 'registered.npz')
    gt = np.load(sample_bag / 'gt.npz')
    assert data['points'].shape == (60, 2000, 3)
    np.testing.assert_allclose(data['stamps'], gt['stamps'])
    assert str(data['frame_id']) == 'camera_depth_optical_frame'
    # frame 0: nobody has moved yet, so no rest pose; from frame 1 on every frame is registered
    assert list(data['status']).count('ok') == 59 and data['status'][0] == 'empty'
    assert np.isfinite(data['points'][1:]).all() and np.isnan(data['points'][0]).all()
    assert (data['background_fraction'][1:] > 0.9).all() and (data['subject_points'][1:] > 2500).all()
    skeleton = json.loads((out / 'skeleton.json').read_text())
    assert skeleton['frame_id'] == 'camera_depth_optical_frame'
    n_joints = len(skeleton['joint_names'])
    assert len(skeleton['parents']) == n_joints == len(skeleton['rest_positions'])
    assert skeleton['parents'].count(-1) == 1
    assert len(skeleton['frames']) == 59
    assert skeleton['frames'][5]['stamp'] == pytest.approx(float(gt['stamps'][6]))
    assert np.isfinite([f['positions'] for f in skeleton['frames']]).all()
    assert (out / 'skeleton.png').stat().st_size > 10_000
    done = run('evaluate', '--gt', sample_bag / 'gt.npz', '--registered', out / 'registered.npz',
               '--pred', out / 'skeleton.json', '--json')
    check_sample_scores(json.loads(done.stdout))


def test_run_says_plainly_when_nothing_moves(tmp_path):
    """A still subject: nobody is found (nothing moved); with the segmentation off it is
    registered, but no bones can be separated. Each says so in one line."""
    from skel_extract_ros.codecs.bag import write_cloud_bag
    from skel_extract_ros.sim import generate_sequence
    seq = generate_sequence('fish', 1, seed=3, progress=False)
    bag = write_cloud_bag(tmp_path / 'still', [seq.clouds[0]] * 12,
                          1_700_000_000 * 10**9 + np.arange(12) * 33_333_333, 'camera_depth_optical_frame')
    done = run('run', bag, '--out', tmp_path / 'out')
    assert done.returncode == 2
    assert 'found in 0 of 12 frames' in done.stderr.strip().splitlines()[-1]
    params = tmp_path / 'p.yaml'
    params.write_text('registration_node:\n  ros__parameters:\n    segmentation:\n      enabled: false\n')
    done = run('run', bag, '--out', tmp_path / 'out2', '--params', params)
    assert done.returncode == 2
    assert 'too small to separate any bones' in done.stderr.strip().splitlines()[-1]
    assert (tmp_path / 'out2' / 'registered.npz').is_file()  # the registration is kept


def test_run_errors(tmp_path, sample_bag):
    done = run('run', tmp_path / 'missing', '--out', tmp_path / 'o')
    assert done.returncode == 2 and 'does not exist' in done.stderr
    done = run('run', sample_bag, '--out', tmp_path / 'o', '--frames', '3:4')
    assert done.returncode == 2 and 'at least 2' in done.stderr
    done = run('run', sample_bag, '--out', tmp_path / 'o', '--topic', '/nope')
    assert done.returncode == 2 and 'no PointCloud2 topic /nope' in done.stderr
    params = tmp_path / 'p.yaml'
    params.write_text('registration_node:\n  ros__parameters:\n    omgea: 0.1\n')
    done = run('run', sample_bag, '--out', tmp_path / 'o', '--params', params)
    assert done.returncode == 2 and 'omgea' in done.stderr
    assert all(len(d.strip().splitlines()) == 1 for d in [done.stderr])
