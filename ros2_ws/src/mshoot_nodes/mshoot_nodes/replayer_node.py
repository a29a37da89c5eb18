"""
The bag replayer node: republishes a rosbag2 bag with its timing, scaled by ``rate``.

Messages go out as the raw CDR bytes they were recorded as (``publish(bytes)``),
on publishers with the recorded type and offered QoS (so ``/forecast`` stays
latched). Message k is published ``(t_k - t_0) / rate`` wall seconds after the
start; ``/clock`` is replayed like any other topic, so nodes with use_sim_time
follow the recorded simulated time. On a full ROS 2 install the equivalent is
``ros2 bag play BAG --rate R``. Health on ``/diagnostics`` (``mshoot/replayer``):
messages published of the total.
"""
from __future__ import annotations

from typing import Any

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.publisher import Publisher

from mshoot_nodes.bags import qos_from_rosbags, read_bag
from mshoot_nodes.contract import message_class
from mshoot_nodes.diagnostics import DiagnosticsPublisher, Level, Report
from mshoot_nodes.params import declare, ParamSpec, values
from mshoot_nodes.startup import run_node

PARAMS = (
    ParamSpec('bag_path', '', 'bag directory to play', read_only=True),
    ParamSpec('rate', 1.0, 'playback speed: recorded seconds per wall second [-]', low=1e-6,
              high=1e9),
    ParamSpec('topics', [''], "topics to play ([''] = all)", read_only=True),
    ParamSpec('exclude_topics', [''], 'topics not to play (e.g. the outputs of the node under '
              "test) [''] = none", read_only=True),
    ParamSpec('start_delay_s', 0.5, 'wall time to let subscribers match before the first '
              'message [s]', low=0.0, high=3600.0, read_only=True),
    ParamSpec('autostart', True, 'start playing on a wall-clock timer (false: only through '
              'publish_until, for tests)', read_only=True),
    ParamSpec('exit_when_done', True, 'stand-alone process: exit after the last message',
              read_only=True),
)


def _check(v: dict[str, Any]) -> str | None:
    if 'bag_path' in v and not v['bag_path']:
        return 'bag_path must name a bag directory'
    return None


def _names(value: list[str]) -> set[str]:
    return {name for name in value if name}


class ReplayerNode(Node):
    """
    Plays a bag (see the module docstring).

    Attributes
    ----------
    published : int
        Messages published so far.
    done : bool
        True after the last message.

    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('replayer', **kwargs)
        declare(self, PARAMS, [_check])
        self.params = values(self, PARAMS)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        p = self.params
        wanted, excluded = _names(p['topics']), _names(p['exclude_topics'])
        contents = read_bag(p['bag_path'])
        topics = [t for t in contents.topics
                  if (not wanted or t in wanted) and t not in excluded]
        self._topic_publishers: dict[str, Publisher] = {}
        for topic in topics:
            msgtype, offered = contents.topics[topic]
            qos = qos_from_rosbags(offered[0]) if offered else 10
            self._topic_publishers[topic] = self.create_publisher(message_class(msgtype), topic,
                                                                  qos)
        self.messages = [m for m in contents.messages if m.topic in self._topic_publishers]
        self.published = 0
        self.done = not self.messages
        self._t0 = self.messages[0].timestamp_ns if self.messages else 0
        self._rate = float(p['rate'])
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._start_ns: int | None = None
        self._timer = None
        if p['autostart'] and self.messages:
            self._timer = self.create_timer(max(p['start_delay_s'], 1e-3), self._on_timer,
                                            clock=self._steady)
        span = (self.messages[-1].timestamp_ns - self._t0) / 1e9 if self.messages else 0.0
        self.diagnostics = DiagnosticsPublisher(self, self.health)
        self.get_logger().info(f"{p['bag_path']}: {len(self.messages)} messages on "
                               f'{len(topics)} topics over {span:.1f} s, rate {self._rate:g}')

    def _on_parameters_set(self, params: list) -> None:
        for param in params:
            if param.name == 'rate' and self._start_ns is not None:
                # Keep the current bag position when the rate changes.
                now = self._steady.now().nanoseconds
                position = (now - self._start_ns) * self._rate
                self._rate = float(param.value)
                self._start_ns = now - int(position / self._rate)
            elif param.name == 'rate':
                self._rate = float(param.value)

    def health(self) -> Report:
        """Return the replayer's status for /diagnostics."""
        values_ = {'bag': self.params['bag_path'], 'published': self.published,
                   'messages': len(self.messages), 'rate': self._rate,
                   'topics': len(self._topic_publishers)}
        if self.done:
            return Report(Level.OK, f'replay finished: {self.published} messages', values_)
        return Report(Level.OK, f'replaying: {self.published} of {len(self.messages)} '
                      'messages', values_)

    def publish_until(self, bag_offset_ns: int) -> int:
        """
        Publish every message recorded at most ``bag_offset_ns`` after the first one.

        Returns the number published by this call.
        """
        count = 0
        while self.published < len(self.messages):
            message = self.messages[self.published]
            if message.timestamp_ns - self._t0 > bag_offset_ns:
                break
            self._topic_publishers[message.topic].publish(message.rawdata)
            self.published += 1
            count += 1
        if self.published == len(self.messages) and not self.done:
            self.done = True
            self.get_logger().info(f'replay finished: {self.published} messages')
        return count

    def next_offset_ns(self) -> int | None:
        """Bag offset of the next message to publish (None when done)."""
        if self.published >= len(self.messages):
            return None
        return self.messages[self.published].timestamp_ns - self._t0

    def _on_timer(self) -> None:
        now = self._steady.now().nanoseconds
        if self._start_ns is None:
            self._start_ns = now
        self.publish_until(int((now - self._start_ns) * self._rate))
        following = self.next_offset_ns()
        if following is None:
            self._timer.cancel()
            return
        wait_ns = following / self._rate - (now - self._start_ns)
        self._timer.timer_period_ns = int(min(max(wait_ns, 1e5), 1e9))
        self._timer.reset()


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes replayer --ros-args -p bag_path:=out/demo/bag -p rate:=10.0``."""
    run_node(ReplayerNode, 'replayer', args, until_done=True)


if __name__ == '__main__':
    main()
