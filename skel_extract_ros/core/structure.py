"""Skeletal structure extraction (paper Sec. 5): motion clusters -> bones -> bone tree.

1. K-means on the rest points (on their whole registered trajectories by default, or on
   rest positions), K deliberately larger than the number of bones.
2. `n_rounds` rounds of (i) a rigid fit per cluster and frame (Eq. 9, Kabsch with the det
   correction), (ii) relabelling every point to the bone with the smallest residual over
   the sequence, (iii) local continuity: each point takes the majority label in a ball.
3. Bone graph between clusters that touch, weighted by Eq. (10) (residuals after swapping
   transforms), minimum spanning tree, root = the cluster whose centre is closest to the
   rest pose centre.
4. Refinement (thresholds are fractions of M or of the subject size, so they carry over
   from a hand to a body), repeated until nothing changes:
   - bones with fewer than `min_bone_fraction` of the points are dropped (their points go
     to the bone that fits them best): too few points for a reliable rigid fit;
   - a bone whose motion against its parent the registration's own noise could explain
     is merged into the parent (see "Split evidence" below);
   - paper rule 1: at a joint with several children, a child that is a leaf and holds
     fewer than `leaf_min_fraction` of the points is removed;
   - paper rule 2: loops cannot occur, the graph is a spanning tree rebuilt after each
     change;
   - paper rule 3: two adjacent joints closer than `joint_merge_fraction` of the subject
     size are merged (the short bone between them goes to its parent);
   - last (`min_turn_deg`), once no other rule removes a bone: the joint whose two
     bones turn least against each other over the window (the largest angle between two
     frames' relative rotations, core.rigid.turn_spans) is merged while that turn is under
     the threshold: a cut through a part that sways a few degrees (a torso) is a joint by
     evidence but not one that bends.
5. Initial joint locations c_jk minimise E_Joint (Sec. 6.3, the joint term of Eq. 12a) for
   the fitted transforms:
   eta |c - c~|^2 + sum_t |(R_j^t - R_k^t) c + T_j^t - T_k^t|^2, c~ the centroid of the
   boundary points between the two bones; a 3 x 3 solve per joint.

Split evidence (deviation: the paper merges nothing by motion). Two adjacent clusters are
two bones when two rigid motions explain their points better than one by more than the
registration's noise could. The physical quantity is their relative rotation over the
window, measured on the points: moving each cluster with the other's transform (the swap of
Eq. 10) displaces its points by an RMS `d` per frame, and for clusters turning against each
other by an angle theta about a joint, d ~ theta x r, r the RMS distance of their points from
their centre. The noise is measured on the sequence: `noise`, the RMS residual per point and
frame of every cluster's own rigid fit (median over points: what the registration leaves
when nothing bends; with `evidence_noise: clusters`, the same of the K-means clusters after
the relabelling rounds, measured once: as bones merge, a part that sways a little (a torso
over the legs) leaves its sway in its one rigid fit, and the bones' noise rises with it).
Noise alone turns two clusters against each other by about noise / r, so the evidence for a
joint is the ratio
    split_evidence = (d / r) / (noise / r) = d / noise,
relative rotation over the rotation noise produces at that size: scale-free, so the same
`motion_noise_factor` serves a hand, a body and a cow. The bone with the least evidence is
merged first, one at a time, until every joint has evidence >= motion_noise_factor. The
relative rotation is measured through the points rather than as the angle between fitted
rotations because the turn of a thin part about its own axis barely moves its points and
is barely determined by them (the fitted angle can show a 180 degree "bend" between the
halves of a rigid forearm).

The two thresholds work together. The noise is measured on the current bones, so merging a
part that sways (a torso over the legs) raises it and lowers every other joint's evidence:
near the threshold one merge pulls a bending wrist under it. The evidence threshold
therefore sits low enough to keep such joints, and the least turn (`min_turn_deg`, an angle:
the same for a hand, a body and a cow) then removes the cuts through parts that do not bend,
which a low threshold lets through. What the least turn merges is a part that moves, a few
degrees, not one the registration failed to fit: its sway left in the merged bone's rigid fit
is motion, not registration noise. So by default (`evidence_noise: until_turn`) the noise is
measured on the current bones until the least turn merges its first joint and held from
then on; measured after each of those merges (`bones`), it grows with them and pulls
joints that bend under the threshold.

Joint locations and anchors: core/joint_centres.py.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.cluster.vq import kmeans2
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.spatial import cKDTree

from .joint_centres import (PivotEvidence, boundary_centroids, joint_trajectories, medial_anchors, pivot_evidence,
                             solve_joints)
from .parameters import INF, parameter, validate
from .point_sets import median_spacing
from .rigid import fit_rigid_segments, segment_matrix, turn_spans


class StructureError(ValueError):
    """The sequence cannot give a skeleton (e.g. no motion separates any bones)."""


@dataclass
class StructureParams:
    """Parameters of the skeletal structure extraction (the refinement thresholds are
    fractions of the points or of the subject size: the module docstring)."""

    n_clusters: int = parameter(60, 'initial K-means clusters (deliberately more than the bones: each true '
                                'boundary needs a cluster boundary near it before the evidence merges the rest)',
                                2, 10_000)
    cluster_on: str = parameter('trajectories', "K-means features: trajectories (each point's whole registered "
                                'path) or rest (rest positions)', choices=('trajectories', 'rest'))
    n_rounds: int = parameter(10, 'rounds of rigid fit / relabel / local continuity (paper: 10)', 0, 1000)
    neighbour_radius: float | None = parameter(None, 'ball radius for local continuity and bone adjacency, m; '
                                               '0 = automatic (neighbour_radius_factor)', 0.0, INF)
    neighbour_radius_factor: float = parameter(2.5, 'automatic radius = this x the median rest point spacing, '
                                               'dimensionless', 0.1, 100.0)
    min_bone_fraction: float = parameter(0.01, 'bones holding less than this fraction of the points are dropped',
                                         0.0, 1.0)
    motion_noise_factor: float = parameter(4.0, 'evidence a joint needs: its relative rotation over the window '
                                           'over the rotation the registration noise alone makes (swap '
                                           'displacement / rigid-fit noise); below it the bone is merged into its '
                                           'parent, dimensionless', 0.0, INF)
    leaf_min_fraction: float = parameter(0.02, 'paper rule 1: leaf bones at branching joints below this share of '
                                         'the points are dropped, a fraction', 0.0, 1.0)
    joint_merge_fraction: float = parameter(0.03, 'paper rule 3: joints closer than this x the subject size are '
                                            'merged, a fraction', 0.0, 1.0)
    evidence_noise: str = parameter('until_turn', 'the noise the split evidence divides by: until_turn (the '
                                    "current bones' rigid-fit residual, again at each refinement pass until "
                                    'the least turn merges a joint, then held: the sway it merges is motion), '
                                    "bones (the same at every pass) or clusters (the K-means clusters' after "
                                    'the relabelling rounds, once: small parts, nearly rigid)',
                                    choices=('until_turn', 'bones', 'clusters'))
    min_turn_deg: float = parameter(15.0, 'once the other rules keep every bone, a joint whose two bones turn '
                                    'against each other by less than this over the window is merged, the least '
                                    'turn first (0 = off), degrees', 0.0, 180.0)
    eta: float = parameter(1.0, 'weight of the joint data term in the Step 2 joint solve (Table 1), '
                           'dimensionless', 0.0, INF)
    max_key_frames: int = parameter(90, 'the growing skeleton is learned from at most this many frames, the most '
                                    'different poses seen so far', 2, 100_000)
    joint_match_fraction: float = parameter(0.05, 'joints of two updates closer than this x the subject size are '
                                            'the same joint (keep id and name), a fraction', above=0.0, below=1.0)
    anchor_depth: str = parameter('medial', "joint anchors c~: medial (moved back along the camera ray to the "
                                  "bone's cross-section centre) or surface (the paper's boundary centroid)",
                                  choices=('medial', 'surface'))
    camera_location: tuple = parameter((0.0, 0.0, 0.0), '[x, y, z] m, the sensor origin in the cloud frame '
                                       '(camera rays for medial anchors)', size=3)
    seed: int = parameter(0, 'K-means seed', 0, 2**31 - 1)

    def __post_init__(self):
        validate(self)


@dataclass
class SkeletalStructure:
    """Bones and bone tree of a registered sequence.

    labels: (M,) bone of each rest point; parents: (B,) parent bone (-1 for the root);
    rotations (F, B, 3, 3) and translations (F, B, 3): bone transforms, rest -> frame;
    joints: (B, 3) rest-frame joint between each bone and its parent (for the root: its
    centre); boundary_centroids: (B, 3) the anchor c~ of each joint (root: its centre),
    moved to the medial depth unless anchor_depth is 'surface'; split_evidence: (B,) the
    evidence for each joint (module docstring; inf for the root); anchor_spread: (B,) m, how
    far from its anchor the bone boundary alone leaves each joint (joint_centres.
    boundary_centroids; None: not known, e.g. a structure from an older message); depth_rays:
    (B, 3) the unit camera ray of each anchor whose depth its cross-section measured (zero
    rows: not measured; None: surface anchors or not known), along which Alg. 2 takes the
    joint's depth from the anchor (joint_centres.solve_joints, JointParams.joint_depth).
    """

    labels: np.ndarray
    parents: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    joints: np.ndarray
    boundary_centroids: np.ndarray
    split_evidence: np.ndarray | None = None
    anchor_spread: np.ndarray | None = None
    depth_rays: np.ndarray | None = None

    @property
    def n_bones(self) -> int:
        return len(self.parents)

    @property
    def root(self) -> int:
        return int(np.flatnonzero(self.parents < 0)[0])

    def joint_trajectories(self) -> np.ndarray:
        """(F, B, 3) joint positions per frame (metres)."""
        return joint_trajectories(self.rotations, self.translations, self.joints, self.parents)

    def pivot_evidence(self, joints: np.ndarray | None = None) -> PivotEvidence | None:
        """How far these bones' rigid fits fixed joints (B, 3) (default: Step 2's), see
        joint_centres.pivot_evidence; None without anchor_spread."""
        if self.anchor_spread is None:
            return None
        return pivot_evidence(self.rotations, self.translations, self.parents,
                              self.joints if joints is None else joints, self.anchor_spread)


def _neighbour_graph(rest: np.ndarray, radius: float) -> sparse.csr_matrix:
    """(M, M) symmetric 0/1 adjacency of points within `radius`, with the diagonal."""
    pairs = cKDTree(rest).query_pairs(radius, output_type='ndarray')
    M = len(rest)
    rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(M)])
    cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(M)])
    return sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(M, M))


def _compact(labels: np.ndarray) -> np.ndarray:
    return np.unique(labels, return_inverse=True)[1].ravel()


def _residuals(rest, registered, rotations, translations) -> np.ndarray:
    """(M, S) sum over frames of |y_m^t - (R_s^t q_m + T_s^t)|^2 (m^2).

    Expanded into sums over frames that are matrix products, instead of forming the
    (F, S, M, 3) predictions, which would be most of Step 2's time:
    sum_t |y|^2 + F |q|^2 + sum_t |T_s|^2 - 2 q . sum_t R_s^T y - 2 sum_t y . T_s
    + 2 q . sum_t R_s^T T_s. The terms are O(1 m^2) and the residuals ~1e-4 m^2, far
    above float64 cancellation (~1e-13 m^2).
    """
    F, M, _ = registered.shape
    S = rotations.shape[1]
    trajectories = registered.transpose(1, 0, 2).reshape(M, F * 3)             # (M, 3F)
    rotated = trajectories @ rotations.transpose(0, 2, 1, 3).reshape(F * 3, S * 3)   # sum_t y^T R_s
    cross_rotation = np.einsum('msj,mj->ms', rotated.reshape(M, S, 3), rest)
    cross_translation = trajectories @ translations.transpose(0, 2, 1).reshape(F * 3, S)
    carried = np.einsum('tsij,tsi->sj', rotations, translations)               # sum_t R_s^T T_s
    residual = (np.sum(registered ** 2, axis=(0, 2))[:, None] + F * np.sum(rest ** 2, axis=1)[:, None]
                + np.sum(translations ** 2, axis=(0, 2))[None, :] - 2.0 * cross_rotation
                - 2.0 * cross_translation + 2.0 * rest @ carried.T)
    return np.maximum(residual, 0.0)


def _majority(labels: np.ndarray, adjacency: sparse.csr_matrix, n_labels: int) -> np.ndarray:
    """Each point's most frequent label within its ball (itself included)."""
    # (M, n_labels) dense: a few dozen labels; scipy's sparse argmax loops over rows in Python
    counts = (adjacency @ segment_matrix(labels, n_labels).T).toarray()
    return counts.argmax(axis=1)


