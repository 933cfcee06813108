"""The synthetic subjects, their motion and the virtual depth camera."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from skel_extract_ros.sim import SUBJECTS, DepthCamera, Intrinsics, NoiseModel, generate_sequence, make_subject

EXPECTED_JOINTS = {'human': 15, 'upper_body': 8, 'arm': 2, 'hand': 15, 'fish': 5}


@pytest.mark.parametrize('name', sorted(SUBJECTS))
def test_every_subject_renders_and_every_joint_moves(name):
    seq = generate_sequence(name, 30, seed=1, progress=False)
    gt = seq.ground_truth
    frames, joints = gt['joints'].shape[:2]
    assert frames == 30 and joints == EXPECTED_JOINTS[name]
    assert len(gt['joint_names']) == joints and len(gt['joint_parents']) == joints
    # every joint moves relative to its parent bone's joint, i.e. it articulates (not just
    # carried along by the root sway): the joint's angle changes.
    transforms = gt['bone_transforms']
    for b in gt['joint_bones']:
        rotations = transforms[:, b, :3, :3]
        parent_rotations = transforms[:, int(gt['bone_parents'][b]), :3, :3]
        local = np.einsum('fji,fjk->fik', parent_rotations, rotations)
        angle = np.arccos(np.clip((np.trace(local[0].T @ local[1:], axis1=1, axis2=2) - 1) / 2, -1, 1))
        assert angle.max() > 0.1, f'{name}: joint of bone {b} barely moves ({angle.max():.3f} rad)'
    counts = seq.points_per_frame()
    assert counts.min() > 1000, f'{name}: too few points {counts.min()}'
    # organized clouds at the requested resolution, NaN where nothing is hit
    assert seq.clouds[0].shape == (240, 320, 3)
    assert np.isnan(seq.clouds[0][0, 0]).all()


def test_human_has_at_least_15_joints_and_is_upright_in_optical_frame(human_clean):
    gt = human_clean.ground_truth
    names = list(gt['joint_names'])
    assert len(names) >= 15
    neck, ankle = names.index('neck'), names.index('l_ankle')
    # optical frame: y points down, so the neck has a smaller y than the ankle; z forward.
    assert gt['joints'][0, neck, 1] < gt['joints'][0, ankle, 1] - 1.0
    assert 1.8 < gt['joints'][0, :, 2].mean() < 3.0


def test_seeded_sequences_repeat_and_differ_by_seed():
    a = generate_sequence('fish', 5, seed=11, progress=False)
    b = generate_sequence('fish', 5, seed=11, progress=False)
    c = generate_sequence('fish', 5, seed=12, progress=False)
    np.testing.assert_array_equal(a.clouds[3], b.clouds[3])
    assert not np.allclose(a.ground_truth['joints'], c.ground_truth['joints'])


def test_noise_free_points_lie_on_the_visible_surface_only(human_clean):
    """Every observed point is on the true surface, and the far side is not observed."""
    gt = human_clean.ground_truth
    surface = gt['surface_points'][5].astype(np.float64)
    points = human_clean.clouds[5].reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    distance, _ = cKDTree(surface).query(points)
    assert np.median(distance) < 0.02  # surface samples are ~2-3 cm apart
    # self-occlusion: surface samples farther than the observed surface along their ray
    # (the back of the body) have no observed point near them.
    seen, _ = cKDTree(points).query(surface)
    back = surface[:, 2] > np.median(surface[:, 2]) + 0.08
    assert back.sum() > 50
    assert np.median(seen[back]) > 2 * np.median(seen[~back])


def test_axial_noise_and_quantisation_follow_the_kinect_model():
    rng = np.random.default_rng(0)
    depth = np.full((200, 200), 2.0)
    axial = NoiseModel(quantization_disparity=0.0, flying_pixel_probability=0.0,
                       outlier_fraction=0.0, dropout_fraction=0.0)
    noisy = axial.apply(depth, rng)
    expected = 0.0012 + 0.0019 * (2.0 - 0.4) ** 2
    assert abs(np.std(noisy - 2.0) - expected) < 0.1 * expected
    quantised = NoiseModel(axial=False, flying_pixel_probability=0.0, outlier_fraction=0.0,
                           dropout_fraction=0.0).apply(np.linspace(1.9, 2.1, 40000).reshape(200, 200), rng)
    steps = np.diff(np.unique(quantised))
    assert np.allclose(steps, 0.00285 * 2.0 ** 2, rtol=0.1)  # dz = z^2 * d(disparity)


def test_dropouts_outliers_and_flying_pixels():
    rng = np.random.default_rng(1)
    depth = np.full((100, 100), np.nan)
    depth[20:80, 20:80] = 1.0
    depth[:, :10] = 3.0
    dropped = NoiseModel(axial=False, quantization_disparity=0.0, flying_pixel_probability=0.0,
                         outlier_fraction=0.0, dropout_fraction=0.2).apply(depth, rng)
    lost = np.isnan(dropped[20:80, 20:80]).mean()
    assert 0.15 < lost < 0.25
    outliers = NoiseModel(axial=False, quantization_disparity=0.0, flying_pixel_probability=0.0,
                          outlier_fraction=0.1, dropout_fraction=0.0).apply(depth, rng)
    assert 0.07 < (np.abs(outliers[20:80, 20:80] - 1.0) > 1e-9).mean() < 0.13
    flying = NoiseModel(axial=False, quantization_disparity=0.0, flying_pixel_probability=1.0,
                        outlier_fraction=0.0, dropout_fraction=0.0).apply(depth, rng)
    changed = np.abs(flying - depth) > 1e-9
    # only pixels on depth edges move (the square's rim, the strip's rim), and backwards
    assert changed[20:80, 20:80].sum() > 0
    assert not changed[22:78, 22:78].any() and not changed[1:99, 1:9].any()
    assert (flying[changed] > depth[changed]).all()


def test_scenes_add_floor_and_room_but_never_cover_the_subject():
    plain = generate_sequence('human', 1, seed=2, progress=False, noise=NoiseModel.none())
    floor = generate_sequence('human', 1, seed=2, progress=False, noise=NoiseModel.none(), scene='floor')
    room = generate_sequence('human', 1, seed=2, progress=False, noise=NoiseModel.none(), scene='room')
    assert floor.points_per_frame()[0] > 3 * plain.points_per_frame()[0]
    assert room.points_per_frame()[0] > floor.points_per_frame()[0]
    mask = plain.ground_truth['subject_mask'][0]
    # the subject mask is where the empty scene sees anything; rooms leave it untouched
    np.testing.assert_array_equal(mask, np.isfinite(plain.clouds[0][..., 2]))
    for seq in (floor, room):
        np.testing.assert_array_equal(seq.ground_truth['subject_mask'][0], mask)
        np.testing.assert_array_equal(seq.clouds[0][mask], plain.clouds[0][mask])
    with pytest.raises(ValueError, match='unknown scene'):
        generate_sequence('arm', 1, scene='garden', progress=False)


def test_640x480_intrinsics_and_back_projection():
    intrinsics = Intrinsics.from_resolution('640x480')
    camera = DepthCamera(intrinsics)
    depth = np.full((480, 640), 2.0)
    points = camera.back_project(depth)
    assert points.shape == (480, 640, 3)
    np.testing.assert_allclose(points[240, 320], [(320 - 319.5) * 2 / 525, (240 - 239.5) * 2 / 525, 2.0], atol=1e-6)
    with pytest.raises(ValueError, match='unknown resolution'):
        Intrinsics.from_resolution('100x100')


def test_unknown_subject_is_a_clear_error():
    with pytest.raises(ValueError, match='unknown subject'):
        make_subject('dragon')


def test_one_limb_at_a_time_moves_each_limb_in_its_own_slot():
    from skel_extract_ros.sim.motion import limb_activity, limb_groups
    from skel_extract_ros.sim.subjects import make_subject
    human = make_subject('human')
    groups = limb_groups(human)
    names = {bone.name: g for bone, g in zip(human.bones, groups)}
    # an arm is one limb from shoulder to hand, apart from the other arm, the head and the legs
    assert names['l_upper_arm'] == names['l_forearm'] == names['l_hand'] != names['r_upper_arm']
    assert len({names['head'], names['l_upper_arm'], names['r_upper_arm'], names['l_thigh'], names['r_thigh']}) == 5
    assert names['pelvis'] == -1
    times = np.arange(300) / 30.0
    activity = limb_activity(human, times)
    limbs = np.unique(groups[groups >= 0])
    per_limb = np.stack([activity[:, groups == limb].max(axis=1) for limb in limbs], axis=1)   # (F, L)
    assert (activity[:, groups < 0] == 1).all()                 # the root always sways
    assert (np.sum(per_limb > 0, axis=1) <= 1).all()             # never two limbs at once
    assert (per_limb.max(axis=0) == 1).all()                     # every limb gets its full slot
    # and the rendered motion follows: a leg bone does not turn while the arms have their turn
    sequence = generate_sequence('human', 300, progress=False, one_limb_at_a_time=True, surface_samples=200)
    transforms = sequence.ground_truth['bone_transforms'][:, :, :3, :3]
    thigh, pelvis = human.bone_names.index('l_thigh'), 0
    relative = np.einsum('fji,fjk->fik', transforms[:, pelvis], transforms[:, thigh])
    idle = per_limb[:, list(limbs).index(names['l_thigh'])] == 0
    assert np.ptp(relative[idle].reshape(idle.sum(), -1), axis=0).max() < 1e-5     # float32 ground truth
    assert np.ptp(relative[~idle].reshape((~idle).sum(), -1), axis=0).max() > 0.2
