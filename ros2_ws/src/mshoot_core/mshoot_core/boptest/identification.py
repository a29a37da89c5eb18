"""
Identification of the BOPTEST house's control model from data the emulator produces.

Stable API::

    from mshoot_core.boptest import identification as ident
    records = ident.excite(case, 33, 101, seed=1)         # the plant under an excitation
    table = ident.hourly_table(records, case)              # hourly means, zone at the hours
    hp = ident.fit_heat_pump(records)                      # qa, qb, pa, pb, paux
    result = ident.identify(table, hp)                     # CalibrationResult (+ periods)

The excitation (outside BOPTEST's test periods and their warm-ups: days 16-30 and 108-122)
holds random levels for 1 to 8 h each: a zone setpoint ``oveTSet_u`` in 15-25 degC for the
building's own loop (40 %), the heat pump off (10 %), a modulation ``oveHeaPumY_u`` in 0.1-1
(20 %), or full-load bursts of a random duty per hour (30 %: the way the MPC runs it); above
26 degC the heat pump is stopped until the zone is below 25 degC again.

The fit (:func:`mshoot_core.calibration.calibrate`) simulates each period freely from its
first hour: the zone from the measurement, the floor and the envelope from the steady state of
the model with the measured zone temperature and the first day's mean inputs.
"""
from __future__ import annotations

import dataclasses
import logging
import pathlib
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core import calibration
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import KELVIN

logger = logging.getLogger(__name__)

#: Excitation runs (first day, last day, seed) of the reference identification.
RUNS = ((33, 101, 1), (313, 358, 2))
#: Training and validation periods of the reference identification [days of the year].
TRAIN = ((40.0, 95.0), (335.0, 358.0))
VALIDATION = ((95.0, 101.0), (320.0, 335.0))
#: Days before an excitation starts, under the building's own control.
LEAD_DAYS = 3.0
#: Above this zone temperature the excitation stops the heat pump, until below RESUME [degC].
GUARD_C, RESUME_C = 26.0, 25.0
#: Modulation above which the heat pump counts as at full load, for its fit [-].
FULL_LOAD = 0.98
#: Free parameters of the house model: start values and bounds.
FREE = (calibration.FreeParameter('Cz', 5e6, 1e4, 1e8),
        calibration.FreeParameter('Cf', 3e7, 1e6, 3e8),
        calibration.FreeParameter('Ce', 5e7, 1e6, 1e10),
        calibration.FreeParameter('Rzf', 2e-3, 1e-5, 5e-2),
        calibration.FreeParameter('Rze', 5e-3, 1e-4, 1e-1),
        calibration.FreeParameter('Rzo', 2e-2, 1e-3, 1.0),
        calibration.FreeParameter('Reo', 1e-2, 1e-4, 1e-1),
        calibration.FreeParameter('gz', 5.0, 0.0, 50.0),
        calibration.FreeParameter('ge', 5.0, 0.0, 50.0),
        calibration.FreeParameter('gi', 1.0, 0.0, 3.0))
_DAY_S = 86400.0


def _test_days(case: TestCase) -> list[tuple[float, float]]:
    """Days [first, last) of every test period with its warm-up."""
    return [(d - 14.0, d + 7.0) for d in case.days.values()]


