"""The registration node in a room, from clouds and from depth images (real DDS, in process)."""
import numpy as np
import pytest
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger

from ros_harness import cloud, header, stamps_of
from skel_extract_ros.core.segmentation import SegmentationParams
from skel_extract_ros.core.sequence import SequenceRegistration
from skel_extract_ros.codecs.depth_image import encode_depth
from skel_extract_ros.nodes.common import LATCHED_QOS, STREAM_QOS
from skel_extract_ros.nodes.registration_node import RegistrationNode
from skel_extract_ros.core.rest_pose import RestPoseParams
from skel_extract_ros.codecs.pointcloud import decode_xyz
from skel_extract_ros.sim import generate_sequence

from rclpy.parameter import Parameter

N_POINTS = 600


@pytest.fixture(scope='module')
def walk_in():
    """The upper body in a room, walking into the view over the first 10 frames."""
    return generate_sequence('upper_body', 16, scene='room', seed=6, enter_frames=10, progress=False)


def registration_node(ros, **extra):
    overrides = [Parameter('rest_pose.n_points', value=N_POINTS)]
    overrides += [Parameter(k, value=v) for k, v in extra.items()]
    return ros.add(RegistrationNode, parameter_overrides=overrides)


def depth_messages(depth, stamp_ns, intrinsics, encoding='16UC1', pad=0):
    height, width, step, data = encode_depth(depth, encoding, pad)
    image = Image(header=header(stamp_ns), height=height, width=width, encoding=encoding,
                  is_bigendian=0, step=step, data=data)
    _, _, fx, fy, cx, cy = intrinsics
    info = CameraInfo(header=header(stamp_ns), height=height, width=width, distortion_model='plumb_bob',
                      d=[0.0] * 5, k=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0])
    return image, info


def offline(sequence, clouds):
    """The same frames through the offline pipeline objects (`skel-extract run`)."""
    registration = SequenceRegistration(rest_params=RestPoseParams(n_points=N_POINTS),
                                        segmentation_params=SegmentationParams())
    return registration, registration.register(clouds)


def check_against_offline(ros, sequence, filtered, registered, clouds):
    registration, points = offline(sequence, clouds)
    ok = np.flatnonzero(registration.statuses_ == 'ok')
    # a rest pose chosen when the stream went quiet is published before its held frames
    # are registered: they follow it, on the registration stage's thread
    ros.wait(lambda: len(registered) >= len(ok), what=f'{len(ok)} registered frames')
    assert stamps_of(registered) == list(sequence.stamps_ns[ok])
    np.testing.assert_allclose(np.stack([decode_xyz(m) for m in registered]), points[ok], atol=1e-4)
    # filtered_points is the subject: every filtered point of the last frame lies on it
    subject = decode_xyz(filtered[-1])
    surface = sequence.ground_truth['surface_points'][-1]
    from scipy.spatial import cKDTree
    distance, _ = cKDTree(surface).query(subject)
    assert np.percentile(distance, 99) < 0.05 and len(subject) > 1000


def publish_one_at_a_time(ros, node, filtered, sequence):
    """The sequence's clouds on `points`, each once the node has handled the one before;
    returns the publisher."""
    pub = ros.publisher('points', PointCloud2, QoSProfile(depth=10))
    ros.wait_matched(pub)
    for i, (points, stamp) in enumerate(zip(sequence.clouds, sequence.stamps_ns)):
        pub.publish(cloud(points, stamp))
        # one at a time: the node publishes filtered_points before it registers, and a
        # cloud right behind would replace a frame still waiting for the registration
        ros.wait(lambda: len(filtered) == i + 1 and node.stages.processed == i + 1, what=f'frame {i} handled')
    return pub


