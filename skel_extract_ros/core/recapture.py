"""Recapture of a part the registration lost: a limb that moved farther in one frame than
the E-step reaches (a kick, a fast wave: 20-25 cm a frame at 30 Hz).

After a frame's EM such a part is left behind, and both sides show it: the part's graph
nodes receive (almost) no posterior mass, and the limb's observations lie beyond every
centroid's reach. EM alone never brings the part back, since nothing pulls it. Here both
are found, matched, and the lost part is moved rigidly onto those observations: an ICP
started by turning the part about where it hangs on the tracked body (the mean position of
its tracked neighbour nodes) so that it points at them. The caller re-runs EM from
the recaptured state and keeps it only if the frame is then explained better.

Everything is in metres; the thresholds come from the frame (the E-step's reach, the
observation spacing, the part's own size).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .point_sets import median_spacing
from .rigid import weighted_rigid_fit

ICP_ITERATIONS = 15


@dataclass
class Recapture:
    """A rigid motion x -> rotation x + shift ((3, 3), (3,)) for the graph nodes `nodes` (n,);
    explained: the share of the part's points it brings within reach of the observations."""

    nodes: np.ndarray
    rotation: np.ndarray
    shift: np.ndarray
    explained: float


def unexplained_clusters(observed: np.ndarray, points: np.ndarray, reach: float, link_spacings: float,
                         min_points: int) -> list:
    """Observations (N, 3) farther than `reach` from every model point (M, 3), split into
    connected pieces (neighbours within `link_spacings` times the observations' median
    spacing); pieces of at least `min_points`."""
    distance, _ = cKDTree(points).query(observed, distance_upper_bound=reach)
    far = observed[~np.isfinite(distance)]
    if len(far) < min_points:
        return []
    # the spacing only here: most frames with a lost part have too few far observations,
    # and it is a k-d tree over the whole frame
    link = link_spacings * median_spacing(observed)
    pairs = cKDTree(far).query_pairs(link, output_type='ndarray')
    adjacency = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(far), len(far)))
    _, labels = connected_components(adjacency, directed=False)
    sizes = np.bincount(labels)
    return [far[labels == c] for c in np.flatnonzero(sizes >= min_points)]


def lost_parts(support: np.ndarray, edges: np.ndarray) -> list:
    """Connected groups of nodes without data, each with the tracked nodes it hangs on.

    support: (J,) in [0, 1], the posterior mass per point a node's points received;
    edges: (E, 2). Returns [(lost nodes (n,), anchor nodes (a,))] for groups with anchors.
    """
    lost = support < 0.1
    if not lost.any():
        return []
    inside = lost[edges[:, 0]] & lost[edges[:, 1]]
    n_nodes = len(support)
    adjacency = sparse.coo_matrix((np.ones(int(inside.sum())), (edges[inside, 0], edges[inside, 1])),
                                  shape=(n_nodes, n_nodes))
    _, labels = connected_components(adjacency, directed=False)
    labels = np.where(lost, labels, -1)
    border = lost[edges[:, 0]] & ~lost[edges[:, 1]]
    parts = []
    for label in np.unique(labels[lost]):       # a loop over lost groups (a few), not points
        nodes = np.flatnonzero(labels == label)
        anchors = np.unique(edges[border & (labels[edges[:, 0]] == label), 1])
        if len(anchors):
            parts.append((nodes, anchors))
    return parts


def _turn(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking direction u onto direction v."""
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    axis = np.cross(u, v)
    s, c = np.linalg.norm(axis), float(np.dot(u, v))
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        # opposite: half a turn about any axis perpendicular to u
        other = np.eye(3)[np.argmin(np.abs(u))]
        axis = np.cross(u, other)
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    axis /= s
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + s * K + (1.0 - c) * K @ K


def rigid_onto(part_points: np.ndarray, target: np.ndarray, pivot: np.ndarray) -> tuple:
    """ICP: (R (3, 3), t (3,)) taking part_points (P, 3) onto target (T, 3), x -> R x + t.

    Started by turning the part about `pivot` so that its direction from there (pivot to
    centroid) points at the target's; then every point of either set is paired with its
    nearest in the other (symmetric ICP: the lost part may be a foot of a whole leg that
    moved, or a whole arm of which the camera sees a forearm) and (R, t) is the Procrustes
    fit of the pairs. The translation is free because the pivot itself may be off (the
    part of a limb left tracked can be wrong too).
    """
    rotation = _turn((part_points - pivot).mean(axis=0), target.mean(axis=0) - pivot)
    shift = pivot - rotation @ pivot
    target_tree = cKDTree(target)
    for _ in range(ICP_ITERATIONS):
        moved = part_points @ rotation.T + shift
        _, to_part = cKDTree(moved).query(target)
        _, to_target = target_tree.query(moved)
        updated, updated_shift = weighted_rigid_fit(np.vstack([part_points[to_part], part_points]),
                                                    np.vstack([target, target[to_target]]))
        converged = np.allclose(updated, rotation, atol=1e-6) and np.allclose(updated_shift, shift, atol=1e-6)
        rotation, shift = updated, updated_shift
        if converged:
            break
    return rotation, shift


def find_recaptures(observed: np.ndarray, points: np.ndarray, node_positions: np.ndarray,
                    support: np.ndarray, edges: np.ndarray, point_nodes: np.ndarray, reach: float) -> list:
    """Lost parts matched with the unexplained observations they can turn onto.

    observed (N, 3); points (M, 3) the registered model; node_positions (J, 3) the nodes
    where the registration put them (g + T); support (J,) as in `lost_parts`; edges (E, 2);
    point_nodes (M,) the node carrying each point most; reach: the E-step's radius (m).
    A match needs the observations to start within the part's reach from its pivot, and
    is kept only if more than half of the moved part lands within `reach` of them (none
    of them was within reach of the model before).
    """
    parts = lost_parts(support, edges)
    if not parts:
        return []
    # a lost part is at least a node's worth of points: smaller pieces are noise
    min_points = max(10, int(len(observed) / max(len(node_positions), 1)))
    clusters = unexplained_clusters(observed, points, reach, 2.5, min_points)
    found = []
    for nodes, anchors in parts:                  # loops over a few parts and clusters
        part_points = points[np.isin(point_nodes, nodes)]
        if len(part_points) < 3:
            continue
        pivot = node_positions[anchors].mean(axis=0)
        extent = float(np.linalg.norm(part_points - pivot, axis=1).max())
        best = None
        for cluster in clusters:
            if np.linalg.norm(cluster - pivot, axis=1).min() > extent + reach:
                continue
            rotation, shift = rigid_onto(part_points, cluster, pivot)
            moved = part_points @ rotation.T + shift
            explained = float(np.mean(cKDTree(cluster).query(moved)[0] <= reach))
            if explained > 0.5 and (best is None or explained > best.explained):
                best = Recapture(nodes, rotation, shift, explained)
        if best is not None:
            found.append(best)
    return found
