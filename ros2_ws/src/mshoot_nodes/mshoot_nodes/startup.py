"""Start-up of a node process: configuration errors end it with one clear line and exit 2.

Bad parameters, YAML values, FMU paths or variable names and CSV columns are
all found while the node is constructed (parameters are validated on
declaration, models and scenarios are loaded in ``__init__``). The process
must then say what is wrong and stop with a non-zero code, not print a
traceback or run on with a default.
"""
from __future__ import annotations

from typing import Callable, TypeVar

import rclpy
from rclpy.exceptions import InvalidParameterValueException

NodeT = TypeVar('NodeT')
#: Exit code of a process whose configuration is invalid.
EXIT_CONFIG = 2
#: Errors that carry a message meant for the operator as it is.
_CLEAR = (InvalidParameterValueException, ValueError, FileNotFoundError)


def construct(factory: Callable[[], NodeT], name: str) -> NodeT | None:
    """Build a node; on a configuration error log it (fatal) and return None.

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
        text = str(exc) if isinstance(exc, _CLEAR) else f'{type(exc).__name__}: {exc}'
        rclpy.logging.get_logger(name).fatal(f'cannot start: {text}')
        return None
