"""
The topic contract of mshoot: default topic names, message types and QoS profiles.

| topic                | type                      | publisher  | QoS                            |
|----------------------|---------------------------|------------|--------------------------------|
| ``/clock``           | rosgraph_msgs/Clock       | emulator   | best effort, depth 1           |
| ``/zone/state``      | mshoot_msgs/ZoneState     | emulator   | reliable, volatile, depth 10   |
| ``/zone/disturbances`` | mshoot_msgs/Disturbances | emulator  | reliable, volatile, depth 10   |
| ``/forecast``        | mshoot_msgs/Forecast      | forecaster | reliable, transient local, 1   |
| ``/mpc/setpoint``    | mshoot_msgs/Setpoint      | mpc        | reliable, volatile, depth 10   |
| ``/mpc/status``      | mshoot_msgs/MpcStatus     | mpc        | reliable, volatile, depth 10   |
| ``/recorder/ready``  | std_msgs/String           | recorder   | reliable, transient local, 1   |
| ``/diagnostics``     | diagnostic_msgs/DiagnosticArray | every node | reliable, volatile, 10   |

Every name is remappable (``-r /zone/state:=/building/zone1/state``); the
nodes use the names below as their defaults.
"""
from __future__ import annotations

import importlib

from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

CLOCK = '/clock'
ZONE_STATE = '/zone/state'
ZONE_DISTURBANCES = '/zone/disturbances'
FORECAST = '/forecast'
SETPOINT = '/mpc/setpoint'
STATUS = '/mpc/status'

#: Message type of every contract topic (ROS 2 names: ``package/msg/Name``).
TOPIC_TYPES: dict[str, str] = {
    CLOCK: 'rosgraph_msgs/msg/Clock',
    ZONE_STATE: 'mshoot_msgs/msg/ZoneState',
    ZONE_DISTURBANCES: 'mshoot_msgs/msg/Disturbances',
    FORECAST: 'mshoot_msgs/msg/Forecast',
    SETPOINT: 'mshoot_msgs/msg/Setpoint',
    STATUS: 'mshoot_msgs/msg/MpcStatus',
}
#: The topics a run records by default, in a stable order.
RECORDED_TOPICS: tuple[str, ...] = tuple(TOPIC_TYPES)
#: Latched (std_msgs/String) by the recorder node once each of its subscriptions has matched
#: a publisher: what is published from then on is in the bag. A run waits for its publisher
#: in the graph (:mod:`mshoot_nodes.readiness`).
RECORDER_READY = '/recorder/ready'

#: States, disturbances, setpoints and status: every message matters.
DATA_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
#: Forecasts are latched: a late joiner gets the last one.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: Subscribers of latched topics keep a few samples: a malformed message published right
#: after a good one must not displace it before it is taken (compatible with LATCHED_QOS).
LATCHED_READER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                                reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: /clock as rclpy's time source subscribes to it.
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                       reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)

#: The QoS each contract topic is offered with.
TOPIC_QOS: dict[str, QoSProfile] = {
    CLOCK: CLOCK_QOS,
    ZONE_STATE: DATA_QOS,
    ZONE_DISTURBANCES: DATA_QOS,
    FORECAST: LATCHED_QOS,
    SETPOINT: DATA_QOS,
    STATUS: DATA_QOS,
}


def message_class(type_name: str) -> type:
    """
    Return the Python class of a ROS 2 message type.

    Parameters
    ----------
    type_name : str
        ``'package/msg/Name'`` (or ``'package/Name'``).

    Raises
    ------
    ValueError
        If the name is malformed or the package is not installed.

    """
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"message type must look like 'package/msg/Name', got {type_name!r}")
    package, kind, name = parts
    try:
        module = importlib.import_module(f'{package}.{kind}')
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f'message type {type_name!r} is not installed ({exc})') from exc
