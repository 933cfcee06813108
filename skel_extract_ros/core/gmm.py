"""Truncated GMM E-step shared by registration (Eq. 3) and joint estimation (Eq. 11).

The observed points V (N, 3) come from a GMM with centroids X (M, 3), one variance sigma2,
equal priors 1/M and a uniform outlier component of weight omega and density 1/N:

    p_mi = exp(-|v_i - x_m|^2 / 2 sigma2) / (sum_m' exp(...) + c),
    c    = (2 pi sigma2)^{3/2} omega M / ((1 - omega) N).

Each observation keeps only its `n_neighbours` nearest centroids within
`truncation_sigmas` * sigma (k-d tree over the centroids), so no N x M matrix is formed;
what the M-steps need are the sufficient statistics below. `CandidateCache` keeps those
neighbour lists across the iterations of one EM run while the centroids move little.

Balanced E-step (`mass_cap`, a deviation from Eq. 3 for the registration). Eq. 3 normalises
each observation over the centroids, never each centroid over the observations. When a
featureless limb has slid along itself (the hand's centroids on the forearm's observations,
the hand's own observations beyond them), only the chain's last centroid is within reach of
most of the stranded observations: it takes them all and is pulled alone, while the
centroids behind it stay put and the graph holds it back. With `mass_cap` > 0, each of
three passes scales down the kernel of every centroid whose posterior mass sum_i p_mi is
above mass_cap times the median mass of the centroids with data, to that bound, then
normalises the observations' rows again (a Sinkhorn-like balance, on the centroid side
only capped, never raised: a centroid hidden from the camera rightly has no data). An
observation shared by the over-full centroid and the ones behind it then goes more to
those, so the chain's end is pulled out along the data as a whole. The rows give part of
the mass back each time, so the bound is approached, not reached. The likelihood (nll)
stays Eq. 1's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .point_sets import nearest_within


@dataclass
class GMMStatistics:
    """Sufficient statistics of the posteriors.

    P1: (M,) sum_i p_mi; Px: (M, 3) sum_i p_mi v_i (m); Np: sum of P1; nll: -log-likelihood
    of the observations; weighted_sq: sum_mi p_mi |v_i|^2 (m^2).
    """

    P1: np.ndarray
    Px: np.ndarray
    Np: float
    nll: float
    weighted_sq: float

    def targets(self) -> np.ndarray:
        """(M, 3) x~_m = Px / P1, the posterior-weighted mean observation (0 without mass)."""
        has_mass = self.P1 > 1e-12
        return np.where(has_mass[:, None], self.Px / np.where(has_mass, self.P1, 1.0)[:, None], 0.0)

    def squared_residual(self, centroids: np.ndarray) -> float:
        """sum_mi p_mi |v_i - x_m|^2 for new centroids (M, 3), from the statistics alone."""
        return float(self.weighted_sq - 2.0 * np.sum(self.Px * centroids)
                     + np.sum(self.P1 * np.sum(centroids ** 2, axis=1)))


def nearest_centroids(observed: np.ndarray, centroids: np.ndarray, n_neighbours: int = 8,
                      radius: float = np.inf) -> np.ndarray:
    """(N, K) indices of each observation's K nearest centroids within `radius` (m); M where
    there are fewer. observed (N, 3), centroids (M, 3)."""
    return nearest_within(observed, centroids, n_neighbours, radius)[1]


def gmm_posteriors(observed: np.ndarray, centroids: np.ndarray, sigma2: float, omega: float,
                   n_neighbours: int = 8, truncation_sigmas: float = 4.0,
                   candidates: np.ndarray | None = None, mass_cap: float = 0.0) -> GMMStatistics:
    """E-step: observed (N, 3), centroids (M, 3), sigma2 (m^2) -> GMMStatistics.

    candidates: (N, K) centroid indices from `nearest_centroids` to use instead of a new
    query (M = none); the posteriors are exact over them, with the truncation radius applied.
    mass_cap: 0 for Eq. 3 as written, else the balanced E-step (module docstring).
    """
    M, N = len(centroids), len(observed)
    radius = truncation_sigmas * np.sqrt(sigma2)
    if candidates is None:   # a fresh query already gives the distances
        # a k-d tree over the centroids, rebuilt per call: its query cost does not grow with
        # sigma, unlike a fixed-radius search that visits every centroid in the ball
        distances, idx = nearest_within(observed, centroids, n_neighbours, radius)
        found = idx < M
        d2 = np.where(found, distances, 0.0) ** 2
    else:
        idx = candidates
        valid = idx < M
        offsets = centroids[np.where(valid, idx, 0)] - observed[:, None, :]
        # einsum, not a sum over the last axis of 3: a reduction along a short axis is slow
        d2 = np.einsum('nki,nki->nk', offsets, offsets)
        found = valid & (d2 <= radius ** 2)
    gauss = np.exp(d2 * (-0.5 / sigma2)) * found
    row_sum = gauss.sum(axis=1)
    c = (2.0 * np.pi * sigma2) ** 1.5 * omega * M / ((1.0 - omega) * N)
    flat = np.where(found, idx, M).ravel()
    posteriors, P1 = _normalised(gauss, flat, c, M)
    if mass_cap > 0:
        posteriors, P1 = _capped(gauss, posteriors, P1, flat, c, M, mass_cap)
    Px = np.stack([np.bincount(flat, weights=(posteriors * observed[:, axis:axis + 1]).ravel(),
                               minlength=M + 1)[:M] for axis in range(3)], axis=1)
    likelihood = (1.0 - omega) / M * (2.0 * np.pi * sigma2) ** -1.5 * row_sum + omega / N
    nll = float(-np.sum(np.log(likelihood[likelihood > 0])))
    weighted_sq = float(posteriors.sum(axis=1) @ np.einsum('ni,ni->n', observed, observed))
    return GMMStatistics(P1, Px, float(P1.sum()), nll, weighted_sq)


def _normalised(kernel: np.ndarray, flat: np.ndarray, c: float, M: int) -> tuple:
    """Eq. 3's row normalisation of kernel (N, K) -> (posteriors (N, K), P1 (M,))."""
    denominator = kernel.sum(axis=1) + c
    # with omega = 0 an observation out of every centroid's reach has 0 / 0: it has no mass
    posteriors = kernel / np.where(denominator > 0, denominator, 1.0)[:, None]
    return posteriors, np.bincount(flat, weights=posteriors.ravel(), minlength=M + 1)[:M]


