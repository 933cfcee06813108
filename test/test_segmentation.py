"""Finding the subject in a room (core/segmentation.py) and reading depth images
(depth_image.py), scored against the simulator's per-pixel subject mask."""
import numpy as np
import pytest

from skel_extract_ros.core.segmentation import (STATUS_NOBODY, STATUS_SUBJECT, SegmentationParams,
                                                SubjectSegmenter)
from skel_extract_ros.core.sequence import SequenceRegistration
from skel_extract_ros.core.stream import split_layout
from skel_extract_ros.codecs.depth_image import (DepthDecodeError, back_project, decode_depth, depth_to_cloud,
                                          encode_depth)
from skel_extract_ros.sim import generate_sequence


@pytest.fixture(scope='module')
def room():
    """The upper body moving in a room (floor, walls, a table, a lamp), and walking in."""
    return generate_sequence('upper_body', 24, scene='room', seed=4, progress=False)


def segment_all(clouds, params=None):
    segmenter = SubjectSegmenter(params)
    return [segmenter(*split_layout(cloud)) for cloud in clouds]


def scores(results, ground_truth):
    """Per frame: share of the measurable subject pixels kept, share of the kept pixels
    that are background (not the subject at all)."""
    kept, background = [], []
    for result, measured, subject in zip(results, ground_truth['subject_measured'],
                                         ground_truth['subject_mask']):
        mask = result.mask.reshape(measured.shape)
        kept.append(mask[measured].mean() if measured.any() else np.nan)
        background.append((mask & ~subject).sum() / max(mask.sum(), 1))
    return np.array(kept), np.array(background)


def test_the_moving_subject_is_kept_and_the_room_removed(room):
    results = segment_all(room.clouds)
    statuses = [r.status for r in results]
    # the subject is found as soon as it has moved (motion is the evidence), then always
    first = statuses.index(STATUS_SUBJECT)
    assert first <= 3 and all(s == STATUS_SUBJECT for s in statuses[first:])
    kept, background = scores(results[first:], {k: v[first:] for k, v in room.ground_truth.items()
                                                if k in ('subject_measured', 'subject_mask')})
    # the targets: >= 98 % of the subject kept, <= 1 % background, every frame
    assert kept.min() >= 0.98, kept
    assert background.max() <= 0.01, background
    # floor and walls are planes; the table and the lamp are still regions, never followed
    assert results[-1].n_planes >= 2
    assert results[-1].background_fraction > 0.8
    assert all(r.n_moving_regions == 1 for r in results[first:])


def test_a_vga_camera_is_segmented_on_the_working_grid_and_kept_at_full_resolution():
    """640x480 (a RealSense, an Xtion): the analysis runs on every 2nd row and column
    (max_pixels 320x240), the subject's mask comes back at full resolution with the same
    targets as a 320x240 camera: the cells' pixels that are off the subject's depths (the
    wall behind an arm) or on the floor are not kept."""
    vga = generate_sequence('upper_body', 12, scene='room', seed=4, resolution='640x480', progress=False)
    results = segment_all(vga.clouds)
    assert all(r.mask.shape == (640 * 480,) for r in results)
    first = [r.status for r in results].index(STATUS_SUBJECT)
    assert first <= 3 and all(r.status == STATUS_SUBJECT for r in results[first:])
    kept, background = scores(results[first:], {k: v[first:] for k, v in vga.ground_truth.items()
                                                if k in ('subject_measured', 'subject_mask')})
    assert kept.min() >= 0.98, kept
    assert background.max() <= 0.01, background
    # the grid's own answer upsampled, without the depth and plane checks, takes in the
    # background around the subject: the checks are what keeps it out
    grid = SubjectSegmenter(SegmentationParams(max_pixels=320 * 240))
    for cloud in vga.clouds:
        points, height, width = split_layout(cloud)
        coarse = grid._organized(points.reshape(height, width, 3)[::2, ::2].astype(np.float64),
                                 np.isfinite(points).all(axis=1).reshape(height, width)[::2, ::2])
    blocky = np.repeat(np.repeat(coarse.mask.reshape(240, 320), 2, axis=0), 2, axis=1)
    assert (blocky & ~vga.ground_truth['subject_mask'][-1]).sum() > 2 * (
        results[-1].mask.reshape(480, 640) & ~vga.ground_truth['subject_mask'][-1]).sum()


