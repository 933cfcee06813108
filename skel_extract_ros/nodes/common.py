"""What the three nodes share: QoS profiles, parameter declaration from the core
dataclasses, throttled warnings that count what they suppressed, and the main() idiom."""
from __future__ import annotations

import collections
import threading
import time
from typing import NoReturn

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType,
                                SetParametersResult)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from ..config import Declaration, declarations, node_params
from ..config.docs import ros_description

# Depth drivers publish best effort or reliable; a best-effort reader matches both.
SENSOR_QOS = qos_profile_sensor_data
# Between our nodes nothing may be lost: a window frame that vanished would silently
# change the skeleton. Deep enough for a 60-frame window burst during replay.
STREAM_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
# Latched: a node (or RViz) that starts later still gets the current skeleton / rest pose.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


class WorkingNode(Node):
    """A node with threads or child processes of its own. `stop_work` stops them: spin_node
    calls it on the way out, once the executor stopped, and run_node destroys the ROS
    entities after it (see there); destroy_node (the in-process tests) does both."""

    def stop_work(self) -> None:
        raise NotImplementedError

    def destroy_node(self):
        self.stop_work()
        return super().destroy_node()


class ParameterError(ValueError):
    """A parameter value the node cannot run with (the message names it)."""


_ROS_TYPES = ((bool, ParameterType.PARAMETER_BOOL), (int, ParameterType.PARAMETER_INTEGER),
              (float, ParameterType.PARAMETER_DOUBLE), (str, ParameterType.PARAMETER_STRING),
              (list, ParameterType.PARAMETER_DOUBLE_ARRAY))


def _descriptor(declaration: Declaration) -> ParameterDescriptor:
    """The ParameterDescriptor of a parameter: its description, type and range from the
    dataclass field, read-only unless live; an empty list is typed by its first value."""
    spec, default = declaration.spec, declaration.default
    descriptor = ParameterDescriptor(name=declaration.name, description=ros_description(declaration),
                                     dynamic_typing=declaration.untyped, read_only=not spec.live)
    descriptor.type = next(kind for python_type, kind in _ROS_TYPES if isinstance(default, python_type))
    low, high = spec.bounds()
    if low is not None and isinstance(default, float):
        descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high))]
    elif low is not None and isinstance(default, int) and not isinstance(default, bool):
        descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=1)]
    return descriptor


def _declare(node, declaration: Declaration):
    """Declare one parameter; returns its value. A value of the wrong type or out of range
    raises ParameterError with the name and what is expected."""
    try:
        return node.declare_parameter(declaration.name, declaration.default, _descriptor(declaration)).value
    except (InvalidParameterTypeException, InvalidParameterValueException) as error:
        raise ParameterError(f'parameter {declaration.name}: {error} ({declaration.spec.description})') from None


def declare_params(node, section: str) -> dict:
    """Declare every parameter of the node `section` (config.nodes.NODES: the fields of its
    dataclasses, with their descriptions and ranges) and return its dataclasses built from
    the values the node was started with, {section key: dataclass} (config.node_params).
    A value out of range or choices raises ParameterError naming it."""
    values = {d.name: _declare(node, d) for d in declarations(section)}
    try:
        return node_params(section, values)
    except ValueError as error:
        raise ParameterError(str(error)) from None


def on_live_parameters(node, section: str, apply) -> None:
    """Apply `ros2 param set` on the node's live parameters (field metadata `live`; the
    others are read-only, rclpy refuses them before this). apply(params, changed) gets the
    node's dataclasses built with the new values ({section key: dataclass}, as
    declare_params) and the names that change; a ValueError, raised by the dataclasses'
    validation or by apply, refuses the whole set with its message as the reason."""
    names = [d.name for d in declarations(section)]

    def callback(parameters) -> SetParametersResult:
        changed = {p.name: p.value for p in parameters if p.name in names}
        if not changed:
            return SetParametersResult(successful=True)
        values = {name: node.get_parameter(name).value for name in names if node.has_parameter(name)}
        values.update(changed)
        try:
            apply(node_params(section, values), set(changed))
        except ValueError as error:
            return SetParametersResult(successful=False, reason=str(error))
        node.get_logger().info('parameters set: ' + ', '.join(f'{k} = {v!r}' for k, v in sorted(changed.items())))
        return SetParametersResult(successful=True)
    node.add_on_set_parameters_callback(callback)


