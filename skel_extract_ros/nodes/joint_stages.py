"""The joint estimation node's work, without ROS: the frames it keeps (registered and
filtered pairs for Alg. 2, registered frames for the live answers), Alg. 2 on each
structure's window on a Worker (one at a time; a newer structure replaces a waiting one,
or, with `lossless`, waits behind it), the model served (Step 2's provisional one first),
and the live joints: the learned model fitted to every camera frame
(core.live.CameraTracker, live_frames camera) or to every registered frame
(core.live.LiveJointTracker, live_frames registered). What it publishes goes through the
node's SkeletonOutput (nodes/skeleton_output.py).
"""
from __future__ import annotations

import collections
import copy
import threading
import time

import numpy as np

from ..codecs.messages import set_stamp_ns, stamp_ns
from ..core.articulated import blend, dense_weights
from ..core.confidence import fit_noise
from ..core.joints import JointEstimation
from ..core.live import CameraTracker, LiveJointTracker
from ..core.point_sets import finite_rows
from ..core.skeleton_model import SkeletonModel
from ..core.structure import SkeletalStructure
from .common import StampPairer, release_freed_memory
from .skeleton_output import registered_hints
from .worker import LOSSLESS_CAPACITY, RateMeter, Worker

# structures whose moved joints wait for a description, at most (Alg. 2 failing on each)
MAX_UNDESCRIBED = 32
# the camera's frame period is the median interval of this many newest frames' stamps
CAMERA_PERIOD_FRAMES = 30


