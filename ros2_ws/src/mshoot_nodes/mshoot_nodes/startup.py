"""
Start-up of a node process: configuration errors end it with one clear line and exit 2.

Bad parameters, YAML values, FMU paths or variable names and CSV columns are
all found while the node is constructed (parameters are validated on
declaration, models and scenarios are loaded in ``__init__``). The process
must then say what is wrong and stop with a non-zero code, not print a
traceback or run on with a default.
"""
from __future__ import annotations

import sys
from typing import Callable, TypeVar

import rclpy
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import ExternalShutdownException

from mshoot_nodes.logbridge import bridge_core_logging
from mshoot_nodes.memory import bound_message_memory

NodeT = TypeVar('NodeT')
#: Exit code of a process whose configuration is invalid.
EXIT_CONFIG = 2
#: Errors that carry a message meant for the operator as it is.
_CLEAR = (InvalidParameterValueException, ValueError, FileNotFoundError)


class StartupError(Exception):
    """
    A node could not be built from its configuration (bad parameters, model, scenario).

    The message is one line naming the node and the reason; bring-ups exit with
    :data:`EXIT_CONFIG`.
    """


def startup_reason(exc: BaseException) -> str:
    """
    Say in one line why a node could not start.

    The message of a clear configuration error as it is, else the exception's type and message
    (never a traceback); the lines of a message of several lines are joined with '; '.
    """
    text = str(exc) if isinstance(exc, _CLEAR) else f'{type(exc).__name__}: {exc}'
    if getattr(exc, 'reason', None):  # params.ParameterRejected: not every value given
        text = str(exc.reason)
    elif isinstance(exc, InvalidParameterValueException) and 'Reason: ' in text:
        text = text.split('Reason: ', 1)[1]
    return '; '.join(line.strip() for line in text.splitlines() if line.strip())


def construct(factory: Callable[[], NodeT], name: str) -> NodeT | None:
    """
    Build a node; on a configuration error log it (fatal) and return None.

    Parameters
    ----------
    factory : callable
        Builds the node (e.g. the node class).
    name : str
        Logger name for the error (the node's name).

    """
    try:
        return factory()
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - any start-up failure ends the process clearly
        rclpy.logging.get_logger(name).fatal(f'cannot start: {startup_reason(exc)}')
        return None


def run_node(factory: Callable[[], NodeT], name: str, args: list[str] | None = None, *,
             until_done: bool = False, bridge_logging: bool = False) -> NodeT | None:
    """
    Run a node process (its ``main``): bound its message memory, init, construct, spin, clean up.

    Ctrl-C and an external shutdown end the spin quietly; the node is destroyed
    and the context shut down in every case. A configuration error exits with
    :data:`EXIT_CONFIG` after one clear line (see :func:`construct`).

    Parameters
    ----------
    factory : callable
        Builds the node (e.g. the node class).
    name : str
        The node's name (for the start-up error).
    args : list of str, optional
        Command-line arguments for ``rclpy.init``.
    until_done : bool
        Spin until the node says ``done`` and its ``exit_when_done`` parameter
        is set (a finite job: the emulator, the replayer), not until shutdown.
    bridge_logging : bool
        Forward ``mshoot_core`` warnings and errors to the node's logger.

    Returns
    -------
    node
        The node after it was destroyed (for its final state, e.g. ``failed``), or
        None when Ctrl-C came before it was built.

    """
    bound_message_memory()
    rclpy.init(args=args)
    node = None
    try:
        node = construct(factory, name)
        if node is None:
            sys.exit(EXIT_CONFIG)
        if bridge_logging:
            bridge_core_logging(node.get_logger())
        if until_done:
            while rclpy.ok() and not (node.done and node.params['exit_when_done']):
                rclpy.spin_once(node, timeout_sec=0.5)
        else:
            rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return node
