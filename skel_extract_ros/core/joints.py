r"""Skeleton joint estimation (paper Sec. 6, Alg. 2): LBS fitted to raw and registered points.

The LBS-deformed rest points x_m^t = sum_j w_mj (R_j^t q_m + T_j^t) (Eq. 8) are the
centroids of a GMM for the preprocessed points V^t of every frame, with per-frame variance
tau^t and outlier weight omega' (Eq. 11). EM minimises (Eq. 12)
    E_Total = E_GMM + zeta/2 E_Register + alpha/2 E_Joint + gamma/2 sum_t E_small^t
    E_Register = sum_t sum_m |y_m^t - x_m^t|^2
    E_Joint    = eta sum_<j,k> |c_jk - c~_jk|^2 + sum_t sum_<j,k> |(R_j^t c_jk + T_j^t) - (R_k^t c_jk + T_k^t)|^2
subject to w_mj >= 0, sum_j w_mj = 1, at most 4 non-zero weights per point (12b), and
R_j^t in SO(3) (12c). alpha starts at zeta * M and grows by `alpha_growth` per iteration.

M-step blocks, each solved exactly:
- Weights, point by point: with a_m^t = P1_m^t / tau^t, x~ the posterior mean of the
  observations and p_mj^t = R_j^t q_m + T_j^t,
      E(w_m) = sum_t (a + zeta)/2 |z_m^t - sum_j w_mj p_mj^t|^2 + const,
      z_m^t = (a x~_m^t + zeta y_m^t) / (a + zeta).
  The 4 bones with the smallest single-bone objective are kept and the quadratic
  programme over the simplex is solved exactly: for each of the 15 supports the KKT system
  with the sum-to-one constraint is solved (vectorised over points) and the best feasible
  support is taken.
- Bone transforms, bone by bone (Eq. 13-15), all frames at once: every term has the form
  lambda |R a + T - b|^2 (registration: lambda = zeta w^2, b = (y - u)/w; data: lambda =
  P1 w^2 / tau, b = (x~ - u)/w; joints: lambda = alpha, a = c_jk, b = R_k c_jk + T_k;
  E_small: lambda = gamma, a = 0, b = T^pre), u being the other bones' part, so T = mu_b -
  R mu_a (Eq. 14) and R maximises tr(R Z) with Z = sum lambda (a - mu_a)(b - mu_b)^T +
  gamma R^pre^T (Eq. 15, SVD with the det correction).
- Joints c_jk: minimise E_Joint, a 3 x 3 solve each (see structure.solve_joints).
- tau^t as Eq. (7); x^t by Eq. (8).
"""
from __future__ import annotations

import itertools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .gmm import CandidateCache
from .point_sets import median_spacing
from .rigid import rotations_from_h
from .structure import SkeletalStructure, joint_trajectories, solve_joints


@dataclass
class JointParams:
    """Parameters of Alg. 2 (defaults: the paper's Table 1 and Sec. 7).

    omega: outlier weight omega' (Eq. 11); eta: joint data weight; zeta: weight of
    E_Register; gamma: weight of E_small; alpha_growth: alpha = zeta * M * growth^iteration;
    initial_tau: tau^t at the start (m^2); max_iterations, tolerance: EM stopping (10, not
    the 20 of Alg. 1: on the real-motion benchmark the joints after 10 iterations are as
    good as after 20, at half the time, bench/README.md);
    max_influences: bones per point (Eq. 12b); e_step_neighbours, truncation_sigmas: the
    truncated E-step (see core.gmm); min_tau: floor on tau (m^2).
    """

    omega: float = 0.01
    eta: float = 1.0
    zeta: float = 1e4
    gamma: float = 0.1
    alpha_growth: float = 1.45
    initial_tau: float = 6e-4
    max_iterations: int = 10
    tolerance: float = 1e-3
    max_influences: int = 4
    e_step_neighbours: int = 8
    truncation_sigmas: float = 4.0
    min_tau: float = 1e-6


