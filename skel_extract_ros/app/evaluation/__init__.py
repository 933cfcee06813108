"""Accuracy metrics against simulated ground truth, made hard to game.

Joint accuracy follows the paper (Sec. 7): the Euclidean distance error over the *common
subset* of joints, with Helten et al.'s per-joint normalisation. Predicted and true joints
are paired one-to-one (Hungarian assignment on the mean distance over the frames, the
pairs within a threshold first), and a pair farther apart than the threshold does not count
as found. What users downstream need is the joints that move, where the body bends, in
every frame; what each number cannot be fooled by, with a test for each in
test/test_evaluation.py:

- predicting many joints: each true joint takes at most one, and `precision` (matched /
  predicted) and `n_predicted` stand beside every recall (2,000 surface points given as
  "joints" score recall 1 but precision 0.01);
- predicting joints that never bend: `articulated_recall` counts only the true joints
  whose rotation relative to their parent bone spans >= ARTICULATION_MIN_DEG within the
  scored frames, the joints a motion-based method can find at all, and
  `articulated_precision` the predicted joints matched to one of those (cuts through rigid
  parts land within the threshold of a true joint that does not bend easily);
- placing two joints in the middle of a bone shorter than the threshold: the articulated
  recall at 5 and 10 cm stands beside the 15 cm one;
- standing still: `tracking_skill` compares the error on the joints that travel
  (>= MOVING_MIN_M from their median) with holding each true joint at its geometric
  median, the best static answer, so any skeleton that does not move scores 0 or below
  and `moving_recall` counts only the moving joints tracked better than that;
- leaving frames out, repeating one, or blanking the bad ones: every ground-truth frame
  from the registration's start is scored, a frame with no answer (missing, repeated
  stamp, NaN) costs the subject's size, more than any answer on the body, and
  `frame_coverage` says how many frames had every joint;
- registration that collapses or drifts off the body: each registered point is tied at
  the registration's first frame to the true surface and followed as that material point
  (with the sample's bone transform in simulation, barycentric coordinates on a captured
  mesh), and it pays how far it was from the surface there beyond the ground truth's own
  sampling spacing, so points collapsed to the centroid score their distance to the
  surface instead of 0, and `coverage` (the share of the true surface near a registered
  point at the start: about half for one camera's view, 0 for a collapse) says how much
  of the body the points stand for; a registered point that is non-finite after the
  registration's first frame costs the subject's size.
"""
from __future__ import annotations

from .data import EvaluationError, GroundTruth, PredictedSkeleton, load_registered, match_frames
from .joints import (ARTICULATION_MIN_DEG, DEFAULT_MATCH_THRESHOLD_M, MISS_PENALTY_FACTOR, MOVING_MIN_M,
                     RECALL_RADII_M, JointReport, articulation_spans, evaluate_joints, geometric_median,
                     match_threshold, scored_window)
from .registration import evaluate_registration, registration_span

__all__ = ['ARTICULATION_MIN_DEG', 'DEFAULT_MATCH_THRESHOLD_M', 'MISS_PENALTY_FACTOR', 'MOVING_MIN_M',
           'RECALL_RADII_M', 'EvaluationError', 'GroundTruth', 'JointReport', 'PredictedSkeleton',
           'articulation_spans', 'evaluate_joints', 'evaluate_outputs', 'evaluate_registration',
           'geometric_median', 'load_registered', 'match_frames', 'match_threshold', 'registration_span',
           'scored_window']


def evaluate_outputs(gt: GroundTruth, skeleton_path=None, registered_path=None,
                     threshold_m: float | None = None) -> dict:
    """{'joints': JointReport as a dict, 'registration': ...} for the files `run` and
    `replay` write; the joints are scored over the registration's frames when the
    registered points are given."""
    result = {}
    span = (None, None)
    if registered_path is not None:
        points, stamps, rest_points = load_registered(registered_path)
        result['registration'] = evaluate_registration(points, stamps, gt, rest_points=rest_points)
        span = registration_span(points, stamps)
    if skeleton_path is not None:
        result['joints'] = evaluate_joints(PredictedSkeleton.load(skeleton_path), gt, threshold_m,
                                           *span).as_dict()
    return result
