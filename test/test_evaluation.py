"""The evaluation metric is honest: perfect scores 0, noise and omissions show up."""
import json

import numpy as np
import pytest

from skel_extract_ros.app.evaluation import (EvaluationError, GroundTruth, PredictedSkeleton,
                                         evaluate_joints, evaluate_registration, match_frames)
from skel_extract_ros.sim import generate_sequence


def skeleton_json(path, stamps, positions, names=None, confidence=None):
    """A skeleton.json of positions (F, J, 3), with each frame's confidence (F, J) when
    given: a chain, joint 0 its root."""
    names = names or [f'joint_{i}' for i in range(positions.shape[1])]
    doc = {'frame_id': 'camera_depth_optical_frame', 'joint_names': names,
           'parents': [-1] + list(range(len(names) - 1)),
           'rest_positions': positions[0].tolist(),
           'frames': [{'stamp': float(s), 'positions': p.tolist()} for s, p in zip(stamps, positions)]}
    for frame, values in zip(doc['frames'], confidence if confidence is not None else []):
        frame['confidence'] = values.tolist()
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
    report = evaluate(tmp_path, gt, gt.joints, gt.stamps + 0.002)      # driver jitter
    assert report.n_frames == 30 and report.mean_error_m < 1e-6 and report.frame_coverage == 1.0
    with pytest.raises(EvaluationError, match='same stamp'):
        evaluate(tmp_path, gt, gt.joints, gt.stamps + 100.0)
    pred_idx, gt_idx = match_frames(np.array([0.0, 0.5, 1.0]), np.array([1.0, 0.0]), 0.1)
    assert list(pred_idx) == [0, 2] and list(gt_idx) == [1, 0]
    # scoring starts at the registration's start: the frames before it are not misses
    pred = PredictedSkeleton.load(skeleton_json(tmp_path / 'late.json', gt.stamps[5:], gt.joints[5:]))
    late = evaluate_joints(pred, gt, start_stamp=float(gt.stamps[5]))
    assert late.n_frames == 25 and late.n_frames_before_start == 5 and late.recall == 1.0


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


def test_registration_is_tied_to_the_surface_in_the_rest_poses_frame(gt_pair):
    """A rest pose built from frame 10, the frames before it registered backward from it:
    each point is the material point it was in frame 10. A mix-up in frame 0 is frame 0's
    error only; tied at frame 0 (no rest points given), every frame would pay for it."""
    gt = gt_pair[0]
    chosen = np.random.default_rng(2).choice(gt.surface_points.shape[1], 1500, replace=False)
    registered = gt.surface_points[:, chosen].copy()
    registered[0] = registered[0][np.random.default_rng(3).permutation(len(chosen))]   # mixed up
    result = evaluate_registration(registered, gt.stamps, gt, rest_points=registered[10] + 0.002)
    assert result['tied_at_frame'] == 10 and result['per_frame_error_m'][0] > 0.1
    assert max(result['per_frame_error_m'][1:]) < 1e-6
    tied_first = evaluate_registration(registered, gt.stamps, gt)
    assert tied_first['tied_at_frame'] == 0 and min(tied_first['per_frame_error_m'][1:]) > 0.1


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


# -- the loopholes an audit found, each closed ------------------------------------------
def test_articulated_recall_counts_only_joints_that_bend(tmp_path, gt_pair):
    gt = gt_pair[0]
    report = evaluate(tmp_path, gt, gt.joints)
    assert report.articulated_recall == 1.0 and report.n_articulated >= 10
    assert report.precision == 1.0 and report.motion_skill == pytest.approx(1.0)
    # predicting only the articulated joints: full articulated recall, partial recall
    spans = np.array([row['span_deg'] or 0.0 for row in report.per_joint])
    articulated = [g for g, row in enumerate(report.per_joint) if row['articulated']]
    only = evaluate(tmp_path, gt, gt.joints[:, [0] + articulated])   # a skeleton has a root
    assert only.articulated_recall == 1.0 and only.recall < 1.0
    # a joint held rigid is not counted: give one bone its parent's rotation in every frame
    import copy
    rigid = copy.copy(gt)
    rigid.bone_transforms = gt.bone_transforms.copy()
    bone = int(gt.joint_bones[articulated[0]])
    parent = int(gt.bone_parents[bone])
    rigid.bone_transforms[:, bone, :3, :3] = gt.bone_transforms[:, parent, :3, :3]
    held = evaluate(tmp_path, rigid, gt.joints)
    assert held.n_articulated == report.n_articulated - 1
    assert spans.max() > 25.0


