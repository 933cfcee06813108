"""Closed-form rotations over SO(3), the weighted rigid fit of two point sets and batched rigid
fits per segment (Kabsch with det correction)."""
from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.linalg.lapack import dgesdd as _gesdd


def rotations_from_h(H: np.ndarray) -> np.ndarray:
    """argmax_R tr(R H) over SO(3) for a batch (..., 3, 3) of H (paper Eq. 6 and 15).

    U S V^T = svd(H^T), R = U diag(1, 1, det(U V^T)) V^T (Myronenko and Song 2009).
    """
    if H.shape == (3, 3):
        # one matrix (the bone-by-bone updates of Alg. 2 and the live fit call this per
        # bone): LAPACK's gesdd called directly, as np.linalg.svd does (the same U, Vt) but
        # without its per-call overhead
        U, _, Vt, info = _gesdd(H.T)
        if info != 0:
            U, _, Vt = np.linalg.svd(H.T)      # did not converge (NaN, inf): numpy's error or answer
        R = U @ Vt
        # R is orthogonal, det +-1: the sign from the cofactor expansion in Python floats,
        # cheaper than np.linalg.det on one 3 x 3 (called ~60 times a live frame)
        (a, b, c), (d, e, f), (g, h, i) = R.tolist()
        if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0:
            U[:, 2] = -U[:, 2]
            R = U @ Vt
        return R
    shape = H.shape
    H = H.reshape(-1, 3, 3)
    U, _, Vt = np.linalg.svd(np.transpose(H, (0, 2, 1)))
    det = np.linalg.det(U @ Vt)
    correction = np.ones((len(H), 3))
    correction[:, 2] = np.where(det < 0, -1.0, 1.0)
    return ((U * correction[:, None, :]) @ Vt).reshape(shape)


def weighted_rigid_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> tuple:
    """argmin_(R, t) sum_i weights_i |R source_i + t - target_i|^2 (source, target (n, 3) m,
    weights (n,) >= 0 with a positive sum, None: all 1): (R (3, 3), t (3,))."""
    weights = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
    total = weights.sum()
    source_centre, target_centre = weights @ source / total, weights @ target / total
    R = rotations_from_h(((source - source_centre) * weights[:, None]).T @ (target - target_centre))
    return R, target_centre - R @ source_centre


def segment_matrix(labels: np.ndarray, n_segments: int) -> sparse.csr_matrix:
    """(S, M) one-hot matrix: row s sums the points labelled s."""
    M = len(labels)
    return sparse.csr_matrix((np.ones(M), (labels, np.arange(M))), shape=(n_segments, M))


def fit_rigid_segments(rest: np.ndarray, frames: np.ndarray, labels: np.ndarray, n_segments: int):
    """Eq. (9) for every segment and frame: argmin sum_{m in s} |y_m^t - (R q_m + T)|^2.

    rest: (M, 3) rest points q; frames: (F, M, 3) registered points y; labels: (M,) in
    [0, n_segments). Returns rotations (F, S, 3, 3) and translations (F, S, 3). Segments
    without points get the identity.
    """
    return fit_weighted_segments(rest, frames, segment_matrix(labels, n_segments))


def fit_weighted_segments(rest: np.ndarray, frames: np.ndarray, membership: sparse.spmatrix):
    """argmin sum_m membership[s, m] |y_m^t - (R q_m + T)|^2 for every segment s and frame t:
    the weighted rigid fit of each segment's points (soft membership, e.g. a deformation
    node's blend weights). rest (M, 3), frames (F, M, 3), membership sparse (S, M) >= 0 ->
    rotations (F, S, 3, 3), translations (F, S, 3); a segment without weight: identity."""
    F, M, _ = frames.shape
    summer = sparse.csr_matrix(membership)
    n_segments = summer.shape[0]
    counts = np.asarray(summer.sum(axis=1)).ravel()
    safe = np.where(counts > 0, counts, 1.0)      # (soft weights may sum below 1)
    rest_centres = (summer @ rest) / safe[:, None]                                # (S, 3)
    by_point = frames.transpose(1, 0, 2).reshape(M, -1)                           # (M, F * 3)
    frame_centres = (summer @ by_point).reshape(n_segments, F, 3)
    frame_centres = frame_centres.transpose(1, 0, 2) / safe[None, :, None]        # (F, S, 3)
    # H[t, s, i, j] = sum_m w_sm q_mi y_mj^t, then centred: one sparse product per component
    # i of q (the same sums as over an (M, F, 3, 3) outer product, without forming it)
    H = np.stack([(summer.multiply(rest[None, :, i]).tocsr() @ by_point).reshape(n_segments, F, 3)
                  for i in range(3)], axis=2).transpose(1, 0, 2, 3)
    H -= counts[None, :, None, None] * rest_centres[None, :, :, None] * frame_centres[:, :, None, :]
    rotations = rotations_from_h(H)
    rotations[:, counts == 0] = np.eye(3)
    translations = frame_centres - np.einsum('fsij,sj->fsi', rotations, rest_centres)
    return rotations, translations


def turn_spans(rotations: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(B,) degrees: for each bone, the largest angle between two frames' rotations of it
    relative to its parent (rotations (F, B, 3, 3), rest -> frame; parents (B,), -1 at the
    root, whose span is 0): how far the joint turned over the frames."""
    rotations = np.asarray(rotations, dtype=np.float64)
    spans = np.zeros(len(parents))
    for bone, parent in enumerate(np.asarray(parents, dtype=int)):    # over bones: (F, F) each
        if parent < 0:
            continue
        relative = np.einsum('fji,fjk->fik', rotations[:, parent], rotations[:, bone])     # (F, 3, 3)
        # trace(R_a^T R_b) = 1 + 2 cos(angle between frames a and b): the largest angle has
        # the smallest trace
        traces = np.einsum('aji,bji->ab', relative, relative)
        spans[bone] = np.degrees(np.arccos(np.clip((traces.min() - 1.0) / 2.0, -1.0, 1.0)))
    return spans
