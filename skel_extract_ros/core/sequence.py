"""Registration of a whole sequence: subject segmentation, preprocessing, rest pose, then
Alg. 1 frame by frame.

    >>> registration = SequenceRegistration(RegistrationParams())
    >>> registered = registration.register(frames)      # iterable of (N_t, 3) -> (F, M, 3)
    >>> registration.rest_pose_.points                  # (M, 3) rest points Q
    >>> registration.statuses_                          # per frame: ok / empty / diverged

Frames are consumed one at a time (a generator is fine), so memory holds the results only.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from .preprocess import PreprocessParams, Preprocessor
from .registration import STATUS_EMPTY, NonRigidRegistration, RegistrationParams
from .rest_pose import RestPose, RestPoseError, RestPoseParams
from .segmentation import STATUS_NOBODY, Segmentation, SegmentationParams, SubjectSegmenter

# A subject that touches the image border is partly out of view: its rest pose waits until
# it is whole, but no longer than this (a subject too close to ever fit gets one anyway).
PARTIAL_VIEW_PATIENCE_FRAMES = 30


def split_layout(raw: np.ndarray) -> tuple:
    """(points (N, 3), height, width) of a frame given as (H, W, 3) organized or (N, 3)."""
    raw = np.asarray(raw)
    if raw.ndim == 3 and raw.shape[2] == 3:
        return raw.reshape(-1, 3), raw.shape[0], raw.shape[1]
    return raw, 1, len(raw)


class RestPoseGate:
    """Which frame may become the rest pose (the offline sequence and the registration node
    alike): one where somebody is in view, wholly (or partly, once that has lasted
    PARTIAL_VIEW_PATIENCE_FRAMES frames), with at least a tenth of the rest pose's points
    (100 at least) left after preprocessing."""

    def __init__(self, rest_params: RestPoseParams):
        self.min_points = max(100, rest_params.n_points // 10)
        self.partial_frames = 0

    def reason_to_wait(self, segmentation: Segmentation, n_observed: int) -> str | None:
        """None when this frame may become the rest pose, else why not: 'nobody',
        'partial' (the subject touches the image border) or 'few_points'."""
        partial = segmentation.touches_border and self.partial_frames < PARTIAL_VIEW_PATIENCE_FRAMES
        self.partial_frames += int(segmentation.touches_border)
        if segmentation.status == STATUS_NOBODY:
            return 'nobody'
        if partial:
            return 'partial'
        return 'few_points' if n_observed < self.min_points else None


@dataclass
class StepTimes:
    """Wall-clock seconds spent in each step, and per-frame registration times (s)."""

    segmentation: float = 0.0
    preprocess: float = 0.0
    rest_pose: float = 0.0
    registration: float = 0.0
    per_frame_registration: list = field(default_factory=list)


class SequenceRegistration:
    """The subject found in every frame, its rest pose from the first frame where it is
    wholly in view, then every frame registered from the previous.

    Parameters are dataclasses (see their docstrings). Frames before the rest pose get NaN
    points and status 'empty'. Attributes set by `register` (sklearn style): rest_pose_,
    statuses_ (F,), sigma2_ (F,), iterations_ (F,), recaptured_ (F,) parts recaptured, times_, segmentation_ (F,) Segmentation
    summaries (status, subject points, background fraction, moving regions; masks dropped),
    and with keep_observed the preprocessed frames observed_ (list of (N_t, 3) float32).
    """

    def __init__(self, params: RegistrationParams | None = None,
                 rest_params: RestPoseParams | None = None,
                 preprocess_params: PreprocessParams | None = None,
                 keep_observed: bool = False,
                 segmentation_params: SegmentationParams | None = None):
        self.params = params or RegistrationParams()
        self.rest_params = rest_params or RestPoseParams()
        self.preprocess_params = preprocess_params or PreprocessParams()
        self.segmentation_params = segmentation_params or SegmentationParams()
        # Joint estimation (Alg. 2) needs the preprocessed points of every frame; keeping
        # them costs about 60 kB per frame (float32, 5000 points).
        self.keep_observed = keep_observed

    def register(self, frames: Iterable[np.ndarray],
                 on_frame: Callable[[int, str], None] | None = None) -> np.ndarray:
        """Register raw frames -> (F, M, 3) float32 metres. A frame is an organized cloud
        (H, W, 3) or (N, 3) points, NaN allowed.

        `on_frame(index, status)` is called after each frame (progress reporting).
        """
        segmenter = SubjectSegmenter(self.segmentation_params)
        preprocess = Preprocessor(self.preprocess_params)
        self.times_ = StepTimes()
        self.rest_pose_ = None
        self.segmentation_ = []
        registration = None
        gate = RestPoseGate(self.rest_params)
        points, statuses, sigma2, iterations, recaptured = [], [], [], [], []
        self.observed_ = []
        M = self.rest_params.n_points
        for index, raw in enumerate(frames):
            started = time.perf_counter()
            flat, height, width = split_layout(raw)
            segmentation = segmenter(flat, height, width)
            self.times_.segmentation += time.perf_counter() - started
            self.segmentation_.append(segmentation.summary())
            started = time.perf_counter()
            observed = preprocess(flat[segmentation.mask])
            self.times_.preprocess += time.perf_counter() - started
            if self.keep_observed:
                self.observed_.append(observed.astype(np.float32))
            if registration is None:
                if gate.reason_to_wait(segmentation, len(observed)) is None:
                    started = time.perf_counter()
                    try:
                        self.rest_pose_ = RestPose.from_points(observed, self.rest_params)
                    except RestPoseError:
                        self.rest_pose_ = None
                    self.times_.rest_pose += time.perf_counter() - started
                if self.rest_pose_ is None:
                    points.append(np.full((M, 3), np.nan, dtype=np.float32))
                    statuses.append(STATUS_EMPTY)
                    sigma2.append(np.nan)
                    iterations.append(0)
                    recaptured.append(0)
                    if on_frame:
                        on_frame(index, STATUS_EMPTY)
                    continue
                registration = NonRigidRegistration(self.rest_pose_.points, self.params)
                self.registration_ = registration
            started = time.perf_counter()
            result = registration.register_frame(observed)
            elapsed = time.perf_counter() - started
            self.times_.registration += elapsed
            self.times_.per_frame_registration.append(elapsed)
            points.append(result.points.astype(np.float32))
            statuses.append(result.status)
            sigma2.append(result.sigma2)
            iterations.append(result.iterations)
            recaptured.append(result.recaptured)
            if on_frame:
                on_frame(index, result.status)
        self.statuses_ = np.array(statuses)
        self.sigma2_ = np.array(sigma2)
        self.iterations_ = np.array(iterations)
        self.recaptured_ = np.array(recaptured, dtype=int)
        if not points:
            return np.empty((0, M, 3), dtype=np.float32)
        return np.stack(points)