def test_many_joints_do_not_buy_recall_without_precision(tmp_path, gt_pair):
    gt = gt_pair[0]
    rng = np.random.default_rng(2)
    points = gt.surface_points[:, rng.choice(gt.surface_points.shape[1], 2000, replace=False)]
    report = evaluate(tmp_path, gt, points)
    assert report.recall >= 0.9 and report.precision <= 0.01 and report.n_predicted == 2000
    hundred = evaluate(tmp_path, gt, points[:, :100])
    assert hundred.precision <= 0.15


def test_nan_predictions_count_as_misses(tmp_path, gt_pair):
    gt = gt_pair[0]
    gone = gt.joints.copy()
    gone[1:] = np.nan                          # joints after frame 0 missing
    report = evaluate(tmp_path, gt, gone)
    assert report.recall == 0.0 and report.nonfinite_fraction > 0.95
    tenth = gt.joints.copy()
    tenth[::10] = np.nan
    report = evaluate(tmp_path, gt, tenth)
    assert report.nonfinite_fraction == pytest.approx(0.1) and report.frame_coverage == pytest.approx(0.9)
    assert report.recall == 0.0, 'a joint missing in a tenth of the frames costs a tenth of the body'
    # the registration: NaN after its first frame is not a perfect score
    chosen = np.random.default_rng(1).choice(gt.surface_points.shape[1], 1500, replace=False)
    registered = gt.surface_points[:, chosen].copy()
    registered[1:] = np.nan
    result = evaluate_registration(registered, gt.stamps, gt)
    assert result['mean_error_m'] >= 0.9 * gt.subject_scale_m and result['nonfinite_fraction'] > 0.95
    # frames before the registration's start (waiting for the subject) are not scored
    late = gt.surface_points[:, chosen].copy()
    late[:5] = np.nan
    result = evaluate_registration(late, gt.stamps, gt)
    assert result['n_frames_before_start'] == 5 and result['mean_error_m'] < 1e-6


def test_a_collapsed_registration_scores_its_distance_from_the_body(gt_pair):
    gt = gt_pair[0]
    centroid = gt.surface_points[0].mean(axis=0)
    collapsed = np.repeat(centroid[None, None], 2000, axis=1).repeat(len(gt.stamps), axis=0)
    result = evaluate_registration(collapsed, gt.stamps, gt)
    # it was scored 4.8 cm before the tie was checked; now it pays its distance from the
    # surface, and covers nothing of the body
    assert result['mean_error_m'] >= 0.05 and result['coverage'] <= 0.01, result
    chosen = np.random.default_rng(1).choice(gt.surface_points.shape[1], 2000, replace=False)
    assert evaluate_registration(gt.surface_points[:, chosen], gt.stamps, gt)['coverage'] >= 0.7
    # the rest pose that never moves is bad too
    static = np.repeat(gt.surface_points[:1, chosen], len(gt.stamps), axis=0)
    assert evaluate_registration(static, gt.stamps, gt)['mean_error_m'] > 0.03


def test_a_static_skeleton_at_the_mean_has_no_motion_skill(tmp_path, gt_pair):
    gt = gt_pair[0]
    static = np.repeat(gt.joints.mean(axis=0, keepdims=True), len(gt.stamps), axis=0)
    report = evaluate(tmp_path, gt, static)
    assert report.motion_skill <= 0.05
    jittered = evaluate(tmp_path, gt, gt.joints + np.random.default_rng(0).normal(scale=0.01, size=gt.joints.shape))
    assert 0.05 < jittered.motion_skill < 1.0


