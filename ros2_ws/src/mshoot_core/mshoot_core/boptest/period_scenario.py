"""
A BOPTEST test period as a scenario (:mod:`mshoot_core.scenario`) for the emulator and forecaster.

:func:`period_scenario`: the scenario of a test period, hourly rows from its start (index:
seconds since the start, the scenario convention; ``attrs['start']`` the ISO date-time of the
start in :data:`YEAR`): ``Tout`` [degC] and ``solrad`` [W/m2] from ``weather.csv`` (what the
building sees), ``occ`` [persons], ``dpos`` 0, the band ``comfort_min``/``comfort_max``
[degC] from ``LowerSetp[z]``/``UpperSetp[z]`` of one zone (the first of ``kpis.json`` unless
named; each row: the tightest band over the step ending there, as the forecasts have it:
:func:`~mshoot_core.boptest.forecasts.interval_band`), the electricity price ``price``
[EUR/kWh] of the chosen scenario, and ``fmu_time_s`` (the FMU clock, seconds from 1 January).

The plant the emulator drives on it is a card of kind ``boptest``
(:class:`~mshoot_core.boptest.card_plant.CardPlant`).
"""
from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from mshoot_core.boptest.forecasts import BandSource, interval_band
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)

#: The calendar year the scenario dates are placed in (a non-leap year; the data are a
#: typical year without a date).
YEAR = 2023
#: The scenario's weather columns from the test case's: column -> (test case column, offset
#: added): the outdoor temperature [degC] and the global horizontal irradiance [W/m2].
SCENARIO_WEATHER = {'Tout': ('TDryBul', -KELVIN), 'solrad': ('HGloHor', 0.0)}


def year_start() -> pd.Timestamp:
    """Return 1 January of :data:`YEAR` (FMU time 0), naive."""
    return pd.Timestamp(year=YEAR, month=1, day=1)


def period_scenario(case: TestCase, period: str, hours: int | None = None,
                    price: str = 'constant', step_s: float | None = None,
                    zone: str | None = None) -> pd.DataFrame:
    """
    Return the scenario of a test period (module docstring): ``hours`` steps, ``hours + 1`` rows.

    Parameters
    ----------
    case : TestCase
        The test case.
    period : str
        A test period (its start is the first row).
    hours : int, optional
        Control steps (default: the whole 14-day period).
    price : str
        Price scenario of the ``price`` column.
    step_s : float, optional
        Row spacing [s] (default the test case's control step).
    zone : str, optional
        The zone of the band and the occupancy (default the first of ``kpis.json``).

    Raises
    ------
    ValueError
        For an unknown period or price scenario, or a bad length.

    """
    _, start, end = case.test_period(period)
    step = case.control_step_s if step_s is None else float(step_s)
    steps = int(round((end - start) / step)) if hours is None else int(hours)
    if steps < 1:
        raise ValueError(f'hours must be >= 1, got {hours!r}')
    fmu_times = start + np.arange(steps + 1) * step
    zone = case.zones[0] if zone is None else str(zone)
    lower, upper = case.band_columns(zone)
    occupancy = f'Occupancy[{zone}]'
    data = case.lookup_frame([*(c for c, _ in SCENARIO_WEATHER.values()),
                              case.price_column(price)], fmu_times)
    comfort_min, comfort_max = interval_band(case, BandSource(lower, upper), fmu_times, step)
    occupants = (case.lookup(occupancy, fmu_times) if occupancy in case.columns
                 else np.zeros(fmu_times.size))
    weather = {name: data[column].to_numpy() + offset
               for name, (column, offset) in SCENARIO_WEATHER.items()}
    scenario = pd.DataFrame({
        'solrad': weather['solrad'], 'Tout': weather['Tout'],
        'occ': occupants, 'dpos': np.zeros(fmu_times.size),
        'comfort_min': comfort_min, 'comfort_max': comfort_max,
        'price': data[case.price_column(price)].to_numpy(), 'fmu_time_s': fmu_times,
    }, index=pd.Index(fmu_times - start, name='time_s'))
    scenario.attrs['start'] = (year_start() + pd.Timedelta(seconds=start)).isoformat()
    scenario.attrs['boptest'] = {'test_case': str(case.directory), 'period': period,
                                 'price': price, 'start_s': start, 'zone': zone,
                                 'weather': {k: list(v) for k, v in SCENARIO_WEATHER.items()}}
    return scenario
