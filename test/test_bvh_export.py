"""skeleton.bvh (skel_extract_ros/app/bvh_export.py), read back with bvhio, the BVH library the
simulator uses: a synthetic branching skeleton with known motion, the sample bag's
`skel-extract run` output, and bad input."""
import json

import bvhio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skel_extract_ros.app.bvh_export import skeleton_motion, write_skeleton_bvh

from conftest import check_bvh_joints

# root 2 with three chains of two: 2 -> 0 -> 1, 2 -> 3 -> 4, 2 -> 5 -> 6 (the root is not
# joint 0, so the file order differs from the joint order)
PARENTS = np.array([2, 0, -1, 2, 3, 2, 5])
REST = np.array([[0.00, -0.25, 2.0], [0.00, -0.45, 2.02], [0.0, 0.0, 2.0], [-0.20, -0.20, 2.0],
                 [-0.45, -0.22, 1.98], [0.10, 0.30, 2.0], [0.12, 0.72, 2.05]])
LEAF_TIPS = {1: np.array([0.0, -0.60, 2.02]), 4: np.array([-0.70, -0.20, 1.95]), 6: np.array([0.12, 1.10, 2.1])}
NAMES = [f'joint_{i}' for i in range(7)]
F = 20
GIMBAL = (7, 3)   # frame, joint whose local rotation is Euler ZXY (30, 90, 20): x at +90 deg


def _world(local):
    world = np.empty_like(local)
    for b in (2, 0, 1, 3, 4, 5, 6):
        world[:, b] = local[:, b] if PARENTS[b] < 0 else world[:, PARENTS[b]] @ local[:, b]
    return world


def _motion():
    """(local rotations (F, J, 3, 3), world rotations, root positions (F, 3), joint
    positions (F, J, 3)) of a known motion: smooth rotations up to about 70 deg per joint."""
    t = np.linspace(0.0, 1.0, F)[:, None]
    rng = np.random.default_rng(5)
    axes, phases = rng.normal(size=(7, 3)), rng.uniform(0, 2 * np.pi, size=7)
    rotvecs = axes[None] / np.linalg.norm(axes, axis=1)[None, :, None] \
        * (1.2 * np.sin(2 * np.pi * t + phases[None]))[..., None]
    local = Rotation.from_rotvec(rotvecs.reshape(-1, 3)).as_matrix().reshape(F, 7, 3, 3)
    local[GIMBAL] = Rotation.from_euler('ZXY', [30, 90, 20], degrees=True).as_matrix()
    world = _world(local)
    root = REST[2] + np.column_stack([0.3 * np.sin(3 * t[:, 0]), 0.1 * t[:, 0], -0.2 * t[:, 0]])
    positions = np.empty((F, 7, 3))
    for b in (2, 0, 1, 3, 4, 5, 6):
        p = PARENTS[b]
        positions[:, b] = root if p < 0 else positions[:, p] + world[:, p] @ (REST[b] - REST[p])
    return local, world, root, positions


def _bone_points(world, positions):
    """Rest points on cylinders around each bone (radius 3 cm, in mirrored pairs, so a
    leaf's centroid is on its axis), their labels, and their registered positions moved
    rigidly with their bone."""
    rng = np.random.default_rng(2)
    points, labels = [], []
    for b in range(7):
        ends = [REST[c] for c in np.flatnonzero(PARENTS == b)] or [LEAF_TIPS[b]]
        for end in ends:
            axis = (end - REST[b]) / np.linalg.norm(end - REST[b])
            s = rng.uniform(0.0, 1.0, 30)[:, None]
            radial = rng.normal(size=(30, 3))
            radial -= (radial @ axis)[:, None] * axis
            radial *= 0.03 / np.linalg.norm(radial, axis=1)[:, None]
            on_axis = REST[b] + s * (end - REST[b])
            points += [on_axis + radial, on_axis - radial]
            labels += [b] * 60
    points, labels = np.concatenate(points), np.array(labels)
    # the leaves' far ends exactly, so the End Site is known: the tip is the farthest point
    for b, tip in LEAF_TIPS.items():
        points = np.vstack([points, tip])
        labels = np.append(labels, b)
    registered = np.einsum('fmij,mj->fmi', world[:, labels], points - REST[labels]) + positions[:, labels]
    return points, labels, registered


def _read_positions(path, names):
    """(F, J, 3) world joint positions by bvhio's forward kinematics, joints in `names` order."""
    root = bvhio.readAsHierarchy(str(path))
    layout = root.layout()
    index = {name: i for i, name in enumerate(names)}
    assert sorted(j.Name for j, _, _ in layout) == sorted(names)
    frames = bvhio.readAsBvh(str(path)).FrameCount
    result = np.full((frames, len(names), 3), np.nan)
    for frame in range(frames):
        root.loadPose(frame)
        for joint, _, _ in layout:
            p = joint.PositionWorld
            result[frame, index[joint.Name]] = (p.x, p.y, p.z)
    return result


