"""The registration node's two stages, without ROS: the camera stage finds the subject in
every frame (core.stream.SubjectFinder) and passes it on at once; the registration stage
gives it to core.stream.FrameRegistrar (rest-pose gate, rest pose, Alg. 1), with the rest
pose and Alg. 1 in child processes (nodes/registration_process.py). Each stage is a Worker
(nodes/worker.py); this module holds their queue policy, the epochs of the rest pose and
the start of each frame's registration.

Queue policy: while the first window is learned (rest pose to the first skeleton) the
registration stage takes frames in order, holding up to `learning_queue_size`, and a frame
the queue has no room for is skipped before it is decoded (nothing else uses a subject
frame yet: the cores go to learning). Once a skeleton is learned it holds `queue_size`
frames and skips the oldest, and Alg. 1 runs `registration_niceness` nicer (idle class
with `registration_sched_idle`), so Alg. 2 and the live path come first. With `lossless`
nothing is skipped: the camera stage waits for room.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from ..config.nodes import RegistrationNodeParams
from ..core.registration import STATUS_OK
from ..core.segmentation import STATUS_NOBODY
from ..core.stream import (ORDER_REPEATED, ORDER_WENT_BACK, PARTIAL_VIEW_PATIENCE_FRAMES, WAIT_FEW_POINTS,
                           WAIT_PARTIAL, WAIT_REST_POSE_FAILED, FrameRegistrar, StampOrder, SubjectFinder)
from .common import release_freed_memory
from ..codecs.messages import stamp_ns
from .registration_process import (REST_POSE_IDLE_RELEASE_S, ChildProcessDied, RegistrationProcess,
                                   RestPoseProcess)
from .worker import Worker


# At the node's stop, how long (s) a child may take to end by itself before it is killed.
CHILD_EXIT_WAIT_S = 1.0

# No cloud received and none in either stage for this long while frames are held for the
# rest pose's choice: the stream ended or paused, and the choice is made from the frames
# held. Ten frame intervals of the slowest usual depth camera (15 Hz), so a live camera
# never hits it; counted from the last frame finished too, so a slow segmentation is not
# taken for a pause.
CHOICE_QUIET_S = 0.7
# how often the node's timer calls flush_if_quiet
QUIET_CHECK_S = CHOICE_QUIET_S / 2
# the registration stage's item for that
_FLUSH = object()


@dataclass
class _SubjectFrame:
    """What the camera stage hands to the registration stage: the epoch of the rest pose it
    belongs to, the cloud's header, the preprocessed subject (N, 3) m and the segmentation
    result without its mask."""

    epoch: int
    header: object
    observed: np.ndarray
    segmentation: object


class RegistrationStages:
    """method: the (RegistrationParams, RestPoseParams, PreprocessParams,
    SegmentationParams) of the node; settings: its own parameters (queues, priority,
    live_start); decode(msg, info) -> (points (H*W, 3), height, width) or None (it says why);
    publish.filtered / .registered / .rest(points, header) send the outputs; log is a
    nodes.common.ThrottledLog, logger the node's logger, context_ok() False once ROS shuts
    down (a frame failing then is not worth a line)."""

    def __init__(self, method: tuple, settings: RegistrationNodeParams, decode, publish, log, logger, context_ok):
        (self.params, self.rest_params, self.preprocess_params, self.segmentation_params) = method
        self.settings, self.decode, self.publish = settings, decode, publish
        self.log, self.logger, self.context_ok = log, logger, context_ok
        self._stopping = False      # stop() began: a child's end is no failure
        # a skeleton is described: subject frames feed the live fit too (not only registration)
        self.described = False
        # the joint node's newest posed model (stamp ns, (M, 3)): where the next frame's
        # registration starts (live_start); frames registered from it, for /diagnostics
        self.posed = None
        self.registered_from_live_pose = 0
        # set by the services, acted on by the camera stage before its next frame
        self.background_reset_requested = self.reset_requested = False
        # a new rest pose is wanted: the camera stage counts epochs, the registration
        # stage starts over when a frame of a newer epoch reaches it (skips cannot lose it)
        self.epoch, self._registration_epoch = 0, 0
        self.stamp_order = StampOrder()
        self.subject_finder = SubjectFinder(self.segmentation_params, self.preprocess_params)
        self.registration_process = RegistrationProcess(settings.registration_niceness,
                                                        settings.registration_sched_idle)
        self.rest_pose_process = RestPoseProcess()
        self.frame_registrar = FrameRegistrar(self.params, self.rest_params, self.rest_pose_process.build,
                                              self.registration_process, self._publish_rest)
        # when a cloud last arrived or a frame last finished, and when flush_if_quiet last
        # ran (time.monotonic(), s)
        self._last_activity_s = self._last_quiet_check_s = time.monotonic()
        self._start_registration()
        self._done = 0                 # frames finished by either stage (tests, diagnostics)
        self._count_lock = threading.Lock()
        self.last_status = ''          # what happened to the newest frame, for /diagnostics
        self.last_registration_status = 'no frame yet'
        self.camera = Worker(self._observe, 'camera', capacity=1, on_error=self._failed)
        self.registration = Worker(self._register, 'registration', capacity=settings.queue_size,
                                   on_error=self._registration_failed)
        self._learn()

    # -- what the node tells the stages ------------------------------------------------------
    def submit(self, item) -> None:
        """A frame (msg, camera info or None) for the camera stage (the newest one waits)."""
        self._last_activity_s = time.monotonic()
        if self.camera.submit(item):
            self.warn_skipped()

    def skeleton_learned(self) -> None:
        """The first window is learned (skeleton/structure) or a skeleton tracked: from now on
        Alg. 2 and the live path come first; registration only grows the skeleton (not with
        lossless: there every frame waits for its registration, and a nicer one only slows all)."""
        if self.settings.lossless:
            return
        if self.registration.keep == 'oldest':
            # the backlog of the window's frames is not needed for growing the skeleton
            self.registration.configure(self.settings.queue_size, keep='newest')
            release_freed_memory()
        if not self.registration_process.lowered:
            self.registration_process.make_nicer()
            idle = ' in the idle scheduling class' if self.registration_process.in_idle_class else ''
            self.logger.info(f'the skeleton is learned: registration runs at nice {self.registration_process.nice}'
                             f'{idle} and takes the newest frames from now on')

    @property
    def rest_pose(self):
        """The current rest pose (core.rest_pose.RestPose), None until one is built."""
        return self.frame_registrar.rest_pose

    @property
    def skipped(self) -> int:
        """Frames dropped unprocessed (by either stage) because its queue was full."""
        return self.camera.dropped + self.registration.dropped

    @property
    def processed(self) -> int:
        """Frames handled (registered, held for the rest pose's choice, refused, or not
        passed on by the camera stage); processed + skipped reaches the frames received."""
        return self._done

    def warn_skipped(self) -> None:
        camera, registration = self.camera.stats(), self.registration.stats()
        if self.registration.keep == 'oldest':
            policy = (f'learning_queue_size {self.registration.capacity}; median '
                      f'{registration["latency_ms_median"]:.0f} ms per frame): the first window\'s '
                      'frames are registered in order, newer ones skipped until it is learned')
        else:
            policy = (f'queue_size {self.registration.capacity}; median {registration["latency_ms_median"]:.0f} '
                      'ms per frame): the newest frames are registered')
        self.log.warn('skipped', f'{camera["dropped"]} cloud(s) skipped so far before segmentation '
                                 f'(median {camera["latency_ms_median"]:.0f} ms per cloud) and '
                                 f'{registration["dropped"]} skipped for registration ({policy}')

    def stop(self) -> None:
        """Stop both stages and the child processes, the children at once: the node is
        ending and their work in progress is of no use. Once the skeleton is tracked the
        registration child runs in the idle scheduling class, where on a busy machine it may
        get no CPU for seconds, neither to finish its frame nor to see its stdin close;
        waited for, it kept the node alive past the 20 s a Ctrl-C is given."""
        self._stopping = True
        # the registration stage first: a lossless camera stage blocked on it wakes at once;
        # not joined yet: its frame in progress may be waiting on a child
        self.registration.stop(timeout=0.0)
        self.registration_process.close(timeout=CHILD_EXIT_WAIT_S)
        self.rest_pose_process.close(timeout=CHILD_EXIT_WAIT_S)
        self.registration.stop()
        self.camera.stop()

    # -- camera stage ----------------------------------------------------------------------
    def _learn(self) -> None:
        """Learning the first window: consecutive frames, in order (not with lossless, where
        every frame is registered anyway, with back-pressure)."""
        if not self.settings.lossless:
            self.registration.configure(self.settings.learning_queue_size, keep='oldest')

    def _start_over(self) -> None:
        """A new rest pose from the next good frame (the registration stage sees the epoch)."""
        self.subject_finder = SubjectFinder(self.segmentation_params, self.preprocess_params)
        self.epoch += 1
        self.described = False
        self._learn()

    def _observe(self, item) -> None:
        msg, info = item
        if self.reset_requested:
            self.reset_requested = False
            self.stamp_order = StampOrder()
            self._start_over()
        if self.background_reset_requested:
            self.background_reset_requested = False
            self.subject_finder.reset_background()
        if not self.described and not self.settings.lossless and self.registration.full:
            # Until a skeleton is described nothing but the registration uses a subject
            # frame (no live fit yet), and a full queue would drop this one after its
            # segmentation: skip the decoding and segmentation too, so the cores go to
            # registering the window and to Alg. 2; counted as the queue's drop.
            self.registration.refuse()
            self.warn_skipped()
            return
        if not self._find_and_pass_on(msg, info):
            self._finished()

    def _find_and_pass_on(self, msg, info) -> bool:
        """Decode one frame, find the subject in it, publish it on filtered_points and hand
        it to the registration stage; False when the frame goes no further."""
        stamp = stamp_ns(msg.header)
        decoded = self.decode(msg, info)
        if decoded is None:
            return False
        raw, height, width = decoded
        if len(raw) > self.preprocess_params.max_input_points:
            self.log.warn('large', f'cloud of {len(raw)} points: randomly thinned to '
                                   f'preprocess.max_input_points = {self.preprocess_params.max_input_points}')
        previous_stamp, previous_frame = self.stamp_order.last_stamp, self.stamp_order.frame_id
        order = self.stamp_order(stamp, msg.header.frame_id)
        if order == ORDER_REPEATED:
            self.log.warn('duplicate', f'ignoring a second cloud with stamp {stamp * 1e-9:.3f} s')
            return False
        if order is not None:
            why = (f'stamps went back by {(previous_stamp - stamp) * 1e-9:.3f} s (bag looped or clock reset)'
                   if order == ORDER_WENT_BACK else f'frame_id changed from {previous_frame!r} to '
                   f'{msg.header.frame_id!r}: the registered points would mix coordinate frames')
            self.log.always(why + '; starting over with a new rest pose')
            self._start_over()
        subject = self.subject_finder(raw, height, width)
        segmentation = subject.segmentation
        self.last_status = f'subject {segmentation.status}'
        if segmentation.status == STATUS_NOBODY:
            self.log.warn('nobody', f'nobody in view: no region of the {segmentation.n_valid} valid points '
                                    'has moved yet (waiting for the subject)')
        elif segmentation.n_moving_regions > 1:
            self.log.warn('several', f'{segmentation.n_moving_regions} moving regions (people?) in view: '
                                     'following the one that moves most')
        self.publish.filtered(subject.observed, msg.header)
        frame = _SubjectFrame(self.epoch, msg.header, subject.observed, segmentation)
        if self.registration.submit(frame, block=self.settings.lossless):
            self.warn_skipped()
        return True

    def _failed(self, item, error) -> None:
        """A frame whose processing raised: one throttled line, the node goes on."""
        self._finished()
        if self.context_ok():  # else Ctrl-C closed the context under a frame in progress
            self.log.warn('failed', f'cloud at {stamp_ns(item[0].header) * 1e-9:.3f} s failed: '
                                    f'{type(error).__name__}: {error}')

    # -- registration stage ------------------------------------------------------------------
    def _start_registration(self) -> None:
        self.frame_registrar.reset()
        self._rest_stamp = self._registered_stamp = None
        self.rest_pose_process.while_waiting(somebody=True)   # warm: a subject may come at once

    def _live_start(self, stamp: int) -> np.ndarray | None:
        """(M, 3) the joint node's newest posed model, where this frame's registration starts,
        when it is of this rest pose, newer than the last registered frame and not newer than
        this one (else None: from the last registered frame, as Alg. 1). Once a skeleton is
        tracked the registration takes the newest frame, a second or more after the last one
        it registered: a limb that moved since may be beyond the E-step's reach, and the live
        fit of a frame or two before is closer."""
        posed = self.posed
        if not self.settings.live_start or self.settings.lossless or posed is None or self.rest_pose is None:
            return None
        posed_stamp, points = posed
        newest_registered = self._registered_stamp if self._registered_stamp is not None else self._rest_stamp
        if not newest_registered < posed_stamp <= stamp or points.shape != self.rest_pose.points.shape:
            return None
        if not np.isfinite(points).all():
            self.log.warn('posed', 'ignoring skeleton/posed_points with non-finite points')
            return None
        return points

    def flush_if_quiet(self) -> None:
        """Frames held for the rest pose's choice, both stages idle, and no cloud received
        or finished for CHOICE_QUIET_S: the stream ended or paused (a bag's end, a stopped
        camera), so the rest pose is chosen from the frames held (on the registration
        stage's thread, after the frames queued before). Called by a timer of the node every
        QUIET_CHECK_S."""
        now = time.monotonic()
        # a call long after the last one ran after the executor was held up elsewhere:
        # clouds may be waiting in its queue, not yet received, so the quiet is not evidence
        late = now - self._last_quiet_check_s > 2.0 * QUIET_CHECK_S
        self._last_quiet_check_s = now
        if (not late and self.frame_registrar.held and now - self._last_activity_s > CHOICE_QUIET_S
                and self.camera.idle and self.registration.idle):
            self.registration.submit(_FLUSH)

    def _register(self, frame) -> None:
        try:
            self._register_frame(frame)
        finally:
            if frame is not _FLUSH:
                self._finished()

    def _register_frame(self, frame) -> None:
        if frame is _FLUSH:
            self._publish_steps(self._surviving_the_child(self.frame_registrar.flush))
            return
        if frame.epoch != self._registration_epoch:
            self._registration_epoch = frame.epoch
            self._start_registration()
            if self.registration_process.lowered:
                self.registration_process.restart()     # learning the new skeleton comes first
        stamp, observed = stamp_ns(frame.header), frame.observed
        somebody = frame.segmentation.status != STATUS_NOBODY
        if self.rest_pose is None and self.rest_pose_process.while_waiting(somebody):
            self.logger.info(f'nobody in view for {REST_POSE_IDLE_RELEASE_S:.0f} s: the rest pose process ends '
                             'until something moves')
        live_start = self._live_start(stamp)
        self._publish_steps(self._surviving_the_child(
            lambda: self.frame_registrar(observed, frame.segmentation, live_start, frame, stamp * 1e-9)))

    def _surviving_the_child(self, registrar_call) -> list:
        """registrar_call()'s FrameSteps, or none when the registration process died under
        it: a new process and a new rest pose (the frames held or registered so far are lost)."""
        try:
            return registrar_call()
        except ChildProcessDied:
            if self.context_ok() and not self._stopping:
                self.log.always('the registration process ended unexpectedly (out of memory? killed?): '
                                'starting a new one and a new rest pose')
                self.registration_process.restart()
                self._start_registration()
            return []

    def _publish_rest(self, rest_pose, first: _SubjectFrame, chosen: _SubjectFrame) -> None:
        """The rest pose as soon as it is built, before its held frames are registered,
        stamped with the first of them: the accumulator and the joint node take frames
        stamped before it for an older rest pose's."""
        self._rest_stamp = stamp_ns(first.header)
        release_freed_memory()
        self.publish.rest(rest_pose.points, first.header)
        choice = '' if first is chosen else f' (the most spread-out since {self._rest_stamp * 1e-9:.3f} s)'
        self.logger.info(f'rest pose built from the cloud at {stamp_ns(chosen.header) * 1e-9:.3f} s{choice} '
                         f'({len(rest_pose.points)} points, frame {chosen.header.frame_id!r})')

    def _publish_steps(self, steps: list) -> None:
        """Publish what core.stream.FrameRegistrar's steps say, in their (stamp) order."""
        for step in steps:
            self._publish_step(step)

    def _publish_step(self, step) -> None:
        frame = step.frame
        stamp, observed = stamp_ns(frame.header), frame.observed
        if step.result is None:
            self._warn_waiting(step, frame)
            return
        result = step.result
        self.last_registration_status = f'frame {result.status}'
        if result.status != STATUS_OK:
            self.log.warn(f'status:{result.status}:{len(observed) == 0}',
                          f'cloud at {stamp * 1e-9:.3f} s not registered ({result.status}: '
                          f'{len(observed)} points after preprocessing); holding the last pose')
            return
        self._registered_stamp = stamp
        self.registered_from_live_pose += step.started_from_given
        self.publish.registered(result.points, frame.header)
        if self.registration.processed % 100 == 99:
            stats = self.registration.stats()
            self.logger.info(f'{self.registration.processed + 1} frames through registration, latency median '
                             f'{stats["latency_ms_median"]:.0f} ms, p95 {stats["latency_ms_p95"]:.0f} ms, '
                             f'{self.skipped} skipped')

    def _warn_waiting(self, step, frame: _SubjectFrame) -> None:
        """Why this frame did not become the rest pose (nobody in view: the camera stage says so)."""
        if step.status == WAIT_PARTIAL:
            self.log.warn('partial', 'no rest pose yet: the subject is only partly in view '
                                     f'(waiting up to {PARTIAL_VIEW_PATIENCE_FRAMES} frames for all of it)')
        elif step.status == WAIT_FEW_POINTS:
            self.log.warn('no_rest', f'no rest pose yet: only {len(frame.observed)} points after preprocessing '
                                     f'(of {frame.segmentation.n_valid} valid); is the subject in view?')
        elif step.status == WAIT_REST_POSE_FAILED:
            self.log.warn('no_rest', f'no rest pose from this cloud: {step.error}')

    def _registration_failed(self, item, error) -> None:
        if not self.context_ok():
            return
        what = ('the rest pose\'s choice among the held clouds' if item is _FLUSH
                else f'registration of the cloud at {stamp_ns(item.header) * 1e-9:.3f} s')
        self.log.warn('failed', f'{what} failed: {type(error).__name__}: {error}')

    def _finished(self) -> None:
        self._last_activity_s = time.monotonic()
        with self._count_lock:
            self._done += 1
