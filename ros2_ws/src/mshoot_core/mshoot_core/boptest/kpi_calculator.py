"""
BOPTEST's key performance indicators from a record table of a run.

Stable API::

    from mshoot_core.boptest.kpi_calculator import compute_kpis, kpi_records, KPI_NAMES
    kpis = compute_kpis(table, case, start_s, end_s, price='dynamic', step_wall_s=walls)
    # {'tdis_tot': K h, 'idis_tot': ppm h, 'ener_tot': kWh/m2, 'cost_tot': EUR/m2,
    #  'emis_tot': kgCO2/m2, 'pele_tot': kW/m2, 'pgas_tot': kW/m2, 'pdih_tot': kW/m2,
    #  'time_rat': -, 'tdis_zones': {zone: K h}}

The definitions are those of BOPTEST's KPI calculator (``kpis/kpi_calculator.py`` of
``ibpsa/project1-boptest``, as the test cases' READMEs write them out), over the test period
``[start_s, end_s]``, from the outputs stored during the run (``table``: a ``time`` column
[s from 1 January] and the outputs named in the test case's ``kpis.json``, sampled at
<= 60 s as :class:`~mshoot_core.boptest.plant.BoptestPlant` records them), with the test case's
data (band, CO2 limit, prices, emission factors) held constant between their rows (forward
fill) and integrals by the trapezoid rule over the samples:

- ``tdis_tot`` [K h]: for each zone z of ``kpis.json`` (``OperativeZoneTemperature[z]`` or
  ``AirZoneTemperature[z]``), ∫ (max(0, LowerSetp[z] - T_z) + max(0, T_z - UpperSetp[z])) dt
  / 3600 (``tdis_zones``), averaged over the zones;
- ``idis_tot`` [ppm h]: ∫ max(0, CO2_z - UpperCO2[z]) dt / 3600, averaged over the zones
  (``CO2Concentration[z]``);
- ``ener_tot`` [kWh/m2]: ∫ Σ P dt / 3.6e6 / area, P [W] every output of every energy vector
  of ``kpis.json`` (``ElectricPower``, ``GasPower``, ``DistrictHeatingPower``, ...:
  :data:`~mshoot_core.boptest.testcase.ENERGY_VECTORS`);
- ``cost_tot`` [EUR/m2]: ∫ Σ_v P_v * price_v dt / 3.6e6 / area, the price of electricity that
  of the scenario (``PriceElectricPower<Scenario>``), of every other vector ``Price<vector>``;
- ``emis_tot`` [kgCO2/m2]: the same with the emission factors ``Emissions<vector>``;
- ``pele_tot``, ``pgas_tot``, ``pdih_tot`` [kW/m2]: the largest 15-minute mean of the electric,
  gas, district heating power / area / 1000 (None when the test case has no such vector); the
  means are over the samples in each 900 s bin [k 900, (k + 1) 900) of FMU time (as pandas'
  ``resample('15min')`` of BOPTEST), within the period;
- ``time_rat`` [-]: the mean over control steps of the controller's wall time between two
  emulator advances divided by the control step (None when no wall times are given).

A test case's FMU may report a power output with the wrong sign (the two-zone office's chiller
power is below zero while it runs, so BOPTEST's sums count cooling as energy earned). Its card
says so (``boptest.power_signs``: output -> -1); :func:`compute_kpis` then counts the output
with the sign corrected in ``ener_tot``, ``cost_tot``, ``emis_tot`` and the peaks, and keeps
BOPTEST's sums as written under ``as_defined``.
"""
from __future__ import annotations

import logging
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core.boptest.testcase import PEAK_KPIS, PRICE_SCENARIOS, TestCase
from mshoot_core.kpis import band_distances, hours_integral, JOULES_PER_KWH

logger = logging.getLogger(__name__)

#: BOPTEST's KPIs, in the order of its reports.
KPI_NAMES = ('tdis_tot', 'idis_tot', 'ener_tot', 'cost_tot', 'emis_tot', 'pele_tot',
             'pgas_tot', 'pdih_tot', 'time_rat')
#: Bin of the peak power KPI [s].
PEAK_BIN_S = 900.0


def _window(table: pd.DataFrame, start_s: float, end_s: float) -> pd.DataFrame:
    if 'time' not in table.columns:
        raise ValueError('the record table lacks the column "time" [s]')
    if not end_s > start_s:
        raise ValueError(f'empty test period [{start_s:g}, {end_s:g}] s')
    times = table['time'].to_numpy(dtype=float)
    if np.any(np.diff(times) <= 0):
        raise ValueError('the record table\'s "time" must increase strictly')
    eps = 1e-6
    if times.size == 0 or times[0] > start_s + eps or times[-1] < end_s - eps:
        span = f'[{times[0]:g}, {times[-1]:g}]' if times.size else 'empty'
        raise ValueError(f'the records ({span} s) do not cover the period [{start_s:g}, '
                         f'{end_s:g}] s')
    keep = (times >= start_s - eps) & (times <= end_s + eps)
    return table[keep].reset_index(drop=True)


