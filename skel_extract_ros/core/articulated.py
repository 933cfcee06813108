r"""The articulated model's two equations, written once: linear blend skinning (Eq. 8) and
the exact bone-by-bone update of the bone transforms (Eq. 13-15).

Rest points q_m (M, 3) follow up to k bones each with LBS weights w_mj (rows sum to 1):

    x_m^t = sum_j w_mj (R_j^t q_m + T_j^t)                                   (Eq. 8)

Every term of one bone's energy, with the other bones held, has the form
lambda |R a + T - b|^2:
- data: lambda = c_m w_mj^2, a = q_m, b = (z_m - u_m) / w_mj, with z_m the point's target,
  c_m its weight and u_m the other bones' part of x_m;
- joints: lambda = alpha, a = c_jk, b = R_k c_jk + T_k for each joint with a neighbour k;
- E_small: lambda = gamma, a = 0, b = the anchor translation, plus gamma tr(R R_anchor^T).
So T = mu_b - R mu_a (Eq. 14) and R maximises tr(R Z) with
Z = sum lambda a b^T - Lambda mu_a mu_b^T + gamma R_anchor^T (Eq. 15, SVD with the det
correction), Lambda the sum of the lambdas.

Alg. 2 (core.joints) puts its registration and GMM terms into one data term per frame:
c = zeta + P1 / tau and z = (zeta y + (P1 / tau) x~) / c. The live fits (core.live) use one
frame: c = P1 / tau and z the posterior mean (camera frames), or c = zeta and z = y
(registered frames). Both go through `BoneBlocks.update`, every frame at once.
"""
from __future__ import annotations

import numpy as np
from scipy import sparse

from .rigid import rotations_from_h


def dense_weights(influences: np.ndarray, weights: np.ndarray, n_bones: int) -> np.ndarray:
    """(M, B) LBS weight matrix W from each point's k bones (M, k) and their weights (M, k)
    (a bone listed twice in a row gets both weights)."""
    dense = np.zeros((len(weights), n_bones))
    np.add.at(dense, (np.arange(len(weights))[:, None], influences), weights)
    return dense


def stacked_transposed(rotations: np.ndarray) -> np.ndarray:
    """(3, 3F) [R_1^T ... R_F^T] of one bone's rotations (F, 3, 3): q (n, 3) times it is
    (n, 3F), row m the point R^t q_m for every frame t."""
    return np.transpose(rotations, (2, 0, 1)).reshape(3, -1)


