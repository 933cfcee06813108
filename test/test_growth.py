"""The growing skeleton (core.growth): windows that each show one joint end in one model."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skel_extract_ros.core.growth import GrowthSchedule, SkeletonGrowth, aligned_poses, farthest_poses
from skel_extract_ros.core.structure import StructureError, StructureParams

LEFT_JOINT, RIGHT_JOINT = np.array([-0.3, 0.0, 0.0]), np.array([0.3, 0.0, 0.0])


def three_part_chain(n_frames, bending, seed=0):
    """A 1.2 m cylinder cut in three parts (joints at x = -0.3 and 0.3 m), swaying and
    travelling as a whole; only the joint `bending` ('left' or 'right') bends, by up to 40
    degrees. 1 mm noise. Returns rest (M, 3) and registered (F, M, 3)."""
    rng = np.random.default_rng(seed)
    along = np.random.default_rng(1).uniform(-0.6, 0.6, 1800)
    angle = np.random.default_rng(2).uniform(0, 2 * np.pi, 1800)
    rest = np.column_stack([along, 0.05 * np.cos(angle), 0.05 * np.sin(angle)])
    if bending == 'left':
        part, joint = rest[:, 0] < LEFT_JOINT[0], LEFT_JOINT
    else:
        part, joint = rest[:, 0] > RIGHT_JOINT[0], RIGHT_JOINT
    frames = []
    for f in range(n_frames):
        phase = 2 * np.pi * f / n_frames
        bend = Rotation.from_rotvec(np.radians(40.0) * np.array([0.0, 0.3 * np.cos(phase), np.sin(phase)])).as_matrix()
        body = Rotation.from_rotvec([0.0, 0.2 * np.sin(phase), 0.1]).as_matrix()
        moved = rest.copy()
        moved[part] = (rest[part] - joint) @ bend.T + joint
        moved = moved @ body.T + np.array([0.3 * f / n_frames, 0.0, 2.5])
        frames.append(moved + rng.normal(scale=0.001, size=moved.shape))
    return rest, np.array(frames)


def _rest_joint_ids(update, position):
    """The id of the update's joint nearest `position` (rest frame) and its distance."""
    joints = update.estimate.joints if update.estimate is not None else update.structure.joints
    distances = np.linalg.norm(joints - position, axis=1)
    return int(update.joint_ids[np.argmin(distances)]), float(distances.min())


def test_two_limbs_moving_in_different_windows_end_in_one_model_with_stable_ids():
    rest, first = three_part_chain(40, 'left')
    _, second = three_part_chain(40, 'right', seed=1)
    second = second - second[0] + first[-1]           # the second window carries on from the first
    growth = SkeletonGrowth(rest, StructureParams(n_clusters=20, max_key_frames=40))

    one = growth.update(np.arange(40), first)
    assert one.structure.n_bones == 2
    left_id, distance = _rest_joint_ids(one, LEFT_JOINT)
    assert distance < 0.05

    two = growth.update(np.arange(40, 80), second)
    assert two.structure.n_bones == 3, 'the joint of the first window must survive the second'
    assert two.changed
    # the joint seen first keeps its id and name; the new one is announced
    left_again, distance = _rest_joint_ids(two, LEFT_JOINT)
    assert distance < 0.05 and left_again == left_id
    right_id, distance = _rest_joint_ids(two, RIGHT_JOINT)
    assert distance < 0.05 and right_id not in one.joint_ids
    assert f'joint_{right_id}' in two.changes['added']
    assert f'joint_{left_id}' not in two.changes['added'] + two.changes['removed']
    # key frames stay bounded and keep frames of both windows
    assert len(growth.key_stamps) == 40
    assert (growth.key_stamps < 40).any() and (growth.key_stamps >= 40).any()


def test_a_skeleton_started_after_another_continues_its_ids():
    """A new rest pose starts a new skeleton (the accumulator node's SkeletonGrowth with the
    previous one's next_id): its joints get ids the first never used, in the structure, the
    changes and the model, so no name means two joints."""
    rest, first = three_part_chain(40, 'left')
    _, second = three_part_chain(40, 'right', seed=1)
    params = StructureParams(n_clusters=20, max_key_frames=40)
    before = SkeletonGrowth(rest, params)
    old = before.update(np.arange(40), first)
    after = SkeletonGrowth(rest, params, first_id=before.next_id)
    new = after.update(np.arange(40), second, [frame[::3] for frame in second])
    assert before.next_id == max(old.joint_ids) + 1 and min(new.joint_ids) == before.next_id
    assert set(new.joint_names).isdisjoint(old.joint_names)
    assert set(new.changes['added']) == set(new.joint_names) and new.model.joint_names == new.joint_names
    assert after.next_id == max(new.joint_ids) + 1