def excite(case: TestCase, first_day: float, last_day: float, seed: int,
           lead_days: float = LEAD_DAYS,
           sample_s: float = 60.0) -> pd.DataFrame:
    """
    Run the plant under the excitation from ``first_day`` to ``last_day`` (see the module).

    Parameters
    ----------
    case : TestCase
        The test case.
    first_day, last_day : float
        The excited days of the year (the plant starts ``lead_days`` earlier, under the
        building's own control).
    seed : int
        Seed of the random levels.
    lead_days : float
        Days simulated before the excitation [days].
    sample_s : float
        Plant step and guard check [s].

    Returns
    -------
    DataFrame
        The plant's records (:meth:`BoptestPlant.records`) from ``first_day``.

    Raises
    ------
    ValueError
        If the days overlap a test period or its warm-up, or are out of the year.

    """
    from mshoot_core.boptest.plant import BoptestPlant
    if not (0 <= first_day - lead_days and first_day < last_day <= 365):
        raise ValueError(f'excitation days must satisfy {lead_days:g} <= first < last <= 365, '
                         f'got {first_day:g} and {last_day:g}')
    for lo, hi in _test_days(case):
        if first_day < hi and last_day > lo:
            raise ValueError(f'excitation days [{first_day:g}, {last_day:g}) overlap a test '
                             f'period with its warm-up [{lo:g}, {hi:g})')
    rng = np.random.default_rng(seed)
    t0, t_end = first_day * _DAY_S, last_day * _DAY_S
    with BoptestPlant(case) as plant:
        plant.start(t0 - lead_days * _DAY_S)
        plant.advance(t0)
        t, segment_end, kind, level, hot = t0, t0, 'off', 0.0, False
        while t < t_end - 1e-6:
            if t >= segment_end - 1e-6:
                segment_end = t + 3600.0 * int(rng.integers(1, 9))
                draw = rng.uniform()
                if draw < 0.4:
                    kind, level = 'setpoint', KELVIN + rng.uniform(15.0, 25.0)
                elif draw < 0.5:
                    kind, level = 'off', 0.0
                elif draw < 0.7:
                    kind, level = 'modulation', rng.uniform(0.1, 1.0)
                else:
                    kind, level = 'bursts', rng.uniform(0.0, 1.0)
            zone_c = plant.outputs['reaTZon_y'] - KELVIN
            hot = zone_c > GUARD_C or (hot and zone_c > RESUME_C)
            if hot or kind == 'off':
                overwrites = {'oveHeaPumY_u': 0.0}
            elif kind == 'setpoint':
                overwrites = {'oveTSet_u': level}
            elif kind == 'modulation':
                overwrites = {'oveHeaPumY_u': level}
            else:
                overwrites = {'oveHeaPumY_u': 1.0 if (t % 3600.0) / 3600.0 < level else 0.0}
            plant.advance(t + sample_s, overwrites)
            t += sample_s
        return plant.records(t0, t_end)


def excitation_records(case: TestCase, cache: str | pathlib.Path | None = None,
                       runs: Sequence[tuple[float, float, int]] = RUNS) -> list[pd.DataFrame]:
    """
    Return the records of the excitation ``runs``, from ``cache`` if there (else run and store).

    Parameters
    ----------
    case : TestCase
        The test case.
    cache : path, optional
        Folder of the cached records (``excitation_<first>_<last>_<seed>.pkl``); None: no cache.
    runs : sequence of (first_day, last_day, seed)
        The excitation runs (:func:`excite`).

    """
    out = []
    for first, last, seed in runs:
        path = None if cache is None else (
            pathlib.Path(cache) / f'excitation_{first:g}_{last:g}_{seed}.pkl')
        if path is not None and path.is_file():
            out.append(pd.read_pickle(path))
            continue
        logger.info('exciting the plant over days %g-%g (seed %d)', first, last, seed)
        records = excite(case, first, last, seed)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            records.to_pickle(path)
        out.append(records)
    return out


def fit_heat_pump(records: pd.DataFrame | Sequence[pd.DataFrame]) -> dict[str, float]:
    """
    Return the heat pump at full load: heat qa + qb Tout, compressor power pa + pb Tout [W].

    Straight lines through the samples at full load (modulation above :data:`FULL_LOAD`),
    Tout in degC; ``paux`` the mean fan and emission pump power there [W].

    Raises
    ------
    ValueError
        With fewer than 10 samples at full load.

    """
    table = records if isinstance(records, pd.DataFrame) else pd.concat(list(records))
    full = table[table['reaHeaPumY_y'] > FULL_LOAD]
    if len(full) < 10:
        raise ValueError(f'{len(full)} samples at full load: too few to fit the heat pump')
    tout = full['weaSta_reaWeaTDryBul_y'].to_numpy() - KELVIN
    qb, qa = np.polyfit(tout, full['reaQHeaPumCon_y'].to_numpy(), 1)
    pb, pa = np.polyfit(tout, full['reaPHeaPum_y'].to_numpy(), 1)
    paux = float(full['reaPFan_y'].mean() + full['reaPPumEmi_y'].mean())
    return {'qa': float(qa), 'qb': float(qb), 'pa': float(pa), 'pb': float(pb), 'paux': paux}


