"""/diagnostics for the nodes: each publishes one diagnostic_msgs/DiagnosticStatus a second
on the absolute topic `/diagnostics` (what rqt_robot_monitor and diagnostic_aggregator
read), named by the node's fully qualified name, with its state as the message and its
rates, latencies and counts as key/values (README, "Diagnostics").

    >>> rate = RateMeter()                            # nodes.worker.RateMeter
    >>> rate.tick()                                   # on every message
    >>> NodeDiagnostics(node, lambda: (OK, 'tracking', {'rate_in_hz': rate.rate()}))
"""
from __future__ import annotations

from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
PERIOD_S = 1.0


def _format(value) -> str:
    if isinstance(value, float):
        return 'nan' if value != value else f'{value:.3g}'
    return str(value)


class NodeDiagnostics:
    """Publishes collect() -> (level, message, {key: value}) once every PERIOD_S seconds."""

    def __init__(self, node, collect: Callable[[], tuple]):
        self._node, self._collect = node, collect
        self._publisher = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._name = node.get_fully_qualified_name()
        self._timer = node.create_timer(PERIOD_S, self.publish)

    def status(self) -> DiagnosticStatus:
        level, message, values = self._collect()
        return DiagnosticStatus(level=level, name=self._name, message=message, hardware_id='',
                                values=[KeyValue(key=k, value=_format(v)) for k, v in values.items()])

    def publish(self) -> None:
        array = DiagnosticArray(status=[self.status()])
        array.header.stamp = self._node.get_clock().now().to_msg()
        self._publisher.publish(array)
