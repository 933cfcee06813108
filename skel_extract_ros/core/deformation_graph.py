"""Embedded deformation graph (Sumner et al. 2007; Li et al. 2009), paper Eq. (2).

Nodes g_j are sampled evenly over the rest points; every rest point q_m is carried by its
k nearest nodes with weights (1 - d / d_max)^2, normalised to sum to 1, where d_max is the
distance to the (k + 1)-th nearest node:

    y'_m = sum_j w_mj [ R_j (q_m - g_j) + g_j + T_j ]                         (Eq. 2)

Two nodes are graph neighbours (for E_smooth) when they carry a common point, so the graph
follows the surface rather than straight-line proximity.

The node updates of the registration M-step are exact block-coordinate steps: one node at
a time with all others fixed. Nodes that share no point and no edge do not interact, so
`colors` partitions the nodes into independent sets that can be updated together, in a
vectorised batch, without changing the result of the one-at-a-time scheme.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .point_sets import voxel_centroids


@dataclass
class DeformationGraph:
    """Graph over rest points Q (M, 3), metres.

    node_positions: (J, 3) g_j; point_nodes: (M, k) node index per point;
    point_weights: (M, k) blend weights (rows sum to 1); edges: (E, 2) directed pairs
    (j, k) with both directions present; colors: list of node-index arrays, independent sets.
    """

    rest_points: np.ndarray
    node_positions: np.ndarray
    point_nodes: np.ndarray
    point_weights: np.ndarray
    edges: np.ndarray
    colors: list

    @property
    def n_nodes(self) -> int:
        return len(self.node_positions)

    @classmethod
    def build(cls, rest_points: np.ndarray, node_spacing: float, n_influence: int = 4) -> 'DeformationGraph':
        """Sample nodes `node_spacing` metres apart over `rest_points` (M, 3).

        Nodes are voxel-grid representatives snapped to the nearest rest point, so they lie
        on the surface. `n_influence` (k) nodes carry each point.
        """
        rest_points = np.asarray(rest_points, dtype=np.float64)
        if len(rest_points) < n_influence + 1:
            raise ValueError(f'need more than {n_influence} rest points, got {len(rest_points)}')
        if node_spacing <= 0:
            raise ValueError(f'node_spacing must be positive, got {node_spacing}')
        centres = voxel_centroids(rest_points, node_spacing)
        _, nearest = cKDTree(rest_points).query(centres)
        node_positions = rest_points[np.unique(nearest)]
        if len(node_positions) < n_influence + 1:
            # Too coarse for this subject: fall back to the fewest nodes that still blend.
            step = max(1, len(rest_points) // (n_influence + 1))
            node_positions = rest_points[::step][:max(n_influence + 1, len(rest_points) // step)]

        distances, nodes = cKDTree(node_positions).query(rest_points, k=n_influence + 1)
        d_max = distances[:, -1:]
        weights = (1.0 - distances[:, :-1] / np.maximum(d_max, 1e-12)) ** 2
        weights_sum = weights.sum(axis=1, keepdims=True)
        # A point equidistant to all k+1 nodes would get all-zero weights: use its nearest.
        degenerate = weights_sum[:, 0] <= 1e-12
        weights[degenerate] = 0.0
        weights[degenerate, 0] = 1.0
        weights /= weights.sum(axis=1, keepdims=True)
        point_nodes = nodes[:, :-1]

        n_nodes = len(node_positions)
        pairs = np.stack(np.broadcast_arrays(point_nodes[:, :, None], point_nodes[:, None, :]), -1)
        pairs = pairs.reshape(-1, 2)
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        edges = np.unique(pairs, axis=0)
        colors = _greedy_colors(n_nodes, edges)
        return cls(rest_points, node_positions, point_nodes, weights, edges, colors)

    def deform(self, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """Eq. (2): (J, 3, 3) rotations and (J, 3) translations -> (M, 3) deformed points."""
        g = self.node_positions[self.point_nodes]                        # (M, k, 3)
        local = self.rest_points[:, None, :] - g
        moved = np.einsum('mkij,mkj->mki', rotations[self.point_nodes], local) + g + translations[self.point_nodes]
        return np.einsum('mk,mki->mi', self.point_weights, moved)


def _greedy_colors(n_nodes: int, edges: np.ndarray) -> list:
    """Partition nodes into sets with no edge inside a set (largest-degree-first greedy).

    Python loop over nodes (a few hundred), not over points; done once per rest pose.
    """
    neighbours = [[] for _ in range(n_nodes)]
    for a, b in edges:
        neighbours[a].append(b)
    degree = np.array([len(n) for n in neighbours])
    color = np.full(n_nodes, -1)
    for node in np.argsort(-degree, kind='stable'):
        used = {color[n] for n in neighbours[node]}
        c = 0
        while c in used:
            c += 1
        color[node] = c
    return [np.flatnonzero(color == c) for c in range(color.max() + 1)]
