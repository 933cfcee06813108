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
- Bone transforms, bone by bone (Eq. 13-15), all frames at once (core.articulated): the
  registration and data terms share a = q_m and add up to one data term per point and
  frame with weight c = zeta + a and target z (above); joints: lambda = alpha, a = c_jk,
  b = R_k c_jk + T_k; E_small towards the previous transforms.
- Joints c_jk: minimise E_Joint, a 3 x 3 solve each (see structure.solve_joints).
- tau^t as Eq. (7); x^t by Eq. (8).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from .articulated import BoneBlocks, blend, dense_weights, influenced_positions
from .gmm import CandidateCache
from .parallel import parallel_map
from .parameters import INF, parameter, validate
from .point_sets import median_spacing
from .joint_centres import PivotEvidence, joint_trajectories, solve_joints
from .skeleton_model import SkeletonModel
from .structure import SkeletalStructure


@dataclass
class JointParams:
    """Parameters of Alg. 2 (defaults: the paper's Table 1 and Sec. 7). A running joint node
    applies new values from the next structure (they are all live)."""

    omega: float = parameter(0.01, "outlier weight omega' of the GMM (Eq. 11), a probability", 0.0, 0.999,
                             live=True)
    eta: float = parameter(1.0, 'weight of the joint data term in E_Joint (Table 1), dimensionless', 0.0, INF,
                           live=True)
    zeta: float = parameter(1e4, 'weight of E_Register, the pull to the registered points (Table 1), 1/m^2',
                            0.0, INF, live=True)
    gamma: float = parameter(0.1, 'weight of E_small (Table 1), dimensionless', 0.0, INF, live=True)
    alpha_growth: float = parameter(1.45, 'the E_Joint weight alpha = zeta * M * alpha_growth^iteration, '
                                    'dimensionless', 1.0, 100.0, live=True)
    initial_tau: float = parameter(6e-4, 'initial per-frame GMM variance tau, m^2', 1e-12, INF, live=True)
    max_iterations: int = parameter(10, "Alg. 2 EM iterations at most; 0 = Step 2's joints unchanged", 0, 1000,
                                    live=True)
    tolerance: float = parameter(1e-3, 'stop Alg. 2 when the relative energy change is below this, '
                                 'dimensionless', 0.0, 1.0, live=True)
    max_influences: int = parameter(4, 'bones per point in the LBS weights (Eq. 12b)', 1, 4, live=True)
    e_step_neighbours: int = parameter(8, 'truncated E-step: nearest centroids per observed point', 1, 64,
                                       live=True)
    truncation_sigmas: float = parameter(4.0, 'truncated E-step: neighbour radius in standard deviations',
                                         1.0, 100.0, live=True)
    min_tau: float = parameter(1e-6, 'lower bound of tau, m^2', 0.0, INF, live=True)
    joint_depth: str = parameter('anchor', "where a joint's depth along the camera ray comes from: anchor (the "
                                 "medial anchor's, where its bone's cross-section gave one; E_Joint places "
                                 'the joint across the ray) or motion (E_Joint in all three directions, the '
                                 'paper)', choices=('anchor', 'motion'), live=True)

    def __post_init__(self):
        validate(self)


