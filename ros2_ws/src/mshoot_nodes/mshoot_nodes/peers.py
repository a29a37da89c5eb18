"""
The peers of a node on ``/diagnostics``: who writes the topics it reads, and who went quiet.

Glue around :class:`mshoot_core.peers.PeerWatch`, where the decisions are: the node tells
:meth:`PeerMonitor.heard` when it takes a message of a peer, and the diagnostics timer calls
:meth:`PeerMonitor.statuses`, which first reads the ROS graph
(``get_publishers_info_by_topic``) for the writers of every peer's topic. Each peer gets a
status of its own, ``<node status name>/peer/<peer>`` (e.g. ``mshoot/mpc/peer/state``), kept
for as long as the node runs: OK, STALE (not heard from within ``timeout_s`` of wall time,
or never) or ERROR (an intruder writes its topic: node name and GID). Every intruder is
logged once, as an error.
"""
from __future__ import annotations

from typing import Sequence

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from mshoot_core.peers import format_gid, Peer, PeerWatch, Writer
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

#: diagnostic_msgs levels by the names :mod:`mshoot_core.peers` uses.
LEVELS = {'OK': 0, 'WARN': 1, 'ERROR': 2, 'STALE': 3}


def writers_of(node: Node, topic: str) -> list[Writer]:
    """Return the publishers of ``topic`` (resolved with the node's remappings) in the graph."""
    infos = node.get_publishers_info_by_topic(node.resolve_topic_name(topic))
    return [Writer(f"{info.node_namespace.rstrip('/')}/{info.node_name}",
                   format_gid(info.endpoint_gid)) for info in infos]


class PeerMonitor:
    """
    A node's peers: when each was heard from, and the writers of their topics.

    Parameters
    ----------
    node : Node
        The node (its logger, the graph, its remappings).
    peers : sequence of Peer
        The peers it expects (:class:`mshoot_core.peers.Peer`).

    Attributes
    ----------
    watch : PeerWatch
        The decisions.

    """

    def __init__(self, node: Node, peers: Sequence[Peer]) -> None:
        self.node = node
        self.watch = PeerWatch(peers)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)

    def heard(self, name: str) -> None:
        """Record that a message of peer ``name`` was taken now."""
        self.watch.heard(name, self._steady.now().nanoseconds)

    def read_graph(self) -> None:
        """Read the writers of every peer's topic from the graph; log new intruders once."""
        for peer in self.watch.peers.values():
            if not peer.writer:
                continue
            for writer in self.watch.writers(peer.name, writers_of(self.node, peer.topic)):
                self.node.get_logger().error(
                    f'intruder on {self.node.resolve_topic_name(peer.topic)}: node '
                    f'{writer.node} (gid {writer.gid}) writes it besides the one expected '
                    f'writer {peer.writer!r}; its messages are validated like any other but '
                    'cannot be told apart (detection, not authentication)')

    def statuses(self, prefix: str, hardware_id: str = '') -> list[DiagnosticStatus]:
        """Read the graph, then return one status per peer, named ``<prefix>/peer/<name>``."""
        self.read_graph()
        out = []
        for status in self.watch.statuses(self._steady.now().nanoseconds):
            peer = status.peer
            values = [KeyValue(key='topic', value=self.node.resolve_topic_name(peer.topic)),
                      KeyValue(key='expected_writer', value=peer.writer or 'any'),
                      KeyValue(key='silent_s', value='never heard' if status.silent_s is None
                               else f'{status.silent_s:.1f}'),
                      KeyValue(key='timeout_s', value=f'{peer.timeout_s:g}')]
            values += [KeyValue(key=f'intruder {w.node}', value=w.gid) for w in status.intruders]
            out.append(DiagnosticStatus(level=bytes([LEVELS[status.level]]),
                                        name=f'{prefix}/peer/{peer.name}',
                                        message=status.message, hardware_id=hardware_id,
                                        values=values))
        return out
