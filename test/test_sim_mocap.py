"""Real motion in the simulator: the BVH reader, the body put on a skeleton, the choice of
window, the scenes and late entry."""
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from skel_extract_ros.sim.bvh import BvhError, load_bvh
from skel_extract_ros.sim.mocap_body import body_part, limb_motion, mocap_body, most_active_start
from skel_extract_ros.sim.sources import simulate_mocap

from conftest import SHARED_DATA

MOCAP = SHARED_DATA / 'mocap'
CLIPS = sorted(MOCAP.glob('*.bvh'))
needs_mocap = pytest.mark.skipif(not CLIPS, reason=f'no BVH clips in {MOCAP}')

# A small person in centimetres: ground root, hips, spine, head, one arm, one leg.
HIERARCHY = """HIERARCHY
ROOT Root
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Hips
  {
    OFFSET 0 95 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Spine
    {
      OFFSET 0 20 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      JOINT Head
      {
        OFFSET 0 35 0
        CHANNELS 3 Zrotation Xrotation Yrotation
        End Site
        {
          OFFSET 0 0 0
        }
      }
      JOINT LeftArm
      {
        OFFSET 18 30 0
        CHANNELS 3 Zrotation Xrotation Yrotation
        JOINT LeftForeArm
        {
          OFFSET 28 0 0
          CHANNELS 3 Zrotation Xrotation Yrotation
          JOINT LeftHand
          {
            OFFSET 25 0 0
            CHANNELS 3 Zrotation Xrotation Yrotation
            End Site
            {
              OFFSET 0 0 0
            }
          }
        }
      }
    }
    JOINT LeftUpLeg
    {
      OFFSET 10 -5 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      JOINT LeftLeg
      {
        OFFSET 0 -42 0
        CHANNELS 3 Zrotation Xrotation Yrotation
        JOINT LeftFoot
        {
          OFFSET 0 -42 0
          CHANNELS 3 Zrotation Xrotation Yrotation
          End Site
          {
            OFFSET 0 -5 12
          }
        }
      }
    }
  }
}
"""
N_CHANNELS = 6 + 3 * 9


def write_bvh(path, elbow_degrees, root_x_cm=None):
    """A clip whose only motion is the elbow (LeftForeArm Z rotation) per frame."""
    frames = np.zeros((len(elbow_degrees), N_CHANNELS))
    frames[:, 6 + 3 * 4] = elbow_degrees          # LeftForeArm Zrotation
    if root_x_cm is not None:
        frames[:, 0] = root_x_cm
    lines = [HIERARCHY, 'MOTION', f'Frames: {len(frames)}', 'Frame Time: 0.0333333']
    lines += [' '.join(f'{v:.4f}' for v in row) for row in frames]
    Path(path).write_text('\n'.join(lines) + '\n')
    return path


def test_forward_kinematics_and_units(tmp_path):
    clip = load_bvh(write_bvh(tmp_path / 'a.bvh', [0.0, 90.0]))
    assert clip.unit_scale == 0.01 and clip.n_frames == 2
    names = clip.joint_names
    hand, fore = names.index('LeftHand'), names.index('LeftForeArm')
    # Frame 0 is the rest pose: offsets added up, in metres.
    np.testing.assert_allclose(clip.positions[0, hand], [0.71, 1.45, 0.0], atol=1e-4)
    # 90 degrees about z at the elbow turns the forearm from +x to +y.
    np.testing.assert_allclose(clip.positions[1, hand], clip.positions[1, fore] + [0.0, 0.25, 0.0], atol=1e-4)
    # Joint frames are rigid with their segments: the hand stays put in the forearm's frame.
    local = [clip.world_transforms[f, fore, :3, :3].T @ (clip.positions[f, hand] - clip.positions[f, fore])
             for f in range(2)]
    np.testing.assert_allclose(local[0], local[1], atol=1e-6)
    # The end site (toe) of the foot is kept in the foot's frame.
    foot = names.index('LeftFoot')
    toe = clip.world_transforms[0, foot, :3, :3] @ clip.end_sites[foot] + clip.positions[0, foot]
    np.testing.assert_allclose(toe - clip.positions[0, foot], [0.0, -0.05, 0.12], atol=1e-6)


@pytest.mark.parametrize('edit, message', [
    (lambda text: text.rsplit('\n', 2)[0] + '\n', 'truncated MOTION block'),
    (lambda text: text.replace('Frames: 2', 'Frames: 2').rstrip('\n') + ' 1.0\n', 'declares 33 channels'),
    (lambda text: text.replace('MOTION', 'MOTOIN'), 'no MOTION block'),
    (lambda text: 'hello\n' + text, 'not a BVH file'),
    (lambda text: text.replace('Frame Time: 0.0333333', 'Frame Time: x'), 'Frame Time'),
])
def test_malformed_bvh_is_one_clear_error(tmp_path, edit, message):
    path = write_bvh(tmp_path / 'bad.bvh', [0.0, 10.0])
    path.write_text(edit(path.read_text()))
    with pytest.raises(BvhError, match=message):
        load_bvh(path)
    done = run_cli('simulate', '--bvh', path, '--out', tmp_path / 'out')
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('skel-extract: error:') and message in lines[0]
    with pytest.raises(BvhError, match='does not exist'):
        load_bvh(tmp_path / 'missing.bvh')


