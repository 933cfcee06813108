"""Messages <-> numpy and JSON for the nodes: PointCloud2, PoseArray, MarkerArray and the
std_msgs/String JSON documents (skeleton/structure, skeleton/description).

The JSON documents are plain dicts so that tests and `skel-extract replay` can read them
without ROS. Stamps travel as integer nanoseconds (a float second loses the nanoseconds
of a 2020s epoch stamp, and the nodes pair frames by exact stamp).
"""
from __future__ import annotations

import json

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseArray
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from ..core.skeleton_model import SkeletonModel, pivot_document
from ..core.structure import SkeletalStructure
from .pointcloud import pointcloud2
from .stamps import stamp_to_ns

# 2: the bones' rigid fits at the key frames (rotations, translations) added
STRUCTURE_VERSION = 2


def stamp_ns(header) -> int:
    """Header stamp in integer nanoseconds."""
    return stamp_to_ns(header.stamp)


def set_stamp_ns(header, stamp: int) -> None:
    """Set a header's stamp to `stamp` integer nanoseconds (stamp_ns's inverse), in place."""
    header.stamp.sec, header.stamp.nanosec = divmod(int(stamp), 1_000_000_000)


def cloud_message(points: np.ndarray, header: Header, float64: bool = False) -> PointCloud2:
    """(N, 3) points as an unorganized PointCloud2 with `header`; float64 fields when exact
    values matter (the rest points, which every downstream step starts from)."""
    return pointcloud2(PointCloud2, PointField, header, np.asarray(points).reshape(-1, 3), 16, float64)


def structure_document(structure: SkeletalStructure, rest_stamp_ns: int, window_stamps_ns, frame_id: str,
                       joint_ids=None, changes: dict | None = None) -> dict:
    """The skeleton/structure JSON: bones, bone tree, per-point labels, the stamps of the
    frames it was learned on (a growing skeleton's key frames) and each bone's rigid fit at
    each of them (rotations as 9 row-major numbers, translations m; Alg. 2 starts from
    them, so the joint node does not fit them again), stable joint ids (default 0..B-1) and
    what changed since the previous one (core.growth)."""
    joint_ids = range(structure.n_bones) if joint_ids is None else joint_ids
    return {
        'version': STRUCTURE_VERSION,
        'frame_id': frame_id,
        'rest_stamp_ns': int(rest_stamp_ns),
        'window_stamps_ns': [int(s) for s in window_stamps_ns],
        'n_points': int(len(structure.labels)),
        'n_bones': int(structure.n_bones),
        'parents': [int(p) for p in structure.parents],
        'labels': [int(label) for label in structure.labels],
        'joints': structure.joints.tolist(),
        'boundary_centroids': structure.boundary_centroids.tolist(),
        'anchor_spread': None if structure.anchor_spread is None else structure.anchor_spread.tolist(),
        'depth_rays': None if structure.depth_rays is None else structure.depth_rays.tolist(),
        'rotations': structure.rotations.reshape(len(structure.rotations), structure.n_bones, 9).tolist(),
        'translations': structure.translations.tolist(),
        'joint_ids': [int(i) for i in joint_ids],
        'changes': changes or {},
    }


def _optional_per_bone(value, key: str, n_bones: int, row_shape: tuple) -> np.ndarray | None:
    """An optional per-bone array of a structure message: None when not sent (not known),
    else (B, *row_shape) float64; ValueError when it does not match the bone count."""
    if value is None:
        return None
    array = np.asarray(value, dtype=np.float64).reshape(-1, *row_shape)
    if len(array) != n_bones:
        raise ValueError(f'{key} does not match the bone count')
    return array


