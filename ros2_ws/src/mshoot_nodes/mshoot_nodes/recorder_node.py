r"""
The bag recorder node: writes rosbag2 bags (mcap or sqlite3) from raw serialized messages.

It subscribes with ``raw=True`` (no deserialisation: the CDR bytes go to the
bag as they came), registers the message definitions of the custom types from
the installed ``share/<package>/msg/*.msg``, and stores the offered QoS of each
topic, so ``ros2 bag info`` and ``ros2 bag play`` on a ROS 2 install accept the
bag. Receive times are the middleware's reception times (system clock: the
bag keeps the order in which messages arrived across topics, not the order in
which the executor happened to take them), or with use_sim_time the node's
simulated clock (as ``ros2 bag record --use-sim-time``). Built with
``message_info=False`` (the in-process bring-up, whose ``EventsExecutor`` runs the
callbacks in the order the messages came), the node's clock when the callback runs.

Contract topics are subscribed at once with their contract QoS (nothing is
missed at start-up); other topics when a publisher shows up, with its type and
offered QoS from the graph.

Nothing recorded is lost: every ``flush_period_s`` (wall time) what was
written goes to disk (the mcap chunk is closed, the sqlite3 transaction
committed), so a crash or ``kill -9`` loses at most that much and the bag is
recovered with ``python -m mshoot_nodes.bags recover BAG``. SIGINT and
SIGTERM end the process cleanly: the messages already received (waiting in
the subscriptions) are written, then the bag is closed with its metadata.

Readiness: once each subscription of ``ready_topics`` (default: every recorded
topic) has matched a publisher, the recorder creates its latched ``~/ready``
publisher (``/recorder/ready``, std_msgs/String naming the matched topics):
from then on what those publishers send is in the bag. A run's start gate
waits for that publisher in the ROS graph (:mod:`mshoot_nodes.readiness`).
Health on ``/diagnostics`` (``mshoot/recorder``): messages written per topic.

On a full ROS 2 install the equivalent is::

    ros2 bag record -s mcap /clock /zone/state /zone/disturbances /forecast \
        /mpc/setpoint /mpc/status
"""
from __future__ import annotations

import pathlib
import shutil
import sys
import time
from typing import Any

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosbags.rosbag2 import Writer
from std_msgs.msg import String

from mshoot_nodes import contract
from mshoot_nodes.bags import ensure_type, flush_writer, qos_to_rosbags, STORAGES, typestore
from mshoot_nodes.contract import message_class
from mshoot_nodes.diagnostics import DiagnosticsPublisher, Level, Report
from mshoot_nodes.params import declare, ParamSpec, values
from mshoot_nodes.signals import StopSignals
from mshoot_nodes.startup import construct, EXIT_CONFIG

#: Wall time between checks of the subscriptions' matched publishers [s]
MATCH_POLL_S = 0.05
#: The readiness topic, relative to the node (``/recorder/ready`` by default).
READY_TOPIC = '~/ready'

PARAMS = (
    ParamSpec('bag_path', 'mshoot_bag', 'bag directory to create', read_only=True),
    ParamSpec('storage', 'mcap', 'storage plugin of the bag', choices=tuple(STORAGES),
              read_only=True),
    ParamSpec('topics', list(contract.RECORDED_TOPICS), 'topics to record', read_only=True),
    ParamSpec('overwrite', False, 'replace an existing bag directory', read_only=True),
    ParamSpec('queue_depth', 100, 'subscription depth of every topic (latched ones too) [-]',
              low=1, high=100_000, read_only=True),
    ParamSpec('flush_period_s', 1.0, 'wall time between flushes to disk: a crash loses at '
              'most this much [s]', low=0.01, high=3600.0, read_only=True),
    ParamSpec('ready_topics', [''], 'topics whose subscriptions must each have matched a '
              "publisher before ~/ready is published ([''] = every recorded topic)",
              read_only=True),
)


def _check(v: dict[str, Any]) -> str | None:
    if 'topics' in v:
        topics = list(v['topics'])
        if not topics or not all(isinstance(t, str) and t.startswith('/') for t in topics):
            return f'topics must be absolute topic names, got {topics}'
    if 'bag_path' in v and not v['bag_path']:
        return 'bag_path must not be empty'
    if {'ready_topics', 'topics'} <= v.keys():
        extra = sorted({t for t in v['ready_topics'] if t} - set(v['topics']))
        if extra:
            return f'ready_topics must be recorded topics, got {extra} not in topics'
    if {'bag_path', 'overwrite'} <= v.keys() and not v['overwrite'] \
            and pathlib.Path(v['bag_path']).exists():
        return f"bag_path {v['bag_path']!r} exists (set overwrite:=true to replace it)"
    return None