def test_node_in_a_room_waits_for_the_subject_and_registers_only_it(ros, walk_in, monkeypatch):
    from skel_extract_ros.nodes import registration_process as module
    # the rest pose process ends at the first frame with nobody in view, starts again when
    # the subject moves in
    monkeypatch.setattr(module, 'REST_POSE_IDLE_RELEASE_S', 0.0)
    node = registration_node(ros)
    assert node.stages.rest_pose_process.is_warm
    registered = ros.listen('registered_points', PointCloud2, STREAM_QOS)
    filtered = ros.listen('filtered_points', PointCloud2, STREAM_QOS)
    rests = ros.listen('rest_points', PointCloud2, LATCHED_QOS)
    pub = publish_one_at_a_time(ros, node, filtered, walk_in)
    ros.wait(lambda: len(rests) == 1, what='rest pose')
    # nobody in view at first: said (throttled), nothing registered, no rest pose from the room
    assert any('nobody in view' in line for line in node.log.history)
    assert len(decode_xyz(filtered[0])) == 0
    # ended with nobody in view, started again when the subject came, ended with its rest pose
    assert node.stages.rest_pose_process.starts >= 2 and not node.stages.rest_pose_process.is_warm
    check_against_offline(ros, walk_in, filtered, registered, walk_in.clouds)
    # the camera moved: forget the scene, keep going
    done = ros.call(Trigger, 'registration_node/reset_background')
    assert done.success
    pub.publish(cloud(walk_in.clouds[-1], walk_in.stamps_ns[-1] + 33_333_333))
    ros.wait(lambda: len(filtered) == len(walk_in.clouds) + 1, what='frame after the reset')


def test_a_frame_slow_to_segment_is_not_taken_for_a_pause(ros, walk_in):
    """The rest pose is chosen from the frames held once the stream pauses; a frame that
    takes longer than that pause to segment (a loaded machine) is still the stream: the
    choice waits for it and the frames after it, as `run` does."""
    import time
    from skel_extract_ros.nodes.registration_stages import CHOICE_QUIET_S
    node = registration_node(ros)
    finder, calls = node.stages.subject_finder, []

    def slow_eleventh_frame(raw, height, width):
        calls.append(len(calls))
        if len(calls) == 11:     # the subject in view, frames held for the choice
            time.sleep(2.0 * CHOICE_QUIET_S)
        return finder(raw, height, width)

    node.stages.subject_finder = slow_eleventh_frame
    registered = ros.listen('registered_points', PointCloud2, STREAM_QOS)
    filtered = ros.listen('filtered_points', PointCloud2, STREAM_QOS)
    publish_one_at_a_time(ros, node, filtered, walk_in)
    assert len(calls) == len(walk_in.clouds)
    check_against_offline(ros, walk_in, filtered, registered, walk_in.clouds)


def test_node_reads_depth_images(ros, walk_in):
    node = registration_node(ros, input='depth_image')
    registered = ros.listen('registered_points', PointCloud2, STREAM_QOS)
    filtered = ros.listen('filtered_points', PointCloud2, STREAM_QOS)
    images = ros.publisher('depth/image', Image, QoSProfile(depth=10))
    infos = ros.publisher('depth/camera_info', CameraInfo, QoSProfile(depth=10))
    ros.wait_matched(images)
    ros.wait_matched(infos)
    # an image before any camera info is ignored with a warning
    first_image, _ = depth_messages(walk_in.clouds[0][..., 2], walk_in.stamps_ns[0] - 33_333_333,
                                    walk_in.ground_truth['intrinsics'])
    images.publish(first_image)
    ros.wait(lambda: any('CameraInfo' in line for line in node.log.history), what='no camera info warning')
    depths = []
    ros.wait(lambda: node.stages.processed == 1, what='the image without camera info handled')
    for i, (points, stamp) in enumerate(zip(walk_in.clouds, walk_in.stamps_ns)):
        # RealSense-style rows padded to 64 bytes
        image, info = depth_messages(points[..., 2], stamp, walk_in.ground_truth['intrinsics'], pad=64 - 640 % 64)
        infos.publish(info)
        images.publish(image)
        # one at a time: the node publishes filtered_points before it registers, and a
        # cloud right behind would replace a frame still waiting for the registration
        ros.wait(lambda: len(filtered) == i + 1 and node.stages.processed == i + 2, what=f'frame {i} handled')
        depths.append(points)
    # the depth-image path is the cloud path after millimetre rounding
    from skel_extract_ros.codecs.depth_image import back_project, decode_depth
    _, _, fx, fy, cx, cy = walk_in.ground_truth['intrinsics']
    rounded = [back_project(decode_depth(depth_messages(c[..., 2], 0, walk_in.ground_truth['intrinsics'])[0]),
                            fx, fy, cx, cy) for c in walk_in.clouds]
    check_against_offline(ros, walk_in, filtered, registered, rounded)
