"""
A BOPTEST test case on disk: its FMU, configuration, test periods, KPI map and data.

Stable API (other modules build on it)::

    from mshoot_core.boptest.testcase import TestCase, PRICE_SCENARIOS, load_shim
    case = TestCase.load()                 # or TestCase.load('/path/to/test_case')
    case.area_m2, case.control_step_s, case.fmu_path, case.days, case.kpi_outputs
    warmup_start_s, start_s, end_s = case.test_period('peak_heat_day')
    case.test_period('peak_heat_day', warmup_days=1, length_days=2)   # shortened
    case.lookup('LowerSetp[1]', times_s) -> np.ndarray   # forward-filled
    case.lookup_frame(['TDryBul', 'HGloHor'], times_s) -> pd.DataFrame (index: time [s])
    case.price_column('dynamic') -> 'PriceElectricPowerDynamic'
    load_shim(case.directory) -> tuple[str, ...]          # stand-ins (shim/), loaded RTLD_GLOBAL

The test case folder (``bestest_hydronic_heat_pump`` of BOPTEST, read-only) is found by
:func:`default_directory`: the environment variable ``MSHOOT_BOPTEST_DIR`` or else
``../shared/boptest/bestest_hydronic_heat_pump`` beside the repository. It holds
``wrapped.fmu``, ``config.json`` (floor area, control step), ``days.json`` (test period days),
``kpis.json`` (which outputs feed which KPI) and ``Resources/*.csv`` (900 s rows over one year,
``time`` in seconds from 1 January, the FMU's clock): the comfort band and occupancy
(``dataFromModel.csv``), prices, emissions and weather. Between their rows these data are held
constant (forward-filled), as BOPTEST's KPI calculator does.

The FMU's binary may need a library the host lacks (the heat pump house's ``libgfortran.so.4``,
GCC 7, which current Debian does not ship); the test case carries the source of a stand-in
(``shim/``). :func:`load_shim` checks the binary in a child process and compiles the stand-in
once into the project's cache for the library found missing (see
:mod:`mshoot_core.fmu_binary`), never into the test case folder, and loads it with
``RTLD_GLOBAL`` so the FMU's binary resolves against it.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import logging
import os
import pathlib
from typing import Sequence

import numpy as np
import pandas as pd

from mshoot_core import fmu_cache

logger = logging.getLogger(__name__)

#: Environment variable naming the test case folder.
DIR_ENV = 'MSHOOT_BOPTEST_DIR'
#: The test case beside the repository (a checkout with ``shared/`` next to it).
DEFAULT_DIR = (pathlib.Path(__file__).resolve().parents[5] / '..' / 'shared' / 'boptest'
               / 'bestest_hydronic_heat_pump')
#: BOPTEST's warm-up before a test period and the period's length [days].
WARMUP_DAYS = 7.0
LENGTH_DAYS = 14.0
#: Price scenario name -> column of ``prices.csv`` [EUR/kWh].
PRICE_SCENARIOS = {'constant': 'PriceElectricPowerConstant',
                   'dynamic': 'PriceElectricPowerDynamic',
                   'highly_dynamic': 'PriceElectricPowerHighlyDynamic'}
#: Column of ``emissions.csv`` [kgCO2/kWh].
EMISSIONS_COLUMN = 'EmissionsElectricPower'
#: Resource files read (``Resources/<name>``).
RESOURCE_FILES = ('dataFromModel.csv', 'prices.csv', 'emissions.csv', 'weather.csv')
#: Comfort band columns of zone 1 [K].
LOWER_SETPOINT = 'LowerSetp[1]'
UPPER_SETPOINT = 'UpperSetp[1]'
SECONDS_PER_DAY = 86400.0
#: BOPTEST's weather points (the ``weather`` category of its ``data/categories.json``): its
#: forecasts interpolate them linearly between rows and hold every other series.
WEATHER_POINTS = frozenset({
    'pAtm', 'nTot', 'nOpa', 'HGloHor', 'HDifHor', 'HDirNor', 'ceiHei', 'winSpe', 'HHorIR',
    'winDir', 'cloTim', 'solTim', 'TDewPoi', 'relHum', 'TDryBul', 'TWetBul', 'solAlt', 'solZen',
    'solDec', 'solHouAng', 'lon', 'lat', 'TBlaSky'})


def default_directory() -> pathlib.Path:
    """Return the test case folder: ``$MSHOOT_BOPTEST_DIR`` or :data:`DEFAULT_DIR`."""
    value = os.environ.get(DIR_ENV)
    if value:
        return pathlib.Path(value).expanduser().resolve()
    return DEFAULT_DIR.resolve()


def _read_json(path: pathlib.Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f'BOPTEST test case file missing: {path}')
    with open(path, encoding='utf-8') as stream:
        return json.load(stream)


@dataclasses.dataclass(frozen=True, eq=False)
class TestCase:
    """
    One BOPTEST test case folder (see the module docstring).

    Attributes
    ----------
    directory : pathlib.Path
        The test case folder.
    name : str
        Its name (``config.json``).
    area_m2 : float
        Floor area [m2], the KPIs' normalisation.
    control_step_s : float
        BOPTEST's default control step [s].
    days : dict of str to int
        Test period name -> its day of the year (``days.json``).
    kpi_outputs : dict of str to list of str
        KPI quantity -> the FMU outputs that feed it (``kpis.json``), e.g.
        ``'ElectricPower': ['reaPFan_y', 'reaPHeaPum_y', 'reaPPumEmi_y']``.

    """

    __test__ = False  # not a pytest test class

    directory: pathlib.Path
    name: str
    area_m2: float
    control_step_s: float
    days: dict[str, int]
    kpi_outputs: dict[str, list[str]]

    @classmethod
    def load(cls, directory: str | os.PathLike | None = None) -> TestCase:
        """
        Read a test case folder.

        Parameters
        ----------
        directory : path, optional
            The folder; default :func:`default_directory`.

        Raises
        ------
        FileNotFoundError
            If the folder, its FMU or one of its JSON files is missing.
        ValueError
            If ``config.json`` lacks the floor area or it is not positive.

        """
        folder = pathlib.Path(directory).expanduser().resolve() if directory is not None \
            else default_directory()
        if not folder.is_dir():
            raise FileNotFoundError(
                f'BOPTEST test case folder not found: {folder} (set ${DIR_ENV} or pass the '
                'folder)')
        if not (folder / 'wrapped.fmu').is_file():
            raise FileNotFoundError(f'BOPTEST test case without its FMU: {folder / "wrapped.fmu"}')
        config = _read_json(folder / 'config.json')
        area = float(config.get('area', float('nan')))
        if not area > 0:
            raise ValueError(f'{folder / "config.json"}: expected a positive "area" [m2], got '
                             f'{config.get("area")!r}')
        days = {str(k): int(v) for k, v in _read_json(folder / 'days.json').items()}
        kpis = {str(k): [str(n) for n in v]
                for k, v in _read_json(folder / 'kpis.json').items()}
        return cls(folder, str(config.get('name', folder.name)), area,
                   float(config.get('step', 3600.0)), days, kpis)

    # -- files ---------------------------------------------------------------------------------
    @property
    def fmu_path(self) -> pathlib.Path:
        """Return the test case's FMI 2.0 Co-Simulation FMU."""
        return self.directory / 'wrapped.fmu'

    @property
    def power_outputs(self) -> list[str]:
        """Return the FMU outputs whose sum is the electric power [W] (``kpis.json``)."""
        return list(self.kpi_outputs.get('ElectricPower', []))

    @property
    def zone_temperature_outputs(self) -> list[str]:
        """Return the FMU outputs of the zones' operative temperatures [K] (``kpis.json``)."""
        return [n for k, v in self.kpi_outputs.items()
                if k.startswith('OperativeZoneTemperature') for n in v]

    @property
    def co2_outputs(self) -> list[str]:
        """Return the FMU outputs of the zones' CO2 concentrations [ppm] (``kpis.json``)."""
        return [n for k, v in self.kpi_outputs.items() if k.startswith('CO2Concentration')
                for n in v]

    # -- test periods --------------------------------------------------------------------------
    def test_period(self, name: str, warmup_days: float = WARMUP_DAYS,
                    length_days: float = LENGTH_DAYS) -> tuple[float, float, float]:
        """
        Return the times of a test period [s from 1 January].

        BOPTEST's period of day ``d``: start = (d - 7) * 86400 s, end = start + 14 days, after a
        warm-up from start - 7 days. A shortened period keeps the start and changes the warm-up
        and the length.

        Parameters
        ----------
        name : str
            A key of :attr:`days` (``peak_heat_day``, ``typical_heat_day``).
        warmup_days : float
            Warm-up before the start [days], >= 0.
        length_days : float
            Length of the test period [days], > 0.

        Returns
        -------
        tuple of float
            ``(warmup_start_s, start_s, end_s)``.

        Raises
        ------
        ValueError
            For an unknown period or bad lengths.

        """
        if name not in self.days:
            raise ValueError(f'unknown test period {name!r}: expected one of {sorted(self.days)}')
        if not warmup_days >= 0 or not length_days > 0:
            raise ValueError(f'expected warmup_days >= 0 and length_days > 0, got '
                             f'{warmup_days!r} and {length_days!r}')
        start = (self.days[name] - WARMUP_DAYS) * SECONDS_PER_DAY
        warmup_start = start - warmup_days * SECONDS_PER_DAY
        if warmup_start < 0:
            raise ValueError(f'a warm-up of {warmup_days} days before {name} starts before '
                             '1 January')
        return warmup_start, start, start + length_days * SECONDS_PER_DAY

    # -- data ----------------------------------------------------------------------------------
    @functools.cached_property
    def _resources(self) -> dict[str, pd.DataFrame]:
        return _read_resources(str(self.directory))

    @functools.cached_property
    def _column_file(self) -> dict[str, str]:
        owner: dict[str, str] = {}
        for file, frame in self._resources.items():
            for column in frame.columns:
                owner.setdefault(str(column), file)
        return owner

    @property
    def columns(self) -> list[str]:
        """Every data column of the resource files (``time`` excluded)."""
        return list(self._column_file)

    def data(self, file: str) -> pd.DataFrame:
        """
        Return one resource file as read (index: time [s from 1 January]).

        Parameters
        ----------
        file : str
            One of :data:`RESOURCE_FILES`.

        """
        if file not in RESOURCE_FILES:
            raise ValueError(f'unknown resource {file!r}: expected one of {RESOURCE_FILES}')
        return self._resources[file]

    def lookup(self, column: str, times_s: Sequence[float] | np.ndarray | float) -> np.ndarray:
        """
        Return a data column at the given times, forward-filled between rows.

        Parameters
        ----------
        column : str
            A column of one of the resource files (e.g. ``LowerSetp[1]``, ``TDryBul``,
            ``PriceElectricPowerDynamic``).
        times_s : array-like of float
            Times [s from 1 January], within the data.

        Returns
        -------
        np.ndarray
            The value of the last row at or before each time (same shape as ``times_s``).

        Raises
        ------
        ValueError
            For an unknown column or a time before the first row or after the last row plus
            one row interval.

        """
        if column not in self._column_file:
            raise ValueError(f'unknown test case data column {column!r}: expected one of '
                             f'{self.columns}')
        frame = self._resources[self._column_file[column]]
        index = frame.index.to_numpy(dtype=float)
        times = np.asarray(times_s, dtype=float)
        last = index[-1] + (index[-1] - index[-2] if index.size > 1 else 0.0)
        if times.size and (not np.all(np.isfinite(times)) or times.min() < index[0]
                           or times.max() > last):
            raise ValueError(f'times outside the data of {column!r} ([{index[0]:g}, {last:g}] s)'
                             f': got [{np.nanmin(times):g}, {np.nanmax(times):g}]')
        rows = np.clip(np.searchsorted(index, times, side='right') - 1, 0, index.size - 1)
        return frame[column].to_numpy(dtype=float)[rows]

    def forecast_values(self, column: str,
                        times_s: Sequence[float] | np.ndarray | float) -> np.ndarray:
        """
        Return a data column at the given times as BOPTEST's forecasts have it.

        Weather points (:data:`WEATHER_POINTS`) are interpolated linearly between rows, every
        other series is held (:meth:`lookup`), as BOPTEST's data manager does.

        Raises
        ------
        ValueError
            For an unknown column or times outside the data (a weather point: after its last
            row).

        """
        if column not in WEATHER_POINTS:
            return self.lookup(column, times_s)
        values = self.lookup(column, times_s)  # checks the column and the range
        frame = self._resources[self._column_file[column]]
        index = frame.index.to_numpy(dtype=float)
        times = np.asarray(times_s, dtype=float)
        if times.size and times.max() > index[-1]:
            raise ValueError(f'times outside the data of {column!r} ([{index[0]:g}, '
                             f'{index[-1]:g}] s): got [{times.min():g}, {times.max():g}]')
        return np.interp(times, index, frame[column].to_numpy(dtype=float)).reshape(values.shape)

    def lookup_frame(self, columns: Sequence[str],
                     times_s: Sequence[float] | np.ndarray) -> pd.DataFrame:
        """Return several columns at ``times_s`` (:meth:`lookup`), index = time [s]."""
        times = np.asarray(times_s, dtype=float).reshape(-1)
        return pd.DataFrame({c: self.lookup(c, times) for c in columns}, index=times)

    def price_column(self, scenario: str) -> str:
        """Return the price column [EUR/kWh] of a scenario of :data:`PRICE_SCENARIOS`."""
        if scenario not in PRICE_SCENARIOS:
            raise ValueError(f'unknown price scenario {scenario!r}: expected one of '
                             f'{list(PRICE_SCENARIOS)}')
        return PRICE_SCENARIOS[scenario]