# passes of the capped normalisation (module docstring); each costs one more normalisation
# of the (N, K) posteriors
_CAP_PASSES = 3
# a centroid with less posterior mass than this has no data (hidden, or off the subject)
_HAS_DATA = 1e-3


def _capped(kernel: np.ndarray, posteriors: np.ndarray, P1: np.ndarray, flat: np.ndarray, c: float, M: int,
            mass_cap: float) -> tuple:
    """The balanced E-step (module docstring): from kernel (N, K) and its Eq. 3 posteriors
    and P1, the columns of centroids over mass_cap x the median mass of the centroids with
    data scaled down and the rows normalised again, _CAP_PASSES times; flat (N * K,) the
    centroid of each entry (M = none). -> (posteriors (N, K), P1 (M,))."""
    for _ in range(_CAP_PASSES):
        with_data = P1[P1 > _HAS_DATA]
        if len(with_data) == 0:
            break
        limit = mass_cap * np.median(with_data)
        scale = np.minimum(1.0, limit / np.maximum(P1, 1e-300))
        if scale.min() >= 1.0:
            break
        kernel = kernel * np.append(scale, 0.0)[flat].reshape(kernel.shape)
        posteriors, P1 = _normalised(kernel, flat, c, M)
    return posteriors, P1


class CandidateCache:
    """Each observation's candidate centroids for the truncated E-step, kept across the EM
    iterations of one frame: the centroids move by millimetres per iteration once EM has
    found the frame, so the k-d tree query (a third of an iteration's time in Alg. 1, more
    in Alg. 2) is repeated only when a centroid has moved more than `spacing` since the
    last query, or the truncation radius has grown past the radius queried. The posteriors
    are exact over the candidates, the truncation radius applied; a candidate list can
    miss a centroid that came within the K nearest since the query: the price of the cache,
    small while no centroid has moved a spacing.

    observed (N, 3) m; spacing m (the rest points' median spacing: a centroid that moved
    less has not passed another); radius_margin: the query reaches this many times the
    truncation radius (inf: no radius, every observation keeps its K nearest however far).
    """

    def __init__(self, observed: np.ndarray, spacing: float, n_neighbours: int, radius_margin: float = 1.5):
        self.observed = np.ascontiguousarray(observed, dtype=np.float64)
        self.spacing = float(spacing)
        self.n_neighbours = int(n_neighbours)
        self.radius_margin = float(radius_margin)
        self.candidates = None      # (N, K) centroid indices, M where none
        self._queried_at = None     # (M, 3) the centroids of that query
        self._radius = 0.0          # and its radius (m)
        self.queries = 0

    def candidates_for(self, centroids: np.ndarray, radius: float = np.inf) -> np.ndarray:
        """(N, K) candidate indices for the centroids (M, 3) and a truncation radius (m)."""
        moved = None if self.candidates is None or len(centroids) != len(self._queried_at) \
            else centroids - self._queried_at
        if moved is None or radius > self._radius or np.max(np.einsum('mi,mi->m', moved, moved)) > self.spacing ** 2:
            self._radius = self.radius_margin * radius
            self.candidates = nearest_centroids(self.observed, centroids, self.n_neighbours, self._radius)
            self._queried_at = np.array(centroids, dtype=np.float64)
            self.queries += 1
        return self.candidates

    def posteriors(self, centroids: np.ndarray, sigma2: float, omega: float,
                   truncation_sigmas: float = 4.0, mass_cap: float = 0.0) -> GMMStatistics:
        """gmm_posteriors of the cached observations over these candidates."""
        candidates = self.candidates_for(centroids, truncation_sigmas * np.sqrt(sigma2))
        return gmm_posteriors(self.observed, centroids, sigma2, omega, self.n_neighbours, truncation_sigmas,
                              candidates=candidates, mass_cap=mass_cap)
