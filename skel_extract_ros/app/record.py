"""`skel-extract record`: an example consumer of the skeleton, and a demonstration recorder.

It subscribes to `skeleton/trajectory` (trajectory_msgs/MultiDOFJointTrajectory) and
nothing else, as a learning-from-demonstration node would: each message names its joints
(the stable joint ids, `joint_<id>`), so no other topic is needed to know which joint a
pose is, even when the skeleton grows while recording (a joint added later gets a new
name; the others keep theirs). On Ctrl-C (or after `--idle` seconds without a message, or
`--frames` messages) it writes

  OUT/demonstration.csv  one row per stamp and joint: stamp_ns, stamp_s, frame_id, joint,
                         x, y, z (m, the camera frame), qx, qy, qz, qw (the joint's bone
                         rotation from the rest pose, in the camera frame), and the joint's
                         linear (vx, vy, vz m/s) and angular (wx, wy, wz rad/s) velocity
                         (empty where the message had none)
  OUT/demonstration.bvh  the same poses as a BVH motion: the trajectory carries no bone
                         tree, so every joint is a child of a fixed root named after the
                         frame, with 6 channels (its position, then its rotation as
                         Zrotation Xrotation Yrotation in degrees, R = Rz Rx Ry, the
                         convention of skeleton.bvh). A joint missing from a frame (before a
                         growth update added it) holds its nearest recorded pose.

A joint's rotation is the one skeleton.bvh is built from: skeleton.bvh's local rotation of
joint b is W_parent^T W_b, with the parents from skeleton/description (docs/contract.md).
Messages are stored by header stamp; a stamp received twice keeps the last message.
"""
from __future__ import annotations

import csv
import signal
import threading
import time
from pathlib import Path

import numpy as np

CSV_FIELDS = ('stamp_ns', 'stamp_s', 'frame_id', 'joint', 'x', 'y', 'z', 'qx', 'qy', 'qz', 'qw',
              'vx', 'vy', 'vz', 'wx', 'wy', 'wz')