@dataclass
class JointEstimate:
    """Result of Alg. 2.

    influences: (M, 4) bone indices and weights: (M, 4) LBS weights (rows sum to 1);
    rotations (F, B, 3, 3), translations (F, B, 3); joints (B, 3) rest-frame joint of each
    bone with its parent (root: its centre); parents (B,); tau (F,) m^2.
    """

    influences: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    joints: np.ndarray
    parents: np.ndarray
    tau: np.ndarray
    energies: list = field(default_factory=list)

    def joint_trajectories(self) -> np.ndarray:
        """(F, B, 3) joint positions per frame (metres)."""
        return joint_trajectories(self.rotations, self.translations, self.joints, self.parents)

    def dense_weights(self) -> np.ndarray:
        """(M, B) weight matrix W."""
        return dense_weights(self.influences, self.weights, len(self.parents))


def dense_weights(influences: np.ndarray, weights: np.ndarray, n_bones: int) -> np.ndarray:
    """(M, B) LBS weight matrix W from each point's k bones (M, k) and their weights (M, k)
    (a bone listed twice in a row gets both weights)."""
    dense = np.zeros((len(weights), n_bones))
    np.add.at(dense, (np.arange(len(weights))[:, None], influences), weights)
    return dense


_SUPPORTS = {k: [s for r in range(1, k + 1) for s in itertools.combinations(range(k), r)] for k in range(1, 5)}


def simplex_least_squares(G: np.ndarray, h: np.ndarray) -> np.ndarray:
    """argmin_w 1/2 w^T G w - h^T w s.t. w >= 0, sum w = 1, for a batch (P, k, k), (P, k).

    Exact: enumerates every support, solves its KKT system with the equality constraint
    and keeps the feasible one with the lowest objective (k <= 4: at most 15 supports).
    """
    P, k = h.shape
    ridge = 1e-12 * np.maximum(np.trace(G, axis1=1, axis2=2), 1e-30)[:, None, None] * np.eye(k)
    G = G + ridge
    best = np.full(P, np.inf)
    result = np.zeros((P, k))
    for support in _SUPPORTS[k]:
        s = len(support)
        idx = np.array(support)
        kkt = np.zeros((P, s + 1, s + 1))
        kkt[:, :s, :s] = G[:, idx[:, None], idx[None, :]]
        kkt[:, :s, s] = 1.0
        kkt[:, s, :s] = 1.0
        rhs = np.concatenate([h[:, idx], np.ones((P, 1))], axis=1)
        try:
            solution = np.linalg.solve(kkt, rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            solution = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in zip(kkt, rhs)])
        w = np.zeros((P, k))
        w[:, idx] = solution[:, :s]
        feasible = (w >= -1e-10).all(axis=1) & np.isfinite(w).all(axis=1)
        w = np.clip(w, 0.0, None)
        w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
        value = 0.5 * np.einsum('pi,pij,pj->p', w, G, w) - np.einsum('pi,pi->p', h, w)
        better = feasible & (value < best)
        best[better] = value[better]
        result[better] = w[better]
    return result


