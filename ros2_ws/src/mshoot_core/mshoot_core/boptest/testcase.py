"""
A BOPTEST test case folder on disk: its FMU, configuration, test periods, KPI map and data.

Stable API (other modules build on it)::

    from mshoot_core.boptest.testcase import TestCase, PRICE_SCENARIOS, load_shim
    case = TestCase.load('/path/to/test_case')   # or $MSHOOT_BOPTEST_DIR
    case.area_m2, case.control_step_s, case.fmu_path, case.days, case.kpi_outputs
    case.zones                                   # ['1'] or ['nZ', 'sZ'] (from kpis.json)
    case.energy_outputs                          # {'ElectricPower': [...], 'GasPower': [...]}
    warmup_start_s, start_s, end_s = case.test_period('peak_heat_day')
    case.test_period('peak_heat_day', warmup_days=1, length_days=2)   # shortened
    case.lookup('LowerSetp[1]', times_s) -> np.ndarray   # forward-filled
    case.lookup_frame(['TDryBul', 'HGloHor'], times_s) -> pd.DataFrame (index: time [s])
    case.band_columns('1') -> ('LowerSetp[1]', 'UpperSetp[1]')
    case.price_column('dynamic') -> 'PriceElectricPowerDynamic'
    case.price_column('dynamic', 'GasPower') -> 'PriceGasPower'
    case.emission_column('GasPower') -> 'EmissionsGasPower'
    load_shim(case.directory) -> tuple[str, ...]          # stand-ins (shim/), loaded RTLD_GLOBAL

Any folder in BOPTEST's layout: ``wrapped.fmu`` or ``models/wrapped.fmu`` (FMI 2.0, Model
Exchange or Co-Simulation), ``config.json`` (floor area, control step), ``days.json`` (test
period days), ``kpis.json`` (which outputs feed which KPI: ``OperativeZoneTemperature[z]``,
``CO2Concentration[z]``, ``ElectricPower``, ``GasPower``, ``DistrictHeatingPower``, ...) and
``Resources/*.csv`` (rows in time, a ``time`` column in seconds from 1 January, the FMU's
clock). Every series is found by its BOPTEST column name in whichever CSV holds it (the band
``LowerSetp[z]`` may be in ``dataFromModel.csv`` or in ``setpoints.csv``; the first file in
name order wins a name two files share). Between their rows these data are held constant
(forward-filled), as BOPTEST's KPI calculator does. A folder without weather (no ``TDryBul``
column, e.g. no ``weather.csv``) reads the weather derived once from its FMU's weather station
outputs, from the cache, when it has been derived (:mod:`mshoot_core.boptest.weather`).

The folder is found by :func:`default_directory`: the argument, else the environment variable
``MSHOOT_BOPTEST_DIR`` (``env.sh`` sets it to the heat pump house beside the repository).

The FMU's binary may need a library the host lacks (e.g. ``libgfortran.so.4`` or ``.so.3``,
which current Debian does not ship); the test case may carry the source of a stand-in
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
#: BOPTEST's warm-up before a test period and the period's length [days].
WARMUP_DAYS = 7.0
LENGTH_DAYS = 14.0
#: Price scenario name -> column of the electricity price [EUR/kWh] (BOPTEST's scenarios).
PRICE_SCENARIOS = {'constant': 'PriceElectricPowerConstant',
                   'dynamic': 'PriceElectricPowerDynamic',
                   'highly_dynamic': 'PriceElectricPowerHighlyDynamic'}
#: BOPTEST's energy vectors (``kpis.json`` keys, its signal exchange names), each priced by
#: ``Price<vector>`` (electricity: the scenario's column) and weighed by ``Emissions<vector>``
#: [EUR/kWh, kgCO2/kWh]; the KPI of its peak power [kW/m2] where BOPTEST reports one.
ENERGY_VECTORS = ('ElectricPower', 'DistrictHeatingPower', 'GasPower', 'BiomassPower',
                  'SolarThermalPower')
PEAK_KPIS = {'ElectricPower': 'pele_tot', 'GasPower': 'pgas_tot',
             'DistrictHeatingPower': 'pdih_tot'}
#: ``kpis.json`` keys of the zone temperatures the comfort KPI reads (``<key>[<zone>]``).
ZONE_TEMPERATURE_KEYS = ('OperativeZoneTemperature', 'AirZoneTemperature')
#: ``kpis.json`` key of the zones' CO2 concentrations (``CO2Concentration[<zone>]``).
CO2_KEY = 'CO2Concentration'
#: Where the FMU may be in the folder (BOPTEST's release layout and its parser's output).
FMU_PATHS = ('wrapped.fmu', 'models/wrapped.fmu')
SECONDS_PER_DAY = 86400.0
#: Name of the weather derived from the FMU's outputs among the resources (a folder without
#: weather.csv; :mod:`mshoot_core.boptest.weather`).
DERIVED_WEATHER = 'weather.csv (derived from the FMU)'
#: BOPTEST's weather points (the ``weather`` category of its ``data/categories.json``): its
#: forecasts interpolate them linearly between rows and hold every other series.
WEATHER_POINTS = frozenset({
    'pAtm', 'nTot', 'nOpa', 'HGloHor', 'HDifHor', 'HDirNor', 'ceiHei', 'winSpe', 'HHorIR',
    'winDir', 'cloTim', 'solTim', 'TDewPoi', 'relHum', 'TDryBul', 'TWetBul', 'solAlt', 'solZen',
    'solDec', 'solHouAng', 'lon', 'lat', 'TBlaSky'})


def default_directory() -> pathlib.Path:
    """
    Return the test case folder named by ``$MSHOOT_BOPTEST_DIR``.

    Raises
    ------
    FileNotFoundError
        When the variable is not set (``env.sh`` sets it; or pass the folder).

    """
    value = os.environ.get(DIR_ENV)
    if not value:
        raise FileNotFoundError(f'no BOPTEST test case folder: pass one, or set ${DIR_ENV} '
                                '(env.sh sets it to the heat pump house beside the repository)')
    return pathlib.Path(value).expanduser().resolve()


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
        ``'ElectricPower': [<the outputs of electric power, W>]``.
    fmu_path : pathlib.Path
        The FMU (``wrapped.fmu`` or ``models/wrapped.fmu``).

    """

    __test__ = False  # not a pytest test class

    directory: pathlib.Path
    name: str
    area_m2: float
    control_step_s: float
    days: dict[str, int]
    kpi_outputs: dict[str, list[str]]
    fmu_path: pathlib.Path

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
        fmu = find_fmu(folder)
        config = _read_json(folder / 'config.json')
        area = float(config.get('area', float('nan')))
        if not area > 0:
            raise ValueError(f'{folder / "config.json"}: expected a positive "area" [m2], got '
                             f'{config.get("area")!r}')
        days = {str(k): int(v) for k, v in _read_json(folder / 'days.json').items()}
        kpis = {str(k): [str(n) for n in v]
                for k, v in _read_json(folder / 'kpis.json').items()}
        return cls(folder, str(config.get('name', folder.name)), area,
                   float(config.get('step', 3600.0)), days, kpis, fmu)

    # -- files ---------------------------------------------------------------------------------
    @property
    def zones(self) -> list[str]:
        """Return the zones whose temperature the comfort KPI reads, in ``kpis.json``'s order."""
        return [_zone(key) for key in self.kpi_outputs
                if key.split('[')[0] in ZONE_TEMPERATURE_KEYS]

    @property
    def zone_temperature_outputs(self) -> dict[str, list[str]]:
        """Return zone -> the FMU outputs of its temperature [K] (``kpis.json``)."""
        out: dict[str, list[str]] = {}
        for key, names in self.kpi_outputs.items():
            if key.split('[')[0] in ZONE_TEMPERATURE_KEYS:
                out.setdefault(_zone(key), []).extend(names)
        return out

    @property
    def co2_outputs(self) -> dict[str, list[str]]:
        """Return zone -> the FMU outputs of its CO2 concentration [ppm] (``kpis.json``)."""
        return {_zone(key): list(names) for key, names in self.kpi_outputs.items()
                if key.split('[')[0] == CO2_KEY}

    @property
    def energy_outputs(self) -> dict[str, list[str]]:
        """Return energy vector -> the FMU outputs of its power [W], those ``kpis.json`` has."""
        return {vector: list(self.kpi_outputs[vector]) for vector in ENERGY_VECTORS
                if self.kpi_outputs.get(vector)}

    @property
    def power_outputs(self) -> list[str]:
        """Return the FMU outputs whose sum is the electric power [W] (``kpis.json``)."""
        return list(self.kpi_outputs.get('ElectricPower', []))

    @property
    def kpi_output_names(self) -> list[str]:
        """Return every FMU output ``kpis.json`` names, once, in its order."""
        return list(dict.fromkeys(n for names in self.kpi_outputs.values() for n in names))

    def band_columns(self, zone: str) -> tuple[str, str]:
        """Return the data columns of a zone's comfort band [K]: (lower, upper)."""
        return f'LowerSetp[{zone}]', f'UpperSetp[{zone}]'

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
        frames = _read_resources(str(self.directory))
        if any('TDryBul' in frame.columns for frame in frames.values()):
            return frames
        path = self.derived_weather_path  # no weather.csv: the derived one, if derived
        if not path.is_file():
            return frames
        derived = pd.read_csv(path, index_col=0)
        derived.index = derived.index.to_numpy(dtype=float)
        return {**frames, DERIVED_WEATHER: derived}

    @property
    def weather_derived(self) -> bool:
        """Return True when the folder has no weather of its own (it is derived, see below)."""
        return not any('TDryBul' in frame.columns
                       for frame in _read_resources(str(self.directory)).values())

    @property
    def derived_weather_path(self) -> pathlib.Path:
        """
        Return where the weather derived from this FMU file's outputs lives (in the cache).

        ``<cache base>/boptest/weather/<sha256 of the FMU file, 16 hex>/weather.csv``, written
        by :func:`mshoot_core.boptest.weather.ensure_weather`, never in the test case folder.
        """
        digest = fmu_cache.file_sha256(self.fmu_path)[:16]
        return fmu_cache.cache_dir().parent / 'boptest' / 'weather' / digest / 'weather.csv'

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

    @property
    def resource_files(self) -> list[str]:
        """Return the data files read (``Resources/*.csv``, in name order)."""
        return list(self._resources)

    def data(self, file: str) -> pd.DataFrame:
        """
        Return one resource file as read (index: time [s from 1 January]).

        Parameters
        ----------
        file : str
            One of :attr:`resource_files` (e.g. ``prices.csv``).

        """
        if file not in self._resources:
            raise ValueError(f'unknown resource {file!r}: expected one of '
                             f'{self.resource_files}')
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
            hint = (f' (a weather point: derive the weather of a folder without weather.csv '
                    f'once, python -m mshoot_core.boptest.weather {self.directory})'
                    if column in WEATHER_POINTS and DERIVED_WEATHER not in self._resources
                    else '')
            raise ValueError(f'unknown test case data column {column!r}: expected one of '
                             f'{self.columns}{hint}')
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

    def row_times(self, column: str) -> np.ndarray:
        """Return the row times [s from 1 January] of the file holding a data column."""
        if column not in self._column_file:
            raise ValueError(f'unknown test case data column {column!r}: expected one of '
                             f'{self.columns}')
        return self._resources[self._column_file[column]].index.to_numpy(dtype=float)

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

    def price_column(self, scenario: str, vector: str = 'ElectricPower') -> str:
        """
        Return the price column [EUR/kWh] of an energy vector under a price scenario.

        Electricity: the scenario's column (:data:`PRICE_SCENARIOS`); any other vector of
        :data:`ENERGY_VECTORS`: ``Price<vector>`` (one price for every scenario).

        Raises
        ------
        ValueError
            For an unknown scenario or vector.

        """
        if scenario not in PRICE_SCENARIOS:
            raise ValueError(f'unknown price scenario {scenario!r}: expected one of '
                             f'{list(PRICE_SCENARIOS)}')
        if vector not in ENERGY_VECTORS:
            raise ValueError(f'unknown energy vector {vector!r}: expected one of '
                             f'{list(ENERGY_VECTORS)}')
        return PRICE_SCENARIOS[scenario] if vector == 'ElectricPower' else f'Price{vector}'

    def emission_column(self, vector: str) -> str:
        """Return the emission factor column [kgCO2/kWh] of an energy vector."""
        if vector not in ENERGY_VECTORS:
            raise ValueError(f'unknown energy vector {vector!r}: expected one of '
                             f'{list(ENERGY_VECTORS)}')
        return f'Emissions{vector}'


