"""Any moving body (`AnimatedBody`) through the virtual depth camera, in a scene, with exact
ground truth: the one renderer behind the built-in subjects, motion capture, rigs and mesh
sequences."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..app.progress import progress_bar
from .animated import AnimatedBody
from .camera import DepthCamera, Intrinsics, NoiseModel, look_at
from .meshes import inside_any, mesh_area, sample_surface
from .scenes import SCENES, entry_offsets, scene_meshes

FRAME_ID = 'camera_depth_optical_frame'
FRAME_RATE_HZ = 30.0
FIRST_STAMP_NS = 1_700_000_000 * 10**9
UP = np.array([0.0, 1.0, 0.0])


@dataclass
class SimulatedSequence:
    """A rendered sequence.

    clouds: list of F organized clouds, each (H, W, 3) float32 metres in the camera optical
        frame, NaN where the camera saw nothing.
    stamps_ns: (F,) int64 header stamps.
    ground_truth: the arrays written to gt.npz (see `render_body`).
    """

    name: str
    clouds: list
    stamps_ns: np.ndarray
    ground_truth: dict
    frame_id: str = FRAME_ID

    def points_per_frame(self) -> np.ndarray:
        return np.array([int(np.isfinite(c[..., 2]).sum()) for c in self.clouds])


def camera_looking_at(body: AnimatedBody, intrinsics: Intrinsics, facing: np.ndarray,
                      distance: float, azimuth_deg: float = 0.0, height_offset: float = 0.1,
                      margin: float = 0.1, max_distance: float = 4.5) -> np.ndarray:
    """(4, 4) camera-from-world transform of a still camera in front of the body.

    The camera looks at the centre of the space the body moves through over all frames,
    from `distance` m along `facing` (the body's front, horizontal) turned by `azimuth_deg`
    about the vertical, `height_offset` m above the centre. If some joint would leave the
    image (with `margin` of its size) or come closer than 0.8 m, the camera backs off in
    0.25 m steps, but not beyond `max_distance` (a Kinect's useful range): a body that
    travels farther than a depth camera can follow leaves the view for part of the clip.
    """
    joints = body.key_points().reshape(-1, 3)
    centre = (joints.min(axis=0) + joints.max(axis=0)) / 2.0
    facing = np.asarray(facing, float) * np.array([1.0, 0.0, 1.0])
    facing /= np.linalg.norm(facing)
    angle = np.radians(azimuth_deg)
    c, s = np.cos(angle), np.sin(angle)
    direction = np.array([c * facing[0] + s * facing[2], 0.0, -s * facing[0] + c * facing[2]])
    size = np.array([intrinsics.width, intrinsics.height])
    low, high = margin * size, (1.0 - margin) * size
    steps = max(1, int(np.floor((max(max_distance, distance) - distance) / 0.25)) + 1)
    for step in range(steps):
        eye = centre + direction * (distance + 0.25 * step) + UP * height_offset
        camera_from_world = np.linalg.inv(look_at(eye, centre))
        points = joints @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        pixels = points[:, :2] / points[:, 2:] * [intrinsics.fx, intrinsics.fy] + [intrinsics.cx, intrinsics.cy]
        if points[:, 2].min() > 0.8 and (pixels >= low).all() and (pixels <= high).all():
            break
    return camera_from_world


def _surface_samples(body: AnimatedBody, count: int, rng: np.random.Generator,
                     reference_transforms: np.ndarray | None):
    """Bone-local samples (S, 3) on the rigid parts and their bones (S,), leaving out the
    samples buried inside another part in the reference pose (default: the first frame)."""
    reference = body.bone_transforms[0] if reference_transforms is None else reference_transforms
    world = [(p.vertices @ reference[p.bone, :3, :3].T + reference[p.bone, :3, 3], p.triangles)
             for p in body.parts]
    areas = np.array([mesh_area(v, t) for v, t in world])
    counts = np.maximum(1, np.round(count * areas / areas.sum()).astype(int))
    local_samples, sample_bones = [], []
    for i, (part, n) in enumerate(zip(body.parts, counts)):
        samples = sample_surface(part.vertices, part.triangles, int(n), rng)
        in_world = samples @ reference[part.bone, :3, :3].T + reference[part.bone, :3, 3]
        keep = ~inside_any(in_world, [m for j, m in enumerate(world) if j != i])
        local_samples.append(samples[keep])
        sample_bones.append(np.full(int(keep.sum()), part.bone))
    return np.concatenate(local_samples), np.concatenate(sample_bones)


def render_body(body: AnimatedBody, camera_from_world: np.ndarray, intrinsics: Intrinsics,
                noise: NoiseModel, rng: np.random.Generator, scene: str = 'empty',
                enter_frames: int = 0, surface_samples: int = 4000,
                reference_transforms: np.ndarray | None = None, progress: bool = True,
                extra_ground_truth: dict | None = None) -> SimulatedSequence:
    """Render every frame of `body` through a still camera.

    scene: one of SCENES (what else the camera sees: nothing, a floor, or a room with
        walls, furniture and a second still object). enter_frames: the body starts outside
        the view and walks in sideways over that many frames (0 = in view throughout).
    Returns organized clouds and the ground truth, all in the camera optical frame (m):
    joints (F, G, 3), joint_names / joint_parents / joint_bones (G,), bone_names /
    bone_parents (B,), bone_transforms (F, B, 4, 4) camera-from-bone, surface_points
    (F, S, 3) with surface_bone_ids (S,) (and surface_faces (T, 3) for a deforming mesh),
    subject_mask (F, H, W) bool: pixels whose first surface is the body, before noise;
    subject_measured (F, H, W): those of them the noise left on the body (not dropped,
    not turned into a flying pixel or an outlier): what a segmentation can keep.
    """
    if scene not in SCENES:
        raise ValueError(f'unknown scene {scene!r}; choose one of {", ".join(SCENES)}')
    n_frames = body.n_frames
    bone_transforms = body.bone_transforms.copy()
    skin_vertices = None if body.skin is None else body.skin.vertices.copy()
    if enter_frames > 0:
        offsets = entry_offsets(body, camera_from_world, intrinsics, enter_frames)   # (F, 3)
        bone_transforms[:, :, :3, 3] += offsets[:, None]
        if skin_vertices is not None:
            skin_vertices += offsets[:, None]
    moved = AnimatedBody(body.name, bone_transforms, body.bone_names, body.bone_parents,
                         body.joint_names, body.joint_parents, body.joint_bones, body.parts,
                         None if body.skin is None else type(body.skin)(skin_vertices, body.skin.faces,
                                                                         body.skin.vertex_bones),
                         body.frame_time, body.description)
    if body.parts is not None:
        local_samples, sample_bones = _surface_samples(moved, surface_samples, rng, reference_transforms)
    scene_world = scene_meshes(scene, moved, camera_from_world)
    to_camera = camera_from_world[:3, :3], camera_from_world[:3, 3]
    scene_camera = [(v @ to_camera[0].T + to_camera[1], t) for v, t in scene_world]
    transforms = camera_from_world @ bone_transforms               # (F, B, 4, 4) camera from bone
    camera = DepthCamera(intrinsics)

    clouds = []
    masks = np.zeros((n_frames, intrinsics.height, intrinsics.width), dtype=bool)
    measured = np.zeros_like(masks)
    if body.parts is not None:
        surface = np.empty((n_frames, len(local_samples), 3), dtype=np.float32)
    else:
        surface = (skin_vertices @ to_camera[0].T + to_camera[1]).astype(np.float32)
    bar = progress_bar(total=n_frames, desc=f'simulate {body.name}', unit='frame', disable=not progress)
    for f in range(n_frames):
        body_meshes = [(v @ to_camera[0].T + to_camera[1], t) for v, t in moved.world_meshes(f)]
        depth, hit_body = camera.render(body_meshes, scene_camera)
        masks[f] = hit_body
        noisy = noise.apply(depth, rng)
        with np.errstate(invalid='ignore'):
            measured[f] = hit_body & (np.abs(noisy - depth) <= noise.tolerance(depth))
        clouds.append(camera.back_project(noisy))
        if body.parts is not None:
            rotations, origins = transforms[f, :, :3, :3], transforms[f, :, :3, 3]
            surface[f] = np.einsum('sij,sj->si', rotations[sample_bones], local_samples) + origins[sample_bones]
        bar.update()
    bar.close()

    stamps_ns = FIRST_STAMP_NS + np.round(np.arange(n_frames) * 1e9 / FRAME_RATE_HZ).astype(np.int64)
    joint_bones = np.asarray(body.joint_bones, dtype=np.int64)
    ground_truth = {
        'subject': np.array(body.name),
        'frame_id': np.array(FRAME_ID),
        'stamps': stamps_ns.astype(np.float64) * 1e-9,
        'stamps_ns': stamps_ns,
        'joints': transforms[:, joint_bones][:, :, :3, 3].astype(np.float32),
        'joint_names': np.array(body.joint_names, dtype=str),
        'joint_parents': np.asarray(body.joint_parents, dtype=np.int64),
        'joint_bones': joint_bones,
        'bone_names': np.array(body.bone_names, dtype=str),
        'bone_parents': np.asarray(body.bone_parents, dtype=np.int64),
        'bone_transforms': transforms.astype(np.float32),
        'surface_points': surface,
        'surface_bone_ids': (sample_bones if body.parts is not None else body.skin.vertex_bones).astype(np.int64),
        'subject_scale_m': np.float64(np.linalg.norm(np.ptp(surface[0], axis=0))),
        'subject_mask': masks,
        'subject_measured': measured,
        'scene': np.array(scene),
        'camera_from_world': camera_from_world,
        'intrinsics': np.array([intrinsics.width, intrinsics.height, intrinsics.fx,
                                intrinsics.fy, intrinsics.cx, intrinsics.cy]),
    }
    if body.skin is not None:
        ground_truth['surface_faces'] = np.asarray(body.skin.faces, dtype=np.int64)
    ground_truth.update(extra_ground_truth or {})
    return SimulatedSequence(body.name, clouds, stamps_ns, ground_truth)
