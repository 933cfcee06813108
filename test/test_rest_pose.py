"""Rest pose: Poisson surface of the first frame, trimmed and evenly resampled."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from skel_extract_ros.core.preprocess import Preprocessor
from skel_extract_ros.core.rest_pose import RestPose, RestPoseError, RestPoseParams
from skel_extract_ros.sim import generate_sequence


@pytest.mark.parametrize('subject', ['human', 'hand'])
def test_reconstructed_rest_set_is_closer_to_the_surface_than_the_raw_frame(subject):
    seq = generate_sequence(subject, 1, seed=5, progress=False)
    frame = Preprocessor()(seq.clouds[0].reshape(-1, 3))
    surface = seq.ground_truth['surface_points'][0].astype(np.float64)
    rest = RestPose.from_points(frame, RestPoseParams(n_points=2000))
    raw = RestPose.from_raw(frame, 2000)
    assert rest.points.shape == (2000, 3)
    to_surface = cKDTree(surface).query(rest.points)[0]
    raw_to_surface = cKDTree(surface).query(raw.points)[0]
    assert to_surface.mean() < raw_to_surface.mean()
    # nothing invented far from the data: every rest point is near an observed point
    assert cKDTree(frame).query(rest.points)[0].max() < 0.05 * float(seq.ground_truth['subject_scale_m'])
    # evenly spread: nearest-neighbour spacing varies little
    spacing = cKDTree(rest.points).query(rest.points, k=2)[0][:, 1]
    assert spacing.std() / spacing.mean() < 0.5


def test_too_few_points_is_a_clear_error():
    with pytest.raises(RestPoseError, match='usable points'):
        RestPose.from_points(np.random.default_rng(0).normal(size=(50, 3)))
