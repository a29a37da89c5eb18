"""
rosbag2 bags without the rosbag2 binaries, through the pure-Python ``rosbags`` library.

- :func:`typestore`: the Jazzy message types plus every custom type found as
  ``share/<package>/msg/<Name>.msg`` in the ament index (``mshoot_msgs``), so
  bags carry full message definitions and ``ros2 bag info/play`` accept them;
- :func:`qos_to_rosbags` / :func:`qos_from_rosbags`: offered QoS profiles as
  stored in ``metadata.yaml`` (version 9, as Jazzy writes it);
- :func:`read_bag`: all messages of a bag as raw CDR bytes, with their topics,
  types and receive times; :func:`read_messages` deserialises them with rclpy;
- crash safety: :func:`flush_writer` puts everything written so far on disk
  (closes the pending mcap chunk, commits the sqlite3 transaction); a bag cut
  short by a crash or ``kill -9`` has no ``metadata.yaml`` and no mcap summary,
  :func:`salvage_bag` reads it up to its last complete chunk and
  :func:`recover_bag` rewrites it as a valid bag (the damaged file is kept
  beside it as ``*.damaged``)::

      python -m mshoot_nodes.bags recover out/demo/bag
      python -m mshoot_nodes.bags info out/demo/bag
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import os
import pathlib
import shutil
import sqlite3
import struct
import sys
from typing import Iterable, Sequence

from ament_index_python.packages import get_package_share_directory, PackageNotFoundError
from rclpy.duration import Duration
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)
from rclpy.serialization import deserialize_message
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.metadata import parse_qos
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
    """Return the ROS 2 Jazzy typestore with the installed ``.msg`` files of ``packages`` added."""
    store = _get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for package in packages:
        for path in _msg_files(package):
            types.update(get_types_from_msg(path.read_text(), f'{package}/msg/{path.stem}'))
    store.register(types)
    return store


def ensure_type(store: Typestore, type_name: str) -> None:
    """
    Register ``type_name``'s package in ``store`` if it is not known yet.

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
    """Return an rclpy QoS profile as a rosbags ``Qos`` (for the bag metadata)."""
    return Qos(history=QosHistory(int(qos.history)), depth=int(qos.depth),
               reliability=QosReliability(int(qos.reliability)),
               durability=QosDurability(int(qos.durability)),
               deadline=_time_to_rosbags(qos.deadline), lifespan=_time_to_rosbags(qos.lifespan),
               liveliness=QosLiveliness(int(qos.liveliness)),
               liveliness_lease_duration=_time_to_rosbags(qos.liveliness_lease_duration),
               avoid_ros_namespace_conventions=bool(qos.avoid_ros_namespace_conventions))


def qos_from_rosbags(qos: Qos, min_depth: int = 10) -> QoSProfile:
    """
    Return a QoS profile to re-publish a recorded topic with.

    Its offered reliability and durability; keep-last with at least ``min_depth`` unless transient
    local.
    """
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
    """
    A bag read into memory.

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


class IncompleteBagError(ValueError):
    """A bag directory without ``metadata.yaml``: its recording was cut short."""


def check_complete(path: str | pathlib.Path) -> None:
    """
    Raise :class:`IncompleteBagError` (saying how to recover) if ``path`` lacks its metadata.

    The metadata is ``metadata.yaml``; FileNotFoundError if ``path`` is not a directory.
    """
    path = pathlib.Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f'no bag directory at {path}')
    if not (path / 'metadata.yaml').is_file():
        data = sorted(p.name for p in path.iterdir() if p.suffix in ('.mcap', '.db3'))
        raise IncompleteBagError(
            f'{path} has no metadata.yaml: the recording was cut short (a crash or kill -9)'
            + (f'; {", ".join(data)} holds what was flushed. Recover it with: python -m '
               f'mshoot_nodes.bags recover {path}' if data else '; it holds no data file'))


def read_bag(path: str | pathlib.Path, topics: Iterable[str] | None = None) -> BagContents:
    """
    Read a rosbag2 bag (mcap or sqlite3) into memory.

    Parameters
    ----------
    path : path-like
        The bag directory (holding ``metadata.yaml``).
    topics : iterable of str, optional
        Only these topics (default: all).

    Raises
    ------
    IncompleteBagError
        A bag cut short by a crash (the message says how to recover it).

    """
    check_complete(path)
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
    """Return the ``rosbag2_bagfile_information`` of a bag's ``metadata.yaml``."""
    text = (pathlib.Path(path) / 'metadata.yaml').read_text()
    return dict(yaml.safe_load(text)['rosbag2_bagfile_information'])


