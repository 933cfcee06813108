"""Where the joints are: E_Joint's solve for the joint locations c_jk (paper Sec. 6.3, the
joint term of Eq. 12a), their anchors c~ (the boundary between two bones, moved to the
bone's cross-section centre), each joint carried through the frames by its two bones, and
how far the motion fixed each joint (`pivot_evidence`).

Deviation (anchor_depth='medial', the default): one depth camera sees only the front of
each limb, so the boundary centroid c~ lies on the visible surface, about a limb radius in
front of the joint, and wherever the motion leaves a joint's depth unconstrained (a hinge
whose axis points at the camera, a root bone's centre) E_Joint puts the joint there too.
`medial_anchors` moves each c~ back along its camera ray to the depth of the bone's
cross-section centre, fitted to the visible half of that cross-section (see there). The
paper's plain centroid is anchor_depth='surface'.

Deviation (JointParams.joint_depth='anchor', the default): where a section gave an anchor
its depth, Alg. 2's E_Joint places the joint only across that camera ray and takes its
depth from the anchor (`solve_joints`' depth_rays). The registered points of a limb that
turns stay on its visible side, so the pivot the bones' fitted motion gives lies in front
of the joint; 'motion' is the paper's solve in all three directions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rigid import segment_matrix


def joint_trajectories(rotations, translations, joints, parents) -> np.ndarray:
    """(F, B, 3) per-frame joints: each joint (B, 3) carried by the mean of its bone's and its
    parent bone's transforms (the root joint by the root bone)."""
    own = np.einsum('fbij,bj->fbi', rotations, joints) + translations
    parent_of = np.where(parents < 0, np.arange(len(parents)), parents)
    by_parent = np.einsum('fbij,bj->fbi', rotations[:, parent_of], joints) + translations[:, parent_of]
    return 0.5 * (own + by_parent)


def relative_motion(rotations, translations, parents) -> tuple:
    """Each non-root bone b against its parent p, the terms of E_Joint's kinematic part
    |D_t c + dT_t|^2: child (E,) the bones b, D (F, E, 3, 3) = R_p^t - R_b^t and
    dT (F, E, 3) = T_p^t - T_b^t."""
    child = np.flatnonzero(parents >= 0)
    parent = parents[child]
    return child, rotations[:, parent] - rotations[:, child], translations[:, parent] - translations[:, child]


def solve_joints(rotations, translations, parents, anchors, eta: float,
                 depth_rays: np.ndarray | None = None) -> np.ndarray:
    """(B, 3) rest-frame joints minimising E_Joint (Eq. 12a's joint term) for each bone and
    its parent, with the bone transforms fixed: setting its gradient in c to zero gives

    (eta I + sum_t D_t^T D_t) c = eta c~ - sum_t D_t^T (T_p - T_b), D_t = R_p^t - R_b^t.
    Root rows return their anchor.

    depth_rays (B, 3): for a joint with a unit row, its depth along that camera ray is its
    anchor's (`medial_anchors`' section centre) and E_Joint places it only across the ray,
    c = c~ + P w with P (3, 2) an orthonormal basis across the ray: (eta I + sum_t P^T D_t^T
    D_t P) w = -sum_t P^T D_t^T (D_t c~ + T_p - T_b). A zero row: all three directions.
    """
    joints = anchors.copy()
    child, D, dT = relative_motion(rotations, translations, parents)
    if len(child) == 0:
        return joints
    A = eta * np.eye(3) + np.einsum('feji,fejk->eik', D, D)
    b = eta * anchors[child] - np.einsum('feji,fej->ei', D, dT)
    joints[child] = np.linalg.solve(A, b[..., None])[..., 0]
    if depth_rays is None:
        return joints
    rays = np.asarray(depth_rays, dtype=np.float64)[child]
    across = np.linalg.norm(rays, axis=1) > 0.5
    if not across.any():
        return joints
    edges, rays = np.flatnonzero(across), rays[across]
    basis = _across(rays)                                                        # (E', 3, 2)
    D_across = np.einsum('feij,ejk->feik', D[:, edges], basis)                   # (F, E', 3, 2)
    at_anchor = np.einsum('feij,ej->fei', D[:, edges], anchors[child[edges]]) + dT[:, edges]
    A = eta * np.eye(2) + np.einsum('feji,fejk->eik', D_across, D_across)
    b = -np.einsum('feji,fej->ei', D_across, at_anchor)
    w = np.linalg.solve(A, b[..., None])[..., 0]
    joints[child[edges]] = anchors[child[edges]] + np.einsum('eij,ej->ei', basis, w)
    return joints