class ThrottledLog:
    """At most one line per `period` s for each kind of problem, with the number of the
    same problem seen since the last line. rclpy's own throttling keys on the call site
    and says nothing about how many messages it swallowed, which a user debugging a
    driver needs to know."""

    def __init__(self, logger, period: float = 5.0):
        self._logger = logger
        self._period = period
        self._last = {}
        self._suppressed = {}
        self._lock = threading.Lock()
        # the last lines written, so tests and callers can see what a node said without
        # depending on /rosout delivery
        self.history = collections.deque(maxlen=200)

    def warn(self, kind: str, message: str) -> None:
        now = time.monotonic()
        with self._lock:
            last = self._last.get(kind)
            if last is not None and now - last < self._period:
                self._suppressed[kind] = self._suppressed.get(kind, 0) + 1
                return
            suppressed = self._suppressed.pop(kind, 0)
            self._last[kind] = now
        more = f' ({suppressed} more like this in the last {self._period:.0f} s)' if suppressed else ''
        self.always(message + more)

    def always(self, message: str) -> None:
        """A warning that is rare by nature (a reset, a new frame): never throttled."""
        self.history.append(message)
        self._logger.warning(message)


def decode_rest_or_warn(msg, log: ThrottledLog) -> tuple | None:
    """(rest points Q (M, 3) float64, stamp ns) of a rest_points message, or None (warned)."""
    import numpy as np

    from ..codecs.messages import stamp_ns
    rest = decode_or_warn(msg, log, 'rest_points', np.float64)
    return None if rest is None else (rest, stamp_ns(msg.header))


def decode_or_warn(msg, log: ThrottledLog, what: str, dtype=None):
    """x, y, z of a PointCloud2 from another node, or None after a throttled warning naming
    the topic; dtype defaults to float32 (float64 for the exact rest points)."""
    import numpy as np

    from ..codecs.pointcloud import CloudDecodeError, decode_xyz
    try:
        return decode_xyz(msg, dtype=dtype or np.float32)
    except CloudDecodeError as error:
        log.warn(what, f'ignoring {what}: {error}')
        return None


def decode_registered_or_warn(msg, log: ThrottledLog, rest):
    """(M, 3) float32 registered_points, or None after a throttled warning when the cloud
    does not decode or its size is not the rest pose's (rest: (M, 3) or None, not known yet)."""
    points = decode_or_warn(msg, log, 'registered_points')
    if points is not None and rest is not None and len(points) != len(rest):
        log.warn('size', f'registered_points has {len(points)} points, the rest pose {len(rest)}: ignored')
        return None
    return points


def release_freed_memory() -> None:
    """Hand the heap freed by a large job (Alg. 2, a structure extraction, a Poisson rest
    pose) back to the system. glibc keeps freed memory in its per-thread arenas, so a node
    keeps its peak for good; malloc_trim releases it. No-op where libc has no malloc_trim
    (musl, macOS)."""
    from . import libc
    getattr(libc(), 'malloc_trim', lambda _pad: None)(0)


# how long a node process waits for its ROS entities to be destroyed on the way out
# before it ends without (run_node)
RELEASE_TIMEOUT_S = 5.0


def run_node(node_factory, args=None) -> NoReturn:
    """A node process's main: `spin_node`, then the node's ROS entities are destroyed on a
    thread given RELEASE_TIMEOUT_S, and the process ends with its exit code (`os._exit` once
    stdout and stderr are flushed) instead of leaving them to the interpreter's finalisation.

    Why destroyed: the last node of a process holds its Fast DDS participant, and only
    destroying it removes the participant's shared-memory segment (4 MB with the large-message
    profile) from /dev/shm; a process that exits without it leaves the segment behind, in
    memory, until the machine restarts (every Ctrl-C of a node, every replay and every test
    that starts one). Why on a thread with a timeout: both ways of destroying them hung now
    and then, rclpy's destroy_node woken into the executor that rclpy's signal thread was
    shutting down after a Ctrl-C (the accumulator's main thread in Node._wake_executor), and
    the garbage collector finalising them after main returned (a joint node in CI: its only
    thread "Garbage-collecting", no Python frame; rclpy's Fast DDS destruction-order hangs,
    ros2/rclpy#456, #470). A destruction that hangs costs the segment, not the exit. Nothing
    else is left to finalise that a user would miss: the work threads are joined, the child
    processes reaped, the context shut down. An exception escaping spin_node (a real
    failure) still gets its traceback and the interpreter's own exit."""
    import os
    import sys

    made = []

    def remembered():
        made.append(node_factory())
        return made[-1]

    exit_code = spin_node(remembered, args)
    if made:
        release_entities(made[0], RELEASE_TIMEOUT_S)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(exit_code)