class JointEstimation:
    """Alg. 2 on a window: `fit(rest, registered, observed, structure) -> JointEstimate`."""

    def __init__(self, params: JointParams | None = None):
        self.params = params or JointParams()

    def fit(self, rest: np.ndarray, registered: np.ndarray, observed: list,
            structure: SkeletalStructure) -> JointEstimate:
        """rest (M, 3); registered (F, M, 3); observed: F arrays (N_t, 3) of preprocessed
        points (metres); structure from Step 2 (labels, tree, transforms, joints)."""
        p = self.params
        rest = np.asarray(rest, dtype=np.float64)
        registered = np.asarray(registered, dtype=np.float64)
        F, M, _ = registered.shape
        if len(observed) != F:
            raise ValueError(f'{len(observed)} observed frames for {F} registered frames')
        parents = structure.parents
        B = len(parents)
        k = min(p.max_influences, B)
        rotations = structure.rotations.astype(np.float64).copy()
        translations = structure.translations.astype(np.float64).copy()
        joints = structure.joints.copy()
        anchors = structure.boundary_centroids
        # initial weights: the hard labels of Step 2
        influences = np.repeat(structure.labels[:, None], k, axis=1)
        weights = np.zeros((M, k))
        weights[:, 0] = 1.0
        if k > 1:  # fill the other slots with distinct bones at weight 0
            others = np.argsort(np.abs(np.arange(B)[None, :] - structure.labels[:, None]), axis=1)[:, 1:k]
            influences[:, 1:] = others
        tau = np.full(F, p.initial_tau)
        observed = [np.asarray(v, dtype=np.float64) for v in observed]
        alpha = p.zeta * M
        edges = [(int(b), int(parents[b])) for b in range(B) if parents[b] >= 0]
        energies = []
        previous = None          # (data terms, E_Joint, alpha) of the previous iterate
        deformed = self._deform(rest, rotations, translations, influences, weights)
        # The E-step was two thirds of the time. Each frame keeps its observations' candidate
        # centroids across iterations (core.gmm.CandidateCache: measured here, a fifth of the
        # queries, joints within 0.1 mm of querying every time). Frames are independent, and
        # the queries and numpy reductions release the GIL, so threads use every core.
        spacing = median_spacing(rest)
        caches = [CandidateCache(v, spacing, p.e_step_neighbours) if len(v) else None for v in observed]
        pool = ThreadPoolExecutor(max_workers=min(os.cpu_count() or 1, 8))

        def e_step(frame):
            if caches[frame] is None:
                return None
            return caches[frame].posteriors(deformed[frame], tau[frame], p.omega, p.truncation_sigmas)
        try:
            for _ in range(p.max_iterations):
                stats = list(pool.map(e_step, range(F)))
                P1 = np.stack([s.P1 if s else np.zeros(M) for s in stats])              # (F, M)
                targets = np.stack([s.targets() if s else np.zeros((M, 3)) for s in stats])
                data = sum(s.nll for s in stats if s) + 0.5 * p.zeta * np.sum((registered - deformed) ** 2)
                joint_term = self._joint_energy(rotations, translations, joints, anchors, edges, p.eta)
                energies.append(float(data + 0.5 * alpha * joint_term))
                # alpha grows every iteration, so consecutive totals differ even at a fixed point:
                # the convergence test compares the two iterates under the same (previous) alpha.
                if previous is not None:
                    before = previous[0] + 0.5 * previous[2] * previous[1]
                    after = data + 0.5 * previous[2] * joint_term
                    if abs(before - after) <= p.tolerance * abs(after):
                        break
                previous = (data, joint_term, alpha)
                a = P1 / tau[:, None]                                                    # (F, M)
                influences, weights = self._update_weights(rest, rotations, translations, registered, targets,
                                                              a, k)
                self.update_bones(rest, registered, targets, a, rotations, translations, influences, weights,
                                   joints, edges, alpha)
                joints = solve_joints(rotations, translations, parents, anchors, p.eta)
                deformed = self._deform(rest, rotations, translations, influences, weights)
                tau = np.array([max(s.squared_residual(x) / (3.0 * max(s.Np, 1e-12)), p.min_tau) if s else t
                                for s, x, t in zip(stats, deformed, tau)])
                alpha *= p.alpha_growth
        finally:
            pool.shutdown()
        return JointEstimate(influences, weights, rotations, translations, joints, parents, tau, energies)

    # ------------------------------------------------------------------------------------
    @staticmethod
    def influenced_positions(rest, rotations, translations, influences) -> np.ndarray:
        """(F, M, k, 3) each rest point moved by each of its k influencing bones: R_j^t q_m +
        T_j^t. Only those k: every point under every bone is (F, B, M, 3), 55 MB for a
        60-frame window of a 19-bone body, and was the joint node's peak memory."""
        F, M, k = len(rotations), len(rest), influences.shape[1]
        positions = np.empty((F, M, k, 3))
        for slot in range(k):   # k <= max_influences (4): a few (F, M, 3, 3) products
            bones = influences[:, slot]
            positions[:, :, slot] = (np.einsum('fmij,mj->fmi', rotations[:, bones], rest)
                                     + translations[:, bones])
        return positions

    @staticmethod
    def _deform(rest, rotations, translations, influences, weights) -> np.ndarray:
        """Eq. (8): (F, M, 3) LBS positions. sum_b W_mb (R_b^t q_m + T_b^t) as one matrix
        product, the (M, 3B) rows W_mb q_m times the (3B, 3F) stacked rotations, plus W T:
        4 against 21 ms for a 60-frame window of 2 000 points (forming each point under each
        of its bones first)."""
        F, B = rotations.shape[:2]
        M = len(rest)
        dense = dense_weights(influences, weights, B)
        weighted_rest = (dense[:, :, None] * rest[:, None, :]).reshape(M, B * 3)        # (M, 3B)
        stacked = np.transpose(rotations, (1, 3, 0, 2)).reshape(B * 3, F * 3)          # (3B, 3F)
        moved = weighted_rest @ stacked + dense @ np.transpose(translations, (1, 0, 2)).reshape(B, F * 3)
        return np.ascontiguousarray(np.transpose(moved.reshape(M, F, 3), (1, 0, 2)))

    @staticmethod
    def _joint_energy(rotations, translations, joints, anchors, edges, eta: float) -> float:
        """E_Joint (m^2): eta sum |c_jk - c~_jk|^2 + sum_t sum |(R_j c + T_j) - (R_k c + T_k)|^2."""
        if not edges:
            return 0.0
        child = np.array([e[0] for e in edges])
        parent = np.array([e[1] for e in edges])
        c = joints[child]
        gap = (np.einsum('feij,ej->fei', rotations[:, child], c) + translations[:, child]
               - np.einsum('feij,ej->fei', rotations[:, parent], c) - translations[:, parent])
        return float(np.sum(gap ** 2) + eta * np.sum((c - anchors[child]) ** 2))

    @staticmethod
    def single_bone_costs(rest, rotations, translations, c, z) -> np.ndarray:
        """(M, B) sum_t c_tm |z_tm - (R_b^t q_m + T_b^t)|^2 for rest (M, 3), rotations
        (F, B, 3, 3), translations (F, B, 3), c (F, M), z (F, M, 3): expanded into matrix
        products rather than forming every point under every bone (half the weight step)."""
        F, M = c.shape
        B = rotations.shape[1]
        weighted = (c[..., None] * z).transpose(1, 0, 2).reshape(M, F * 3)          # c z, (M, 3F)
        rotated = (weighted @ rotations.transpose(0, 2, 1, 3).reshape(F * 3, B * 3)).reshape(M, B, 3)
        carried = np.einsum('tbij,tbi->tbj', rotations, translations).reshape(F, B * 3)   # R^T T
        return (np.sum(c * np.sum(z ** 2, axis=2), axis=0)[:, None]
                - 2.0 * np.einsum('mbj,mj->mb', rotated, rest)
                - 2.0 * weighted @ translations.transpose(0, 2, 1).reshape(F * 3, B)
                + (np.sum(rest ** 2, axis=1) * c.sum(axis=0))[:, None]
                + c.T @ np.sum(translations ** 2, axis=2)
                + 2.0 * np.einsum('mbj,mj->mb', (c.T @ carried).reshape(M, B, 3), rest))

    def _update_weights(self, rest, rotations, translations, registered, targets, a, k):
        """Per point: the k bones with the smallest single-bone objective, then the exact
        simplex-constrained least squares on them."""
        zeta = self.params.zeta
        F, M, _ = registered.shape
        c = a + zeta                                                                  # (F, M)
        z = (a[..., None] * targets + zeta * registered) / c[..., None]               # (F, M, 3)
        single = self.single_bone_costs(rest, rotations, translations, c, z)
        influences = np.argsort(single, axis=1)[:, :k]
        chosen = self.influenced_positions(rest, rotations, translations, influences)  # (F, M, k, 3)
        per_point = chosen.transpose(1, 2, 0, 3).reshape(M, k, F * 3)                 # (M, k, 3F)
        weighted = (chosen * c[:, :, None, None]).transpose(1, 2, 0, 3).reshape(M, k, F * 3)
        G = weighted @ per_point.transpose(0, 2, 1)
        h = (weighted @ z.transpose(1, 0, 2).reshape(M, F * 3, 1))[..., 0]
        return influences, simplex_least_squares(G, h)

    def update_bones(self, rest, registered, targets, a, rotations, translations, influences, weights,
                      joints, edges, alpha) -> None:
        """Eq. (13)-(15), bone after bone, every frame at once (in place)."""
        p = self.params
        F, M, _ = registered.shape
        B = rotations.shape[1]
        neighbours = {b: [] for b in range(B)}
        for child, parent in edges:
            neighbours[child].append((parent, child))   # joint stored on the child bone
            neighbours[parent].append((child, child))
        contributions = weights[None, :, :, None] * self.influenced_positions(rest, rotations, translations,
                                                                              influences)
        deformed = contributions.sum(axis=2)                                          # (F, M, 3)
        for bone in range(B):  # loop over bones (a few dozen), vectorised over frames and points
            # each point lists a bone at most once, so m has no repeats
            m, slot = np.nonzero((influences == bone) & (weights > 1e-8))
            w = weights[m, slot]
            points = rest[m]                                                          # (P, 3)
            others = deformed[:, m] - contributions[:, m, slot]                       # (F, P, 3)
            # The registration and data terms share a = q_m, so they add up to one term with
            # lambda = zeta w^2 + a w^2 and lambda b = w (zeta (y - u) + a (x~ - u)).
            lam_points = (p.zeta + a[:, m]) * w[None, :] ** 2                          # (F, P)
            lam_b = w[None, :, None] * (p.zeta * (registered[:, m] - others)
                                        + a[:, m, None] * (targets[:, m] - others))   # (F, P, 3)
            total = lam_points.sum(axis=1) + p.gamma                                   # E_small: a = 0
            sum_a = lam_points @ points                                               # (F, 3)
            sum_b = lam_b.sum(axis=1) + p.gamma * translations[:, bone]
            sum_ab = np.transpose(lam_b, (0, 2, 1)) @ points                          # (F, 3, 3), transposed
            for other, joint_bone in neighbours[bone]:
                c = joints[joint_bone]
                target = np.einsum('fij,j->fi', rotations[:, other], c) + translations[:, other]   # (F, 3)
                total = total + alpha
                sum_a = sum_a + alpha * c
                sum_b = sum_b + alpha * target
                sum_ab = sum_ab + alpha * target[:, :, None] * c[None, None, :]
            mu_a = sum_a / total[:, None]
            mu_b = sum_b / total[:, None]
            # sum lambda (a - mu_a)(b - mu_b)^T = sum lambda a b^T - total mu_a mu_b^T
            Z = np.transpose(sum_ab, (0, 2, 1)) - total[:, None, None] * mu_a[:, :, None] * mu_b[:, None, :]
            Z += p.gamma * np.transpose(rotations[:, bone], (0, 2, 1))
            R = rotations_from_h(Z)
            rotations[:, bone] = R
            translations[:, bone] = mu_b - np.einsum('fij,fj->fi', R, mu_a)
            new = w[None, :, None] * (points @ np.transpose(R, (0, 2, 1)) + translations[:, bone][:, None, :])
            contributions[:, m, slot] = new
            deformed[:, m] = others + new
