"""
Rejected input messages: counted, and logged one clear line each, rate-limited.

The rules live in :mod:`mshoot_core.safety`; this module only turns a
:class:`~mshoot_core.safety.Rejection` into a log line on the node's logger
and a count. Lines are throttled per (stream, kind) with rclpy's
``throttle_duration_sec``: a flood of one defect does not hide another one,
and every line carries the running totals, so nothing is lost by the
throttling but repetition. A throttled rejection costs a few microseconds: the
rate limit is checked before rclpy's logger, whose call-site lookup takes about
a millisecond (a flood of bad messages must not load the node).
"""
from __future__ import annotations

import time

from mshoot_core.safety import Rejection, RejectionCounter
from mshoot_core.units import NS_PER_S
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node


class RejectionLog:
    """
    Counts rejections of a node's inputs and logs them, throttled per (stream, kind).

    Parameters
    ----------
    node : Node
        Whose logger to use.
    period_s : float
        Shortest time between two lines of one (stream, kind) [s] (wall time).
    counter : RejectionCounter, optional
        Where rejections are counted (e.g. the core controller's own counter);
        default: a new one.

    Attributes
    ----------
    counter : RejectionCounter
        Every rejection, by stream and kind.

    """

    def __init__(self, node: Node, period_s: float = 5.0,
                 counter: RejectionCounter | None = None) -> None:
        self._name = node.get_logger().name
        self.period_s = float(period_s)
        self.counter = counter if counter is not None else RejectionCounter()
        # One logger object per (stream, kind): rclpy keeps a throttle state per logger
        # object and call site, so each kind gets its own rate limit.
        self._loggers: dict[tuple[str, str], RcutilsLogger] = {}
        self._logged_at: dict[tuple[str, str], float] = {}

    def reject(self, stream: str, topic: str, stamp_ns: int, rejection: Rejection) -> int:
        """Count a rejected message and log it (throttled); return the stream's total."""
        self.counter.add(stream, rejection)
        return self.log(stream, topic, stamp_ns, rejection)

    def log(self, stream: str, topic: str, stamp_ns: int, rejection: Rejection) -> int:
        """Log a rejection already counted (throttled); return the stream's total."""
        total = self.counter.total(stream)
        key = (stream, rejection.kind)
        now = time.monotonic()
        if key in self._logged_at and now - self._logged_at[key] < self.period_s:
            return total
        self._logged_at[key] = now
        logger = self._loggers.get(key)
        if logger is None:
            logger = self._loggers[key] = RcutilsLogger(self._name)
        logger.warning(f'rejected {topic} stamped {stamp_ns / NS_PER_S:.3f} s '
                       f'[{rejection.kind}]: {rejection.reason} ({total} {stream} rejections '
                       f'so far, {self.counter.counts[key]} of this kind)',
                       throttle_duration_sec=self.period_s)
        return total

    def total(self, stream: str | None = None) -> int:
        """Rejections of ``stream`` so far (all when None)."""
        return self.counter.total(stream)
