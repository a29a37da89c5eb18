"""
Forward the Python ``logging`` records of mshoot_core to a node's ROS logger.

mshoot_core logs with :mod:`logging` (it never imports ROS). In a node
process those records should reach the operator the same way as the node's
own messages: on the console and on ``/rosout``.
"""
from __future__ import annotations

import logging

from rclpy.impl.rcutils_logger import RcutilsLogger


class RosLogHandler(logging.Handler):
    """A :class:`logging.Handler` writing to an rclpy logger."""

    def __init__(self, ros_logger: RcutilsLogger, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = f'[{record.name}] {self.format(record)}'
            if record.levelno >= logging.ERROR:
                self.ros_logger.error(text)
            elif record.levelno >= logging.WARNING:
                self.ros_logger.warning(text)
            elif record.levelno >= logging.INFO:
                self.ros_logger.info(text)
            else:
                self.ros_logger.debug(text)
        except Exception:  # noqa: BLE001 - a log handler must never raise
            self.handleError(record)


def bridge_core_logging(ros_logger: RcutilsLogger, level: int = logging.WARNING) -> RosLogHandler:
    """
    Route ``mshoot_core`` log records at ``level`` and above to ``ros_logger``.

    Returns the handler (remove it with ``logging.getLogger('mshoot_core').removeHandler``).
    """
    core = logging.getLogger('mshoot_core')
    handler = RosLogHandler(ros_logger, level)
    core.addHandler(handler)
    core.setLevel(min(level, core.level) if core.level else level)
    core.propagate = False
    return handler