def _columns(table: pd.DataFrame, names: Sequence[str]) -> np.ndarray:
    missing = [n for n in names if n not in table.columns]
    if missing:
        raise ValueError(f'the record table lacks the KPI outputs {missing}')
    values = table[list(names)].to_numpy(dtype=float)
    if not np.all(np.isfinite(values)):
        raise ValueError(f'non-finite values in the KPI outputs {list(names)}')
    return values


def vector_power(table: pd.DataFrame, case: TestCase, vector: str,
                 power_signs: Mapping[str, float] | None = None) -> np.ndarray:
    """
    Return the power of one energy vector [W]: the sum of its ``kpis.json`` outputs, per row.

    ``power_signs`` (output -> -1 or 1, default 1) corrects outputs reported with the wrong
    sign (module docstring).
    """
    names = case.energy_outputs.get(vector, [])
    signs = np.array([float((power_signs or {}).get(name, 1.0)) for name in names])
    return (_columns(table, names) * signs).sum(axis=1)


def check_power_signs(case: TestCase, power_signs: Mapping[str, float] | None) -> None:
    """
    Check sign corrections: each names a power output of ``kpis.json`` and is -1 or 1.

    Raises
    ------
    ValueError
        For an output no energy vector of the test case has, or a sign other than -1 and 1.

    """
    outputs = [name for names in case.energy_outputs.values() for name in names]
    unknown = sorted(set(power_signs or {}) - set(outputs))
    if unknown:
        raise ValueError(f'power_signs: {unknown} are not power outputs of the kpis.json of '
                         f'{case.name} (expected some of {outputs})')
    bad = {name: sign for name, sign in (power_signs or {}).items() if sign not in (-1, 1)}
    if bad:
        raise ValueError(f'power_signs: expected -1 or 1, got {bad}')


def zone_discomfort(table: pd.DataFrame, case: TestCase) -> dict[str, tuple[np.ndarray, ...]]:
    """
    Return zone -> (below, above) the band [K] per row (the ``tdis`` integrands).

    Raises
    ------
    ValueError
        When ``kpis.json`` names no zone temperature, or for missing columns.

    """
    times = table['time'].to_numpy(dtype=float)
    out = {}
    for zone, outputs in case.zone_temperature_outputs.items():
        lower_column, upper_column = case.band_columns(zone)
        lower, upper = case.lookup(lower_column, times), case.lookup(upper_column, times)
        temperatures = _columns(table, outputs)
        below, above = band_distances(temperatures, lower[:, None], upper[:, None])
        out[zone] = (below.sum(axis=1), above.sum(axis=1))
    if not out:
        raise ValueError(f'{case.name}: kpis.json names no OperativeZoneTemperature[z]')
    return out


def co2_discomfort(table: pd.DataFrame, case: TestCase) -> np.ndarray:
    """Return the CO2 excess [ppm] per row, averaged over the zones (``idis_tot`` integrand)."""
    times = table['time'].to_numpy(dtype=float)
    per_zone = []
    for zone, outputs in case.co2_outputs.items():
        co2 = _columns(table, outputs)
        limit = case.lookup(f'UpperCO2[{zone}]', times)
        per_zone.append(np.maximum(0.0, co2 - limit[:, None]).sum(axis=1))
    if not per_zone:
        return np.zeros(len(table))
    return np.mean(per_zone, axis=0)


def peak_power(times_s: np.ndarray, power_w: np.ndarray) -> float:
    """
    Return the largest 15-minute mean of a power [W] (module docstring).

    Parameters
    ----------
    times_s : np.ndarray
        Sample times [s]; bins are [k 900, (k + 1) 900).
    power_w : np.ndarray
        The power at those times [W].

    """
    bins = np.floor(np.asarray(times_s, dtype=float) / PEAK_BIN_S + 1e-9).astype(np.int64)
    means = pd.Series(np.asarray(power_w, dtype=float)).groupby(bins).mean()
    return float(means.max())