class JointStages:
    """params: JointParams; settings: the node's own parameters (JointNodeParams); output:
    the node's SkeletonOutput; publish_posed(points (M, 3), header); log: ThrottledLog;
    logger: the node's logger; context_ok() False once ROS shuts down."""

    def __init__(self, params, settings, output, publish_posed, log, logger, context_ok):
        self.params, self.output, self.publish_posed = params, output, publish_posed
        self.log, self.logger, self.context_ok = log, logger, context_ok
        self.buffer_size, self.live_sweeps = settings.buffer_size, settings.live_sweeps
        self.provisional_skeleton, self.live_chain = settings.provisional_skeleton, settings.live_chain
        self.live_limb_poses = settings.live_limb_poses
        self.live_frames, self.live_iterations = settings.live_frames, settings.live_iterations
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
        self.last_published = None           # stamp of the newest frame with joints published
        # the newest camera frame the live fit answered: (its DescribedSkeleton, (stamp ns,
        # header, positions (J, 3), hints, confidence (J,))); None after a frame without joints
        self._last_fitted = None
        self._early_structure = None
        self._moved = []                     # (structure number, joint names it moved), not yet described
        self._structures = 0                 # structures accepted so far: each job's number
        # Alg. 2 runs for seconds beside the live fit of every camera frame: below it.
        # Lossless, every structure waits its turn
        self.lossless = settings.lossless
        self.estimator = Worker(self._estimate, 'joints', capacity=LOSSLESS_CAPACITY if self.lossless else 1,
                                on_error=self._estimation_failed, niceness=settings.estimation_niceness)
        self.live_ms = collections.deque(maxlen=1000)      # per live frame fit
        self.joints_rate = RateMeter()
        self.live_fits = {'fitted': 0, 'chained': 0, 'lost': 0, 'registered': 0, 'too_few_points': 0,
                          'chain_skipped': 0, 'reposed': 0, 'interpolated': 0}
        self._camera_stamps = collections.deque(maxlen=CAMERA_PERIOD_FRAMES + 1)   # the newest frames' stamps, ns
        self.live = Worker(self._live_camera_frame, 'live', capacity=1, on_error=self._live_failed)

    def apply(self, params, settings) -> None:
        """New parameters (`ros2 param set`): the method's, provisional_skeleton, live_chain
        and live_limb_poses from the next structure (Alg. 2 and the trackers of the model it
        gives), the rest from the next frame."""
        with self._lock:
            self.params = params
            self.buffer_size, self.provisional_skeleton = settings.buffer_size, settings.provisional_skeleton
            self.live_chain, self.live_limb_poses = settings.live_chain, settings.live_limb_poses
            self.live_sweeps, self.live_iterations = settings.live_sweeps, settings.live_iterations
            self.output.joint_diameter = float(settings.joint_diameter)
            if self.tracker is not None:       # the model tracked now, from its next frame
                self.tracker.sweeps = self.live_sweeps
                for tracker in (self.camera_tracker.tracker, self.camera_tracker.chain):
                    if tracker is not None:
                        tracker.iterations = self.live_iterations

    @property
    def estimating(self) -> bool:
        """Alg. 2 is running or a structure waits for it."""
        return not self.estimator.idle

    def status(self) -> tuple:
        """(tracking, number of joints, has a rest pose) now."""
        with self._lock:
            return (self.tracker is not None, 0 if self.model_parents is None else len(self.model_parents),
                    self.rest is not None)

    def stop(self) -> None:
        """Stop Alg. 2's and the live fit's threads."""
        self.estimator.stop()
        self.live.stop()

    # -- the frames ----------------------------------------------------------------------------
    def rest_pose(self, rest: np.ndarray, rest_stamp: int) -> None:
        """A new rest pose Q (M, 3) stamped rest_stamp (ns): frames and model of the old go."""
        with self._lock:
            self.rest, self.rest_stamp = rest, rest_stamp
            # frames of this rest pose may have come in before it (two topics, no order)
            for frames in (self.buffer, self.registered_only, self.kept):
                for stamp in [s for s in frames if s < rest_stamp]:
                    del frames[stamp]
            had_model = self.tracker is not None
            self.tracker, self.camera_tracker, self.last_published = None, None, None
            self._last_fitted = None
            early, self._early_structure = self._early_structure, None
            self._moved.clear()
        if had_model:
            self.logger.info('new rest pose: live joints pause until the next skeleton/structure')
        if early is not None:
            self.structure(early)

    def filtered(self, header, points: np.ndarray) -> None:
        """A camera frame's subject points (N, 3): paired with its registered frame for Alg.
        2, and fitted live (live_frames camera)."""
        arrived = time.perf_counter()       # the frame's deadline counts from here
        self._pair(1, header, points)
        with self._lock:
            self._camera_stamps.append(stamp_ns(header))
        if self.live_frames == 'camera' and self.tracker is not None:
            if self.live.submit((header, points, arrived)):
                stats = self.live.stats()
                self.log.warn('live_skipped', f'the live fit is slower than the camera: {stats["dropped"]} '
                                              f'frame(s) skipped so far (median {stats["latency_ms_median"]:.0f} '
                                              'ms per frame)')

    def registered(self, header, points: np.ndarray) -> None:
        """A registered frame (M, 3): paired for Alg. 2, and answered (live_frames registered)."""
        stamp = stamp_ns(header)
        with self._lock:
            self.registered_only[stamp] = (header, points)
            while len(self.registered_only) > self.buffer_size:
                self.registered_only.popitem(last=False)
        self._pair(0, header, points)
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
    def structure(self, document: dict) -> None:
        """A parsed skeleton/structure: Alg. 2 on its window's frames (on the estimator)."""
        with self._lock:
            if self.rest_stamp is None or document['rest_stamp_ns'] > self.rest_stamp:
                # its rest pose is still on the way (latched topics arrive in any order)
                self._early_structure = document
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
                self.logger.warning(f'{len(wanted) - len(found)} of the {len(wanted)} window frames '
                                          f'are not in the buffer (buffer_size {self.buffer_size}); '
                                          f'estimating joints on the {len(found)} available')
            if len(found) < 2:
                self.logger.warning('fewer than 2 window frames available: structure ignored')
                return
            frames = [available[s] for s in found]
            self.kept = dict(zip(found, frames))
            # a structure Alg. 2 skips (a newer one replaces it while it waits) still moved
            # its joints: the next structure's description lists them
            self._structures += 1
            sequence = self._structures
            self._moved.append((sequence, document['changes'].get('moved', [])))
            if len(self._moved) > MAX_UNDESCRIBED:
                # Alg. 2 failing structure after structure: the oldest two become one entry
                # (their names go with the newer one's description), so this stays bounded
                (_, older), (number, newer) = self._moved[:2]
                self._moved[:2] = [(number, older + newer)]
            rest = self.rest
        if not self.estimator.idle:
            self.logger.info('joint estimation running: the new structure waits '
                             + ('its turn' if self.lossless else '(a newer one replaces it)'))
        if self.estimator.submit((document, rest, found, frames, sequence)) and self.lossless:
            self.log.warn('structures_dropped', f'{LOSSLESS_CAPACITY} structures wait for Alg. 2: the oldest is '
                                                'dropped (Alg. 2 is much slower than the accumulator)')

    def _estimation_failed(self, _job, error) -> None:
        self.logger.error(f'joint estimation failed: {type(error).__name__}: {error} '
                                '(serving the previous model)')

    def _estimate(self, job) -> None:
        document, rest, stamps, frames, sequence = job
        started = time.perf_counter()
        registered = np.stack([f[1] for f in frames]).astype(np.float64)
        observed = [f[2] for f in frames]
        labels, parents = document['labels'], document['parents']
        # the structure's rigid fits at the frames found (the key frames the buffer had)
        found = [document['window_stamps_ns'].index(stamp) for stamp in stamps]
        rotations, translations = document['rotations'][found], document['translations'][found]
        structure = SkeletalStructure(labels, parents, rotations, translations, document['joints'],
                                      document['boundary_centroids'], anchor_spread=document['anchor_spread'],
                                      depth_rays=document['depth_rays'])
        if self.provisional_skeleton and self.live_frames == 'camera':
            # Step 2's skeleton, each point on its bone, is tracked while Alg. 2 runs (seconds),
            # so joints come before Alg. 2's; Alg. 2's model then replaces it under the same
            # joint names. Not with live_frames
            # registered: lossless replay publishes Alg. 2's joints for the window, as run does.
            own_bone, full_weight = labels[:, None], np.ones((len(rest), 1))
            # its noise: how far the window's observed points lie from its bones' rigid fits
            posed = blend(rest, dense_weights(own_bone, full_weight, len(parents)), rotations, translations)
            noise = fit_noise(posed, observed)
            step2 = SkeletonModel(rest, labels, parents, structure.joints, own_bone, full_weight,
                                  document['joint_ids'], structure.pivot_evidence(),
                                  None if noise is None else max(noise, np.sqrt(3.0 * self.params.min_tau)))
            self._serve(step2, document, sequence, stamps, frames, (rotations, translations), started,
                        provisional=True)
        estimate = JointEstimation(self.params).fit(rest, registered, observed, structure)
        model = estimate.model(rest, labels, document['joint_ids'])
        self._serve(model, document, sequence, stamps, frames, (estimate.rotations, estimate.translations), started)
        release_freed_memory()

    def _serve(self, model: SkeletonModel, document: dict, sequence: int, stamps: list, frames: list,
               window_pose: tuple, started: float, provisional: bool = False) -> None:
        """Publish model's description, the joints of the window frames that have none yet
        (window_pose: the model's bone rotations (F, B, 3, 3) and translations (F, B, 3) at
        them), then track it live (on the registered frames without joints first).
        sequence: the structure's number (its description lists the joints it and the
        structures skipped before it moved); provisional: Step 2's model, which Alg. 2's
        will replace."""
        with self._lock:
            stale = self.rest is not model.rest_points
        if stale:
            # a new rest pose came while this window's model was learned: its frames are
            # another subject's (or the same one started over), and the next structure's
            # model serves them
            self.logger.info('a new rest pose came while the joints were estimated: this model '
                                   'is not used')
            return
        tracker = LiveJointTracker(model, self.params, self.live_sweeps)
        # the window's poses are the key frames the model was learned on: the limbs' poses
        camera = CameraTracker.for_model(model, self.params, tracker, self.live_iterations, chain=self.live_chain,
                                         key_poses=window_pose if self.live_limb_poses else None)
        window = [(stamp, header, *self._registered_outputs(model, tracker, registered, rotations, translations,
                                                            observed))
                  for stamp, (header, registered, observed), rotations, translations
                  in zip(stamps, frames, *window_pose)]
        # the skeleton's confidence: each joint's median over the frames it was learned on
        confidence = np.median([frame[-1] for frame in window], axis=0)
        with self._lock:
            # what this structure and those skipped before it moved (none when Alg. 2's model
            # refines Step 2's: described with it)
            through = sum(1 for number, _ in self._moved if number <= sequence)
            moved = {name for _, names in self._moved[:through] for name in names}
            del self._moved[:through]
        described = self.output.describe(model, document['frame_id'], stamps, moved, provisional, confidence)
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
            published = [stamps[-1]] + [s for s, _ in catch_up[-1:]]
            self.last_published = max(published + [self.last_published or published[0]])
        what = 'Step 2, provisional while Alg. 2 runs' if provisional else 'Alg. 2'
        self.logger.info(f'{model.n_joints} joints from {len(stamps)} frames in '
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
        for stamp, (header, registered) in frames:
            started = time.perf_counter()
            rotations, translations = tracker.fit(registered)
            self.live_ms.append(1000.0 * (time.perf_counter() - started))
            with self._lock:
                paired = self.buffer.get(stamp)
            self._publish_joints(described, header, *self._registered_outputs(
                described.model, tracker, registered, rotations, translations,
                None if paired is None else paired[2]))

    @staticmethod
    def _registered_outputs(model, tracker, registered, rotations, translations, observed) -> tuple:
        """(positions (J, 3) m, twist hints (B, 3, 3), confidence (J,)) of a registered frame
        (M, 3) from the model's bone transforms at it (rotations (B, 3, 3), translations
        (B, 3)): twist and confidence from its registered points, the confidence also from
        the silhouette of the frame's observed points (N, 3) when its filtered_points came
        (None: not)."""
        return (tracker.joints_of(rotations, translations), registered_hints(model, registered),
                tracker.confidence(rotations, translations, registered, True, observed))

    def _live_camera_frame(self, item) -> None:
        """Joints for one camera frame (live_frames camera), on the live Worker."""
        header, observed, arrived = item
        stamp = stamp_ns(header)
        with self._lock:
            period = camera_period(self._camera_stamps)
            if self.tracker is None or (self.last_published is not None and stamp <= self.last_published):
                return
            newest = [s for s in self.registered_only if s <= stamp]
            if not newest:
                return
            registered_stamp = newest[-1]
            registered = self.registered_only[registered_stamp][1]
            camera, described = self.camera_tracker, self.described
            self.last_published = stamp
            last_fitted, self._last_fitted = self._last_fitted, None
            # the camera frames since the last one fitted (by this model) that the live fit had
            # no time for (the Worker kept the newest): answered below, between the two
            previous = last_fitted[1] if last_fitted is not None and last_fitted[0] is described else None
            unanswered = [] if previous is None else [s for s in self._camera_stamps if previous[0] < s < stamp]
        started = time.perf_counter()
        camera.registered(registered_stamp, registered)      # nothing to do when already taken
        if registered_stamp != stamp and finite_rows(observed).sum() < 10:
            self.log.warn('live_empty', f'camera frame at {stamp * 1e-9:.3f} s has {len(observed)} subject '
                                        'points: no live joints (subject out of view?)')
            self.live_fits['too_few_points'] += 1
            return
        # done before the next frame comes: a second fit that does not fit in the camera's
        # period would cost frames (CameraTracker)
        skipped, reposed = camera.chain_skipped, camera.counts['reposed']
        positions, outcome = camera.track(stamp, observed, None if period is None else arrived + period)
        self.live_fits[outcome] += 1
        self.live_fits['chain_skipped'] += camera.chain_skipped - skipped
        self.live_fits['reposed'] += camera.counts['reposed'] - reposed
        self.live_ms.append(1000.0 * (time.perf_counter() - started))
        current = (stamp, header, positions, np.array(camera.pose[0]), np.array(camera.confidence))
        for unanswered_stamp in unanswered:
            self._publish_joints(described, *interpolated_frame(previous, current, unanswered_stamp),
                                 interpolated=True)
        self.live_fits['interpolated'] += len(unanswered)
        with self._lock:
            if self.last_published == stamp:     # no rest pose came meanwhile
                self._last_fitted = (described, current)
        # the fit's own bone rotations give the twist; the confidence is the served pose's
        # against this frame's points (a lost frame's registered pose scores what it explains)
        self._publish_joints(described, header, positions, camera.pose[0], camera.confidence)
        posed = camera.posed_points()
        if posed is not None:
            self.publish_posed(posed, header)

    def _live_failed(self, item, error) -> None:
        """item: (header, points, arrival time) of the camera frame whose fit or publish raised."""
        if not self.context_ok():
            return   # Ctrl-C closed the context under a frame in progress: its publish failed
        self.log.warn('live_failed', f'live joints for the camera frame at {stamp_ns(item[0]) * 1e-9:.3f} s '
                                     f'failed: {type(error).__name__}: {error}')

    def _publish_joints(self, described, header, positions, hints, confidence, interpolated=False) -> None:
        """positions (J, 3) m; hints (B, 3, 3) the fit's bone rotations; confidence (J,);
        interpolated: a frame the live fit had no time for (`interpolated_frame`)."""
        self.joints_rate.tick()
        self.output.publish(described, header, positions, hints, confidence, interpolated)


def interpolated_frame(before: tuple, after: tuple, stamp: int) -> tuple:
    """The joints of a camera frame stamped `stamp` (ns) that the live fit had no time for,
    between the frames fitted before and after it (each (stamp ns, header, positions (J,
    3) m, hints, confidence (J,))): (header, positions, hints, confidence) with the
    positions linear in time between the two, the hints (the bone rotations that give the
    twist) of the nearer frame, and the lower of the two confidences, joint by joint:
    nothing measured this frame's points, so it is trusted no more than either side."""
    # the header is the later frame's, with this frame's stamp
    (stamp_0, _, positions_0, hints_0, confidence_0), (stamp_1, header_1, positions_1, hints_1,
                                                       confidence_1) = before, after
    share = (stamp - stamp_0) / max(stamp_1 - stamp_0, 1)
    header = copy.deepcopy(header_1)
    set_stamp_ns(header, stamp)
    positions = (1.0 - share) * np.asarray(positions_0) + share * np.asarray(positions_1)
    hints = hints_0 if share < 0.5 else hints_1
    return header, positions, hints, np.minimum(confidence_0, confidence_1)


def camera_period(stamps) -> float | None:
    """The camera's frame period (s): the median interval of consecutive stamps (ns, in
    arrival order), intervals that go backwards or stand still left out; None before two
    frames."""
    intervals = np.diff(np.asarray(stamps, dtype=np.int64))
    intervals = intervals[intervals > 0]
    return float(np.median(intervals)) * 1e-9 if len(intervals) else None
