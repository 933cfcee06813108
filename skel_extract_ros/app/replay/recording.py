"""What a replay records: the nodes' output topics, written raw into the MCAP file and
decoded into `Received` (stamps, points, joints, the skeleton's documents, diagnostics)."""
from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field

import numpy as np

NODES = ('registration_node', 'accumulator_node', 'joint_estimation_node')
# (relative topic, message type, latched)
OUTPUT_TOPICS = (
    ('registered_points', 'sensor_msgs/msg/PointCloud2', False),
    ('filtered_points', 'sensor_msgs/msg/PointCloud2', False),
    ('rest_points', 'sensor_msgs/msg/PointCloud2', True),
    ('skeleton/structure', 'std_msgs/msg/String', True),
    ('skeleton/description', 'std_msgs/msg/String', True),
    ('skeleton/joints', 'geometry_msgs/msg/PoseArray', False),
    ('skeleton/trajectory', 'trajectory_msgs/msg/MultiDOFJointTrajectory', False),
    ('skeleton/confidence', 'std_msgs/msg/String', False),
    ('skeleton/markers', 'visualization_msgs/msg/MarkerArray', False),
    ('skeleton/posed_points', 'sensor_msgs/msg/PointCloud2', False),
    ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray', False),     # every node's health, 1 Hz
)

RECORDED_ONLY = ('skeleton/markers', 'skeleton/trajectory')


@dataclass
class Received:
    """What came back from the nodes, keyed by header stamp (ns); times are perf_counter s."""

    published_at: dict = field(default_factory=dict)      # input stamp -> publish time
    filtered: dict = field(default_factory=dict)          # stamp -> (N, 3)
    filtered_at: dict = field(default_factory=dict)
    registered: dict = field(default_factory=dict)        # stamp -> (M, 3)
    registered_at: dict = field(default_factory=dict)
    joints: dict = field(default_factory=dict)            # stamp -> (J, 3), last received
    joint_names: dict = field(default_factory=dict)       # stamp -> its joints' names (skeleton/confidence)
    confidence: dict = field(default_factory=dict)        # stamp -> (J,) its joints' confidence
    interpolated: set = field(default_factory=set)        # stamps whose joints were interpolated
    structures: list = field(default_factory=list)        # every skeleton/structure, in order
    descriptions: list = field(default_factory=list)      # every skeleton/description, in order
    joints_at: dict = field(default_factory=dict)
    rest: np.ndarray | None = None
    structure: dict | None = None
    description: dict | None = None
    description_at: float | None = None                   # when the first one came: tracking from then
    frame_id: str = ''
    counts: dict = field(default_factory=dict)            # topic -> messages
    accumulator: dict = field(default_factory=dict)       # its newest /diagnostics values (str)
    accumulator_reports: int = 0                          # how many of those came
    registration: dict = field(default_factory=dict)      # the registration node's, the same


def _ros_type(name: str):
    package, _, message = name.split('/')
    module = __import__(f'{package}.msg', fromlist=[message])
    return getattr(module, message)


class _Recorder:
    """rclpy node: publishes the input clouds, records and decodes every output."""

    def __init__(self, node, writer, store, received: Received, depth_image: bool = False,
                 lossless: bool = True):
        from rclpy.serialization import deserialize_message

        from ...nodes.common import LATCHED_QOS, SENSOR_QOS, STREAM_QOS
        input_qos = STREAM_QOS if lossless else SENSOR_QOS     # realtime: as a camera driver
        self.node, self.writer, self.received = node, writer, received
        self._deserialize = deserialize_message
        self.condition = threading.Condition()
        if depth_image:
            self.publisher = node.create_publisher(_ros_type('sensor_msgs/msg/Image'), 'depth/image', input_qos)
            self.info_publisher = node.create_publisher(_ros_type('sensor_msgs/msg/CameraInfo'),
                                                        'depth/camera_info', input_qos)
        else:
            self.publisher = node.create_publisher(_ros_type('sensor_msgs/msg/PointCloud2'), 'points', input_qos)
            self.info_publisher = None
        self.connections = {}
        for topic, type_name, latched in OUTPUT_TOPICS:
            resolved = node.resolve_topic_name(topic)
            self.connections[topic] = writer.add_connection(resolved, type_name, typestore=store)
            node.create_subscription(_ros_type(type_name), topic,
                                     lambda raw, t=topic, n=type_name: self._on_message(t, n, raw),
                                     LATCHED_QOS if latched else STREAM_QOS, raw=True)

    def _on_message(self, topic: str, type_name: str, raw: bytes) -> None:
        from ...codecs.messages import pose_array_positions, stamp_ns
        from ...codecs.pointcloud import decode_xyz
        now = time.perf_counter()
        self.writer.write(self.connections[topic], time.time_ns(), raw)
        # markers and trajectory are recorded only: the files do not need them
        msg = None if topic in RECORDED_ONLY else self._deserialize(raw, _ros_type(type_name))
        r = self.received
        with self.condition:
            r.counts[topic] = r.counts.get(topic, 0) + 1
            if topic == 'filtered_points':
                stamp = stamp_ns(msg.header)
                r.filtered[stamp], r.filtered_at[stamp] = decode_xyz(msg), now
            elif topic == 'registered_points':
                stamp = stamp_ns(msg.header)
                r.registered[stamp], r.registered_at[stamp] = decode_xyz(msg), now
                r.frame_id = msg.header.frame_id
            elif topic == 'rest_points':
                r.rest = decode_xyz(msg, dtype=np.float64)
            elif topic == 'skeleton/structure':
                r.structure = json.loads(msg.data)
                r.structures.append(r.structure)
            elif topic == 'skeleton/description':
                r.description = json.loads(msg.data)
                r.descriptions.append(r.description)
                if r.description_at is None:
                    r.description_at = now
            elif topic == 'skeleton/joints':
                stamp = stamp_ns(msg.header)
                r.joints[stamp], r.joints_at[stamp] = pose_array_positions(msg), now
            elif topic == 'skeleton/confidence':
                # which skeleton's joints a frame has: a PoseArray says nothing of it
                document = json.loads(msg.data)
                r.joint_names[int(document['stamp_ns'])] = document['joint_names']
                r.confidence[int(document['stamp_ns'])] = document['confidence']
                if document.get('interpolated'):
                    r.interpolated.add(int(document['stamp_ns']))
            elif topic == '/diagnostics':
                for status in msg.status:
                    if status.name.endswith('/accumulator_node'):
                        r.accumulator = {kv.key: kv.value for kv in status.values}
                        r.accumulator_reports += 1
                    elif status.name.endswith('/registration_node'):
                        r.registration = {kv.key: kv.value for kv in status.values}
            self.condition.notify_all()

    def wait_for(self, predicate, timeout: float, alive=None) -> bool:
        deadline = time.monotonic() + timeout
        with self.condition:
            while not predicate():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                if alive is not None:
                    alive()
                self.condition.wait(min(remaining, 0.2))
        return True
