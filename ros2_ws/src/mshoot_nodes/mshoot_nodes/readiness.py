"""
Readiness from the ROS graph: start a run once the endpoints it needs are there.

The emulator drives simulated time, so it is the one that waits: in its start
gate it polls the ROS graph until every requirement holds (at least so many
publishers and/or subscribers on a topic, as the emulator's participant sees
them), then starts the scenario; after ``ready_timeout_s`` it stops with an
error that names the missing endpoints. Every way of starting a run (the
in-process ``bringup``, ``bringup_processes``, ``closed_loop.launch.py``, a
plain ``ros2 run`` of each node) gets the same check from the same
requirements (:func:`run_requirements`); nothing parses log text.

A requirement is a string, so that it fits a ROS parameter (a string array)::

    '/mpc/setpoint publishers>=1'
    '/zone/state subscribers>=2'
    '/mpc/setpoint publishers>=1 subscribers>=2'

The bag recorder's guarantee (the bag holds every setpoint and status, even
when discovery is slow) needs the recorder's own view: a subscriber seen by
the emulator may not have matched the MPC's publisher yet. So the recorder
creates its latched ``/recorder/ready`` publisher only once each of its
subscriptions has matched a publisher, and the requirement
``'/recorder/ready publishers>=1'`` puts that fact in the graph.
"""
from __future__ import annotations

import dataclasses
import re
from typing import Callable, Iterable, Sequence

from mshoot_core.units import NS_PER_S
from rclpy.exceptions import InvalidTopicNameException
from rclpy.node import Node
from rclpy.validate_topic_name import validate_topic_name

from mshoot_nodes import contract

_KINDS = ('publishers', 'subscribers')
_CONDITION = re.compile(r'(publishers|subscribers)>=(\d+)')
#: What a requirement looks like (for error messages).
FORMAT = "'TOPIC publishers>=N', 'TOPIC subscribers>=N' or both conditions"
#: Recorders a bring-up may run (see :func:`run_requirements`).
RECORDERS = ('none', 'mshoot', 'rosbag2')


@dataclasses.dataclass(frozen=True)
class Requirement:
    """At least ``publishers`` publishers and ``subscribers`` subscribers on ``topic``."""

    topic: str
    publishers: int = 0
    subscribers: int = 0

    def __str__(self) -> str:
        conditions = [f'{kind}>={getattr(self, kind)}' for kind in _KINDS
                      if getattr(self, kind)]
        return ' '.join([self.topic] + conditions)


def parse_requirement(text: str) -> Requirement:
    """
    Parse a requirement from its text (see the module docstring).

    Raises
    ------
    ValueError
        If ``text`` is not ``TOPIC`` followed by one or two conditions.

    """
    parts = str(text).split()
    if len(parts) < 2:
        raise ValueError(f'a readiness requirement must look like {FORMAT}, got {text!r}')
    topic, counts = parts[0], {}
    for part in parts[1:]:
        match = _CONDITION.fullmatch(part)
        if match is None or match.group(1) in counts:
            raise ValueError(f'a readiness requirement must look like {FORMAT}, got {text!r} '
                             f'({part!r} is not a new condition)')
        counts[match.group(1)] = int(match.group(2))
    try:
        validate_topic_name(topic)
    except InvalidTopicNameException as exc:
        raise ValueError(f'a readiness requirement must start with a topic name, got '
                         f'{topic!r} in {text!r}') from exc
    return Requirement(topic, **counts)


def parse_requirements(texts: Iterable[str]) -> list[Requirement]:
    """Parse requirements from texts; blank ones are skipped (``['']``: wait for nothing)."""
    return [parse_requirement(text) for text in texts if str(text).strip()]


def check_requirements(texts: Iterable[str]) -> str | None:
    """Check requirement texts for a parameter: the reason they do not parse, else None."""
    try:
        parse_requirements(texts)
    except ValueError as exc:
        return str(exc)
    return None


def unmet(node: Node, requirements: Sequence[Requirement]) -> list[str]:
    """
    Return the requirements the graph does not meet now, as the node sees it.

    Topic names are resolved with the node's remappings. Returns one text per
    unmet condition, e.g. ``'/mpc/setpoint: 0 of 1 publishers'``.
    """
    missing = []
    for requirement in requirements:
        topic = node.resolve_topic_name(requirement.topic)
        for kind, count in (('publishers', node.count_publishers),
                            ('subscribers', node.count_subscribers)):
            wanted = getattr(requirement, kind)
            if wanted:
                have = count(topic)
                if have < wanted:
                    missing.append(f'{topic}: {have} of {wanted} {kind}')
    return missing


