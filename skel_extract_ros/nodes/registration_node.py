"""registration_node: Steps 0-1 live. Rest pose from the first good cloud, then every
new cloud registered from the previous one (Alg. 1).

Subscribes  points            sensor_msgs/PointCloud2  sensor-data QoS (best effort; reliable
                              with input_reliability:=reliable), with input:=cloud (default)
            depth/image       sensor_msgs/Image (16UC1 mm, 32FC1 m) and
            depth/camera_info sensor_msgs/CameraInfo, with input:=depth_image: back-projected
                              into the same organized cloud
            skeleton/structure, skeleton/description std_msgs/String (transient local): the
                              first window is learned (the joint node's Alg. 2 comes next)
                              or a skeleton is tracked; from then on Alg. 1 runs
                              registration_niceness nicer (and with registration_sched_idle
                              in the idle scheduling class)
            skeleton/posed_points PointCloud2 (M points, from the joint node): the live fit's
                              pose of a recent camera frame; with live_start the next frame
                              is registered from it, not from the last registered frame
Publishes   registered_points PointCloud2 (M points, fixed order, input header; ok frames only)
            filtered_points   PointCloud2 (the subject, preprocessed, input header; every decodable cloud)
            rest_points       PointCloud2 (float64, transient local; the rest pose Q, header of its cloud)
Services    ~/reset           std_srvs/Trigger: forget the rest pose, build a new one
            ~/reset_background std_srvs/Trigger: forget the learned scene (planes, motion
                              evidence, the subject) after the camera moved

Two stages (nodes/registration_stages.py) over the per-frame step `skel-extract run` uses
(core/stream.py): the camera stage finds the subject in every frame and publishes it on
filtered_points at once, for the joint node's live fit; the registration stage builds the
rest pose and registers the frames (Alg. 1) in child processes. While the first window is
learned frames are registered in order (up to `learning_queue_size` wait); once a skeleton
is learned the newest are, at lower priority (`queue_size`, `registration_niceness`,
`registration_sched_idle`). With `lossless` nothing is skipped.
"""
from __future__ import annotations

from typing import NoReturn

import numpy as np
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ..codecs.depth_image import DepthDecodeError, depth_to_cloud
from ..codecs.messages import cloud_message, stamp_ns
from ..codecs.pointcloud import CloudDecodeError, decode_xyz
from .common import (LATCHED_QOS, SENSOR_QOS, STREAM_QOS, ThrottledLog, WorkingNode, declare_params, decode_or_warn,
                     run_node)
from .diagnostics import OK, WARN, NodeDiagnostics
from .registration_stages import QUIET_CHECK_S, RegistrationStages

SECTION = 'registration_node'


class _Outputs:
    """The stages' outputs as ROS messages on the input header."""

    def __init__(self, node):
        self.registered_pub = node.create_publisher(PointCloud2, 'registered_points', STREAM_QOS)
        self.filtered_pub = node.create_publisher(PointCloud2, 'filtered_points', STREAM_QOS)
        self.rest_pub = node.create_publisher(PointCloud2, 'rest_points', LATCHED_QOS)

    def registered(self, points, header) -> None:
        self.registered_pub.publish(cloud_message(points, header))

    def filtered(self, points, header) -> None:
        self.filtered_pub.publish(cloud_message(points, header))

    def rest(self, points, header) -> None:
        self.rest_pub.publish(cloud_message(points, header, float64=True))


