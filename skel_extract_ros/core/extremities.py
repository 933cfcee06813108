"""Geodesic extremities of a point set: the far ends of its limbs (hands, feet, head, a tail),
found without a template as the accumulative geodesic extrema of its neighbour graph (AGEX:
Plagemann et al., "Real-time identification and localization of body parts from depth
images", ICRA 2010), and matched between the model and a frame (`match_extremities`).

Why geodesic: along the surface a hand stays about as far from the chest whatever the arm
does, while in space it does not; the far ends of the surface's geodesic paths from the body's
centre are the limbs' ends in any pose, so they can be found in each frame's own points and
told apart from the model's by their geodesic depth, with no template and no training.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from .matching import min_cost_assignment


@dataclass
class Extremities:
    """The extremities of one point set (N, 3).

    tips (K,): indices of the tip points, in the order AGEX found them; depth (K,) m: each
    tip's geodesic distance from the centre; regions: K index arrays, each tip's end cap (the
    limb's end, whose centroid is matched: a single tip point is as noisy as one
    observation); centroids (K, 3) m: theirs; limbs (K, N) bool: the points within
    limb_fraction x the tip's depth of it along the surface (the limb the end is on);
    spacing m: the set's median distance to the nearest other point, so a region's surface
    is about its point count x spacing^2 whatever the set's density (`areas`).
    """

    tips: np.ndarray
    depth: np.ndarray
    regions: list
    centroids: np.ndarray
    limbs: np.ndarray
    spacing: float

    @property
    def areas(self) -> np.ndarray:
        """(K,) m^2: each end cap's surface, its points times the spacing squared."""
        return np.array([len(region) for region in self.regions], dtype=np.float64) * self.spacing ** 2

    def __len__(self) -> int:
        return len(self.tips)


def neighbour_graph(points: np.ndarray, neighbours: int = 8, max_edge_spacings: float = 3.0) -> tuple:
    """(N, N) sparse symmetric graph of each point (N, 3) to its nearest neighbours, edge
    weights their distances (m), and the set's spacing (m: the median distance to the nearest
    other point, as point_sets.median_spacing); edges longer than max_edge_spacings x the
    spacing are left out, so a gap in the surface (one leg in front of the other, a hand off
    the hip) is not bridged."""
    count = min(neighbours + 1, len(points))
    distances, indices = cKDTree(points).query(points, k=count)
    spacing = float(np.median(distances[:, 1]))
    rows = np.repeat(np.arange(len(points)), count - 1)
    distances, indices = distances[:, 1:].ravel(), indices[:, 1:].ravel()
    keep = np.isfinite(distances) & (distances <= max_edge_spacings * spacing) & (distances > 0)
    graph = coo_matrix((distances[keep], (rows[keep], indices[keep])), shape=(len(points), len(points))).tocsr()
    return graph.maximum(graph.T), spacing