def release_entities(node: Node, timeout_s: float) -> bool:
    """Destroy the ROS entities of a node whose work has stopped (rclpy's Node.destroy_node,
    not WorkingNode's: stop_work ran already) on a daemon thread, waiting at most timeout_s
    s for it; True when it finished. An error there is a node on its way out: ignored."""
    def destroy():
        try:
            Node.destroy_node(node)
        except Exception:   # the context is down; whatever is left goes with the process
            pass

    thread = threading.Thread(target=destroy, name='release-entities', daemon=True)
    thread.start()
    thread.join(timeout_s)
    return not thread.is_alive()


def spin_node(node_factory, args=None) -> int:
    """The demo_nodes_py main: spin until Ctrl-C or shutdown, no traceback; returns the
    exit code. Parameter errors end the node with one line and exit code 2. SIGUSR1 writes
    every thread's stack to stderr (the node's log) and the node goes on: what a node that
    does not end or answer is doing (`skel-extract replay` sends it before killing a node
    that did not end on Ctrl-C). On the way out the node's own threads and child processes
    stop (`stop_work`) and the context shuts down; its ROS entities are left to the
    caller (`run_node` destroys them)."""
    import faulthandler
    import signal
    import sys

    import rclpy
    from rclpy.executors import ExternalShutdownException

    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rclpy.init(args=args)
    node = None
    try:
        # the executor before the node: the node's "waiting for ..." line says it is up, and a
        # Ctrl-C right after it once landed inside the executor's constructor (rclpy.spin makes
        # it on first use), whose half-built object then raised in __del__ (a traceback in the log)
        executor = rclpy.get_global_executor()
        node = node_factory()
        rclpy.spin(node, executor)
    except ParameterError as error:
        print(f'{sys.argv[0]}: error: {error}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # rclpy's deferred SIGINT handler shuts the context down from its own thread; an
        # executor creating its wait set at that moment raises RCLError instead of
        # ExternalShutdownException (ros2/rclpy#1166; ros2cli catches it the same way):
        # a Ctrl-C, not a failure, once the context is down
        if rclpy.ok():
            raise
    finally:
        if isinstance(node, WorkingNode):
            node.stop_work()
        try:
            rclpy.try_shutdown()
        except RuntimeError:
            # the same race: try_shutdown checks the context, then the SIGINT handler's
            # thread shuts it down first, and rcl says "already called"; the context is down
            if rclpy.ok():
                raise
    return 0


class StampPairer:
    """Pairs two streams by exact header stamp (ns). The registration node publishes the
    filtered and the registered cloud of a frame on two topics, and DDS does not order
    messages across topics, so either may come first; unmatched items are kept for the
    last `capacity` stamps of each side. Side 0 (registered frames) comes in stamp order
    (registration takes frames in order): an item of side 1 older than the newest of side 0
    will never be matched and is dropped at once, so side 1 holds only the frames the
    registration may still answer (while the first window is learned it registers
    consecutive frames, seconds behind the camera). Not thread-safe: call from one
    callback group."""

    def __init__(self, capacity: int = 1800):
        # a minute at 30 Hz: how far the first window's registration may fall behind (side 1
        # holds about that lag's frames while it learns, a few once it takes the newest)
        self.capacity = capacity
        self._sides = (collections.OrderedDict(), collections.OrderedDict())

    def add(self, side: int, stamp: int, value):
        """Offer `value` on side 0 or 1; returns (value_0, value_1) once both are in."""
        if side == 0:   # (not assuming arrival order: stamps go back when a bag loops)
            unmatched = self._sides[1]
            for older in [s for s in unmatched if s < stamp]:
                del unmatched[older]
        other = self._sides[1 - side].pop(stamp, None)
        if other is not None:
            return (value, other) if side == 0 else (other, value)
        waiting = self._sides[side]
        waiting[stamp] = value
        while len(waiting) > self.capacity:
            waiting.popitem(last=False)
        return None

    def clear(self) -> None:
        for waiting in self._sides:
            waiting.clear()
