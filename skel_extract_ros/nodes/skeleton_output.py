"""What the joint node publishes for each frame with joints, from one place (docs/contract.md):

  skeleton/description  std_msgs/String JSON, latched: the skeleton, with a `version` that
                        changes whenever the skeleton does (grows, is refined, starts over)
  skeleton/trajectory   trajectory_msgs/MultiDOFJointTrajectory, one point per frame:
                        joint_names, per joint a transform (translation = joint position,
                        rotation = its bone's rotation from the rest pose) and velocities
  skeleton/joints       geometry_msgs/PoseArray, the same poses in the description's order
  skeleton/confidence   std_msgs/String JSON: per-joint confidence of the frame
  skeleton/markers      visualization_msgs/MarkerArray (only while a reader is matched)

all on the input frame's header. A frame's messages are built from one DescribedSkeleton
(the model they come from and its description version), so a frame fitted with the old
model while a new one is described is published under the old names and version.

Rotations: the bone's world rotation W_b (rest frame -> this frame, in the cloud frame)
computed as skeleton.bvh computes it (bvh_export.bone_rotations: the rotation that best
carries the rest offsets of the bone's child joints onto the frame's, the twist they leave
open taken from the fit's own rotation of the bone), so a BVH written from the trajectory
holds skeleton.bvh's angles: local rotation of joint b = W_parent^T W_b.
"""
from __future__ import annotations

import json
import threading
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseArray, Transform, Twist
from scipy.spatial.transform import Rotation
from std_msgs.msg import String
from trajectory_msgs.msg import MultiDOFJointTrajectory, MultiDOFJointTrajectoryPoint
from visualization_msgs.msg import MarkerArray

from ..core.bone_rotations import bone_rotations, point_fit_rotations
from ..core.skeleton_model import SkeletonModel
from .common import LATCHED_QOS, STREAM_QOS
from ..codecs.messages import description_changes, description_document, pose_array, skeleton_markers, stamp_ns

# consecutive frames further apart than this get no velocities (a gap in the data: a
# finite difference over it is not a velocity)
MAX_VELOCITY_GAP_S = 0.5


@dataclass(frozen=True)
class DescribedSkeleton:
    """A model as described on skeleton/description: the model and its version."""
    model: SkeletonModel
    version: int


def registered_hints(model: SkeletonModel, registered: np.ndarray) -> np.ndarray:
    """(B, 3, 3) each bone's rigid fit of its rest points onto a registered frame (M, 3):
    the twist skeleton.bvh takes for a registered frame (NaN for a bone without points)."""
    return point_fit_rotations(model.rest_points, model.labels, np.asarray(registered)[None], model.n_joints)[0]


class FrameVelocities:
    """Velocities of consecutive frames of one skeleton version, by finite difference of the
    published poses: linear (J, 3) m/s of the joint positions, angular (J, 3) rad/s of the
    bone rotations (in the cloud frame). None for a frame that follows no earlier frame of the
    same version within MAX_VELOCITY_GAP_S. Thread-safe."""

    def __init__(self):
        self._last = None        # (version, stamp ns, positions, rotations)
        self._lock = threading.Lock()

    def update(self, version: int, stamp: int, positions: np.ndarray, rotations: np.ndarray):
        with self._lock:
            last, self._last = self._last, (version, stamp, positions, rotations)
        if last is None or last[0] != version or not 0 < stamp - last[1] <= MAX_VELOCITY_GAP_S * 1e9:
            return None
        dt = (stamp - last[1]) * 1e-9
        linear = (positions - last[2]) / dt
        step = rotations @ np.transpose(last[3], (0, 2, 1))          # W_t W_{t-1}^T, world frame
        angular = Rotation.from_matrix(step).as_rotvec() / dt
        return linear, angular