def test_same_subject_alone_and_in_the_room(room):
    """The room changes nothing about the subject found (the noise differs pixel by pixel
    between the two renderings, so the scores are compared, not the masks)."""
    alone = generate_sequence('upper_body', 24, scene='empty', seed=4, progress=False)
    truth = ('subject_measured', 'subject_mask')
    kept_room, background_room = scores(segment_all(room.clouds)[-5:],
                                        {k: room.ground_truth[k][-5:] for k in truth})
    kept_alone, background_alone = scores(segment_all(alone.clouds)[-5:],
                                          {k: alone.ground_truth[k][-5:] for k in truth})
    assert kept_room.min() >= 0.98 and kept_alone.min() >= 0.98
    assert abs(kept_room.mean() - kept_alone.mean()) < 0.01
    assert background_alone.max() == 0.0 and background_room.max() <= 0.01


def test_a_subject_walking_in_is_picked_up_when_it_appears():
    seq = generate_sequence('upper_body', 30, scene='room', seed=5, enter_frames=18, progress=False)
    results = segment_all(seq.clouds)
    visible = seq.ground_truth['subject_mask'].sum(axis=(1, 2))
    for result, pixels in zip(results, visible):
        if pixels == 0:   # nobody in view: nothing is taken for the subject
            assert result.status == STATUS_NOBODY and result.n_subject == 0
    assert results[-1].status == STATUS_SUBJECT
    kept, background = scores(results[-5:], {k: v[-5:] for k, v in seq.ground_truth.items()
                                             if k in ('subject_measured', 'subject_mask')})
    assert kept.min() >= 0.98 and background.max() <= 0.01
    # while it comes in it touches the image border: the rest pose waits for all of it
    entering = [r for r, pixels in zip(results, visible) if pixels > 0 and r.status == STATUS_SUBJECT]
    assert entering[0].touches_border and not results[-1].touches_border


def test_two_people_the_one_that_moves_most_is_followed(room):
    """Two moving subjects side by side (the second moving at half speed): two moving
    regions are reported and the faster one is the subject."""
    fast = room.clouds
    slow_source = generate_sequence('upper_body', 24, scene='empty', seed=4, progress=False)
    shift = 170      # pixels: the second person stands about 1 m to the right
    merged = []
    for f, cloud in enumerate(fast):
        slow = np.full_like(cloud, np.nan)
        slow[:, shift:] = slow_source.clouds[f // 2][:, :-shift]
        slow[..., 0] += (shift / 262.5) * slow[..., 2]        # consistent 3-D x for the shifted pixels
        closer = np.nan_to_num(slow[..., 2], nan=np.inf) < np.nan_to_num(cloud[..., 2], nan=np.inf)
        merged.append(np.where(closer[..., None], slow, cloud))
    results = segment_all(merged)
    assert max(r.n_moving_regions for r in results) == 2
    mask = results[-1].mask.reshape(fast[0].shape[:2])
    fast_subject = room.ground_truth['subject_mask'][-1]
    assert mask[fast_subject].mean() > 0.9 and (mask & ~fast_subject).sum() < 0.05 * mask.sum()


def test_nothing_moves_nobody_is_in_view(room):
    still = [room.clouds[0]] * 10
    results = segment_all(still)
    assert all(r.status == STATUS_NOBODY and r.n_subject == 0 for r in results)


def test_unorganized_clouds_take_planes_and_the_moving_cluster(room):
    results = segment_all([cloud.reshape(-1, 3)[np.isfinite(cloud.reshape(-1, 3)).all(axis=1)]
                           for cloud in room.clouds])
    assert results[-1].status == STATUS_SUBJECT
    # against the organized result as reference
    organized = segment_all(room.clouds)[-1]
    finite = np.isfinite(room.clouds[-1].reshape(-1, 3)).all(axis=1)
    reference = organized.mask[finite]
    agree = (results[-1].mask == reference).mean()
    assert agree > 0.97 and results[-1].mask[reference].mean() > 0.9


def test_disabled_keeps_every_valid_point(room):
    result = SubjectSegmenter(SegmentationParams(enabled=False))(*split_layout(room.clouds[0]))
    assert result.n_subject == np.isfinite(room.clouds[0][..., 2]).sum()
    with pytest.raises(ValueError, match='noise_sigmas'):
        SegmentationParams(noise_sigmas=0.0)


def test_rest_pose_is_built_from_the_subject_once_in_view():
    seq = generate_sequence('upper_body', 26, scene='room', seed=5, enter_frames=16, progress=False)
    registration = SequenceRegistration()
    registered = registration.register(seq.clouds)
    first = int(np.argmax(registration.statuses_ == 'ok'))
    # not before the subject is wholly in view
    assert first >= 16 - 3 and not registration.segmentation_[first].touches_border
    # the rest pose is the subject only: every rest point lies on the true surface
    surface = seq.ground_truth['surface_points'][first]
    from scipy.spatial import cKDTree
    distance, _ = cKDTree(surface).query(registration.rest_pose_.points)
    assert np.percentile(distance, 99) < 0.05
    assert np.isfinite(registered[first:]).all()


# -- depth images --------------------------------------------------------------------------
class Image:
    """A stand-in with sensor_msgs/Image's attributes (decoding needs no ROS)."""

    def __init__(self, depth, encoding, pad=0, bigendian=False):
        self.height, self.width, self.step, self.data = encode_depth(depth, encoding, pad, bigendian)
        self.encoding, self.is_bigendian = encoding, int(bigendian)


class Info:
    def __init__(self, height, width, fx=262.5, fy=262.5, cx=159.5, cy=119.5):
        self.height, self.width = height, width
        self.k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]


