"""Joint scores against the true joints (see the package docstring for what each number
cannot be fooled by)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import rankdata

from ...core.matching import gated_assignment
from ...core.rigid import turn_spans
from .data import EvaluationError, GroundTruth, PredictedSkeleton, match_frames

DEFAULT_MATCH_THRESHOLD_M = 0.15
# A joint that bends less than this within the scored frames cannot be told from its
# parent by motion; 25 degrees moves a 30 cm limb's end by 13 cm.
ARTICULATION_MIN_DEG = 25.0
# A frame with no finite answer for a joint costs the subject's size, and never less than
# this many thresholds (a small subject's size can be close to them).
MISS_PENALTY_FACTOR = 2.0
# A true joint whose trajectory reaches this far from its median travels: it is what a
# downstream consumer follows, and holding it still is visibly wrong (scaled like the
# threshold for subjects smaller than a person).
MOVING_MIN_M = 0.10
# Stricter match radii reported beside the threshold (m, scaled like it): 15 cm is longer
# than a forearm, so two joints placed mid-bone can both match at 15 cm.
RECALL_RADII_M = (0.05, 0.10)
# Subjects smaller than this (bounding-box diagonal, m) get a proportionally smaller
# threshold: 15 cm is a fair "same joint" radius for a person, not for a finger.
REFERENCE_SUBJECT_SIZE_M = 1.5


def match_threshold(subject_scale_m: float, base_m: float = DEFAULT_MATCH_THRESHOLD_M) -> float:
    """`base_m` scaled down for subjects smaller than REFERENCE_SUBJECT_SIZE_M (m)."""
    return base_m * min(1.0, subject_scale_m / REFERENCE_SUBJECT_SIZE_M)


@dataclass
class JointReport:
    """Joint scores (metres); see `evaluate_joints`."""

    mean_error_m: float
    normalized_error_m: float
    recall: float
    n_predicted: int
    n_ground_truth: int
    n_matched: int
    n_frames: int
    threshold_m: float
    precision: float = 0.0
    articulated_precision: float = float('nan')
    articulated_recall: float = float('nan')
    articulated_recall_5cm: float = float('nan')
    articulated_recall_10cm: float = float('nan')
    n_articulated: int = 0
    moving_recall: float = float('nan')
    n_moving: int = 0
    tracking_skill: float = float('nan')
    frame_coverage: float = 0.0
    n_frames_before_start: int = 0
    n_repeated_frames: int = 0
    motion_skill: float = float('nan')
    nonfinite_fraction: float = 0.0
    confidence_auc: float = float('nan')
    n_confident_answers: int = 0
    n_far_answers: int = 0
    missed_articulated: list = field(default_factory=list)
    missed_moving: list = field(default_factory=list)
    per_joint: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def articulation_spans(gt: GroundTruth, gt_idx: np.ndarray) -> np.ndarray:
    """(G,) degrees: for each true joint, the largest angle between two of its bone's
    rotations relative to the parent bone over the frames `gt_idx` (0 for root joints,
    NaN for every joint when the ground truth has no bone transforms)."""
    n_joints = gt.joints.shape[1]
    if gt.bone_transforms is None or gt.joint_bones is None or gt.bone_parents is None:
        return np.full(n_joints, np.nan)
    rotations = gt.bone_transforms[gt_idx][..., :3, :3]                       # (F, B, 3, 3)
    return turn_spans(rotations, gt.bone_parents)[np.asarray(gt.joint_bones, dtype=int)]


def geometric_median(trajectories: np.ndarray, iterations: int = 100) -> np.ndarray:
    """(G, 3): the point of each trajectory (F, G, 3) with the least mean distance to it
    (Weiszfeld's iteration). No static point is closer on average, so holding a joint
    there is the best any prediction that does not move can do."""
    centre = np.median(trajectories, axis=0)
    for _ in range(iterations):
        distance = np.maximum(np.linalg.norm(trajectories - centre, axis=-1), 1e-9)   # (F, G)
        weights = 1.0 / distance
        centre = np.einsum('fg,fgi->gi', weights, trajectories) / weights.sum(axis=0)[:, None]
    return centre


def scored_window(pred: PredictedSkeleton, gt: GroundTruth, start_stamp: float | None,
                  end_stamp: float | None = None):
    """The ground-truth frames scored, (W,) indices from the start to the end, and (W,) the
    index of the predicted frame for each, -1 where none; the number of predicted frames
    that repeat a ground-truth frame another one already answers; the number of frames
    before the start.

    The start is `start_stamp` (the registration's first frame), else the first frame in
    which the subject is in view (the whole sequence without that record); the end is
    `end_stamp` (the last frame given to the method, s), else the last frame."""
    ordered = np.argsort(gt.stamps, kind='stable')
    sorted_stamps = gt.stamps[ordered]
    tolerance = 0.25 * (float(np.median(np.diff(sorted_stamps))) if len(gt.stamps) > 1 else 1.0)
    if start_stamp is None:
        in_view = gt.subject_in_view
        start = int(np.argmax(in_view[ordered])) if in_view is not None and in_view.any() else 0
    else:
        start = int(np.searchsorted(sorted_stamps, start_stamp - tolerance))
    end = len(ordered) if end_stamp is None else int(np.searchsorted(sorted_stamps, end_stamp + tolerance))
    window = ordered[start:end]
    pred_idx, gt_idx = match_frames(pred.stamps, gt.stamps)
    slot = np.full(len(gt.stamps), -1)
    # the first predicted frame answers a ground-truth frame; a copy under the same stamp
    # answers nothing more
    first_of_each = np.unique(gt_idx, return_index=True)[1]
    slot[gt_idx[first_of_each]] = pred_idx[first_of_each]
    return window, slot[window], len(gt_idx) - len(first_of_each), start


def confidence_auc(confidence: np.ndarray, errors: np.ndarray, threshold: float) -> tuple:
    """How well a published confidence ranks a frame's answers: over the answers (K,) with
    a finite confidence (K,) and error (K,) m, the probability that an answer within
    `threshold` has a higher confidence than one beyond it (ties count half; the Mann-Whitney
    U over both counts): 1 = every far answer flagged below every near one, 0.5 = no
    information. Returns (auc, near answers, far answers); auc NaN when either is empty."""
    usable = np.isfinite(confidence) & np.isfinite(errors)
    confidence, errors = confidence[usable], errors[usable]
    near = errors <= threshold
    n_near, n_far = int(near.sum()), int((~near).sum())
    if n_near == 0 or n_far == 0:
        return float('nan'), n_near, n_far
    ranks = rankdata(confidence)
    return float((ranks[near].sum() - n_near * (n_near + 1) / 2) / (n_near * n_far)), n_near, n_far


def limb_directions(truth: np.ndarray, parents) -> np.ndarray:
    """(W, G, 3) unit direction of each true joint's limb per frame, from the joint towards
    its farthest child (the bone it starts), or for a joint without children from its
    parent through it; NaN where the limb has no length. truth (W, G, 3) m, parents (G,)
    -1 for the root. A joint placed along this direction sits inside the limb, before or
    past where the limb bends; across it, beside the limb."""
    parents = np.asarray(parents)
    lengths = np.linalg.norm(truth - truth[:, np.maximum(parents, 0)], axis=-1).mean(axis=0)   # (G,)
    lengths[parents < 0] = -np.inf
    n = truth.shape[1]
    longest_child = np.full(n, -1)
    for child in np.argsort(lengths):   # loop over joints: the longest child written last
        if parents[child] >= 0:
            longest_child[parents[child]] = child
    has_child = longest_child >= 0
    direction = np.where(has_child[None, :, None], truth[:, np.maximum(longest_child, 0)] - truth,
                         truth - truth[:, np.maximum(parents, 0)])
    norm = np.linalg.norm(direction, axis=-1, keepdims=True)
    return np.where(norm > 1e-9, direction / np.maximum(norm, 1e-12), np.nan)


def evaluate_joints(pred: PredictedSkeleton, gt: GroundTruth, threshold_m: float | None = None,
                    start_stamp: float | None = None, end_stamp: float | None = None) -> JointReport:
    """Joint accuracy of `pred` against `gt` over the W ground-truth frames from the start
    to the end (see `scored_window`; pass the registration's first and last stamps).

    Every scored frame is answered by the predicted frame with its stamp or it is a miss:
    a frame with no prediction, a repeated stamp and a non-finite joint cost `miss_cost`
    (the subject's size, at least MISS_PENALTY_FACTOR thresholds: more than any answer on
    the body, so leaving a bad frame out never pays). A predicted root (parent -1) pairs
    only with a true root: it is the root bone's centre, not a joint where the body bends.

    mean_error_m: mean over matched joints of the mean distance over the W frames (m);
    normalized_error_m: the same after removing each matched joint's mean offset (finite
    frames); recall: matched / ground-truth joints; precision: matched / predicted joints;
    articulated_precision: those matched to a bending joint / predicted joints (a joint
    matched to a true joint that does not bend in these frames is one the motion cannot
    justify; on a body of 21 joints a cut through a rigid part lands within the threshold
    of one easily);
    articulated_recall over the n_articulated joints that bend >= ARTICULATION_MIN_DEG in
    these frames (NaN without bone transforms), also counted with pairs within 5 and 10 cm
    (scaled like the threshold); moving joints (n_moving) travel >= MOVING_MIN_M from their
    median: moving_recall counts those matched whose error is below holding the true joint
    still at its geometric median (its static error), tracking_skill = 1 - their summed
    error / summed static error, an unmatched moving joint costing its static error (so any
    skeleton that does not move scores <= 0, the truth 1); frame_coverage: scored frames
    with every joint finite / W; motion_skill: 1 - mean normalized error / mean true motion
    spread over matched joints; nonfinite_fraction: share of scored joint-frames missing.
    per_joint: one row per true joint: found, the predicted joint, its error; the nearest
    predicted joint (mean distance over the frames, a miss costing as above) and the true
    joint it was matched to, if any (a joint not found whose nearest answers another: the
    skeleton has one joint where the truth has two); the offset along the camera ray (+ =
    farther than the truth) and across it, along its limb (`limb_directions`, + = towards
    the limb's far end; None where the limb has no length), the offset-removed error,
    travel and static error. Read every error next to recall and precision.
    """
    if gt.joints.shape[1] == 0:
        raise EvaluationError('the ground truth has no joints (a captured mesh sequence?): '
                              'only the registration can be scored')
    window, answer, n_repeated, n_before = scored_window(pred, gt, start_stamp, end_stamp)
    if len(window) == 0 or (answer < 0).all():
        raise EvaluationError('no predicted frame has a ground-truth frame with the same stamp '
                              f'from the start on (prediction {pred.stamps.min():.3f}..'
                              f'{pred.stamps.max():.3f} s, ground truth {gt.stamps[0]:.3f}..'
                              f'{gt.stamps[-1]:.3f} s, scored from frame {n_before})')
    threshold = match_threshold(gt.subject_scale_m) if threshold_m is None else float(threshold_m)
    scale = threshold / DEFAULT_MATCH_THRESHOLD_M
    miss_cost = max(gt.subject_scale_m, MISS_PENALTY_FACTOR * threshold)
    n_pred = pred.positions.shape[1]
    predicted = np.full((len(window), n_pred, 3), np.nan)                # (W, J, 3)
    predicted[answer >= 0] = pred.positions[answer[answer >= 0]]
    truth = gt.joints[window].astype(np.float64)                          # (W, G, 3)
    n_gt = truth.shape[1]
    spans = articulation_spans(gt, window)
    articulated = spans >= ARTICULATION_MIN_DEG
    median = geometric_median(truth)                                      # (G, 3)
    static_error = np.linalg.norm(truth - median, axis=-1).mean(axis=0)   # (G,)
    travel = np.linalg.norm(truth - np.median(truth, axis=0), axis=-1).max(axis=0)
    moving = travel >= MOVING_MIN_M * scale
    finite = np.isfinite(predicted).all(axis=-1)                          # (W, J)
    report = JointReport(float('nan'), float('nan'), 0.0, n_pred, n_gt, 0, len(window), threshold,
                         n_articulated=int(articulated.sum()), n_moving=int(moving.sum()),
                         n_frames_before_start=n_before, n_repeated_frames=n_repeated,
                         frame_coverage=float(finite.all(axis=1).mean()) if n_pred else 0.0,
                         nonfinite_fraction=float(1.0 - finite.mean()) if n_pred else 1.0)
    # (W, J, G) distances: J and G are tens, W a few hundred frames
    distances = np.linalg.norm(predicted[:, :, None, :] - truth[:, None, :, :], axis=-1)
    distances = np.where(finite[:, :, None], distances, miss_cost)
    cost = distances.mean(axis=0)                                          # (J, G)
    # a predicted root is the root bone's centre, not a place where two bones turn: it answers
    # the true root only (else it "finds" a hip or a shoulder it happens to lie near)
    predicted_root = np.asarray(pred.parents, dtype=int) < 0
    true_root = np.asarray(gt.joint_parents, dtype=int) < 0
    cost[predicted_root[:, None] & ~true_root[None, :]] = np.inf
    # the most pairs within the threshold, then the nearest (the bare assignment can pair a
    # joint 8 cm from the wrist with a joint 40 cm away, and drop both)
    rows, cols = gated_assignment(cost, threshold)
    match = np.full(n_gt, -1)
    match[cols] = rows
    error = np.where(match >= 0, cost[np.maximum(match, 0), np.arange(n_gt)], np.nan)   # (G,)
    within = {radius: (match >= 0) & (error <= radius * scale) for radius in RECALL_RADII_M}
    tracks = (match >= 0) & (error < static_error)
    if pred.confidence is not None and len(rows):
        confidence = np.full((len(window), n_pred), np.nan)
        confidence[answer >= 0] = pred.confidence[answer[answer >= 0]]
        answer_error = np.linalg.norm(predicted[:, rows] - truth[:, cols], axis=-1)     # (W, matched)
        report.confidence_auc, report.n_confident_answers, report.n_far_answers = confidence_auc(
            confidence[:, rows].ravel(), answer_error.ravel(), threshold)
    report.precision = len(rows) / n_pred if n_pred else 0.0
    report.n_matched = len(rows)
    report.recall = len(rows) / n_gt
    if not np.isnan(spans).all() and articulated.any():
        report.articulated_recall = float((match >= 0)[articulated].mean())
        report.articulated_precision = float((match >= 0)[articulated].sum() / n_pred) if n_pred else 0.0
        report.articulated_recall_5cm = float(within[0.05][articulated].mean())
        report.articulated_recall_10cm = float(within[0.10][articulated].mean())
        report.missed_articulated = [gt.joint_names[g] for g in np.flatnonzero(articulated & (match < 0))]
    if moving.any():
        report.moving_recall = float(tracks[moving].mean())
        report.tracking_skill = float(1.0 - np.where(match >= 0, error, static_error)[moving].sum()
                                      / max(static_error[moving].sum(), 1e-12))
        report.missed_moving = [gt.joint_names[g] for g in np.flatnonzero(moving & ~tracks)]
    # camera rays: the optical frame's origin is the camera, so a true joint's mean position
    # is its ray
    rays = truth.mean(axis=0)
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-9)
    limbs = limb_directions(truth, gt.joint_parents)                       # (W, G, 3)
    normalized, spreads = [], []
    # each true joint's nearest predicted joint (mean distance, misses costed): for a joint not
    # found, whether the skeleton lacks a joint there (its nearest answers another true joint)
    # or has one too far off
    nearest = np.where(np.isfinite(cost).any(axis=0), cost.argmin(axis=0), -1) if n_pred else np.full(n_gt, -1)
    answers = np.full(n_pred, -1)
    answers[rows] = cols
    for g in range(n_gt):   # loop over true joints, not points
        j = int(nearest[g])
        row = {'ground_truth': gt.joint_names[g], 'predicted': None, 'found': False,
               'nearest_predicted': pred.joint_names[j] if j >= 0 else None,
               'nearest_m': float(cost[j, g]) if j >= 0 else None,
               'nearest_answers': gt.joint_names[answers[j]] if j >= 0 and answers[j] >= 0 else None,
               'found_5cm': bool(within[0.05][g]), 'found_10cm': bool(within[0.10][g]),
               'articulated': bool(articulated[g]), 'span_deg': float(spans[g]) if np.isfinite(spans[g]) else None,
               'moving': bool(moving[g]), 'tracks': bool(tracks[g]), 'travel_m': float(travel[g]),
               'static_error_m': float(static_error[g])}
        r = int(match[g])
        if r >= 0:
            offsets = (predicted[:, r] - truth[:, g])[finite[:, r]]
            mean_offset = offsets.mean(axis=0)
            along = float(mean_offset @ rays[g])
            normalized.append(float(np.linalg.norm(offsets - mean_offset, axis=1).mean()))
            spreads.append(float(np.linalg.norm(truth[:, g] - truth[:, g].mean(axis=0), axis=1).mean()))
            along_limb = np.einsum('wi,wi->w', offsets, limbs[finite[:, r], g])
            row.update(predicted=pred.joint_names[r], found=True, error_m=float(error[g]),
                       normalized_error_m=normalized[-1], offset_along_ray_m=along,
                       offset_across_ray_m=float(np.linalg.norm(mean_offset - along * rays[g])),
                       offset_along_limb_m=float(np.nanmean(along_limb)) if np.isfinite(along_limb).any() else None)
        report.per_joint.append(row)
    if len(rows):
        report.mean_error_m = float(np.nanmean(error))
        report.normalized_error_m = float(np.mean(normalized))
        report.motion_skill = float(1.0 - np.mean(normalized) / max(np.mean(spreads), 1e-9))
    return report
