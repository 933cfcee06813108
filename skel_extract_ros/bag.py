"""Reading and writing ROS 2 bags of point clouds with rosbags (no ROS install needed).

Accepted inputs: a rosbag2 directory (mcap or sqlite3 storage, with metadata.yaml) or a
bare .mcap file. Clouds come out as numpy arrays with their header stamp and frame_id.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from .pointcloud import CloudDecodeError, decode_xyz, encode_xyz, xyz_cloud_fields

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
DEFAULT_TOPIC = '/camera/depth/points'

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


def stamp_to_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _make_pointcloud2(points: np.ndarray, stamp_ns: int, frame_id: str, point_step: int = 16):
    store = typestore()
    types = store.types
    height, width, point_step, row_step, data, is_dense = encode_xyz(points, point_step)
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=stamp_ns // 1_000_000_000,
                                                   nanosec=stamp_ns % 1_000_000_000),
        frame_id=frame_id)
    fields = [types['sensor_msgs/msg/PointField'](name=n, offset=o, datatype=d, count=c)
              for n, o, d, c in xyz_cloud_fields(point_step)]
    return types[POINTCLOUD2](header=header, height=height, width=width, fields=fields,
                              is_bigendian=False, point_step=point_step, row_step=row_step,
                              data=np.frombuffer(data, dtype=np.uint8), is_dense=is_dense)


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


def _check_input(path: Path) -> None:
    if not path.exists():
        raise BagError(f'input {path} does not exist')
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        raise BagError(f'{path} is a directory without metadata.yaml, not a rosbag2 bag')
    if path.is_file() and path.suffix != '.mcap':
        raise BagError(f'{path} is not a rosbag2 directory or an .mcap file')


def cloud_topics(path) -> dict:
    """{topic: message count} of the PointCloud2 topics in a bag."""
    path = Path(path)
    _check_input(path)
    if path.is_file():
        from mcap.reader import make_reader
        with open(path, 'rb') as stream:
            summary = make_reader(stream).get_summary()
        if summary is None:
            raise BagError(f'{path} has no summary section; is it a complete mcap file?')
        schemas = {sid: s.name for sid, s in summary.schemas.items()}
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        return {c.topic: int(counts.get(cid, 0)) for cid, c in summary.channels.items()
                if schemas.get(c.schema_id) == POINTCLOUD2}
    try:
        with Reader(path) as reader:
            return {c.topic: c.msgcount for c in reader.connections if c.msgtype == POINTCLOUD2}
    except Exception as error:  # rosbags raises several types for unreadable bags
        raise BagError(f'cannot read bag {path}: {error}') from error


def select_cloud_topic(path, topic: str | None = None) -> str:
    """The PointCloud2 topic to read: `topic` if given and present, else the only one."""
    topics = cloud_topics(path)
    if topic is not None:
        if topic not in topics:
            listed = ', '.join(topics) or 'none'
            raise BagError(f'bag {path} has no PointCloud2 topic {topic} (PointCloud2 topics: {listed})')
        return topic
    if not topics:
        raise BagError(f'bag {path} contains no sensor_msgs/msg/PointCloud2 messages')
    if len(topics) > 1:
        if DEFAULT_TOPIC in topics:
            return DEFAULT_TOPIC
        raise BagError(f'bag {path} has several PointCloud2 topics ({", ".join(topics)}); pass --topic')
    return next(iter(topics))


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
    """Yield every PointCloud2 on `topic` (see `select_cloud_topic`) as a CloudFrame.

    A message that cannot be decoded raises BagError naming its index and the reason.
    """
    path = Path(path)
    topic = select_cloud_topic(path, topic)
    store = typestore()
    for index, (_timestamp, raw) in enumerate(_raw_messages(path, topic)):
        msg = store.deserialize_cdr(raw, POINTCLOUD2)
        try:
            points = decode_xyz(msg)
        except CloudDecodeError as error:
            raise BagError(f'message {index} on {topic}: {error}') from error
        yield CloudFrame(index, stamp_to_ns(msg.header.stamp), msg.header.frame_id, points,
                         int(msg.height), int(msg.width))
