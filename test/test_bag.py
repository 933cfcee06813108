"""Bag writing and reading with rosbags, for directories and bare .mcap files."""
import numpy as np
import pytest

from skel_extract_ros.codecs.bag import (BagError, cloud_topics, read_cloud_frames, select_cloud_topic,
                                  typestore, write_cloud_bag)
from rosbags.rosbag2 import StoragePlugin, Writer


def test_round_trip_directory_and_bare_mcap(tmp_path):
    rng = np.random.default_rng(0)
    clouds = [rng.normal(size=(6, 8, 3)).astype(np.float32) for _ in range(4)]
    clouds[1][2, 3] = np.nan
    stamps = np.array([10, 20, 30, 40], dtype=np.int64) * 10**9 + 5
    bag = write_cloud_bag(tmp_path / 'bag', clouds, stamps, 'cam', topic='/points')
    frames = list(read_cloud_frames(bag))
    assert [f.stamp_ns for f in frames] == list(stamps)
    assert all(f.frame_id == 'cam' and (f.height, f.width) == (6, 8) for f in frames)
    np.testing.assert_array_equal(frames[1].points.reshape(6, 8, 3), clouds[1])
    mcap_file = next(bag.glob('*.mcap'))
    assert cloud_topics(mcap_file) == {'/points': 4}
    np.testing.assert_array_equal(list(read_cloud_frames(mcap_file))[3].points, frames[3].points)


def test_sqlite3_bag_is_read(tmp_path):
    from skel_extract_ros.codecs.bag import _make_pointcloud2
    store = typestore()
    path = tmp_path / 'sqlite_bag'
    with Writer(path, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        conn = writer.add_connection('/cloud', 'sensor_msgs/msg/PointCloud2', typestore=store)
        for i in range(3):
            msg = _make_pointcloud2(np.full((5, 3), i, np.float32), 10**9 * (i + 1), 'f')
            writer.write(conn, 10**9 * (i + 1), store.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2'))
    frames = list(read_cloud_frames(path))
    assert len(frames) == 3 and frames[2].points[0, 0] == 2


def test_topic_selection_errors(tmp_path):
    bag = write_cloud_bag(tmp_path / 'b', [np.zeros((3, 3), np.float32)], [1], 'f', topic='/a')
    assert select_cloud_topic(bag) == '/a'
    with pytest.raises(BagError, match='no PointCloud2 topic /b'):
        select_cloud_topic(bag, '/b')
    with pytest.raises(BagError, match='does not exist'):
        list(read_cloud_frames(tmp_path / 'missing'))
    (tmp_path / 'empty_dir').mkdir()
    with pytest.raises(BagError, match='metadata.yaml'):
        cloud_topics(tmp_path / 'empty_dir')
    with pytest.raises(BagError, match='already exists'):
        write_cloud_bag(bag, [], [], 'f')


def test_bag_without_clouds(tmp_path):
    store = typestore()
    path = tmp_path / 'strings'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection('/chatter', 'std_msgs/msg/String', typestore=store)
        msg = store.types['std_msgs/msg/String'](data='hi')
        writer.write(conn, 1, store.serialize_cdr(msg, 'std_msgs/msg/String'))
    with pytest.raises(BagError, match='no sensor_msgs/msg/PointCloud2'):
        list(read_cloud_frames(path))


def test_sample_bag_matches_its_ground_truth(sample_bag):
    gt = np.load(sample_bag / 'gt.npz')
    frames = list(read_cloud_frames(sample_bag))
    assert len(frames) == len(gt['stamps']) >= 30
    np.testing.assert_array_equal([f.stamp_ns for f in frames], gt['stamps_ns'])
    assert frames[0].frame_id == 'camera_depth_optical_frame'
    assert (frames[0].height, frames[0].width) == (240, 320)
    size = sum(p.stat().st_size for p in sample_bag.iterdir())
    assert size < 8 * 2**20, f'sample bag is {size / 2**20:.1f} MiB'