def parse_structure(text: str) -> dict:
    """Validate a skeleton/structure JSON; labels/parents as int arrays, joints (B, 3).
    Raises ValueError with the reason."""
    try:
        document = json.loads(text)
        if not isinstance(document, dict):
            raise TypeError(f'a JSON object is expected, not {type(document).__name__}')
        for key in ('rest_stamp_ns', 'window_stamps_ns', 'frame_id'):
            if key not in document:
                raise KeyError(key)
        document['rest_stamp_ns'] = int(document['rest_stamp_ns'])
        document['window_stamps_ns'] = [int(stamp) for stamp in document['window_stamps_ns']]
        if document.get('version') != STRUCTURE_VERSION:
            raise ValueError(f'unsupported structure version {document.get("version")!r}')
        document['parents'] = np.asarray(document['parents'], dtype=np.int64)
        document['labels'] = np.asarray(document['labels'], dtype=np.int64)
        document['joints'] = np.asarray(document['joints'], dtype=np.float64).reshape(-1, 3)
        document['boundary_centroids'] = np.asarray(document['boundary_centroids'], dtype=np.float64).reshape(-1, 3)
        B, F = len(document['parents']), len(document['window_stamps_ns'])
        if len(document['joints']) != B or len(document['boundary_centroids']) != B:
            raise ValueError('joints / boundary_centroids do not match the bone count')
        document['rotations'] = np.asarray(document['rotations'], dtype=np.float64).reshape(F, B, 3, 3)
        document['translations'] = np.asarray(document['translations'], dtype=np.float64).reshape(F, B, 3)
        for key, row_shape in (('anchor_spread', ()), ('depth_rays', (3,))):
            document[key] = _optional_per_bone(document.get(key), key, B, row_shape)
        document['joint_ids'] = np.asarray(document.get('joint_ids', np.arange(B)), dtype=np.int64)
        if len(document['joint_ids']) != B or len(set(document['joint_ids'].tolist())) != B:
            raise ValueError('joint_ids must be one distinct id per bone')
        if not isinstance(document.setdefault('changes', {}), dict):
            raise TypeError('changes must be an object')
        if len(document['labels']) and (document['labels'].min() < 0 or document['labels'].max() >= B):
            raise ValueError('labels out of range')
        return document
    except (KeyError, TypeError, ValueError) as error:  # JSONDecodeError is a ValueError
        raise ValueError(f'malformed skeleton/structure message: {error}') from None


def description_changes(before: SkeletonModel | None, after: SkeletonModel, moved=()) -> dict:
    """What changed from the description of `before` (None: there was none) to that of
    `after`: joint names added, removed, reparented (a different parent name) and moved
    (names in `moved`, the structures' own moved joints since `before`, that both keep).
    Taken from the two descriptions themselves, so the changes hold when structures were
    skipped between them (one replaced while waiting for Alg. 2, one ignored)."""
    def parent_names(model):
        names = model.joint_names
        return {name: (names[p] if p >= 0 else None) for name, p in zip(names, model.parents)}
    old = {} if before is None else parent_names(before)
    new, moved = parent_names(after), set(moved)
    kept = [name for name in after.joint_names if name in old]
    return {'added': [name for name in after.joint_names if name not in old],
            'removed': [name for name in old if name not in new],
            'reparented': [name for name in kept if old[name] != new[name]],
            'moved': [name for name in kept if name in moved]}


def description_document(model: SkeletonModel, frame_id: str, window_stamps_ns, changes: dict | None = None,
                         provisional: bool = False, version: int = 1, confidence=None) -> dict:
    """The skeleton/description JSON: version (a counter that changes with every new
    description: skeleton/confidence carries the version of each frame), joint_names
    (stable across updates), parents, rest_positions, frame, the frames it was learned on,
    what changed since the previous description (joint names added / removed / reparented
    / moved), whether it is provisional (Step 2's skeleton, tracked while Alg. 2 runs;
    the next description refines it under the same joint names), the per-joint
    confidence (J,) in [0, 1] of the frames it was learned on (core/confidence.py; None:
    not given), how far the motion fixed each joint's pivot (the model's pivot evidence,
    core.skeleton_model.pivot_document; None: not known) and the skeleton's noise (m, the
    scale its per-frame confidence judges a fit against; None: not known)."""
    return {'version': int(version), 'frame_id': frame_id, 'joint_names': model.joint_names,
            'parents': [int(p) for p in model.parents],
            'rest_positions': np.round(model.rest_joints, 6).tolist(),
            'window_stamps_ns': [int(s) for s in window_stamps_ns],
            'changes': changes or {}, 'provisional': bool(provisional),
            'confidence': None if confidence is None else np.round(np.asarray(confidence, dtype=float), 4).tolist(),
            'pivot': pivot_document(model.pivot),
            'noise_m': None if model.noise_m is None else round(float(model.noise_m), 5)}