def influenced_positions(rest, rotations, translations, influences) -> np.ndarray:
    """(M, k, F, 3) each rest point (M, 3) moved by each of its k influencing bones (M, k):
    R_j^t q_m + T_j^t for rotations (F, B, 3, 3), translations (F, B, 3). Only those k:
    every point under every bone is (F, B, M, 3), tens of MB for a window of a body."""
    M, k = influences.shape
    F = len(rotations)
    flat = influences.ravel()
    order = np.argsort(flat, kind='stable')
    bounds = np.searchsorted(flat[order], np.arange(rotations.shape[1] + 1))
    positions = np.empty((M * k, F, 3))
    for bone in np.flatnonzero(np.diff(bounds)):   # one (n, 3) x (3, 3F) product per bone its points use
        rows = order[bounds[bone]:bounds[bone + 1]]
        positions[rows] = (rest[rows // k] @ stacked_transposed(rotations[:, bone])).reshape(-1, F, 3) \
            + translations[None, :, bone]
    return positions.reshape(M, k, F, 3)


def blend(rest, dense, rotations, translations) -> np.ndarray:
    """Eq. (8): (F, M, 3) LBS positions of rest (M, 3) with the (M, B) weight matrix for
    rotations (F, B, 3, 3), translations (F, B, 3). sum_b W_mb (R_b^t q_m + T_b^t) as one
    matrix product, the (M, 3B) rows W_mb q_m times the (3B, 3F) stacked rotations, plus
    W T: five times faster on a window than moving each point by each of its bones."""
    F, B = rotations.shape[:2]
    M = len(rest)
    weighted_rest = (dense[:, :, None] * rest[:, None, :]).reshape(M, B * 3)          # (M, 3B)
    stacked = np.transpose(rotations, (1, 3, 0, 2)).reshape(B * 3, F * 3)            # (3B, 3F)
    moved = weighted_rest @ stacked + dense @ np.transpose(translations, (1, 0, 2)).reshape(B, F * 3)
    return np.ascontiguousarray(np.transpose(moved.reshape(M, F, 3), (1, 0, 2)))


class BoneBlocks:
    """Eq. 8 and the block update of Eq. 13-15 for rest points with fixed LBS weights.

    rest (M, 3) m; influences (M, k) bone indices; weights (M, k) LBS weights; parents (B,)
    the bone tree (-1: root). The joint between bone b and its parent is stored on b, so a
    bone's joints are its own (with its parent) and its children's.

    What the weights fix is derived once: every (point, slot) a bone carries, flattened in
    bone order (bone b's entries are entry_start[b]:entry_start[b + 1]), so a sweep sums
    what its point weights fix (each bone's lambda total and mu_a) for all bones at once.
    """

    def __init__(self, rest: np.ndarray, influences: np.ndarray, weights: np.ndarray, parents: np.ndarray):
        self.rest = np.asarray(rest, dtype=np.float64)
        self.influences = np.asarray(influences)
        self.weights = np.asarray(weights, dtype=np.float64)
        self.parents = np.asarray(parents)
        n_bones = len(self.parents)
        self.dense = dense_weights(self.influences, self.weights, n_bones)
        point, slot = np.nonzero(self.weights > 1e-8)
        bone_of_entry = self.influences[point, slot]
        order = np.argsort(bone_of_entry, kind='stable')      # row-major within each bone
        self._entry_point = point[order]
        bone_of_entry = bone_of_entry[order]
        self._entry_start = np.concatenate([[0], np.cumsum(np.bincount(bone_of_entry, minlength=n_bones))])
        self._entry_weight = self.weights[point[order], slot[order]]
        self._entry_rest = self.rest[self._entry_point]
        # (B, E) one-hot: row b sums bone b's entries (B bones x a few entries a point)
        self._entry_sum = (bone_of_entry[None, :] == np.arange(n_bones)[:, None]).astype(np.float64)
        # (M, E): row m sums point m's entries (Eq. 8 from the entries' contributions)
        n_entries = len(self._entry_point)
        self._entry_to_point = sparse.csr_matrix((np.ones(n_entries), (self._entry_point, np.arange(n_entries))),
                                                 shape=(len(self.rest), n_entries))
        # a bone listed twice in a point's row puts that point twice in the bone's block
        self._repeated = any(len(np.unique(self._entry_point[a:b])) < b - a
                             for a, b in zip(self._entry_start[:-1], self._entry_start[1:]))
        # per bone, its block of entries: (slice, points (n,), rest q (n, 3), w q (n, 3), w (n, 1, 1))
        self._blocks = []
        for a, b in zip(self._entry_start[:-1], self._entry_start[1:]):
            span = slice(int(a), int(b))
            weight = self._entry_weight[span]
            self._blocks.append((span, self._entry_point[span], self._entry_rest[span],
                                 weight[:, None] * self._entry_rest[span], weight[:, None, None]))
        # each bone's joints: (the other bone, the bone the joint is stored on)
        self._links = []
        for bone in range(n_bones):
            links = [(int(self.parents[bone]), bone)] if self.parents[bone] >= 0 else []
            links += [(int(child), int(child)) for child in np.flatnonzero(self.parents == bone)]
            self._links.append((np.array([o for o, _ in links], dtype=int), np.array([j for _, j in links], dtype=int)))
        self._link_counts = np.array([len(others) for others, _ in self._links], dtype=np.float64)

    @property
    def n_bones(self) -> int:
        return len(self.parents)

    def deform(self, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """Eq. (8): (F, M, 3) for rotations (F, B, 3, 3), translations (F, B, 3)."""
        return blend(self.rest, self.dense, rotations, translations)

    def _moved(self, bone: int, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """(n, F, 3) w_mj (R_j q_m + T_j) for bone j's n entries, rotations (F, 3, 3) and
        translations (F, 3) its transforms."""
        _, _, _, weighted_rest, weight = self._blocks[bone]
        return (weighted_rest @ stacked_transposed(rotations)).reshape(-1, len(rotations), 3) + weight * translations

    def update(self, targets: np.ndarray, point_weights, rotations: np.ndarray, translations: np.ndarray,
               joints: np.ndarray, alpha: float, gamma: float, anchors: tuple | None = None,
               sweeps: int = 1) -> np.ndarray:
        """`sweeps` passes of Eq. (13)-(15), bone after bone, every frame at once, in place
        on rotations (F, B, 3, 3) and translations (F, B, 3).

        targets (F, M, 3) m; point_weights: the data term's weight c (F, M), or anything
        that broadcasts to it (1/m^2); joints (B, 3) rest-frame c_jk; alpha, gamma: the
        joint and E_small weights; anchors: (rotations, translations) E_small pulls towards
        (None: each bone's transform as the update reaches it, a proximal step). Returns
        the (F, M, 3) contributions' sum, Eq. (8) at the new transforms."""
        F, M = len(rotations), len(self.rest)
        point_weights = np.broadcast_to(np.asarray(point_weights, dtype=np.float64), (F, M))
        # Entry-major (E, F, 3) and point-major (M, F, 3): a bone's entries are one block and
        # its points' rows are whole frames, so the loop over bones slices and gathers rows
        # instead of gathering scattered (frame, point) pairs (bench/README.md, "Steps 2 and
        # 3's time").
        contributions = np.concatenate([self._moved(bone, rotations[:, bone], translations[:, bone])
                                        for bone in range(self.n_bones)])                # (E, F, 3)
        deformed = np.asarray(self._entry_to_point @ contributions.reshape(-1, F * 3)).reshape(M, F, 3)
        weight_w = point_weights[:, self._entry_point] * self._entry_weight          # (F, E) c w
        lam = weight_w * self._entry_weight                                          # (F, E) c w^2
        lam_totals = lam @ self._entry_sum.T + alpha * self._link_counts + gamma       # (F, B)
        centre_sums = np.stack([joints[stored].sum(axis=0) for _, stored in self._links])      # (B, 3)
        mu_as = (np.matmul(self._entry_sum, lam[:, :, None] * self._entry_rest)
                 + alpha * centre_sums) / lam_totals[..., None]                        # (F, B, 3)
        entry_cw = np.ascontiguousarray(weight_w.T)                                    # (E, F) c w
        entry_targets = np.transpose(targets, (1, 0, 2))[self._entry_point]            # (E, F, 3)
        for _ in range(sweeps):
            for bone, (others, stored) in enumerate(self._links):   # loop over bones, vectorised
                span, m, rest, _, _ = self._blocks[bone]
                anchor_r = rotations[:, bone] if anchors is None else anchors[0][:, bone]
                anchor_t = translations[:, bone] if anchors is None else anchors[1][:, bone]
                lam_total, mu_a = lam_totals[:, bone], mu_as[:, bone]                 # (F,), (F, 3)
                own = contributions[span]                                              # (n, F, 3)
                # lambda b = c w (z - u) of each entry (the data term's b = (z - u) / w)
                weighted_residual = entry_cw[span, :, None] * (entry_targets[span] - (deformed[m] - own))
                centres = joints[stored]                                               # (L, 3)
                carried = (np.matmul(rotations[:, others], centres[None, :, :, None])[..., 0]
                           + translations[:, others])                                  # (F, L, 3)
                mu_b = (weighted_residual.sum(axis=0) + alpha * carried.sum(axis=1)
                        + gamma * anchor_t) / lam_total[:, None]
                Z = (np.transpose((rest.T @ weighted_residual.reshape(len(m), F * 3)).reshape(3, F, 3),
                                  (1, 0, 2))                                           # sum c w q b^T
                     + alpha * np.matmul(centres.T, carried)
                     - lam_total[:, None, None] * mu_a[:, :, None] * mu_b[:, None, :]
                     + gamma * np.transpose(anchor_r, (0, 2, 1)))
                # one frame (the live fits): the single-matrix path, a fraction of the batch's cost
                R = rotations_from_h(Z[0])[None] if F == 1 else rotations_from_h(Z)
                rotations[:, bone] = R
                translations[:, bone] = mu_b - np.matmul(R, mu_a[..., None])[..., 0]
                new = self._moved(bone, R, translations[:, bone])
                if self._repeated:
                    np.add.at(deformed, m, new - own)
                else:
                    deformed[m] += new - own
                contributions[span] = new
        return np.ascontiguousarray(np.transpose(deformed, (1, 0, 2)))