@pytest.mark.parametrize('layout, encoding, pad, bigendian, tolerance', [
    ('OpenNI / Kinect v1: 16UC1 mm', '16UC1', 0, False, 5e-4),
    ('RealSense: 16UC1 mm, rows padded to 64 bytes', '16UC1', 64 - (320 * 2) % 64, False, 5e-4),
    ('Azure Kinect: 32FC1 m', '32FC1', 0, False, 1e-6),
    ('32FC1 big-endian with padding', '32FC1', 12, True, 1e-6),
    ('mono16 mm, big-endian', 'mono16', 0, True, 5e-4),
])
def test_depth_images_of_every_driver_layout(room, layout, encoding, pad, bigendian, tolerance):
    truth = room.clouds[5][..., 2].astype(np.float64)
    image = Image(truth, encoding, pad, bigendian)
    depth = decode_depth(image)
    assert depth.shape == truth.shape
    np.testing.assert_array_equal(np.isnan(depth), np.isnan(truth))      # 0 / NaN = no return
    assert np.nanmax(np.abs(depth - truth)) <= tolerance, layout
    cloud = depth_to_cloud(image, Info(*truth.shape))
    np.testing.assert_allclose(cloud, room.clouds[5], atol=tolerance * 1.5, equal_nan=True)


def test_depth_image_errors_are_clear():
    image = Image(np.ones((4, 6)), '16UC1')
    image.encoding = 'rgb8'
    with pytest.raises(DepthDecodeError, match='rgb8'):
        decode_depth(image)
    image = Image(np.ones((4, 6)), '16UC1')
    image.data = image.data[:10]
    with pytest.raises(DepthDecodeError, match='truncated'):
        decode_depth(image)
    image = Image(np.ones((4, 6)), '16UC1')
    image.step = 4
    with pytest.raises(DepthDecodeError, match='step'):
        decode_depth(image)
    with pytest.raises(DepthDecodeError, match='camera_info is 5x6'):
        depth_to_cloud(Image(np.ones((4, 6)), '16UC1'), Info(5, 6))
    with pytest.raises(DepthDecodeError, match='K'):
        depth_to_cloud(Image(np.ones((4, 6)), '16UC1'), Info(4, 6, fx=0.0))


def test_back_projection_is_the_pinhole_model():
    depth = np.full((3, 4), 2.0, dtype=np.float32)
    cloud = back_project(depth, 100.0, 50.0, 1.5, 1.0)
    np.testing.assert_allclose(cloud[0, 0], [(0 - 1.5) * 2 / 100, (0 - 1.0) * 2 / 50, 2.0])
    np.testing.assert_allclose(cloud[2, 3], [(3 - 1.5) * 2 / 100, (2 - 1.0) * 2 / 50, 2.0])


def test_the_fast_opening_is_scipy_s_binary_opening_up_to_the_image_border():
    from scipy import ndimage

    from skel_extract_ros.core.segmentation.organized import _opening3x3
    rng = np.random.default_rng(4)
    for density in (0.3, 0.7, 0.95):
        mask = rng.uniform(size=(60, 80)) < density
        mask[:, :3] = True                      # blobs touching the border
        expected = ndimage.binary_opening(mask, structure=np.ones((3, 3), bool))
        np.testing.assert_array_equal(_opening3x3(mask), expected)
    for shape in ((1, 10), (2, 5), (3, 3), (4, 1)):     # images thinner than the structure
        for mask in (np.ones(shape, bool), rng.uniform(size=shape) < 0.8):
            expected = ndimage.binary_opening(mask, structure=np.ones((3, 3), bool))
            np.testing.assert_array_equal(_opening3x3(mask), expected)
