"""Live joints: the learned LBS model fitted to frames it was not learned from."""
import numpy as np
import pytest

from skel_extract_ros.core.joints import JointEstimation
from skel_extract_ros.core.live import FIT_OBSERVED, FIT_POINTS, ArticulatedTracker, CameraTracker, LiveJointTracker
from skel_extract_ros.core.skeleton_model import SkeletonModel
from skel_extract_ros.core.structure import StructureParams, extract_structure
from two_bone import two_bone_sequence


@pytest.fixture(scope='module')
def learned():
    rest, registered, _labels, joint, joint_path = two_bone_sequence(n_frames=40)
    window = registered[::2]          # learn from every other frame, track the rest
    structure = extract_structure(rest, window, StructureParams(n_clusters=12))
    estimate = JointEstimation().fit(rest, window, list(window), structure)
    model = SkeletonModel(rest, structure.labels, estimate.parents, estimate.joints,
                          estimate.influences, estimate.weights)
    return model, registered, joint_path, estimate


@pytest.mark.parametrize('sweeps', [0, 2])
def test_live_joints_follow_unseen_frames(learned, sweeps):
    """Noise-free unseen frames: measured 0.98 mm (sweeps 0) / 1.04 mm (sweeps 2) at worst."""
    model, registered, joint_path, _ = learned
    tracker = LiveJointTracker(model, sweeps=sweeps)
    child = int(np.flatnonzero(model.parents >= 0)[0])
    unseen = np.arange(1, len(registered), 2)
    tracked = np.array([tracker.track(registered[f])[child] for f in unseen])
    assert np.linalg.norm(tracked - joint_path[unseen], axis=1).max() < 1.4e-3


def test_live_fit_matches_alg2_on_its_own_window(learned):
    """On Alg. 2's own frames the live fit gives Alg. 2's joints: 0.23 mm apart at most (measured)."""
    model, registered, _, estimate = learned
    tracker = LiveJointTracker(model, sweeps=2)
    live = np.array([tracker.track(frame) for frame in registered[::2]])
    np.testing.assert_allclose(live, estimate.joint_trajectories(), atol=3e-4)
    rotations, _ = tracker.fit(registered[0])
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-9)


def test_live_rejects_a_frame_of_another_size(learned):
    model = learned[0]
    with pytest.raises(ValueError, match='points'):
        LiveJointTracker(model).track(np.zeros((10, 3)))
    with pytest.raises(ValueError, match='sweeps'):
        LiveJointTracker(model, sweeps=-1)


@pytest.mark.parametrize('sweeps, max_gap, max_error', [(1, 0.086e-3, 3.4e-3), (2, 0.117e-3, 3.2e-3)])
def test_sweeps_enforce_the_joint_constraint_on_noisy_frames(learned, sweeps, max_gap, max_error):
    """Noise-free, the per-bone rigid fits are already exact, so broken sweeps pass the tests
    above. On the unseen frames with 1 cm noise the independent rigid fits (sweeps = 0) tear
    the joint apart: parent and child carry it to places 1.67 mm apart on average (measured).
    The sweeps' joint term (Eq. 13-15) closes the gap: measured 0.066 mm (1 sweep), 0.090 mm
    (2 sweeps); bounds 1.3 x, so sweeps that skip the joint term, or do nothing, fail by
    more than 10 x. The reported joint (the mean of both carriages) is not more accurate
    for it (measured worst 2.62 / 2.45 mm with sweeps, 1.97 mm without): the error bound
    (1.3 x measured) only checks that closing the gap does not move the joint away."""
    model, registered, joint_path, _ = learned
    child = int(np.flatnonzero(model.parents >= 0)[0])
    parent = int(model.parents[child])
    rest_joint = np.asarray(model.rest_joints)[child]
    rng = np.random.default_rng(1)
    unseen = np.arange(1, len(registered), 2)
    frames = [registered[f] + rng.normal(scale=0.01, size=registered[f].shape) for f in unseen]

    def mismatch(sweeps):
        tracker = LiveJointTracker(model, sweeps=sweeps)
        gaps, tracked = [], []
        for frame in frames:
            R, T = tracker.fit(frame)
            gaps.append(np.linalg.norm(R[child] @ rest_joint + T[child] - R[parent] @ rest_joint - T[parent]))
            tracked.append(tracker.track(frame)[child])
        return np.mean(gaps), np.linalg.norm(np.array(tracked) - joint_path[unseen], axis=1).max()

    rigid_gap, _ = mismatch(0)
    swept_gap, swept_error = mismatch(sweeps)
    assert rigid_gap > 1.3e-3, rigid_gap
    assert swept_gap < max_gap and swept_gap < 0.07 * rigid_gap, (rigid_gap, swept_gap)
    assert swept_error < max_error, swept_error