def power_errors(records: pd.DataFrame, heat_pump: Mapping[str, float]) -> dict[str, float]:
    """
    Score the electric power model on records: RMSE and mean error at full load [W].

    Also the COP at full load as a line in Tout (a + b Tout) from ``reaCOP_y`` and its RMSE.
    """
    full = records[records['reaHeaPumY_y'] > FULL_LOAD]
    tout = full['weaSta_reaWeaTDryBul_y'].to_numpy() - KELVIN
    power = (full['reaPHeaPum_y'] + full['reaPFan_y'] + full['reaPPumEmi_y']).to_numpy()
    model = heat_pump['pa'] + heat_pump['pb'] * tout + heat_pump['paux']
    heat = full['reaQHeaPumCon_y'].to_numpy()
    heat_model = heat_pump['qa'] + heat_pump['qb'] * tout
    cop_b, cop_a = np.polyfit(tout, full['reaCOP_y'].to_numpy(), 1)
    cop_error = full['reaCOP_y'].to_numpy() - (cop_a + cop_b * tout)
    return {'samples': int(len(full)),
            'power_rmse_w': float(np.sqrt(np.mean((power - model) ** 2))),
            'power_mean_error_w': float(np.mean(model - power)),
            'power_mean_w': float(np.mean(power)),
            'heat_rmse_w': float(np.sqrt(np.mean((heat - heat_model) ** 2))),
            'heat_mean_w': float(np.mean(heat)),
            'cop_a': float(cop_a), 'cop_b': float(cop_b),
            'cop_rmse': float(np.sqrt(np.mean(cop_error ** 2)))}


def hourly_table(records: pd.DataFrame, case: TestCase, step_s: float = 3600.0) -> pd.DataFrame:
    """
    Return the records as model inputs per step and the zone temperature at each step's start.

    Index: step start [s]; columns ``Tout`` [degC], ``solar`` [W/m2] (the building's weather
    outputs), ``gains`` [W] (data), ``Q`` mean condenser heat [W], ``P`` mean electric power
    [W], ``Tz`` zone temperature [degC] at the index time. Steps not fully covered are dropped.
    """
    times = records['time'].to_numpy(dtype=float)
    step_of = np.floor((times - 1e-6) / step_s).astype(int)  # a row ends the sample before it
    frame = pd.DataFrame({
        'step': step_of, 'Tout': records['weaSta_reaWeaTDryBul_y'].to_numpy() - KELVIN,
        'solar': records['weaSta_reaWeaHGloHor_y'].to_numpy(),
        'Q': records['reaQHeaPumCon_y'].to_numpy(),
        'P': (records['reaPHeaPum_y'] + records['reaPFan_y']
              + records['reaPPumEmi_y']).to_numpy()})
    grouped = frame.iloc[1:].groupby('step')
    table = grouped.mean()
    counts = grouped.size()
    table = table[counts >= counts.max()]
    table.index = table.index.to_numpy(dtype=float) * step_s
    zone = pd.Series(records['reaTZon_y'].to_numpy() - KELVIN, index=times)
    table['Tz'] = zone.reindex(table.index).to_numpy()
    from mshoot_core.boptest.economic import _interval_means
    starts = table.index.to_numpy(dtype=float)
    table['gains'] = (_interval_means(case, 'InternalGainsCon[1]', starts, step_s)
                      + _interval_means(case, 'InternalGainsRad[1]', starts, step_s))
    return table.dropna()


class _SteadyStart(Model):
    """
    The house's control model, floor and envelope started at the steady state of the first day.

    Parameters
    ----------
    model : Model
        The network of the card ``boptest_house``
        (:func:`~mshoot_core.boptest.economic.control_model`).

    """

    def __init__(self, model: Model) -> None:
        self.model = model
        self.input_names = model.input_names
        self.state_names = model.state_names
        self.output_names = model.output_names

    def simulate(self, udf: pd.DataFrame, x0: Sequence[float]) -> tuple[pd.DataFrame,
                                                                        pd.DataFrame]:
        p = self.model.parameters
        first = udf.iloc[:min(len(udf), 24)]
        heat = float((first['d'] * (p['qa'] + p['qb'] * first['Tout'])).mean())
        tout = float(first['Tout'].mean()) + KELVIN
        solar = float(first['solar'].mean())
        tz = float(x0[0])
        tf = tz + heat * p['Rzf']
        te = ((tz / p['Rze'] + tout / p['Reo'] + p['ge'] * solar)
              / (1.0 / p['Rze'] + 1.0 / p['Reo']))
        return self.model.simulate(udf, [tz, tf, te])