@dataclass
class JointEstimate:
    """Result of Alg. 2.

    influences: (M, 4) bone indices and weights: (M, 4) LBS weights (rows sum to 1);
    rotations (F, B, 3, 3), translations (F, B, 3); joints (B, 3) rest-frame joint of each
    bone with its parent (root: its centre); parents (B,); tau (F,) m^2; pivot: how far the
    bones' own motion (Step 2's unconstrained rigid fits) fixed these joints (None when the
    structure does not say, see SkeletalStructure.pivot_evidence).
    """

    influences: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    joints: np.ndarray
    parents: np.ndarray
    tau: np.ndarray
    energies: list = field(default_factory=list)
    pivot: PivotEvidence | None = None

    def joint_trajectories(self) -> np.ndarray:
        """(F, B, 3) joint positions per frame (metres)."""
        return joint_trajectories(self.rotations, self.translations, self.joints, self.parents)

    def dense_weights(self) -> np.ndarray:
        """(M, B) weight matrix W."""
        return dense_weights(self.influences, self.weights, len(self.parents))

    def model(self, rest: np.ndarray, labels: np.ndarray, joint_ids: np.ndarray | None = None) -> SkeletonModel:
        """The learned skeleton: these joints and LBS weights on rest (M, 3) with Step 2's
        labels (M,), the joints named by joint_ids (B,) (None: 0..B-1)."""
        # Eq. 7's tau is a variance per coordinate: the RMS distance is sqrt(3 tau)
        noise = float(np.sqrt(3.0 * np.median(self.tau))) if len(self.tau) else None
        return SkeletonModel(rest, labels, self.parents, self.joints, self.influences, self.weights, joint_ids,
                             self.pivot, noise)


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
        # the registration keeps a turning limb's points on its visible side, so the depth the
        # bones' motion gives a joint lies in front of it; the section's depth does not
        depth_rays = structure.depth_rays if p.joint_depth == 'anchor' else None
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
        deformed = blend(rest, dense_weights(influences, weights, B), rotations, translations)
        # The E-step dominates: each frame keeps its observations' candidate centroids across
        # iterations (core.gmm.CandidateCache). Frames are independent, and the queries and
        # numpy reductions release the GIL, so threads use every core.
        spacing = median_spacing(rest)
        caches = [CandidateCache(v, spacing, p.e_step_neighbours) if len(v) else None for v in observed]

        def e_step(frame):
            if caches[frame] is None:
                return None
            return caches[frame].posteriors(deformed[frame], tau[frame], p.omega, p.truncation_sigmas)
        for _ in range(p.max_iterations):
            stats = parallel_map(e_step, range(F))
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
            # the registration and data terms as one: weight c and target z per point and frame
            a = P1 / tau[:, None]                                                    # (F, M)
            c = a + p.zeta
            z = (a[..., None] * targets + p.zeta * registered) / c[..., None]        # (F, M, 3)
            influences, weights = self._update_weights(rest, rotations, translations, c, z, k)
            deformed = BoneBlocks(rest, influences, weights, parents).update(
                z, c, rotations, translations, joints, alpha, p.gamma)
            joints = solve_joints(rotations, translations, parents, anchors, p.eta, depth_rays)
            tau = np.array([max(s.squared_residual(x) / (3.0 * max(s.Np, 1e-12)), p.min_tau) if s else t
                            for s, x, t in zip(stats, deformed, tau)])
            alpha *= p.alpha_growth
        # the evidence is read from the unconstrained fits: Alg. 2's transforms meet at the
        # joints by construction (alpha grows without bound), so their gap says nothing
        return JointEstimate(influences, weights, rotations, translations, joints, parents, tau, energies,
                             structure.pivot_evidence(joints))

    # ------------------------------------------------------------------------------------
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

    def _update_weights(self, rest, rotations, translations, c, z, k):
        """Per point: the k bones with the smallest single-bone objective, then the exact
        simplex-constrained least squares on them (c (F, M) and z (F, M, 3): the data
        term's weight and target)."""
        F, M = c.shape
        single = self.single_bone_costs(rest, rotations, translations, c, z)
        influences = np.argsort(single, axis=1)[:, :k]
        chosen = influenced_positions(rest, rotations, translations, influences)      # (M, k, F, 3)
        per_point = chosen.reshape(M, k, F * 3)                                       # (M, k, 3F)
        weighted = (chosen * c.T[:, None, :, None]).reshape(M, k, F * 3)
        G = weighted @ per_point.transpose(0, 2, 1)
        h = (weighted @ z.transpose(1, 0, 2).reshape(M, F * 3, 1))[..., 0]
        return influences, simplex_least_squares(G, h)
