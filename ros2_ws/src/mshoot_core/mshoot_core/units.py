"""
Constants of units and time shared by every package, defined once.

``KELVIN``: the offset of the Kelvin scale over the Celsius scale [K] (a zone temperature
state in K is the comfort band in degC plus it). ``NS_PER_S``: nanoseconds per second (ROS
stamps and clocks are in ns). :func:`json_ready`: plain Python values of numpy scalars and
containers, for the JSON files the applications write.
"""
from __future__ import annotations

import math
from typing import Any

#: Kelvin over Celsius [K].
KELVIN = 273.15
#: Nanoseconds per second.
NS_PER_S = 1_000_000_000


def json_ready(value: Any) -> Any:
    """
    Return ``value`` as JSON can hold it.

    Mappings (keys as strings) and sequences recursively; numpy scalars as Python numbers;
    non-finite floats as None; strings, bools, ints and None as they are; anything else as its
    ``repr``.
    """
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if hasattr(value, 'item') and callable(value.item) and getattr(value, 'ndim', 1) == 0:
        value = value.item()  # a numpy scalar
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return repr(value)