def periods(table: pd.DataFrame, heat_pump: Mapping[str, float],
            ranges: Sequence[tuple[float, float]], name: str) -> list[calibration.Period]:
    """
    Return calibration periods of the hourly ``table`` over day ``ranges``.

    The duty input is the measured heat over the full-load heat at the hour's mean Tout.
    """
    out = []
    for k, (first, last) in enumerate(ranges):
        part = table.loc[first * _DAY_S:last * _DAY_S]
        if len(part) < 2:
            raise ValueError(f'no data over days {first:g}-{last:g}')
        full = heat_pump['qa'] + heat_pump['qb'] * part['Tout']
        inputs = pd.DataFrame({'Tout': part['Tout'], 'solar': part['solar'],
                               'gains': part['gains'], 'price': 0.0,
                               'd': (part['Q'] / full).clip(lower=0.0)}, index=part.index)
        tz = part['Tz'].to_numpy()
        out.append(calibration.Period(f'{name}_{k}' if len(ranges) > 1 else name, inputs,
                                      np.array([tz[0] + KELVIN, tz[0] + KELVIN,
                                                tz[0] + KELVIN]), tz))
    return out


@dataclasses.dataclass
class Identification:
    """
    An identified house model.

    Attributes
    ----------
    parameters : dict
        The parameters of the card ``boptest_house``'s network (name -> value).
    result : CalibrationResult
        The fit of the thermal parameters (metrics per period: RMSE, MAE [K]).
    heat_pump : dict
        The full-load heat pump fit (qa, qb, pa, pb, paux).
    power : dict
        :func:`power_errors` on the validation records.

    """

    parameters: dict[str, float]
    result: calibration.CalibrationResult
    heat_pump: dict[str, float]
    power: dict[str, float]

    def to_dict(self) -> dict:
        return {'parameters': dict(self.parameters), 'fit': self.result.to_dict(),
                'heat_pump': self.heat_pump, 'power_model': self.power}


def identify(tables: Sequence[pd.DataFrame], records: Sequence[pd.DataFrame],
             train: Sequence[tuple[float, float]] = TRAIN,
             validation: Sequence[tuple[float, float]] = VALIDATION,
             free: Sequence[calibration.FreeParameter] = FREE, starts: int = 1,
             max_evaluations: int | None = None) -> Identification:
    """
    Fit the house model to hourly tables (:func:`hourly_table`) of the excitation records.

    Parameters
    ----------
    tables : sequence of DataFrame
        Hourly tables; the day ranges may fall in any of them.
    records : sequence of DataFrame
        The records the tables came from (the heat pump fit; the power model's score on the
        validation days).
    train, validation : sequence of (first_day, last_day)
        Days of the year fitted, and only scored.
    free : sequence of FreeParameter
        The thermal parameters fitted (the heat pump's are fitted before, at full load).
    starts, max_evaluations : int
        See :func:`~mshoot_core.calibration.calibrate`.

    """
    table = pd.concat(list(tables)).sort_index()
    table = table[~table.index.duplicated()]
    all_records = pd.concat(list(records)).sort_values('time')
    in_train = np.zeros(len(all_records), dtype=bool)
    for first, last in train:
        t = all_records['time'].to_numpy()
        in_train |= (t >= first * _DAY_S) & (t < last * _DAY_S)
    heat_pump = fit_heat_pump(all_records[in_train])
    power = power_errors(all_records[~in_train], heat_pump)
    train_periods = periods(table, heat_pump, train, 'train')
    validation_periods = periods(table, heat_pump, validation, 'validation')

    from mshoot_core.boptest.economic import control_model

    def build(values: Mapping[str, float]) -> Model:
        return _SteadyStart(control_model({**heat_pump, **values}))

    result = calibration.calibrate(build, free, train_periods, validation_periods,
                                   starts=starts, max_evaluations=max_evaluations)
    parameters = {**control_model().parameters, **heat_pump, **result.parameters}
    return Identification(parameters, result, heat_pump, power)
