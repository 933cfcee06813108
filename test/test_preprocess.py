"""Per-frame preprocessing: bad input never crashes, every step does its job."""
import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from skel_extract_ros.core.preprocess import PreprocessError, PreprocessParams, Preprocessor


def blob(rng, n, centre, scale=0.1):
    return rng.normal(size=(n, 3)) * scale + centre


def test_empty_all_nan_and_bad_shapes():
    preprocess = Preprocessor()
    assert preprocess(np.empty((0, 3))).shape == (0, 3)
    assert preprocess(np.full((500, 3), np.nan)).shape == (0, 3)
    assert preprocess(np.array([[np.inf, 0, 1], [1, 2, 3]])).shape[0] <= 1
    with pytest.raises(PreprocessError, match='shape'):
        preprocess(np.zeros((10, 4)))
    with pytest.raises(PreprocessError, match='shape'):
        preprocess(np.zeros(12))


def test_a_million_points_is_bounded_and_reaches_the_target_size():
    rng = np.random.default_rng(0)
    surface = rng.uniform(-1, 1, size=(1_000_000, 3)) * [1.0, 1.0, 0.0] + [0, 0, 2.0]
    preprocess = Preprocessor(PreprocessParams(target_points=5000))
    started = time.perf_counter()
    out = preprocess(surface)
    assert time.perf_counter() - started < 30.0
    assert 3500 <= len(out) <= 6500
    # the adapted voxel size is reused: the next frame lands near the target at once
    assert 3500 <= len(preprocess(surface[:500_000])) <= 6500


def _members(points, reference):
    """How many of `points` are (exactly) points of `reference`."""
    return int(np.sum(cKDTree(reference).query(points)[0] < 1e-12))


def test_crop_plane_cluster_and_outliers():
    """Each step removes exactly what it must and keeps what it must, by count: a floor
    (6000 points at y = 1 m), a subject blob (3000), a small far blob (300) and 20 isolated
    points, no downsampling. Measured: the crop keeps exactly the 3319 points in its box,
    plane removal removes the 6000 floor points and nothing else, the largest cluster is
    2603 subject points and nothing else (the blob's sparse fringe is dropped by DBSCAN and
    the statistical filter: 397 points), statistical outlier removal removes all 20
    isolated points and 5 of the 3000 subject points (its sparse tail). Bounds on the
    subject points lost: 1.3 x measured."""
    rng = np.random.default_rng(1)
    floor = np.column_stack([rng.uniform(-1, 1, 6000), np.full(6000, 1.0), rng.uniform(1, 3, 6000)])
    subject = blob(rng, 3000, [0.0, 0.5, 2.0])
    far_blob = blob(rng, 300, [0.9, -0.5, 2.0], 0.03)
    isolated = rng.uniform(-1, 1, size=(20, 3)) + [0, 0, 2]
    cloud = np.vstack([floor, subject, far_blob, isolated])
    rest = np.vstack([subject, far_blob, isolated])

    cropped = Preprocessor(PreprocessParams(crop_min=(-2, -2, 0), crop_max=(2, 0.9, 5), target_points=0,
                                            outlier_neighbours=0))(cloud)
    in_box = cloud[(cloud >= [-2, -2, 0]).all(axis=1) & (cloud <= [2, 0.9, 5]).all(axis=1)]
    assert len(cropped) == len(in_box) == 3319 and _members(cropped, in_box) == len(in_box)

    no_floor = Preprocessor(PreprocessParams(remove_plane=True, target_points=0, outlier_neighbours=0))(cloud)
    assert _members(no_floor, floor) == 0                       # the whole floor goes
    assert len(no_floor) == _members(no_floor, rest) == len(rest) == 3320   # nothing else does

    largest = Preprocessor(PreprocessParams(remove_plane=True, keep_largest_cluster=True, target_points=0,
                                            cluster_eps=0.05))(cloud)
    assert len(largest) == _members(largest, subject)            # only the subject ...
    assert _members(largest, subject) >= 3000 - 516, _members(largest, subject)   # ... most of it (2603)
    assert np.linalg.norm(largest.mean(axis=0) - [0, 0.5, 2.0]) < 0.004    # measured 3.0 mm

    # statistical outlier removal: every isolated point goes, the subject stays
    kept = Preprocessor(PreprocessParams(target_points=0))(np.vstack([subject, isolated]))
    assert _members(kept, isolated) == 0
    assert len(kept) == _members(kept, subject) >= 3000 - 6, len(kept)   # measured 2995
    # and switched off, nothing is removed: the 20 isolated points are what the step removes
    kept_all = Preprocessor(PreprocessParams(target_points=0, outlier_neighbours=0))(np.vstack([subject, isolated]))
    assert len(kept_all) == 3020 and _members(kept_all, isolated) == 20
