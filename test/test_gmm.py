"""The truncated E-step (core.gmm) against the dense GMM posteriors of Eq. (3) / (11)."""
import numpy as np

from skel_extract_ros.core.gmm import gmm_posteriors, nearest_centroids


def _dense_statistics(observed, centroids, sigma2, omega):
    """P1 (M,) and Px (M, 3) from the full N x M posterior matrix (small sizes only)."""
    squared = np.sum((observed[:, None] - centroids[None]) ** 2, axis=2)
    gauss = np.exp(-squared / (2 * sigma2))
    M, N = len(centroids), len(observed)
    c = (2 * np.pi * sigma2) ** 1.5 * omega * M / ((1 - omega) * N)
    posteriors = gauss / (gauss.sum(axis=1, keepdims=True) + c)
    return posteriors.sum(axis=0), posteriors.T @ observed


def test_truncated_e_step_matches_the_dense_posteriors():
    rng = np.random.default_rng(0)
    centroids = rng.uniform(0, 0.5, (300, 3))
    observed = centroids[rng.integers(0, 300, 800)] + rng.normal(scale=0.01, size=(800, 3))
    sigma2 = 1e-4
    P1, Px = _dense_statistics(observed, centroids, sigma2, 0.01)
    # all centroids within 10 sigma of every observation are kept: truncation loses < 1e-9
    stats = gmm_posteriors(observed, centroids, sigma2, 0.01, n_neighbours=64, truncation_sigmas=10.0)
    assert np.allclose(stats.P1, P1, atol=1e-6) and np.allclose(stats.Px, Px, atol=1e-6)


def test_given_candidates_give_the_same_statistics_and_tolerate_small_moves():
    rng = np.random.default_rng(1)
    centroids = rng.uniform(0, 0.5, (400, 3))
    observed = centroids[rng.integers(0, 400, 1000)] + rng.normal(scale=0.005, size=(1000, 3))
    sigma2 = 1e-4
    fresh = gmm_posteriors(observed, centroids, sigma2, 0.01)
    candidates = nearest_centroids(observed, centroids, 8, 4.0 * np.sqrt(sigma2))
    given = gmm_posteriors(observed, centroids, sigma2, 0.01, candidates=candidates)
    assert np.allclose(given.P1, fresh.P1) and np.allclose(given.Px, fresh.Px) and np.isclose(given.nll, fresh.nll)
    # centroids moved by a millimetre: the old candidate lists still give nearly the exact answer
    moved = centroids + rng.normal(scale=0.001, size=centroids.shape)
    exact = gmm_posteriors(observed, moved, sigma2, 0.01)
    stale = gmm_posteriors(observed, moved, sigma2, 0.01, candidates=candidates)
    assert np.abs(stale.P1 - exact.P1).max() < 0.02 * exact.P1.max()
    # no candidate: everything is an outlier, no mass anywhere
    none = gmm_posteriors(observed, centroids, sigma2, 0.01, candidates=np.full((1000, 8), 400))
    assert none.Np == 0.0 and np.isfinite(none.nll)
