"""
Who writes the streams a node reads, and which peers have gone quiet.

Two decisions of a node about its peers, made here so that a plain test reaches them; the
nodes only read the ROS graph and a steady clock:

- **One writer per stream** (:func:`intruders`): every stream a node reads (``/zone/state``,
  ``/forecast``, ``/mpc/setpoint``) has one expected writer, a node of a known name. Any other
  writer of the topic is an intruder; two or more writers with the expected name are all
  reported (one of them impersonates the other, and the graph cannot tell which). This is
  detection, not authentication: a message carries no identity of its publisher (rclpy on
  Jazzy), so a message of an intruder that passes validation is still taken.
- **Staleness** (:class:`PeerWatch`): a peer not heard from within its timeout (wall time)
  is STALE, named, with how long it has been silent; one never heard from is STALE too.

Levels are the names of ``diagnostic_msgs/DiagnosticStatus`` levels: 'OK', 'STALE', 'ERROR'.
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

from mshoot_core.units import NS_PER_S


@dataclasses.dataclass(frozen=True)
class Writer:
    """
    A publisher of a topic as the ROS graph shows it.

    Attributes
    ----------
    node : str
        Fully qualified node name ('/ns/name', or '/name').
    gid : str
        Global identifier of the publisher (hex bytes, see :func:`format_gid`).

    """

    node: str
    gid: str

    @property
    def base_name(self) -> str:
        """Return the node name without its namespace."""
        return self.node.rstrip('/').rsplit('/', 1)[-1]


def format_gid(gid: Sequence[int] | bytes) -> str:
    """Return a publisher GID as dotted hex bytes (trailing zero padding dropped)."""
    data = bytes(gid).rstrip(b'\0') or b'\0'
    return '.'.join(f'{b:02x}' for b in data)


def intruders(writers: Sequence[Writer], expected: str) -> list[Writer]:
    """
    Return the writers of a stream that are not its one expected writer.

    Parameters
    ----------
    writers : sequence of Writer
        Every publisher of the topic.
    expected : str
        Node name (without namespace) of the one expected writer.

    Returns
    -------
    list of Writer
        Writers of another name; and, when more than one writer has the expected name, all of
        those too (an impersonator cannot be told from the original).

    """
    named = [w for w in writers if w.base_name == expected]
    return [w for w in writers if w.base_name != expected or len(named) > 1]


@dataclasses.dataclass(frozen=True)
class Peer:
    """
    A peer a node expects to hear from.

    Attributes
    ----------
    name : str
        What the node hears from it: 'state', 'clock', 'forecast', 'setpoint'.
    topic : str
        The topic it is heard on.
    writer : str
        Node name of its one expected writer ('' = not checked in the graph).
    timeout_s : float
        Wall time without hearing from it after which it is STALE [s].

    """

    name: str
    topic: str
    writer: str
    timeout_s: float

    def __post_init__(self) -> None:
        if not self.timeout_s > 0:
            raise ValueError(f'timeout_s of peer {self.name!r} must be > 0, got '
                             f'{self.timeout_s}')


@dataclasses.dataclass(frozen=True)
class PeerStatus:
    """
    How a peer stands.

    Attributes
    ----------
    peer : Peer
    level : str
        'OK', 'STALE' (not heard from within its timeout, or never) or 'ERROR' (intruders
        write its topic).
    message : str
        One sentence.
    silent_s : float or None
        Wall time since it was last heard from [s] (None: never).
    intruders : tuple of Writer
        Other writers of its topic.

    """

    peer: Peer
    level: str
    message: str
    silent_s: float | None
    intruders: tuple[Writer, ...] = ()


class PeerWatch:
    """
    The peers of a node: when each was last heard from and who else writes its topic.

    Parameters
    ----------
    peers : sequence of Peer
        The peers the node expects (distinct names).

    """

    def __init__(self, peers: Sequence[Peer]) -> None:
        names = [p.name for p in peers]
        if len(set(names)) != len(names):
            raise ValueError(f'peer names must be distinct, got {names}')
        self.peers = {p.name: p for p in peers}
        self._heard: dict[str, int] = {}
        self._intruders: dict[str, tuple[Writer, ...]] = {name: () for name in self.peers}
        #: Every intruder seen so far (by GID), for logging each once.
        self.seen: dict[str, Writer] = {}

    def heard(self, name: str, steady_ns: int) -> None:
        """Record a message of peer ``name`` taken at ``steady_ns`` (a steady clock [ns])."""
        self._heard[name] = int(steady_ns)

    def writers(self, name: str, writers: Sequence[Writer]) -> list[Writer]:
        """
        Take the writers of peer ``name``'s topic as the graph shows them now.

        Returns
        -------
        list of Writer
            The intruders not seen before (to be logged once).

        """
        peer = self.peers[name]
        found = tuple(intruders(writers, peer.writer)) if peer.writer else ()
        self._intruders[name] = found
        new = [w for w in found if w.gid not in self.seen]
        self.seen.update({w.gid: w for w in new})
        return new

    def status(self, name: str, steady_ns: int) -> PeerStatus:
        """Return how peer ``name`` stands at ``steady_ns``."""
        peer = self.peers[name]
        heard = self._heard.get(name)
        silent = None if heard is None else max(0, int(steady_ns) - heard) / NS_PER_S
        found = self._intruders[name]
        if found:
            who = ', '.join(f'{w.node} (gid {w.gid})' for w in found)
            return PeerStatus(peer, 'ERROR', f'{len(found)} intruder(s) write {peer.topic}, '
                              f'expected only {peer.writer}: {who}', silent, found)
        if silent is None:
            return PeerStatus(peer, 'STALE', f'nothing heard on {peer.topic} yet', None)
        if silent > peer.timeout_s:
            return PeerStatus(peer, 'STALE', f'nothing heard on {peer.topic} for {silent:.1f} s '
                              f'(timeout {peer.timeout_s:g} s)', silent)
        return PeerStatus(peer, 'OK', f'heard {silent:.1f} s ago', silent)

    def statuses(self, steady_ns: int) -> list[PeerStatus]:
        """Return how every peer stands, in the order given."""
        return [self.status(name, steady_ns) for name in self.peers]
