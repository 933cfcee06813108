"""In-process rclpy on a private domain: nodes under test, a probe node that publishes and
records, and predicate waits (never fixed sleeps)."""
import os
import threading
import time

import rclpy
from rcl_interfaces.msg import Log
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from skel_extract_ros.codecs.pointcloud import pointcloud2

from ros_domains import private_domain

# Stamps of the hand-made sequences: the first frame and the 30 Hz period, ns.
T0 = 1_700_000_000_000_000_000
DT = 33_333_333


class Harness:
    """Each node spun by a SingleThreadedExecutor on a thread of its own, as `rclpy.spin`
    spins each installed node in its process: callbacks of one node never overlap, those of
    different nodes do. A callback runs inside spin_once, so once the threads are joined no
    callback is in flight (a pool executor's could still run while close() destroys its
    node: an rclpy InvalidHandle that nobody retrieves, printed at interpreter exit)."""

    def __init__(self):
        os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        # private domain per test process so parallel runs and other graphs never mix
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=private_domain())
        self._stop = threading.Event()
        self._spinners = []
        self.nodes = []
        self.received = {}
        self._lock = threading.Lock()
        self.probe = rclpy.create_node('probe', context=self.context)
        self.logs = self.listen('/rosout', Log, QoSProfile(depth=1000))
        self._spin_in_thread(self.probe)

    def _spin_in_thread(self, node):
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(node)
        thread = threading.Thread(target=self._spin, args=(executor,), name=f'{node.get_name()}-spin', daemon=True)
        self._spinners.append((executor, thread))
        thread.start()

    def _spin(self, executor):
        # spin_once in a loop, not executor.spin(): close() ends this loop before shutting the
        # executor down. Jazzy's Executor.shutdown() destroys its guard condition without
        # waiting for the callbacks in flight, and one of them then triggers it (rclpy
        # InvalidHandle in the spin thread; seen under load)
        while not self._stop.is_set() and self.context.ok():
            executor.spin_once(timeout_sec=0.05)

    def add(self, node_class, **kwargs):
        node = node_class(context=self.context, **kwargs)
        self.nodes.append(node)
        self._spin_in_thread(node)
        return node

    def listen(self, topic, msg_type, qos):
        messages = []
        self.probe.create_subscription(msg_type, topic, messages.append, qos)
        return messages

    def publisher(self, topic, msg_type, qos):
        return self.probe.create_publisher(msg_type, topic, qos)

    def wait(self, predicate, timeout=60.0, what='condition'):
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f'timed out after {timeout:.0f} s waiting for {what}')
            time.sleep(0.01)

    def spinning(self) -> bool:
        """Whether every node is still spun: a callback that raises ends its node's thread."""
        return all(thread.is_alive() for _executor, thread in self._spinners)

    def wait_matched(self, publisher, timeout=30.0):
        self.wait(lambda: publisher.get_subscription_count() >= 1, timeout, 'a subscription to match')

    def warnings(self, node_name):
        """Warnings of the nodes under test named `node_name`: what their ThrottledLog wrote,
        and what reached /rosout."""
        said = [line for node in self.nodes if node.get_name() == node_name
                for line in list(getattr(getattr(node, 'log', None), 'history', []))]
        return said + [log.msg for log in list(self.logs) if log.name == node_name and log.level >= Log.WARN]

    def call(self, service_type, name, timeout=30.0):
        client = self.probe.create_client(service_type, name)
        assert client.wait_for_service(timeout_sec=timeout), f'service {name} not available'
        future = client.call_async(service_type.Request())
        self.wait(future.done, timeout, f'a reply from {name}')
        return future.result()

    def close(self):
        self._stop.set()
        for executor, thread in self._spinners:
            thread.join(timeout=10.0)
            executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        self.probe.destroy_node()
        rclpy.shutdown(context=self.context)


def header(stamp_ns, frame_id='camera_depth_optical_frame'):
    msg = Header(frame_id=frame_id)
    msg.stamp.sec, msg.stamp.nanosec = int(stamp_ns // 1_000_000_000), int(stamp_ns % 1_000_000_000)
    return msg


def cloud(points, stamp_ns, frame_id='camera_depth_optical_frame', point_step=16):
    """An organized (H, W, 3) or unorganized (N, 3) float32 PointCloud2."""
    return pointcloud2(PointCloud2, PointField, header(stamp_ns, frame_id), points, point_step)


def stamps_of(messages):
    return [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in list(messages)]