def _observations(registered, seed=0):
    """Each frame as a camera gives it: 800 of the surface points, in another order, 3 mm noise."""
    rng = np.random.default_rng(seed)
    return [frame[rng.choice(len(frame), 800, replace=False)] + rng.normal(scale=0.003, size=(800, 3))
            for frame in registered]


@pytest.mark.parametrize('iterations, max_error', [(5, 3.1e-3)])
def test_articulated_fit_follows_the_observed_points_alone(learned, iterations, max_error):
    """No registration: seeded once, the model is fitted to each frame's observations only.
    Measured on the 39 frames after the seed: 2.36 mm worst, 0.96 mm mean (5 EM
    iterations); one iteration per frame falls behind the motion (7.6 mm worst), so the
    bound (1.3 x) fails a fit that does not iterate to the data."""
    model, registered, joint_path, _ = learned
    child = int(np.flatnonzero(model.parents >= 0)[0])
    observed = _observations(registered)
    tracker = ArticulatedTracker(model, iterations=iterations)
    tracker.seed(*LiveJointTracker(model).fit(registered[0]))
    errors = [np.linalg.norm(tracker.track(observed[f])[child] - joint_path[f]) for f in range(1, len(registered))]
    assert max(errors) < max_error, max(errors)
    assert not tracker.lost
    single = ArticulatedTracker(model, iterations=1)
    single.seed(*LiveJointTracker(model).fit(registered[0]))
    lagging = [np.linalg.norm(single.track(observed[f])[child] - joint_path[f]) for f in range(1, len(registered))]
    assert max(lagging) > max_error


def test_articulated_fit_reports_a_bone_without_data_as_lost(learned):
    model, registered, _, _ = learned
    observed = _observations(registered)
    tracker = ArticulatedTracker(model)
    tracker.seed(*LiveJointTracker(model).fit(registered[0]))
    for frame in observed[1:10]:
        tracker.track(frame)
    assert not tracker.lost
    child = int(np.flatnonzero(model.parents >= 0)[0])
    # the child bone leaves the view: only the parent's points are observed
    parent_only = registered[10][np.asarray(model.labels) != child]
    positions = tracker.track(parent_only)
    assert tracker.lost and np.isfinite(positions).all()
    tracker.seed(*LiveJointTracker(model).fit(registered[11]))
    tracker.track(observed[12])
    assert not tracker.lost


def test_articulated_fit_rejects_what_it_cannot_fit(learned):
    model, registered, _, _ = learned
    tracker = ArticulatedTracker(model)
    with pytest.raises(ValueError, match='seed'):
        tracker.track(registered[0])
    with pytest.raises(ValueError, match='seed needs'):
        tracker.seed(np.eye(3)[None], np.zeros((1, 3)))
    tracker.seed(*LiveJointTracker(model).fit(registered[0]))
    with pytest.raises(ValueError, match='finite'):
        tracker.track(np.full((50, 3), np.nan))
    with pytest.raises(ValueError, match=r'\(N, 3\)'):
        tracker.track(np.zeros((50, 2)))
    with pytest.raises(ValueError, match='iterations'):
        ArticulatedTracker(model, iterations=0)


