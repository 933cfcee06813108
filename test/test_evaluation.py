"""The evaluation metric is honest: perfect scores 0, noise and omissions show up."""
import json

import numpy as np
import pytest

from skel_extract_ros.evaluation import (EvaluationError, GroundTruth, PredictedSkeleton,
                                         evaluate_joints, evaluate_registration, match_frames)
from skel_extract_ros.sim import generate_sequence


def skeleton_json(path, stamps, positions, names=None):
    names = names or [f'joint_{i}' for i in range(positions.shape[1])]
    doc = {'frame_id': 'camera_depth_optical_frame', 'joint_names': names,
           'parents': [-1] + list(range(len(names) - 1)),
           'rest_positions': positions[0].tolist(),
           'frames': [{'stamp': float(s), 'positions': p.tolist()} for s, p in zip(stamps, positions)]}
    path.write_text(json.dumps(doc))
    return path


@pytest.fixture(scope='module')
def gt_pair(tmp_path_factory):
    root = tmp_path_factory.mktemp('gt')
    paths = []
    for seed in (5, 6):
        seq = generate_sequence('human', 30, seed=seed, progress=False)
        np.savez(root / f'gt{seed}.npz', **seq.ground_truth)
        paths.append(root / f'gt{seed}.npz')
    return [GroundTruth.load(p) for p in paths]


def evaluate(tmp_path, gt, positions, stamps=None):
    stamps = gt.stamps if stamps is None else stamps
    pred = PredictedSkeleton.load(skeleton_json(tmp_path / 'skeleton.json', stamps, positions))
    return evaluate_joints(pred, gt)


def test_ground_truth_scores_zero(tmp_path, gt_pair):
    gt = gt_pair[0]
    report = evaluate(tmp_path, gt, gt.joints)
    assert report.mean_error_m < 1e-6 and report.normalized_error_m < 1e-6
    assert report.recall == 1.0 and report.n_matched == gt.joints.shape[1]


def test_jitter_of_3cm_scores_about_5cm(tmp_path, gt_pair):
    gt = gt_pair[0]
    noisy = gt.joints + np.random.default_rng(0).normal(scale=0.03, size=gt.joints.shape)
    report = evaluate(tmp_path, gt, noisy)
    assert 0.04 <= report.mean_error_m <= 0.05
    assert report.recall == 1.0


def test_constant_offset_is_removed_by_normalisation(tmp_path, gt_pair):
    gt = gt_pair[0]
    report = evaluate(tmp_path, gt, gt.joints + np.array([0.05, 0.0, 0.0]))
    assert report.mean_error_m == pytest.approx(0.05, abs=1e-6)
    assert report.normalized_error_m < 1e-6


def test_half_the_joints_gives_half_recall(tmp_path, gt_pair):
    gt = gt_pair[0]
    half = gt.joints[:, ::2]
    report = evaluate(tmp_path, gt, half)
    assert report.recall == pytest.approx(half.shape[1] / gt.joints.shape[1])
    assert 0.45 <= report.recall <= 0.55


def test_duplicated_joints_do_not_raise_recall(tmp_path, gt_pair):
    gt = gt_pair[0]
    doubled = np.concatenate([gt.joints[:, :3]] * 5, axis=1)
    report = evaluate(tmp_path, gt, doubled)
    assert report.n_matched == 3


def test_another_sequence_scores_near_zero_recall(tmp_path, gt_pair):
    report = evaluate(tmp_path, gt_pair[0], gt_pair[1].joints)
    assert report.recall <= 0.2


def test_frames_are_matched_by_stamp(tmp_path, gt_pair):
    gt = gt_pair[0]
    # predicted only every other frame, stamps slightly off (driver jitter)
    report = evaluate(tmp_path, gt, gt.joints[::2], gt.stamps[::2] + 0.002)
    assert report.n_frames == 15 and report.mean_error_m < 1e-6
    with pytest.raises(EvaluationError, match='same stamp'):
        evaluate(tmp_path, gt, gt.joints, gt.stamps + 100.0)
    pred_idx, gt_idx = match_frames(np.array([0.0, 0.5, 1.0]), np.array([1.0, 0.0]), 0.1)
    assert list(pred_idx) == [0, 2] and list(gt_idx) == [1, 0]


def test_registration_metric(gt_pair):
    gt = gt_pair[0]
    rng = np.random.default_rng(1)
    chosen = rng.choice(gt.surface_points.shape[1], 1500, replace=False)
    perfect = gt.surface_points[:, chosen]
    result = evaluate_registration(perfect, gt.stamps, gt)
    assert result['mean_error_m'] < 1e-6 and result['tie_distance_m'] < 1e-6
    static = np.repeat(perfect[:1], len(gt.stamps), axis=0)
    result = evaluate_registration(static, gt.stamps, gt)
    assert result['mean_error_m'] > 0.03
    assert result['per_frame_error_m'][0] < 1e-6
    assert result['drift_m']['30'] > result['per_frame_error_m'][1]
    noisy = perfect + rng.normal(scale=0.01, size=perfect.shape)
    assert 0.01 < evaluate_registration(noisy, gt.stamps, gt)['mean_error_m'] < 0.025


def test_malformed_inputs_are_clear_errors(tmp_path):
    bad = tmp_path / 'bad.json'
    bad.write_text('{"joint_names": ["a"], "parents": [-1]}')
    with pytest.raises(EvaluationError, match='no "frames"'):
        PredictedSkeleton.load(bad)
    bad.write_text('{"joint_names": ["a"], "parents": [-1], "frames": [{"stamp": 1, "positions": [[1, 2]]}]}')
    with pytest.raises(EvaluationError, match='1 x 3'):
        PredictedSkeleton.load(bad)
    bad.write_text('not json')
    with pytest.raises(EvaluationError, match='not valid JSON'):
        PredictedSkeleton.load(bad)
    with pytest.raises(EvaluationError, match='does not exist'):
        GroundTruth.load(tmp_path / 'nope.npz')
    np.savez(tmp_path / 'gt.npz', stamps=np.zeros(2))
    with pytest.raises(EvaluationError, match='lacks joints'):
        GroundTruth.load(tmp_path / 'gt.npz')