def test_per_part_registration_names_the_lost_limb(gt_pair):
    gt = gt_pair[0]
    chosen = np.random.default_rng(1).choice(gt.surface_points.shape[1], 2000, replace=False)
    registered = gt.surface_points[:, chosen].copy()
    bones = gt.surface_bone_ids[chosen]
    lost = gt.bone_names.index('l_forearm')
    registered[10:, bones == lost] += np.array([0.0, 0.0, 0.3])      # the forearm lost from frame 10
    result = evaluate_registration(registered, gt.stamps, gt)
    worst = max(result['per_part'], key=lambda name: result['per_part'][name]['mean_error_m'])
    assert worst == 'l_forearm'
    assert result['per_part']['l_forearm']['worst_frame_error_m'] == pytest.approx(0.3, abs=0.01)
    assert result['per_part']['chest']['mean_error_m'] < 1e-6
    assert result['worst_frame_error_m'] > result['per_frame_error_m'][5]


def test_ground_truth_without_joints_scores_registration_only(tmp_path, gt_pair):
    gt = gt_pair[0]
    meshless = GroundTruth(gt.stamps, np.zeros((len(gt.stamps), 0, 3)), [], np.zeros(0), gt.surface_points, 1.8)
    with pytest.raises(EvaluationError, match='no joints'):
        evaluate(tmp_path, meshless, gt.joints)
    chosen = np.arange(0, gt.surface_points.shape[1], 3)
    assert evaluate_registration(gt.surface_points[:, chosen], gt.stamps, meshless)['mean_error_m'] < 1e-6


# -- the games of the joints issue: each gamed prediction fails ---------------------------
def test_leaving_frames_out_costs_more_than_a_wrong_answer(tmp_path, gt_pair):
    gt = gt_pair[0]
    every_other = evaluate(tmp_path, gt, gt.joints[::2], gt.stamps[::2])
    assert every_other.frame_coverage == pytest.approx(0.5) and every_other.recall == 0.0
    one = evaluate(tmp_path, gt, gt.joints[-1:], gt.stamps[-1:])
    assert one.recall == 0.0 and one.frame_coverage == pytest.approx(1 / 30)
    assert not one.tracking_skill > 0.0 and one.moving_recall == 0.0
    # frame 0 repeated 30 times under its stamp answers frame 0 only
    repeated = evaluate(tmp_path, gt, np.repeat(gt.joints[:1], 30, axis=0), np.repeat(gt.stamps[:1], 30))
    assert repeated.n_repeated_frames == 29 and repeated.frame_coverage == pytest.approx(1 / 30)
    assert repeated.recall == 0.0


def test_blanking_the_bad_frames_never_pays(tmp_path, gt_pair):
    gt = gt_pair[0]
    rng = np.random.default_rng(3)
    predicted = gt.joints + rng.normal(scale=0.03, size=gt.joints.shape)
    bad = np.zeros(len(gt.stamps), dtype=bool)
    bad[rng.choice(len(bad), 9, replace=False)] = True
    predicted[bad] += np.array([0.45, 0.0, 0.0])       # 30 % of the frames 45 cm off
    answered = evaluate(tmp_path, gt, predicted)
    blanked = predicted.copy()
    blanked[bad] = np.nan
    left_out = evaluate(tmp_path, gt, predicted[~bad], gt.stamps[~bad])
    blanked = evaluate(tmp_path, gt, blanked)
    # with a miss costing two thresholds the blanked frames made every joint match
    assert answered.recall == 0.0 and blanked.recall == 0.0 and left_out.recall == 0.0
    fixed = predicted.copy()
    fixed[bad] -= np.array([0.45, 0.0, 0.0])
    assert evaluate(tmp_path, gt, fixed).recall == 1.0


