r"""The subject's own limb poses as starts of the live fit: a limb that moved beyond the fit's
reach since the registered pose is put where one of the poses the skeleton was learned on
puts it, when that explains the frame's points clearly better.

The live fit (core.live.ArticulatedTracker) is a local EM: started from the newest registered
pose, it follows what moved a few tau since, and a hand that swung 40-90 cm within one
registration lag lies beyond its reach (its data are out of the truncated E-step, or taken
by the wrong bone). The skeleton was learned on key frames that show how this subject's limbs
move; each of those frames' bone transforms (Alg. 2's, A_j^k = (R_j^k, T_j^k)) gives each
limb a pose relative to the bone it hangs from, A_p^k^-1 A_j^k, which carries over to any
frame whatever the body does. So before each fit from the registered pose, every limb may be
re-posed: with its parent's transform A_p of the start, hypothesis k poses the limb's bones
as A_p A_p^k^-1 A_j^k (its joint with the parent stays where the learned pose had it, up to
the joint term's slack), and is scored against the frame's observed points V by a truncated
symmetric chamfer distance

    E_k = mean_{i in limb} min(d(x_i^k, V), c)^2 + mean_{v in U} min(d(v, X^k), c)^2

over the limb's posed points x_i^k (a strided subset) and the observations U no other part of
the start explains (farther than c from every other posed model point) within the limb's
reach of its joint (its rest points' farthest distance from it, + c), c = CAP_MULTIPLE x the
skeleton's own noise scale (core.confidence.half_residual: a hand's millimetres and a cow's
centimetres alike). The first term keeps a limb off empty space, the second makes it explain
the points the rest leaves; the start's own limb pose is hypothesis 0, and a limb is re-posed
only when the best hypothesis scores under MARGIN x it. A frame that the start explains
(fewer than MIN_SAMPLES observations farther than c from it) and a limb with fewer such
observations in reach are left as they are. The fit that follows refines the pose as from
any start.

A limb starts where the tree branches: every bone whose parent is the root or has several
children (an arm at the chest, a leg at the pelvis, a finger at the palm, the neck), with
everything below it; limbs are taken from the root down, so a limb re-posed moves its
sub-limbs, which are then scored from there. Issue 30's "several hypotheses for a lost limb,
scored by the data", on the live path; measured in bench/README.md, the live fit's table.
"""
from __future__ import annotations

import numpy as np

from .bone_rotations import children_of
from .confidence import MIN_SAMPLES, half_residual
from .growth import farthest_poses
from .point_sets import finite_rows, nearest_within, strided_subset, subset_stride
from .skeleton_model import SkeletonModel

# the truncation of the chamfer distance in units of the skeleton's noise scale
# (half_residual): past it a point is unexplained, however far
CAP_MULTIPLE = 3.0
# a limb is re-posed when its best hypothesis scores under this share of its start's
MARGIN = 0.8
# hypotheses a limb keeps at most: the key frames' poses farthest apart (a window of 60
# frames repeats poses; the score's cost grows with their number)
MAX_POSES = 16
# model points the start is posed on, posed points a limb is scored on, observations (the
# frame's, and those the rest leaves unexplained), each at most: strided subsets, a chamfer
# mean needs no more
MODEL_POINTS = 1000
LIMB_POINTS = 30
SCORED_OBSERVED = 1000
UNEXPLAINED_POINTS = 60
# neighbours of each observation among the start's posed points, from which its distance to
# the start without a limb is read: an observation whose nearest all lie on the limb counts as
# one the rest leaves (it lies on the limb's own surface, which the limb's pose explains)
NEIGHBOURS = 8


