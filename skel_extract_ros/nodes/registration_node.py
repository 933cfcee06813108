"""registration_node: Steps 0-1 live. Rest pose from the first good cloud, then every
new cloud registered from the previous one (Alg. 1).

Subscribes  points            sensor_msgs/PointCloud2  sensor-data QoS (best effort; reliable
                              with input_reliability:=reliable), with input:=cloud (default)
            depth/image       sensor_msgs/Image (16UC1 mm, 32FC1 m) and
            depth/camera_info sensor_msgs/CameraInfo, with input:=depth_image: back-projected
                              into the same organized cloud
Publishes   registered_points PointCloud2 (M points, fixed order, input header; ok frames only)
            filtered_points   PointCloud2 (the subject, preprocessed, input header; every decodable cloud)
            rest_points       PointCloud2 (float64, transient local; the rest pose Q, header of its cloud)
Services    ~/reset           std_srvs/Trigger: forget the rest pose, build a new one
            ~/reset_background std_srvs/Trigger: forget the learned scene (planes, motion
                              evidence, the subject) after the camera moved

Every cloud is segmented first (core/segmentation.py): only the subject, the connected
region that moves, is preprocessed, published on filtered_points and registered; the rest
pose waits until the subject is wholly in view.

Registration takes longer than a camera frame, so clouds are taken off the executor by
a cheap callback and processed by one Worker (nodes/worker.py) holding at most
`queue_size` waiting clouds; when it is full the oldest cloud is skipped, counted and
reported.
"""
from __future__ import annotations

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger

from ..core.preprocess import PreprocessParams, Preprocessor
from ..core.registration import STATUS_OK, NonRigidRegistration, RegistrationParams
from ..core.rest_pose import RestPose, RestPoseError, RestPoseParams
from ..core.segmentation import STATUS_NOBODY, SegmentationParams, SubjectSegmenter
from ..core.sequence import PARTIAL_VIEW_PATIENCE_FRAMES, waits_for_subject
from ..depth_image import DepthDecodeError, depth_to_cloud
from ..params import NODE_ONLY, registration_params_from_dict
from ..pointcloud import CloudDecodeError, decode_xyz
from .common import (LATCHED_QOS, SENSOR_QOS, STREAM_QOS, ParameterError, ThrottledLog, declare,
                     declare_dataclass, run_node)
from .conversions import cloud_message, stamp_ns
from .diagnostics import OK, WARN, NodeDiagnostics
from .worker import Worker

SECTION = 'registration_node'


