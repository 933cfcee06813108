r"""Non-rigid GMM registration with an embedded deformation graph (paper Sec. 4, Alg. 1).

Model. The observed points V (N, 3) of a frame are drawn from a GMM whose M centroids are
the deformed rest points y'_m (Eq. 2), with one isotropic variance sigma2 and a uniform
outlier component of weight omega (Eq. 1). EM alternates:

E-step (Eq. 3), truncated: p_mi = exp(-|v_i - y'_m|^2 / 2 sigma2) / (sum_m' ... + c),
    c = (2 pi sigma2)^{3/2} omega M / ((1 - omega) N).
    Only pairs within `truncation_sigmas` * sigma of each other, at most
    `e_step_neighbours` observations per centroid, found with a k-d tree over V built once
    per frame, are kept: a Gaussian beyond 3 sigma weighs < 1.1 % of its peak, and the
    dense N x M matrix is never formed (memory O(M k), not O(N M)).

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

Choice of blocks (deviation, measured in bench/README.md). One node at a time with
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

sigma2 (Eq. 7): sigma2 = sum_mi p_mi |v_i - y'_m|^2 / (3 N_p), with the new y'.

Convergence: the quantity EM decreases is the negative log-likelihood of Eq. (1) plus
beta_smooth / 2 E_smooth (E_small vanishes at the previous iterate, so it acts as a
proximal term and cannot make the objective rise). `FrameResult.energies` reports exactly
that. With exact EM (all centroids, no radius) it never increases (tested). With the
truncated E-step it may rise late in a frame, for a precise reason: as sigma shrinks, an
observation that leaves every centroid's truncation ball loses its Gaussian term and counts
as an outlier only, so the truncated likelihood changes support between iterations; noise
with heavier tails than the Gaussian (depth quantisation, flying pixels) makes this happen.
The sigma2 floor (min_sigma2) can likewise stop the sigma2 step from being a full minimiser.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from .deformation_graph import DeformationGraph
from .gmm import GMMStatistics, gmm_posteriors
from .rigid import rotations_from_h

STATUS_OK = 'ok'
STATUS_EMPTY = 'empty'
STATUS_DIVERGED = 'diverged'
M_STEPS = ('translations_rotations', 'per_node')


@dataclass
class RegistrationParams:
    """Parameters of the registration (defaults: the paper's Table 1 where it gives one).

    omega: weight of the uniform outlier component (Eq. 1).
    beta_smooth, beta_small: weights of E_smooth and E_small (Eq. 4).
    initial_sigma2: GMM variance at the start of every frame, m^2 (Sec. 7).
    max_iterations, tolerance: EM stops after max_iterations or when the relative energy
        change falls below tolerance (Sec. 6, last paragraph).
    m_step: 'translations_rotations' (default) or 'per_node' (the paper's scheme); see the
        module docstring.
    node_spacing: deformation-graph node spacing in metres; None picks
        `node_spacing_factor` times the median spacing of the rest points, so the graph is
        equally fine on a hand and on a body.
    n_influence: nodes carrying each point (k in Eq. 2).
    e_step_neighbours, truncation_sigmas: the truncated E-step (each observation sees at
        most this many centroids, within this many sigmas); e_step_neighbours >= M with
        truncation_sigmas = inf is exact EM.
    min_sigma2: floor on sigma2 (m^2), so a perfect fit cannot collapse the Gaussians.
    max_sigma2, min_matched_fraction: a frame whose sigma2 ends above max_sigma2, or whose
        observations are explained by the GMM for less than this fraction of their mass,
        has diverged: the last good state is kept.
    min_points: fewer observed points than this is an empty frame.
    """

    omega: float = 0.01
    beta_smooth: float = 1e5
    beta_small: float = 1.0
    initial_sigma2: float = 6e-4
    max_iterations: int = 20
    tolerance: float = 1e-3
    m_step: str = 'translations_rotations'
    node_spacing: float | None = None
    node_spacing_factor: float = 3.5
    n_influence: int = 4
    e_step_neighbours: int = 8
    truncation_sigmas: float = 4.0
    min_sigma2: float = 1e-6
    max_sigma2: float = 1e-2
    min_matched_fraction: float = 0.3
    min_points: int = 50

    def __post_init__(self):
        if not 0.0 <= self.omega < 1.0:
            raise ValueError(f'omega must be in [0, 1), got {self.omega}')
        for name in ('beta_smooth', 'beta_small'):
            if getattr(self, name) < 0:
                raise ValueError(f'{name} must be non-negative')
        for name in ('initial_sigma2', 'min_sigma2', 'max_sigma2', 'truncation_sigmas', 'node_spacing_factor'):
            if getattr(self, name) <= 0:
                raise ValueError(f'{name} must be positive')
        if self.max_iterations < 1 or self.e_step_neighbours < 1 or self.n_influence < 1:
            raise ValueError('max_iterations, e_step_neighbours and n_influence must be >= 1')
        if self.m_step not in M_STEPS:
            raise ValueError(f'm_step must be one of {M_STEPS}, got {self.m_step!r}')


@dataclass
class FrameResult:
    """Outcome of registering one frame.

    points: (M, 3) registered points y' (the last good ones if the frame failed), metres.
    sigma2: final variance (m^2); energies: objective after each E-step.
    matched_fraction: N_p / N, the share of the observations the GMM explains.
    """

    points: np.ndarray
    status: str
    sigma2: float
    iterations: int
    matched_fraction: float
    energies: list = field(default_factory=list)


def median_spacing(points: np.ndarray) -> float:
    """Median distance from each point to its nearest neighbour (m)."""
    distances, _ = cKDTree(points).query(points, k=2)
    return float(np.median(distances[:, 1]))


class NonRigidRegistration:
    """Tracks a rest point set through a sequence, frame by frame (Alg. 1).

    >>> registration = NonRigidRegistration(rest_points, RegistrationParams())
    >>> result = registration.register_frame(observed_points)   # (N, 3) -> FrameResult

    State (node rotations and translations) carries over from frame to frame; a frame that
    is empty or diverges leaves it unchanged.
    """

    def __init__(self, rest_points: np.ndarray, params: RegistrationParams | None = None):
        self.params = params or RegistrationParams()
        rest_points = np.asarray(rest_points, dtype=np.float64)
        if rest_points.ndim != 2 or rest_points.shape[1] != 3 or len(rest_points) < 10:
            raise ValueError(f'rest points must be (M >= 10, 3), got {rest_points.shape}')
        spacing = self.params.node_spacing or self.params.node_spacing_factor * median_spacing(rest_points)
        self.node_spacing = spacing
        self.graph = DeformationGraph.build(rest_points, spacing, self.params.n_influence)
        n_nodes = self.graph.n_nodes
        self.rotations = np.tile(np.eye(3), (n_nodes, 1, 1))
        self.translations = np.zeros((n_nodes, 3))
        self.points = rest_points.copy()
        self._prepare()

    @property
    def rest_points(self) -> np.ndarray:
        return self.graph.rest_points

    def reset(self) -> None:
        """Back to the rest pose (identity node transforms)."""
        self.rotations[:] = np.eye(3)
        self.translations[:] = 0.0
        self.points = self.rest_points.copy()

    # ----------------------------------------------------------------------------------
    def _prepare(self) -> None:
        """Static structures: per-colour index sets, blend and incidence matrices."""
        graph = self.graph
        M, k = graph.point_nodes.shape
        n_nodes = graph.n_nodes
        g = graph.node_positions
        pair_point = np.repeat(np.arange(M), k)
        pair_slot = np.tile(np.arange(k), M)
        pair_node = graph.point_nodes.ravel()
        pair_weight = graph.point_weights.ravel()
        edges = graph.edges
        self._rest_offsets = graph.rest_points[:, None, :] - g[graph.point_nodes]   # (M, k, 3) a_mj
        self._batches = []
        # The colour batches serve only the paper's node-by-node M-step.
        for nodes in (graph.colors if self.params.m_step == 'per_node' else []):
            local = np.full(n_nodes, -1)
            local[nodes] = np.arange(len(nodes))
            pairs = np.flatnonzero(local[pair_node] >= 0)
            out_edges = np.flatnonzero(local[edges[:, 0]] >= 0)   # node predicts neighbour
            in_edges = np.flatnonzero(local[edges[:, 1]] >= 0)    # neighbour predicts node
            segments = np.concatenate([local[pair_node[pairs]], local[edges[out_edges, 0]],
                                       local[edges[in_edges, 1]], np.arange(len(nodes))])
            n_terms = len(segments)
            # Sparse "segment sum" over each node's terms: one product per colour.
            summer = sparse.csr_matrix((np.ones(n_terms), (segments, np.arange(n_terms))),
                                       shape=(len(nodes), n_terms))
            self._batches.append({
                'nodes': nodes,
                'local_of_pair': local[pair_node[pairs]],
                'pair_point': pair_point[pairs], 'pair_slot': pair_slot[pairs],
                'pair_node': pair_node[pairs], 'pair_weight': pair_weight[pairs],
                'a_gmm': self._rest_offsets[pair_point[pairs], pair_slot[pairs]],
                'out_edges': edges[out_edges], 'in_edges': edges[in_edges],
                'a_out': g[edges[out_edges, 1]] - g[edges[out_edges, 0]],
                'points': np.unique(pair_point[pairs]),
                'summer': summer,
                'n_pairs': len(pairs), 'n_out': len(out_edges), 'n_in': len(in_edges),
            })
        # Rotation block (all nodes at once): terms are [all (point, node) pairs, all edges].
        n_terms = len(pair_node) + len(edges)
        self._rotation_summer = sparse.csr_matrix(
            (np.ones(n_terms), (np.concatenate([pair_node, edges[:, 0]]), np.arange(n_terms))),
            shape=(n_nodes, n_terms))
        self._edge_offsets = g[edges[:, 1]] - g[edges[:, 0]]
        # Translation block: the J x J system's sparsity pattern is fixed; only the data
        # weights change, so each iteration sums its entries into precomputed CSC slots.
        incidence = sparse.csr_matrix(
            (np.concatenate([np.ones(len(edges)), -np.ones(len(edges))]),
             (np.tile(np.arange(len(edges)), 2), np.concatenate([edges[:, 0], edges[:, 1]]))),
            shape=(len(edges), n_nodes))                      # +1 at j, -1 at k for edge (j, k)
        laplacian = (incidence.T @ incidence).tocoo()
        rows = np.concatenate([np.repeat(graph.point_nodes, k, axis=1).ravel(), laplacian.row, np.arange(n_nodes)])
        cols = np.concatenate([np.tile(graph.point_nodes, (1, k)).ravel(), laplacian.col, np.arange(n_nodes)])
        unique_keys, entry_key = np.unique(rows * n_nodes + cols, return_inverse=True)
        key_rows, key_cols = unique_keys // n_nodes, unique_keys % n_nodes
        csc_order = np.lexsort((key_rows, key_cols))
        csc_position = np.empty_like(csc_order)
        csc_position[csc_order] = np.arange(len(csc_order))
        self._system_slots = csc_position[entry_key.ravel()]
        self._system_pattern = (key_rows[csc_order],
                                np.searchsorted(key_cols[csc_order], np.arange(n_nodes + 1)))
        self._laplacian_values = laplacian.data
        self._pair_outer = (graph.point_weights[:, :, None] * graph.point_weights[:, None, :]).reshape(M, -1)
        self._blend = sparse.csr_matrix((pair_weight, (pair_point, pair_node)), shape=(M, n_nodes))
        self._incidence = incidence

    def _rotated_offsets(self, rotations: np.ndarray) -> np.ndarray:
        """(M, k, 3) R_j (q_m - g_j) + g_j for every point and carrying node."""
        nodes = self.graph.point_nodes
        return np.einsum('mkij,mkj->mki', rotations[nodes], self._rest_offsets) + self.graph.node_positions[nodes]

    def _contributions(self, rotations: np.ndarray, translations: np.ndarray,
                       rotated: np.ndarray | None = None) -> np.ndarray:
        """(M, k, 3) per-node parts w_mj [R_j (q_m - g_j) + g_j + T_j] of Eq. (2);
        `rotated` reuses _rotated_offsets(rotations) when the caller has it."""
        rotated = self._rotated_offsets(rotations) if rotated is None else rotated
        moved = rotated + translations[self.graph.point_nodes]
        return self.graph.point_weights[..., None] * moved

    def smooth_energy(self, rotations: np.ndarray, translations: np.ndarray) -> float:
        """E_smooth (m^2) of node transforms."""
        g = self.graph.node_positions
        j, k = self.graph.edges[:, 0], self.graph.edges[:, 1]
        predicted = np.einsum('eij,ej->ei', rotations[j], g[k] - g[j]) + g[j] + translations[j]
        return float(np.sum((predicted - g[k] - translations[k]) ** 2))

    # ----------------------------------------------------------------------------------
    def _e_step(self, observed: np.ndarray, points: np.ndarray, sigma2: float) -> GMMStatistics:
        p = self.params
        return gmm_posteriors(observed, points, sigma2, p.omega, p.e_step_neighbours, p.truncation_sigmas)

    def _solve_translations(self, estep: GMMStatistics, sigma2: float, rotations: np.ndarray,
                            translations: np.ndarray, rotated: np.ndarray) -> None:
        """Exact minimisation of E over all node translations at once (in place);
        rotated: _rotated_offsets(rotations)."""
        p = self.params
        graph = self.graph
        g = graph.node_positions
        n_nodes = graph.n_nodes
        weights = estep.P1 / sigma2
        residual_targets = estep.targets() - np.einsum('mk,mki->mi', graph.point_weights, rotated)
        j, k = graph.edges[:, 0], graph.edges[:, 1]
        c = np.einsum('eij,ej->ei', rotations[j], g[k] - g[j]) + g[j] - g[k]
        entries = np.concatenate([(weights[:, None] * self._pair_outer).ravel(),
                                  p.beta_smooth * self._laplacian_values,
                                  np.full(n_nodes, p.beta_small)])
        values = np.bincount(self._system_slots, weights=entries, minlength=len(self._system_pattern[0]))
        system = sparse.csc_matrix((values, *self._system_pattern), shape=(n_nodes, n_nodes))
        rhs = self._blend.T @ (weights[:, None] * residual_targets) \
            - p.beta_smooth * (self._incidence.T @ c) + p.beta_small * translations
        translations[:] = spsolve(system, rhs).reshape(-1, 3)

    def _update_rotations(self, estep: GMMStatistics, sigma2: float, contributions: np.ndarray,
                          rotations: np.ndarray, translations: np.ndarray, rotated: np.ndarray) -> None:
        """All rotations at once from the separable majoriser (module docstring), in place;
        rotated: _rotated_offsets(rotations)."""
        p = self.params
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
        lam = np.concatenate([lam, np.full(len(j), p.beta_smooth)])
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

    # ----------------------------------------------------------------------------------
    def register_frame(self, observed: np.ndarray) -> FrameResult:
        """Register the current state to one frame's observed points (N, 3), metres."""
        p = self.params
        observed = np.asarray(observed, dtype=np.float64)
        if observed.ndim != 2 or observed.shape[1] != 3:
            raise ValueError(f'observed points must be (N, 3), got {observed.shape}')
        observed = np.ascontiguousarray(observed[np.isfinite(observed).all(axis=1)])
        if len(observed) < p.min_points:
            return FrameResult(self.points.copy(), STATUS_EMPTY, float('nan'), 0, 0.0)

        rotations, translations = self.rotations.copy(), self.translations.copy()
        rotated = self._rotated_offsets(rotations)
        contributions = self._contributions(rotations, translations, rotated)
        points = contributions.sum(axis=1)
        sigma2 = p.initial_sigma2
        energies = []
        iterations = 0
        estep = None
        for iterations in range(1, p.max_iterations + 1):
            estep = self._e_step(observed, points, sigma2)
            energies.append(estep.nll + 0.5 * p.beta_smooth * self.smooth_energy(rotations, translations))
            if len(energies) > 1 and abs(energies[-2] - energies[-1]) <= p.tolerance * abs(energies[-1]):
                break
            if estep.Np <= 1e-9:
                break
            if p.m_step == 'translations_rotations':
                self._solve_translations(estep, sigma2, rotations, translations, rotated)
                contributions = self._contributions(rotations, translations, rotated)
                self._update_rotations(estep, sigma2, contributions, rotations, translations, rotated)
                rotated = self._rotated_offsets(rotations)
                contributions = self._contributions(rotations, translations, rotated)
            else:
                self._update_nodes(estep, sigma2, contributions, rotations, translations)
            points = contributions.sum(axis=1)
            # Eq. (7): sum_mi p_mi |v_i - y'_m|^2 / (3 N_p)
            sigma2 = max(estep.squared_residual(points) / (3.0 * estep.Np), p.min_sigma2)
            if sigma2 > p.max_sigma2:
                break

        matched_fraction = estep.Np / len(observed) if estep is not None else 0.0
        if not np.isfinite(sigma2) or sigma2 > p.max_sigma2 or matched_fraction < p.min_matched_fraction \
                or not np.isfinite(points).all():
            return FrameResult(self.points.copy(), STATUS_DIVERGED, float(sigma2), iterations,
                               float(matched_fraction), energies)
        self.rotations, self.translations, self.points = rotations, translations, points
        return FrameResult(points.copy(), STATUS_OK, float(sigma2), iterations, float(matched_fraction), energies)