@functools.lru_cache(maxsize=4)
def _read_resources(directory: str) -> dict[str, pd.DataFrame]:
    """Read the resource CSVs of a test case once per process (they are read-only)."""
    frames = {}
    for file in RESOURCE_FILES:
        path = pathlib.Path(directory) / 'Resources' / file
        if not path.is_file():
            raise FileNotFoundError(f'BOPTEST resource missing: {path}')
        frame = pd.read_csv(path)
        if 'time' not in frame.columns:
            raise ValueError(f'{path}: no "time" column')
        times = frame['time'].to_numpy(dtype=float)
        if times.size == 0 or np.any(np.diff(times) <= 0):
            raise ValueError(f'{path}: "time" must increase strictly')
        frames[file] = frame.set_index('time')
        frames[file].index = times
    return frames


# -- the libraries the FMU's binary needs ----------------------------------------------------
def load_shim(directory: str | os.PathLike | None = None) -> tuple[str, ...]:
    """
    Check the test case's binary in a child process, with its stand-ins; preload them here.

    The folder's ``shim/`` (one C file and a version script), if there is one, is built into
    the cache as the library the binary lacks (whichever soname that is), and loaded
    ``RTLD_GLOBAL`` (:func:`mshoot_core.fmu_binary.check_binary`; cached per binary).

    Parameters
    ----------
    directory : path, optional
        The test case folder; default :func:`default_directory`.

    Returns
    -------
    tuple of str
        The libraries preloaded for the binary.

    Raises
    ------
    mshoot_core.fmu_binary.FmuBinaryError
        A ValueError, one line: the binary lacks a library (named) or is damaged.

    """
    from mshoot_core import fmu_binary
    folder = pathlib.Path(directory) if directory is not None else default_directory()
    shim = folder / 'shim'
    libraries = [fmu_binary.Library(source=shim)] if shim.is_dir() else []
    unzipped = fmu_cache.extract_fmu(folder / 'wrapped.fmu')
    preloaded: tuple[str, ...] = ()
    for identifier in fmu_binary.model_identifiers(unzipped):
        preloaded += fmu_binary.check_binary(unzipped, identifier, libraries, label=folder.name)
    return preloaded
