"""joint_estimation_node: Step 3 (Alg. 2) on each structure's window, then live joints.

Subscribes  skeleton/structure (std_msgs/String JSON, transient local)
            registered_points, filtered_points (PointCloud2, reliable), rest_points (transient local)
Publishes   (nodes/skeleton_output.py; the contract: docs/contract.md; all on the input header)
            skeleton/description (std_msgs/String JSON, transient local): version, joint_names,
            parents, rest_positions, frame_id, window_stamps_ns, changes, provisional
            skeleton/trajectory (trajectory_msgs/MultiDOFJointTrajectory, one point per frame:
            per joint its position and its bone's rotation from the rest pose, velocities)
            skeleton/joints  (geometry_msgs/PoseArray, the same poses in joint_names order)
            skeleton/confidence (std_msgs/String JSON: per-joint confidence, core/confidence.py)
            skeleton/markers (visualization_msgs/MarkerArray, only while a reader is matched:
            SPHERE and name label per joint, id = stable joint id; LINE_LIST of bones;
            DELETEALL first when the skeleton changed)
            skeleton/posed_points (PointCloud2, M points in the registered points' order,
            input header): the learned model posed by LBS at each fitted camera frame;
            the registration node starts its next frame from it (`live_start`)

The work (nodes/joint_stages.py): on a structure, Alg. 2 on its window's frames (found by
stamp among the `buffer_size` frames kept), joints for the window's frames that have none
yet, then live joints: with live_frames camera (default) every filtered_points frame gets
the learned model fitted to its subject points (never waiting for registration; a frame
the fit cannot keep up with is skipped and counted); with live_frames registered every
registered frame gets the model fitted to its registered points, as `skel-extract run`
does. With provisional_skeleton, Step 2's skeleton is described and tracked while Alg. 2
runs; Alg. 2's model then replaces it under the same names.
"""
from __future__ import annotations

from typing import NoReturn

from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String

from ..codecs.messages import cloud_message, parse_structure
from .common import (LATCHED_QOS, STREAM_QOS, ThrottledLog, WorkingNode, declare_params, decode_or_warn,
                     decode_registered_or_warn, decode_rest_or_warn, on_live_parameters, run_node)
from .diagnostics import OK, WARN, NodeDiagnostics
from .joint_stages import JointStages
from .skeleton_output import SkeletonOutput
from .worker import RateMeter

SECTION = 'joint_estimation_node'


class JointEstimationNode(WorkingNode):
    def __init__(self, **kwargs):
        super().__init__('joint_estimation_node', **kwargs)
        params = declare_params(self, SECTION)
        own = params['node']
        self.log = ThrottledLog(self.get_logger())
        # description, joints, trajectory, confidence, markers (nodes/skeleton_output.py)
        self.output = SkeletonOutput(self, own.joint_diameter)
        self.markers_pub = self.output.markers_pub
        # the model posed at each fitted camera frame: the registration starts from it
        posed_pub = self.create_publisher(PointCloud2, 'skeleton/posed_points', STREAM_QOS)
        self.stages = JointStages(params['joints'], own, self.output,
                                  lambda points, header: posed_pub.publish(cloud_message(points, header)),
                                  self.log, self.get_logger(), self.context.ok)
        on_live_parameters(self, SECTION, self._apply_parameters)
        self.registered_rate = RateMeter()
        self.create_subscription(PointCloud2, 'rest_points', self._on_rest, LATCHED_QOS)
        self.create_subscription(PointCloud2, 'registered_points', self._on_registered, STREAM_QOS)
        self.create_subscription(PointCloud2, 'filtered_points', self._on_filtered, STREAM_QOS)
        self.create_subscription(String, 'skeleton/structure', self._on_structure, LATCHED_QOS)
        self.diagnostics = NodeDiagnostics(self, self._diagnostics)
        self.get_logger().info('waiting for skeleton/structure')

    def _apply_parameters(self, params: dict, _changed: set) -> None:
        """`ros2 param set` (the live parameters), see JointStages.apply."""
        self.stages.apply(params['joints'], params['node'])

    @property
    def live_frames(self) -> str:
        return self.stages.live_frames

    @property
    def provisional_skeleton(self) -> bool:
        return self.stages.provisional_skeleton

    # -- inputs: decoded here, handed to the stages -------------------------------------------
    def _on_rest(self, msg: PointCloud2) -> None:
        decoded = decode_rest_or_warn(msg, self.log)
        if decoded is not None:
            self.stages.rest_pose(*decoded)

    def _on_filtered(self, msg: PointCloud2) -> None:
        points = decode_or_warn(msg, self.log, 'filtered_points')
        if points is not None:
            self.stages.filtered(msg.header, points)

    def _on_registered(self, msg: PointCloud2) -> None:
        self.registered_rate.tick()
        points = decode_registered_or_warn(msg, self.log, self.stages.rest)
        if points is not None:
            self.stages.registered(msg.header, points)

    def _on_structure(self, msg: String) -> None:
        try:
            document = parse_structure(msg.data)
        except ValueError as error:
            self.log.warn('structure', f'ignoring skeleton/structure: {error}')
            return
        self.stages.structure(document)

    def _diagnostics(self) -> tuple:
        """(level, state, values) for /diagnostics."""
        stages = self.stages
        tracking, n_joints, has_rest = stages.status()
        live = sorted(stages.live_ms.copy())      # copy(): atomic against the appending thread
        if stages.estimating:
            meanwhile = f'; tracking {n_joints} joints meanwhile' if tracking else ''
            level, state = OK, 'estimating joints (Alg. 2)' + meanwhile
        elif tracking:
            level, state = OK, f'tracking {n_joints} joints'
        else:
            level, state = WARN, 'waiting for skeleton/structure' if has_rest else 'waiting for rest_points'
        return level, state, {
            'rate_in_hz': self.registered_rate.rate(), 'rate_out_hz': stages.joints_rate.rate(),
            'live_fit_ms_median': live[len(live) // 2] if live else float('nan'),
            'live_fit_ms_p95': live[int(0.95 * (len(live) - 1))] if live else float('nan'),
            'estimations': stages.estimator.processed, 'failed': stages.estimator.failed,
            'structures_replaced': stages.estimator.dropped, 'joints': n_joints, 'live_frames': self.live_frames,
            'camera_frames_skipped': stages.live.dropped, 'camera_frames_in_hz': stages.live.rate_in.rate(),
            **{f'live_{k}': v for k, v in stages.live_fits.items()}}

    def stop_work(self) -> None:
        """Stop Alg. 2's and the live fit's threads (not the ROS entities: destroy_node)."""
        self.stages.stop()


def main(args=None) -> NoReturn:
    run_node(JointEstimationNode, args)


if __name__ == '__main__':
    main()
