"""Reading and writing ROS 2 bags of point clouds with rosbags (no ROS install needed).

Accepted inputs: a rosbag2 directory (mcap or sqlite3 storage, with metadata.yaml) or a
bare .mcap file, holding sensor_msgs/PointCloud2 clouds or sensor_msgs/Image depth images
with their CameraInfo (back-projected to the same organized clouds). Clouds come out as
numpy arrays with their header stamp and frame_id.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from .depth_image import DepthDecodeError, depth_to_cloud, encode_depth
from .pointcloud import CloudDecodeError, decode_xyz, pointcloud2
from .stamps import stamp_to_ns

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
IMAGE = 'sensor_msgs/msg/Image'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
DEFAULT_TOPIC = '/camera/depth/points'
DEFAULT_DEPTH_TOPIC = '/camera/depth/image_raw'

_TYPESTORE = None


def typestore():
    """The ROS 2 Jazzy message definitions (shared, built once)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


class BagError(ValueError):
    """A bag that cannot be used; the message is one line meant for the user."""


@dataclass
class CloudFrame:
    """One PointCloud2 from a bag.

    points: (height * width, 3) float32 metres, invalid points kept as NaN.
    """

    index: int
    stamp_ns: int
    frame_id: str
    points: np.ndarray
    height: int
    width: int

    @property
    def stamp(self) -> float:
        return self.stamp_ns * 1e-9


def _make_pointcloud2(points: np.ndarray, stamp_ns: int, frame_id: str, point_step: int = 16):
    types = typestore().types
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=stamp_ns // 1_000_000_000,
                                                   nanosec=stamp_ns % 1_000_000_000),
        frame_id=frame_id)
    return pointcloud2(types[POINTCLOUD2], types['sensor_msgs/msg/PointField'], header, points, point_step,
                       data_as_array=True)


def write_cloud_bag(path, clouds, stamps_ns, frame_id: str, topic: str = DEFAULT_TOPIC,
                    point_step: int = 16) -> Path:
    """Write clouds ((H, W, 3) organized or (N, 3)) as a zstd-compressed mcap rosbag2 directory.

    The bag receive time of each message equals its header stamp. Raises BagError if `path`
    exists already.
    """
    path = Path(path)
    if path.exists():
        raise BagError(f'{path} already exists; choose a new output path or remove it')
    if len(clouds) != len(stamps_ns):
        raise ValueError('one stamp per cloud is required')
    store = typestore()
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        connection = writer.add_connection(topic, POINTCLOUD2, typestore=store)
        for points, stamp_ns in zip(clouds, stamps_ns):
            msg = _make_pointcloud2(points, int(stamp_ns), frame_id, point_step)
            writer.write(connection, int(stamp_ns), store.serialize_cdr(msg, POINTCLOUD2))
    return path


def camera_info_topic(image_topic: str) -> str:
    """The CameraInfo topic drivers publish beside a depth image topic
    (/camera/depth/image_raw -> /camera/depth/camera_info)."""
    return image_topic.rsplit('/', 1)[0] + '/camera_info'


def write_depth_bag(path, depths, stamps_ns, frame_id: str, intrinsics: tuple,
                    topic: str = DEFAULT_DEPTH_TOPIC, encoding: str = '16UC1') -> Path:
    """Write (H, W) depth images in metres (NaN = no return) as sensor_msgs/Image with a
    CameraInfo per frame (intrinsics = (fx, fy, cx, cy)), as a depth driver records them."""
    path = Path(path)
    if path.exists():
        raise BagError(f'{path} already exists; choose a new output path or remove it')
    store = typestore()
    types = store.types
    fx, fy, cx, cy = intrinsics
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        image_connection = writer.add_connection(topic, IMAGE, typestore=store)
        info_connection = writer.add_connection(camera_info_topic(topic), CAMERA_INFO, typestore=store)
        for depth, stamp_ns in zip(depths, stamps_ns):
            stamp_ns = int(stamp_ns)
            header = types['std_msgs/msg/Header'](
                stamp=types['builtin_interfaces/msg/Time'](sec=stamp_ns // 1_000_000_000,
                                                           nanosec=stamp_ns % 1_000_000_000),
                frame_id=frame_id)
            height, width, step, data = encode_depth(depth, encoding)
            image = types[IMAGE](header=header, height=height, width=width, encoding=encoding,
                                 is_bigendian=0, step=step, data=np.frombuffer(data, dtype=np.uint8))
            roi = types['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0,
                                                            do_rectify=False)
            info = types[CAMERA_INFO](
                header=header, height=height, width=width, distortion_model='plumb_bob',
                d=np.zeros(5), k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], float),
                r=np.eye(3).reshape(-1), p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], float),
                binning_x=0, binning_y=0, roi=roi)
            writer.write(info_connection, stamp_ns, store.serialize_cdr(info, CAMERA_INFO))
            writer.write(image_connection, stamp_ns, store.serialize_cdr(image, IMAGE))
    return path


def _check_input(path: Path) -> None:
    if not path.exists():
        raise BagError(f'input {path} does not exist')
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        raise BagError(f'{path} is a directory without metadata.yaml, not a rosbag2 bag')
    if path.is_file() and path.suffix != '.mcap':
        raise BagError(f'{path} is not a rosbag2 directory or an .mcap file')