class LimbPoses:
    """Each limb's poses relative to the bone it hangs from, on the key frames of a model.

    model: the SkeletonModel; key_rotations (K, B, 3, 3), key_translations (K, B, 3): the
    bone transforms (rest -> frame) of the frames it was learned on (Alg. 2's,
    JointEstimate.rotations / translations). `limbs`: the first bone of each limb, root
    first; `reposed`: how many limbs `repose` has moved so far.
    """

    def __init__(self, model: SkeletonModel, key_rotations: np.ndarray, key_translations: np.ndarray):
        key_rotations = np.asarray(key_rotations, dtype=np.float64)
        key_translations = np.asarray(key_translations, dtype=np.float64)
        parents = np.asarray(model.parents, dtype=np.int64)
        B = len(parents)
        if key_rotations.ndim != 4 or key_rotations.shape[1:] != (B, 3, 3) or \
                key_translations.shape != key_rotations.shape[:2] + (3,):
            raise ValueError(f'key poses must be (K, {B}, 3, 3) rotations and (K, {B}, 3) translations, got '
                             f'{key_rotations.shape} and {key_translations.shape}')
        rest = np.asarray(model.rest_points, dtype=np.float64)
        stride = subset_stride(len(rest), MODEL_POINTS)
        self._rest, self._labels = rest[::stride], np.asarray(model.labels, dtype=np.int64)[::stride]
        self._parents = parents
        self._cap = CAP_MULTIPLE * half_residual(model.noise_m)
        children = children_of(parents)
        self.limbs = [int(b) for b in _breadth_first(parents, children)
                      if parents[b] >= 0 and (parents[parents[b]] < 0 or len(children[parents[b]]) > 1)]
        self.reposed = 0
        self._bones, self._points, self._local, self._relative, self._reach = {}, {}, {}, {}, {}
        self._in_limb = {}
        self._rest_joints = rest_joints = np.asarray(model.rest_joints, dtype=np.float64)
        for limb in self.limbs:
            bones = _subtree(limb, children)
            members = np.flatnonzero(np.isin(self._labels, bones))
            if len(members) < MIN_SAMPLES:
                continue
            # how far from its joint any pose of the limb can put its points
            self._reach[limb] = float(np.max(np.linalg.norm(self._rest[members] - rest_joints[limb], axis=1)))
            points = strided_subset(members, LIMB_POINTS)
            local = np.searchsorted(bones, self._labels[points])                  # bones is sorted
            parent = parents[limb]
            # A_p^k^-1 A_j^k for the limb's bones j: (K, b, 3, 3), (K, b, 3)
            rotations = np.einsum('kji,kbjl->kbil', key_rotations[:, parent], key_rotations[:, bones])
            translations = np.einsum('kji,kbj->kbi', key_rotations[:, parent],
                                     key_translations[:, bones] - key_translations[:, parent, None])
            posed = np.einsum('knij,nj->kni', rotations[:, local], self._rest[points]) + translations[:, local]
            keep = farthest_poses(posed.reshape(len(posed), -1), MAX_POSES)
            self._bones[limb], self._points[limb], self._local[limb] = bones, points, local
            # by a neighbour query's index: the model subset's points on the limb (the index
            # "none within the cap", the subset's length, is on no bone)
            self._in_limb[limb] = np.append(np.isin(self._labels, bones), False)
            self._relative[limb] = (rotations[keep], translations[keep])

    def repose(self, rotations: np.ndarray, translations: np.ndarray, observed: np.ndarray) -> tuple:
        """The start (rotations (B, 3, 3), translations (B, 3)) with each limb whose best key
        pose explains observed (N, 3) m (non-finite rows ignored) clearly better put in that
        pose: (rotations, translations), copies, and the limbs re-posed (list of bones).
        Raises ValueError on observed points that are not (N, 3)."""
        rotations = np.array(rotations, dtype=np.float64)
        translations = np.array(translations, dtype=np.float64)
        observed = np.asarray(observed, dtype=np.float64)
        if observed.ndim != 2 or observed.shape[1] != 3:
            raise ValueError(f'observed points must be (N, 3), got shape {observed.shape}')
        observed = observed[finite_rows(observed)]
        observed = strided_subset(observed, SCORED_OBSERVED)
        moved = []
        if len(observed) < MIN_SAMPLES or not self._relative:
            return rotations, translations, moved
        cap = self._cap
        distance, nearest = self._nearest(rotations, translations, observed)
        if np.count_nonzero(distance[:, 0] >= cap) < MIN_SAMPLES:
            return rotations, translations, moved       # the start explains the frame: nothing to re-pose
        for limb, (relative_rotations, relative_translations) in self._relative.items():
            bones, points, local = self._bones[limb], self._points[limb], self._local[limb]
            # each observation's distance to the start without this limb (cap: none within it)
            outside = np.isfinite(distance) & ~self._in_limb[limb][nearest]
            rest_distance = np.where(outside.any(axis=1),
                                     distance[np.arange(len(observed)), np.argmax(outside, axis=1)], cap)
            # the observations nothing else explains, within the limb's reach of its joint
            parent = self._parents[limb]
            joint = rotations[parent] @ self._rest_joints[limb] + translations[parent]
            reachable = np.linalg.norm(observed - joint, axis=1) <= self._reach[limb] + cap
            unexplained = observed[(rest_distance >= cap) & reachable]
            if len(unexplained) < MIN_SAMPLES:
                continue
            unexplained = strided_subset(unexplained, UNEXPLAINED_POINTS)
            hypotheses_r = np.einsum('ij,kbjl->kbil', rotations[parent], relative_rotations)
            hypotheses_t = np.einsum('ij,kbj->kbi', rotations[parent], relative_translations) + translations[parent]
            start = np.einsum('nij,nj->ni', rotations[bones[local]], self._rest[points]) + translations[bones[local]]
            candidates = np.concatenate([start[None], np.einsum('knij,nj->kni', hypotheses_r[:, local],
                                                                self._rest[points]) + hypotheses_t[:, local]])
            count, n = candidates.shape[:2]                                    # (1 + K, n, 3)
            to_data = np.minimum(nearest_within(candidates.reshape(-1, 3), observed, 1, cap)[0][:, 0], cap)
            # (1 + K, U): each unexplained observation's squared distance to each candidate's
            # nearest point, dense (both sets are small strided subsets) and expanded as
            # |c|^2 + |u|^2 - 2 c.u, a matrix product instead of (1 + K, n, U, 3) differences
            squared = (np.einsum('knd,knd->kn', candidates, candidates)[:, :, None]
                       + np.einsum('ud,ud->u', unexplained, unexplained) - 2.0 * candidates @ unexplained.T)
            to_model = np.minimum(np.maximum(np.min(squared, axis=1), 0.0), cap ** 2)
            scores = np.mean(to_data.reshape(count, n) ** 2, axis=1) + np.mean(to_model, axis=1)
            best = int(np.argmin(scores))
            if best == 0 or scores[best] >= MARGIN * scores[0]:
                continue
            rotations[bones], translations[bones] = hypotheses_r[best - 1], hypotheses_t[best - 1]
            moved.append(limb)
            # the limbs below and beside it are scored against the start as it is now
            distance, nearest = self._nearest(rotations, translations, observed)
        self.reposed += len(moved)
        return rotations, translations, moved

    def _nearest(self, rotations, translations, observed) -> tuple:
        """(N, k) distances (inf past the cap) and indices (len(model subset) where none) of
        each observation's nearest posed model points."""
        posed = np.einsum('nij,nj->ni', rotations[self._labels], self._rest) + translations[self._labels]
        return nearest_within(observed, posed, NEIGHBOURS, self._cap)


def _breadth_first(parents: np.ndarray, children: list) -> list:
    """The bones in breadth-first order from the root (parents (B,), -1 at the root;
    children: bone_rotations.children_of's): every top-level limb before the limbs below
    them (bone_rotations.depth_first is parents-first too, but scores a limb's sub-limbs
    before its siblings)."""
    order = [int(b) for b in np.flatnonzero(parents < 0)]
    for bone in order:                     # grows while iterated: a loop over bones
        order.extend(children[bone])
    return order


def _subtree(bone: int, children: list) -> np.ndarray:
    """(b,) sorted: the bone and every bone below it."""
    members, stack = [], [bone]
    while stack:
        current = stack.pop()
        members.append(current)
        stack.extend(children[current])
    return np.sort(np.array(members, dtype=np.int64))