class SkeletonOutput:
    """The joint node's skeleton publishers (see the module docstring)."""

    def __init__(self, node, joint_diameter: float):
        self.node = node
        self.joint_diameter = float(joint_diameter)
        self.description_pub = node.create_publisher(String, 'skeleton/description', LATCHED_QOS)
        self.joints_pub = node.create_publisher(PoseArray, 'skeleton/joints', STREAM_QOS)
        self.trajectory_pub = node.create_publisher(MultiDOFJointTrajectory, 'skeleton/trajectory', STREAM_QOS)
        self.confidence_pub = node.create_publisher(String, 'skeleton/confidence', STREAM_QOS)
        self.markers_pub = node.create_publisher(MarkerArray, 'skeleton/markers', STREAM_QOS)
        self._lock = threading.Lock()
        self._version = 0
        self._described = None            # the model of the last description
        self._markers_version = None      # the version the markers reader last got
        self.velocities = FrameVelocities()

    def describe(self, model: SkeletonModel, frame_id: str, window_stamps_ns, moved,
                 provisional: bool, confidence) -> DescribedSkeleton:
        """Publish the description of a new skeleton (the next version) and return it;
        moved: names the structures since the previous description moved; confidence (J,):
        the skeleton's per-joint confidence. Its changes are from the previous description."""
        with self._lock:
            self._version += 1
            before, self._described = self._described, model
            described = DescribedSkeleton(model, self._version)
        document = description_document(model, frame_id, window_stamps_ns, description_changes(before, model, moved),
                                        provisional, described.version, confidence)
        self.description_pub.publish(String(data=json.dumps(document)))
        return described

    def publish(self, skeleton: DescribedSkeleton, header, positions: np.ndarray, hints: np.ndarray,
                confidence: np.ndarray, interpolated: bool = False) -> None:
        """One frame's joints: positions (J, 3) m, hints (J, 3, 3) the fit's bone rotations
        (the twist, see the module docstring; NaN rows: none), confidence (J,) in [0, 1];
        interpolated: a camera frame the live fit had no time for, its joints between the
        fitted frames around it (said in its skeleton/confidence message)."""
        model = skeleton.model
        positions = np.asarray(positions, dtype=np.float64)
        rotations = np.broadcast_to(np.eye(3), (len(positions), 3, 3)).copy()
        if np.isfinite(positions).all():
            rotations = bone_rotations(model.parents, model.rest_joints, positions[None], np.asarray(hints)[None])[0]
        stamp = stamp_ns(header)
        velocities = self.velocities.update(skeleton.version, stamp, positions, rotations)
        quaternions = Rotation.from_matrix(rotations).as_quat()                        # (J, 4) x y z w
        self.joints_pub.publish(pose_array(positions, header, quaternions))
        self.trajectory_pub.publish(trajectory_message(header, model.joint_names, positions, quaternions,
                                                       velocities))
        self.confidence_pub.publish(String(data=json.dumps(
            {'stamp_ns': stamp, 'frame_id': header.frame_id, 'version': skeleton.version,
             'joint_names': model.joint_names, 'confidence': np.round(confidence, 4).tolist(),
             'interpolated': bool(interpolated)})))
        # markers only for a reader (RViz): building and serialising them is ~0.9 ms of every
        # live frame, and a volatile topic drops what it sends unmatched anyway
        if self.markers_pub.get_subscription_count() > 0:
            with self._lock:
                changed, self._markers_version = self._markers_version != skeleton.version, skeleton.version
            self.markers_pub.publish(skeleton_markers(positions, model.parents, header, self.joint_diameter,
                                                      model.ids, model.joint_names,
                                                      confidence, delete_all=changed))


def trajectory_message(header, joint_names, positions, quaternions, velocities=None) -> MultiDOFJointTrajectory:
    """One MultiDOFJointTrajectory point: per joint a Transform (translation = position (J, 3)
    m, rotation = quaternions (J, 4) x y z w) and, when known, a Twist (velocities: (linear
    (J, 3) m/s, angular (J, 3) rad/s); None: the point's velocities list stays empty)."""
    point = MultiDOFJointTrajectoryPoint(time_from_start=Duration())
    for (x, y, z), (qx, qy, qz, qw) in zip(positions.tolist(), quaternions.tolist()):
        transform = Transform()
        transform.translation.x, transform.translation.y, transform.translation.z = x, y, z
        transform.rotation.x, transform.rotation.y, transform.rotation.z, transform.rotation.w = qx, qy, qz, qw
        point.transforms.append(transform)
    if velocities is not None:
        for (vx, vy, vz), (wx, wy, wz) in zip(velocities[0].tolist(), velocities[1].tolist()):
            twist = Twist()
            twist.linear.x, twist.linear.y, twist.linear.z = vx, vy, vz
            twist.angular.x, twist.angular.y, twist.angular.z = wx, wy, wz
            point.velocities.append(twist)
    return MultiDOFJointTrajectory(header=header, joint_names=list(joint_names), points=[point])
