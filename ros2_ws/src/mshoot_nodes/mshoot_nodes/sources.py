"""
Scenarios, models and the simulated-time origin, built from parameter values.

Models come from the one registry of :mod:`mshoot_core.models.registry`
(re-exported here as ``build_model``, ``check_model``).

A small adapter between node parameters and :mod:`mshoot_core`: the emulator
and the forecaster read the same scenario parameters, so they must build the
same DataFrame and place it at the same ROS time.
"""
from __future__ import annotations

import logging
import pathlib
from typing import Any

from mshoot_core.models.registry import build_model, check_model  # noqa: F401 (API)
from mshoot_core.models.registry import BUILTIN as MODELS  # noqa: F401 (API)
from mshoot_core.scenario import reference_scenario
from mshoot_core.units import NS_PER_S
import pandas as pd

from mshoot_nodes.params import ParamSpec

logger = logging.getLogger(__name__)

#: Scenario names understood besides a CSV path (and ``boptest:<period>[:<price>]``).
SCENARIOS = ('synthetic', 'ou44')
#: Prefix of a BOPTEST test period scenario (see mshoot_core.boptest.period_scenario).
BOPTEST_PREFIX = 'boptest:'


def parse_boptest(name: str) -> tuple[str, str]:
    """Return (period, price scenario) of ``boptest:<period>[:<price>]`` (default constant)."""
    parts = name[len(BOPTEST_PREFIX):].split(':')
    if len(parts) > 2 or not parts[0]:
        raise ValueError(f"a BOPTEST scenario is 'boptest:<period>[:<price>]', got {name!r}")
    return parts[0], parts[1] if len(parts) == 2 else 'constant'


def _boptest_reason(name: str, data: str) -> str | None:
    from mshoot_core.boptest.testcase import PRICE_SCENARIOS, TestCase
    try:
        period, price = parse_boptest(name)
        case = TestCase.load(data or None)
    except (ValueError, FileNotFoundError) as exc:
        return f'scenario {name!r}: {exc}'
    if period not in case.days:
        return f'scenario {name!r}: unknown test period {period!r}; expected one of ' \
               f'{sorted(case.days)}'
    if price not in PRICE_SCENARIOS:
        return f'scenario {name!r}: unknown price scenario {price!r}; expected one of ' \
               f'{list(PRICE_SCENARIOS)}'
    return None


#: First row of the OU44 reference case (5 April 2018, local time).
#: Used when a scenario carries no start time in ``attrs['start']``.
DEFAULT_START = '2018-04-05T00:00:00'


def check_scenario(name: str, data: str) -> str | None:
    """Reason why scenario parameters are invalid, or None."""
    if name.startswith(BOPTEST_PREFIX):
        return _boptest_reason(name, data)
    if name in SCENARIOS:
        if name == 'ou44' and data and not pathlib.Path(data).is_file():
            return f'data must be the OU44 measurements.csv, got {data!r} (no such file)'
        return None
    if name.endswith('.csv'):
        return None if pathlib.Path(name).is_file() else f'scenario file {name!r} not found'
    return f'scenario must be one of {list(SCENARIOS)}, boptest:<period>[:<price>] or a path ' \
           f'to an OU44-format CSV, got {name!r}'


#: The scenario parameters a BOPTEST-only node declares besides ``scenario`` (checked by
#: :func:`check_boptest_parameters`).
BOPTEST_SCENARIO_PARAMS = (
    ParamSpec('data', '', "the BOPTEST test case folder ('' = the default)", read_only=True),
    ParamSpec('hours', 336, 'control steps of the scenario [-]', low=1, high=1_000_000,
              read_only=True),
    ParamSpec('start_time', '', "ROS time of the first scenario row ('' = the scenario's)",
              read_only=True),
)


