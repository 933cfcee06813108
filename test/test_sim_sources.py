"""The real rig (cow) and the captured mesh sequence (samba) as simulator subjects; skipped
when the shared data directory (SKEL_SHARED_DATA) is absent."""
import os
from pathlib import Path

import numpy as np
import pytest

from skel_extract_ros.sim.mesh_sequence import MeshSequenceError, load_mesh_sequence
from skel_extract_ros.sim.rig import RigError, _read_obj, _skin, bone_tree, load_rig, rig_body

DATA = Path(os.environ.get('SKEL_SHARED_DATA', Path(__file__).resolve().parents[2] / 'shared' / 'data'))
COW = DATA / 'rigs' / 'cow'
SAMBA = DATA / 'samba_mesh_sequence.npz'
needs_cow = pytest.mark.skipif(not (COW / 'cow.tgf').is_file(), reason=f'no cow rig in {COW}')
needs_samba = pytest.mark.skipif(not SAMBA.is_file(), reason=f'no {SAMBA}')


@pytest.fixture(scope='module')
def cow():
    return load_rig(COW)


@needs_cow
def test_the_rig_reads_and_its_key_poses_reproduce_the_posed_meshes(cow):
    assert cow.vertices.shape == (11666, 3) and cow.bones.shape == (15, 2) and len(cow.joints) == 16
    np.testing.assert_allclose(cow.weights.sum(axis=1), 1.0, atol=1e-3)
    size = np.ptp(cow.vertices, axis=0).max()
    for k, pose in enumerate(cow.poses, start=1):
        posed, _ = _read_obj(COW / f'cow-{k}.obj')
        assert np.abs(_skin(cow, pose[None])[0] - posed).max() < 1e-3 * size   # file precision
    parents = bone_tree(cow)
    assert (parents < 0).sum() == 1
    assert len(np.flatnonzero(parents == int(np.flatnonzero(parents < 0)[0]))) >= 3   # legs, neck, hips


@needs_cow
def test_the_blended_rig_moves_smoothly_through_its_key_poses(cow):
    body = rig_body(cow, 90, seed=0)
    vertices = body.skin.vertices
    assert vertices.shape == (90, 11666, 3)
    assert np.ptp(vertices[0], axis=0).max() == pytest.approx(2.0) and abs(vertices[0][:, 1].min()) < 1e-9
    steps = np.linalg.norm(np.diff(vertices, axis=0), axis=2).max(axis=1)
    assert steps.max() < 0.1                                  # no jumps (2 m animal, 30 Hz)
    scale = 2.0 / np.ptp(cow.vertices, axis=0).max()
    offset = -np.array([cow.vertices[:, 0].mean(), cow.vertices[:, 1].min(), cow.vertices[:, 2].mean()])
    for k in (1, 2):
        posed, _ = _read_obj(COW / f'cow-{k}.obj')
        error = np.abs(vertices - ((posed + offset) * scale)[None]).max(axis=(1, 2))
        assert error.min() < 1e-3, f'key pose {k} never reached ({error.min():.3f} m)'
    # every ground-truth joint is the origin of its bone, and bones stay connected
    joints = body.joints
    assert joints.shape == (90, 10, 3) and (body.joint_parents[1:] >= 0).all() and body.joint_parents[0] == -1
    transforms = body.bone_transforms
    for bone, parent in enumerate(body.bone_parents):
        if parent >= 0 and cow.bones[bone, 0] == cow.bones[parent, 1]:
            # the child's origin is the parent's end joint, carried by the parent
            end = (cow.joints[cow.bones[parent, 1]] - cow.joints[cow.bones[parent, 0]]) * scale
            carried = np.einsum('fij,j->fi', transforms[:, parent, :3, :3], end) + transforms[:, parent, :3, 3]
            np.testing.assert_allclose(carried, transforms[:, bone, :3, 3], atol=1e-9)


def test_bad_rigs_are_one_clear_error(tmp_path):
    with pytest.raises(RigError, match='does not exist'):
        load_rig(tmp_path / 'none')
    (tmp_path / 'a.tgf').write_text('1 0 0 0\n2 0 1 0\n#\n1 2\n')
    with pytest.raises(RigError, match='a.obj is missing'):
        load_rig(tmp_path)
    (tmp_path / 'a.obj').write_text('v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n')
    (tmp_path / 'a.DMAT').write_text('1 2\n1 1\n')
    with pytest.raises(RigError, match='weights are 2 x 1, the rig has 3 vertices'):
        load_rig(tmp_path)
    (tmp_path / 'a.DMAT').write_text('1 3\n1 1 1\n')
    with pytest.raises(RigError, match='no key pose'):
        load_rig(tmp_path)
    (tmp_path / 'a-1.Tmat').write_text('1 0 0\n')
    with pytest.raises(RigError, match='4 x 3 numbers'):
        load_rig(tmp_path)


@needs_samba
def test_the_captured_mesh_sequence_faces_the_camera():
    body = load_mesh_sequence(SAMBA, frames=30)
    assert body.n_frames == 30 and len(body.joint_names) == 0 and body.bone_transforms.shape == (30, 0, 4, 4)
    vertices = body.skin.vertices
    assert abs(vertices[0][:, 1].min()) < 1e-9 and 1.5 < np.ptp(vertices[0][:, 1]) < 2.0
    # the performer faces +z: the toes are in front of the heels (+z), i.e. the lowest
    # vertices reach farther towards +z than towards -z from the ankles' centre
    feet = vertices[0][vertices[0][:, 1] < 0.05]
    centre = vertices[0][vertices[0][:, 1] < 0.15].mean(axis=0)
    assert feet[:, 2].max() - centre[2] > centre[2] - feet[:, 2].min()
    with pytest.raises(MeshSequenceError, match='does not exist'):
        load_mesh_sequence(SAMBA.parent / 'missing.npz')


@needs_cow
def test_cli_simulates_the_rig_and_the_mesh_sequence(tmp_path):
    from conftest import run_cli
    done = run_cli('simulate', '--rig', COW, '--frames', '6', '--scene', 'floor', '--out', tmp_path / 'cow')
    assert done.returncode == 0, done.stderr
    gt = np.load(tmp_path / 'cow' / 'gt.npz')
    assert gt['joints'].shape == (6, 10, 3) and gt['surface_faces'].shape[1] == 3
    assert gt['surface_points'].shape == (6, 11666, 3) and gt['subject_mask'].sum(axis=(1, 2)).min() > 2000
    if SAMBA.is_file():
        done = run_cli('simulate', '--mesh-sequence', SAMBA, '--frames', '4', '--out', tmp_path / 'samba')
        assert done.returncode == 0, done.stderr
        assert '0 ground-truth joints' in done.stdout
