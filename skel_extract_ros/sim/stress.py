"""Stress motions for the registration, with ground truth: what real people do and smooth
sines do not.

`swing_body`: a torso with a head and one arm (upper arm, forearm with the hand) that hangs
beside the torso, a few centimetres from it (so a deformation graph built on the first
frame ties arm and torso together), then
  1. swings up sideways by 85 degrees in `swing_frames` frames (4: the hand moves 22 cm a
     frame at 30 Hz, a fast wave or a punch; 12: 7 cm a frame, an ordinary raise),
  2. holds, then sweeps horizontally forward and across in front of the chest (the torso
     is hidden behind the arm), and back out,
  3. holds again.
`swing_phases` gives the frame ranges, so a test can ask "recovered within 3 frames of the
swing" and "the torso stays put while the arm passes in front of it".
World convention as `animated.py`: metres, y up, the body facing +z.
"""
from __future__ import annotations

import numpy as np

from .animated import AnimatedBody, RigidPart
from .meshes import capsule_mesh, ellipsoid_mesh

UPPER_ARM_M = 0.30
FOREARM_M = 0.30            # elbow to fingertips
SHOULDER = np.array([0.22, 1.42, 0.0])


def swing_phases(swing_frames: int = 4) -> dict:
    """Frame ranges [start, stop) of the phases: rest, swing, hold, across, after."""
    swing_end = 5 + swing_frames
    return {'rest': (0, 5), 'swing': (5, swing_end), 'hold': (swing_end, swing_end + 5),
            'across': (swing_end + 5, swing_end + 25), 'after': (swing_end + 25, swing_end + 31)}


def _rotation(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def swing_angles(n_frames: int, swing_frames: int = 4) -> tuple:
    """Per frame (abduction, horizontal sweep) of the shoulder, radians (F,) each."""
    frames = np.arange(n_frames, dtype=float)
    phases = swing_phases(swing_frames)
    start, end = phases['swing']
    # 0 -> 85 deg sideways in (end - start) frames at constant speed: in 4 frames, 0.37 rad
    # a frame moves the hand (0.6 m from the shoulder) 22 cm a frame.
    abduction = np.radians(85.0) * np.clip((frames - start + 1) / (end - start), 0.0, 1.0)
    first, last = phases['across']
    half = (last - first) / 2.0
    # forward and across the chest (110 deg) and back, smoothly: at most about 9 cm a frame
    sweep = np.radians(110.0) * (_smoothstep((frames - first) / half) - _smoothstep((frames - first - half) / half))
    return abduction, sweep


def swing_body(n_frames: int = 40, swing_frames: int = 4) -> AnimatedBody:
    """The torso-and-arm stress body over `n_frames` frames (see the module docstring)."""
    abduction, sweep = swing_angles(n_frames, swing_frames)
    torso = ellipsoid_mesh([0.0, 1.15, 0.0], np.eye(3), [0.17, 0.36, 0.11])
    head = ellipsoid_mesh([0.0, 1.68, 0.0], np.eye(3), [0.09, 0.11, 0.10])
    hips = capsule_mesh([-0.09, 0.80, 0.0], [0.09, 0.80, 0.0], 0.12)
    # the arm hangs straight down, 4 cm clear of the torso's side
    upper = capsule_mesh([0.0, 0.0, 0.0], [0.0, -UPPER_ARM_M, 0.0], 0.045)
    forearm = capsule_mesh([0.0, 0.0, 0.0], [0.0, -FOREARM_M, 0.0], 0.04)
    # bone 3 is the fingertip (no mesh): a joint, so the camera frames the whole reach
    transforms = np.tile(np.eye(4), (n_frames, 4, 1, 1))
    for f in range(n_frames):
        # abduction about the camera axis (z), then the horizontal sweep about the vertical
        # axis towards the front (+z) and across the body (-x)
        shoulder = _rotation([0.0, 1.0, 0.0], -sweep[f]) @ _rotation([0.0, 0.0, 1.0], abduction[f])
        transforms[f, 1, :3, :3] = shoulder
        transforms[f, 1, :3, 3] = SHOULDER
        transforms[f, 2, :3, :3] = shoulder
        transforms[f, 2, :3, 3] = SHOULDER + shoulder @ [0.0, -UPPER_ARM_M, 0.0]
        transforms[f, 3, :3, :3] = shoulder
        transforms[f, 3, :3, 3] = SHOULDER + shoulder @ [0.0, -UPPER_ARM_M - FOREARM_M, 0.0]
    parts = [RigidPart(0, np.vstack([torso[0], head[0], hips[0]]),
                       np.vstack([torso[1], head[1] + len(torso[0]), hips[1] + len(torso[0]) + len(head[0])])),
             RigidPart(1, *upper), RigidPart(2, *forearm)]
    return AnimatedBody('swing', transforms, ['torso', 'upper_arm', 'forearm', 'fingertip'], np.array([-1, 0, 1, 2]),
                        ['root', 'shoulder', 'elbow', 'fingertip'], np.array([-1, 0, 1, 2]), np.array([0, 1, 2, 3]),
                        parts=parts,
                        description='an arm swinging up at 22 cm a frame, then across in front of the torso')


def hand_speed(n_frames: int = 40, swing_frames: int = 4) -> np.ndarray:
    """(F - 1,) fingertip travel per frame, m (what the stress test is about)."""
    abduction, sweep = swing_angles(n_frames, swing_frames)
    tips = np.array([_rotation([0.0, 1.0, 0.0], -s) @ _rotation([0.0, 0.0, 1.0], a) @ [0.0, -0.6, 0.0]
                     for a, s in zip(abduction, sweep)])
    return np.linalg.norm(np.diff(tips, axis=0), axis=1)
