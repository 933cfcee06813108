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

Two stages, each on its own Worker (nodes/worker.py), so the subject reaches the live path
at camera rate whatever registration costs:
- the *camera stage* (latest cloud only) decodes every cloud, segments it
  (core/segmentation/: only the subject, the connected region that moves, is kept),
  preprocesses it and publishes it on filtered_points at once: the joint node fits the
  skeleton to it;
- the *registration stage* registers the subject clouds it is given (Alg. 1). While the
  first window is learned (from the rest pose to the first skeleton/structure) it takes
  them in order, holding up to `learning_queue_size` (new ones are skipped when full): the
  window is consecutive camera frames, as `skel-extract run`'s, and frames 33 ms apart
  register in a third of the time of frames a second apart (fewer EM iterations). Until
  the first skeleton is described nothing else uses a subject frame, so the camera stage
  skips a cloud the queue has no room for before decoding it (counted as the queue's
  drop): the cores go to learning. After
  that it holds at most `queue_size` waiting ones: when it falls behind, the oldest
  waiting cloud is skipped, counted and reported, so it always works on recent frames.
  With `lossless` nothing is skipped: the camera stage waits for room (back-pressure; for
  bag replay with reliable input). The rest pose waits until the subject is wholly in
  view. Alg. 1 itself runs in a child process (nodes/registration_process.py): it never
  takes the GIL from the camera stage, and once the first window is learned
  (skeleton/structure) it runs `registration_niceness` nicer and, with
  `registration_sched_idle`, in the idle scheduling class, so when the cores are short the
  joint node's Alg. 2 and then the live path go first, and growing the skeleton waits.
  A new rest pose (reset, stamps going back) starts a new child at full priority.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ..core.preprocess import Preprocessor
from ..core.registration import STATUS_OK, NonRigidRegistration
from ..core.rest_pose import RestPoseError
from ..core.segmentation import STATUS_NOBODY, SubjectSegmenter
from ..core.sequence import PARTIAL_VIEW_PATIENCE_FRAMES, RestPoseGate
from ..depth_image import DepthDecodeError, depth_to_cloud
from ..pointcloud import CloudDecodeError, decode_xyz
from .common import (LATCHED_QOS, SENSOR_QOS, STREAM_QOS, ThrottledLog, WorkingNode, declare_params, decode_or_warn,
                     release_freed_memory, run_node)
from .conversions import cloud_message, stamp_ns
from .diagnostics import OK, WARN, NodeDiagnostics
from .registration_process import ChildProcessDied, RegistrationProcess, RestPoseProcess
from .worker import Worker

SECTION = 'registration_node'
# The rest pose child (290 MB resident, Open3D loaded) waits warm this long with nobody in
# view, then is ended until a region moves: an idle robot does not carry it for hours, and a
# subject who comes at once does not wait for its start (bench/README.md)
REST_POSE_IDLE_RELEASE_S = 10.0


@dataclass
class _SubjectFrame:
    """What the camera stage hands to the registration stage: the epoch of the rest pose it
    belongs to, the cloud's header, the preprocessed subject (N, 3) m and the segmentation
    result without its mask (for the rest pose's wait for a whole subject; it counts the
    cloud's valid points)."""

    epoch: int
    header: object
    observed: np.ndarray
    segmentation: object