def read_messages(path: str | pathlib.Path, topic: str) -> list:
    """Return the messages of one topic of a bag, deserialised with rclpy (receive-time order)."""
    contents = read_bag(path, [topic])
    if topic not in contents.topics:
        return []
    cls = message_class(contents.topics[topic][0])
    return [deserialize_message(m.rawdata, cls) for m in contents.messages]


# -- crash safety -------------------------------------------------------------------------
def flush_writer(writer: Writer) -> None:
    """
    Put everything written so far on disk, so a crash loses nothing before this call.

    mcap: closes the pending chunk (the unit a reader can recover) and flushes
    the file; sqlite3: commits the open transaction. Uses the storage objects of
    the pinned ``rosbags`` version (0.11).
    """
    storage = getattr(writer, 'storage', None)
    if storage is None:
        return
    chunk = getattr(storage, 'chunk', None)
    if chunk is not None:  # mcap
        if chunk.msgs:
            storage.close_chunk()
        storage.bio.flush()
        os.fsync(storage.bio.fileno())
    elif hasattr(storage, 'conn'):  # sqlite3
        storage.conn.commit()


@dataclasses.dataclass
class Salvage:
    """
    What a bag cut short still holds.

    Attributes
    ----------
    storage : str
        'mcap' or 'sqlite3'.
    data_file : pathlib.Path
        The storage file read.
    connections : dict
        Topic -> (message type, offered QoS list, message definition or '').
    messages : list of BagMessage
        Readable messages, in the order written.
    complete_chunks : int
        mcap: chunks read completely (0 for sqlite3).
    lost_bytes : int
        Bytes after the last complete record (a partial chunk) [B].

    """

    storage: str
    data_file: pathlib.Path
    connections: dict[str, tuple[str, list[Qos], str]]
    messages: list[BagMessage]
    complete_chunks: int = 0
    lost_bytes: int = 0


_MCAP_MAGIC = b'\x89MCAP0\r\n'


class _Cursor:

    def __init__(self, data: bytes | memoryview) -> None:
        self.data, self.pos = memoryview(data), 0

    def take(self, n: int) -> memoryview:
        if self.pos + n > len(self.data):
            raise EOFError
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def u16(self) -> int:
        return struct.unpack('<H', self.take(2))[0]

    def u32(self) -> int:
        return struct.unpack('<I', self.take(4))[0]

    def u64(self) -> int:
        return struct.unpack('<Q', self.take(8))[0]

    def string(self) -> str:
        return bytes(self.take(self.u32())).decode()


def _mcap_records(data: bytes | memoryview) -> Iterable[tuple[int, memoryview, int]]:
    """(opcode, content, end offset) of the complete records of an mcap byte string."""
    cursor = _Cursor(data)
    while True:
        try:
            opcode = cursor.take(1)[0]
            content = cursor.take(cursor.u64())
        except EOFError:
            return
        yield opcode, content, cursor.pos


def _decompress(compression: str, payload: memoryview, size: int) -> bytes:
    if compression == '':
        return bytes(payload)
    if compression == 'zstd':
        if sys.version_info >= (3, 14):  # pragma: no cover
            from compression import zstd
        else:
            from backports import zstd
        return zstd.decompress(bytes(payload))
    if compression == 'lz4':
        from lz4.frame import decompress
        return decompress(bytes(payload))
    raise ValueError(f'unknown mcap chunk compression {compression!r}')


