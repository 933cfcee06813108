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

from .growth import SkeletonGrowth
from .joints import JointEstimate, JointParams
from .live import LiveJointTracker
from .preprocess import PreprocessParams
from .registration import STATUS_OK, RegistrationParams
from .rest_pose import RestPoseParams
from .segmentation import SegmentationParams
from .sequence import SequenceRegistration
from .skeleton_model import SkeletonModel
from .rigid import fit_rigid_segments
from .structure import SkeletalStructure, StructureParams, joint_trajectories


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
                 joints: JointParams | None = None, segmentation: SegmentationParams | None = None):
        self.registration = SequenceRegistration(registration, rest_pose, preprocess, keep_observed=True,
                                                 segmentation_params=segmentation)
        self.structure_params = structure or StructureParams()
        self.joint_params = joints or JointParams()

    def register(self, frames: Iterable[np.ndarray], on_frame: Callable[[int, str], None] | None = None):
        """Step 0-1 only: (F, M, 3) registered points (see SequenceRegistration)."""
        return self.registration.register(frames, on_frame)

    def extract(self, registered: np.ndarray) -> PipelineResult:
        """Steps 2 and 3 on the frames `register` produced (raises StructureError).

        The skeleton is learned on the key frames (core.growth: the most different poses,
        at most structure max_key_frames of them; every frame of a shorter sequence), so a
        long recording in which the limbs move at different times gives one skeleton with
        all of them. Key frames get Alg. 2's joints; the other frames the learned model
        fitted to their registered points (core.live), Step 2 positions from per-bone rigid
        fits."""
        reg = self.registration
        statuses = reg.statuses_
        # only frames the registration fitted: empty and diverged frames repeat the last
        # good pose, which would weigh that pose twice (the nodes publish only these too)
        frames = np.flatnonzero(statuses == STATUS_OK)
        window = registered[frames].astype(np.float64)
        rest = reg.rest_pose_.points
        seconds = {'segmentation': reg.times_.segmentation, 'preprocess': reg.times_.preprocess,
                   'rest_pose': reg.times_.rest_pose,
                   'registration': reg.times_.registration}
        observed = [reg.observed_[i] for i in frames]
        growth = SkeletonGrowth(rest, self.structure_params, self.joint_params)
        started = time.perf_counter()
        update = growth.update(frames, window, observed)       # frame indices serve as stamps
        seconds['structure'] = growth.seconds_['structure']
        seconds['joints'] = growth.seconds_['joints']
        structure, estimate = update.structure, update.estimate
        model = SkeletonModel(rest, structure.labels, estimate.parents, estimate.joints,
                              estimate.influences, estimate.weights, update.joint_ids)
        key = np.searchsorted(frames, update.key_stamps)             # key frames among `frames`
        # Step 2: per-bone rigid fits on every frame; Step 3: Alg. 2 on the key frames, the
        # learned model fitted to the others
        rotations, translations = fit_rigid_segments(rest, window, structure.labels, structure.n_bones)
        step2 = joint_trajectories(rotations, translations, structure.joints, structure.parents)
        joint_positions = np.empty_like(step2)
        confidence = np.empty(step2.shape[:2])
        joint_positions[key] = estimate.joint_trajectories()
        tracker = LiveJointTracker(model, self.joint_params)
        for k, i in enumerate(key):
            confidence[i] = tracker.confidence(estimate.rotations[k], estimate.translations[k], window[i], True)
        for i in np.setdiff1d(np.arange(len(frames)), key):
            rotations_i, translations_i = tracker.fit(window[i])
            joint_positions[i] = tracker.joints_of(rotations_i, translations_i)
            confidence[i] = tracker.confidence(rotations_i, translations_i, window[i], True)
        # the rest: choosing the key frames, the Step 2 fits and the live fits of the others
        seconds['live'] = time.perf_counter() - started - seconds['structure'] - seconds['joints']
        return PipelineResult(registered, statuses, frames, structure, estimate, model, step2, joint_positions,
                              observed, seconds, frames[key], confidence)