def find_extremities(points: np.ndarray, centre: int, cap_fraction: float = 0.1,
                     min_branch_fraction: float = 0.6, max_tips: int = 8, limb_fraction: float = 0.3,
                     max_width: float = 0.6) -> Extremities:
    """AGEX on points (N, 3) m from the point index `centre`: the first tip is the point
    geodesically farthest from the centre; each next one is the farthest from the centre and
    the tips found so far, as long as that branch is at least min_branch_fraction x the first
    (scale-free: the same fraction finds a person's limbs and a hand's fingers); at most
    max_tips. Each tip's region is its limb's end cap: the points of its branch (within twice
    the cap of the tip) no more than cap_fraction x the tip's depth nearer the centre than
    the tip. A level set of the distance from the centre, not a ball around the tip point: on
    a blunt end (a head, a fist) the farthest point wanders over the end from frame to frame,
    the cap does not. Points not connected to the centre are never tips.

    Only slender tips are kept: the limb's section between 2/3 and 1 x limb_fraction x the
    tip's depth from it along the surface (20-30 %) is at most max_width x its mean distance
    from the tip across (twice its points' RMS distance from their centroid). A hand, a foot
    or a head ends a limb much longer than it is wide; a corner of a box-like trunk, a bump on
    the torso or two hands held together does not, and where its farthest point lies depends
    on what hides it, so it is no landmark."""
    points = np.asarray(points, dtype=np.float64)
    graph, spacing = neighbour_graph(points)
    from_centre = dijkstra(graph, directed=False, indices=int(centre))
    nearest = from_centre.copy()
    tips = []
    first = None
    for _ in range(max_tips):
        reachable = np.isfinite(nearest)
        if not reachable.any():
            break
        tip = int(np.flatnonzero(reachable)[np.argmax(nearest[reachable])])
        branch = nearest[tip]
        if first is None:
            first = branch
        if branch <= 0.0 or branch < min_branch_fraction * first:
            break
        tips.append(tip)
        # only paths shorter than this branch can lower the distances that choose the next tip
        nearest = np.minimum(nearest, dijkstra(graph, directed=False, indices=tip, limit=branch))
    tips = np.array(tips, dtype=np.int64)
    if len(tips) == 0:
        return Extremities(tips, np.zeros(0), [], np.zeros((0, 3)), np.zeros((0, len(points)), dtype=bool), spacing)
    depth = from_centre[tips]
    caps = cap_fraction * depth
    limbs = limb_fraction * depth
    around = np.atleast_2d(dijkstra(graph, directed=False, indices=tips, limit=max(2.0 * caps.max(), limbs.max())))
    slender = np.zeros(len(tips), dtype=bool)
    for k, row in enumerate(around):   # a few tips
        inner, outer = 2.0 / 3.0 * limbs[k], limbs[k]
        section = points[(row >= inner) & (row <= outer)]
        if len(section) >= 3:
            width = 2.0 * np.sqrt(np.mean(np.sum((section - section.mean(axis=0)) ** 2, axis=1)))
            slender[k] = width <= max_width * 0.5 * (inner + outer)
    tips, depth, caps, limbs, around = tips[slender], depth[slender], caps[slender], limbs[slender], around[slender]
    regions = [np.flatnonzero((row <= 2.0 * cap) & (from_centre >= from_centre[tip] - cap))
               for row, tip, cap in zip(around, tips, caps)]
    centroids = np.array([points[region].mean(axis=0) for region in regions]).reshape(-1, 3)
    return Extremities(tips, depth, regions, centroids, around <= limbs[:, None], spacing)


def match_extremities(model: Extremities, model_points: np.ndarray, observed: Extremities, reach,
                      depth_tolerance: float = 0.15, size_ratio: float = 2.0, distinct: float = 1.5) -> list:
    """Pairs (model tip k, observed tip l): one to one, the nearest in space first (Hungarian
    on the distance between the model's end centroids where the frame starts its points,
    model_points (M, 3) m, and the observed ones), among the pairs that are the same limb's
    end by four tests:
    - their geodesic depths agree to depth_tolerance x the model's;
    - their centroids are within reach (m, a scalar or (K,)) of each other: the reach keeps a
      still foot from taking the other, swinging one;
    - the model point nearest the observed end is on the model end's own limb (`limbs`): an
      end the frame left behind (a forearm swung away faster than EM follows) is not pulled
      onto another part's end that its own points already explain;
    - their regions' surfaces (`areas`: point counts times each set's spacing squared, so a
      frame sampled more densely than the rest points, a subject near the camera, compares
      alike) agree to a factor size_ratio: an end the model's own frame saw cut short (a hand
      out of view, edge-on or hidden there) is not the end a frame sees whole, and pulling
      one onto the other stretches the limb.
    And a pair is kept only when every other model end is at least `distinct` x farther from
    the observed end than its partner (gated or not): two hands that meet, or a foot passing
    the other, are not told apart by where they are, and one wrong pull glues a limb to
    the other.
    A tip the frame lost (a hand on the hip, a foot behind the other leg) has no partner and
    pulls nothing."""
    if len(model) == 0 or len(observed) == 0:
        return []
    centroids = np.array([model_points[region].mean(axis=0) for region in model.regions])
    distance = np.linalg.norm(centroids[:, None, :] - observed.centroids[None, :, :], axis=2)
    nearest_point = np.argmin(np.linalg.norm(model_points[None, :, :] - observed.centroids[:, None, :], axis=2), axis=1)
    reach = np.broadcast_to(np.asarray(reach, dtype=np.float64), model.depth.shape)
    ratio = observed.areas[None, :] / np.maximum(model.areas[:, None], 1e-12)
    allowed = (np.abs(observed.depth[None, :] - model.depth[:, None]) <= depth_tolerance * model.depth[:, None]) \
        & (distance <= reach[:, None]) & model.limbs[:, nearest_point] \
        & (ratio <= size_ratio) & (ratio >= 1.0 / size_ratio)
    if not allowed.any():
        return []
    cost = np.where(allowed, distance, 1e6 + distance)
    rows, columns = min_cost_assignment(cost)
    pairs = []
    for k, l in zip(rows, columns):   # a few ends
        others = np.delete(distance[:, l], k)
        if allowed[k, l] and (len(others) == 0 or others.min() >= distinct * distance[k, l]):
            pairs.append((int(k), int(l)))
    return pairs