def test_a_window_without_new_motion_changes_nothing():
    rest, first = three_part_chain(40, 'left')
    growth = SkeletonGrowth(rest, StructureParams(n_clusters=20, max_key_frames=40))
    one = growth.update(np.arange(40), first)
    # the same motion again (new noise): same joints, same ids, nothing to publish
    _, again = three_part_chain(40, 'left', seed=5)
    two = growth.update(np.arange(40, 80), again)
    assert sorted(two.joint_ids) == sorted(one.joint_ids)
    assert not two.changed and not any(two.changes.values())


def test_a_window_showing_no_articulation_raises_until_one_does():
    rest, frames = three_part_chain(20, 'left')
    # the subject only travels, in its rest pose: one rigid motion, 1 mm noise
    rigid = rest[None] + np.linspace(0.0, 0.2, 20)[:, None, None] \
        + np.random.default_rng(0).normal(scale=0.001, size=(20,) + rest.shape)
    growth = SkeletonGrowth(rest, StructureParams(n_clusters=20))
    with pytest.raises(StructureError):
        growth.update(np.arange(20), rigid)
    update = growth.update(np.arange(20, 40), frames)
    assert update.structure.n_bones == 2


def test_farthest_poses_keeps_the_extremes_and_ignores_rigid_motion():
    rest, frames = three_part_chain(60, 'left')
    # the same pose moved far away is no new pose
    moved = frames @ Rotation.from_rotvec([0, 0, 1.0]).as_matrix().T + 5.0
    poses = aligned_poses(rest, np.concatenate([frames, moved]), np.arange(0, len(rest), 7))
    assert np.abs(poses[:60] - poses[60:]).max() < 1e-6
    keep = farthest_poses(poses[:60], 5)
    assert len(keep) == 5 and len(set(keep)) == 5
    assert (farthest_poses(poses[:3], 5) == np.arange(3)).all()


def test_bad_frames_and_shapes():
    rest, frames = three_part_chain(10, 'left')
    growth = SkeletonGrowth(rest, StructureParams(max_key_frames=8))
    frames[3] = np.nan
    growth.add_frames(np.arange(10), frames)
    assert 3 not in growth.key_stamps and len(growth.key_stamps) == 8
    with pytest.raises(ValueError, match='registered frames'):
        growth.add_frames(np.arange(2), frames[:2, :10])
    with pytest.raises(ValueError, match='one entry per frame'):
        growth.add_frames(np.arange(3), frames[:2])
    with pytest.raises(ValueError, match='max_key_frames'):
        StructureParams(max_key_frames=1)


def test_previous_labels_must_match_the_rest_points():
    from skel_extract_ros.core.structure import extract_structure
    rest, frames = three_part_chain(10, 'left')
    with pytest.raises(ValueError, match='previous_labels'):
        extract_structure(rest, frames, StructureParams(n_clusters=12), previous_labels=np.zeros(5, dtype=int))


def test_the_growth_schedule_learns_when_the_window_is_full_and_then_every_stride_when_sliding():
    once = GrowthSchedule(window_size=5)
    assert [once.due(n, False) for n in range(1, 7)] == [False] * 4 + [True, True]
    assert not any(once.due(n, True) for n in range(1, 100)), 'without sliding: learned once'
    sliding = GrowthSchedule(window_size=5, sliding=True, stride=3)
    assert [sliding.due(n, True) for n in range(1, 5)] == [False, False, True, True]
    with pytest.raises(ValueError, match='window_size'):
        GrowthSchedule(window_size=1)


def test_with_observed_points_the_ids_are_the_accumulators_and_alg2_runs_only_on_a_change():
    """`run` grows the skeleton with the observed points (Alg. 2 in the same update); the
    nodes grow it without them (the accumulator) and run Alg. 2 on each published, changed
    structure (the joint node). Both key the joints alike, so the two give the same names;
    and a window that changed nothing costs no Alg. 2."""
    rest, first = three_part_chain(30, 'left')
    _, again = three_part_chain(30, 'left', seed=5)
    _, second = three_part_chain(30, 'right', seed=1)
    again, second = again - again[0] + first[-1], second - second[0] + first[-1]
    windows = [first, again, second]
    params = StructureParams(n_clusters=20, max_key_frames=40)
    nodes, run = SkeletonGrowth(rest, params), SkeletonGrowth(rest, params)
    changed = []
    for k, window in enumerate(windows):
        stamps = np.arange(30 * k, 30 * (k + 1))
        by_nodes = nodes.update(stamps, window)
        by_run = run.update(stamps, window, [frame[::3] for frame in window])
        assert list(by_run.joint_ids) == list(by_nodes.joint_ids)
        assert by_run.changes == by_nodes.changes and by_run.changed == by_nodes.changed
        assert (by_run.estimate is not None) == by_run.changed and (by_run.model is not None) == by_run.changed
        changed.append(by_run.changed)
    assert changed == [True, False, True] and by_run.structure.n_bones == 3