def test_a_static_skeleton_does_not_track(tmp_path, gt_pair):
    gt = gt_pair[0]
    truth = evaluate(tmp_path, gt, gt.joints)
    assert truth.tracking_skill == pytest.approx(1.0) and truth.moving_recall == 1.0
    assert truth.n_moving >= 6 and truth.frame_coverage == 1.0
    at_mean = np.repeat(gt.joints.mean(axis=0, keepdims=True), len(gt.stamps), axis=0)
    static = evaluate(tmp_path, gt, at_mean)
    assert static.recall >= 0.8, 'placement alone: the static skeleton is near every joint'
    assert static.tracking_skill <= 0.0 and static.moving_recall == 0.0
    assert set(static.missed_moving) == {row['ground_truth'] for row in static.per_joint if row['moving']}
    # a skeleton 5 cm off that follows the motion tracks; frozen at its own mean it keeps
    # its articulated recall but not its tracking
    offset = gt.joints + np.array([0.0, 0.05, 0.0])
    moving = evaluate(tmp_path, gt, offset)
    frozen = evaluate(tmp_path, gt, np.repeat(offset.mean(axis=0, keepdims=True), len(gt.stamps), axis=0))
    assert moving.tracking_skill > 0.5 and moving.moving_recall == 1.0
    assert frozen.articulated_recall >= 0.5 * moving.articulated_recall
    assert frozen.tracking_skill < 0.0 and frozen.moving_recall == 0.0


def test_per_joint_offset_along_the_limb_is_signed_towards_its_far_end(tmp_path, gt_pair):
    """A joint moved 4 cm down the bone it starts (a shoulder placed inside the upper arm),
    or past the end of the last one (a wrist moved into the hand), is +4 cm along its limb;
    moved back towards the body, -4 cm; moved across the limb, 0."""
    from skel_extract_ros.app.evaluation.joints import limb_directions
    gt = gt_pair[0]
    elbow, wrist = gt.joint_names.index('l_elbow'), gt.joint_names.index('l_wrist')
    limbs = limb_directions(gt.joints, gt.joint_parents)
    expected_elbow = gt.joints[:, wrist] - gt.joints[:, elbow]
    np.testing.assert_allclose(limbs[:, elbow], expected_elbow / np.linalg.norm(expected_elbow, axis=1, keepdims=True))
    assert np.all(np.isfinite(limbs[:, elbow]))
    for sign in (1.0, -1.0):
        report = evaluate(tmp_path, gt, gt.joints + sign * 0.04 * np.nan_to_num(limbs))
        rows = {row['ground_truth']: row for row in report.per_joint}
        for name in ('l_elbow', 'l_wrist'):
            assert rows[name]['offset_along_limb_m'] == pytest.approx(sign * 0.04, abs=1e-6)
    sideways = np.cross(np.nan_to_num(limbs), np.array([0.0, 0.0, 1.0]))
    sideways /= np.maximum(np.linalg.norm(sideways, axis=-1, keepdims=True), 1e-9)
    rows = {row['ground_truth']: row for row in evaluate(tmp_path, gt, gt.joints + 0.03 * sideways).per_joint}
    assert abs(rows['l_elbow']['offset_along_limb_m']) < 1e-6


def test_two_joints_mid_bone_match_at_15_cm_but_not_at_5(tmp_path, gt_pair):
    gt = gt_pair[0]
    elbow, wrist = gt.joint_names.index('l_elbow'), gt.joint_names.index('l_wrist')
    assert 0.15 < np.linalg.norm(gt.joints[0, elbow] - gt.joints[0, wrist]) < 0.30
    mid_bone = gt.joints.copy()
    mid_bone[:, [elbow, wrist]] = 0.5 * (gt.joints[:, [elbow]] + gt.joints[:, [wrist]])
    report = evaluate(tmp_path, gt, mid_bone)
    rows = {row['ground_truth']: row for row in report.per_joint}
    assert rows['l_elbow']['found'] and rows['l_wrist']['found']
    assert not rows['l_elbow']['found_5cm'] and not rows['l_wrist']['found_5cm']
    assert report.articulated_recall_5cm < report.articulated_recall == 1.0
    assert evaluate(tmp_path, gt, gt.joints).articulated_recall_5cm == 1.0