def run_requirements(recorder: str = 'none') -> list[str]:
    """
    Return what the emulator of a closed-loop run waits for, by recorder.

    Parameters
    ----------
    recorder : str
        'none', 'mshoot' (the recorder node: its ``/recorder/ready``) or
        'rosbag2' (``ros2 bag record`` of the contract topics: its subscriptions,
        as the emulator sees them).

    Returns
    -------
    list of str
        Requirements for the emulator's ``ready_endpoints`` parameter: the MPC
        (subscribes to the state, publishes setpoints) and the forecaster (publishes
        forecasts), and the recorder's endpoints.

    """
    if recorder not in RECORDERS:
        raise ValueError(f'recorder must be one of {list(RECORDERS)}, got {recorder!r}')
    states = 2 if recorder != 'none' else 1
    requirements = [f'{contract.ZONE_STATE} subscribers>={states}',
                    f'{contract.SETPOINT} publishers>=1',
                    f'{contract.FORECAST} publishers>=1']
    if recorder == 'mshoot':
        requirements.append(f'{contract.RECORDER_READY} publishers>=1')
    elif recorder == 'rosbag2':
        requirements[1] = f'{contract.SETPOINT} publishers>=1 subscribers>=2'
        requirements += [f'{contract.STATUS} subscribers>=1',
                         f'{contract.FORECAST} subscribers>=2',
                         f'{contract.ZONE_DISTURBANCES} subscribers>=1']
    return requirements


class ReadinessGate:
    """
    Polls the graph on a steady timer until the requirements hold, or times out.

    Parameters
    ----------
    node : Node
        Whose view of the graph counts (and whose timer polls).
    requirements : sequence of Requirement
        What must be there (empty: ready at the first poll).
    on_ready : callable
        Called once, ``settle_s`` after the requirements first held together.
    on_timeout : callable
        Called once with the error text (naming the unmet requirements) when
        they did not hold within ``timeout_s``.
    timeout_s : float
        Wall time allowed [s] (0: wait forever).
    settle_s : float
        Wall time to wait once everything is there (separate processes: time
        for the peers to find each other too) [s].
    poll_s : float
        Wall time between two looks at the graph [s].
    warn_every_s : float
        Wall time between two warnings that name what is missing [s].

    Attributes
    ----------
    missing : list of str
        The unmet requirements at the last poll.
    ready : bool
        True once on_ready was called.

    """

    def __init__(self, node: Node, requirements: Sequence[Requirement], *,
                 on_ready: Callable[[], None], on_timeout: Callable[[str], None],
                 timeout_s: float = 0.0, settle_s: float = 0.0, poll_s: float = 0.05,
                 warn_every_s: float = 5.0) -> None:
        self.node = node
        self.requirements = list(requirements)
        self.on_ready, self.on_timeout = on_ready, on_timeout
        self.timeout_ns = int(timeout_s * NS_PER_S)
        self.settle_ns = int(settle_s * NS_PER_S)
        self.warn_every_ns = int(warn_every_s * NS_PER_S)
        self.missing = unmet(node, self.requirements)
        self.ready = False
        self._steady = getattr(node, 'steady_clock', None)
        if self._steady is None:
            from rclpy.clock import Clock, ClockType
            self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._started_ns = self._steady.now().nanoseconds
        self._met_since_ns = 0
        self._warned_ns = self._started_ns
        self._timer = node.create_timer(poll_s, self.poll, clock=self._steady)

    def poll(self) -> bool:
        """Look at the graph once (the timer calls this); True once ready."""
        if self.ready or self._timer is None:
            return self.ready
        now = self._steady.now().nanoseconds
        self.missing = unmet(self.node, self.requirements)
        if not self.missing:
            self._met_since_ns = self._met_since_ns or now
            if now - self._met_since_ns >= self.settle_ns:
                self.ready = True
                self.cancel()
                self.on_ready()
            return self.ready
        self._met_since_ns = 0
        waited_ns = now - self._started_ns
        if self.timeout_ns and waited_ns >= self.timeout_ns:
            self.cancel()
            self.on_timeout(f'not ready after {waited_ns / NS_PER_S:.1f} s: missing '
                            f"{'; '.join(self.missing)}")
        elif now - self._warned_ns >= self.warn_every_ns:
            self._warned_ns = now
            self.node.get_logger().warning(f'waiting for peers: {"; ".join(self.missing)}')
        return False

    def cancel(self) -> None:
        """Stop polling (the timer is destroyed)."""
        if self._timer is not None:
            self.node.destroy_timer(self._timer)
            self._timer = None
