"""Registration of a whole sequence: the per-frame step of core.stream (subject
segmentation, preprocessing, rest-pose gate, rest pose, Alg. 1) over every frame, as the
registration node runs it on a stream.

    >>> registration = SequenceRegistration(RegistrationParams())
    >>> registered = registration.register(frames)      # iterable of (N_t, 3) -> (F, M, 3)
    >>> registration.rest_pose_.points                  # (M, 3) rest points Q
    >>> registration.statuses_                          # per frame: ok / empty / diverged

Frames are consumed one at a time (a generator is fine), so memory holds the results only.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from .preprocess import PreprocessParams
from .registration import STATUS_EMPTY, RegistrationParams
from .registration.params import FrameResult
from .rest_pose import RestPoseParams
from .segmentation import SegmentationParams
from .stream import FrameRegistrar, SubjectFinder, split_layout


@dataclass
class StepTimes:
    """Wall-clock seconds spent in each step, and per-frame registration times (s); the
    registration's is the sum of its frames' (the rest pose's two chains run at once, so
    over their frames it exceeds the wall time)."""

    segmentation: float = 0.0
    preprocess: float = 0.0
    rest_pose: float = 0.0
    registration: float = 0.0
    per_frame_registration: list = field(default_factory=list)


class SequenceRegistration:
    """The subject found in every frame, its rest pose (core.stream.FrameRegistrar: the most
    spread-out of the first frames where it is wholly in view), then every frame registered
    from its neighbour.

    Parameters are dataclasses (see their docstrings). Frames before the rest pose get NaN
    points and status 'empty'. Attributes set by `register` (sklearn style): rest_pose_,
    rest_frame_ (the index of the frame it was built from),
    statuses_ (F,), sigma2_ (F,), iterations_ (F,), recaptured_ (F,) parts recaptured,
    landmarks_ (F,) limb ends matched, times_, segmentation_ (F,) Segmentation summaries
    (status, subject points, background fraction, moving regions; masks dropped), and with
    keep_observed the preprocessed frames observed_ (list of (N_t, 3) float32).
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

        `on_frame(index, status)` is called after each frame (progress reporting; the frames
        held while the rest pose is chosen all at once, when it is).
        """
        finder = SubjectFinder(self.segmentation_params, self.preprocess_params)
        registrar = FrameRegistrar(self.params, self.rest_params)
        self.times_ = StepTimes()
        self.rest_pose_, self.rest_frame_ = None, None
        self.segmentation_ = []
        self.observed_ = []
        M = self.rest_params.n_points
        # a frame's result may come frames later (held while the rest pose is chosen)
        results = []

        def record(steps) -> None:
            for step in steps:
                self.times_.rest_pose += step.seconds_rest_pose
                if step.rest_pose_built:
                    self.rest_pose_, self.rest_frame_ = registrar.rest_pose, step.frame
                    self.registration_ = registrar.registration.registration
                result = step.result
                if result is None:
                    result = FrameResult(np.full((M, 3), np.nan), STATUS_EMPTY, np.nan, 0, 0.0)
                else:
                    self.times_.registration += step.seconds_registration
                    self.times_.per_frame_registration.append(step.seconds_registration)
                results[step.frame] = result
                if on_frame:
                    on_frame(step.frame, result.status)

        for index, raw in enumerate(frames):
            subject = finder(*split_layout(raw))
            self.times_.segmentation += subject.seconds_segmentation
            self.times_.preprocess += subject.seconds_preprocess
            self.segmentation_.append(subject.segmentation)
            if self.keep_observed:
                self.observed_.append(subject.observed.astype(np.float32))
            results.append(None)
            # a sequence's frames are evenly spaced: the index is their time (inertia's step)
            record(registrar(subject.observed, subject.segmentation, frame=index, stamp=float(index)))
        record(registrar.flush())
        points = [result.points.astype(np.float32) for result in results]
        statuses = [result.status for result in results]
        sigma2 = [result.sigma2 for result in results]
        iterations = [result.iterations for result in results]
        recaptured = [result.recaptured for result in results]
        landmarks = [result.landmarks for result in results]
        self.statuses_ = np.array(statuses)
        self.sigma2_ = np.array(sigma2)
        self.iterations_ = np.array(iterations)
        self.recaptured_ = np.array(recaptured, dtype=int)
        self.landmarks_ = np.array(landmarks, dtype=int)
        if not points:
            return np.empty((0, M, 3), dtype=np.float32)
        return np.stack(points)
