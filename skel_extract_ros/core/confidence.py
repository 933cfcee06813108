r"""Per-joint confidence in [0, 1]: how far the data of a frame supports a published joint.

The one place that defines it is `joint_confidence`; the nodes publish what it returns
(skeleton/confidence, the markers' colours and labels; docs/contract.md) and nothing else
computes a per-frame confidence. How far the motion fixed each joint's pivot is a property
of the learned skeleton, not of a frame: it is published beside, in the description's and
skeleton.json's `pivot` (core.joint_centres.pivot_evidence), and not folded in here.

The measure here is the live fit's residual of each bone's points, which every path that
publishes joints has at hand:
- a frame with registered points (the window, `live_frames registered`, a camera frame
  whose own registration is in): sample m is the model point m, its residual the
  distance between the registered point and the LBS-posed model point (they correspond);
- a camera frame fitted to its observed points: sample n is an observed point, its bones
  those of the nearest posed model point, its residual the distance to it (the camera
  sees one side of the body: a model point on the far side has no observation, an
  observation always has a model point).
A sample counts towards each bone its model point follows, by its LBS weight w (Eq. 8): a
short bone between two longer ones may be no point's main bone and still has its share of
points. Bone b gets

    c_b = 1 / (1 + mean_b(r^2) / h^2) * min(1, n_b / MIN_SAMPLES)

(mean_b and n_b weighted by w; 1 when its points sit on the data, 1/2 at an RMS residual
of h, and 0 for a bone the frame did not see at all: its joint then comes from the joint
term and the previous pose only).
h is NOISE_MULTIPLE times the skeleton's own noise, the RMS distance of the observed points
to its fit on the frames it was learned on (SkeletonModel.noise_m: from Alg. 2's tau, and for
Step 2's provisional skeleton `fit_noise` of its bones' rigid fits): what counts as off is
measured on the subject and the camera at hand, so a hand's millimetres and a cow's
centimetres are judged alike (HALF_RESIDUAL where the noise is not known).

c_b is multiplied by 1 - o_b when the frame's observed points are at hand, o_b the share of
bone b's posed points that lie outside the subject's silhouette (no observed ray passes
near theirs: `outside_silhouette`). The camera saw nothing where those points are, so the
pose there is wrong whatever the residual says: a registration that lost a limb carries it
into empty space with its points, and fits it as well as any other (the residual of a
registered frame compares the pose with the registration, not with the camera). A bone
hidden behind the body stays inside the silhouette and keeps its confidence: the camera
cannot tell.

Joint b, which sits between bone b and its parent bone, gets the smaller of the two bones'
confidences (the root joint, the root bone's centre, its bone's). It says how well the
posed model explains the points near a joint, not whether the joint is anatomically right:
a bone that fits its points may still pivot at the wrong place.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .point_sets import finite_rows, strided_subset
from .registration.visibility import ObservedView

# a bone's confidence is one half at an RMS residual of this many times the skeleton's own
# noise (SkeletonModel.noise_m); chosen on the real-motion bench's tuning half and the
# built-in hand (bench/HISTORY.md, "The joints' confidence from the silhouette")
NOISE_MULTIPLE = 1.5
# the RMS residual (m) of confidence 1/2 where the skeleton's noise is unknown: about twice
# the spread of the registered points around the posed model on the sample bag's good frames
HALF_RESIDUAL = 0.03
# a bone with fewer samples than this in a frame is partly seen: its confidence shrinks in
# proportion (0 samples: 0)
MIN_SAMPLES = 10
# observed points a frame's fit noise is measured on at most (a strided subset): an RMS
# distance needs no more
NOISE_SAMPLES = 1000


def half_residual(noise_m: float | None) -> float:
    """The RMS residual (m) at which a bone's confidence is one half, for a skeleton whose
    fit noise is noise_m (m; None: not known)."""
    if noise_m is None or not np.isfinite(noise_m) or noise_m <= 0:
        return HALF_RESIDUAL
    return NOISE_MULTIPLE * float(noise_m)


def fit_noise(posed: np.ndarray, observed: list) -> float | None:
    """m: the median over frames of the RMS distance from each frame's observed points (N_t,
    3) m to the nearest of its posed model points (posed (F, M, 3) m): the noise of a fit
    whose GMM variance is not at hand (Step 2's bones' rigid fits), as SkeletonModel.noise_m
    is Alg. 2's (sqrt(3 tau): the same RMS distance, its posterior-weighted form). None when
    no frame has observed points."""
    rms = []
    for points, observed_points in zip(posed, observed):
        observed_points = np.asarray(observed_points, dtype=np.float64)
        observed_points = observed_points[finite_rows(observed_points)]
        if len(observed_points) == 0:
            continue
        observed_points = strided_subset(observed_points, NOISE_SAMPLES)
        distance, _ = cKDTree(points).query(observed_points)
        rms.append(np.sqrt(np.mean(distance ** 2)))
    return float(np.median(rms)) if rms else None


def _per_bone(n_bones: int, bone_of_sample, values, sample_weights) -> tuple:
    """(sum of weight x value, sum of weight) per bone (B,), (B,): samples (K,) or, with
    their LBS weights (K, k), a sample counted towards each bone it follows by its weight."""
    bones = np.asarray(bone_of_sample, dtype=np.int64)
    values = np.broadcast_to(np.asarray(values, dtype=np.float64).reshape(len(bones), *([1] * (bones.ndim - 1))),
                             bones.shape)
    weights = np.ones(bones.shape) if sample_weights is None else np.asarray(sample_weights, dtype=np.float64)
    weights = np.where(np.isfinite(values), weights, 0.0)
    bones, values, weights = bones.ravel(), np.where(np.isfinite(values), values, 0.0).ravel(), weights.ravel()
    return (np.bincount(bones, weights=weights * values, minlength=n_bones)[:n_bones],
            np.bincount(bones, weights=weights, minlength=n_bones)[:n_bones])


def bone_confidence(n_bones: int, bone_of_sample: np.ndarray, squared_residuals: np.ndarray,
                    half: float = HALF_RESIDUAL, sample_weights: np.ndarray | None = None) -> np.ndarray:
    """(B,) confidence of each bone from samples: bone_of_sample (K,) bone index per sample,
    or (K, k) the bones it follows with their LBS weights sample_weights (K, k), so that a
    bone whose points all follow a neighbour more than it still has its share of them;
    squared_residuals (K,) m^2 (non-finite samples are ignored); half (m): the RMS residual
    of confidence 1/2 (`half_residual`)."""
    sums, counts = _per_bone(n_bones, bone_of_sample, squared_residuals, sample_weights)
    mean_squared = sums / np.maximum(counts, 1e-12)
    fit = 1.0 / (1.0 + mean_squared / half ** 2)
    return fit * np.minimum(1.0, counts / MIN_SAMPLES)


def outside_silhouette(n_bones: int, bone_of_point: np.ndarray, posed: np.ndarray, view: ObservedView,
                       point_weights: np.ndarray | None = None) -> np.ndarray:
    """(B,) share of each bone's posed points (M, 3) m that lie outside the silhouette of the
    frame's observed view (no observed ray within the view's SILHOUETTE_SPACINGS ray
    spacings of theirs); bone_of_point (M,) or (M, k) with LBS weights point_weights (M, k),
    as in bone_confidence; 0 for a bone without points."""
    outside, counts = _per_bone(n_bones, bone_of_point, view.outside(posed), point_weights)
    return outside / np.maximum(counts, 1e-12)


def joint_confidence(parents, bone_of_sample: np.ndarray, squared_residuals: np.ndarray,
                     bone_outside: np.ndarray | None = None, half: float = HALF_RESIDUAL,
                     sample_weights: np.ndarray | None = None) -> np.ndarray:
    """(J,) confidence in [0, 1] of each joint of a frame (joint b: between bone b and its
    parent bone; parents (J,), -1 for the root). Samples as in bone_confidence;
    bone_outside (B,): each bone's share of posed points outside the silhouette
    (`outside_silhouette`; None: not known); half as in bone_confidence."""
    parents = np.asarray(parents, dtype=np.int64)
    bones = bone_confidence(len(parents), bone_of_sample, squared_residuals, half, sample_weights)
    if bone_outside is not None:
        bones = bones * (1.0 - np.clip(bone_outside, 0.0, 1.0))
    return np.where(parents >= 0, np.minimum(bones, bones[np.maximum(parents, 0)]), bones)