def _bvh_joints(path):
    """{name: bvhio.BvhJoint} of the file as bvhio parses it (offsets, channels, keyframes)."""
    return {joint.Name: joint for joint, _, _ in bvhio.readAsBvh(str(path)).Root.layout()}


def test_round_trip_of_a_branching_skeleton_with_known_rotations(tmp_path):
    local, world, root, positions = _motion()
    points, labels, registered = _bone_points(world, positions)
    stamps = 1_700_000_000.0 + 0.04 * np.delete(np.arange(F + 1), 9)    # 25 Hz, one frame dropped
    path = tmp_path / 'skeleton.bvh'
    motion = write_skeleton_bvh(path, NAMES, PARENTS, REST, stamps, positions, points, labels, registered)

    container = bvhio.readAsBvh(str(path))
    assert container.FrameCount == F and container.FrameTime == pytest.approx(0.04, rel=1e-6)
    joints = _bvh_joints(path)
    # the bone tree, the root with position and rotation channels, rest offsets
    assert container.Root.Name == 'joint_2' and len(container.Root.Channels) == 6
    for b, name in enumerate(NAMES):
        children = {c.Name for c in joints[name].Children}
        assert children == {NAMES[c] for c in np.flatnonzero(PARENTS == b)}
        if PARENTS[b] >= 0:
            assert joints[name].Channels == ['Zrotation', 'Xrotation', 'Yrotation']
            np.testing.assert_allclose(list(joints[name].Offset), REST[b] - REST[PARENTS[b]], atol=1e-6)
    # the leaves end at their bone's far end
    for b, tip in LEAF_TIPS.items():
        np.testing.assert_allclose(list(joints[NAMES[b]].EndSite), tip - REST[b], atol=1e-6)

    # bvhio's forward kinematics put every joint where it was, in every frame (gimbal lock included)
    read = _read_positions(path, NAMES)
    error = np.linalg.norm(read - positions, axis=2)
    assert error.max() < 1e-3, error.max()
    assert np.nanmax(motion.deviation) < 1e-6 and not motion.held.any()

    # every joint's rotation is its bone's (relative to the parent bone), twist included:
    # the rotation bvhio builds from the file's Euler channels is the known local rotation
    for b, name in enumerate(NAMES):
        for frame in range(F):
            q = joints[name].Keyframes[frame].Rotation
            read_rotation = Rotation.from_quat([q.x, q.y, q.z, q.w])
            angle = (read_rotation.inv() * Rotation.from_matrix(local[frame, b])).magnitude()
            assert np.degrees(angle) < 0.01, (name, frame, np.degrees(angle))


def test_without_points_the_positions_still_round_trip_and_the_twist_follows_the_parent(tmp_path):
    local, world, root, positions = _motion()
    path = tmp_path / 'skeleton.bvh'
    motion = write_skeleton_bvh(path, NAMES, PARENTS, REST, np.arange(F) / 30.0, positions)
    assert np.linalg.norm(_read_positions(path, NAMES) - positions, axis=2).max() < 1e-3
    # a leaf turns with its parent: identity local rotation, End Site continuing the bone
    joints = _bvh_joints(path)
    for b in LEAF_TIPS:
        np.testing.assert_allclose(motion.local_rotations[:, b], np.broadcast_to(np.eye(3), (F, 3, 3)), atol=1e-9)
        np.testing.assert_allclose(list(joints[NAMES[b]].EndSite), REST[b] - REST[PARENTS[b]], atol=1e-6)
    # and a joint with one child does not twist about it relative to its parent: the
    # local rotation is the smallest turning the rest offset onto the frame's
    for b in (0, 3, 5):
        child = int(np.flatnonzero(PARENTS == b)[0])
        rest = REST[child] - REST[b]
        angles = Rotation.from_matrix(motion.local_rotations[:, b]).magnitude()
        current = np.einsum('fji,fj->fi', world[:, PARENTS[b]], positions[:, child] - positions[:, b])
        smallest = np.arccos(np.clip(current @ rest / (np.linalg.norm(current, axis=1) * np.linalg.norm(rest)),
                                     -1, 1))
        np.testing.assert_allclose(angles, smallest, atol=1e-6)