def _mean_residual(residual: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(B, B): entry (i, j) is the mean over the points of bone i of their residual under
    bone j's transforms (the halves of Eq. 10)."""
    summer = segment_matrix(labels, residual.shape[1])
    counts = np.maximum(np.asarray(summer.sum(axis=1)).ravel(), 1)
    return (summer @ residual) / counts[:, None]


def _bone_tree(labels, residual, adjacency, rest):
    """MST over touching clusters with Eq. (10) weights; returns parents (B,)."""
    B = residual.shape[1]
    summer = segment_matrix(labels, B)
    counts = np.asarray(summer.sum(axis=1)).ravel()
    mean_residual = _mean_residual(residual, labels)
    weights = mean_residual + mean_residual.T                                  # Eq. (10)
    touching = (summer @ adjacency @ summer.T).toarray() > 0
    # Bones that do not touch can only be joined if the touching graph is disconnected:
    # a large offset keeps them out of the tree otherwise.
    offset = 1.0 + 10.0 * weights.max()
    graph = np.where(touching, weights, weights + offset)
    np.fill_diagonal(graph, 0.0)
    tree = minimum_spanning_tree(sparse.csr_matrix(graph + 1e-12 * (1 - np.eye(B)))).toarray()
    tree = (tree + tree.T) > 0
    centres = (summer @ rest) / np.maximum(counts, 1)[:, None]
    root = int(np.argmin(np.linalg.norm(centres - rest.mean(axis=0), axis=1)))
    order, predecessors = breadth_first_order(sparse.csr_matrix(tree), root, directed=False)
    parents = np.where(predecessors < 0, -1, predecessors)
    parents[root] = -1
    return parents


def _own_motion(residual: np.ndarray, labels: np.ndarray, parents: np.ndarray, n_frames: int) -> np.ndarray:
    """(B,) RMS displacement (m) per frame of bone b's points and its parent's when each is
    moved with the other's transform (the symmetric swap of Eq. 10); inf for the root."""
    B = len(parents)
    mean_residual = _mean_residual(residual, labels)
    result = np.full(B, np.inf)
    child = np.flatnonzero(parents >= 0)
    result[child] = np.sqrt((mean_residual[child, parents[child]] + mean_residual[parents[child], child])
                            / (2.0 * n_frames))
    return result


def rigid_fit_noise(residual: np.ndarray, labels: np.ndarray, n_frames: int, size: float = 1.0) -> float:
    """m: the median over the points of the RMS residual per frame of their own bone's rigid
    fit (residual (M, B) as _residuals; labels (M,)). size: the subject's size (m), for the
    floor: 1e-6 of it is float64 round-off in the expanded residuals, not registration
    noise (an exactly rigid sequence)."""
    own = residual[np.arange(len(labels)), labels]
    return max(np.sqrt(float(np.median(own)) / n_frames), 1e-6 * size)


def split_evidence(residual: np.ndarray, labels: np.ndarray, parents: np.ndarray, n_frames: int,
                   size: float = 1.0, noise: float | None = None) -> np.ndarray:
    """(B,) for each bone, its relative rotation against its parent over the window in units
    of the rotation the registration noise produces (module docstring, "Split evidence"):
    the swap displacement (`_own_motion`) over `noise` (m; None: `rigid_fit_noise` of these
    bones). inf for the root. residual (M, B) as _residuals; size: the subject's size (m)."""
    if noise is None:
        noise = rigid_fit_noise(residual, labels, n_frames, size)
    return _own_motion(residual, labels, parents, n_frames) / noise


def _refit_receivers(rest, registered, labels, removed: int, receivers: np.ndarray, rotations, translations,
                     residual) -> tuple:
    """The bones' rigid fits and residuals (as fit_rigid_segments and _residuals) once bone
    `removed` has handed its points to `receivers` (labels (M,): the new labels, before
    compacting): only the receivers' fits change, every other bone keeps its points, so
    only theirs are fitted again (a refinement pass costs a few bones, not all of them)."""
    rotations, translations = np.delete(rotations, removed, axis=1), np.delete(translations, removed, axis=1)
    residual = np.delete(residual, removed, axis=1)
    changed = receivers - (receivers > removed)                         # their indices once compacted
    points = np.isin(labels, receivers)
    local = np.searchsorted(receivers, labels[points])
    changed_rotations, changed_translations = fit_rigid_segments(rest[points], registered[:, points], local,
                                                                 len(receivers))
    rotations[:, changed], translations[:, changed] = changed_rotations, changed_translations
    residual[:, changed] = _residuals(rest, registered, changed_rotations, changed_translations)
    return rotations, translations, residual


def _anchors(labels, parents, adjacency, rest, params: 'StructureParams') -> tuple:
    """The joint anchors c~ (B, 3) as the parameters ask for, their spread (B,) m, and the
    camera rays (B, 3) of those whose depth a section measured (medial_anchors; None for
    surface anchors)."""
    anchors, spread = boundary_centroids(labels, parents, adjacency, rest)
    rays = None
    if params.anchor_depth == 'medial':
        anchors, rays = medial_anchors(labels, parents, rest, anchors, params.camera_location)
    return anchors, spread, rays


def extract_structure(rest: np.ndarray, registered: np.ndarray, params: StructureParams | None = None,
                      previous_labels: np.ndarray | None = None) -> SkeletalStructure:
    """Bones and bone tree from rest points (M, 3) and their registered sequence (F, M, 3).

    previous_labels (M,): the bones of an earlier structure of the same rest pose (a growing
    skeleton): the K-means clusters are cut along its bone boundaries too, so a boundary
    found before is a candidate again (kept if the evidence still holds), instead of
    depending on where this run's K-means happens to put its clusters."""
    params = params or StructureParams()
    rest = np.asarray(rest, dtype=np.float64)
    registered = np.asarray(registered, dtype=np.float64)
    registered = registered[np.isfinite(registered).all(axis=(1, 2))]
    if len(registered) < 2:
        raise StructureError('fewer than 2 registered frames: no motion to separate bones')
    M = len(rest)
    size = float(np.linalg.norm(np.ptp(rest, axis=0)))
    spacing = median_spacing(rest)
    radius = params.neighbour_radius or params.neighbour_radius_factor * spacing
    adjacency = _neighbour_graph(rest, radius)

    features = rest if params.cluster_on == 'rest' else registered.transpose(1, 0, 2).reshape(M, -1)
    K = min(params.n_clusters, M // 10)
    rng = np.random.default_rng(params.seed)
    _, labels = kmeans2(features, K, minit='++', seed=rng)
    if previous_labels is not None:
        previous_labels = np.asarray(previous_labels, dtype=np.int64)
        if previous_labels.shape != (M,):
            raise ValueError(f'previous_labels must be ({M},), got {previous_labels.shape}')
        labels = labels * (previous_labels.max() + 1) + previous_labels
    labels = _compact(labels)

    for _ in range(params.n_rounds):
        S = labels.max() + 1
        rotations, translations = fit_rigid_segments(rest, registered, labels, S)
        residual = _residuals(rest, registered, rotations, translations)
        labels = _compact(np.argmin(residual, axis=1))
        labels = _compact(_majority(labels, adjacency, labels.max() + 1))

    held_noise = None       # the noise the evidence divides by once held (None: the current bones')
    rotations, translations = fit_rigid_segments(rest, registered, labels, labels.max() + 1)
    residual = _residuals(rest, registered, rotations, translations)
    for _ in range(4 * K):  # refinement until stable; each pass removes one bone at most
        B = labels.max() + 1
        if params.evidence_noise == 'clusters' and held_noise is None:
            # the first pass fits the clusters the relabelling rounds left
            held_noise = rigid_fit_noise(residual, labels, len(registered), size)
        if B == 1:
            parents = np.array([-1])
            break
        parents = _bone_tree(labels, residual, adjacency, rest)
        counts = np.bincount(labels, minlength=B)
        remove = None
        small = np.flatnonzero(counts < params.min_bone_fraction * M)
        if len(small):
            remove = int(small[np.argmin(counts[small])])
        evidence = split_evidence(residual, labels, parents, len(registered), size, held_noise)
        if remove is None:
            still = np.flatnonzero(evidence < params.motion_noise_factor)
            if len(still):
                remove = int(still[np.argmin(evidence[still])])
        if remove is None:
            children = np.bincount(parents[parents >= 0], minlength=B)
            for b in np.flatnonzero(parents >= 0):
                if children[b] == 0 and children[parents[b]] > 1 and counts[b] < params.leaf_min_fraction * M:
                    remove = int(b)
                    break
        if remove is None:
            anchors = _anchors(labels, parents, adjacency, rest, params)[0]
            joints = solve_joints(rotations, translations, parents, anchors, params.eta)
            for b in np.flatnonzero(parents >= 0):
                p = parents[b]
                if parents[p] >= 0 and np.linalg.norm(joints[b] - joints[p]) < params.joint_merge_fraction * size:
                    remove = int(p)   # the short bone between the two joints
                    break
        if remove is None and params.min_turn_deg > 0:
            # last, on the bones every other rule keeps: during the refinement a joint's turn
            # is shared by the small bones across it, each turning less than the joint
            turns = np.where(parents >= 0, turn_spans(rotations, parents), np.inf)
            if turns.min() < params.min_turn_deg:
                remove = int(np.argmin(turns))
                if params.evidence_noise == 'until_turn' and held_noise is None:
                    held_noise = rigid_fit_noise(residual, labels, len(registered), size)
        if remove is None:
            break
        # hand the removed bone's points to the remaining bone that fits each best
        keep = np.flatnonzero(np.arange(B) != remove)
        moved = labels == remove
        labels[moved] = keep[np.argmin(residual[moved][:, keep], axis=1)]
        rotations, translations, residual = _refit_receivers(rest, registered, labels, remove, np.unique(labels[moved]),
                                                             rotations, translations, residual)
        labels = _compact(labels)

    B = labels.max() + 1
    if B < 2:
        raise StructureError('the motion is too small to separate any bones: every part '
                             'of the subject moves rigidly together')
    anchors, spread, rays = _anchors(labels, parents, adjacency, rest, params)
    joints = solve_joints(rotations, translations, parents, anchors, params.eta)
    return SkeletalStructure(labels, parents, rotations, translations, joints, anchors, evidence, spread, rays)