def _salvage_mcap(file: pathlib.Path) -> Salvage:
    data = file.read_bytes()
    if len(data) < len(_MCAP_MAGIC) and _MCAP_MAGIC.startswith(data):
        return Salvage('mcap', file, {}, [], 0, len(data))  # cut before anything was flushed
    if not data.startswith(_MCAP_MAGIC):
        raise ValueError(f'{file} is not an mcap file (no magic bytes)')
    schemas: dict[int, tuple[str, str]] = {}
    channels: dict[int, tuple[str, str, list[Qos]]] = {}
    messages: list[BagMessage] = []
    chunks, good_end, closed = 0, len(_MCAP_MAGIC), False

    def handle(opcode: int, content: memoryview) -> None:
        cursor = _Cursor(content)
        if opcode == 0x03:  # schema
            schema_id = cursor.u16()
            name = cursor.string()
            cursor.string()  # schema encoding: ros2msg
            schemas[schema_id] = (name, bytes(cursor.take(cursor.u32())).decode())
        elif opcode == 0x04:  # channel
            channel_id, schema_id = cursor.u16(), cursor.u16()
            topic = cursor.string()
            cursor.string()  # message encoding: cdr
            meta = _Cursor(cursor.take(cursor.u32()))
            metadata = {}
            while meta.pos < len(meta.data):
                key = meta.string()
                metadata[key] = meta.string()
            msgtype = schemas.get(schema_id, ('', ''))[0]
            channels[channel_id] = (topic, msgtype,
                                    parse_qos(metadata.get('offered_qos_profiles', '')))
        elif opcode == 0x05 and channels:  # message
            channel_id = cursor.u16()
            cursor.u32()  # sequence
            log_time = cursor.u64()
            cursor.u64()  # publish time
            if channel_id in channels:
                topic, msgtype, _ = channels[channel_id]
                messages.append(BagMessage(topic, msgtype, log_time,
                                           bytes(content[cursor.pos:])))

    body = memoryview(data)[len(_MCAP_MAGIC):]
    for opcode, content, end in _mcap_records(body):
        if opcode == 0x06:  # chunk: start, end, size, crc, compression, records
            cursor = _Cursor(content)
            cursor.u64(), cursor.u64()  # message start and end time
            size = cursor.u64()
            cursor.u32()  # crc of the uncompressed records (not checked)
            compression = cursor.string()
            try:
                records = _decompress(compression, cursor.take(cursor.u64()), size)
            except (EOFError, ValueError, RuntimeError):
                break
            for inner, inner_content, _ in _mcap_records(records):
                handle(inner, inner_content)
            chunks += 1
        elif opcode in (0x03, 0x04, 0x05):
            handle(opcode, content)
        elif opcode == 0x0F:  # data end: what follows is the summary of a closed file
            closed = True
            break
        good_end = len(_MCAP_MAGIC) + end
    definitions = dict(schemas.values())
    connections = {topic: (msgtype, qos, definitions.get(msgtype, ''))
                   for topic, msgtype, qos in channels.values()}
    lost = 0 if closed else len(data) - good_end
    return Salvage('mcap', file, connections, messages, chunks, lost)


def _salvage_sqlite3(file: pathlib.Path) -> Salvage:
    # Opened read-write on purpose: sqlite rolls back an interrupted transaction (a hot
    # journal) when it opens the file; what was committed stays.
    with contextlib.closing(sqlite3.connect(file)) as con:
        definitions = dict(con.execute(
            'SELECT topic_type, encoded_message_definition FROM message_definitions'))
        topics = {row[0]: (row[1], row[2], parse_qos(row[3] or ''))
                  for row in con.execute('SELECT id, name, type, offered_qos_profiles '
                                         'FROM topics')}
        rows = con.execute('SELECT topic_id, timestamp, data FROM messages ORDER BY id')
        messages = [BagMessage(topics[tid][0], topics[tid][1], int(ts), bytes(raw))
                    for tid, ts, raw in rows if tid in topics]
    connections = {name: (msgtype, qos, definitions.get(msgtype, ''))
                   for name, msgtype, qos in topics.values()}
    return Salvage('sqlite3', file, connections, messages)