class RecorderNode(Node):
    """
    Records topics into a rosbag2 bag (see the module docstring).

    Parameters
    ----------
    message_info : bool
        Stamp every message with the middleware's reception time (its ``MessageInfo``);
        False: with the node's clock when its callback runs (for rclpy's ``EventsExecutor``,
        which cannot pass the ``MessageInfo`` in Jazzy, and runs the callbacks in the order
        the messages came).
    **kwargs
        Passed to :class:`rclpy.node.Node` (context, parameter_overrides, ...).

    Attributes
    ----------
    counts : dict
        Topic -> messages written so far.
    matched : set of str
        Topics whose subscription has matched a publisher.
    ready : bool
        True once ``~/ready`` is published.

    """

    def __init__(self, message_info: bool = True, **kwargs: Any) -> None:
        super().__init__('recorder', **kwargs)
        self._message_info = message_info
        declare(self, PARAMS, [_check])
        self.params = values(self, PARAMS)
        p = self.params
        self.path = pathlib.Path(p['bag_path'])
        if self.path.exists() and p['overwrite']:
            shutil.rmtree(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._store = typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=STORAGES[p['storage']])
        self._writer.open()
        self._connections: dict[str, Any] = {}
        self._recorded: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self.matched: set[str] = set()
        self.ready = False
        self._ready_topics = {self.resolve_topic_name(t)
                              for t in ([t for t in p['ready_topics'] if t] or p['topics'])}
        self._ready_pub = None
        self._closed = False
        self._unflushed = 0
        self.create_timer(p['flush_period_s'], self.flush,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._waiting = [t for t in p['topics'] if not self._subscribe_contract(t)]
        if self._waiting:
            self._discover()
            self._discovery_timer = self.create_timer(1.0, self._discover)
        flush_writer(self._writer)  # the file header and the contract topics' definitions
        self._match_timer = self.create_timer(MATCH_POLL_S, self._check_matches,
                                              clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.diagnostics = DiagnosticsPublisher(self, self.health)
        self.get_logger().info(f"recording {len(p['topics'])} topics to {self.path} "
                               f"({p['storage']})")

    def _subscribe_contract(self, topic: str) -> bool:
        resolved = self.resolve_topic_name(topic)
        type_name = contract.TOPIC_TYPES.get(topic)
        if type_name is None:
            return False
        offered = contract.TOPIC_QOS[topic]
        self._subscribe(resolved, type_name, offered)
        return True

    def _discover(self) -> None:
        """Subscribe to the waiting topics that have a publisher now."""
        for topic in list(self._waiting):
            infos = self.get_publishers_info_by_topic(self.resolve_topic_name(topic))
            if not infos:
                continue
            try:
                self._subscribe(self.resolve_topic_name(topic), infos[0].topic_type,
                                infos[0].qos_profile)
            except ValueError as exc:
                self.get_logger().error(f'cannot record {topic}: {exc}')
            self._waiting.remove(topic)
        if not self._waiting and hasattr(self, '_discovery_timer'):
            self._discovery_timer.cancel()

    def _check_matches(self) -> None:
        """
        Note each subscription's first matched publisher; publish ``~/ready`` once all matched.

        The ready topics are polled on a steady timer.
        """
        for topic, subscription in self._recorded.items():
            if topic in self.matched:
                continue
            publishers = subscription.get_publisher_count()
            if publishers:
                self.matched.add(topic)
                self.get_logger().info(f'matched {topic}: {publishers} publisher(s)')
        if not self.ready and self._ready_topics <= self.matched:
            self.ready = True
            self._ready_pub = self.create_publisher(String, READY_TOPIC, contract.LATCHED_QOS)
            self._ready_pub.publish(String(data='matched: ' + ', '.join(sorted(self.matched))))
            self.get_logger().info(f'ready: {self._ready_pub.topic_name}')
        if self.ready and len(self.matched) == len(self.params['topics']):
            self._match_timer.cancel()

    def health(self) -> Report:
        """Return the recorder's status for /diagnostics."""
        values_: dict[str, Any] = {'bag': str(self.path), 'storage': self.params['storage'],
                                   'messages_total': self.total, 'ready': self.ready}
        values_.update({f'messages {topic}': count for topic, count in self.counts.items()})
        unmatched = sorted(set(self._recorded) - self.matched) + list(self._waiting)
        values_['unmatched'] = unmatched or 'none'
        if self._closed:
            return Report(Level.OK, f'closed: {self.total} messages', values_)
        if not self.ready:
            return Report(Level.OK, 'recording, waiting for publishers of '
                          + ', '.join(sorted(self._ready_topics - self.matched)), values_)
        return Report(Level.OK, f'recording {len(self.counts)} topics: {self.total} messages',
                      values_)

    def _subscribe(self, topic: str, type_name: str, offered: QoSProfile) -> None:
        ensure_type(self._store, type_name)
        cls = message_class(type_name)
        latched = offered.durability == DurabilityPolicy.TRANSIENT_LOCAL
        # A deeper reader queue than the writer's is compatible, also for latched topics.
        qos = QoSProfile(depth=max(offered.depth, self.params['queue_depth']),
                         reliability=offered.reliability
                         if offered.reliability in (ReliabilityPolicy.RELIABLE,
                                                    ReliabilityPolicy.BEST_EFFORT)
                         else ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                         else DurabilityPolicy.VOLATILE)
        self._connections[topic] = self._writer.add_connection(
            topic, type_name, typestore=self._store,
            offered_qos_profiles=[qos_to_rosbags(offered)])
        self.counts[topic] = 0
        self._recorded[topic] = self.create_subscription(
            cls, topic, (lambda raw, info, t=topic: self._write(t, raw, info))
            if self._message_info else (lambda raw, t=topic: self._write(t, raw)), qos, raw=True)
        self.get_logger().debug(f'recording {topic} [{type_name}]')

    def _write(self, topic: str, raw: bytes, info: dict | None = None) -> None:
        if self._closed:
            return
        clock = self.get_clock()
        received = int((info or {}).get('received_timestamp') or 0)
        if received <= 0 or clock.ros_time_is_active:  # (use_sim_time)
            received = clock.now().nanoseconds
        self._writer.write(self._connections[topic], received, raw)
        self.counts[topic] += 1
        self._unflushed += 1

    @property
    def total(self) -> int:
        """Messages written so far."""
        return sum(self.counts.values())

    def flush(self) -> None:
        """Put what was written on disk (a crash after this loses none of it)."""
        if not self._closed and self._unflushed:
            flush_writer(self._writer)
            self._unflushed = 0

    def drain(self, executor: SingleThreadedExecutor, quiet_s: float = 0.1,
              limit_s: float = 2.0) -> int:
        """
        Take the messages already received (waiting in the subscriptions) before closing.

        Spins until nothing new arrived for ``quiet_s`` (at most ``limit_s``) of
        wall time; returns the number written meanwhile.
        """
        before = last = self.total
        started = quiet_since = time.monotonic()
        while time.monotonic() - started < limit_s:
            executor.spin_once(timeout_sec=0.01)
            if self.total != last:
                last, quiet_since = self.total, time.monotonic()
            elif time.monotonic() - quiet_since >= quiet_s:
                break
        return self.total - before

    def close(self) -> None:
        """Finish the bag (writes metadata.yaml); further messages are dropped."""
        if not self._closed:
            self._closed = True
            self._writer.close()
            total = sum(self.counts.values())
            self.get_logger().info(f'closed {self.path}: {total} messages '
                                   f'({", ".join(f"{t} {n}" for t, n in self.counts.items())})')

    def destroy_node(self) -> None:
        self.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """
    ``ros2 run mshoot_nodes recorder --ros-args -p bag_path:=out/bag``; Ctrl-C ends it.

    SIGINT and SIGTERM only request the stop (no exception in the middle of a
    write, and the context stays valid): what was received is written, then the
    bag is closed and logged.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    with StopSignals() as stop:
        code = _record(stop)
    if code:
        sys.exit(code)


def _record(stop: StopSignals) -> int:
    """Record until a stop is requested (or the context shuts down); the exit code."""
    node = construct(RecorderNode, 'recorder')
    if node is None:
        rclpy.try_shutdown()
        return EXIT_CONFIG
    executor = SingleThreadedExecutor()
    try:
        executor.add_node(node)
        while rclpy.ok() and not stop.requested:  # short waits: signals are seen fast
            executor.spin_once(timeout_sec=0.1)
        if stop.requested:
            drained = node.drain(executor)
            node.get_logger().info(f'{stop.received}: wrote the {drained} messages still '
                                   'queued, closing the bag')
    except ExternalShutdownException:
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    main()
