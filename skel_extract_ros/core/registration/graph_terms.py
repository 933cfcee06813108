r"""The deformation graph's part of the registration energy: its static structures (blend,
incidence, colour batches, the translation system's sparsity) and E_smooth.

Robust smoothness (deviation, `smoothness='robust'`, the default). The graph is built on
the first frame, where a hanging arm touches the torso and the legs touch each other, so
edges join parts that later move apart. With the
quadratic E_smooth at beta_smooth = 1e5 a raised arm stays tied to the torso: it lags
further every frame and is lost. Instead
    E_smooth = sum_e rho(r_e),   rho(r) = r^2 / (1 + r^2 / tau_e^2)   (Geman-McClure),
r_e the residual of edge e as above and tau_e = edge_strain_scale x the edge's rest length
(a residual that size is a relative rotation of about edge_strain_scale radians), weighted
beta_smooth_relative / sigma2 so that it is measured in the units of E_GMM: the balance of
data and smoothness is then the same for a hand at 0.8 m and a body at 4 m. Inside each EM
iteration the loss is replaced by its IRLS majoriser, the quadratic with edge weights
w_e = 1 / (1 + r_e^2 / tau_e^2)^2 at the current transforms (tight there), so both blocks
above stay exact and still cannot raise the iteration's objective; an edge strained far
beyond tau_e (two parts moving apart) stops pulling, one strained little (a bending joint,
noise) acts as before. Because the weight scales with 1 / sigma2 and sigma2 changes between
iterations, the reported objective is not a single fixed function across a frame: the
exact-EM monotonicity holds for `smoothness='paper'` (tested), not for 'robust'.
"""
from __future__ import annotations

import numpy as np
from scipy import sparse


class GraphTerms:
    """Mixin of NonRigidRegistration: needs `self.graph` (DeformationGraph) and `self.params`
    (RegistrationParams); `_prepare` derives the static structures once."""

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
        # A directed edge (j, k) with stiffness s adds s at (j, j) and (k, k), -s at (j, k) and (k, j).
        j, k_ = edges[:, 0], edges[:, 1]
        rows = np.concatenate([np.repeat(graph.point_nodes, k, axis=1).ravel(), j, k_, j, k_, np.arange(n_nodes)])
        cols = np.concatenate([np.tile(graph.point_nodes, (1, k)).ravel(), j, k_, k_, j, np.arange(n_nodes)])
        unique_keys, entry_key = np.unique(rows * n_nodes + cols, return_inverse=True)
        key_rows, key_cols = unique_keys // n_nodes, unique_keys % n_nodes
        csc_order = np.lexsort((key_rows, key_cols))
        csc_position = np.empty_like(csc_order)
        csc_position[csc_order] = np.arange(len(csc_order))
        self._system_slots = csc_position[entry_key.ravel()]
        self._system_pattern = (key_rows[csc_order],
                                np.searchsorted(key_cols[csc_order], np.arange(n_nodes + 1)))
        self._edge_lengths = np.linalg.norm(self._edge_offsets, axis=1)
        self._pair_outer = (graph.point_weights[:, :, None] * graph.point_weights[:, None, :]).reshape(M, -1)
        self._blend = sparse.csr_matrix((pair_weight, (pair_point, pair_node)), shape=(M, n_nodes))
        self._node_mass = np.maximum(np.asarray(self._blend.sum(axis=0)).ravel(), 1e-12)   # (J,)
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

    def edge_residuals(self, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """(E,) |R_j (g_k - g_j) + g_j + T_j - (g_k + T_k)| per directed edge (m)."""
        g = self.graph.node_positions
        j, k = self.graph.edges[:, 0], self.graph.edges[:, 1]
        predicted = np.einsum('eij,ej->ei', rotations[j], g[k] - g[j]) + g[j] + translations[j]
        return np.linalg.norm(predicted - g[k] - translations[k], axis=1)

    def smooth_energy(self, rotations: np.ndarray, translations: np.ndarray) -> float:
        """E_smooth (m^2) of node transforms (Eq. 4, unweighted)."""
        return float(np.sum(self.edge_residuals(rotations, translations) ** 2))

    def edge_stiffness(self, rotations: np.ndarray, translations: np.ndarray, sigma2: float,
                       visible: np.ndarray | None = None, residuals: np.ndarray | None = None) -> np.ndarray:
        """(E,) weight of each edge's squared residual in the M-step: beta_smooth ('paper'),
        or the IRLS weight of the robust loss at the current transforms ('robust'). With
        visible (M,) bool, an edge at a node whose points are mostly hidden keeps its full
        weight: being out of sight is no evidence that the surface tore there. residuals:
        edge_residuals(rotations, translations) when the caller has them."""
        p = self.params
        if p.smoothness == 'paper':
            return np.full(len(self.graph.edges), p.beta_smooth)
        scale = p.edge_strain_scale * self._edge_lengths
        if residuals is None:
            residuals = self.edge_residuals(rotations, translations)
        strain = residuals / scale
        weights = 1.0 / (1.0 + strain ** 2) ** 2
        if visible is not None:
            seen = (self._blend.T @ visible.astype(float)) / self._node_mass
            j, k = self.graph.edges[:, 0], self.graph.edges[:, 1]
            weights = np.where(np.minimum(seen[j], seen[k]) < 0.5, 1.0, weights)
        return p.beta_smooth_relative / sigma2 * weights

    def smoothness_penalty(self, rotations: np.ndarray, translations: np.ndarray, sigma2: float,
                           residuals: np.ndarray | None = None) -> float:
        """The smoothness part of the objective: beta_smooth / 2 E_smooth ('paper'), or
        beta_smooth_relative / (2 sigma2) sum_e rho(r_e) with the Geman-McClure
        rho(r) = r^2 / (1 + r^2 / tau_e^2) ('robust'). residuals: as in edge_stiffness."""
        p = self.params
        if residuals is None:
            residuals = self.edge_residuals(rotations, translations)
        if p.smoothness == 'paper':
            return 0.5 * p.beta_smooth * float(np.sum(residuals ** 2))
        scale = p.edge_strain_scale * self._edge_lengths
        return 0.5 * p.beta_smooth_relative / sigma2 * float(np.sum(residuals ** 2 / (1.0 + (residuals / scale) ** 2)))
