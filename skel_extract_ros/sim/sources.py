"""The simulator's subjects beyond the built-in ones: real motion capture on a body,
a skinned rig blended between key poses, a captured mesh sequence. Each becomes an
`AnimatedBody` and goes through the same renderer and scenes."""
from __future__ import annotations

import numpy as np

from .camera import Intrinsics, NoiseModel
from .mocap_body import facing_direction, mocap_body, most_active_start
from .render import FRAME_RATE_HZ, SimulatedSequence, camera_looking_at, render_body


def _window(body, frames: int, start: int | None):
    """The frames [start, start + frames) of `body` (the most active stretch when start is
    None); fewer when the clip is shorter. Returns (body, start)."""
    if start is None:
        start = most_active_start(body, frames)
    if not 0 <= start < body.n_frames:
        raise ValueError(f'--start {start} is outside the clip (0..{body.n_frames - 1})')
    return body.window(start, min(start + frames, body.n_frames)), start


def render_in_view(body, *, resolution: str = '320x240', noise: NoiseModel | None = None,
                   scene: str = 'empty', distance: float = 3.0, azimuth: float = 0.0,
                   facing=None, height_offset: float = 0.1, seed: int = 0,
                   enter_frames: int = 0, surface_samples: int = 4000, progress: bool = True,
                   extra_ground_truth: dict | None = None) -> SimulatedSequence:
    """Render `body` through a still camera `distance` m in front of it (turned `azimuth`
    degrees about the vertical from its facing direction), backing off until the whole
    motion is in view."""
    intrinsics = Intrinsics.from_resolution(resolution)
    noise = NoiseModel.kinect() if noise is None else noise
    rng = np.random.default_rng(seed)
    facing = np.array([0.0, 0.0, 1.0]) if facing is None else facing
    camera_from_world = camera_looking_at(body, intrinsics, facing, distance, azimuth, height_offset)
    return render_body(body, camera_from_world, intrinsics, noise, rng, scene=scene,
                       enter_frames=enter_frames, surface_samples=surface_samples,
                       progress=progress, extra_ground_truth=extra_ground_truth)


def in_place(body):
    """`body` with its root's horizontal travel taken out (turns, bobbing and limb motion
    kept), as on a treadmill: a 5 m run does not fit a depth camera's view."""
    root = int(np.flatnonzero(body.bone_parents < 0)[0])
    travel = (body.bone_transforms[:, root, :3, 3] - body.bone_transforms[0, root, :3, 3]) * [1.0, 0.0, 1.0]
    transforms = body.bone_transforms.copy()
    transforms[:, :, :3, 3] -= travel[:, None]
    return type(body)(body.name, transforms, body.bone_names, body.bone_parents, body.joint_names,
                      body.joint_parents, body.joint_bones, body.parts, body.skin, body.frame_time,
                      body.description)


def simulate_mocap(path, frames: int = 90, start: int | None = None, units: str = 'auto',
                   treadmill: bool = False, **render_options) -> SimulatedSequence:
    """A BVH clip on a body of capsules, resampled to the camera's 30 Hz; the window of
    `frames` frames with the most limb motion unless `start` is given; `treadmill` takes
    the horizontal travel out (see `in_place`)."""
    from pathlib import Path

    from .bvh import load_bvh

    clip = load_bvh(path, units).resampled(1.0 / FRAME_RATE_HZ)
    body, start = _window(mocap_body(clip, Path(path).stem), frames, start)
    if treadmill:
        body = in_place(body)
    extra = {'source': np.array(str(path)), 'source_start_frame': np.int64(start),
             'seed': np.int64(render_options.get('seed', 0))}
    return render_in_view(body, facing=facing_direction(body), extra_ground_truth=extra,
                          **render_options)


def simulate_rig(directory, frames: int = 90, **render_options) -> SimulatedSequence:
    """A skinned rig (e.g. the cow) blended smoothly between its key poses, seen from its
    side (the rig's long axis runs across the image)."""
    from .rig import load_rig, rig_body

    body = rig_body(load_rig(directory), frames, seed=render_options.get('seed', 0))
    extra = {'source': np.array(str(directory)), 'seed': np.int64(render_options.get('seed', 0))}
    # rigs face +z: a camera on +x sees the flank, where the legs and neck bend
    return render_in_view(body, facing=np.array([1.0, 0.0, 0.0]), extra_ground_truth=extra, **render_options)


def simulate_mesh_sequence(path, frames: int = 90, start: int = 0, **render_options) -> SimulatedSequence:
    """A captured mesh sequence (exact vertex motion, no joints) seen from the front."""
    from .mesh_sequence import load_mesh_sequence

    body = load_mesh_sequence(path, frames=frames, start=start)
    extra = {'source': np.array(str(path)), 'source_start_frame': np.int64(start),
             'seed': np.int64(render_options.get('seed', 0))}
    return render_in_view(body, extra_ground_truth=extra, **render_options)


def simulate_swing(frames: int = 40, swing_frames: int = 4, **render_options) -> SimulatedSequence:
    """The registration stress body (`stress.swing_body`): an arm swinging up (at 22 cm a
    frame with swing_frames = 4), then across in front of the torso, seen from the front."""
    from .stress import swing_body

    return render_in_view(swing_body(frames, swing_frames), distance=2.0,
                          extra_ground_truth={'seed': np.int64(render_options.get('seed', 0))}, **render_options)
