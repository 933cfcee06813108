"""Live joints: the learned LBS model fitted to one new registered frame at a time.

After Alg. 2 has run on a window, the skeleton (rest points Q, weights W, joints c_jk,
bone tree) is fixed; for every later frame only the bone transforms change. For a
registered frame Y (M, 3) this minimises the single-frame part of Eq. (12) without the
GMM term:

    zeta/2 sum_m |y_m - sum_j w_mj (R_j q_m + T_j)|^2 + alpha/2 sum_<j,k> |(R_j - R_k) c_jk + T_j - T_k|^2
    + gamma/2 sum_j |T_j - T_j^init|^2

starting from a per-bone rigid fit (Eq. 9, Kabsch on the points each bone dominates),
with `sweeps` bone-by-bone exact updates (Eq. 13-15, the same block solve as Alg. 2).
The GMM data term of Alg. 2 is left out on purpose: the registration's Y^t already
follows the observed points, and one truncated E-step would cost more than the whole
live budget (about 5 ms for 5,000 points).

    >>> tracker = LiveJointTracker(model, JointParams())
    >>> positions = tracker.track(registered_frame)     # (J, 3) metres, input frame
"""
from __future__ import annotations

import numpy as np

from .joints import JointParams
from .rigid import fit_rigid_segments, rotations_from_h
from .skeleton_model import SkeletonModel
from .structure import joint_trajectories


class LiveJointTracker:
    """Per-frame bone transforms and joints of a fixed SkeletonModel.

    sweeps: bone-by-bone passes of the exact block update after the rigid initialisation
    (0 = rigid fits only). The joint weight alpha is Alg. 2's starting value zeta * M.
    The block update is Alg. 2's (JointEstimation.update_bones) specialised to one frame
    with the per-bone point sets precomputed, since the weights no longer change: the
    general one spends ~1 ms per bone re-deriving them, which would blow the live budget.
    """

    def __init__(self, model: SkeletonModel, params: JointParams | None = None, sweeps: int = 2):
        if sweeps < 0:
            raise ValueError(f'sweeps must be >= 0, got {sweeps}')
        self.model = model
        self.params = params or JointParams()
        self.sweeps = int(sweeps)
        rest = np.asarray(model.rest_points, dtype=np.float64)
        self._rest = rest
        influences, weights = np.asarray(model.influences), np.asarray(model.weights, dtype=np.float64)
        self._influences, self._weights = influences, weights
        # the bone each point follows most: the rigid initialisation fits those points
        self._dominant = influences[np.arange(len(rest)), np.argmax(weights, axis=1)]
        parents = np.asarray(model.parents)
        self._parents = parents
        joints = np.asarray(model.rest_joints, dtype=np.float64)
        self._joints = joints
        self._alpha = self.params.zeta * len(rest)
        # per bone: its weighted points (index, slot, weight, rest position), its joints
        # (other bone, c_jk), and the constant parts of the block update's weighted sums
        zeta, gamma = self.params.zeta, self.params.gamma
        self._bones = []
        for bone in range(len(parents)):
            m, slot = np.nonzero((influences == bone) & (weights > 1e-8))
            w = weights[m, slot]
            links = [(int(parents[bone]), joints[bone])] if parents[bone] >= 0 else []
            links += [(int(child), joints[child]) for child in np.flatnonzero(parents == bone)]
            others = np.array([k for k, _ in links], dtype=int)
            centres = np.array([c for _, c in links]).reshape(-1, 3)
            lam_total = zeta * np.sum(w ** 2) + self._alpha * len(links) + gamma
            sum_a = zeta * (w ** 2) @ rest[m] + self._alpha * centres.sum(axis=0)
            self._bones.append((m, slot, w, rest[m], zeta * w[:, None] * rest[m], others, centres,
                                lam_total, sum_a / lam_total))

    def fit(self, registered: np.ndarray) -> tuple:
        """Bone transforms for one frame: registered (M, 3) -> rotations (B, 3, 3),
        translations (B, 3), rest -> frame. Raises ValueError on a wrong shape."""
        registered = np.asarray(registered, dtype=np.float64)
        if registered.shape != self._rest.shape:
            raise ValueError(f'registered frame has shape {registered.shape}, the model has '
                             f'{self._rest.shape[0]} points')
        B = len(self._parents)
        rotations, translations = fit_rigid_segments(self._rest, registered[None], self._dominant, B)
        rotations, translations = rotations[0], translations[0]
        if self.sweeps == 0:
            return rotations, translations
        zeta, gamma = self.params.zeta, self.params.gamma
        moved = np.einsum('bij,mj->mbi', rotations, self._rest) + translations          # (M, B, 3)
        contributions = self._weights[..., None] * moved[np.arange(len(self._rest))[:, None], self._influences]
        deformed = contributions.sum(axis=1)                                            # (M, 3)
        for _ in range(self.sweeps):
            for bone, (m, slot, w, q, zeta_w_q, others, centres, lam_total, mu_a) in enumerate(self._bones):
                # terms lam |R a + T - b|^2: registration (lam = zeta w^2, a = q,
                # b = (y - rest of the blend) / w), joints (alpha, a = c, b = R_k c + T_k),
                # E_small (gamma, a = 0, b = T_init); Z = sum lam a b^T - Lam mu_a mu_b^T
                residual = registered[m] - (deformed[m] - contributions[m, slot])       # = w b
                carried = np.einsum('lij,lj->li', rotations[others], centres) + translations[others]
                sum_b = zeta * w @ residual + self._alpha * carried.sum(axis=0) + gamma * translations[bone]
                mu_b = sum_b / lam_total
                Z = (zeta_w_q.T @ residual + self._alpha * centres.T @ carried
                     - lam_total * np.outer(mu_a, mu_b) + gamma * rotations[bone].T)
                R = rotations_from_h(Z)
                rotations[bone], translations[bone] = R, mu_b - R @ mu_a
                new = w[:, None] * (q @ R.T + translations[bone])
                deformed[m] += new - contributions[m, slot]
                contributions[m, slot] = new
        return rotations, translations

    def track(self, registered: np.ndarray) -> np.ndarray:
        """(J, 3) joint positions (metres, the registered frame's coordinates)."""
        rotations, translations = self.fit(registered)
        return joint_trajectories(rotations[None], translations[None], self._joints, self._parents)[0]
