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

On a structure: Alg. 2 on the window's frames (found by stamp in a buffer of
`buffer_size` frames, or among the previous structure's frames, which are kept: a growing
skeleton's key frames can be older than the buffer) on a Worker (nodes/worker.py: one at
a time; a structure that arrives meanwhile waits, a newer one replaces it), then joints and
markers for every window frame that has none yet. Joint names carry the structure's
stable joint ids. With live_frames camera and provisional_skeleton, Step 2's skeleton
(each point on its bone) is described (`provisional: true`), published for the window and
tracked live first, while Alg. 2 runs; Alg. 2's model then replaces it, same names.
After that, live joints (`live_frames`):
- camera (default): every filtered_points frame (the registration node publishes one per
  camera frame, before registering it) gets the learned model fitted to its subject
  points (core.live.CameraTracker: started from the model's fit of the newest registered
  frame at or before it, up to a second old, and moved to the frame's points by the
  whole-body move and the joint weight ramp), on a latest-frame Worker: the joints never
  wait for registration, and a frame the fit cannot keep up with is skipped and counted. A
  frame whose fit diverges gets the registered pose's joints; a frame whose own
  registered points are already in gets their fit.
- registered: every registered frame gets the model fitted to its registered points
  (core.live.LiveJointTracker), as `skel-extract run` does: none is skipped (lossless
  replay).