def salvage_bag(path: str | pathlib.Path) -> Salvage:
    """
    Read what a bag cut short holds, without its metadata.yaml.

    Parameters
    ----------
    path : path-like
        The bag directory (one ``*.mcap`` or ``*.db3`` file).

    Raises
    ------
    FileNotFoundError
        No data file in ``path``.
    ValueError
        A data file that is not a bag.

    """
    path = pathlib.Path(path)
    files = sorted(path.glob('*.mcap')) + sorted(path.glob('*.db3'))
    if not files:
        raise FileNotFoundError(f'no .mcap or .db3 file in {path}')
    file = files[0]
    return _salvage_mcap(file) if file.suffix == '.mcap' else _salvage_sqlite3(file)


def recover_bag(path: str | pathlib.Path) -> Salvage:
    """
    Rewrite a bag cut short as a valid bag, in place; return what was recovered.

    The readable messages (up to the last complete mcap chunk, or the last
    sqlite3 commit) go into a fresh bag of the same storage with metadata;
    the damaged data file stays beside it as ``<name>.damaged``.

    Raises
    ------
    ValueError
        The bag is complete (it has a metadata.yaml): nothing to recover.

    """
    path = pathlib.Path(path)
    if (path / 'metadata.yaml').is_file():
        raise ValueError(f'{path} has a metadata.yaml: it is complete, nothing to recover')
    salvage = salvage_bag(path)
    staging = path.parent / f'.{path.name}.recovering'
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir()
    fresh = staging / path.name
    store = typestore()
    writer = Writer(fresh, version=9, storage_plugin=STORAGES[salvage.storage])
    writer.open()
    connections = {}
    for topic, (msgtype, qos, definition) in salvage.connections.items():
        try:
            ensure_type(store, msgtype)
            connections[topic] = writer.add_connection(topic, msgtype, typestore=store,
                                                       offered_qos_profiles=qos)
        except ValueError:
            if not definition:
                raise
            store.register(get_types_from_msg(definition, msgtype))
            connections[topic] = writer.add_connection(topic, msgtype, typestore=store,
                                                       offered_qos_profiles=qos)
    for message in salvage.messages:
        writer.write(connections[message.topic], message.timestamp_ns, message.rawdata)
    writer.close()
    damaged = salvage.data_file.with_name(salvage.data_file.name + '.damaged')
    salvage.data_file.replace(damaged)
    for extra in path.glob(salvage.data_file.name + '-*'):  # a sqlite3 journal
        extra.replace(extra.with_name(extra.name + '.damaged'))
    for item in fresh.iterdir():
        item.replace(path / item.name)
    shutil.rmtree(staging)
    return salvage


def _counts(messages: Sequence[BagMessage]) -> dict[str, int]:
    out: dict[str, int] = {}
    for message in messages:
        out[message.topic] = out.get(message.topic, 0) + 1
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m mshoot_nodes.bags {info,recover} BAG``."""
    parser = argparse.ArgumentParser(prog='python -m mshoot_nodes.bags',
                                     description='Inspect or recover rosbag2 bags.')
    parser.add_argument('command', choices=('info', 'recover'),
                        help='info: topics and counts; recover: rebuild a bag cut short')
    parser.add_argument('bag', type=pathlib.Path, help='bag directory')
    args = parser.parse_args(argv)
    try:
        if args.command == 'info':
            contents = read_bag(args.bag)
            print(f'{args.bag}: {contents.storage}, {len(contents.messages)} messages')
            for topic, (msgtype, _) in contents.topics.items():
                print(f'  {topic} [{msgtype}]: {contents.counts.get(topic, 0)}')
            return 0
        salvage = recover_bag(args.bag)
    except (ValueError, FileNotFoundError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    counts = ', '.join(f'{t} {n}' for t, n in _counts(salvage.messages).items())
    print(f'recovered {len(salvage.messages)} messages ({counts}) from {salvage.data_file.name}'
          + (f', {salvage.complete_chunks} complete chunks' if salvage.storage == 'mcap' else '')
          + (f'; {salvage.lost_bytes} bytes of a partial chunk dropped' if salvage.lost_bytes
             else '') + f'; the damaged file is kept as {salvage.data_file.name}.damaged')
    return 0


if __name__ == '__main__':
    sys.exit(main())
