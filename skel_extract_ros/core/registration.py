r"""Non-rigid GMM registration with an embedded deformation graph (paper Sec. 4, Alg. 1).

Model. The observed points V (N, 3) of a frame are drawn from a GMM whose M centroids are
the deformed rest points y'_m (Eq. 2), with one isotropic variance sigma2 and a uniform
outlier component of weight omega (Eq. 1). EM alternates:

E-step (Eq. 3), truncated: p_mi = exp(-|v_i - y'_m|^2 / 2 sigma2) / (sum_m' ... + c),
    c = (2 pi sigma2)^{3/2} omega M / ((1 - omega) N).
    Only pairs within `truncation_sigmas` * sigma of each other, at most
    `e_step_neighbours` centroids per observation (its nearest: a k-d tree over the
    centroids, `core.gmm`), are kept: a Gaussian beyond 3 sigma weighs < 1.1 % of its
    peak, and the dense N x M matrix is never formed (memory O(N k), not O(N M)). The
    neighbour lists are queried again only when a centroid has moved a rest spacing or
    sigma has grown (`core.gmm.CandidateCache`, as in Alg. 2 and the live fit): once EM
    has found the frame the centroids move by millimetres, and the query is a large part
    of an iteration.

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

sigma2 (Eq. 7): sigma2 = sum_mi p_mi |v_i - y'_m|^2 / (3 N_p), with the new y'.

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

Recapture (`recapture=True`, core/recapture.py): after EM, a part with no posterior mass
and a group of observations beyond every centroid's reach are matched, the part is moved
rigidly onto them and EM is re-run from there; the result is kept if it explains more of the
frame (larger N_p).

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
from .gmm import CandidateCache, GMMStatistics, gmm_posteriors
from .point_sets import finite_rows, median_spacing
from .recapture import find_recaptures, lost_parts
from .rigid import fit_weighted_segments, rotations_from_h, weighted_rigid_fit

STATUS_OK = 'ok'
STATUS_EMPTY = 'empty'
STATUS_DIVERGED = 'diverged'
M_STEPS = ('translations_rotations', 'per_node')
SMOOTHNESS = ('robust', 'paper')


@dataclass
class RegistrationParams:
    """Parameters of the registration (defaults: the paper's Table 1 where it gives one).

    omega: weight of the uniform outlier component (Eq. 1).
    smoothness: 'robust' (default) or 'paper'. 'paper' is Eq. (4) as written: E_smooth
        quadratic with the fixed weight beta_smooth. 'robust' (see "Robust smoothness" in
        the module docstring) weighs E_smooth by beta_smooth_relative / sigma2 and gives
        every graph edge a Geman-McClure loss with scale edge_strain_scale.
    beta_smooth: weight of E_smooth with smoothness='paper' (1 / m^2, Table 1).
    beta_smooth_relative: with smoothness='robust', E_smooth is weighted
        beta_smooth_relative / sigma2, in the units of the data term.
    edge_strain_scale: with smoothness='robust', the Geman-McClure scale of an edge's
        residual as a fraction of its rest length (about the relative rotation of its
        two nodes, radians) at which the edge weighs a quarter.
    beta_small: weight of E_small (Eq. 4).
    visibility: model points the camera cannot see in a frame (behind an observed surface
        by more than the E-step's reach) take no part in that frame's E-step and follow
        the graph (`ObservedView`). False: every point may claim observations (the paper).
    recapture: after EM, a part left without data is moved rigidly onto the observations
        nothing explains, and EM re-run from there (`core.recapture`).
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
    smoothness: str = 'robust'
    beta_smooth: float = 1e5
    beta_smooth_relative: float = 4.0
    edge_strain_scale: float = 0.5
    beta_small: float = 1.0
    visibility: bool = False
    recapture: bool = True
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
        for name in ('beta_smooth', 'beta_small', 'beta_smooth_relative'):
            if getattr(self, name) < 0:
                raise ValueError(f'{name} must be non-negative')
        for name in ('initial_sigma2', 'min_sigma2', 'max_sigma2', 'truncation_sigmas', 'node_spacing_factor',
                     'edge_strain_scale'):
            if getattr(self, name) <= 0:
                raise ValueError(f'{name} must be positive')
        if self.max_iterations < 1 or self.e_step_neighbours < 1 or self.n_influence < 1:
            raise ValueError('max_iterations, e_step_neighbours and n_influence must be >= 1')
        if self.m_step not in M_STEPS:
            raise ValueError(f'm_step must be one of {M_STEPS}, got {self.m_step!r}')
        if self.smoothness not in SMOOTHNESS:
            raise ValueError(f'smoothness must be one of {SMOOTHNESS}, got {self.smoothness!r}')
        if self.m_step == 'per_node' and self.smoothness != 'paper':
            raise ValueError("m_step 'per_node' is the paper's scheme and needs smoothness 'paper'")


@dataclass
class FrameResult:
    """Outcome of registering one frame.

    points: (M, 3) registered points y' (the last good ones if the frame failed), metres.
    sigma2: final variance (m^2); energies: objective after each E-step.
    matched_fraction: N_p / N, the share of the observations the GMM explains.
    recaptured: parts moved back onto their observations in this frame (`recapture`).
    """

    points: np.ndarray
    status: str
    sigma2: float
    iterations: int
    matched_fraction: float
    energies: list = field(default_factory=list)
    recaptured: int = 0


class ObservedView:
    """What the camera saw of one frame, as directions and ranges from the camera (the
    origin of the cloud frame), to tell which model points it could have seen.

    A model point is hidden when an observation lies on (nearly) the same ray and is
    closer to the camera by more than `margin`: the surface there is in front of it. That
    covers self-occlusion (the torso behind an arm) and the back of a turned body (behind
    its front) alike. Rays are compared on the unit sphere (k-d tree over the observed
    directions), so any camera orientation works.

    observed: (N, 3) metres.
    """

    def __init__(self, observed: np.ndarray):
        ranges = np.linalg.norm(observed, axis=1)
        self.ranges = ranges
        directions = observed / np.maximum(ranges, 1e-9)[:, None]
        self.tree = cKDTree(directions)
        # the angular pixel footprint: how far apart neighbouring rays are
        self.ray_spacing = float(np.median(self.tree.query(directions, k=2)[0][:, 1]))

    def visible(self, points: np.ndarray, margin: float) -> np.ndarray:
        """(M,) bool: no observation within 1.5 ray spacings of the point's ray is more
        than `margin` (m) nearer the camera. points (M, 3)."""
        ranges = np.linalg.norm(points, axis=1)
        _, nearest = self.tree.query(points / np.maximum(ranges, 1e-9)[:, None], k=4,
                                     distance_upper_bound=1.5 * self.ray_spacing)
        found = nearest < len(self.ranges)
        in_front = np.where(found, self.ranges[np.where(found, nearest, 0)], np.inf)
        return (in_front.min(axis=1) >= ranges - margin)


@dataclass
class _EMState:
    """Node transforms, registered points (M, 3), sigma2 and the last E-step of one EM run."""

    rotations: np.ndarray
    translations: np.ndarray
    points: np.ndarray
    sigma2: float
    estep: GMMStatistics | None
    iterations: int
    energies: list
    recaptured: int = 0


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
        # the rest points' spacing: a centroid that moved less has passed no other (CandidateCache)
        self.point_spacing = median_spacing(rest_points)
        spacing = self.params.node_spacing or self.params.node_spacing_factor * self.point_spacing
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

    # ----------------------------------------------------------------------------------
    def _e_step(self, observed: np.ndarray, points: np.ndarray, sigma2: float,
                view: 'ObservedView | None' = None, cache: CandidateCache | None = None) -> GMMStatistics:
        """Eq. (3) over the centroids the camera can see (all without a view); without a
        view, over the candidates of `cache` (the frame's CandidateCache)."""
        p = self.params
        if view is None:
            if cache is not None:
                return cache.posteriors(points, sigma2, p.omega, p.truncation_sigmas)
            return gmm_posteriors(observed, points, sigma2, p.omega, p.e_step_neighbours, p.truncation_sigmas)
        visible = view.visible(points, p.truncation_sigmas * np.sqrt(sigma2))
        self.last_visible_ = visible
        stats = gmm_posteriors(observed, points[visible], sigma2, p.omega, p.e_step_neighbours,
                               p.truncation_sigmas)
        P1 = np.zeros(len(points))
        Px = np.zeros((len(points), 3))
        P1[visible], Px[visible] = stats.P1, stats.Px
        return GMMStatistics(P1, Px, stats.Np, stats.nll, stats.weighted_sq)

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

    def _node_support(self, estep: GMMStatistics) -> np.ndarray:
        """(J,) posterior mass per carried point that each node's points received (0: no data)."""
        return (self._blend.T @ estep.P1) / self._node_mass

    def _run_em(self, observed: np.ndarray, view: 'ObservedView | None', rotations: np.ndarray,
                translations: np.ndarray, iterations_done: int = 0) -> '_EMState':
        """EM (Alg. 1) from the node transforms given, to convergence or max_iterations."""
        p = self.params
        rotated = self._rotated_offsets(rotations)
        contributions = self._contributions(rotations, translations, rotated)
        points = contributions.sum(axis=1)
        sigma2 = p.initial_sigma2
        energies = []
        iterations = 0
        estep = None
        # the visible subset changes between iterations: its E-step queries every time
        cache = CandidateCache(observed, self.point_spacing, p.e_step_neighbours) if view is None else None
        for iterations in range(1, p.max_iterations + 1):
            estep = self._e_step(observed, points, sigma2, view, cache)
            # the objective and the IRLS weights below are both at these transforms
            residuals = self.edge_residuals(rotations, translations)
            energies.append(estep.nll + self.smoothness_penalty(rotations, translations, sigma2, residuals))
            if len(energies) > 1 and abs(energies[-2] - energies[-1]) <= p.tolerance * abs(energies[-1]):
                break
            if estep.Np <= 1e-9:
                break
            if p.m_step == 'translations_rotations':
                # IRLS: the robust edge weights are fixed at this iteration's transforms
                stiffness = self.edge_stiffness(rotations, translations, sigma2,
                                                None if view is None else self.last_visible_, residuals)
                self._solve_translations(estep, sigma2, rotations, translations, rotated, stiffness)
                contributions = self._contributions(rotations, translations, rotated)
                self._update_rotations(estep, sigma2, contributions, rotations, translations, rotated, stiffness)
                rotated = self._rotated_offsets(rotations)
                contributions = self._contributions(rotations, translations, rotated)
            else:
                self._update_nodes(estep, sigma2, contributions, rotations, translations)
            points = contributions.sum(axis=1)
            # Eq. (7): sum_mi p_mi |v_i - y'_m|^2 / (3 N_p)
            sigma2 = max(estep.squared_residual(points) / (3.0 * estep.Np), p.min_sigma2)
            if sigma2 > p.max_sigma2:
                break
        return _EMState(rotations, translations, points, sigma2, estep, iterations_done + iterations, energies)

    def _recapture(self, observed: np.ndarray, view: 'ObservedView | None', state: '_EMState') -> '_EMState':
        """Turn parts EM left behind onto the observations nothing explains (core.recapture),
        re-run EM from there, and keep that if it explains more of the frame."""
        p = self.params
        graph = self.graph
        if not np.isfinite(state.sigma2):
            return state
        support = self._node_support(state.estep)
        reach = p.truncation_sigmas * np.sqrt(state.sigma2)
        main_node = graph.point_nodes[np.arange(len(graph.rest_points)), np.argmax(graph.point_weights, axis=1)]
        node_positions = graph.node_positions + state.translations
        found = find_recaptures(observed, state.points, node_positions, support, graph.edges, main_node, reach)
        if not found:
            return state
        rotations, translations = state.rotations.copy(), state.translations.copy()
        for capture in found:
            nodes = capture.nodes
            rotations[nodes] = np.einsum('ij,njk->nik', capture.rotation, rotations[nodes])
            moved = node_positions[nodes] @ capture.rotation.T + capture.shift
            translations[nodes] = moved - graph.node_positions[nodes]
        retried = self._run_em(observed, view, rotations, translations, state.iterations)
        if retried.estep is None or not retried.estep.Np > state.estep.Np:
            return state
        retried.energies = state.energies + retried.energies
        retried.recaptured = len(found)
        return retried

    def _carry_unseen_parts(self, state: '_EMState', start: tuple) -> None:
        """Parts without data this frame (out of sight, or lost and not recaptured) move
        rigidly with the tracked nodes they hang on, from where EM started them (the
        previous frame's state, or the predicted pose: `start` = (rotations, translations)),
        in place.

        With the robust smoothness such a part is torn off and, having nothing to follow,
        would stay where it was while the body walks on; the paper's stiff graph dragged it
        along. This keeps the drag, without letting the part pull on the tracked body."""
        graph = self.graph
        support = self._node_support(state.estep)
        start_rotations, start_translations = start
        before = graph.node_positions + start_translations
        after = graph.node_positions + state.translations
        for nodes, anchors in lost_parts(support, graph.edges):     # a few parts, not points
            if len(anchors) >= 3:
                rotation, shift = weighted_rigid_fit(before[anchors], after[anchors])
            else:
                rotation, shift = np.eye(3), (after[anchors] - before[anchors]).mean(axis=0)
            state.rotations[nodes] = np.einsum('ij,njk->nik', rotation, start_rotations[nodes])
            state.translations[nodes] = before[nodes] @ rotation.T + shift - graph.node_positions[nodes]
        state.points = self._contributions(state.rotations, state.translations).sum(axis=1)

    def transforms_onto(self, points: np.ndarray) -> tuple:
        """Node transforms (rotations (J, 3, 3), translations (J, 3)) that carry the rest
        points onto `points` (M, 3) m, e.g. a pose predicted by a tracker: each node's
        weighted rigid fit of the points it carries (its blend weights). Exact for a rigid
        motion of the whole set; an approximation of a non-rigid one that EM refines."""
        points = np.asarray(points, dtype=np.float64)
        if points.shape != self.rest_points.shape or not np.isfinite(points).all():
            raise ValueError(f'start points must be finite ({len(self.rest_points)}, 3), got {points.shape}')
        rotations, centres = fit_weighted_segments(self.rest_points, points[None], self._blend.T)
        rotations, centres = rotations[0], centres[0]               # y = R q + c
        g = self.graph.node_positions
        # the graph's form: y = R (q - g) + g + T, so T = c + R g - g
        return rotations, centres + np.einsum('jik,jk->ji', rotations, g) - g

    # ----------------------------------------------------------------------------------
    def register_frame(self, observed: np.ndarray, start_points: np.ndarray | None = None) -> FrameResult:
        """Register one frame's observed points (N, 3), metres: EM from the previous frame's
        state, or, with start_points (M, 3) (a predicted pose of the registered points,
        e.g. the live skeleton fit of a newer frame than the last registered one), from the
        node transforms that carry the rest points onto it (`transforms_onto`). A frame
        that is empty or diverges leaves the state as it was."""
        p = self.params
        observed = np.asarray(observed, dtype=np.float64)
        if observed.ndim != 2 or observed.shape[1] != 3:
            raise ValueError(f'observed points must be (N, 3), got {observed.shape}')
        observed = np.ascontiguousarray(observed[finite_rows(observed)])
        if len(observed) < p.min_points:
            return FrameResult(self.points.copy(), STATUS_EMPTY, float('nan'), 0, 0.0)
        start = (self.rotations.copy(), self.translations.copy()) if start_points is None \
            else self.transforms_onto(start_points)

        view = ObservedView(observed) if p.visibility else None
        state = self._run_em(observed, view, start[0].copy(), start[1].copy())
        if p.recapture and state.estep is not None:
            state = self._recapture(observed, view, state)
        if p.smoothness == 'robust' and state.estep is not None and np.isfinite(state.sigma2):
            self._carry_unseen_parts(state, start)
        rotations, translations, points, sigma2 = state.rotations, state.translations, state.points, state.sigma2
        estep, iterations, energies = state.estep, state.iterations, state.energies
        matched_fraction = estep.Np / len(observed) if estep is not None else 0.0
        if not np.isfinite(sigma2) or sigma2 > p.max_sigma2 or matched_fraction < p.min_matched_fraction \
                or not np.isfinite(points).all():
            return FrameResult(self.points.copy(), STATUS_DIVERGED, float(sigma2), iterations,
                               float(matched_fraction), energies)
        self.rotations, self.translations, self.points = rotations, translations, points
        return FrameResult(points.copy(), STATUS_OK, float(sigma2), iterations, float(matched_fraction), energies,
                           state.recaptured)
