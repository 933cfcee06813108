"""The joint node's per-frame outputs without a graph: markers, velocities, confidence."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from visualization_msgs.msg import Marker

from ros_harness import T0, DT, header
from skel_extract_ros.core.confidence import HALF_RESIDUAL, MIN_SAMPLES, bone_confidence, joint_confidence
from skel_extract_ros.core.live import LiveJointTracker
from skel_extract_ros.core.skeleton_model import SkeletonModel
from skel_extract_ros.codecs.messages import skeleton_markers
from skel_extract_ros.nodes.skeleton_output import MAX_VELOCITY_GAP_S, FrameVelocities
from two_bone import two_bone_sequence


def test_markers_are_named_by_the_stable_joint_ids():
    positions = np.array([[0.0, 0, 1], [0.2, 0, 1], [0.4, 0, 1]])
    markers = skeleton_markers(positions, [-1, 0, 1], header(T0), 0.04, ids=[7, 3, 12],
                               names=['joint_7', 'joint_3', 'joint_12'], confidence=[1.0, 0.5, 0.0],
                               delete_all=True)
    assert markers.markers[0].action == Marker.DELETEALL
    spheres = [m for m in markers.markers if m.type == Marker.SPHERE]
    texts = [m for m in markers.markers if m.type == Marker.TEXT_VIEW_FACING]
    assert [m.id for m in spheres] == [m.id for m in texts] == [7, 3, 12]
    assert [m.text for m in texts] == ['joint_7', 'joint_3', 'joint_12']
    # green at confidence 1, red at 0
    assert (spheres[0].color.g, spheres[0].color.r) == (1.0, 0.0)
    assert (spheres[2].color.g, spheres[2].color.r) == (0.0, 1.0)
    assert not any(m.action == Marker.DELETEALL for m in skeleton_markers(positions, [-1, 0, 1], header(T0)).markers)


def test_velocities_are_finite_differences_within_one_version():
    velocities = FrameVelocities()
    turn = Rotation.from_rotvec([0.0, 0.0, 0.1]).as_matrix()
    p0, r0 = np.zeros((2, 3)), np.stack([np.eye(3)] * 2)
    assert velocities.update(1, T0, p0, r0) is None                     # nothing before it
    linear, angular = velocities.update(1, T0 + DT, p0 + [0.01, 0, 0], np.stack([turn, np.eye(3)]))
    np.testing.assert_allclose(linear, [[0.01 / (DT * 1e-9), 0, 0]] * 2)
    np.testing.assert_allclose(angular, [[0, 0, 0.1 / (DT * 1e-9)], [0, 0, 0]], atol=1e-9)
    assert velocities.update(2, T0 + 2 * DT, p0, r0) is None            # a new skeleton
    assert velocities.update(2, T0 + DT, p0, r0) is None                # time went back
    gap = T0 + DT + int(MAX_VELOCITY_GAP_S * 1e9) + 1
    assert velocities.update(2, gap, p0, r0) is None                    # a gap in the data


def test_confidence_falls_with_the_residual_and_with_unseen_bones():
    bones = np.repeat([0, 1, 2], 20)
    squared = np.concatenate([np.zeros(20), np.full(20, HALF_RESIDUAL ** 2), np.zeros(20)])
    np.testing.assert_allclose(bone_confidence(4, bones, squared), [1.0, 0.5, 1.0, 0.0])
    # joint b: the smaller of its bone's and its parent bone's
    np.testing.assert_allclose(joint_confidence([-1, 0, 1, 2], bones, squared), [1.0, 0.5, 0.5, 0.0])
    few = bone_confidence(1, np.zeros(MIN_SAMPLES // 2, dtype=int), np.zeros(MIN_SAMPLES // 2))
    np.testing.assert_allclose(few, [0.5])
    # a NaN sample is no sample
    np.testing.assert_allclose(bone_confidence(1, [0] * 10 + [0], [0.0] * 10 + [np.nan]), [1.0])


def test_tracker_confidence_on_registered_and_observed_points():
    rest, registered, labels, _, _ = two_bone_sequence(n_frames=4)
    model = SkeletonModel(rest, labels, np.array([-1, 0]), np.array([[-0.15, 0, 0], [0.0, 0, 0]]),
                          labels[:, None], np.ones((len(rest), 1)))
    tracker = LiveJointTracker(model)
    rotations, translations = tracker.fit(registered[2])
    exact = tracker.confidence(rotations, translations, registered[2], corresponding=True)
    np.testing.assert_allclose(exact, [1.0, 1.0], atol=1e-6)
    # the child bone's points 5 cm off: its joint (and only it) loses confidence
    moved = registered[2].copy()
    moved[labels == 1] += [0.0, 0.05, 0.0]
    off = tracker.confidence(rotations, translations, moved, corresponding=True)
    assert off[0] > 0.99 and off[1] < 0.35, off
    # observed points of the parent bone only: the child's bone is unseen, confidence 0
    seen = tracker.confidence(rotations, translations, registered[2][labels == 0], corresponding=False)
    assert seen[0] > 0.99 and seen[1] == 0.0, seen


def test_a_bone_posed_outside_the_silhouette_loses_its_confidence_whatever_its_residual():
    rest, registered, labels, _, joints = two_bone_sequence(n_frames=4)
    in_front = np.array([0.0, 0.0, 2.0])                 # 2 m from the camera, its rays apart
    rest, registered, joint = rest + in_front, registered + in_front, joints[2] + in_front
    model = SkeletonModel(rest, labels, np.array([-1, 0]), np.array([[-0.15, 0, 2.0], [0.0, 0, 2.0]]),
                          labels[:, None], np.ones((len(rest), 1)))
    tracker = LiveJointTracker(model)
    observed = registered[2]
    # a registration that turned the child bone 90 degrees about its joint, into empty
    # space: the fit follows it
    lost = observed.copy()
    turn = Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix()
    lost[labels == 1] = (observed[labels == 1] - joint) @ turn.T + joint
    rotations, translations = tracker.fit(lost)
    residual_only = tracker.confidence(rotations, translations, lost, corresponding=True)
    assert residual_only.min() > 0.99, residual_only
    seen = tracker.confidence(rotations, translations, lost, corresponding=True, observed=observed)
    assert seen[0] > 0.99 and seen[1] < 0.2, seen        # its end near the joint is still in view
    # the camera path: the same pose against the frame's observed points
    assert tracker.confidence(rotations, translations, observed, corresponding=False)[1] < 0.2
    # where the registration is right, the silhouette takes nothing away
    rotations, translations = tracker.fit(observed)
    np.testing.assert_allclose(tracker.confidence(rotations, translations, observed, True, observed), [1.0, 1.0],
                               atol=1e-6)


def test_the_share_outside_the_silhouette_is_counted_per_bone():
    from skel_extract_ros.core.confidence import outside_silhouette
    from skel_extract_ros.core.registration.visibility import ObservedView
    grid = np.stack(np.meshgrid(np.linspace(-0.2, 0.2, 41), np.linspace(-0.2, 0.2, 41)), -1).reshape(-1, 2)
    observed = np.column_stack([grid, np.full(len(grid), 2.0)])          # a wall 2 m away, 1 cm apart
    posed = np.array([[0.0, 0, 2.0], [0.1, 0.1, 1.9], [0.5, 0, 2.0], [0.0, 0.6, 2.2], [0.05, 0.05, 2.5]])
    shares = outside_silhouette(3, [0, 0, 1, 1, 2], posed, ObservedView(observed))
    np.testing.assert_allclose(shares, [0.0, 1.0, 0.0])
    np.testing.assert_allclose(joint_confidence([-1, 0, 1], [0] * 20 + [1] * 20 + [2] * 20, np.zeros(60), shares),
                               [1.0, 0.0, 0.0])


def test_a_residual_is_judged_against_the_skeletons_own_noise():
    from skel_extract_ros.core.confidence import NOISE_MULTIPLE, half_residual
    rest, registered, labels, _, _ = two_bone_sequence(n_frames=4)
    # a hand-sized fit: the skeleton fitted its learning frames to 2 mm
    small = SkeletonModel(rest, labels, np.array([-1, 0]), np.array([[-0.15, 0, 0], [0.0, 0, 0]]),
                          labels[:, None], np.ones((len(rest), 1)), noise_m=0.002)
    tracker = LiveJointTracker(small)
    rotations, translations = tracker.fit(registered[2])
    off = registered[2].copy()
    off[labels == 1] += [0.0, NOISE_MULTIPLE * 0.002, 0.0]         # the child bone off by its half
    np.testing.assert_allclose(tracker.confidence(rotations, translations, off, corresponding=True), [1.0, 0.5],
                               atol=1e-3)
    # without a known noise (Step 2's provisional skeleton) the same 4 mm is nothing
    unknown = LiveJointTracker(SkeletonModel(rest, labels, small.parents, small.rest_joints, small.influences,
                                             small.weights))
    assert unknown.confidence(rotations, translations, off, corresponding=True)[1] > 0.97
    assert half_residual(None) == HALF_RESIDUAL and half_residual(0.01) == NOISE_MULTIPLE * 0.01


def test_alg2_gives_the_skeleton_the_noise_of_its_fit():
    from skel_extract_ros.core.joints import JointEstimate
    tau = np.array([1e-4, 4e-4, 9e-4])                       # per coordinate, m^2
    estimate = JointEstimate(np.zeros((3, 1), int), np.ones((3, 1)), np.tile(np.eye(3), (3, 1, 1, 1)),
                             np.zeros((3, 1, 3)), np.zeros((1, 3)), np.array([-1]), tau)
    model = estimate.model(np.zeros((3, 3)), np.zeros(3, int))
    assert model.noise_m == pytest.approx(np.sqrt(3 * 4e-4))    # the median frame's RMS distance


def test_step2s_skeleton_is_judged_against_the_noise_of_its_bones_fits():
    """A provisional skeleton has no Alg. 2 tau: its noise is the RMS distance of each
    frame's observed points to the nearest posed point, the median over the frames."""
    from skel_extract_ros.core.confidence import fit_noise
    grid = np.stack(np.meshgrid(np.linspace(-0.2, 0.2, 21), np.linspace(-0.2, 0.2, 21)), -1).reshape(-1, 2)
    wall = np.column_stack([grid, np.full(len(grid), 2.0)])          # posed points 2 cm apart, 2 m away
    posed = np.stack([wall] * 4)
    # the observed surface 1, 3 and 4 mm behind the posed one (NaN rows, as a camera gives,
    # are not points), and a frame the camera saw nothing of
    observed = [np.vstack([wall + [0, 0, depth], [[np.nan] * 3]]) for depth in (0.001, 0.003, 0.004)]
    assert fit_noise(posed, observed + [np.empty((0, 3))]) == pytest.approx(0.003)
    assert fit_noise(posed, [np.empty((0, 3))] * 4) is None