def compute_kpis(table: pd.DataFrame, case: TestCase, start_s: float, end_s: float,
                 price: str = 'constant',
                 step_wall_s: Sequence[float] | None = None,
                 control_step_s: float | None = None,
                 power_signs: Mapping[str, float] | None = None) -> dict[str, float | None]:
    """
    Compute BOPTEST's KPIs of one run over a test period (module docstring).

    Parameters
    ----------
    table : pd.DataFrame
        Records: ``time`` [s from 1 January] increasing, covering [start_s, end_s], and the
        test case's KPI outputs (FMU units: K, W, ppm).
    case : TestCase
        The test case (area, KPI map, data).
    start_s, end_s : float
        The test period [s from 1 January].
    price : str
        Price scenario, a key of :data:`~mshoot_core.boptest.testcase.PRICE_SCENARIOS`.
    step_wall_s : sequence of float, optional
        The controller's wall time of each control step [s] (for ``time_rat``).
    control_step_s : float, optional
        The control step [s] (default the test case's).
    power_signs : dict of str to float, optional
        Power outputs the FMU reports with the wrong sign -> -1 (module docstring).

    Returns
    -------
    dict
        :data:`KPI_NAMES` -> value (``time_rat`` None without wall times; a peak None
        without its energy vector), plus ``tdis_zones``: zone -> its discomfort [K h]; with
        sign corrections, ``power_signs`` and ``as_defined``: the energy, cost, emission and
        peak KPIs of BOPTEST's sums as the outputs are written.

    Raises
    ------
    ValueError
        For missing columns, a period the records do not cover, an unknown price scenario or
        a bad sign correction (:func:`check_power_signs`).

    """
    case.price_column(price)  # an unknown scenario fails here
    check_power_signs(case, power_signs)
    period = _window(table, start_s, end_s)
    times = period['time'].to_numpy(dtype=float)
    vectors = case.energy_outputs
    if not vectors:
        raise ValueError(f'{case.name}: kpis.json names no energy vector (expected one of '
                         'ElectricPower, GasPower, DistrictHeatingPower, ...)')
    per_zone = zone_discomfort(period, case)
    zones = {zone: hours_integral(times, below) + hours_integral(times, above)
             for zone, (below, above) in per_zone.items()}
    mean_excess = np.mean([below + above for below, above in per_zone.values()], axis=0)
    kpis: dict = {
        'tdis_tot': hours_integral(times, mean_excess),
        'idis_tot': hours_integral(times, co2_discomfort(period, case)),
        **_energy_kpis(period, case, price, power_signs),
        'time_rat': None,
    }
    if step_wall_s is not None:
        walls = np.asarray(step_wall_s, dtype=float)
        step = case.control_step_s if control_step_s is None else float(control_step_s)
        if walls.size == 0 or not np.all(np.isfinite(walls)) or not step > 0:
            raise ValueError('time_rat needs finite wall times and a positive control step')
        kpis['time_rat'] = float(walls.mean() / step)
    kpis['tdis_zones'] = zones
    if power_signs:
        kpis['power_signs'] = {name: float(sign) for name, sign in power_signs.items()}
        kpis['as_defined'] = _energy_kpis(period, case, price, None)
    return kpis


def _energy_kpis(period: pd.DataFrame, case: TestCase, price: str,
                 power_signs: Mapping[str, float] | None) -> dict[str, float | None]:
    """Return ``ener_tot``, ``cost_tot``, ``emis_tot`` and the peaks of the period's rows."""
    times = period['time'].to_numpy(dtype=float)
    scale = JOULES_PER_KWH * case.area_m2
    power = {vector: vector_power(period, case, vector, power_signs)
             for vector in case.energy_outputs}
    energy = cost = emissions = 0.0
    for vector, watts in power.items():
        energy += np.trapezoid(watts, times)
        cost += np.trapezoid(watts * case.lookup(case.price_column(price, vector), times),
                             times)
        emissions += np.trapezoid(watts * case.lookup(case.emission_column(vector), times),
                                  times)
    return {'ener_tot': float(energy / scale), 'cost_tot': float(cost / scale),
            'emis_tot': float(emissions / scale),
            **{name: (peak_power(times, power[vector]) / case.area_m2 / 1000.0
                      if vector in power else None) for vector, name in PEAK_KPIS.items()}}


def kpi_records(table: pd.DataFrame, case: TestCase, start_s: float, end_s: float,
                prices: Sequence[str] = tuple(PRICE_SCENARIOS),
                step_wall_s: Sequence[float] | None = None,
                control_step_s: float | None = None,
                power_signs: Mapping[str, float] | None = None,
                **keys: str) -> list[dict[str, float | str | None]]:
    """
    Return one KPI record per price scenario of the same run (only ``cost_tot`` differs).

    Parameters
    ----------
    table, case, start_s, end_s, step_wall_s, control_step_s, power_signs
        As :func:`compute_kpis`.
    prices : sequence of str
        Price scenarios.
    **keys : str
        Added to every record first (e.g. ``controller='rule'``, ``period='peak_heat_day'``).

    Returns
    -------
    list of dict
        ``{**keys, 'price': name, **compute_kpis(...)}`` per scenario.

    """
    records = []
    for price in prices:
        kpis = compute_kpis(table, case, start_s, end_s, price, step_wall_s, control_step_s,
                            power_signs)
        records.append({**keys, 'price': price, **kpis})
    return records
