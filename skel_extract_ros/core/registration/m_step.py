r"""The M-step of Alg. 1 (Eq. 4-6), in exact blocks.

M-step (Eq. 4): minimise
    E = E_GMM + beta_smooth / 2 E_smooth + beta_small / 2 E_small,   R_j in SO(3),
    E_GMM    = 1 / (2 sigma2) sum_mi p_mi |v_i - y'_m|^2 + 3 N_p / 2 log sigma2
    E_smooth = sum_j sum_{k in N(j)} |R_j (g_k - g_j) + g_j + T_j - (g_k + T_k)|^2
    E_small  = sum_j |R_j - R_j^pre|_F^2 + |T_j - T_j^pre|^2
one node at a time with all others fixed (the paper's scheme), which can only lower E.

Derivation of the per-node closed form (Eq. 5, 6). With P1_m = sum_i p_mi and
x~_m = sum_i p_mi v_i / P1_m, E_GMM = 1 / (2 sigma2) sum_m P1_m |x~_m - y'_m|^2 + const.
For node j (position g, unknowns R, T; write t = g + T) and a point m it carries with
weight w_m, y'_m = u_m + w_m (R a_m + t) with a_m = q_m - g and u_m the other nodes'
part, so
    P1_m / sigma2 |x~_m - y'_m|^2 = lambda_m |R a_m + t - b_m|^2,
    lambda_m = P1_m w_m^2 / sigma2,   b_m = (x~_m - u_m) / w_m.
Every other term involving node j has the same form |R a + t - b|^2:
    E_smooth, j predicting neighbour k:  a = g_k - g, b = g_k + T_k,        lambda = beta_smooth
    E_smooth, neighbour k predicting j:  a = 0,       b = R_k (g - g_k) + g_k + T_k, lambda = beta_smooth
    E_small, translation:                a = 0,       b = g + T^pre,        lambda = beta_small
and |R - R^pre|_F^2 = 6 - 2 tr(R^pre^T R). Hence, up to a constant,
    E(R, t) = 1/2 sum_i lambda_i |R a_i + t - b_i|^2 - beta_small tr(R^pre^T R).
dE/dt = 0 gives t = mu_b - R mu_a (Eq. 5; mu = lambda-weighted means). Substituting,
    E(R) = -tr(R H) + z,   H = sum_i lambda_i (a_i - mu_a)(b_i - mu_b)^T + beta_small R^pre^T.
tr(R H) is maximised over SO(3) (Myronenko and Song 2009, Lemma 1) by
    U S V^T = svd(H^T),   R = U diag(1, 1, det(U V^T)) V^T               (Eq. 6)
and T = t - g. Nodes that share no point and no edge do not appear in each other's terms,
so each colour class of the graph is updated in one vectorised batch with exactly the
result of updating its nodes one after another.

Choice of blocks (deviation from the paper's scheme). One node at a time with
beta_smooth = 1e5 is Gauss-Seidel on a very stiff spring system: a translation shared by
many nodes (the whole forearm moving) travels through the graph by about 1 % per sweep, so
20 iterations do not converge. The default `m_step='translations_rotations'` therefore
uses two other exact blocks of the same energy, in turn:
  1. all translations together: for fixed rotations E is quadratic in T, and
         (A^T L A + beta_smooth B^T B + beta_small I) T = A^T L r - beta_smooth B^T c + beta_small T^pre
     with A (M x J) the blend weights, L = diag(P1 / sigma2), r_m = x~_m - sum_j w_mj
     (R_j a_mj + g_j), B the edge incidence matrix and c_jk = R_j (g_k - g_j) + g_j - g_k,
     is one sparse J x J solve;
  2. all rotations with translations fixed, through a majoriser: because sum_j w_mj = 1,
     Jensen's inequality gives
         |x~_m - sum_j w_mj z_mj|^2 <= sum_j w_mj |z_mj - (z_mj^old + x~_m - y'_m^old)|^2,
         z_mj = R_j a_mj + t_j,
     tight at the current iterate. The bound separates over nodes, so every node's
     rotation is the closed form of Eq. (6) with lambda_m = P1_m w_mj / sigma2 and
     b_m = z_mj^old + x~_m - y'_m^old, H = sum_i lambda_i a_i (b_i - t)^T (+ the E_smooth
     terms of the node with a = g_k - g, b = g_k + T_k) + beta_small R^pre^T, all nodes in
     one batched SVD. Minimising a tight upper bound (MM) cannot raise the energy either.
Both blocks keep R in SO(3) exactly and never increase the energy. `m_step='per_node'` is
the paper's scheme (Eq. 5 and 6, node after node, by colour classes).
"""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

from ..gmm import GMMStatistics
from ..rigid import rotations_from_h


