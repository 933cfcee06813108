"""The truncated E-step (core.gmm) against the dense GMM posteriors of Eq. (3) / (11)."""
import numpy as np
import pytest

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


def test_balanced_e_step_pulls_a_slid_chain_out_along_its_stranded_observations():
    """A chain of centroids 1 cm apart that slid back along its data: it covers 0-20 cm of
    observations that reach 26 cm (sigma 1.5 cm). Under Eq. 3 the last centroid takes the
    stranded observations alone (mass 10 against a median of 2) and is the only one pulled
    out (its target 2.7 cm ahead, the third from the end 0.5 cm; measured). Capped at 1.2 x
    the median, that mass goes to the centroids behind it: each of the last six is pulled
    further out, the chain's end as a whole. A centroid without data keeps none, and no
    observation's mass is lost."""
    chain = np.stack([np.arange(21) * 0.01, np.zeros(21), np.zeros(21)], axis=1)
    hidden = np.array([[1.0, 1.0, 1.0]])
    centroids = np.vstack([chain, hidden])
    observed = np.stack([np.arange(53) * 0.005, np.zeros(53), np.zeros(53)], axis=1)
    sigma2 = 0.015 ** 2
    eq3 = gmm_posteriors(observed, centroids, sigma2, 0.01)
    balanced = gmm_posteriors(observed, centroids, sigma2, 0.01, mass_cap=1.2)
    end = slice(15, 21)
    pull_eq3 = eq3.targets()[end, 0] - chain[end, 0]
    pull_balanced = balanced.targets()[end, 0] - chain[end, 0]
    assert (pull_balanced > pull_eq3 + 1e-3).all(), (pull_eq3, pull_balanced)
    assert eq3.P1[20] > 4 * np.median(eq3.P1[:21]) and balanced.P1[20] < 0.6 * eq3.P1[20]
    assert eq3.P1[21] == balanced.P1[21] == 0.0
    assert balanced.Np == pytest.approx(eq3.Np, rel=1e-3)
    # the likelihood is the model's, whatever the balance
    assert balanced.nll == eq3.nll
    # mass_cap 0 is Eq. 3 itself
    same = gmm_posteriors(observed, centroids, sigma2, 0.01, mass_cap=0.0)
    assert np.array_equal(same.P1, eq3.P1) and np.array_equal(same.Px, eq3.Px)
