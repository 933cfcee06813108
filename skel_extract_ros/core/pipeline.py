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

from .joints import JointEstimate, JointEstimation, JointParams
from .preprocess import PreprocessParams
from .registration import STATUS_OK, RegistrationParams
from .rest_pose import RestPoseParams
from .segmentation import SegmentationParams
from .sequence import SequenceRegistration
from .skeleton_model import SkeletonModel
from .structure import SkeletalStructure, StructureParams, extract_structure


@dataclass
class PipelineResult:
    """registered: (F, M, 3); statuses: (F,); frames: indices of the frames with a skeleton
    (those registered with status ok); step2_positions / joint_positions: (F', J, 3) joint
    positions after Step 2 and after Step 3 for those frames; seconds per step."""

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
        """Steps 2 and 3 on the frames `register` produced (raises StructureError)."""
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
        started = time.perf_counter()
        structure = extract_structure(rest, window, self.structure_params)
        seconds['structure'] = time.perf_counter() - started
        started = time.perf_counter()
        observed = [reg.observed_[i] for i in frames]
        estimate = JointEstimation(self.joint_params).fit(rest, window, observed, structure)
        seconds['joints'] = time.perf_counter() - started
        model = SkeletonModel(rest, structure.labels, estimate.parents, estimate.joints,
                              estimate.influences, estimate.weights)
        return PipelineResult(registered, statuses, frames, structure, estimate, model,
                              structure.joint_trajectories(), estimate.joint_trajectories(),
                              observed, seconds)
