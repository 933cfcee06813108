"""A helper node spun in the background: how `skel-extract replay`, `skel-extract record`
and the benches talk to the nodes (the nodes themselves use nodes/worker.py's Worker for
their own threads).

    >>> with BackgroundNode('skel_extract_replay') as helper:
    ...     helper.node.create_subscription(...)     # callbacks run on the spinning thread
"""
from __future__ import annotations

import threading


class BackgroundNode:
    """A node in a context of its own, spun by a single-threaded executor on a daemon
    thread from `start` (or entering the `with`) until `close`.

    namespace: the node's; signal_handlers: False leaves SIGINT to the caller (its
    `finally` stops the nodes as a user would)."""

    def __init__(self, name: str, namespace: str | None = None, signal_handlers: bool = True):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=(
            SignalHandlerOptions.ALL if signal_handlers else SignalHandlerOptions.NO))
        self.node = rclpy.create_node(name, namespace=namespace or '', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f'{name}-spin', daemon=True)

    def start(self) -> 'BackgroundNode':
        self._thread.start()
        return self

    def _spin(self) -> None:
        # spin_once in a loop, not executor.spin(): close() ends the loop before it shuts the
        # executor down (a shutdown under a spinning thread can raise in that thread)
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        import rclpy
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        if self.context.ok():
            rclpy.shutdown(context=self.context)

    def __enter__(self) -> 'BackgroundNode':
        return self.start()

    def __exit__(self, *_exc) -> None:
        self.close()
