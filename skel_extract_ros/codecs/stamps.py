"""ROS time stamps as integer nanoseconds, for any message type with `sec` and `nanosec`
(rclpy's and rosbags' alike).

Its own module so that the nodes, which read stamps, do not import the bag codec and with
it rosbags (6 MB of every node process), and the bag codec does not import ROS messages."""
from __future__ import annotations


def stamp_to_ns(stamp) -> int:
    """A builtin_interfaces/Time-like stamp in integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
