"""
Health on ``/diagnostics``: one ``diagnostic_msgs/DiagnosticStatus`` per node.

Every mshoot node publishes a ``DiagnosticArray`` holding first one status named
``mshoot/<node>`` (``mshoot/emulator``, ``mshoot/mpc``, with the namespace when
there is one): a level (OK, WARN, ERROR, STALE), a one-line message and key
values (counters, the last solve time, fallbacks, rejected inputs, ...), the
convention that ``diagnostic_aggregator``, ``rqt_robot_monitor`` and
``ros2 topic echo /diagnostics`` read. It is published every ``period_s`` of
wall time (a steady timer: it also reports a node whose simulated clock
stands still) and on demand (:meth:`DiagnosticsPublisher.publish`); lifecycle
nodes (:mod:`mshoot_nodes.lifecycle`) also publish after every transition and
get a ``lifecycle_state`` key value. After it come the statuses of the node's peers
(:mod:`mshoot_nodes.peers`): one per peer it expects, STALE when not heard from within its
timeout, ERROR when an intruder writes its topic.

A node gives a function that builds its :class:`Report`::

    self.diagnostics = DiagnosticsPublisher(self, self.health, hardware_id=zone)

    def health(self) -> Report:
        return Report(Level.OK, 'running', {'steps': self.steps_done})
"""
from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from mshoot_nodes.peers import PeerMonitor

#: The topic diagnostic aggregators and monitors read.
DIAGNOSTICS = '/diagnostics'
#: Reliable, volatile, depth 10 (matches reliable and best-effort readers).
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
#: Prefix of the status names.
PREFIX = 'mshoot'


class Level(enum.IntEnum):
    """Levels of ``diagnostic_msgs/DiagnosticStatus``."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3

    def to_msg(self) -> bytes:
        """Return the ``byte`` field value of DiagnosticStatus.level."""
        return bytes([int(self)])


@dataclasses.dataclass
class Report:
    """
    A node's health at one moment.

    Attributes
    ----------
    level : Level
        OK, WARN, ERROR or STALE.
    message : str
        One line saying what the level is about.
    values : dict
        Key values (str -> anything printable; floats are written with 6
        significant digits, bools as 'true'/'false').

    """

    level: Level
    message: str
    values: dict[str, Any] = dataclasses.field(default_factory=dict)


def format_value(value: Any) -> str:
    """Return a key value as text."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return f'{value:.6g}' if math.isfinite(value) else str(value)
    if isinstance(value, dict):
        return ', '.join(f'{k}: {format_value(v)}' for k, v in value.items())
    if isinstance(value, (list, tuple, set)):
        return ', '.join(format_value(v) for v in value)
    return str(value)


def status_values(status: DiagnosticStatus) -> dict[str, str]:
    """Return the key values of a status as a dict."""
    return {kv.key: kv.value for kv in status.values}


class DiagnosticsPublisher:
    """
    Publishes a node's :class:`Report` on ``/diagnostics``, periodically and on demand.

    Parameters
    ----------
    node : Node
        The node (a plain publisher and a steady timer are created on it: they
        live as long as the node, whatever its lifecycle state).
    report : callable
        ``report() -> Report``; an exception in it is published as an ERROR
        status with the exception's text (diagnostics never crash the node).
    period_s : float
        Wall time between two publications [s] (0: only on demand).
    hardware_id : str
        ``hardware_id`` of the status (e.g. the zone the node serves).
    name : str, optional
        Status name (default ``mshoot/<node's fully qualified name without the
        leading slash>``).
    peers : PeerMonitor, optional
        The node's peers: one more status each, ``<name>/peer/<peer>``, after the
        node's own (:mod:`mshoot_nodes.peers`).

    Attributes
    ----------
    name : str
        The status name.
    published : int
        Arrays published so far.

    """

    def __init__(self, node: Node, report: Callable[[], Report], *, period_s: float = 1.0,
                 hardware_id: str = '', name: str | None = None,
                 peers: PeerMonitor | None = None) -> None:
        if period_s < 0 or not math.isfinite(period_s):
            raise ValueError(f'period_s must be >= 0 and finite, got {period_s}')
        self.node = node
        self.report = report
        self.peers = peers
        self.hardware_id = hardware_id
        self.name = name or f'{PREFIX}{node.get_fully_qualified_name()}'
        self.published = 0
        self._publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS, DIAGNOSTICS_QOS)
        self._timer = (node.create_timer(period_s, self.publish,
                                         clock=Clock(clock_type=ClockType.STEADY_TIME))
                       if period_s > 0 else None)

    def status(self) -> DiagnosticStatus:
        """Return the node's status now."""
        try:
            report = self.report()
            level, message, values = Level(report.level), report.message, dict(report.values)
        except Exception as exc:  # noqa: BLE001 - reported, not raised
            level, message, values = Level.ERROR, f'health report failed: {exc!r}', {}
        state = getattr(self.node, 'lifecycle_state', None)
        if state is not None:
            values = {'lifecycle_state': state, **values}
        return DiagnosticStatus(level=level.to_msg(), name=self.name, message=message,
                                hardware_id=self.hardware_id,
                                values=[KeyValue(key=str(k), value=format_value(v))
                                        for k, v in values.items()])

    def publish(self) -> DiagnosticArray:
        """Publish the status now (the node's first, then its peers'); returns the array sent."""
        statuses = [self.status()]
        if self.peers is not None:
            try:
                statuses += self.peers.statuses(self.name, self.hardware_id)
            except Exception as exc:  # noqa: BLE001 - reported, not raised
                statuses.append(DiagnosticStatus(level=Level.ERROR.to_msg(),
                                                 name=f'{self.name}/peer',
                                                 message=f'peer watch failed: {exc!r}',
                                                 hardware_id=self.hardware_id))
        array = DiagnosticArray(status=statuses)
        array.header.stamp = self.node.get_clock().now().to_msg()
        self._publisher.publish(array)
        self.published += 1
        return array
