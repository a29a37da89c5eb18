"""
Scenarios: disturbance time series and the comfort band, indexed by time [s].

A scenario is a DataFrame indexed by seconds since its start (hourly rows by
default) with the columns of :data:`SCENARIO_COLUMNS`:

- ``solrad`` [W/m2], ``Tout`` [degC], ``occ`` [persons], ``dpos`` [%]:
  disturbances held constant over each row's interval;
- ``comfort_min``, ``comfort_max`` [degC]: the comfort band at that time.

The start time of day and date are kept in ``df.attrs['start']`` (an ISO
string) so that the hour of day of each row is known.
"""
from __future__ import annotations

import functools
import logging
import pathlib

import numpy as np
import pandas as pd

logger = logging.getLogger(__name__)

DISTURBANCE_COLUMNS = ('solrad', 'Tout', 'occ', 'dpos')
COMFORT_COLUMNS = ('comfort_min', 'comfort_max')
SCENARIO_COLUMNS = DISTURBANCE_COLUMNS + COMFORT_COLUMNS
#: Start of the reference MPC case (SPEC section 3).
OU44_START = '2018-04-05 00:00'
#: The OU44 measurements where the project sits beside ``shared/`` (a checkout).
DEFAULT_DATA = (pathlib.Path(__file__).resolve().parents[4] / '..' / 'shared' / 'data' / 'ou44'
                / 'measurements.csv')
#: Measured columns the OU44 CSV must hold.
OU44_COLUMNS = ('datetime', 'T', 'solrad', 'Tout', 'occ', 'dpos')
#: Published results of the original MShoot reference case (OU44, 72 h from
#: :data:`OU44_START`, FMU tolerance 1e-11; SPEC section 3) by MPC horizon [h]: energy [kWh],
#: discomfort summed over hourly samples [K h] and wall time [s].
PUBLISHED = {2: {'energy_kwh': 40.9, 'discomfort_kh_hourly': 17.9, 'wall_s': 116.0},
             10: {'energy_kwh': 44.0, 'discomfort_kh_hourly': 13.1, 'wall_s': 3485.0}}


def comfort_band(hours_of_day: np.ndarray, occupied: tuple[float, float] = (21.0, 22.0),
                 unoccupied: tuple[float, float] = (19.0, 24.0),
                 occupied_hours: tuple[float, float] = (8.0, 17.0)
                 ) -> tuple[np.ndarray, np.ndarray]:
    """
    Comfort band of the reference case at the given hours of day.

    Parameters
    ----------
    hours_of_day : ndarray
        Hour of day of each sample [h], 0 <= h < 24.
    occupied, unoccupied : (float, float)
        (min, max) band [degC] for occupied and other hours.
    occupied_hours : (float, float)
        [start, end) of the occupied period [h].

    Returns
    -------
    (comfort_min, comfort_max) : ndarrays [degC]

    """
    hours = np.asarray(hours_of_day, dtype=float)
    occ = (hours >= occupied_hours[0]) & (hours < occupied_hours[1])
    return (np.where(occ, occupied[0], unoccupied[0]),
            np.where(occ, occupied[1], unoccupied[1]))


