"""The whole method on a sequence: Step 0-1 (rest pose, registration), Step 2 (structure),
Step 3 (joints). Used by `skel-extract run`; no I/O, no ROS.

    >>> registered = SkeletonPipeline().register(frames)   # raw (H, W, 3) or (N_t, 3) clouds
    >>> result = pipeline.extract(registered)
    >>> result.joint_positions                       # (F, J, 3) after Step 3
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import numpy as np

from .growth import GrowthSchedule, SkeletonGrowth
from .joints import JointEstimate, JointParams
from .live import LiveJointTracker
from .preprocess import PreprocessParams
from .registration import STATUS_OK, RegistrationParams
from .rest_pose import RestPoseParams
from .segmentation import SegmentationParams
from .sequence import SequenceRegistration
from .skeleton_model import SkeletonModel
from .rigid import fit_rigid_segments
from .joint_centres import joint_trajectories
from .structure import SkeletalStructure, StructureError, StructureParams


@dataclass
class PipelineResult:
    """registered: (F, M, 3); statuses: (F,); frames: indices of the frames with a skeleton
    (those registered with status ok); step2_positions / joint_positions: (F', J, 3) joint
    positions after Step 2 and after Step 3 for those frames; seconds per step; key_frames:
    the frames (indices into registered) the skeleton was learned on; joint_confidence
    (F', J) the Step 3 joints' confidence in [0, 1] (core.confidence, against each frame's
    registered points, as the joint node publishes it)."""

    registered: np.ndarray
    statuses: np.ndarray
    frames: np.ndarray
    structure: SkeletalStructure
    joints: JointEstimate
    model: SkeletonModel
    step2_positions: np.ndarray
    joint_positions: np.ndarray
    observed: list
    seconds: dict = field(default_factory=dict)
    key_frames: np.ndarray | None = None
    joint_confidence: np.ndarray | None = None


class SkeletonPipeline:
    """Runs the three steps with their parameter dataclasses (defaults: Table 1)."""

    def __init__(self, registration: RegistrationParams | None = None, rest_pose: RestPoseParams | None = None,
                 preprocess: PreprocessParams | None = None, structure: StructureParams | None = None,
                 joints: JointParams | None = None, segmentation: SegmentationParams | None = None,
                 schedule: GrowthSchedule | None = None):
        self.registration = SequenceRegistration(registration, rest_pose, preprocess, keep_observed=True,
                                                 segmentation_params=segmentation)
        self.structure_params = structure or StructureParams()
        self.joint_params = joints or JointParams()
        self.schedule = schedule or GrowthSchedule()

    def register(self, frames: Iterable[np.ndarray], on_frame: Callable[[int, str], None] | None = None):
        """Step 0-1 only: (F, M, 3) registered points (see SequenceRegistration)."""
        return self.registration.register(frames, on_frame)

    def extract(self, registered: np.ndarray) -> PipelineResult:
        """Steps 2 and 3 on the frames `register` produced, learned as the nodes learn them
        from a stream (raises StructureError when no window shows articulation).

        The registered frames (status ok, as the nodes publish them) come in order; the
        skeleton is learned when the growth schedule says (core.growth.GrowthSchedule: on
        the first `window_size` frames, with `sliding` again every `stride` frames; a
        sequence shorter than the window is learned on all its frames at the end), each
        time on the key frames seen so far (core.growth). A learned skeleton gives Alg. 2's
        joints to its window's frames that have none yet and the fit of the learned model
        (core.live) to every frame after, as the joint node does for a lossless replay. A
        frame a skeleton with other joints answered gets the final skeleton's fit. Step 2
        positions: per-bone rigid fits of every frame."""
        reg = self.registration
        # only frames the registration fitted: empty and diverged frames repeat the last
        # good pose, which would weigh that pose twice (the nodes publish only these too)
        frames = np.flatnonzero(reg.statuses_ == STATUS_OK)
        window = registered[frames].astype(np.float64)
        rest = reg.rest_pose_.points
        observed = [reg.observed_[i] for i in frames]
        seconds = {'segmentation': reg.times_.segmentation, 'preprocess': reg.times_.preprocess,
                   'rest_pose': reg.times_.rest_pose, 'registration': reg.times_.registration,
                   'structure': 0.0, 'joints': 0.0}
        started = time.perf_counter()
        stream = _LearningStream(SkeletonGrowth(rest, self.structure_params, self.joint_params), self.joint_params,
                                 window, observed, seconds)
        since, extracted_once = 0, False
        for i in range(len(frames)):
            stream.answer_live(i)
            since += 1
            if self.schedule.due(since, extracted_once):
                start = max(0, i + 1 - self.schedule.window_size)
                since, extracted_once = 0, True
                if not stream.learn(start, i + 1, raising=False):
                    extracted_once = self.schedule.sliding
        if stream.update is None:
            # nothing learned yet (a sequence shorter than the window, or no window showed
            # articulation): the frames collected so far, as the accumulator's ~/extract
            stream.learn(max(0, len(frames) - self.schedule.window_size), len(frames), raising=True)
        update, model = stream.update, stream.update.model
        joint_positions, confidence = stream.final_answers()
        rotations, translations = fit_rigid_segments(rest, window, update.structure.labels, update.structure.n_bones)
        step2 = joint_trajectories(rotations, translations, update.structure.joints, update.structure.parents)
        # the rest: the Step 2 fits and the live fits
        seconds['live'] = time.perf_counter() - started - seconds['structure'] - seconds['joints']
        return PipelineResult(registered, reg.statuses_, frames, update.structure, update.estimate, model, step2,
                              joint_positions, observed, seconds, frames[update.key_stamps], confidence)


class _LearningStream:
    """The joint node's answers over a stream of registered frames window (F, M, 3) (indices
    0..F-1 serve as stamps): the current model's live fit for each new frame, Alg. 2's
    joints for the learned window's frames that have none; each answer's joints (J, 3) and
    their confidence (J,) against the frame's registered points."""

    def __init__(self, growth: SkeletonGrowth, joint_params: JointParams, window: np.ndarray, observed: list,
                 seconds: dict):
        self.growth, self.joint_params = growth, joint_params
        self.window, self.observed, self.seconds = window, observed, seconds
        self.update = None                  # the newest learned skeleton's GrowthUpdate
        self.tracker = None                 # its live fit
        self.answers = {}                   # frame -> (GrowthUpdate that answered, positions, confidence)

    def answer_live(self, frame: int) -> None:
        if self.tracker is not None:
            self.answers[frame] = (self.update, *self._fit(self.tracker, frame))

    def _fit(self, tracker: LiveJointTracker, frame: int) -> tuple:
        rotations, translations = tracker.fit(self.window[frame])
        return (tracker.joints_of(rotations, translations),
                tracker.confidence(rotations, translations, self.window[frame], True, self.observed[frame]))

    def learn(self, start: int, stop: int, raising: bool) -> bool:
        """Learn on frames start..stop-1 (with the key frames seen before); False when they
        show no articulation (raised with `raising`)."""
        frames = np.arange(start, stop)
        started = time.perf_counter()
        try:
            update = self.growth.update(frames, self.window[frames], [self.observed[i] for i in frames])
        except StructureError:
            self.seconds['structure'] += time.perf_counter() - started
            if raising:
                raise
            return False
        self.seconds['structure'] += self.growth.seconds_['structure']
        self.seconds['joints'] += self.growth.seconds_['joints']
        if self.update is not None and not update.changed:
            return True             # the same skeleton: the nodes keep the model they have
        newest = max(self.answers, default=-1)
        tracker = LiveJointTracker(update.model, self.joint_params)
        estimate = update.estimate
        for k, (frame, positions) in enumerate(zip(update.key_stamps, estimate.joint_trajectories())):
            if frame > newest:
                confidence = tracker.confidence(estimate.rotations[k], estimate.translations[k],
                                                self.window[frame], True, self.observed[frame])
                self.answers[int(frame)] = (update, positions, confidence)
        self.update, self.tracker = update, tracker
        # frames up to `stop` not in the window and newer than every answer: the new model's fit
        for frame in range(newest + 1, stop):
            if frame not in self.answers:
                self.answer_live(frame)
        return True

    def final_answers(self) -> tuple:
        """(positions (F, J, 3), confidence (F, J)): each frame's answer; the final
        skeleton's fit where a skeleton with other joints answered, or none did."""
        names = self.update.model.joint_names
        positions, confidence = [], []
        for frame in range(len(self.window)):
            update, *answer = self.answers.get(frame, (None, None, None))
            if update is None or update.model.joint_names != names:
                answer = self._fit(self.tracker, frame)
            positions.append(answer[0])
            confidence.append(answer[1])
        return np.stack(positions), np.stack(confidence)