def test_the_description_carries_the_noise_the_confidence_is_judged_against():
    from skel_extract_ros.codecs.messages import description_document
    rest, _, labels, _, _ = two_bone_sequence(n_frames=2)
    model = SkeletonModel(rest, labels, np.array([-1, 0]), np.zeros((2, 3)), labels[:, None],
                          np.ones((len(rest), 1)), noise_m=0.0123456)
    assert description_document(model, 'camera', [1, 2])['noise_m'] == 0.01235
    provisional = SkeletonModel(rest, labels, model.parents, model.rest_joints, model.influences, model.weights)
    assert description_document(provisional, 'camera', [1, 2], provisional=True)['noise_m'] is None


def test_a_bone_that_no_point_follows_most_keeps_its_share_of_them():
    # 60 points: bone 0's, and 30 that follow bone 1 by 0.6 and bone 2 by 0.4 (bone 2 is no
    # point's dominant bone, as a short bone between two longer ones can be)
    influences = np.array([[0, 0]] * 30 + [[1, 2]] * 30)
    weights = np.array([[1.0, 0.0]] * 30 + [[0.6, 0.4]] * 30)
    squared = np.zeros(60)
    np.testing.assert_allclose(joint_confidence([-1, 0, 1], influences, squared, None, HALF_RESIDUAL, weights),
                               [1.0, 1.0, 1.0])
    # counted by the dominant bone alone, bone 2 would have no sample and its joint 0
    dominant = influences[np.arange(60), np.argmax(weights, axis=1)]
    assert joint_confidence([-1, 0, 1], dominant, squared)[2] == 0.0
    # its points 3 cm off count for it by their weight
    squared[30:] = HALF_RESIDUAL ** 2
    np.testing.assert_allclose(bone_confidence(3, influences, squared, HALF_RESIDUAL, weights), [1.0, 0.5, 0.5])