def test_per_joint_offsets_are_split_along_and_across_the_camera_ray(tmp_path, gt_pair):
    gt = gt_pair[0]
    rays = gt.joints.mean(axis=0)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    deeper = evaluate(tmp_path, gt, gt.joints + 0.04 * rays)
    sideways = np.cross(rays, np.array([0.0, 1.0, 0.0]))
    sideways /= np.linalg.norm(sideways, axis=1, keepdims=True)
    across = evaluate(tmp_path, gt, gt.joints + 0.03 * sideways)
    for row in deeper.per_joint:
        assert row['offset_along_ray_m'] == pytest.approx(0.04, abs=1e-6)
        assert row['offset_across_ray_m'] < 1e-6 and row['normalized_error_m'] < 1e-6
    for row in across.per_joint:
        assert abs(row['offset_along_ray_m']) < 1e-6
        assert row['offset_across_ray_m'] == pytest.approx(0.03, abs=1e-6)
    unmatched = evaluate(tmp_path, gt, gt.joints[:, :3])
    assert sum(row['found'] for row in unmatched.per_joint) == 3 and len(unmatched.per_joint) == 15


def test_a_joint_not_found_names_its_nearest_and_whether_it_answers_another(tmp_path, gt_pair):
    """A skeleton without the elbow: the true elbow's nearest predicted joint is one matched
    to another true joint (the skeleton has one joint where the truth has two). An elbow
    placed 25 cm off: its nearest is that joint, matched to nothing (placed too far)."""
    from skel_extract_ros.app.evaluation.report import score_lines
    gt = gt_pair[0]
    elbow = gt.joint_names.index('l_elbow')
    rays = gt.joints[:, elbow].mean(axis=0)
    without = evaluate(tmp_path, gt, np.delete(gt.joints, elbow, axis=1))
    row = {r['ground_truth']: r for r in without.per_joint}['l_elbow']
    assert not row['found'] and row['nearest_answers'] in gt.joint_names
    assert row['nearest_answers'] != 'l_elbow' and row['nearest_m'] > 0.15
    far = gt.joints.copy()
    far[:, elbow] += 0.25 * rays / np.linalg.norm(rays)           # 25 cm deeper along its ray
    report = evaluate(tmp_path, gt, far)
    row = {r['ground_truth']: r for r in report.per_joint}['l_elbow']
    assert not row['found'] and row['nearest_predicted'] == f'joint_{elbow}'
    assert row['nearest_m'] == pytest.approx(0.25, abs=1e-6) and row['nearest_answers'] is None
    found = {r['ground_truth']: r for r in report.per_joint}['l_wrist']
    assert found['found'] and found['nearest_answers'] == 'l_wrist'
    lines = score_lines({'joints': report.as_dict()}, per_joint=True)
    assert any('l_elbow <- not found (nearest joint_' in line and 'at 25.0 cm)' in line for line in lines)


def test_a_joint_within_the_threshold_is_not_given_up_for_a_cheaper_total(tmp_path, gt_pair):
    """One predicted joint 8 cm from the wrist, another 40 cm beyond it (away from the
    ankle): pairing the first with the ankle and the second with the wrist costs less in
    total than the right pairs, and both of those pairs lie beyond the threshold. The wrist
    is found; the other joint matches nothing."""
    gt = gt_pair[0]
    wrist, ankle = gt.joint_names.index('l_wrist'), gt.joint_names.index('r_ankle')
    a, b = gt.joints[:, wrist], gt.joints[:, ankle]
    away = (a - b) / np.linalg.norm(a - b, axis=1, keepdims=True)
    near = a + 0.08 * np.cross(away, np.array([0.0, 0.0, 1.0])) / np.linalg.norm(
        np.cross(away, np.array([0.0, 0.0, 1.0])), axis=1, keepdims=True)
    beyond = a + 0.40 * away
    d = lambda p, q: np.linalg.norm(p - q, axis=1).mean()
    assert d(near, b) + d(beyond, a) < d(near, a) + d(beyond, b), 'the bare assignment would swap them'
    report = evaluate(tmp_path, gt, np.stack([gt.joints[:, 0], near, beyond], axis=1))
    rows = {row['ground_truth']: row for row in report.per_joint}
    assert rows['l_wrist']['found'] and rows['l_wrist']['predicted'] == 'joint_1'
    assert rows['l_wrist']['error_m'] == pytest.approx(0.08, abs=1e-6)
    assert report.n_matched == 2 and not rows['r_ankle']['found']