def read_ou44(path: str | pathlib.Path,
              columns: tuple[str, ...] = OU44_COLUMNS) -> pd.DataFrame:
    """
    Read the OU44 measurements file, indexed by its (local) date-times, sorted.

    Parameters
    ----------
    path : path-like
        The ``measurements.csv`` file (30-minute means).
    columns : tuple of str
        Columns the caller needs (``datetime`` among them).

    Returns
    -------
    DataFrame
        Every column of the file, indexed by ``datetime``.

    Raises
    ------
    FileNotFoundError, ValueError
        If the file is missing, lacks one of ``columns``, or holds a time twice
        (:func:`check_time_order`; rows out of order are sorted, with a warning).

    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'OU44 data not found at {path}')
    raw = pd.read_csv(path)
    missing = [c for c in columns if c not in raw.columns]
    if missing:
        raise ValueError(f'{path}: missing columns {missing}; expected {list(columns)}, '
                         f'got {list(raw.columns)}')
    raw['datetime'] = pd.to_datetime(raw['datetime'])
    check_time_order(raw['datetime'], path)
    return raw.set_index('datetime').sort_index(kind='stable')


#: Duplicate times quoted in one error message (then their count).
MAX_QUOTED_ROWS = 5


def check_time_order(times: pd.Series, path: str | pathlib.Path) -> bool:
    """
    Refuse a data file that holds a time twice; warn when its rows are out of time order.

    A repeated time is ambiguous (which row holds?) and changes results silently, so it is an
    error naming the file's lines; rows out of order are only sorted, with a warning.

    Parameters
    ----------
    times : Series
        The file's time column, in file order (row k is line k + 2 of the file: one header).
    path : path-like
        The file, for messages.

    Returns
    -------
    bool
        Whether the rows were in time order.

    Raises
    ------
    ValueError
        One line: the lines of the first repeated times and how many there are.

    """
    values = pd.Series(np.asarray(times), index=np.arange(len(times)) + 2)  # file lines
    repeated = values[values.duplicated(keep=False)]
    if len(repeated):
        groups = [f'lines {" and ".join(str(n) for n in lines)} ({time})' for time, lines in
                  repeated.groupby(repeated, sort=False).groups.items()]
        more = (f' (and {len(groups) - MAX_QUOTED_ROWS} more times)'
                if len(groups) > MAX_QUOTED_ROWS else '')
        raise ValueError(f'{path}: {len(groups)} time{"s" if len(groups) != 1 else ""} '
                         f'given twice or more: {"; ".join(groups[:MAX_QUOTED_ROWS])}{more}; '
                         'each time must appear once')
    later = values.to_numpy()
    backwards = np.flatnonzero(later[1:] < later[:-1])
    if backwards.size:
        line = int(values.index[backwards[0] + 1])
        logger.warning('%s: %d row%s out of time order (the first at line %d: %s after %s); '
                       'sorted by time', path, backwards.size, 's' if backwards.size > 1 else '',
                       line, values.iloc[backwards[0] + 1], values.iloc[backwards[0]])
        return False
    return True


def load_ou44(path: str | pathlib.Path, start: str = '2018-04-05 00:00',
              end: str = '2018-04-08 00:00', step_s: float = 3600.0) -> pd.DataFrame:
    """
    Load the OU44 measurements, resampled to ``step_s`` means, as a scenario.

    Parameters
    ----------
    path : path-like
        The ``measurements.csv`` file (30-minute means, local time).
    start, end : str
        Inclusive time range (the reference MPC case: 5 to 8 April 2018, 73 rows).
    step_s : float
        Resampling step [s], a multiple of 1800 s.

    Returns
    -------
    DataFrame
        Index: seconds since ``start``; columns :data:`SCENARIO_COLUMNS` plus
        ``T_measured`` [degC]; ``attrs['start']`` the ISO start time.

    Raises
    ------
    FileNotFoundError, ValueError
        If the file is missing, lacks columns, or does not cover the range.

    """
    raw = read_ou44(path)
    if step_s <= 0 or step_s % 1800:
        raise ValueError(f'step_s must be a positive multiple of 1800 s, got {step_s}')
    values = raw[['T', 'solrad', 'Tout', 'occ', 'dpos']].astype(float)
    resampled = values.resample(pd.Timedelta(seconds=step_s)).mean()
    t0, t1 = pd.Timestamp(start), pd.Timestamp(end)
    if t0 < resampled.index[0] or t1 > resampled.index[-1]:
        raise ValueError(f'{path} covers {resampled.index[0]} to {resampled.index[-1]}, '
                         f'not the requested {t0} to {t1}')
    sel = resampled.loc[t0:t1]
    if sel.isna().any().any():
        raise ValueError(f'{path}: gaps in the data between {t0} and {t1}')
    scenario = pd.DataFrame({c: sel[c].to_numpy() for c in DISTURBANCE_COLUMNS},
                            index=(sel.index - t0).total_seconds().to_numpy())
    hours = (sel.index.hour + sel.index.minute / 60.0).to_numpy()
    scenario['comfort_min'], scenario['comfort_max'] = comfort_band(hours)
    scenario['T_measured'] = sel['T'].to_numpy()
    scenario.index.name = 'time_s'
    scenario.attrs['start'] = t0.isoformat()
    return scenario


def synthetic_scenario(hours: int = 73, seed: int = 0, step_s: float = 3600.0) -> pd.DataFrame:
    """
    Return a built-in scenario that needs no files: three spring days in a classroom.

    Outdoor temperature follows a daily sine (mean 7 degC, amplitude 4 K,
    minimum at 04:00), solar radiation a clipped half-sine (peak 450 W/m2 at
    noon), occupancy 25 persons on 08:00-16:00 with a lunch dip; a seeded
    noise makes the days differ. Ventilation is off (dpos = 0), as in the MPC
    reference case.

    Parameters
    ----------
    hours : int
        Number of rows (73 covers 72 h of control).
    seed : int
        Seed of the day-to-day noise.
    step_s : float
        Row spacing [s].

    """
    if hours < 2:
        raise ValueError(f'hours must be >= 2, got {hours}')
    rng = np.random.default_rng(seed)
    t = np.arange(hours) * step_s
    hour = (t / 3600.0) % 24.0
    day = (t // 86400.0).astype(int)
    day_offset = rng.normal(0.0, 1.5, size=day.max() + 1)[day]
    tout = 7.0 - 4.0 * np.cos(2 * np.pi * (hour - 4.0) / 24.0) + day_offset
    cloudiness = rng.uniform(0.5, 1.0, size=day.max() + 1)[day]
    solrad = np.clip(450.0 * np.sin(np.pi * (hour - 6.0) / 13.0), 0.0, None) * cloudiness
    occ = np.where((hour >= 8) & (hour < 16), 25.0, 0.0)
    occ = np.where(hour == 12, 10.0, occ)
    cmin, cmax = comfort_band(hour)
    scenario = pd.DataFrame({'solrad': solrad, 'Tout': tout, 'occ': occ,
                             'dpos': np.zeros(hours), 'comfort_min': cmin, 'comfort_max': cmax},
                            index=pd.Index(t, name='time_s'))
    scenario.attrs['start'] = '2018-04-05T00:00:00'
    return scenario


def validate_scenario(scenario: pd.DataFrame) -> None:
    """
    Raise ValueError if ``scenario`` lacks the band, has NaN, or a band with min > max.

    The disturbances are whatever other columns it has (the models take theirs by name).
    """
    missing = [c for c in COMFORT_COLUMNS if c not in scenario.columns]
    if missing:
        raise ValueError(f'scenario lacks columns {missing}; expected the comfort band '
                         f'{list(COMFORT_COLUMNS)} and the series of the models, got '
                         f'{list(scenario.columns)}')
    values = scenario.select_dtypes('number').to_numpy(dtype=float)
    if not np.all(np.isfinite(values)):
        raise ValueError('scenario holds non-finite values')
    if np.any(scenario['comfort_min'].to_numpy() > scenario['comfort_max'].to_numpy()):
        raise ValueError('scenario comfort band has comfort_min > comfort_max')
    t = np.asarray(scenario.index, dtype=float)
    if t.size < 2 or np.any(np.diff(t) <= 0):
        raise ValueError('scenario index must be strictly increasing times [s]')


#: Time columns of a data CSV: ISO date-times, or seconds since the first row.
TIME_COLUMNS = ('datetime', 'time', 'time_s')
#: Start date of a data CSV timed in seconds (``time_s``) [ISO].
DATA_START = '2020-01-01T00:00:00'


def is_ou44_format(path: str | pathlib.Path) -> bool:
    """Whether a CSV is in the OU44 measurements' format (its columns, no comfort band)."""
    columns = pd.read_csv(path, nrows=0).columns
    return all(c in columns for c in OU44_COLUMNS) and not any(
        c in columns for c in COMFORT_COLUMNS)