class RegistrationNode(WorkingNode):
    def __init__(self, **kwargs):
        super().__init__('registration_node', **kwargs)
        params = declare_params(self, SECTION)
        self.params, self.rest_params = params['registration'], params['rest_pose']
        self.preprocess_params, self.segmentation_params = params['preprocess'], params['segmentation']
        own = params['node']
        self.queue_size, self.learning_queue_size, self.lossless = own.queue_size, own.learning_queue_size, own.lossless
        reliability, self.input, self.live_start = own.input_reliability, own.input, own.live_start
        niceness, sched_idle = own.registration_niceness, own.registration_sched_idle
        self.log = ThrottledLog(self.get_logger())
        self.registered_pub = self.create_publisher(PointCloud2, 'registered_points', STREAM_QOS)
        self.filtered_pub = self.create_publisher(PointCloud2, 'filtered_points', STREAM_QOS)
        self.rest_pub = self.create_publisher(PointCloud2, 'rest_points', LATCHED_QOS)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/reset_background', self._on_reset_background)
        # whichever comes first (a joint node started on its own publishes only the description)
        self.create_subscription(String, 'skeleton/structure', self._on_structure, LATCHED_QOS)
        self.create_subscription(String, 'skeleton/description', self._on_description, LATCHED_QOS)
        # no skeleton described yet: the camera stage works only for the registration (_observe)
        self._described = False
        # the joint node's newest posed model (stamp ns, (M, 3)): where the next frame's
        # registration starts (live_start); frames registered from it, for /diagnostics
        self._posed = None
        self.registered_from_live_pose = 0
        self.create_subscription(PointCloud2, 'skeleton/posed_points', self._on_posed, STREAM_QOS)
        # set by the services, acted on by the camera stage before its next cloud
        self._background_reset_requested = False
        self._reset_requested = False
        # a new rest pose is wanted: the camera stage counts epochs, the registration
        # stage starts over when a cloud of a newer epoch reaches it (skips cannot lose it)
        self.epoch, self._registration_epoch = 0, 0
        self._start_camera()
        self.registration_process = RegistrationProcess(niceness, sched_idle)
        self.rest_pose_process = RestPoseProcess()
        self._start_registration()
        self._done = 0                 # clouds finished by either stage (tests, diagnostics)
        self._count_lock = threading.Lock()
        self.last_registration_status = 'no frame yet'
        self.camera = Worker(self._observe, 'camera', capacity=1, on_error=self._failed)
        self.registrar = Worker(self._register, 'registration', capacity=self.queue_size,
                                on_error=self._registration_failed)
        self._learn()
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
        if self.camera.submit((msg, self.camera_info)):
            self._warn_skipped()

    def _warn_skipped(self) -> None:
        camera, registration = self.camera.stats(), self.registrar.stats()
        if self.registrar.keep == 'oldest':
            policy = (f'learning_queue_size {self.registrar.capacity}; median '
                      f'{registration["latency_ms_median"]:.0f} ms per frame): the first window\'s '
                      'frames are registered in order, newer ones skipped until it is learned')
        else:
            policy = (f'queue_size {self.registrar.capacity}; median {registration["latency_ms_median"]:.0f} '
                      'ms per frame): the newest frames are registered')
        self.log.warn('skipped', f'{camera["dropped"]} cloud(s) skipped so far before segmentation '
                                 f'(median {camera["latency_ms_median"]:.0f} ms per cloud) and '
                                 f'{registration["dropped"]} skipped for registration ({policy}')

    @property
    def skipped(self) -> int:
        """Clouds dropped unprocessed (by either stage) because its queue was full."""
        return self.camera.dropped + self.registrar.dropped

    @property
    def processed(self) -> int:
        """Clouds handled to the end (registered, refused, or not passed on by the camera
        stage); processed + skipped reaches the clouds received."""
        return self._done

    def _on_structure(self, msg: String) -> None:
        if self.count_publishers('skeleton/description') == 0:
            self._described = True      # no joint node will describe it: nothing to wait for
        self._on_skeleton(msg)

    def _on_posed(self, msg: PointCloud2) -> None:
        # the newest to arrive (one writer publishes in stamp order; after stamps went back
        # a larger stamp is the older pose)
        points = decode_or_warn(msg, self.log, 'skeleton/posed_points', np.float64)
        if points is not None:
            self._posed = (stamp_ns(msg.header), points)

    def _live_start(self, stamp: int) -> np.ndarray | None:
        """(M, 3) the joint node's newest posed model, where this frame's registration starts,
        when it is of this rest pose, newer than the last registered frame and not newer than
        this one (else None: from the last registered frame, as Alg. 1).

        Why: once a skeleton is tracked the registration takes the newest camera frame, a
        second or more after the last one it registered; a limb that moved 30 cm since is
        beyond the E-step's reach, and frames that far apart take the most EM iterations.
        The live fit of a frame or two before this one is a few centimetres off instead
        (bench/README.md "Registration started from the live pose")."""
        posed = self._posed
        if not self.live_start or self.lossless or posed is None or self.rest_pose is None:
            return None
        posed_stamp, points = posed
        newest_registered = self._registered_stamp if self._registered_stamp is not None else self._rest_stamp
        if not newest_registered < posed_stamp <= stamp or points.shape != self.rest_pose.points.shape:
            return None
        if not np.isfinite(points).all():
            self.log.warn('posed', 'ignoring skeleton/posed_points with non-finite points')
            return None
        return points

    def _on_description(self, msg: String) -> None:
        self._described = True
        self._on_skeleton(msg)

    def _on_skeleton(self, _msg: String) -> None:
        """The first window is learned (skeleton/structure) or a skeleton tracked: from now on
        Alg. 2 and the live path come first; registration only grows the skeleton. Measured:
        at full priority beside it, Alg. 2 on the first 60-frame window took 23 s (not with
        lossless: there every frame waits for its registration, and a nicer one only slows all)."""
        if self.lossless:
            return
        if self.registrar.keep == 'oldest':
            # the backlog of the window's frames is not needed for growing the skeleton
            self.registrar.configure(self.queue_size, keep='newest')
            release_freed_memory()
        if not self.registration_process.lowered:
            self.registration_process.lower_priority()
            idle = ' in the idle scheduling class' if self.registration_process.in_idle_class else ''
            self.get_logger().info(f'the skeleton is learned: registration runs at nice '
                                   f'{self.registration_process.nice}{idle} and takes the newest frames '
                                   'from now on')

    def _learn(self) -> None:
        """Learning the first window: consecutive frames, in order (not with lossless, where
        every frame is registered anyway, with back-pressure)."""
        if not self.lossless:
            self.registrar.configure(self.learning_queue_size, keep='oldest')

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

    # -- camera stage ----------------------------------------------------------------------
    def _start_camera(self) -> None:
        self.segmenter = SubjectSegmenter(self.segmentation_params)
        self.preprocessor = Preprocessor(self.preprocess_params)
        self.last_stamp = None
        self.frame_id = None

    def _start_registration(self) -> None:
        self.rest_pose_gate = RestPoseGate(self.rest_params)
        self.rest_pose = None
        self._rest_stamp = self._registered_stamp = None
        self.rest_pose_process.warm()
        self._somebody_at = time.monotonic()

    def _rest_pose_process_while_waiting(self, status: str) -> None:
        """Warm while a subject may come; ended after REST_POSE_IDLE_RELEASE_S of nobody."""
        now = time.monotonic()
        if status != STATUS_NOBODY:
            self._somebody_at = now
            self.rest_pose_process.warm()
        elif self.rest_pose_process.is_warm and now - self._somebody_at > REST_POSE_IDLE_RELEASE_S:
            self.rest_pose_process.close()
            self.get_logger().info(f'nobody in view for {REST_POSE_IDLE_RELEASE_S:.0f} s: the rest pose '
                                   'process ends until something moves')

    def _start_over(self) -> None:
        """A new rest pose from the next good cloud (the registration stage sees the epoch)."""
        self._start_camera()
        self.epoch += 1
        self._described = False
        self._learn()

    def _observe(self, item) -> None:
        msg, info = item
        if self._reset_requested:
            self._reset_requested = False
            self._start_over()
        if self._background_reset_requested:
            self._background_reset_requested = False
            self.segmenter.reset()
        if not self._described and not self.lossless and self.registrar.full:
            # Until a skeleton is described nothing but the registration uses a subject
            # frame (no live fit yet), and a full queue would drop this one after its
            # segmentation: skip the decoding and segmentation too. The cores go to
            # registering the window and to Alg. 2 instead (the first skeleton 2.6 s sooner,
            # bench/README.md "Learning first"); the skip is counted as the queue's drop.
            self.registrar.refuse()
            self._warn_skipped()
            return
        if not self._segment_and_pass_on(msg, info):
            self._finished()

    def _diagnostics(self) -> tuple:
        """(level, state, values) for /diagnostics: WARN while there is no rest pose or
        when clouds were skipped since the last report. rate_out_hz / latency: the
        registration stage; filtered_*: the camera stage (what the live path gets)."""
        camera, registration = self.camera.stats(), self.registrar.stats()
        skipped = camera['dropped'] + registration['dropped']
        new_skips, self._reported_skips = skipped - self._reported_skips, skipped
        if camera['submitted'] == 0:
            level, state = WARN, f'waiting for input on {self.resolve_topic_name("points")}'
        elif self.rest_pose is None:
            level, state = WARN, f'waiting for the subject (no rest pose yet): {self.last_status}'
        else:
            level, state = ((WARN if new_skips else OK),
                            f'registering: {self.last_status}, {self.last_registration_status}')
        return level, state, {
            'rate_in_hz': camera['rate_in_hz'], 'filtered_rate_hz': camera['rate_hz'],
            'filtered_latency_ms_median': camera['latency_ms_median'],
            'rate_out_hz': registration['rate_hz'],
            'latency_ms_median': registration['latency_ms_median'],
            'latency_ms_p95': registration['latency_ms_p95'],
            'clouds_in': camera['submitted'], 'processed': self.processed, 'skipped': skipped,
            'skipped_for_registration': registration['dropped'],
            'failed': camera['failed'] + registration['failed'], 'waiting': registration['waiting'],
            'queue_size': self.registrar.capacity, 'lossless': self.lossless,
            'registration_nice': self.registration_process.nice,
            'registration_sched_idle': self.registration_process.in_idle_class,
            'registered_from_live_pose': self.registered_from_live_pose,
            # readers matched to both outputs (DDS drops what a volatile writer sends before)
            'outputs_matched': min(self.registered_pub.get_subscription_count(),
                                   self.filtered_pub.get_subscription_count()),
            'rest_points': 0 if self.rest_pose is None else len(self.rest_pose.points)}

    def _failed(self, item, error) -> None:
        """A cloud whose processing raised: one throttled line, the node goes on."""
        self._finished()
        if not self.context.ok():
            return   # Ctrl-C closed the context under a cloud in progress: its publish failed
        self.log.warn('failed', f'cloud at {stamp_ns(item[0].header) * 1e-9:.3f} s failed: '
                                f'{type(error).__name__}: {error}')

    def _registration_failed(self, item, error) -> None:
        if not self.context.ok():
            return
        self.log.warn('failed', f'registration of the cloud at {stamp_ns(item.header) * 1e-9:.3f} s failed: '
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

    def _segment_and_pass_on(self, msg, info) -> bool:
        """Decode, segment and preprocess one cloud, publish the subject on filtered_points
        and hand it to the registration stage; False when the cloud goes no further."""
        stamp, frame_id = stamp_ns(msg.header), msg.header.frame_id
        decoded = self._decode(msg, info)
        if decoded is None:
            return False
        raw, height, width = decoded
        if len(raw) > self.preprocess_params.max_input_points:
            self.log.warn('large', f'cloud of {len(raw)} points: randomly thinned to '
                                   f'preprocess.max_input_points = {self.preprocess_params.max_input_points}')
        if self.last_stamp is not None:
            if stamp == self.last_stamp:
                self.log.warn('duplicate', f'ignoring a second cloud with stamp {stamp * 1e-9:.3f} s')
                return False
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
        # without its per-pixel mask: up to learning_queue_size frames wait for registration
        frame = _SubjectFrame(self.epoch, msg.header, observed, segmentation.summary())
        if self.registrar.submit(frame, block=self.lossless):
            self._warn_skipped()
        return True

    # -- registration stage ------------------------------------------------------------------
    def _register(self, frame: '_SubjectFrame') -> None:
        try:
            self._register_frame(frame)
        finally:
            self._finished()

    def _register_frame(self, frame: '_SubjectFrame') -> None:
        if frame.epoch != self._registration_epoch:
            self._registration_epoch = frame.epoch
            self._start_registration()
            if self.registration_process.lowered:
                self.registration_process.restart()     # learning the new skeleton comes first
        stamp, observed, segmentation = stamp_ns(frame.header), frame.observed, frame.segmentation
        if self.rest_pose is None:
            self._rest_pose_process_while_waiting(segmentation.status)
            waiting = self.rest_pose_gate.reason_to_wait(segmentation, len(observed))
            if waiting == 'partial':
                self.log.warn('partial', 'no rest pose yet: the subject is only partly in view '
                                         f'(waiting up to {PARTIAL_VIEW_PATIENCE_FRAMES} frames for all of it)')
            elif waiting == 'few_points':
                self.log.warn('no_rest', f'no rest pose yet: only {len(observed)} points after preprocessing '
                                         f'(of {segmentation.n_valid} valid); is the subject in view?')
            if waiting is not None:
                return
            try:
                rest_pose = self.rest_pose_process.build(observed, self.rest_params)
            except RestPoseError as error:
                self.log.warn('no_rest', f'no rest pose from this cloud: {error}')
                return
            self.registration_process.install(NonRigidRegistration(rest_pose.points, self.params))
            self.rest_pose, self._rest_stamp = rest_pose, stamp
            release_freed_memory()
            self.rest_pub.publish(cloud_message(self.rest_pose.points, frame.header, float64=True))
            self.get_logger().info(f'rest pose built from the cloud at {stamp * 1e-9:.3f} s '
                                   f'({len(self.rest_pose.points)} points, frame {frame.header.frame_id!r})')
        start = self._live_start(stamp)
        try:
            result = self.registration_process.register_frame(observed, start)
        except ChildProcessDied:
            if not self.context.ok():
                return
            self.log.always('the registration process ended unexpectedly (out of memory? killed?): '
                            'starting a new one and a new rest pose')
            self.registration_process.restart()
            self._start_registration()
            return
        self.last_registration_status = f'frame {result.status}'
        if result.status != STATUS_OK:
            self.log.warn(f'status:{result.status}:{len(observed) == 0}',
                          f'cloud at {stamp * 1e-9:.3f} s not registered ({result.status}: '
                          f'{len(observed)} points after preprocessing); holding the last pose')
            return
        self._registered_stamp = stamp
        self.registered_from_live_pose += start is not None
        self.registered_pub.publish(cloud_message(result.points, frame.header))
        if self.registrar.processed % 100 == 99:
            stats = self.registrar.stats()
            self.get_logger().info(f'{self.registrar.processed + 1} frames through registration, latency median '
                                   f'{stats["latency_ms_median"]:.0f} ms, p95 {stats["latency_ms_p95"]:.0f} ms, '
                                   f'{self.skipped} skipped')

    def _finished(self) -> None:
        with self._count_lock:
            self._done += 1

    def stop_work(self) -> None:
        """Stop the camera and registration threads and the child processes (not the ROS
        entities: destroy_node)."""
        # the registration stage first: a lossless camera stage blocked on it wakes at once
        self.registrar.stop()
        self.camera.stop()
        self.registration_process.close()
        self.rest_pose_process.close()


def main(args=None) -> int:
    return run_node(RegistrationNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
