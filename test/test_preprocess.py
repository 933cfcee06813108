"""Per-frame preprocessing: bad input never crashes, every step does its job."""
import time

import numpy as np
import pytest

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


def test_crop_plane_cluster_and_outliers():
    rng = np.random.default_rng(1)
    floor = np.column_stack([rng.uniform(-1, 1, 6000), np.full(6000, 1.0), rng.uniform(1, 3, 6000)])
    subject = blob(rng, 3000, [0.0, 0.5, 2.0])
    far_blob = blob(rng, 300, [0.9, -0.5, 2.0], 0.03)
    isolated = rng.uniform(-1, 1, size=(20, 3)) + [0, 0, 2]
    cloud = np.vstack([floor, subject, far_blob, isolated])

    cropped = Preprocessor(PreprocessParams(crop_min=(-2, -2, 0), crop_max=(2, 0.9, 5), target_points=0,
                                            outlier_neighbours=0))(cloud)
    assert (cropped[:, 1] <= 0.9).all() and len(cropped) < len(cloud) - 5000

    no_floor = Preprocessor(PreprocessParams(remove_plane=True, target_points=0, outlier_neighbours=0))(cloud)
    assert np.sum(np.abs(no_floor[:, 1] - 1.0) < 0.01) < 50

    largest = Preprocessor(PreprocessParams(remove_plane=True, keep_largest_cluster=True, target_points=0,
                                            cluster_eps=0.05))(cloud)
    assert np.linalg.norm(largest.mean(axis=0) - [0, 0.5, 2.0]) < 0.05
    assert np.sum(np.linalg.norm(largest - [0.9, -0.5, 2.0], axis=1) < 0.1) == 0

    # statistical outlier removal: every isolated point goes, the subject stays (measured:
    # all 20 removed, 2995 of 3000 subject points kept: the blob's own sparse tail)
    kept = Preprocessor(PreprocessParams(target_points=0))(np.vstack([subject, isolated]))
    from scipy.spatial import cKDTree
    on_subject = cKDTree(subject).query(kept)[0] < 1e-12
    assert on_subject.all()                                    # no isolated point is left
    assert on_subject.sum() >= 0.995 * len(subject)