def test_joints_at_parts_that_do_not_bend_lower_the_articulated_precision(tmp_path, gt_pair):
    """The true joints that bend, plus the ones that do not: precision stays 1 (every
    predicted joint is some true joint), the articulated precision falls to the bending
    share, which is what a skeleton cut through rigid parts looks like."""
    gt = gt_pair[0]
    everything = evaluate(tmp_path, gt, gt.joints)
    bending = [g for g, row in enumerate(everything.per_joint) if row['articulated']]
    assert 0 < len(bending) < len(gt.joint_names)
    assert everything.precision == 1.0
    assert everything.articulated_precision == pytest.approx(len(bending) / len(gt.joint_names))
    # the root is no bend: it lowers the articulated precision of the bending joints alone
    only = evaluate(tmp_path, gt, gt.joints[:, [0] + bending])
    assert only.articulated_precision == pytest.approx(len(bending) / (len(bending) + 1))
    assert only.articulated_recall == 1.0 and only.precision == 1.0


def test_a_root_beside_a_joint_does_not_find_it(tmp_path, gt_pair):
    """The method's root joint is its root bone's centre, not a place where the body bends:
    placed 8 cm from a shoulder (and far from every true root), it matches nothing, and the
    shoulder it lies beside stays unfound; the same point as a child joint finds it."""
    gt = gt_pair[0]
    shoulder = gt.joint_names.index('l_shoulder')
    roots = np.flatnonzero(np.asarray(gt.joint_parents) < 0)
    beside = gt.joints[:, shoulder] + np.array([0.0, 0.08, 0.0])
    assert np.linalg.norm(beside[:, None] - gt.joints[:, roots], axis=-1).mean(axis=0).min() > 0.15
    others = [g for g in range(len(gt.joint_names)) if g != shoulder]
    as_root = evaluate(tmp_path, gt, np.concatenate([beside[:, None], gt.joints[:, others]], axis=1))
    rows = {row['ground_truth']: row for row in as_root.per_joint}
    assert not rows['l_shoulder']['found'] and as_root.n_matched == len(others)
    assert as_root.precision == pytest.approx(len(others) / (len(others) + 1))
    as_child = evaluate(tmp_path, gt, np.concatenate([gt.joints[:, others[:1]], beside[:, None],
                                                       gt.joints[:, others[1:]]], axis=1))
    rows = {row['ground_truth']: row for row in as_child.per_joint}
    assert rows['l_shoulder']['found'] and as_child.n_matched == len(others) + 1


def test_the_confidence_is_scored_by_how_it_ranks_the_answers_beyond_the_threshold(tmp_path, gt_pair):
    gt = gt_pair[0]
    rng = np.random.default_rng(4)
    predicted = gt.joints + rng.normal(scale=0.01, size=gt.joints.shape)
    lost = np.zeros(gt.joints.shape[:2], dtype=bool)
    lost[rng.choice(len(gt.stamps), 6, replace=False), 5:9] = True
    predicted[lost] += np.array([0.0, 0.3, 0.0])       # 4 joints 30 cm off in 6 of 30 frames
    path = tmp_path / 'skeleton.json'

    def scored(confidence):
        return evaluate_joints(PredictedSkeleton.load(skeleton_json(path, gt.stamps, predicted,
                                                                    confidence=confidence)), gt)

    flagged = scored(np.where(lost, 0.2, 0.9))
    assert flagged.recall == 1.0 and flagged.n_far_answers == 24
    assert flagged.confidence_auc == 1.0
    assert scored(np.where(lost, 0.9, 0.2)).confidence_auc == 0.0
    assert scored(np.full(lost.shape, 0.7)).confidence_auc == 0.5
    # a confidence that only half the far answers have below the rest
    half = np.where(lost & (np.arange(lost.shape[1]) < 7), 0.2, 0.9)
    assert 0.5 < scored(half).confidence_auc < 1.0
    assert np.isnan(evaluate(tmp_path, gt, predicted).confidence_auc)      # no confidence published
