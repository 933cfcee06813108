"""The truncated E-step (core.gmm) against the dense GMM posteriors of Eq. (3) / (11)."""
import numpy as np

from skel_extract_ros.core.gmm import CandidateCache, gmm_posteriors, nearest_centroids


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


def test_nearest_centroids_are_the_k_nearest_within_the_radius():
    """The k-d tree query (pykdtree) against brute force: the K nearest centroids, in order
    of distance, M where fewer than K lie within the radius; float32 input as float64."""
    rng = np.random.default_rng(2)
    centroids = rng.uniform(0, 0.5, (500, 3))
    observed = rng.uniform(-0.1, 0.6, (700, 3)).astype(np.float32)    # some far from every centroid
    radius = 0.04
    found = nearest_centroids(observed, centroids, 8, radius)
    distances = np.linalg.norm(observed.astype(np.float64)[:, None] - centroids[None], axis=2)
    order = np.argsort(distances, axis=1)[:, :8]
    expected = np.where(np.take_along_axis(distances, order, axis=1) <= radius, order, len(centroids))
    assert found.dtype == np.int64 and found.shape == (700, 8)
    assert (found == expected).all()
    assert (found == len(centroids)).any() and (found[:, 0] < len(centroids)).any()
    # fewer centroids than K: the missing slots are M
    few = nearest_centroids(observed, centroids[:3], 8)
    assert few.shape == (700, 3) and (few < 3).all()


def test_candidate_cache_queries_again_only_after_a_move_past_the_spacing_or_a_wider_radius():
    rng = np.random.default_rng(2)
    centroids = rng.uniform(0, 0.5, (400, 3))
    observed = centroids[rng.integers(0, 400, 1000)] + rng.normal(scale=0.005, size=(1000, 3))
    sigma2, spacing = 1e-4, 0.02
    cache = CandidateCache(observed, spacing, 8)
    first = cache.posteriors(centroids, sigma2, 0.01)
    fresh = gmm_posteriors(observed, centroids, sigma2, 0.01)
    # a fresh query: exactly gmm_posteriors' own (the margin only widens the candidate ball)
    assert cache.queries == 1 and np.allclose(first.P1, fresh.P1) and np.allclose(first.Px, fresh.Px)
    # every centroid moved by under the spacing, sigma shrank: the same lists, close to exact
    moved = centroids + rng.uniform(-0.005, 0.005, centroids.shape)
    stale = cache.posteriors(moved, 0.5 * sigma2, 0.01)
    exact = gmm_posteriors(observed, moved, 0.5 * sigma2, 0.01)
    assert cache.queries == 1
    assert np.abs(stale.P1 - exact.P1).sum() < 0.01 * exact.Np
    # one centroid moved past the spacing: a new query, exact again
    jumped = moved.copy()
    jumped[7] += [0.03, 0.0, 0.0]
    after_jump = cache.posteriors(jumped, 0.5 * sigma2, 0.01)
    assert cache.queries == 2
    assert np.allclose(after_jump.P1, gmm_posteriors(observed, jumped, 0.5 * sigma2, 0.01).P1)
    # the truncation radius grew past the queried 1.5 x radius: a new query
    cache.posteriors(jumped, 4.0 * sigma2, 0.01)
    assert cache.queries == 3
    # no radius (the live fit): the K nearest however far, never queried again for sigma
    unbounded = CandidateCache(observed, spacing, 8, radius_margin=np.inf)
    assert (unbounded.candidates_for(centroids) < len(centroids)).all()
    unbounded.posteriors(centroids, 100.0 * sigma2, 0.01)
    assert unbounded.queries == 1
