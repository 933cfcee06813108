"""A hand-made articulated case with exact ground truth, shared by several tests."""
import numpy as np
from scipy.spatial.transform import Rotation


def two_bone_sequence(n_frames=30, noise=0.0, seed=0):
    """A bent cylinder pair: bone 0 along -x, bone 1 along +x, joint at the origin.

    Bone 0 sways rigidly; bone 1 rotates about the joint on two axes on top of it.
    Returns rest (M, 3), registered (F, M, 3), true labels, true joint (3,), per-frame joint.
    """
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 2 * np.pi, 1200)
    along = rng.uniform(0.0, 0.3, 1200)
    side = np.where(np.arange(1200) < 600, -1.0, 1.0)
    rest = np.column_stack([side * (along + 0.005), 0.04 * np.cos(t), 0.04 * np.sin(t)])
    labels = (side > 0).astype(int)
    joint = np.zeros(3)
    frames, joints = [], []
    for f in range(n_frames):
        phase = 2 * np.pi * f / n_frames
        base = Rotation.from_rotvec([0.1 * np.sin(phase), 0.2 * np.cos(phase), 0.05]).as_matrix()
        shift = np.array([0.02 * np.sin(phase), 0.01, 0.0])
        bend = Rotation.from_rotvec([0.3 * np.sin(2 * phase), 0.6 * np.sin(phase), 0.8 * np.cos(phase)]).as_matrix()
        moved = rest @ base.T + shift
        moved[labels == 1] = (rest[labels == 1] @ bend.T) @ base.T + shift
        frames.append(moved + rng.normal(scale=noise, size=moved.shape))
        joints.append(base @ joint + shift)
    return rest, np.array(frames), labels, joint, np.array(joints)