def _zone(key: str) -> str:
    """Return the zone of a ``kpis.json`` key ``<quantity>[<zone>]``."""
    if not (key.endswith(']') and '[' in key) or not key[key.index('[') + 1:-1]:
        raise ValueError(f'kpis.json key {key!r} names no zone ("<quantity>[<zone>]")')
    return key[key.index('[') + 1:-1]


def find_fmu(folder: pathlib.Path) -> pathlib.Path:
    """
    Return the FMU of a test case folder (:data:`FMU_PATHS`).

    Raises
    ------
    FileNotFoundError
        If neither exists.

    """
    for name in FMU_PATHS:
        if (folder / name).is_file():
            return folder / name
    raise FileNotFoundError(f'BOPTEST test case without its FMU: expected one of '
                            f'{[str(folder / n) for n in FMU_PATHS]}')


@functools.lru_cache(maxsize=4)
def _read_resources(directory: str) -> dict[str, pd.DataFrame]:
    """
    Read the resource CSVs of a test case once per process (they are read-only).

    Every ``Resources/*.csv`` with a time column (``time``, or ``Time`` as some BOPTEST files
    spell it) [s from 1 January], strictly increasing.
    """
    folder = pathlib.Path(directory) / 'Resources'
    files = sorted(folder.glob('*.csv'))
    if not files:
        raise FileNotFoundError(f'BOPTEST resources missing: no CSV file in {folder}')
    frames = {}
    for path in files:
        frame = pd.read_csv(path)
        time_column = next((c for c in frame.columns if str(c).lower() == 'time'), None)
        if time_column is None:
            raise ValueError(f'{path}: no "time" column (seconds from 1 January)')
        times = frame[time_column].to_numpy(dtype=float)
        if times.size == 0 or np.any(np.diff(times) <= 0):
            raise ValueError(f'{path}: "{time_column}" must increase strictly')
        frame = frame.set_index(time_column)
        frame.index = times
        frames[path.name] = frame
    return frames


# -- the libraries the FMU's binary needs ----------------------------------------------------
def shim_libraries(directory: str | os.PathLike) -> list:
    """Return the stand-ins of a test case folder (its ``shim/``) as libraries for the FMU."""
    from mshoot_core.fmu_binary import Library
    shim = pathlib.Path(directory) / 'shim'
    return [Library(source=shim)] if shim.is_dir() else []


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
    libraries = shim_libraries(folder)
    unzipped = fmu_cache.extract_fmu(find_fmu(folder))
    preloaded: tuple[str, ...] = ()
    for identifier in fmu_binary.model_identifiers(unzipped):
        preloaded += fmu_binary.check_binary(unzipped, identifier, libraries, label=folder.name)
    return preloaded