class Demonstration:
    """Trajectory messages by stamp: {stamp ns: (frame_id, names (J,), positions (J, 3) m,
    quaternions (J, 4) x y z w, velocities (J, 6) or None)}. Thread-safe `add`."""

    def __init__(self):
        self.frames = {}
        self._lock = threading.Lock()

    def add(self, msg) -> None:
        """Store one MultiDOFJointTrajectory (its first point: the joint node sends one)."""
        if not msg.points:
            return
        point = msg.points[0]
        positions = np.array([[t.translation.x, t.translation.y, t.translation.z] for t in point.transforms])
        quaternions = np.array([[t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w] for t in point.transforms])
        velocities = (np.array([[v.linear.x, v.linear.y, v.linear.z, v.angular.x, v.angular.y, v.angular.z]
                                for v in point.velocities]) if len(point.velocities) == len(msg.joint_names) else None)
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self._lock:
            self.frames[stamp] = (msg.header.frame_id, list(msg.joint_names), positions.reshape(-1, 3),
                                  quaternions.reshape(-1, 4), velocities)

    def __len__(self) -> int:
        with self._lock:
            return len(self.frames)

    def write_csv(self, path) -> Path:
        with self._lock:
            frames = sorted(self.frames.items())
        path = Path(path)
        with open(path, 'w', newline='') as stream:
            writer = csv.writer(stream)
            writer.writerow(CSV_FIELDS)
            for stamp, (frame_id, names, positions, quaternions, velocities) in frames:
                for j, name in enumerate(names):
                    moving = [f'{v:.6f}' for v in velocities[j]] if velocities is not None else [''] * 6
                    writer.writerow([stamp, f'{stamp * 1e-9:.9f}', frame_id, name,
                                     *(f'{v:.6f}' for v in positions[j]), *(f'{v:.8f}' for v in quaternions[j]),
                                     *moving])
        return path

    def write_bvh(self, path) -> Path:
        """The flat BVH (module docstring)."""
        from scipy.spatial.transform import Rotation

        from .bvh_export import DEFAULT_FRAME_TIME, euler_channels
        with self._lock:
            frames = sorted(self.frames.items())
        names = []                                  # every joint, in order of first appearance
        for _stamp, (_frame, joint_names, *_rest) in frames:
            names += [n for n in joint_names if n not in names]
        F, J = len(frames), len(names)
        positions = np.full((F, J, 3), np.nan)
        rotations = np.full((F, J, 3, 3), np.nan)
        for f, (_stamp, (_frame, joint_names, p, q, _v)) in enumerate(frames):
            index = [names.index(n) for n in joint_names]
            positions[f, index] = p
            rotations[f, index] = Rotation.from_quat(q).as_matrix() if len(q) else np.empty((0, 3, 3))
        for j in range(J):                          # a joint's missing frames hold its nearest pose
            known = np.flatnonzero(np.isfinite(positions[:, j, 0]))
            if len(known):
                nearest = known[np.abs(np.arange(F)[:, None] - known[None, :]).argmin(axis=1)]
                positions[:, j], rotations[:, j] = positions[nearest, j], rotations[nearest, j]
        angles = euler_channels(rotations) if F else np.zeros((0, J, 3))
        stamps = np.array([s for s, _ in frames], dtype=np.float64) * 1e-9
        steps = np.diff(stamps)
        frame_time = float(np.median(steps[steps > 0])) if (steps > 0).any() else DEFAULT_FRAME_TIME
        root = (frames[0][1][0] if frames else 'camera') or 'camera'
        lines = ['HIERARCHY', f'ROOT {root}', '{', '\tOFFSET 0.000000 0.000000 0.000000',
                 '\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation']
        for name in names:
            lines += [f'\tJOINT {name}', '\t{', '\t\tOFFSET 0.000000 0.000000 0.000000',
                      '\t\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation',
                      '\t\tEnd Site', '\t\t{', '\t\t\tOFFSET 0.000000 0.000000 0.000000', '\t\t}', '\t}']
        lines += ['}', 'MOTION', f'Frames: {F}', f'Frame Time: {frame_time:.9g}']
        for f in range(F):
            values = [0.0] * 6 + [v for j in range(J) for v in (*positions[f, j], *angles[f, j])]
            lines.append(' '.join(f'{v:.6f}' for v in values))
        path = Path(path)
        path.write_text('\n'.join(lines) + '\n')
        return path


def record(out, topic: str = 'skeleton/trajectory', idle: float | None = None, frames: int | None = None,
           namespace: str | None = None, started=None) -> Demonstration:
    """Record `topic` until Ctrl-C (SIGINT / SIGTERM), `idle` s without a message once one
    came, or `frames` messages; write OUT/demonstration.csv and .bvh; returns the recording.
    started(): called once the subscription exists."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from trajectory_msgs.msg import MultiDOFJointTrajectory

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    demonstration = Demonstration()
    last = [None]                                     # monotonic time of the last message
    stop = threading.Event()

    def on_message(msg):
        demonstration.add(msg)
        last[0] = time.monotonic()
        if frames is not None and len(demonstration) >= frames:
            stop.set()
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('skel_extract_recorder', namespace=namespace or '', context=context)
    # reliable and deep: the joint node sends a learned window's frames in one burst
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
    node.create_subscription(MultiDOFJointTrajectory, topic, on_message, qos)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        if started is not None:
            started(node.resolve_topic_name(topic))
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
            if idle is not None and last[0] is not None and time.monotonic() - last[0] > idle:
                break
        # what DDS has delivered already is taken before the files are written: until
        # a short wait brings nothing more
        while True:
            count = len(demonstration)
            executor.spin_once(timeout_sec=0.3)
            if len(demonstration) == count:
                break
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
    demonstration.write_csv(out / 'demonstration.csv')
    demonstration.write_bvh(out / 'demonstration.bvh')
    return demonstration