def test_the_bone_blocks_never_raise_the_energy(learned):
    """The live fit's M-step (Eq. 13-15, bone after bone, each an exact block of the frame's
    energy): from a disturbed pose the energy falls at every sweep, to a small fraction.
    (All bones at once, translations by one linear solve and rotations through a majoriser,
    was measured against it: 25 735 -> 117 after 6 sweeps on this pose, bone by bone 0.26.)"""
    model, registered, _, _ = learned
    tracker = ArticulatedTracker(model, max_points=len(model.rest_points))
    rotations, translations = LiveJointTracker(model).fit(registered[5])
    anchors = (rotations.copy(), translations.copy())
    targets = tracker.deform(*LiveJointTracker(model).fit(registered[8]))
    point_weights = np.random.default_rng(0).uniform(0.5, 2.0, size=len(targets)) * 1e4
    params, alpha = tracker.params, tracker._alpha
    children = np.flatnonzero(model.parents >= 0)
    parents = np.asarray(model.parents)[children]
    centres = np.asarray(model.rest_joints)[children]

    def energy(r, t):
        data = np.sum(point_weights * np.sum((targets - tracker.deform(r, t)) ** 2, axis=1))
        gap = (np.einsum('eij,ej->ei', r[children], centres) + t[children]
               - np.einsum('eij,ej->ei', r[parents], centres) - t[parents])
        small = np.sum((t - anchors[1]) ** 2) + np.sum((r - anchors[0]) ** 2)
        return data + alpha * np.sum(gap ** 2) + params.gamma * small
    energies = [energy(rotations, translations)]
    for _ in range(6):
        tracker.sweep(targets, point_weights, rotations, translations, anchors)
        energies.append(energy(rotations, translations))
    assert all(b <= a * (1 + 1e-9) for a, b in zip(energies, energies[1:])), energies
    assert energies[-1] < 1e-3 * energies[0], energies


def test_the_whole_body_move_brings_a_displaced_body_back_in_one_step(learned):
    """The pose of frame 7 turned 21 degrees and shifted 16 cm as a whole, exact targets:
    one whole-body move restores it (joints within 1e-9 m of where they were; they start
    18.9 cm off). The bone-by-bone update at Alg. 2's joint weight leaves them 9.9 cm off
    after one pass (measured: it holds each bone at joints its neighbours have not moved
    yet); bound 7 cm."""
    from scipy.spatial.transform import Rotation
    model, registered = learned[0], learned[1]
    tracker = ArticulatedTracker(model)
    rotations, translations = LiveJointTracker(model).fit(registered[7])
    targets, true_joints = tracker.deform(rotations, translations), tracker.joints_of(rotations, translations)
    turn = Rotation.from_rotvec([0.1, 0.3, 0.2]).as_matrix()
    moved_r = turn @ rotations
    moved_t = translations @ turn.T + np.array([0.15, -0.05, 0.02])
    start_error = np.linalg.norm(tracker.joints_of(moved_r, moved_t) - true_joints, axis=1).max()
    swept_r, swept_t = moved_r.copy(), moved_t.copy()
    tracker.move_whole_body(targets, np.ones(len(targets)), tracker.deform(moved_r, moved_t), moved_r, moved_t)
    np.testing.assert_allclose(tracker.joints_of(moved_r, moved_t), true_joints, atol=1e-9)
    np.testing.assert_allclose(moved_t, translations, atol=1e-9)
    tracker.sweep(targets, 1e4, swept_r, swept_t)
    swept_error = np.linalg.norm(tracker.joints_of(swept_r, swept_t) - true_joints, axis=1).max()
    assert start_error > 0.15 and swept_error > 0.07, (start_error, swept_error)


def _camera_tracker(model, **kwargs):
    return CameraTracker(ArticulatedTracker(model, **kwargs), LiveJointTracker(model))