class RegistrationNode(WorkingNode):
    def __init__(self, **kwargs):
        super().__init__('registration_node', **kwargs)
        params = declare_params(self, SECTION)
        self.params, self.rest_params = params['registration'], params['rest_pose']
        method = (params['registration'], params['rest_pose'], params['preprocess'], params['segmentation'])
        own = params['node']
        self.input = own.input
        self.log = ThrottledLog(self.get_logger())
        self.outputs = _Outputs(self)
        self.stages = RegistrationStages(method, own, self._decode, self.outputs, self.log,
                                         self.get_logger(), self.context.ok)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/reset_background', self._on_reset_background)
        # whichever comes first (a joint node started on its own publishes only the description)
        self.create_subscription(String, 'skeleton/structure', self._on_structure, LATCHED_QOS)
        self.create_subscription(String, 'skeleton/description', self._on_description, LATCHED_QOS)
        self.create_subscription(PointCloud2, 'skeleton/posed_points', self._on_posed, STREAM_QOS)
        self._reported_skips = 0
        self.diagnostics = NodeDiagnostics(self, self._diagnostics)
        self.create_timer(QUIET_CHECK_S, self.stages.flush_if_quiet)
        # best effort matches every driver; reliable (for bag replay) never loses a
        # fragmented megabyte cloud to a full socket buffer, but needs a reliable publisher
        qos = SENSOR_QOS if own.input_reliability == 'best_effort' else STREAM_QOS
        self.camera_info = None
        if self.input == 'cloud':
            self.create_subscription(PointCloud2, 'points', self._on_cloud, qos)
            source = self.resolve_topic_name('points')
        else:
            self.create_subscription(CameraInfo, 'depth/camera_info', self._on_camera_info, qos)
            self.create_subscription(Image, 'depth/image', self._on_cloud, qos)
            source = (f'{self.resolve_topic_name("depth/image")} with '
                      f'{self.resolve_topic_name("depth/camera_info")}')
        self.get_logger().info(f'waiting for {self.input.replace("_", " ")}s on {source} '
                               f'(M = {self.rest_params.n_points} registered points)')

    # -- executor side: cheap ------------------------------------------------------------
    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.camera_info = msg

    def _on_cloud(self, msg) -> None:
        """A PointCloud2, or a depth Image (queued with the camera info it goes with)."""
        self.stages.submit((msg, self.camera_info))

    def _on_structure(self, msg: String) -> None:
        if self.count_publishers('skeleton/description') == 0:
            self.stages.described = True      # no joint node will describe it: nothing to wait for
        self.stages.skeleton_learned()

    def _on_description(self, msg: String) -> None:
        self.stages.described = True
        self.stages.skeleton_learned()

    def _on_posed(self, msg: PointCloud2) -> None:
        # the newest to arrive (one writer publishes in stamp order; after stamps went back
        # a larger stamp is the older pose)
        points = decode_or_warn(msg, self.log, 'skeleton/posed_points', np.float64)
        if points is not None:
            self.stages.posed = (stamp_ns(msg.header), points)

    def _on_reset(self, _request, response):
        self.stages.reset_requested = True
        response.success = True
        response.message = 'the rest pose will be rebuilt from the next good cloud'
        self.get_logger().info('reset requested: ' + response.message)
        return response

    def _on_reset_background(self, request, response):
        self.stages.background_reset_requested = True
        response.success = True
        response.message = 'the scene is learned again from the next cloud (planes, motion, subject)'
        self.get_logger().info('background reset requested')
        return response

    # -- camera stage's thread -------------------------------------------------------------
    def _decode(self, msg, info) -> tuple | None:
        """(points (H*W, 3), height, width) of a cloud or a depth image, or None (warned)."""
        frame_id = msg.header.frame_id
        if isinstance(msg, PointCloud2):
            try:
                return decode_xyz(msg), int(msg.height), int(msg.width)
            except CloudDecodeError as error:
                self.log.warn(f'decode:{str(error)[:24]}', f'ignoring a cloud in frame {frame_id!r}: {error}')
                return None
        if info is None:
            self.log.warn('no_camera_info', 'ignoring depth images until a CameraInfo arrives on '
                                            f'{self.resolve_topic_name("depth/camera_info")}')
            return None
        try:
            cloud = depth_to_cloud(msg, info)
        except DepthDecodeError as error:
            self.log.warn(f'depth:{str(error)[:24]}', f'ignoring a depth image in frame {frame_id!r}: {error}')
            return None
        return cloud.reshape(-1, 3), cloud.shape[0], cloud.shape[1]

    # -- diagnostics -------------------------------------------------------------------------
    def _diagnostics(self) -> tuple:
        """(level, state, values) for /diagnostics: WARN while there is no rest pose or
        when clouds were skipped since the last report. rate_out_hz / latency: the
        registration stage; filtered_*: the camera stage (what the live path gets)."""
        stages = self.stages
        camera, registration = stages.camera.stats(), stages.registration.stats()
        skipped = camera['dropped'] + registration['dropped']
        new_skips, self._reported_skips = skipped - self._reported_skips, skipped
        if camera['submitted'] == 0:
            level, state = WARN, f'waiting for input on {self.resolve_topic_name("points")}'
        elif stages.rest_pose is None and stages.frame_registrar.held:
            level, state = OK, (f'choosing the rest pose: {len(stages.frame_registrar.held)} of '
                                f'{self.rest_params.choice_frames} clouds held')
        elif stages.rest_pose is None:
            level, state = WARN, f'waiting for the subject (no rest pose yet): {stages.last_status}'
        else:
            level, state = ((WARN if new_skips else OK),
                            f'registering: {stages.last_status}, {stages.last_registration_status}')
        return level, state, {
            'rate_in_hz': camera['rate_in_hz'], 'filtered_rate_hz': camera['rate_hz'],
            'filtered_latency_ms_median': camera['latency_ms_median'],
            'rate_out_hz': registration['rate_hz'],
            'latency_ms_median': registration['latency_ms_median'],
            'latency_ms_p95': registration['latency_ms_p95'],
            'clouds_in': camera['submitted'], 'processed': stages.processed, 'skipped': skipped,
            'skipped_for_registration': registration['dropped'],
            'failed': camera['failed'] + registration['failed'], 'waiting': registration['waiting'],
            'queue_size': stages.registration.capacity, 'lossless': stages.settings.lossless,
            'registration_nice': stages.registration_process.nice,
            'registration_sched_idle': stages.registration_process.in_idle_class,
            'registered_from_live_pose': stages.registered_from_live_pose,
            # readers matched to both outputs (DDS drops what a volatile writer sends before)
            'outputs_matched': min(self.outputs.registered_pub.get_subscription_count(),
                                   self.outputs.filtered_pub.get_subscription_count()),
            'clouds_held': len(stages.frame_registrar.held),
            'rest_points': 0 if stages.rest_pose is None else len(stages.rest_pose.points)}

    def stop_work(self) -> None:
        """Stop the stages' threads and child processes (not the ROS entities: destroy_node)."""
        self.stages.stop()


def main(args=None) -> NoReturn:
    run_node(RegistrationNode, args)


if __name__ == '__main__':
    main()