class RegistrationNode(Node):
    def __init__(self, **kwargs):
        super().__init__('registration_node', **kwargs)
        values = declare_dataclass(self, SECTION, RegistrationParams)
        values['rest_pose'] = declare_dataclass(self, SECTION, RestPoseParams, 'rest_pose.')
        values['preprocess'] = declare_dataclass(self, SECTION, PreprocessParams, 'preprocess.')
        values['segmentation'] = declare_dataclass(self, SECTION, SegmentationParams, 'segmentation.')
        self.queue_size = declare(self, SECTION, 'queue_size', NODE_ONLY[SECTION]['queue_size'])
        reliability = declare(self, SECTION, 'input_reliability', NODE_ONLY[SECTION]['input_reliability'])
        if reliability not in ('best_effort', 'reliable'):
            raise ParameterError(f"parameter input_reliability must be 'best_effort' or 'reliable', "
                                 f'got {reliability!r}')
        self.input = declare(self, SECTION, 'input', NODE_ONLY[SECTION]['input'])
        if self.input not in ('cloud', 'depth_image'):
            raise ParameterError(f"parameter input must be 'cloud' or 'depth_image', got {self.input!r}")
        try:
            (self.params, self.rest_params, self.preprocess_params,
             self.segmentation_params) = registration_params_from_dict(values)
        except ValueError as error:
            raise ParameterError(str(error)) from None
        self.log = ThrottledLog(self.get_logger())
        self.registered_pub = self.create_publisher(PointCloud2, 'registered_points', STREAM_QOS)
        self.filtered_pub = self.create_publisher(PointCloud2, 'filtered_points', STREAM_QOS)
        self.rest_pub = self.create_publisher(PointCloud2, 'rest_points', LATCHED_QOS)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/reset_background', self._on_reset_background)
        # set by the services, acted on by the worker before its next cloud
        self._background_reset_requested = False
        self._reset_requested = False
        self._start_over()
        self.worker = Worker(self._work, 'registration', capacity=self.queue_size, on_error=self._failed)
        self.last_status = ''          # what happened to the newest cloud, for /diagnostics
        self._reported_skips = 0
        self.diagnostics = NodeDiagnostics(self, self._diagnostics)
        # best effort matches every driver; reliable (for bag replay) never loses a
        # fragmented megabyte cloud to a full socket buffer, but needs a reliable publisher
        qos = SENSOR_QOS if reliability == 'best_effort' else STREAM_QOS
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
        if self.worker.submit((msg, self.camera_info)):
            stats = self.worker.stats()
            self.log.warn('skipped', f'registration is slower than the input: {stats["dropped"]} cloud(s) '
                                     f'skipped so far (queue_size {self.queue_size}; median '
                                     f'{stats["latency_ms_median"]:.0f} ms per frame)')

    @property
    def skipped(self) -> int:
        """Clouds dropped unprocessed because the queue was full."""
        return self.worker.dropped

    @property
    def processed(self) -> int:
        """Clouds the worker has handled (registered or not)."""
        return self.worker.processed

    def _on_reset(self, _request, response):
        self._reset_requested = True
        response.success = True
        response.message = 'the rest pose will be rebuilt from the next good cloud'
        self.get_logger().info('reset requested: ' + response.message)
        return response

    def _on_reset_background(self, request, response):
        self._background_reset_requested = True
        response.success = True
        response.message = 'the scene is learned again from the next cloud (planes, motion, subject)'
        self.get_logger().info('background reset requested')
        return response

    # -- worker side ---------------------------------------------------------------------
    def _start_over(self) -> None:
        self.segmenter = SubjectSegmenter(self.segmentation_params)
        self.partial_frames = 0
        self.preprocessor = Preprocessor(self.preprocess_params)
        self.registration = None
        self.rest_pose = None
        self.last_stamp = None
        self.frame_id = None

    def _work(self, item) -> None:
        msg, info = item
        if self._reset_requested:
            self._reset_requested = False
            self._start_over()
        if self._background_reset_requested:
            self._background_reset_requested = False
            self.segmenter.reset()
        self._process(msg, info)
        if (self.worker.processed + 1) % 100 == 0:
            stats = self.worker.stats()
            self.get_logger().info(f'{self.worker.processed + 1} clouds processed, latency median '
                                   f'{stats["latency_ms_median"]:.0f} ms, p95 {stats["latency_ms_p95"]:.0f} ms, '
                                   f'{stats["dropped"]} skipped')

    def _diagnostics(self) -> tuple:
        """(level, state, values) for /diagnostics: WARN while there is no rest pose or
        when clouds were skipped since the last report."""
        stats = self.worker.stats()
        new_skips, self._reported_skips = stats['dropped'] - self._reported_skips, stats['dropped']
        if stats['submitted'] == 0:
            level, state = WARN, f'waiting for input on {self.resolve_topic_name("points")}'
        elif self.registration is None:
            level, state = WARN, f'waiting for the subject (no rest pose yet): {self.last_status}'
        else:
            level, state = (WARN if new_skips else OK), f'registering: {self.last_status}'
        return level, state, {
            'rate_in_hz': stats['rate_in_hz'], 'rate_out_hz': stats['rate_hz'],
            'latency_ms_median': stats['latency_ms_median'], 'latency_ms_p95': stats['latency_ms_p95'],
            'clouds_in': stats['submitted'], 'processed': stats['processed'], 'skipped': stats['dropped'],
            'failed': stats['failed'], 'waiting': stats['waiting'], 'queue_size': self.queue_size,
            'rest_points': 0 if self.rest_pose is None else len(self.rest_pose.points)}

    def _failed(self, item, error) -> None:
        """A cloud whose processing raised: one throttled line, the node goes on."""
        self.log.warn('failed', f'cloud at {stamp_ns(item[0].header) * 1e-9:.3f} s failed: '
                                f'{type(error).__name__}: {error}')

    def _decode(self, msg, info) -> tuple:
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

    def _process(self, msg, info=None) -> None:
        stamp, frame_id = stamp_ns(msg.header), msg.header.frame_id
        decoded = self._decode(msg, info)
        if decoded is None:
            return
        raw, height, width = decoded
        if len(raw) > self.preprocess_params.max_input_points:
            self.log.warn('large', f'cloud of {len(raw)} points: randomly thinned to '
                                   f'preprocess.max_input_points = {self.preprocess_params.max_input_points}')
        if self.last_stamp is not None:
            if stamp == self.last_stamp:
                self.log.warn('duplicate', f'ignoring a second cloud with stamp {stamp * 1e-9:.3f} s')
                return
            if stamp < self.last_stamp:
                self.log.always(f'stamps went back by {(self.last_stamp - stamp) * 1e-9:.3f} s '
                                          '(bag looped or clock reset): starting over with a new rest pose')
                self._start_over()
            elif frame_id != self.frame_id:
                self.log.always(f'frame_id changed from {self.frame_id!r} to {frame_id!r}: the '
                                          'registered points would mix coordinate frames; starting over '
                                          'with a new rest pose')
                self._start_over()
        self.last_stamp, self.frame_id = stamp, frame_id
        segmentation = self.segmenter(raw, height, width)
        self.last_status = f'subject {segmentation.status}'
        if segmentation.status == STATUS_NOBODY:
            self.log.warn('nobody', f'nobody in view: no region of the {segmentation.n_valid} valid points '
                                    'has moved yet (waiting for the subject)')
        elif segmentation.n_moving_regions > 1:
            self.log.warn('several', f'{segmentation.n_moving_regions} moving regions (people?) in view: '
                                     'following the one that moves most')
        self.get_logger().debug(f'subject {segmentation.n_subject} of {segmentation.n_valid} points, '
                                f'background {100 * segmentation.background_fraction:.1f} % removed',
                                throttle_duration_sec=1.0)
        observed = self.preprocessor(raw[segmentation.mask])
        self.filtered_pub.publish(cloud_message(observed, msg.header))
        if self.registration is None:
            waiting = waits_for_subject(segmentation, self.partial_frames)
            self.partial_frames += int(segmentation.touches_border)
            if waiting:
                if segmentation.status != STATUS_NOBODY:
                    self.log.warn('partial', 'no rest pose yet: the subject is only partly in view '
                                             f'(waiting up to {PARTIAL_VIEW_PATIENCE_FRAMES} frames for all of it)')
                return
            if len(observed) < max(100, self.rest_params.n_points // 10):
                self.log.warn('no_rest', f'no rest pose yet: only {len(observed)} points after preprocessing '
                                         f'(of {np.isfinite(raw).all(axis=1).sum()} valid); is the subject in view?')
                return
            try:
                self.rest_pose = RestPose.from_points(observed, self.rest_params)
            except RestPoseError as error:
                self.log.warn('no_rest', f'no rest pose from this cloud: {error}')
                return
            self.registration = NonRigidRegistration(self.rest_pose.points, self.params)
            self.rest_pub.publish(cloud_message(self.rest_pose.points, msg.header, float64=True))
            self.get_logger().info(f'rest pose built from the cloud at {stamp * 1e-9:.3f} s '
                                   f'({len(self.rest_pose.points)} points, frame {frame_id!r})')
        result = self.registration.register_frame(observed)
        self.last_status = f'frame {result.status}'
        if result.status != STATUS_OK:
            self.log.warn(f'status:{result.status}:{len(observed) == 0}', f'cloud at {stamp * 1e-9:.3f} s not registered ({result.status}: '
                                    f'{len(observed)} points after preprocessing); holding the last pose')
            return
        self.registered_pub.publish(cloud_message(result.points, msg.header))

    def destroy_node(self):
        self.worker.stop()
        return super().destroy_node()


def main(args=None) -> int:
    return run_node(RegistrationNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
