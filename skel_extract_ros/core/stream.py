"""The per-frame step of Steps 0-1, one frame at a time: the subject found in a raw frame
(segmentation, preprocessing), then the rest-pose gate, the rest pose and Alg. 1.

`skel-extract run` (core.sequence) loops over both in one thread; the registration node
calls `SubjectFinder` on its camera stage and `FrameRegistrar` on its registration stage,
with the rest pose and Alg. 1 in child processes (nodes/registration_process.py), so both
take the same decisions on the same frames.

    >>> finder, registrar = SubjectFinder(), FrameRegistrar(RegistrationParams())
    >>> subject = finder(points, height, width)        # raw (H*W, 3) m, NaN allowed
    >>> for step in registrar(subject.observed, subject.segmentation, frame=index):
    ...     step.frame, step.status, step.result       # 'nobody' ... or Alg. 1's FrameResult
    >>> registrar.flush()                              # the stream ended: the frames still held
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .preprocess import PreprocessParams, Preprocessor
from .registration import NonRigidRegistration, RegistrationParams, register_chains
from .registration.params import FrameResult
from .rest_pose import RestPose, RestPoseError, RestPoseParams, spread
from .segmentation import STATUS_NOBODY, Segmentation, SegmentationParams, SubjectSegmenter

# A subject that touches the image border is partly out of view: its rest pose waits until
# it is whole, but no longer than this (a subject too close to ever fit gets one anyway).
PARTIAL_VIEW_PATIENCE_FRAMES = 30

# why a frame did not become the rest pose (FrameStep.status before Alg. 1's own statuses)
WAIT_NOBODY, WAIT_PARTIAL, WAIT_FEW_POINTS, WAIT_REST_POSE_FAILED = 'nobody', 'partial', 'few_points', 'no_rest_pose'


def split_layout(raw: np.ndarray) -> tuple:
    """(points (N, 3), height, width) of a frame given as (H, W, 3) organized or (N, 3)."""
    raw = np.asarray(raw)
    if raw.ndim == 3 and raw.shape[2] == 3:
        return raw.reshape(-1, 3), raw.shape[0], raw.shape[1]
    return raw, 1, len(raw)


@dataclass
class Subject:
    """The subject of one frame: observed (N, 3) m, preprocessed; segmentation (core.
    segmentation.Segmentation, its per-pixel mask dropped: frames wait in queues);
    seconds spent segmenting and preprocessing."""

    observed: np.ndarray
    segmentation: Segmentation
    seconds_segmentation: float
    seconds_preprocess: float


class SubjectFinder:
    """Segmentation then preprocessing of raw frames of one camera (the segmenter learns
    the scene across frames: one finder per camera and rest pose)."""

    def __init__(self, segmentation_params: SegmentationParams | None = None,
                 preprocess_params: PreprocessParams | None = None):
        self.segmenter = SubjectSegmenter(segmentation_params or SegmentationParams())
        self.preprocessor = Preprocessor(preprocess_params or PreprocessParams())

    def reset_background(self) -> None:
        """Forget the learned scene (the camera moved)."""
        self.segmenter.reset()

    def __call__(self, points: np.ndarray, height: int, width: int) -> Subject:
        """points (height * width, 3) m of one raw frame (NaN allowed; height 1 when not organized)."""
        started = time.perf_counter()
        segmentation = self.segmenter(points, height, width)
        segmented = time.perf_counter()
        observed = self.preprocessor(points[segmentation.mask])
        return Subject(observed, segmentation.summary(), segmented - started, time.perf_counter() - segmented)


class RestPoseGate:
    """Which frame may become the rest pose: one where somebody is in view, wholly (or
    partly, once that has lasted PARTIAL_VIEW_PATIENCE_FRAMES frames), with at least a
    tenth of the rest pose's points (100 at least) left after preprocessing."""

    def __init__(self, rest_params: RestPoseParams):
        self.min_points = max(100, rest_params.n_points // 10)
        self.partial_frames = 0

    def reason_to_wait(self, segmentation: Segmentation, n_observed: int) -> str | None:
        """None when this frame may become the rest pose, else why not: WAIT_NOBODY,
        WAIT_PARTIAL (the subject touches the image border) or WAIT_FEW_POINTS."""
        partial = segmentation.touches_border and self.partial_frames < PARTIAL_VIEW_PATIENCE_FRAMES
        self.partial_frames += int(segmentation.touches_border)
        if segmentation.status == STATUS_NOBODY:
            return WAIT_NOBODY
        if partial:
            return WAIT_PARTIAL
        return WAIT_FEW_POINTS if n_observed < self.min_points else None


class InProcessRegistration:
    """Alg. 1 in this process: the registration the node's child process holds, in `run`."""

    def __init__(self):
        self.registration = None

    def register_frame(self, observed: np.ndarray, start_points: np.ndarray | None = None,
                       stamp: float | None = None) -> FrameResult:
        return self.registration.register_frame(observed, start_points, stamp)

    def register_chains(self, registration: NonRigidRegistration, chains: list) -> list:
        """core.registration.register_chains; the frames after go on from the last chain."""
        outcomes, self.registration = register_chains(registration, chains)
        return outcomes


@dataclass
class FrameStep:
    """What FrameRegistrar made of one frame. frame: the caller's token of the frame;
    status: a WAIT_* reason (no rest pose yet, result None) or Alg. 1's frame status
    (result its FrameResult); rest_pose_built: this frame became the rest pose;
    started_from_given: Alg. 1 started from the start_points given; error: why no rest
    pose could be built; seconds spent on the rest pose and on Alg. 1."""

    status: str
    result: FrameResult | None = None
    rest_pose_built: bool = False
    started_from_given: bool = False
    error: str = ''
    seconds_rest_pose: float = 0.0
    seconds_registration: float = 0.0
    frame: object = None


@dataclass
class _HeldFrame:
    """A frame held while the rest pose's frame is chosen: its subject (N, 3) m, the
    caller's token, whether the gate let it through (it may become the rest pose), and its
    stamp (s, or None)."""

    observed: np.ndarray
    frame: object
    candidate: bool
    stamp: float | None = None


class FrameRegistrar:
    """The rest pose, then every frame registered (Alg. 1) from the previous one, or from
    `start_points` when given.

    The rest pose (RestPoseParams.choice_frames): from the first frame the gate lets
    through, `choice_frames` consecutive frames are held; the rest pose is built from the
    most spread-out of those the gate lets through (core.rest_pose.spread), and the held
    frames are registered backward from it to the first and forward from it to the last,
    each from its neighbour, as Alg. 1 registers any frame, the two chains at once
    (core.registration.register_chains). Registration then goes on from the last held
    frame. With choice_frames 1 the first frame the gate lets through
    is the rest pose (the paper). `flush` ends the choice early (a stream that ended or
    paused).

    build_rest_pose(observed, rest_params) -> RestPose and registration (register_chains,
    register_frame) run where the caller wants them: here by default, in child processes
    in the registration node. on_rest_pose(rest_pose, first, chosen), when given, is called
    as soon as the rest pose is built, before the held frames are registered (first and
    chosen: the tokens of the first held frame and of the rest pose's)."""

    def __init__(self, params: RegistrationParams | None = None, rest_params: RestPoseParams | None = None,
                 build_rest_pose=RestPose.from_points, registration=None, on_rest_pose=None):
        self.params = params or RegistrationParams()
        self.rest_params = rest_params or RestPoseParams()
        self.build_rest_pose = build_rest_pose
        self.registration = registration or InProcessRegistration()
        self.on_rest_pose = on_rest_pose
        self.reset()

    def reset(self) -> None:
        """Wait for a new rest pose (frames held for it are forgotten)."""
        self.gate = RestPoseGate(self.rest_params)
        self.rest_pose = None
        self.held = []

    def __call__(self, observed: np.ndarray, segmentation: Segmentation,
                 start_points: np.ndarray | None = None, frame=None, stamp: float | None = None) -> list:
        """observed (N, 3) m: the frame's subject; start_points (M, 3) m or None; frame: the
        caller's token, returned in the step; stamp: the frame's time (s) when frames may be
        skipped (RegistrationParams.inertia), None for evenly spaced ones. The FrameSteps of
        the frames this one completes, in the order given: this frame's alone, or none while
        it is held for the rest pose's choice, or every held frame's once the choice is made."""
        if self.rest_pose is None:
            waiting = self.gate.reason_to_wait(segmentation, len(observed))
            if waiting is not None and not self.held:
                return [FrameStep(waiting, frame=frame)]
            self.held.append(_HeldFrame(observed, frame, waiting is None, stamp))
            return self.flush() if len(self.held) >= self.rest_params.choice_frames else []
        return [self._register(observed, start_points, frame, stamp)]

    def flush(self) -> list:
        """The held frames' FrameSteps now: the rest pose from the frames held so far."""
        held, self.held = self.held, []
        if not held:
            return []
        started = time.perf_counter()
        ranked = sorted((i for i, h in enumerate(held) if h.candidate), key=lambda i: -spread(held[i].observed))
        errors = []
        for chosen in ranked:
            try:
                rest_pose = self.build_rest_pose(held[chosen].observed, self.rest_params)
                break
            except RestPoseError as error:
                errors.append(str(error))
        else:
            # no held frame gave a rest pose: the next frame the gate lets through starts over
            steps = [FrameStep(WAIT_REST_POSE_FAILED, error=errors[-1], frame=h.frame) for h in held]
            steps[0].seconds_rest_pose = time.perf_counter() - started
            return steps
        seconds_rest_pose = time.perf_counter() - started
        self.rest_pose = rest_pose
        if self.on_rest_pose is not None:
            self.on_rest_pose(rest_pose, held[0].frame, held[chosen].frame)
        steps = [None] * len(held)
        # backward to the first held frame and forward to the last: two chains at once
        orders = [order for order in (range(chosen - 1, -1, -1), range(chosen, len(held))) if len(order)]
        outcomes = self.registration.register_chains(NonRigidRegistration(rest_pose.points, self.params),
                                                     [[(held[i].observed, held[i].stamp) for i in order]
                                                      for order in orders])
        for order, chain in zip(orders, outcomes):
            for i, (result, seconds) in zip(order, chain):
                steps[i] = FrameStep(result.status, result, frame=held[i].frame, seconds_registration=seconds)
        steps[chosen].rest_pose_built, steps[chosen].seconds_rest_pose = True, seconds_rest_pose
        return steps

    def _register(self, observed: np.ndarray, start_points: np.ndarray | None, frame,
                  stamp: float | None) -> FrameStep:
        started = time.perf_counter()
        result = self.registration.register_frame(observed, start_points, stamp)
        return FrameStep(result.status, result, started_from_given=start_points is not None, frame=frame,
                         seconds_registration=time.perf_counter() - started)


# what StampOrder makes of a frame's stamp and frame_id
ORDER_REPEATED, ORDER_WENT_BACK, ORDER_NEW_FRAME_ID = 'repeated', 'went_back', 'new_frame_id'


class StampOrder:
    """The order of one camera's frames. A repeated stamp is a frame to ignore; a stamp going
    back (a bag looped, a clock reset) or a new frame_id (registered points would mix
    coordinate frames) means a new rest pose."""

    def __init__(self):
        self.last_stamp, self.frame_id = None, None

    def __call__(self, stamp: int, frame_id: str) -> str | None:
        """None for the next frame in order, else ORDER_REPEATED, ORDER_WENT_BACK or
        ORDER_NEW_FRAME_ID (stamp: integer ns). A repeated frame does not count as seen."""
        previous_stamp, previous_frame = self.last_stamp, self.frame_id
        if previous_stamp is not None and stamp == previous_stamp:
            return ORDER_REPEATED
        self.last_stamp, self.frame_id = stamp, frame_id
        if previous_stamp is None:
            return None
        if stamp < previous_stamp:
            return ORDER_WENT_BACK
        return ORDER_NEW_FRAME_ID if frame_id != previous_frame else None