def test_body_parts_by_name():
    assert [body_part(n) for n in ('Hips', 'Spine1', 'LowerBack', 'mixamorig:Neck', 'Head',
                                   'LeftShoulder', 'UpperArm_R', 'LeftForeArm', 'Hand_L',
                                   'LeftUpLeg', 'UpperLeg_L', 'LowerLeg_R', 'LeftLeg', 'Foot_L',
                                   'Toes_R', 'tail_03')] == \
        ['pelvis', 'chest', 'spine', 'neck', 'head', 'clavicle', 'upper_arm', 'forearm', 'hand',
         'thigh', 'thigh', 'shin', 'shin', 'foot', 'toe', 'limb']


def test_body_covers_every_segment_and_leaves_out_the_ground_root(tmp_path):
    clip = load_bvh(write_bvh(tmp_path / 'a.bvh', np.linspace(0, 90, 10)))
    body = mocap_body(clip)
    assert 'Root' not in body.joint_names and body.joint_names[0] == 'Hips'
    assert body.joint_parents[0] == -1 and (body.joint_parents[1:] >= 0).all()
    bones_with_shapes = {part.bone for part in body.parts}
    # every joint carries a shape: leaves too (head, hand, foot from its end site)
    assert bones_with_shapes == set(range(len(body.joint_names)))
    # every segment between a joint and its child runs inside the body
    for frame in (0, 9):
        vertices = np.concatenate([v for v, _ in body.world_meshes(frame)])
        joints = body.joints[frame]
        for child, parent in enumerate(body.joint_parents):
            if parent < 0:
                continue
            midpoint = (joints[child] + joints[parent]) / 2.0
            assert np.linalg.norm(vertices - midpoint, axis=1).min() < 0.12
    # the hand continues the forearm: its shape lies beyond the wrist, along the forearm
    hand = body.joint_names.index('LeftHand')
    hand_vertices = np.concatenate([p.vertices for p in body.parts if p.bone == hand])
    centre = body.bone_transforms[0, hand, :3, :3] @ hand_vertices.mean(axis=0)
    assert centre[0] > 0.05 and abs(centre[1]) < 0.02


def test_window_with_the_most_limb_motion(tmp_path):
    elbow = np.zeros(200)
    elbow[120:150] = 60.0 * np.sin(np.linspace(0, 3 * np.pi, 30)) ** 2   # waves in frames 120-149
    clip = load_bvh(write_bvh(tmp_path / 'a.bvh', elbow, root_x_cm=np.linspace(0, 300, 200)))
    body = mocap_body(clip)
    motion = limb_motion(body)
    assert motion[:110].max() < 1e-6       # walking sideways alone is no limb motion
    start = most_active_start(body, 60)
    assert start <= 120 and start + 60 >= 150
    assert most_active_start(body, 500) == 0


def test_simulated_clip_in_a_room_and_walking_in(tmp_path):
    elbow = 50.0 * (1 - np.cos(np.linspace(0, 4 * np.pi, 30)))
    path = write_bvh(tmp_path / 'a.bvh', elbow)
    empty = simulate_mocap(path, frames=30, progress=False)
    room = simulate_mocap(path, frames=30, scene='room', progress=False)
    gt = room.ground_truth
    assert gt['joints'].shape == (30, len(gt['joint_names']), 3)
    # the mask is exactly the subject's pixels: the same in both scenes, a few thousand
    np.testing.assert_array_equal(gt['subject_mask'], empty.ground_truth['subject_mask'])
    assert 500 < gt['subject_mask'][0].sum() < 10000
    assert room.points_per_frame().min() > 10 * empty.points_per_frame().max()
    # the room touches nothing: every valid pixel outside the mask is farther than the
    # subject's depth range or clearly beside it
    walk_in = simulate_mocap(path, frames=30, scene='room', enter_frames=15, progress=False)
    visible = walk_in.ground_truth['subject_mask'].sum(axis=(1, 2))
    assert visible[0] == 0 and visible[-1] == gt['subject_mask'][-1].sum()
    assert (np.diff(visible[:16]) >= -50).all()


@needs_mocap
def test_every_shared_clip_reads_with_15_or_more_body_joints():
    required = {'pelvis', 'chest', 'neck', 'head', 'upper_arm', 'forearm', 'hand', 'thigh', 'shin', 'foot'}
    for path in CLIPS:
        clip = load_bvh(path)
        body = mocap_body(clip)
        parts = {body_part(n) for n in body.joint_names}
        assert len(body.joint_names) >= 15 and required <= parts, path.name
        assert clip.unit_scale == 0.01 and clip.frame_time == pytest.approx(1 / 30, rel=1e-3)
        # a person: 1-2 m from the lowest to the highest joint at the first frame (a runner leans)
        height = np.ptp(body.joints[0, :, 1])
        assert 1.0 < height < 2.0, (path.name, height)


@needs_mocap
def test_cli_simulates_a_shared_clip_with_ground_truth(tmp_path):
    clip = next(p for p in CLIPS if 'wave-right' in p.name)
    done = run_cli('simulate', '--bvh', clip, '--frames', '20', '--scene', 'floor', '--out', tmp_path / 'bag')
    assert done.returncode == 0, done.stderr
    gt = np.load(tmp_path / 'bag' / 'gt.npz')
    assert gt['joints'].shape == (20, 21, 3) and gt['bone_transforms'].shape == (20, 21, 4, 4)
    assert gt['surface_points'].shape[0] == 20 and len(gt['surface_bone_ids']) == gt['surface_points'].shape[1]
    assert 'source frames' in done.stdout and '21 ground-truth joints' in done.stdout