def check_boptest_parameters(values: dict[str, Any]) -> str | None:
    """
    Reason why a BOPTEST-only node's scenario parameters are invalid, or None.

    A parameter check for :func:`mshoot_nodes.params.declare`: ``values`` holds the parameters
    being set; ``scenario`` must be ``boptest:<period>[:<price>]`` (with ``data``, the test case
    folder).
    """
    if 'scenario' in values:
        if not values['scenario'].startswith(BOPTEST_PREFIX):
            return f"scenario must be 'boptest:<period>[:<price>]', got {values['scenario']!r}"
        return check_scenario(values['scenario'], values.get('data', ''))
    return None


def load_scenario(name: str, data: str = '', hours: int = 72) -> pd.DataFrame:
    """
    Return the scenario of a run: ``hours`` control steps (``hours + 1`` rows).

    Parameters
    ----------
    name : str
        'synthetic' (built in, no files), 'ou44' (the reference case, ventilation
        off; data from ``data`` or the default path), ``boptest:<period>[:<price>]`` (a
        BOPTEST test period from its start, with the price scenario's ``price`` column), or
        a path to a CSV in the OU44 format.
    data : str
        Path of the OU44 ``measurements.csv`` for 'ou44', of the BOPTEST test case folder for
        a BOPTEST scenario ('' = default).
    hours : int
        Control steps.

    Raises
    ------
    FileNotFoundError, ValueError
        Missing data or a scenario that does not cover ``hours``.

    """
    if name.startswith(BOPTEST_PREFIX):
        from mshoot_core.boptest.period_scenario import period_scenario
        from mshoot_core.boptest.testcase import TestCase
        period, price = parse_boptest(name)
        return period_scenario(TestCase.load(data or None), period, hours, price)
    return reference_scenario(name, data or None, hours)


def card_series(model: str | None) -> list[str] | None:
    """
    Return the disturbances a control model card names (the series its forecasts need).

    None for a model that is not a card (the forecaster's own ``series`` then) or a card that
    cannot be read (the MPC node reports why).
    """
    from mshoot_core.models.defaults import is_card_path
    if not model or not is_card_path(model):
        return None
    from mshoot_core.models import card as cards
    try:
        return list(cards.load_card(model).disturbances)
    except (OSError, ValueError):
        return None


def start_ns(scenario: pd.DataFrame, start_time: str = '') -> int:
    """
    ROS time [ns] of the first scenario row.

    ``start_time`` (ISO, read as UTC) or else the scenario's ``attrs['start']``,
    else :data:`DEFAULT_START`. Real dates keep simulated time away from 0,
    which rclpy reads as "no clock received yet".
    """
    text = start_time or scenario.attrs.get('start') or DEFAULT_START
    stamp = pd.Timestamp(text)
    stamp = stamp.tz_localize('UTC') if stamp.tzinfo is None else stamp.tz_convert('UTC')
    seconds = (stamp - pd.Timestamp(0, tz='UTC')).total_seconds()
    if seconds <= 0:
        raise ValueError(f'start_time must be after 1970-01-01, got {text!r}')
    return int(round(seconds)) * NS_PER_S


def check_start_time(text: str) -> str | None:
    """Reason why a start_time parameter is invalid, or None."""
    if not text:
        return None
    try:
        stamp = pd.Timestamp(text)
    except ValueError as exc:
        return f'start_time must be an ISO date-time such as {DEFAULT_START!r}: {exc}'
    if stamp.tzinfo is None:
        stamp = stamp.tz_localize('UTC')
    if stamp <= pd.Timestamp(0, tz='UTC'):
        return f'start_time must be after 1970-01-01, got {text!r}'
    return None


def fmu_available() -> bool:
    """
    Return True if the R1C1 FMU and its batch drivers are built where the runtime finds them.

    They are built by ``make setup``.
    """
    try:
        from mshoot_core.fmu_cache import find_driver, find_fmu, NotBuiltError
    except ImportError:
        return False
    try:
        find_fmu('r1c1')
        find_driver('cs')
        find_driver('me')
    except NotBuiltError:
        return False
    return True