In both, when a model is ready, the registered frames that have no joints yet and are not
in its window (between key frames, in none because a pair completed late, or arrived
while Alg. 2 ran) are tracked and published.
"""
from __future__ import annotations

import collections
import threading
import time

import numpy as np
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String

from ..core.joints import JointEstimation
from ..core.live import ArticulatedTracker, CameraTracker, LiveJointTracker
from ..core.point_sets import finite_rows
from ..core.skeleton_model import SkeletonModel
from ..core.structure import SkeletalStructure
from .common import (LATCHED_QOS, STREAM_QOS, StampPairer, ThrottledLog, WorkingNode,
                     declare_params, decode_or_warn, decode_registered_or_warn, decode_rest_or_warn,
                     on_live_parameters, release_freed_memory, run_node)
from ..codecs.messages import cloud_message, parse_structure, stamp_ns
from .diagnostics import OK, WARN, NodeDiagnostics
from .skeleton_output import SkeletonOutput, registered_hints
from .worker import RateMeter, Worker

SECTION = 'joint_estimation_node'


class JointEstimationNode(WorkingNode):
    def __init__(self, **kwargs):
        super().__init__('joint_estimation_node', **kwargs)
        params = declare_params(self, SECTION)
        self.params, own = params['joints'], params['node']
        self.buffer_size, self.live_sweeps = own.buffer_size, own.live_sweeps
        self.joint_diameter = own.joint_diameter
        self.provisional_skeleton = own.provisional_skeleton
        self.live_frames, self.live_iterations = own.live_frames, own.live_iterations
        self.log = ThrottledLog(self.get_logger())
        on_live_parameters(self, SECTION, self._apply_parameters)
        # description, joints, trajectory, confidence, markers (nodes/skeleton_output.py)
        self.output = SkeletonOutput(self, self.joint_diameter)
        self.markers_pub = self.output.markers_pub
        # the model posed at each fitted camera frame: the registration starts from it
        self.posed_pub = self.create_publisher(PointCloud2, 'skeleton/posed_points', STREAM_QOS)
        self._lock = threading.Lock()
        self.rest, self.rest_stamp = None, None
        self.buffer = collections.OrderedDict()   # stamp ns -> (header, registered (M, 3), filtered (N, 3))
        self.kept = {}                            # the last structure's frames, by stamp, kept past the buffer
        self.pairer = StampPairer()
        self.registered_only = collections.OrderedDict()  # stamp -> (header, registered): live input
        self.tracker = None                  # LiveJointTracker of the current model
        self.described = None                # its DescribedSkeleton (names, version)
        self.camera_tracker = None           # its CameraTracker (live_frames camera)
        self.model_parents = None
        self._provisional = False            # the tracked model is Step 2's, Alg. 2 still running
        self.last_published = None           # stamp of the newest frame with joints published
        self._early_structure = None
        # Alg. 2 runs for seconds beside the live fit of every camera frame: below it
        self.estimator = Worker(self._estimate, 'joints', capacity=1, on_error=self._estimation_failed,
                                niceness=own.estimation_niceness)
        self.live_ms = collections.deque(maxlen=1000)      # per live frame fit
        self.registered_rate, self.joints_rate = RateMeter(), RateMeter()
        self.live_fits = {'fitted': 0, 'lost': 0, 'registered': 0, 'too_few_points': 0}
        self.live = Worker(self._live_camera_frame, 'live', capacity=1, on_error=self._live_failed)
        self.create_subscription(PointCloud2, 'rest_points', self._on_rest, LATCHED_QOS)
        self.create_subscription(PointCloud2, 'registered_points', self._on_registered, STREAM_QOS)
        self.create_subscription(PointCloud2, 'filtered_points', self._on_filtered, STREAM_QOS)
        self.create_subscription(String, 'skeleton/structure', self._on_structure, LATCHED_QOS)
        self.diagnostics = NodeDiagnostics(self, self._diagnostics)
        self.get_logger().info('waiting for skeleton/structure')

    def _apply_parameters(self, params: dict, _changed: set) -> None:
        """`ros2 param set` (the live parameters): the method's parameters and
        provisional_skeleton apply from the next structure (Alg. 2 and the trackers of the
        model it gives), the rest from the next frame."""
        own = params['node']
        with self._lock:
            self.params = params['joints']
            self.buffer_size, self.provisional_skeleton = own.buffer_size, own.provisional_skeleton
            self.live_sweeps, self.live_iterations = own.live_sweeps, own.live_iterations
            self.output.joint_diameter = float(own.joint_diameter)
            if self.tracker is not None:       # the model tracked now, from its next frame
                self.tracker.sweeps = self.live_sweeps
                self.camera_tracker.tracker.iterations = self.live_iterations

    # -- inputs ----------------------------------------------------------------------------
    def _on_rest(self, msg: PointCloud2) -> None:
        decoded = decode_rest_or_warn(msg, self.log)
        if decoded is None:
            return
        rest, rest_stamp = decoded
        with self._lock:
            self.rest, self.rest_stamp = rest, rest_stamp
            # frames of this rest pose may have come in before it (two topics, no order)
            for frames in (self.buffer, self.registered_only, self.kept):
                for stamp in [s for s in frames if s < rest_stamp]:
                    del frames[stamp]
            had_model = self.tracker is not None
            self.tracker, self.camera_tracker, self.last_published = None, None, None
            early, self._early_structure = self._early_structure, None
        if had_model:
            self.get_logger().info('new rest pose: live joints pause until the next skeleton/structure')
        if early is not None:
            self._on_structure(early)

    def _on_filtered(self, msg: PointCloud2) -> None:
        points = decode_or_warn(msg, self.log, 'filtered_points')
        if points is None:
            return
        self._pair(1, msg.header, points)
        if self.live_frames == 'camera' and self.tracker is not None:
            if self.live.submit((msg.header, points)):
                stats = self.live.stats()
                self.log.warn('live_skipped', f'the live fit is slower than the camera: {stats["dropped"]} '
                                              f'frame(s) skipped so far (median {stats["latency_ms_median"]:.0f} '
                                              'ms per frame)')

    def _on_registered(self, msg: PointCloud2) -> None:
        self.registered_rate.tick()
        points = decode_registered_or_warn(msg, self.log, self.rest)
        if points is None:
            return
        stamp = stamp_ns(msg.header)
        with self._lock:
            self.registered_only[stamp] = (msg.header, points)
            while len(self.registered_only) > self.buffer_size:
                self.registered_only.popitem(last=False)
        self._pair(0, msg.header, points)
        if self.live_frames == 'registered':
            self._publish_live()

    def _pair(self, side: int, header, points) -> None:
        stamp = stamp_ns(header)
        with self._lock:
            pair = self.pairer.add(side, stamp, (header, points))
            if pair is None:
                return
            (header, registered), (_, filtered) = pair
            self.buffer[stamp] = (header, registered, filtered)
            while len(self.buffer) > self.buffer_size:
                self.buffer.popitem(last=False)

    # -- Alg. 2 on a window ------------------------------------------------------------------
    def _on_structure(self, msg: String) -> None:
        try:
            document = parse_structure(msg.data)
        except ValueError as error:
            self.log.warn('structure', f'ignoring skeleton/structure: {error}')
            return
        with self._lock:
            if self.rest_stamp is None or document['rest_stamp_ns'] > self.rest_stamp:
                # its rest pose is still on the way (latched topics arrive in any order)
                self._early_structure = msg
                return
            if document['rest_stamp_ns'] != self.rest_stamp:
                self.log.warn('structure', 'skeleton/structure is for an older rest pose than the '
                                           'current rest_points: ignored')
                return
            if len(document['labels']) != len(self.rest):
                self.log.warn('structure', f'skeleton/structure labels {len(document["labels"])} points, '
                                           f'the rest pose has {len(self.rest)}: ignored')
                return
            wanted = document['window_stamps_ns']
            available = {**self.kept, **self.buffer}
            found = [s for s in wanted if s in available]
            if len(found) < len(wanted):
                self.get_logger().warning(f'{len(wanted) - len(found)} of the {len(wanted)} window frames '
                                          f'are not in the buffer (buffer_size {self.buffer_size}); '
                                          f'estimating joints on the {len(found)} available')
            if len(found) < 2:
                self.get_logger().warning('fewer than 2 window frames available: structure ignored')
                return
            frames = [available[s] for s in found]
            self.kept = dict(zip(found, frames))
            rest = self.rest
        if not self.estimator.idle:
            self.get_logger().info('joint estimation running: the new structure waits (a newer one replaces it)')
        self.estimator.submit((document, rest, found, frames))

    @property
    def estimating(self) -> bool:
        """Alg. 2 is running or a structure waits for it."""
        return not self.estimator.idle

    def _diagnostics(self) -> tuple:
        """(level, state, values) for /diagnostics."""
        with self._lock:
            tracking = self.tracker is not None
            n_joints = 0 if self.model_parents is None else len(self.model_parents)
            has_rest = self.rest is not None
        live = sorted(self.live_ms.copy())      # copy(): atomic against the appending thread
        if self.estimating:
            meanwhile = f'; tracking {n_joints} joints meanwhile' if tracking else ''
            level, state = OK, 'estimating joints (Alg. 2)' + meanwhile
        elif tracking:
            level, state = OK, f'tracking {n_joints} joints'
        else:
            level, state = WARN, 'waiting for skeleton/structure' if has_rest else 'waiting for rest_points'
        return level, state, {
            'rate_in_hz': self.registered_rate.rate(), 'rate_out_hz': self.joints_rate.rate(),
            'live_fit_ms_median': live[len(live) // 2] if live else float('nan'),
            'live_fit_ms_p95': live[int(0.95 * (len(live) - 1))] if live else float('nan'),
            'estimations': self.estimator.processed, 'failed': self.estimator.failed,
            'structures_replaced': self.estimator.dropped, 'joints': n_joints, 'live_frames': self.live_frames,
            'camera_frames_skipped': self.live.dropped, 'camera_frames_in_hz': self.live.rate_in.rate(),
            **{f'live_{k}': v for k, v in self.live_fits.items()}}

    def _estimation_failed(self, _job, error) -> None:
        self.get_logger().error(f'joint estimation failed: {type(error).__name__}: {error} '
                                '(serving the previous model)')

    def _estimate(self, job) -> None:
        document, rest, stamps, frames = job
        started = time.perf_counter()
        registered = np.stack([f[1] for f in frames]).astype(np.float64)
        observed = [f[2] for f in frames]
        labels, parents = document['labels'], document['parents']
        # the structure's rigid fits at the frames found (the key frames the buffer had)
        found = [document['window_stamps_ns'].index(stamp) for stamp in stamps]
        rotations, translations = document['rotations'][found], document['translations'][found]
        structure = SkeletalStructure(labels, parents, rotations, translations, document['joints'],
                                      document['boundary_centroids'])
        if self.provisional_skeleton and self.live_frames == 'camera':
            # Step 2's skeleton, each point on its bone, is tracked while Alg. 2 runs (seconds),
            # so joints come before Alg. 2's; Alg. 2's model then replaces it under the same
            # joint names. Not with live_frames
            # registered: lossless replay publishes Alg. 2's joints for the window, as run does.
            step2 = SkeletonModel(rest, labels, parents, structure.joints, labels[:, None],
                                  np.ones((len(rest), 1)), document['joint_ids'])
            self._serve(step2, document, stamps, frames, (rotations, translations), started, provisional=True)
        estimate = JointEstimation(self.params).fit(rest, registered, observed, structure)
        model = estimate.model(rest, labels, document['joint_ids'])
        self._serve(model, document, stamps, frames, (estimate.rotations, estimate.translations), started)
        release_freed_memory()

    def _serve(self, model: SkeletonModel, document: dict, stamps: list, frames: list,
               window_pose: tuple, started: float, provisional: bool = False) -> None:
        """Publish model's description, the joints of the window frames that have none yet
        (window_pose: the model's bone rotations (F, B, 3, 3) and translations (F, B, 3) at
        them), then track it live (on the registered frames without joints first).
        provisional: Step 2's model, which Alg. 2's will replace."""
        with self._lock:
            stale = self.rest is not model.rest_points
            refining = self.tracker is not None and self._provisional
        if stale:
            # a new rest pose came while this window's model was learned: its frames are
            # another subject's (or the same one started over), and the next structure's
            # model serves them
            self.get_logger().info('a new rest pose came while the joints were estimated: this model '
                                   'is not used')
            return
        tracker = LiveJointTracker(model, self.params, self.live_sweeps)
        camera = CameraTracker(ArticulatedTracker(model, self.params, iterations=self.live_iterations), tracker)
        # the refinement of a provisional description lists no changes: same joints, same tree
        changes = {} if refining and not provisional else document['changes']
        window = [(stamp, header, *self._registered_outputs(model, tracker, registered, rotations, translations))
                  for stamp, (header, registered, _), rotations, translations in zip(stamps, frames, *window_pose)]
        # the skeleton's confidence: each joint's median over the frames it was learned on
        confidence = np.median([frame[-1] for frame in window], axis=0)
        described = self.output.describe(model, document['frame_id'], stamps, changes, provisional, confidence)
        with self._lock:
            done = self.last_published
        # a frame that already has joints (live, from the previous model) is not published
        # twice: a growing skeleton's key frames can be minutes old
        for stamp, header, positions, hints, frame_confidence in window:
            if done is None or stamp > done:
                self._publish_joints(described, header, positions, hints, frame_confidence)
        in_window = set(stamps)
        with self._lock:
            # registered frames without joints that are not in the window (between key frames,
            # left out of it when a pair completed late, or arrived during Alg. 2) get the model's
            # tracking now. A previous model has been giving live joints meanwhile: only frames
            # newer than those are new then (none is published twice).
            since = done if self.tracker is None else self.last_published
            catch_up = [(s, v) for s, v in self.registered_only.items()
                        if (since is None or s > since) and s not in in_window]
            self.tracker, self.camera_tracker, self.model_parents = tracker, camera, model.parents
            self.described = described
            self._provisional = provisional
            published = [stamps[-1]] + [s for s, _ in catch_up[-1:]]
            self.last_published = max(published + [self.last_published or published[0]])
        what = 'Step 2, provisional while Alg. 2 runs' if provisional else 'Alg. 2'
        self.get_logger().info(f'{model.n_joints} joints from {len(stamps)} frames in '
                               f'{time.perf_counter() - started:.1f} s ({what}); publishing live joints'
                               + (f' ({len(catch_up)} more frames tracked)' if catch_up else ''))
        self._publish_tracked(tracker, described, catch_up)

    # -- live --------------------------------------------------------------------------------
    def _publish_live(self) -> None:
        """Joints for every registered frame newer than the last published one."""
        with self._lock:
            if self.tracker is None:
                return
            todo = [(s, v) for s, v in self.registered_only.items() if s > self.last_published]
            tracker, described = self.tracker, self.described
            if todo:
                self.last_published = todo[-1][0]
        self._publish_tracked(tracker, described, todo)

    def _publish_tracked(self, tracker, described, frames: list) -> None:
        """Publish tracker joints for [(stamp, (header, registered (M, 3)))] in order."""
        for _stamp, (header, registered) in frames:
            started = time.perf_counter()
            rotations, translations = tracker.fit(registered)
            self.live_ms.append(1000.0 * (time.perf_counter() - started))
            self._publish_registered(described, tracker, header, registered, rotations, translations)

    def _publish_registered(self, described, tracker, header, registered, rotations, translations) -> None:
        """Publish a registered frame's joints (see _registered_outputs)."""
        self._publish_joints(described, header,
                             *self._registered_outputs(described.model, tracker, registered, rotations, translations))

    @staticmethod
    def _registered_outputs(model, tracker, registered, rotations, translations) -> tuple:
        """(positions (J, 3) m, twist hints (B, 3, 3), confidence (J,)) of a registered frame
        (M, 3) from the model's bone transforms at it (rotations (B, 3, 3), translations
        (B, 3)): twist and confidence from its registered points."""
        return (tracker.joints_of(rotations, translations), registered_hints(model, registered),
                tracker.confidence(rotations, translations, registered, corresponding=True))

    def _live_camera_frame(self, item) -> None:
        """Joints for one camera frame (live_frames camera), on the live Worker."""
        header, observed = item
        stamp = stamp_ns(header)
        with self._lock:
            if self.tracker is None or (self.last_published is not None and stamp <= self.last_published):
                return
            newest = [s for s in self.registered_only if s <= stamp]
            if not newest:
                return
            registered_stamp = newest[-1]
            registered = self.registered_only[registered_stamp][1]
            camera, described = self.camera_tracker, self.described
            self.last_published = stamp
        started = time.perf_counter()
        camera.registered(registered_stamp, registered)      # nothing to do when already taken
        if registered_stamp != stamp and finite_rows(observed).sum() < 10:
            self.log.warn('live_empty', f'camera frame at {stamp * 1e-9:.3f} s has {len(observed)} subject '
                                        'points: no live joints (subject out of view?)')
            self.live_fits['too_few_points'] += 1
            return
        positions, outcome = camera.track(stamp, observed)
        self.live_fits[outcome] += 1
        self.live_ms.append(1000.0 * (time.perf_counter() - started))
        rotations, translations = camera.pose
        # the fit's own bone rotations give the twist; the confidence is the served pose's
        # against this frame's points (a lost frame's registered pose scores what it explains)
        self._publish_joints(described, header, positions, rotations,
                             camera.tracker.confidence(rotations, translations, observed, corresponding=False))
        posed = camera.posed_points()
        if posed is not None:
            self.posed_pub.publish(cloud_message(posed, header))

    def _live_failed(self, item, error) -> None:
        """item: (header, points) of the camera frame whose fit or publish raised."""
        if not self.context.ok():
            return   # Ctrl-C closed the context under a frame in progress: its publish failed
        self.log.warn('live_failed', f'live joints for the camera frame at {stamp_ns(item[0]) * 1e-9:.3f} s '
                                     f'failed: {type(error).__name__}: {error}')

    def _publish_joints(self, described, header, positions, hints, confidence) -> None:
        """positions (J, 3) m; hints (B, 3, 3) the fit's bone rotations; confidence (J,)."""
        self.joints_rate.tick()
        self.output.publish(described, header, positions, hints, confidence)

    def stop_work(self) -> None:
        """Stop Alg. 2's and the live fit's threads (not the ROS entities: destroy_node)."""
        self.estimator.stop()
        self.live.stop()


def main(args=None) -> int:
    return run_node(JointEstimationNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