def _late_registrations(model, registered, joint_path, reach, lag=10, camera=None):
    """Errors (m) of the child joint on frames lag.. when each frame is fitted from the
    registered frame `lag` to 2 lag - 1 frames older (the node's cadence)."""
    child = int(np.flatnonzero(model.parents >= 0)[0])
    observed = _observations(registered)
    camera = camera or _camera_tracker(model, reach=reach)
    errors = []
    for frame in range(lag, len(registered)):
        newest = ((frame - lag) // lag) * lag
        camera.registered(newest, registered[newest])
        positions, outcome = camera.track(frame, observed[frame])
        assert outcome in ('fitted', 'chained')
        errors.append(np.linalg.norm(positions[child] - joint_path[frame]))
    return np.array(errors)


def test_camera_tracker_reaches_a_body_that_walked_since_its_registration(learned):
    """The two bones walking 2 cm a frame across their axis (diagonally in y-z), the
    registration 10-19 frames (20-38 cm) old: with reach (the whole-body move, the joint
    weight ramp) the child joint is measured 50 mm off on average, without 286 mm (the fit
    barely leaves the registered pose); bound: reach at most 0.35 x.

    Not along the axis (x): the bones are featureless cylinders along x, so a slide along
    it is nearly unobserved and how far a fit follows it depends on rounding (reach 0.54 x
    on the machines this test was written on, 0.61 x on an AMD EPYC with the same wheels;
    across the axis 0.175 x on both BLAS kernels tried there). Nor bending 60 degrees within
    the lag without walking, where reach is worse on these cylinders (65 against 18 mm:
    loosened, each slides along its own axis), unlike on real motion, where it is better or
    equal on 9 of 10 rows (bench/README.md, "Reach"); those cases are not asserted."""
    model, registered, joint_path, _ = learned
    direction = np.array([0.0, 1.0, 1.0]) / np.sqrt(2.0)
    walked = 0.02 * np.arange(len(registered))
    walking = registered + walked[:, None, None] * direction
    path = joint_path + walked[:, None] * direction
    with_reach = _late_registrations(model, walking, path, reach=True)
    without = _late_registrations(model, walking, path, reach=False)
    assert with_reach.mean() < 0.35 * without.mean(), (with_reach.mean(), without.mean())


def _surface_errors(camera, registered, observed, lag=10):
    """Mean distance (m) of the served pose's posed points from the true surface points, on
    frames lag.. fitted while the registered frame is lag to 2 lag - 1 frames old."""
    errors = []
    for frame in range(lag, len(registered)):
        newest = ((frame - lag) // lag) * lag
        camera.registered(newest, registered[newest])
        camera.track(frame, observed[frame])
        errors.append(np.linalg.norm(camera.fit.deform(*camera.pose) - registered[frame], axis=1).mean())
    return np.array(errors)


def test_camera_tracker_chained_follows_a_limb_the_registered_pose_cannot_reach(learned):
    """The child bone turns 0.6-0.8 rad over the clip while the registration is 10-19
    frames old. Fitted from the registered pose alone the posed points are 59 mm from the
    true surface on average (measured); with the chain (each frame also fitted from the
    pose served for the frame before, the better supported fit served) 1.3 mm, 29 of the 30
    frames served from the chain. Bound: 0.5 x."""
    model, registered, _, _ = learned
    observed = _observations(registered)
    alone = _surface_errors(_camera_tracker(model), registered, observed)
    camera = CameraTracker(ArticulatedTracker(model), LiveJointTracker(model), ArticulatedTracker(model))
    chained = _surface_errors(camera, registered, observed)
    assert chained.mean() < 0.5 * alone.mean(), (chained.mean(), alone.mean())
    assert camera.counts['chained'] > 3 * camera.counts['fitted'], camera.counts


def test_camera_tracker_for_model_gives_each_of_two_starts_half_of_one_fits_points(learned):
    """The node's construction: one fit on FIT_POINTS model points and FIT_OBSERVED
    observations; with the chain two fits, each on half of both (the model here has more
    than FIT_POINTS points, so the halves are real subsets). On half the points, 3 EM
    iterations as the node, the chain follows the turning limb of the test above: the posed
    points 4.0 mm from the true surface on average (measured; both fits on all the points
    2.4 mm, the registered start alone 75 mm); bound 10 mm."""
    model, registered, _, _ = learned
    assert len(model.rest_points) > FIT_POINTS
    one = CameraTracker.for_model(model, None, LiveJointTracker(model), iterations=3)
    two = CameraTracker.for_model(model, None, LiveJointTracker(model), iterations=3, chain=True)
    assert one.chain is None and one.tracker.max_observed == FIT_OBSERVED
    assert len(one.tracker._subset) <= FIT_POINTS < 2 * len(one.tracker._subset)
    for tracker in (two.tracker, two.chain):
        assert tracker.iterations == 3 and tracker.max_observed == FIT_OBSERVED // 2
        assert len(tracker._subset) <= FIT_POINTS // 2 < 2 * len(tracker._subset)
    errors = _surface_errors(two, registered, _observations(registered))
    assert errors.mean() < 0.01, errors.mean()
    assert two.counts['chained'] > 3 * two.counts['fitted'], two.counts


def test_camera_tracker_serves_the_registered_start_when_the_chain_has_drifted(learned):
    """A chain that drifted (here: seeded with a pose 17 frames away and given one EM
    iteration, too few to come back) explains the frame worse than the fit from the
    registered frame before it: that fit is served, and the chain starts again from it."""
    model, registered, _, _ = learned
    observed = _observations(registered)
    fit = LiveJointTracker(model)
    camera = CameraTracker(ArticulatedTracker(model), fit, ArticulatedTracker(model, iterations=1))
    camera.registered(2, registered[2])
    assert camera.track(3, observed[3])[1] in ('fitted', 'chained')
    camera.chain.seed(*fit.fit(registered[20]))
    positions, outcome = camera.track(4, observed[4])
    assert outcome == 'fitted', camera.counts
    assert np.linalg.norm(fit.deform(*camera.pose) - registered[4], axis=1).mean() < 0.01
    # the chain now starts from the served pose: it is served again once it fits as well
    np.testing.assert_allclose(camera.chain.predict()[1], camera.pose[1], atol=1e-12)


def test_camera_tracker_leaves_the_second_fit_out_when_the_frame_has_no_time_for_it(learned):
    """A deadline already passed: every frame is fitted from the registered pose alone (one
    fit, as without a chain) and the skipped second fits are counted; without a deadline
    the chain is fitted again."""
    import time
    model, registered, _, _ = learned
    observed = _observations(registered)
    camera = CameraTracker(ArticulatedTracker(model), LiveJointTracker(model), ArticulatedTracker(model))
    camera.registered(0, registered[0])
    for frame in range(1, 6):
        assert camera.track(frame, observed[frame], deadline=time.perf_counter())[1] == 'fitted'
    assert camera.chain_skipped == 4 and camera.counts['chained'] == 0      # the first frame has no chain yet
    camera.track(6, observed[6])
    assert camera.chain_skipped == 4 and camera.counts['fitted'] + camera.counts['chained'] == 6


def test_camera_tracker_gives_the_registered_pose_when_the_fit_diverges(learned):
    model, registered, _, _ = learned
    observed = _observations(registered)
    camera = _camera_tracker(model)
    with pytest.raises(ValueError, match='no registered frame'):
        camera.track(1, observed[1])
    camera.registered(0, registered[0])
    for frame in range(1, 8):
        assert camera.track(frame, observed[frame])[1] == 'fitted'
    # a bone out of view is carried by the joint term and the whole-body move: not a loss
    child = int(np.flatnonzero(model.parents >= 0)[0])
    assert camera.track(8, registered[8][np.asarray(model.labels) != child])[1] == 'fitted'
    # clutter where the subject was: no pose explains it
    clutter = np.random.default_rng(3).uniform(-1.0, 1.0, size=(800, 3))
    positions, outcome = camera.track(9, clutter)
    assert outcome == 'lost'
    np.testing.assert_allclose(positions, camera.fit.track(registered[0]), atol=1e-12)
    assert camera.track(10, observed[10])[1] == 'fitted'
    camera.registered(12, registered[12])
    camera.registered(11, registered[11])           # older than the newest taken: ignored
    positions, outcome = camera.track(12, observed[12])
    assert outcome == 'registered'
    np.testing.assert_allclose(positions, camera.fit.track(registered[12]), atol=1e-12)
    assert camera.counts == {'fitted': 9, 'chained': 0, 'lost': 1, 'registered': 1, 'reposed': 0}
    # the posed model (where the registration may start) only after a fitted frame
    assert camera.posed_points() is None
    camera.track(13, observed[13])
    rotations, translations = camera.tracker._history[-1]
    np.testing.assert_allclose(camera.posed_points(), camera.fit.deform(rotations, translations), atol=1e-12)
    assert camera.posed_points().shape == registered[13].shape


def test_the_camera_period_is_the_median_interval_of_the_stamps():
    """The joint node's deadline for a camera frame: its period from the stamps, a dropped
    frame (a double interval), a repeated stamp and one going backwards left out of it."""
    from skel_extract_ros.nodes.joint_stages import camera_period
    assert camera_period([]) is None and camera_period([5]) is None
    stamps = [0, 33_000_000, 66_000_000, 132_000_000, 132_000_000, 100_000_000, 133_000_000, 166_000_000]
    assert camera_period(stamps) == 0.033