def test_sample_run_writes_a_bvh_that_reproduces_skeleton_json(sample_run):
    """`skel-extract run` on the sample bag: skeleton.bvh has skeleton.json's joints and
    frames; read back with bvhio (and with the simulator's BVH loader) its joints are where
    skeleton.json's are, up to the bones' length changes a BVH cannot hold
    (conftest.check_bvh_joints)."""
    from skel_extract_ros.sim.bvh import load_bvh

    done, out = sample_run
    assert done.returncode == 0, done.stderr
    assert str(out / 'skeleton.bvh') in done.stdout
    skeleton = json.loads((out / 'skeleton.json').read_text())
    names, parents = skeleton['joint_names'], skeleton['parents']
    positions = np.array([f['positions'] for f in skeleton['frames']], dtype=np.float64)
    stamps = [f['stamp'] for f in skeleton['frames']]
    container = bvhio.readAsBvh(str(out / 'skeleton.bvh'))
    assert container.FrameCount == len(positions) == 59
    assert container.FrameTime == pytest.approx(np.median(np.diff(stamps)), rel=1e-6)
    joints = _bvh_joints(out / 'skeleton.bvh')
    for b, name in enumerate(names):
        assert {c.Name for c in joints[name].Children} == {names[c] for c in range(len(names)) if parents[c] == b}
    error = check_bvh_joints(_read_positions(out / 'skeleton.bvh', names), skeleton)
    # the simulator's loader takes it as metres and gets the same joints as bvhio
    clip = load_bvh(out / 'skeleton.bvh')
    assert clip.unit_scale == 1.0 and clip.n_frames == 59
    order = [clip.joint_names.index(name) for name in names]
    np.testing.assert_allclose(np.linalg.norm(clip.positions[:, order] - positions, axis=2), error, atol=1e-4)


def test_no_frames_gives_the_skeleton_alone(tmp_path):
    path = tmp_path / 'skeleton.bvh'
    motion = write_skeleton_bvh(path, NAMES, PARENTS, REST, np.empty(0), np.empty((0, 7, 3)))
    assert motion.n_frames == 0
    container = bvhio.readAsBvh(str(path))
    assert container.FrameCount == 0 and container.FrameTime == pytest.approx(1 / 30)
    assert len(container.Root.layout()) == 7
    hierarchy = bvhio.readAsHierarchy(str(path))   # the rest pose is the rest joints
    positions = {j.Name: j.PositionWorld for j, _, _ in hierarchy.layout()}
    for b in range(7):
        p = positions[NAMES[b]]
        np.testing.assert_allclose([p.x, p.y, p.z], REST[b] - REST[2], atol=1e-6)


def test_non_finite_joints_hold_the_previous_pose_and_missing_points_lose_only_the_twist(tmp_path):
    local, world, root, positions = _motion()
    points, labels, registered = _bone_points(world, positions)
    positions[0, 4] = np.nan          # a leading frame with one joint unknown
    positions[5] = np.nan             # a whole frame unknown
    registered[9] = np.nan            # no registered points: no twist hint in frame 9
    path = tmp_path / 'skeleton.bvh'
    motion = write_skeleton_bvh(path, NAMES, PARENTS, REST, np.arange(F) / 30.0, positions, points, labels,
                                registered)
    text = path.read_text()
    assert 'nan' not in text.lower() and 'inf' not in text.lower()
    assert list(np.flatnonzero(motion.held)) == [0, 5]
    read = _read_positions(path, NAMES)
    expected = _motion()[3]
    good = ~motion.held
    assert np.linalg.norm(read[good] - positions[good], axis=2).max() < 1e-3
    np.testing.assert_allclose(read[0], expected[1], atol=1e-3)     # the first finite frame
    np.testing.assert_allclose(read[5], expected[4], atol=1e-3)     # the frame before
    motion_lines = text.split('Frame Time:')[1].strip().splitlines()[1:]
    assert motion_lines[5] == motion_lines[4] and motion_lines[0] == motion_lines[1]
    # frame 9 without points: a leaf falls back to its parent's rotation, the others keep theirs
    np.testing.assert_allclose(motion.local_rotations[9, 1], np.eye(3), atol=1e-9)
    np.testing.assert_allclose(motion.local_rotations[8, 1], local[8, 1], atol=1e-6)


def test_every_frame_unknown_is_the_rest_pose_and_mismatched_points_are_ignored(tmp_path):
    positions = np.full((4, 7, 3), np.nan)
    motion = skeleton_motion(NAMES, PARENTS, REST, np.arange(4) / 30.0, positions,
                             rest_points=np.zeros((10, 3)), labels=np.zeros(11, dtype=int),
                             registered=np.zeros((4, 10, 3)))
    assert motion.held.all() and np.isnan(motion.deviation).all()
    np.testing.assert_allclose(motion.forward_kinematics(), np.broadcast_to(REST, (4, 7, 3)), atol=1e-12)
    with pytest.raises(ValueError, match='stamps'):
        skeleton_motion(NAMES, PARENTS, REST, np.arange(3), positions)
    with pytest.raises(ValueError, match='one root'):
        skeleton_motion(NAMES, np.array([-1, 0, -1, 2, 3, 2, 5]), REST, np.arange(4), positions)