def _across(rays: np.ndarray) -> np.ndarray:
    """(E, 3, 2) orthonormal bases of the planes across unit rays (E, 3)."""
    helper = np.where(np.abs(rays[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    first = np.cross(rays, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return np.stack([first, np.cross(rays, first)], axis=2)


def boundary_centroids(labels, parents, adjacency, rest) -> tuple:
    """The anchors c~ (B, 3): the centroid of the points of bone b or of its parent that
    touch the other one (the root gets its own centre), and their spread (B,) m: the RMS
    distance of those points from it (the root: of its bone's points), how far from c~ the
    boundary alone leaves the joint."""
    B = len(parents)
    summer = segment_matrix(labels, B)
    touches = (adjacency @ summer.T).tocsr()                                    # (M, B) neighbours per bone
    counts = np.maximum(np.asarray(summer.sum(axis=1)).ravel(), 1)
    centres = (summer @ rest) / counts[:, None]
    spread = np.sqrt(np.maximum((summer @ np.sum(rest ** 2, axis=1)) / counts - np.sum(centres ** 2, axis=1), 0.0))
    result = centres.copy()
    for b in np.flatnonzero(parents >= 0):  # loop over bones, not points
        p = parents[b]
        on_boundary = ((labels == b) & (touches[:, p].toarray().ravel() > 0)) | \
                      ((labels == p) & (touches[:, b].toarray().ravel() > 0))
        if on_boundary.any():
            boundary = rest[on_boundary]
            result[b] = boundary.mean(axis=0)
            spread[b] = np.sqrt(np.mean(np.sum((boundary - result[b]) ** 2, axis=1)))
        else:
            result[b] = 0.5 * (centres[b] + centres[p])
            spread[b] = 0.5 * np.linalg.norm(centres[b] - centres[p])
    return result, spread


@dataclass
class PivotEvidence:
    """How far the two bones' own motion fixed each joint's pivot, per joint (B,); the
    root's rows are NaN / 0 (its joint is the root bone's centre, not a pivot).

    residual_m: RMS over frames of the pivot gap |(R_p^t - R_b^t) c + T_p^t - T_b^t| at the
    joint c under the bones' unconstrained rigid fits (E_Joint's kinematic term, Eq. 12a),
    m; fixed_directions: in how many of the 3 directions the motion pins c down better than
    the anchor does (3: a ball joint that turned in several planes; 2: a hinge, free along
    its axis; 0: a cut through a part that did not bend); confidence in [0, 1]: the share
    of the anchor's uncertainty the motion removed, averaged over the 3 directions (a hinge
    at most 2/3). `fixed`: at least 2 directions.
    """

    residual_m: np.ndarray
    fixed_directions: np.ndarray
    confidence: np.ndarray

    @property
    def fixed(self) -> np.ndarray:
        """(B,) bool: the motion fixed the pivot across the joint's axis (a ball joint or a
        hinge); False for the root."""
        return self.fixed_directions >= 2


def pivot_evidence(rotations, translations, parents, joints, anchor_spread) -> PivotEvidence:
    """The pivot evidence of joints (B, 3) under rigid fits rotations (F, B, 3, 3) and
    translations (F, B, 3), with anchor spreads (B,) m (boundary_centroids).

    E_Joint's kinematic term is a least-squares estimate of c: with D_t = R_p^t - R_b^t and
    A = sum_t D_t^T D_t (eigenvalues lambda_i), the motion alone fixes c along eigenvector i
    to a variance s_n^2 / lambda_i, s_n^2 the per-axis pivot noise (residual_m^2 / 3,
    measured on the sequence); the anchor fixes it to s_a^2 (anchor_spread^2). Independent
    rotation noise of each fit also makes A: about 2 F theta_n^2 per direction with
    theta_n = s_n / s_a, the pivot noise over the lever it acts on; that much is taken off
    each lambda_i first, so a part cut in two, whose D_t are noise alone, fixes nothing.
    Direction i is fixed when the rest, lambda_i', exceeds s_n^2 / s_a^2, and the
    confidence is the mean of lambda_i' / (lambda_i' + s_n^2 / s_a^2).
    """
    B = len(parents)
    residual = np.full(B, np.nan)
    fixed = np.zeros(B, dtype=np.int64)
    confidence = np.full(B, np.nan)
    child, D, dT = relative_motion(rotations, translations, parents)
    if len(child) == 0:
        return PivotEvidence(residual, fixed, confidence)
    F = len(rotations)
    gap = np.einsum('feij,ej->fei', D, joints[child]) + dT
    residual[child] = np.sqrt(np.mean(np.sum(gap ** 2, axis=2), axis=0))
    spread = np.maximum(np.asarray(anchor_spread, dtype=np.float64)[child], 1e-9)
    # a perfect fit (synthetic data) still needs a noise scale: a micrometre per metre of spread
    noise2 = np.maximum(residual[child] ** 2 / 3.0, (1e-6 * spread) ** 2)
    eta = noise2 / spread ** 2                                                   # s_n^2 / s_a^2
    lam = np.linalg.eigvalsh(np.einsum('feji,fejk->eik', D, D))                  # (E, 3)
    informative = np.maximum(lam - 2.0 * F * eta[:, None], 0.0)
    fixed[child] = np.sum(informative > eta[:, None], axis=1)
    confidence[child] = np.mean(informative / (informative + eta[:, None]), axis=1)
    return PivotEvidence(residual, fixed, confidence)


def medial_anchors(labels, parents, rest, anchors, camera_location, min_section_points: int = 60) -> tuple:
    """(B, 3) the anchors (B, 3) moved back along their camera rays to the depth of the
    centre of their bone's cross-section (for the root: of the root bone itself), and (B, 3)
    the unit camera ray of each anchor whose depth its section gave (zero rows: the anchor
    kept, its depth not measured).

    The cross-section is the slab of the bone's rest points (M, 3) across its main axis
    (first principal direction) around the anchor: 10 % of the bone's length, at least
    `min_section_points` points. One camera samples only its front half: across the bone
    (perpendicular to the axis and the ray) the section spans [middle - a, middle + a]
    (2nd-98th percentile), and a round limb of radius a whose axis turns out of the image
    plane by phi gives depth(s, u) = centre + g u - (a / cos phi) sqrt(1 - (s - middle)^2 /
    a^2) for every visible point, u its offset along the axis from the anchor; centre and
    slope g come from one linear least-squares fit, so a bone turned towards or away from
    the camera, whose section lies on one side of the anchor at its end, does not shift the
    centre by its slope. Anchors only move away from the camera and by at most a / cos phi.
    Bones seen end-on (axis along the ray) and sections not clearly in front of the camera
    keep their anchor.

    Why round, its radius the visible half-width a rather than a fitted depth: the profile's
    curvature lies at the section's grazing edges, which the camera samples worst and the
    rest pose's trimmed surface loses, so a fitted depth comes out too flat on real limbs
    and trunks, and the joints sat in front of the body. A truly flat section (a board) is
    placed up to a too deep.
    """
    camera = np.asarray(camera_location, dtype=np.float64)
    result = anchors.copy()
    rays = np.zeros_like(result)
    for bone in range(len(parents)):  # loop over bones (a few dozen), vectorised over points
        points = rest[labels == bone]
        if len(points) < 10:
            continue
        anchor = anchors[bone]
        ray = anchor - camera
        ray /= max(np.linalg.norm(ray), 1e-12)
        axis = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)[2][0]
        axis = axis - ray * (axis @ ray)
        in_view = np.linalg.norm(axis)   # cosine of the bone's turn out of the image plane
        if in_view < 0.3:                # bone points at the camera: its section is not seen
            continue
        axis /= in_view
        lateral = np.cross(ray, axis)
        along = np.abs((points - anchor) @ axis)
        kth = min(len(along), min_section_points) - 1
        half_slab = max(0.1 * np.ptp(points @ axis), np.partition(along, kth)[kth])
        section = points[along <= half_slab]
        across = (section - anchor) @ lateral
        depth = (section - camera) @ ray
        low, high = np.percentile(across, [2.0, 98.0])
        half_width, middle = 0.5 * (high - low), 0.5 * (high + low)
        # a section reaching to within its own half-width of the camera (or behind it): the
        # cloud is not in the camera's frame or camera_location is wrong; the front-half
        # model does not hold
        if half_width <= 0 or len(section) < 5 or depth.min() <= half_width:
            continue
        # a round limb turned out of the image plane is cut by the ray's plane in an ellipse
        # of half-depth half_width / in_view: depth + half_depth * sqrt(1 - (across -
        # middle)^2 / half_width^2) = centre_depth + slope * along_axis, linear in
        # (centre_depth, slope)
        half_depth = half_width / in_view
        profile = np.sqrt(np.clip(1.0 - ((across - middle) / half_width) ** 2, 0.0, 1.0))
        design = np.column_stack([np.ones_like(profile), (section - anchor) @ axis])
        centre_depth = float(np.linalg.lstsq(design, depth + half_depth * profile, rcond=None)[0][0])
        shift = np.clip(centre_depth - (anchor - camera) @ ray, 0.0, half_depth)
        result[bone] = anchor + shift * ray
        rays[bone] = ray
    return result, rays