class GraphMStep:
    """Mixin of NonRigidRegistration: the M-step blocks over the structures of GraphTerms."""

    def _solve_translations(self, estep: GMMStatistics, sigma2: float, rotations: np.ndarray,
                            translations: np.ndarray, rotated: np.ndarray,
                            stiffness: np.ndarray | None = None) -> None:
        """Exact minimisation of E over all node translations at once (in place);
        rotated: _rotated_offsets(rotations); stiffness: (E,) edge weights (default
        edge_stiffness at the current transforms)."""
        p = self.params
        if stiffness is None:
            stiffness = self.edge_stiffness(rotations, translations, sigma2)
        graph = self.graph
        g = graph.node_positions
        n_nodes = graph.n_nodes
        weights = estep.P1 / sigma2
        residual_targets = estep.targets() - np.einsum('mk,mki->mi', graph.point_weights, rotated)
        j, k = graph.edges[:, 0], graph.edges[:, 1]
        c = np.einsum('eij,ej->ei', rotations[j], g[k] - g[j]) + g[j] - g[k]
        entries = np.concatenate([(weights[:, None] * self._pair_outer).ravel(),
                                  stiffness, stiffness, -stiffness, -stiffness,
                                  np.full(n_nodes, p.beta_small)])
        values = np.bincount(self._system_slots, weights=entries, minlength=len(self._system_pattern[0]))
        system = sparse.csc_matrix((values, *self._system_pattern), shape=(n_nodes, n_nodes))
        rhs = self._blend.T @ (weights[:, None] * residual_targets) \
            - self._incidence.T @ (stiffness[:, None] * c) + p.beta_small * translations
        # the system is symmetric positive definite: a symmetric fill-reducing ordering
        # factors it faster than COLAMD, spsolve's default
        translations[:] = spsolve(system, rhs, permc_spec='MMD_AT_PLUS_A').reshape(-1, 3)

    def _update_rotations(self, estep: GMMStatistics, sigma2: float, contributions: np.ndarray,
                          rotations: np.ndarray, translations: np.ndarray, rotated: np.ndarray,
                          stiffness: np.ndarray | None = None) -> None:
        """All rotations at once from the separable majoriser (module docstring), in place;
        rotated: _rotated_offsets(rotations); stiffness: (E,) edge weights."""
        p = self.params
        if stiffness is None:
            stiffness = self.edge_stiffness(rotations, translations, sigma2)
        graph = self.graph
        g = graph.node_positions
        w = graph.point_weights                                              # (M, k)
        node_centres = g + translations                                      # t_j
        deformed = contributions.sum(axis=1)
        # b - t_j with b = z_mj^old + x~ - y'_old: z_mj^old - t_j = R_j a_mj
        b = rotated - g[graph.point_nodes] + (estep.targets() - deformed)[:, None, :]
        lam = (estep.P1[:, None] * w / sigma2).ravel()
        a = self._rest_offsets.reshape(-1, 3)
        b = b.reshape(-1, 3)
        j, k = graph.edges[:, 0], graph.edges[:, 1]
        a = np.concatenate([a, self._edge_offsets])
        b = np.concatenate([b, node_centres[k] - node_centres[j]])
        lam = np.concatenate([lam, stiffness])
        H = (self._rotation_summer @ (lam[:, None, None] * a[:, :, None] * b[:, None, :]).reshape(-1, 9))
        H = H.reshape(-1, 3, 3) + p.beta_small * np.transpose(rotations, (0, 2, 1))
        rotations[:] = rotations_from_h(H)

    def _update_nodes(self, estep: GMMStatistics, sigma2: float, contributions: np.ndarray,
                      rotations: np.ndarray, translations: np.ndarray) -> None:
        """The paper's M-step: one sweep of joint per-node (R, T) updates (Eq. 5, 6), colour
        by colour (independent nodes together), in place."""
        p = self.params
        g_all = self.graph.node_positions
        targets = estep.targets()
        deformed = contributions.sum(axis=1)
        for batch in self._batches:
            nodes = batch['nodes']
            m, slot, j, w = batch['pair_point'], batch['pair_slot'], batch['pair_node'], batch['pair_weight']
            others = deformed[m] - contributions[m, slot]
            b_gmm = (targets[m] - others) / np.maximum(w, 1e-12)[:, None]
            lam_gmm = estep.P1[m] * w ** 2 / sigma2
            ko = batch['out_edges'][:, 1]
            b_out = g_all[ko] + translations[ko]
            ji, ki = batch['in_edges'][:, 0], batch['in_edges'][:, 1]
            b_in = np.einsum('eij,ej->ei', rotations[ji], g_all[ki] - g_all[ji]) + g_all[ji] + translations[ji]
            b_small = g_all[nodes] + translations[nodes]
            a = np.concatenate([batch['a_gmm'], batch['a_out'], np.zeros((batch['n_in'] + len(nodes), 3))])
            b = np.concatenate([b_gmm, b_out, b_in, b_small])
            lam = np.concatenate([lam_gmm, np.full(batch['n_out'] + batch['n_in'], p.beta_smooth),
                                  np.full(len(nodes), p.beta_small)])
            features = np.concatenate([lam[:, None], lam[:, None] * a, lam[:, None] * b,
                                       (lam[:, None, None] * a[:, :, None] * b[:, None, :]).reshape(-1, 9)],
                                      axis=1)
            sums = batch['summer'] @ features
            total = np.maximum(sums[:, 0], 1e-300)
            mu_a = sums[:, 1:4] / total[:, None]
            mu_b = sums[:, 4:7] / total[:, None]
            H = sums[:, 7:16].reshape(-1, 3, 3) - total[:, None, None] * mu_a[:, :, None] * mu_b[:, None, :]
            H += p.beta_small * np.transpose(rotations[nodes], (0, 2, 1))
            R = rotations_from_h(H)
            rotations[nodes] = R
            translations[nodes] = mu_b - np.einsum('nij,nj->ni', R, mu_a) - g_all[nodes]   # Eq. (5)
            # refresh the contributions of the points these nodes carry
            contributions[m, slot] = w[:, None] * (
                np.einsum('pij,pj->pi', R[batch['local_of_pair']], batch['a_gmm']) + g_all[j] + translations[j])
            touched = batch['points']
            deformed[touched] = contributions[touched].sum(axis=1)