def _topics(path: Path) -> dict:
    """{topic: (message type, count)} of a bag."""
    _check_input(path)
    if path.is_file():
        from mcap.reader import make_reader
        with open(path, 'rb') as stream:
            summary = make_reader(stream).get_summary()
        if summary is None:
            raise BagError(f'{path} has no summary section; is it a complete mcap file?')
        schemas = {sid: s.name for sid, s in summary.schemas.items()}
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        return {c.topic: (schemas.get(c.schema_id, ''), int(counts.get(cid, 0)))
                for cid, c in summary.channels.items()}
    try:
        with Reader(path) as reader:
            return {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
    except Exception as error:  # rosbags raises several types for unreadable bags
        raise BagError(f'cannot read bag {path}: {error}') from error


def topic_counts(path) -> dict:
    """{topic: message count} of every topic of a bag directory or an .mcap file."""
    return {topic: n for topic, (_, n) in _topics(Path(path)).items()}


def cloud_topics(path) -> dict:
    """{topic: message count} of the topics a cloud can be read from: PointCloud2 topics,
    and Image topics that have a CameraInfo topic beside them (depth images)."""
    topics = _topics(Path(path))
    clouds = {t: n for t, (kind, n) in topics.items() if kind == POINTCLOUD2}
    depth = {t: n for t, (kind, n) in topics.items()
             if kind == IMAGE and topics.get(camera_info_topic(t), ('',))[0] == CAMERA_INFO}
    return {**clouds, **depth}


def is_depth_topic(path, topic: str) -> bool:
    return _topics(Path(path)).get(topic, ('',))[0] == IMAGE


def select_cloud_topic(path, topic: str | None = None) -> str:
    """The topic to read clouds from: `topic` if given and present, else the only
    PointCloud2 topic, else the only depth image topic (with its camera_info)."""
    topics = cloud_topics(path)
    if topic is not None:
        if topic not in topics:
            listed = ', '.join(topics) or 'none'
            raise BagError(f'bag {path} has no PointCloud2 topic {topic} and no depth image topic of that '
                           f'name (usable topics: {listed})')
        return topic
    if not topics:
        raise BagError(f'bag {path} contains no sensor_msgs/msg/PointCloud2 messages and no depth '
                       'images (sensor_msgs/msg/Image with a camera_info topic beside them)')
    clouds = [t for t in topics if not is_depth_topic(path, t)]
    candidates = clouds or list(topics)
    if len(candidates) > 1:
        for preferred in (DEFAULT_TOPIC, DEFAULT_DEPTH_TOPIC):
            if preferred in candidates:
                return preferred
        raise BagError(f'bag {path} has several cloud topics ({", ".join(candidates)}); pass --topic')
    return candidates[0]


def _raw_messages(path: Path, topic: str) -> Iterator[tuple]:
    """(receive time ns, CDR bytes) of one topic, in bag order."""
    if path.is_file():
        from mcap.reader import make_reader
        with open(path, 'rb') as stream:
            for _schema, _channel, message in make_reader(stream).iter_messages(topics=[topic]):
                yield message.log_time, message.data
        return
    with Reader(path) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        for _connection, timestamp, raw in reader.messages(connections=connections):
            yield timestamp, raw


def read_cloud_frames(path, topic: str | None = None) -> Iterator[CloudFrame]:
    """Yield every cloud on `topic` (see `select_cloud_topic`) as a CloudFrame: a
    PointCloud2 as it is, a depth image back-projected with the latest CameraInfo.

    A message that cannot be decoded raises BagError naming its index and the reason.
    """
    path = Path(path)
    topic = select_cloud_topic(path, topic)
    store = typestore()
    if is_depth_topic(path, topic):
        yield from _read_depth_frames(path, topic, store)
        return
    for index, (_timestamp, raw) in enumerate(_raw_messages(path, topic)):
        msg = store.deserialize_cdr(raw, POINTCLOUD2)
        try:
            points = decode_xyz(msg)
        except CloudDecodeError as error:
            raise BagError(f'message {index} on {topic}: {error}') from error
        yield CloudFrame(index, stamp_to_ns(msg.header.stamp), msg.header.frame_id, points,
                         int(msg.height), int(msg.width))


def _read_depth_frames(path: Path, topic: str, store) -> Iterator[CloudFrame]:
    info_topic = camera_info_topic(topic)
    infos = [store.deserialize_cdr(raw, CAMERA_INFO) for _t, raw in _raw_messages(path, info_topic)]
    if not infos:
        raise BagError(f'bag {path}: no CameraInfo on {info_topic} for the depth images on {topic}')
    info_stamps = np.array([stamp_to_ns(info.header.stamp) for info in infos])
    for index, (_timestamp, raw) in enumerate(_raw_messages(path, topic)):
        msg = store.deserialize_cdr(raw, IMAGE)
        stamp = stamp_to_ns(msg.header.stamp)
        # the latest camera info at or before the image (the first one for early images)
        info = infos[max(int(np.searchsorted(info_stamps, stamp, side='right')) - 1, 0)]
        try:
            cloud = depth_to_cloud(msg, info)
        except DepthDecodeError as error:
            raise BagError(f'message {index} on {topic}: {error}') from error
        yield CloudFrame(index, stamp, msg.header.frame_id, cloud.reshape(-1, 3),
                         cloud.shape[0], cloud.shape[1])