def pose_array(positions: np.ndarray, header: Header, quaternions: np.ndarray | None = None) -> PoseArray:
    """One pose per joint, in the input frame: positions (J, 3) m, orientations quaternions
    (J, 4) x y z w (None: identity)."""
    msg = PoseArray(header=header)
    positions = np.asarray(positions, dtype=float)
    if quaternions is None:
        quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (len(positions), 1))
    msg.poses = [Pose() for _ in range(len(positions))]
    for pose, (x, y, z), (qx, qy, qz, qw) in zip(msg.poses, positions.tolist(), np.asarray(quaternions).tolist()):
        pose.position.x, pose.position.y, pose.position.z = x, y, z
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = qx, qy, qz, qw
    return msg


def pose_array_positions(msg) -> np.ndarray:
    """(J, 3) joint positions of a PoseArray."""
    return np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses], dtype=np.float64).reshape(-1, 3)


def skeleton_markers(positions: np.ndarray, parents, header: Header, joint_diameter: float = 0.04, ids=None,
                     names=None, confidence=None, delete_all: bool = False) -> MarkerArray:
    """A SPHERE per joint (namespace 'joints', id = the joint's stable id, default its
    index; coloured from red at confidence 0 to green at 1, orange without one), a
    TEXT_VIEW_FACING label per joint with its name (namespace 'names', same id, above the
    sphere) when names are given, and one LINE_LIST of the bones (namespace 'bones', id 0).
    delete_all: a DELETEALL first, so that the joints of an earlier skeleton (a joint a
    growth update removed) leave RViz. positions (J, 3) m; confidence (J,) in [0, 1]."""
    positions = np.asarray(positions, dtype=float)
    ids = range(len(positions)) if ids is None else ids
    markers = MarkerArray()
    if delete_all:
        markers.markers.append(Marker(header=header, action=Marker.DELETEALL))
    for index, (marker_id, (x, y, z)) in enumerate(zip(ids, positions.tolist())):
        sphere = Marker(header=header, ns='joints', id=int(marker_id), type=Marker.SPHERE, action=Marker.ADD)
        sphere.pose.position.x, sphere.pose.position.y, sphere.pose.position.z = x, y, z
        sphere.pose.orientation.w = 1.0
        sphere.scale.x = sphere.scale.y = sphere.scale.z = float(joint_diameter)
        if confidence is None:
            sphere.color = ColorRGBA(r=1.0, g=0.3, b=0.1, a=1.0)
        else:
            level = float(np.clip(confidence[index], 0.0, 1.0))
            sphere.color = ColorRGBA(r=1.0 - level, g=level, b=0.1, a=1.0)
        markers.markers.append(sphere)
        if names is not None:
            label = Marker(header=header, ns='names', id=int(marker_id), type=Marker.TEXT_VIEW_FACING,
                           action=Marker.ADD, text=str(names[index]))
            # above the sphere: y is down in a camera's optical frame, up elsewhere; a
            # diameter to the side keeps the label off the sphere either way
            label.pose.position.x, label.pose.position.y, label.pose.position.z = x + float(joint_diameter), y, z
            label.pose.orientation.w = 1.0
            label.scale.z = float(joint_diameter)          # text height, m
            label.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
            markers.markers.append(label)
    bones = Marker(header=header, ns='bones', id=0, type=Marker.LINE_LIST, action=Marker.ADD)
    bones.pose.orientation.w = 1.0
    bones.scale.x = float(joint_diameter) / 4.0
    bones.color = ColorRGBA(r=0.1, g=0.6, b=1.0, a=1.0)
    for child, parent in enumerate(parents):
        if parent >= 0:
            bones.points.append(Point(x=float(positions[parent, 0]), y=float(positions[parent, 1]),
                                      z=float(positions[parent, 2])))
            bones.points.append(Point(x=float(positions[child, 0]), y=float(positions[child, 1]),
                                      z=float(positions[child, 2])))
    markers.markers.append(bones)
    return markers