def read_data_csv(path: str | pathlib.Path, step_s: float = 3600.0,
                  band: tuple[float, float] | None = None) -> pd.DataFrame:
    """
    Read a data CSV as a scenario: a time column and a column per series, as interval means.

    Parameters
    ----------
    path : path-like
        The CSV: a time column (``datetime`` or ``time``, ISO date-times, or ``time_s``,
        seconds since the first row), one numeric column per series (named as the models'
        inputs, e.g. ``Tout`` [degC], ``solrad`` [W/m2], ``occ``), and the comfort band
        ``comfort_min``, ``comfort_max`` [degC] (per zone also ``comfort_min_<zone>``, ...),
        unless ``band`` is given.
    step_s : float
        Row spacing of the scenario [s]: each row holds the means of the file's rows in
        ``[t, t + step_s)`` (a coarser file is held: its rows repeated).
    band : (float, float), optional
        A constant comfort band [degC] where the file has none (refused if it has one).

    Returns
    -------
    DataFrame
        Index: seconds since the first row; the series and the band; ``attrs['start']``.

    Raises
    ------
    FileNotFoundError, ValueError
        A missing file, no time column, a time given twice, non-numeric series, gaps, no band
        (or two), a band with min > max.

    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f'data CSV not found: {path}')
    if not step_s > 0:
        raise ValueError(f'step_s must be > 0 s, got {step_s}')
    raw = pd.read_csv(path)
    time_column = next((c for c in TIME_COLUMNS if c in raw.columns), None)
    if time_column is None:
        raise ValueError(f'{path}: no time column; expected one of {list(TIME_COLUMNS)}, got '
                         f'{list(raw.columns)}')
    if time_column == 'time_s':
        times = pd.Timestamp(DATA_START) + pd.to_timedelta(raw[time_column], unit='s')
    else:
        times = pd.to_datetime(raw[time_column])
    check_time_order(times, path)
    values = raw.drop(columns=[time_column])
    bad = [c for c in values.columns if not pd.api.types.is_numeric_dtype(values[c])]
    if bad:
        raise ValueError(f'{path}: columns {bad} are not numbers; a data CSV holds a time '
                         'column and numeric series')
    has_band = [c for c in COMFORT_COLUMNS if c in values.columns]
    if band is not None and has_band:
        raise ValueError(f'{path} has a comfort band ({has_band}): give no band besides it')
    if band is None and len(has_band) != 2:
        raise ValueError(f'{path}: no comfort band; expected columns {list(COMFORT_COLUMNS)} '
                         f'[degC], or a band given with it (e.g. --band 20,24)')
    values.index = pd.DatetimeIndex(times)
    values = values.sort_index(kind='stable').astype(float)
    table = values.resample(pd.Timedelta(seconds=step_s), label='left', closed='left').mean()
    table = table.ffill()
    if table.isna().any().any():
        raise ValueError(f'{path}: empty series at the start of the data: '
                         f'{[c for c in table.columns if table[c].isna().any()]}')
    if band is not None:
        table['comfort_min'], table['comfort_max'] = float(band[0]), float(band[1])
    scenario = table.set_axis((table.index - table.index[0]).total_seconds().to_numpy())
    scenario.index.name = 'time_s'
    scenario.attrs['start'] = table.index[0].isoformat()
    validate_scenario(scenario)
    return scenario


def data_scenario(path: str | pathlib.Path, hours: int,
                  band: tuple[float, float] | None = None,
                  step_s: float = 3600.0) -> pd.DataFrame:
    """
    Return the first ``hours`` control steps (``hours + 1`` rows) of a data CSV.

    See :func:`read_data_csv`; a CSV too short is a ValueError saying how long it is.
    """
    scenario = read_data_csv(path, step_s, band)
    if len(scenario) < hours + 1:
        raise ValueError(f'{path} covers {len(scenario) - 1} control steps of {step_s:g} s, '
                         f'not {hours}')
    return scenario.iloc[:hours + 1]


def reference_scenario(name: str, data: str | pathlib.Path | None = None,
                       hours: int = 72) -> pd.DataFrame:
    """
    Return the scenario of the MPC case: ``hours`` control steps (``hours + 1`` rows).

    Parameters
    ----------
    name : str
        'ou44' (5-8 April 2018 from the OU44 data, ventilation off as in the
        MPC case), 'synthetic' (built in, no files), or a path to a CSV in the
        OU44 format (read like 'ou44') or to a data CSV with a band
        (:func:`read_data_csv`, hourly means).
    data : path-like, optional
        The OU44 ``measurements.csv`` for 'ou44' (default :data:`DEFAULT_DATA`).
    hours : int
        Control steps.

    Raises
    ------
    FileNotFoundError, ValueError
        Missing data, or data that does not cover ``hours``.

    """
    if hours < 1:
        raise ValueError(f'hours must be >= 1, got {hours}')
    if name == 'synthetic':
        return synthetic_scenario(hours=hours + 1)
    if name != 'ou44' and not is_ou44_format(name):
        return data_scenario(name, hours)
    path = pathlib.Path(name) if name != 'ou44' else pathlib.Path(data or DEFAULT_DATA)
    end = pd.Timestamp(OU44_START) + pd.Timedelta(hours=hours)
    scenario = load_ou44(path, start=OU44_START, end=str(end))
    scenario['dpos'] = 0.0  # the MPC case runs with the ventilation off
    return scenario


@functools.lru_cache(maxsize=256)
def column_labels(names: tuple[str, ...]) -> pd.Index:
    """
    Return the column labels ``names`` as one (immutable) pandas Index, built once.

    A frame built every control step with the same columns takes this Index instead of a list
    (pandas infers the labels' type from a list at every frame: tens of microseconds).
    """
    return pd.Index(list(names))


def forecast_rows(index: int, horizon_steps: int, length: int) -> np.ndarray:
    """Return the rows of :func:`forecast_window`: ``index .. index + horizon_steps``, clipped."""
    if not 0 <= index < length:
        raise ValueError(f'index must be in [0, {length - 1}], got {index}')
    return np.minimum(np.arange(index, index + horizon_steps + 1), length - 1)


def forecast_window(scenario: pd.DataFrame, index: int, horizon_steps: int) -> pd.DataFrame:
    """
    Rows ``index .. index + horizon_steps`` of ``scenario`` (N+1 rows).

    Past the end of the scenario the last row is repeated (a persistence
    forecast), so the controller can plan the final hours of a run. The index is the
    rows' times [s]; the attrs are the scenario's. A scenario of numbers only (its series
    are floats) comes as one float64 array (taking the rows from it costs a third of
    selecting them in pandas: about a millisecond per step of the forecaster node); other
    columns keep their types.
    """
    rows = forecast_rows(index, horizon_steps, len(scenario))
    times = scenario.index.to_numpy()
    step = float(times[1] - times[0]) if len(times) > 1 else 3600.0
    window_index = pd.Index(float(times[index]) + np.arange(horizon_steps + 1) * step,
                            name=scenario.index.name)
    values = scenario.to_numpy()
    if values.dtype != np.float64:  # not only numbers: each column keeps its type
        window = scenario.iloc[rows]
        window.index = window_index
        return window
    window = pd.DataFrame(values[rows], index=window_index, columns=scenario.columns,
                          copy=False)
    window.attrs = dict(scenario.attrs)
    return window
