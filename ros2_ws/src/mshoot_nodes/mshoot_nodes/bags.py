"""rosbag2 bags without the rosbag2 binaries, through the pure-Python ``rosbags`` library.

- :func:`typestore`: the Jazzy message types plus every custom type found as
  ``share/<package>/msg/<Name>.msg`` in the ament index (``mshoot_msgs``), so
  bags carry full message definitions and ``ros2 bag info/play`` accept them;
- :func:`qos_to_rosbags` / :func:`qos_from_rosbags`: offered QoS profiles as
  stored in ``metadata.yaml`` (version 9, as Jazzy writes it);
- :func:`read_bag`: all messages of a bag as raw CDR bytes, with their topics,
  types and receive times; :func:`read_messages` deserialises them with rclpy.
"""
from __future__ import annotations

import dataclasses
import functools
import pathlib
from typing import Iterable

from ament_index_python.packages import get_package_share_directory, PackageNotFoundError
from rclpy.duration import Duration
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)
from rclpy.serialization import deserialize_message
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import Reader, StoragePlugin
from rosbags.typesys import get_types_from_msg, Stores
from rosbags.typesys import get_typestore as _get_typestore
from rosbags.typesys.store import Typestore
import yaml

from mshoot_nodes.contract import message_class

STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
#: An infinite duration as Jazzy's rosbag2 writes it in metadata.yaml.
INFINITE = QosTime(sec=9223372036, nsec=854775807)
_INFINITE_NS = 9223372036854775807


def _msg_files(package: str) -> list[pathlib.Path]:
    try:
        share = pathlib.Path(get_package_share_directory(package))
    except (PackageNotFoundError, ValueError):
        return []
    return sorted((share / 'msg').glob('*.msg'))


@functools.lru_cache(maxsize=None)
def typestore(packages: tuple[str, ...] = ('mshoot_msgs',)) -> Typestore:
    """The ROS 2 Jazzy typestore with the installed ``.msg`` files of ``packages`` added."""
    store = _get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for package in packages:
        for path in _msg_files(package):
            types.update(get_types_from_msg(path.read_text(), f'{package}/msg/{path.stem}'))
    store.register(types)
    return store


def ensure_type(store: Typestore, type_name: str) -> None:
    """Register ``type_name``'s package in ``store`` if it is not known yet.

    Raises
    ------
    ValueError
        If no ``.msg`` file of that type is installed.
    """
    if type_name in store.types:
        return
    package = type_name.split('/')[0]
    types = {}
    for path in _msg_files(package):
        types.update(get_types_from_msg(path.read_text(), f'{package}/msg/{path.stem}'))
    store.register(types)
    if type_name not in store.types:
        raise ValueError(f'no message definition found for {type_name!r} '
                         f'(looked in share/{package}/msg)')


def _time_to_rosbags(duration: Duration) -> QosTime:
    ns = duration.nanoseconds
    if ns <= 0 or ns >= _INFINITE_NS:
        return INFINITE
    sec, nsec = divmod(ns, 1_000_000_000)
    return QosTime(sec=sec, nsec=nsec)


def _time_from_rosbags(value: QosTime) -> Duration:
    if (value.sec, value.nsec) == (INFINITE.sec, INFINITE.nsec) or value.sec >= 2 ** 31 - 1:
        return Duration(nanoseconds=0)
    return Duration(seconds=value.sec, nanoseconds=value.nsec)


def qos_to_rosbags(qos: QoSProfile) -> Qos:
    """An rclpy QoS profile as a rosbags ``Qos`` (for the bag metadata)."""
    return Qos(history=QosHistory(int(qos.history)), depth=int(qos.depth),
               reliability=QosReliability(int(qos.reliability)),
               durability=QosDurability(int(qos.durability)),
               deadline=_time_to_rosbags(qos.deadline), lifespan=_time_to_rosbags(qos.lifespan),
               liveliness=QosLiveliness(int(qos.liveliness)),
               liveliness_lease_duration=_time_to_rosbags(qos.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(qos.avoid_ros_namespace_conventions))


def qos_from_rosbags(qos: Qos, min_depth: int = 10) -> QoSProfile:
    """A QoS profile to re-publish a recorded topic with (its offered reliability and
    durability; keep-last with at least ``min_depth`` unless transient local)."""
    durability = (DurabilityPolicy(qos.durability.value) if qos.durability.value in (1, 2)
                  else DurabilityPolicy.VOLATILE)
    reliability = (ReliabilityPolicy(qos.reliability.value) if qos.reliability.value in (1, 2)
                   else ReliabilityPolicy.RELIABLE)
    depth = max(int(qos.depth), 1)
    if durability != DurabilityPolicy.TRANSIENT_LOCAL:
        depth = max(depth, min_depth)
    liveliness = (LivelinessPolicy(qos.liveliness.value) if qos.liveliness.value in (1, 3)
                  else LivelinessPolicy.AUTOMATIC)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability,
                      durability=durability, deadline=_time_from_rosbags(qos.deadline),
                      lifespan=_time_from_rosbags(qos.lifespan), liveliness=liveliness,
                      liveliness_lease_duration=_time_from_rosbags(
                          qos.liveliness_lease_duration))


@dataclasses.dataclass(frozen=True)
class BagMessage:
    """One recorded message: topic, type, receive time [ns] and CDR bytes."""

    topic: str
    msgtype: str
    timestamp_ns: int
    rawdata: bytes


@dataclasses.dataclass
class BagContents:
    """A bag read into memory.

    Attributes
    ----------
    messages : list of BagMessage
        In receive-time order.
    topics : dict
        Topic -> (message type, offered QoS profiles as rosbags ``Qos``).
    counts : dict
        Topic -> number of messages (from the metadata).
    storage : str
        'mcap' or 'sqlite3'.
    """

    messages: list[BagMessage]
    topics: dict[str, tuple[str, list[Qos]]]
    counts: dict[str, int]
    storage: str


def read_bag(path: str | pathlib.Path, topics: Iterable[str] | None = None) -> BagContents:
    """Read a rosbag2 bag (mcap or sqlite3) into memory.

    Parameters
    ----------
    path : path-like
        The bag directory (holding ``metadata.yaml``).
    topics : iterable of str, optional
        Only these topics (default: all).
    """
    wanted = None if topics is None else set(topics)
    with Reader(pathlib.Path(path)) as reader:
        connections = [c for c in reader.connections if wanted is None or c.topic in wanted]
        info = {c.topic: (c.msgtype, list(getattr(c.ext, 'offered_qos_profiles', []) or []))
                for c in connections}
        counts: dict[str, int] = {}
        for c in connections:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        messages = [BagMessage(c.topic, c.msgtype, timestamp, bytes(raw))
                    for c, timestamp, raw in reader.messages(connections=connections)]
    messages.sort(key=lambda m: m.timestamp_ns)
    return BagContents(messages, info, counts, bag_metadata(path).get('storage_identifier', ''))


def bag_metadata(path: str | pathlib.Path) -> dict:
    """The ``rosbag2_bagfile_information`` of a bag's ``metadata.yaml``."""
    text = (pathlib.Path(path) / 'metadata.yaml').read_text()
    return dict(yaml.safe_load(text)['rosbag2_bagfile_information'])


def read_messages(path: str | pathlib.Path, topic: str) -> list:
    """The messages of one topic of a bag, deserialised with rclpy (receive-time order)."""
    contents = read_bag(path, [topic])
    if topic not in contents.topics:
        return []
    cls = message_class(contents.topics[topic][0])
    return [deserialize_message(m.rawdata, cls) for m in contents.messages]
