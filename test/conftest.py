"""Shared fixtures: the bundled sample bag, its `skel-extract run` output, small simulated sequences."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skel_extract_ros.core.bone_rotations import depth_first
from skel_extract_ros.sim import NoiseModel, generate_sequence

from ros_domains import private_environment

REPO_ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = REPO_ROOT / 'bags' / 'sample_wave'
# real data the tests that need it read (and skip without): SKEL_SHARED_DATA, else the
# shared data directory beside the checkout
SHARED_DATA = Path(os.environ.get('SKEL_SHARED_DATA', REPO_ROOT.parent / 'shared' / 'data'))


@pytest.fixture(scope='session')
def sample_bag() -> Path:
    assert (SAMPLE_BAG / 'metadata.yaml').is_file(), 'the sample bag must be committed in bags/'
    return SAMPLE_BAG


CLI = shutil.which('skel-extract', path=str(Path(sys.executable).parent)) or 'skel-extract'


def run_cli(*args, timeout=900, env=None):
    return subprocess.run([CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout, env=env)


def run_cli_private_domain(offset, *args, timeout=900):
    """run_cli for commands that start ROS nodes (replay), on a ROS domain of their own
    (`offset` keeps two such tests of one process apart) so parallel runs never mix."""
    return run_cli(*args, timeout=timeout, env=private_environment(offset))


@pytest.fixture
def ros():
    """An in-process ROS graph on a private domain (test/ros_harness.py), closed after the test."""
    from ros_harness import Harness
    harness = Harness()
    yield harness
    harness.close()


@pytest.fixture
def held_alg2(monkeypatch):
    """The joint node's Alg. 2 waits until the test sets the returned threading.Event (it
    takes seconds for real; a test holding it knows what arrives meanwhile)."""
    import threading

    from skel_extract_ros.core.joints import JointEstimation
    from skel_extract_ros.nodes import joint_stages
    release = threading.Event()

    class HeldJointEstimation(JointEstimation):
        def fit(self, *args, **kwargs):
            assert release.wait(60.0), 'the test never released Alg. 2'
            return super().fit(*args, **kwargs)
    monkeypatch.setattr(joint_stages, 'JointEstimation', HeldJointEstimation)
    yield release
    release.set()          # a node still waiting ends with the test


def check_bvh_joints(bvh_positions, skeleton: dict) -> np.ndarray:
    """A BVH's joints read back (bvh_positions (F, J, 3) m, skeleton.json's joint order) are
    skeleton.json's (`skeleton`, its dict) up to what a BVH cannot hold: its bones keep their
    rest lengths, while the estimated joints' distances change by a few mm per bone from frame
    to frame, which adds up along a chain. So each joint's error is at most the change of the
    bones' lengths on its path from the root, plus 1 mm (a bone with several children is
    turned onto them as a whole; the file's rounding). Returns the error (F, J) m."""
    parents = np.asarray(skeleton['parents'])
    positions = np.array([f['positions'] for f in skeleton['frames']], dtype=np.float64)
    rest = np.array(skeleton['rest_positions'], dtype=np.float64)
    error = np.linalg.norm(np.asarray(bvh_positions) - positions, axis=2)
    on_path = np.zeros_like(error)      # (F, J): the bones' length changes from the root to j
    for j in depth_first(parents)[1:]:  # parents first: a parent's sum is complete before its children's
        parent = parents[j]
        on_path[:, j] = on_path[:, parent] + np.abs(np.linalg.norm(positions[:, j] - positions[:, parent], axis=1)
                                                    - np.linalg.norm(rest[j] - rest[parent]))
    assert (error <= on_path + 1e-3).all(), (error - on_path).max()
    assert np.median(error) < 3.5e-3, np.median(error)
    return error


def check_sample_scores(report: dict) -> None:
    """The sample bag's scores (`skel-extract evaluate --json`), by `run` and by `replay`
    alike: bounds close to what is measured (repeatable run to run), so a regression shows.

    Measured: 12 joints, 10 of 21 matched (recall 0.48, precision 0.83), 7 of the 9 joints
    that bend >= 25 deg (7 within 10 cm, 3 within 5), mean 0.063 m, motion skill 0.80, over
    59 frames (the subject is found at frame 1), every one with joints; of the 6 joints that
    travel >= 10 cm, 4 tracked better than held still, tracking skill 0.63; registration
    mean 0.014 m, coverage 0.45. With Step 2's noise measured after every merge
    (`evidence_noise: bones`): 10 joints, precision 1.00, the same bending joints and skill
    (bench/README.md); earlier figures in this docstring's git history.
    The bounds leave one joint of margin. The next issues improve these; their bounds then
    move with them.
    """
    joints, registration = report['joints'], report['registration']
    assert joints['n_frames'] == 59 and joints['nonfinite_fraction'] == 0.0, joints
    assert joints['n_matched'] >= 8 and joints['precision'] >= 0.8, joints
    assert joints['n_articulated'] == 9 and joints['articulated_recall'] >= 6 / 9, joints
    assert joints['mean_error_m'] < 0.075 and joints['normalized_error_m'] < 0.02, joints
    assert joints['motion_skill'] > 0.6, joints
    assert joints['frame_coverage'] == 1.0 and joints['n_repeated_frames'] == 0, joints
    assert joints['n_moving'] == 6 and joints['moving_recall'] >= 3 / 6 and joints['tracking_skill'] > 0.4, joints
    assert joints['articulated_recall_10cm'] >= 5 / 9, joints
    assert registration['n_frames'] == 59 and registration['nonfinite_fraction'] == 0.0, registration
    assert registration['mean_error_m'] < 0.025 and registration['coverage'] > 0.4, registration


@pytest.fixture(scope='session')
def sample_run(sample_bag, tmp_path_factory):
    """(completed process, output dir) of `skel-extract run` on the sample bag (run once)."""
    out = tmp_path_factory.mktemp('sample_run') / 'out'
    return run_cli('run', sample_bag, '--out', out), out


@pytest.fixture(scope='session')
def human_clean():
    """20 noise-free frames of the full body."""
    return generate_sequence('human', 20, noise=NoiseModel.none(), seed=3, progress=False)


@pytest.fixture(scope='session')
def human_noisy():
    return generate_sequence('human', 20, seed=3, progress=False)
