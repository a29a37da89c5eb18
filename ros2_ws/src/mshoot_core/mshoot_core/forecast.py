"""
Forecasts as a building gets them: BOPTEST's forecast uncertainty model and a forecast source.

BOPTEST (from v0.8.0) emulates forecast error on two weather points: the outdoor dry-bulb
temperature (``TDryBul`` [K]) and the global horizontal irradiance (``HGloHor`` [W/m2]); every
other series is forecast exactly. This module is that model, drawn with NumPy's legacy generator
exactly as BOPTEST draws it, so a forecast here is the one BOPTEST's ``PUT /forecast`` returns
for the same scenario (``temperature_uncertainty``, ``solar_uncertainty``, ``seed``):

- temperature error, AR(1) with Gaussian noise: ``e[0] ~ N(F0, K0)``,
  ``e[i+1] ~ N(F e[i] + mu, K)`` (K0, K standard deviations), :data:`TEMPERATURE_ERRORS`;
- solar error, AR(1) with Laplace noise: ``e[0] ~ Laplace(ag0, bg0)``,
  ``e[i] ~ Laplace(phi e[i-1] + ag, bg)`` (location, scale), :data:`SOLAR_ERRORS`.

A forecast at time ``now`` [s] with horizon ``H`` and interval ``dt`` [s] (:func:`hourly_grid`,
:func:`temperature_on_grid`, :func:`solar_on_grid`):

1. the hourly grid ``start = now - now mod 3600``, ``start, start + 3600, ...`` up to
   ``start + H + 3600`` (``floor(H / 3600) + 2`` points);
2. seed ``s = int(seed + now)``; the temperature errors drawn in order from
   ``RandomState(s)`` (the legacy generator ``np.random.seed(s)`` sets);
3. solar: for ``i = 0 .. 199`` the errors drawn from ``RandomState(s + i * i)``; candidate =
   truth - error on the grid; the first candidate whose points with truth > 50 W/m2 all lie in
   [0.2, 2] x truth is kept (else the last one drawn); then a 3-point moving average over the
   interior points, skipping points whose value is exactly 0; then clipped to
   [0.2, 2] x truth (night stays 0);
4. forecast = truth on the grid - temperature error, the solar result; then linear
   interpolation to ``now, now + dt, ..., now + H`` (held at the grid's last value beyond it,
   as ``np.interp`` does: only for a horizon that is not a whole number of hours);
5. errors are redrawn only when ``start`` or ``start + H`` changes (:class:`ForecastSource`
   keeps the draw): requests within one hour with the same horizon get the same errors;
6. a horizon over 48 h is refused for a point with errors.

The levels are BOPTEST's ``forecast/forecast_uncertainty_params.json``; the model is from
Zheng, Zabala, Febres, Blum and Wang (2025), J. Building Performance Simulation,
doi 10.1080/19401493.2025.2453537.

:class:`ForecastSource` serves named series of a "truth" (a callable giving a series at
times) with these errors; :meth:`ForecastSource.from_test_case` is a BOPTEST test case folder's
``Resources/*.csv``, each series by its BOPTEST column name, interpolated as BOPTEST's data
manager does (:meth:`mshoot_core.boptest.testcase.TestCase.forecast_values`). The two points
with errors are named by the caller (default BOPTEST's ``TDryBul`` and ``HGloHor``), so a source
over other series (a scenario's ``Tout`` [degC] and ``solrad``) uses the same model: a
temperature error is the same in K and degC.
:class:`~mshoot_core.scenario_forecasts.ScenarioForecasts` puts these errors on a scenario's step
forecasts (the forecaster node's): for a BOPTEST test period, the test case's points at the
step's FMU time.

Where this differs from BOPTEST v0.8.0 (on purpose): a seed of 0 is a seed (BOPTEST reads 0 as
"no seed": unreproducible draws); the draw of both points is made together, so a request that
adds a point within an hour gets the errors of that hour's first request (BOPTEST draws a
point's errors at the first request that names it, with that request's seed).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import numbers
from typing import Callable, Sequence

import numpy as np
import pandas as pd

from mshoot_core.settings import ForecastErrorSettings, UNCERTAINTY_LEVELS

logger = logging.getLogger(__name__)

#: BOPTEST's names of the two points with errors: outdoor dry-bulb temperature [K] and global
#: horizontal irradiance [W/m2].
TEMPERATURE_POINT = 'TDryBul'
SOLAR_POINT = 'HGloHor'
#: Spacing of the grid the errors are drawn on [s].
GRID_S = 3600.0
#: Longest horizon of a forecast with errors [s].
MAX_HORIZON_S = 48 * 3600.0
#: Solar candidates drawn before the last one is kept anyway.
SOLAR_TRIES = 200
#: Solar acceptance and clipping: the forecast within [low, high] x truth where the truth is
#: above :data:`SOLAR_CHECK_W_M2` [W/m2].
SOLAR_BOUNDS = (0.2, 2.0)
SOLAR_CHECK_W_M2 = 50.0
#: Largest seed NumPy's legacy generator takes.
MAX_SEED = 2 ** 32 - 1

#: A truth: ``truth(series, times_s) -> values`` (shape of ``times_s``).
Truth = Callable[[str, np.ndarray], np.ndarray]


def ar1_shocks(shocks: np.ndarray, first_loc: float, first_scale: float, coefficient: float,
               loc: float, scale: float) -> np.ndarray:
    """
    Return the AR(1) sequence of standard shocks drawn at once, as BOPTEST's scalar draws.

    ``e[0] = first_loc + first_scale z[0]``, ``e[i] = (e[i-1] coefficient + loc) + scale z[i]``:
    NumPy's legacy ``normal(m, s)`` and ``laplace(m, s)`` are ``m + s z`` of the same standard
    draw, one after the other from the generator, so this equals BOPTEST's draws of one value
    at a time, each from the last, bit for bit (``z`` from ``normal(0, 1, size)`` or
    ``laplace(0, 1, size)``), at a fraction of the calls.
    """
    error = np.empty(len(shocks))
    z = shocks.tolist()
    last = first_loc + first_scale * z[0]
    error[0] = last
    for i in range(1, len(z)):
        last = (last * coefficient + loc) + scale * z[i]
        error[i] = last
    return error


@dataclasses.dataclass(frozen=True)
class TemperatureError:
    """
    AR(1) Gaussian temperature error: ``e[0] ~ N(F0, K0)``, ``e[i+1] ~ N(F e[i] + mu, K)``.

    Attributes
    ----------
    F0, K0 : float
        Mean and standard deviation of the first error [K].
    F : float
        Autocorrelation [-].
    K : float
        Standard deviation of the innovation [K].
    mu : float
        Mean of the innovation [K].

    """

    F0: float
    K0: float
    F: float
    K: float
    mu: float

    def draw(self, random: np.random.RandomState, points: int) -> np.ndarray:
        """Return ``points`` errors [K], drawn in order from ``random`` (BOPTEST's order)."""
        return ar1_shocks(random.normal(0.0, 1.0, size=points), self.F0, self.K0, self.F,
                          self.mu, self.K)


@dataclasses.dataclass(frozen=True)
class SolarError:
    """
    AR(1) Laplace solar error: ``e[0] ~ L(ag0, bg0)``, ``e[i] ~ L(phi e[i-1] + ag, bg)``.

    Attributes
    ----------
    ag0, bg0 : float
        Location and scale of the first error [W/m2].
    phi : float
        Autocorrelation [-].
    ag, bg : float
        Location and scale of the innovation [W/m2].

    """

    ag0: float
    bg0: float
    phi: float
    ag: float
    bg: float

    def draw(self, random: np.random.RandomState, points: int) -> np.ndarray:
        """Return ``points`` errors [W/m2], drawn in order from ``random`` (BOPTEST's order)."""
        return ar1_shocks(random.laplace(0.0, 1.0, size=points), self.ag0, self.bg0, self.phi,
                          self.ag, self.bg)


#: BOPTEST's temperature error levels (``none``: no error).
TEMPERATURE_ERRORS: dict[str, TemperatureError] = {
    'low': TemperatureError(F0=0.0, K0=0.6, F=0.92, K=0.4, mu=0.0),
    'medium': TemperatureError(F0=0.15, K0=1.2, F=0.93, K=0.6, mu=0.0),
    'high': TemperatureError(F0=-0.58, K0=1.5, F=0.95, K=0.7, mu=-0.015),
}
#: BOPTEST's solar error levels (``none``: no error).
SOLAR_ERRORS: dict[str, SolarError] = {
    'low': SolarError(ag0=4.44, bg0=57.42, phi=0.62, ag=1.86, bg=45.64),
    'medium': SolarError(ag0=15.02, bg0=122.6, phi=0.63, ag=4.44, bg=91.97),
    'high': SolarError(ag0=32.09, bg0=119.94, phi=0.67, ag=10.63, bg=87.44),
}
assert set(TEMPERATURE_ERRORS) == set(SOLAR_ERRORS) == set(UNCERTAINTY_LEVELS) - {'none'}


def hourly_grid(now_s: float, horizon_s: float) -> np.ndarray:
    """
    Return the grid the errors are drawn on [s]: ``floor(H / 3600) + 2`` whole hours.

    From the hour that holds ``now_s`` (``now - now mod 3600``) to ``start + H + 3600``.
    """
    start = now_s - now_s % GRID_S
    return start + GRID_S * np.arange(math.floor(horizon_s / GRID_S) + 2)


def draw_seed(seed: int, now_s: float) -> int:
    """
    Return BOPTEST's seed of a draw at ``now_s``: ``int(seed + now)``.

    Raises
    ------
    ValueError
        If the draws' seeds (up to ``s + 199**2``) leave NumPy's range [0, 2**32 - 1].

    """
    s = int(seed + now_s)
    if s < 0 or s + (SOLAR_TRIES - 1) ** 2 > MAX_SEED:
        raise ValueError(f'expected seed + time in [0, {MAX_SEED - (SOLAR_TRIES - 1) ** 2}], '
                         f'got {seed} + {now_s:g} s')
    return s


def temperature_on_grid(truth: np.ndarray, level: str, seed: int) -> np.ndarray:
    """
    Return the temperature forecast on the grid: ``truth - error`` [K or degC].

    Parameters
    ----------
    truth : np.ndarray
        The true temperature at the grid's points (:func:`hourly_grid`).
    level : str
        One of :data:`~mshoot_core.settings.UNCERTAINTY_LEVELS`.
    seed : int
        The draw's seed (:func:`draw_seed`).

    """
    truth = np.asarray(truth, dtype=float)
    if _level(level, 'temperature') == 'none':
        return truth.copy()
    return truth - TEMPERATURE_ERRORS[level].draw(np.random.RandomState(seed), truth.size)


def solar_on_grid(truth: np.ndarray, level: str, seed: int) -> np.ndarray:
    """
    Return the solar forecast on the grid [W/m2]: accepted, smoothed and clipped (module doc).

    Parameters
    ----------
    truth : np.ndarray
        The true irradiance at the grid's points (:func:`hourly_grid`) [W/m2].
    level : str
        One of :data:`~mshoot_core.settings.UNCERTAINTY_LEVELS`.
    seed : int
        The draw's seed (:func:`draw_seed`); candidate ``i`` is drawn with ``seed + i * i``.

    """
    truth = np.asarray(truth, dtype=float)
    if _level(level, 'solar') == 'none':
        return truth.copy()
    model = SOLAR_ERRORS[level]
    low, high = SOLAR_BOUNDS[0] * truth, SOLAR_BOUNDS[1] * truth
    checked = truth > SOLAR_CHECK_W_M2
    truth_checked, low_checked, high_checked = truth[checked], low[checked], high[checked]
    random = np.random.RandomState()  # re-seeded: the generator RandomState(s) is, cheaper
    for i in range(SOLAR_TRIES):
        random.seed(seed + i * i)
        error = model.draw(random, truth.size)
        candidate = truth - error
        inside = truth_checked - error[checked]
        if not ((inside > high_checked).any() or (inside < low_checked).any()):
            break
    else:
        logger.debug('no solar candidate of %d within bounds (seed %d): the last one kept',
                     SOLAR_TRIES, seed)
    return np.clip(moving_average(candidate), low, high)


def moving_average(values: np.ndarray) -> np.ndarray:
    """
    Return the 3-point moving average of the interior points (BOPTEST's ``mean_filter``).

    The ends are kept, and so is every point whose value is exactly 0; the averages are of the
    values given (not of those already averaged).
    """
    values = np.asarray(values, dtype=float)
    out = values.copy()
    for i in range(1, values.size - 1):
        if values[i] != 0:
            out[i] = sum(values[i - 1:i + 2]) / 3  # sum(): BOPTEST's rounding, to the last bit
    return out


def forecast_times(now_s: float, horizon_s: float, interval_s: float) -> np.ndarray:
    """Return the forecast's times ``now, now + dt, ... <= now + H`` [s] (BOPTEST's)."""
    return np.arange(now_s, now_s + horizon_s + 0.1, interval_s)


def horizon_problem(levels: Sequence[str], horizon_s: float) -> str | None:
    """
    Return why ``horizon_s`` [s] is too long for points with error ``levels``, or None.

    BOPTEST refuses a horizon over 48 h (:data:`MAX_HORIZON_S`) for a point with errors.
    """
    uncertain = sorted({level for level in levels if level != 'none'})
    if uncertain and horizon_s > MAX_HORIZON_S:
        return (f'expected a horizon <= {MAX_HORIZON_S:.0f} s (48 h) with forecast '
                f'uncertainty {uncertain}, got {horizon_s:g} s')
    return None


def _level(level: str, what: str) -> str:
    if level not in UNCERTAINTY_LEVELS:
        raise ValueError(f'{what} uncertainty must be one of {list(UNCERTAINTY_LEVELS)}, '
                         f'got {level!r}')
    return level


@dataclasses.dataclass(frozen=True)
class _Draw:
    """One draw on the grid of ``start`` and ``stop``: the two points' forecasts there."""

    start_s: float
    stop_s: float
    grid_s: np.ndarray
    temperature: np.ndarray | None
    solar: np.ndarray | None


class ForecastSource:
    """
    Forecasts of named series with BOPTEST's errors (module docstring), at any time.

    Parameters
    ----------
    truth : callable
        ``truth(series, times_s) -> values``: the true series at the times [s]; raises
        ValueError for an unknown series or times outside its data.
    series : sequence of str
        The series it serves.
    errors : ForecastErrorSettings, optional
        Uncertainty levels and seed (default: none, perfect forecasts).
    temperature_point, solar_point : str
        The series the temperature and the solar errors apply to.

    Notes
    -----
    The source keeps its last draw (BOPTEST's forecaster does): a request redraws only when the
    hour of ``now`` or ``start + H`` differs from the draw's. A fresh source gives what a fresh
    BOPTEST request gets.

    """

    def __init__(self, truth: Truth, series: Sequence[str],
                 errors: ForecastErrorSettings | None = None,
                 temperature_point: str = TEMPERATURE_POINT,
                 solar_point: str = SOLAR_POINT) -> None:
        self.truth = truth
        self.series = tuple(series)
        self.errors = errors if errors is not None else ForecastErrorSettings()
        if not isinstance(self.errors, ForecastErrorSettings):
            raise TypeError(f'errors must be ForecastErrorSettings, got '
                            f'{type(self.errors).__name__}')
        self.temperature_point = temperature_point
        self.solar_point = solar_point
        self._draw: _Draw | None = None
        self.draws = 0

    @classmethod
    def from_test_case(cls, case: object, errors: ForecastErrorSettings | None = None,
                       temperature_point: str = TEMPERATURE_POINT,
                       solar_point: str = SOLAR_POINT) -> ForecastSource:
        """
        Return the source of a BOPTEST test case folder's series (BOPTEST's column names).

        Parameters
        ----------
        case : mshoot_core.boptest.testcase.TestCase
            The test case; its times are seconds from 1 January.
        errors : ForecastErrorSettings, optional
            Uncertainty levels and seed.
        temperature_point, solar_point : str
            The columns with errors (default BOPTEST's).

        """
        return cls(case.forecast_values, case.columns, errors, temperature_point, solar_point)

    @property
    def uncertain_points(self) -> dict[str, str]:
        """Return the served series with errors, by name, with their level (none left out)."""
        levels = {self.temperature_point: self.errors.temperature_uncertainty,
                  self.solar_point: self.errors.solar_uncertainty}
        return {name: level for name, level in levels.items()
                if level != 'none' and name in self.series}

    def forecast(self, now_s: float, horizon_s: float, interval_s: float,
                 points: Sequence[str] | None = None) -> pd.DataFrame:
        """
        Return the forecast a request at ``now_s`` gets (BOPTEST's ``PUT /forecast``).

        Parameters
        ----------
        now_s : float
            Time of the request [s] (a test case's: from 1 January), >= 0.
        horizon_s : float
            Horizon [s], >= 0 (<= 48 h for a point with errors).
        interval_s : float
            Interval between the forecast's times [s], > 0.
        points : sequence of str, optional
            The series (default: every one, in :attr:`series` order).

        Returns
        -------
        pd.DataFrame
            Columns ``time`` [s] and one per point, in the truth's units; rows
            ``now, now + dt, ..., <= now + H``.

        Raises
        ------
        ValueError
            For an unknown point, a bad time, horizon or interval, or times outside the data.

        """
        names = list(self.series if points is None else points)
        self._check(now_s, horizon_s, interval_s, names)
        times = forecast_times(float(now_s), float(horizon_s), float(interval_s))
        columns: dict[str, np.ndarray] = {'time': times}
        uncertain = self.uncertain_points
        draw = self._current_draw(float(now_s), float(horizon_s)) \
            if any(n in uncertain for n in names) else None
        for name in names:
            if draw is not None and name == self.temperature_point and name in uncertain:
                columns[name] = np.interp(times, draw.grid_s, draw.temperature)
            elif draw is not None and name == self.solar_point and name in uncertain:
                columns[name] = np.interp(times, draw.grid_s, draw.solar)
            else:
                columns[name] = np.asarray(self.truth(name, times), dtype=float)
        return pd.DataFrame(columns)

    def at(self, point: str, now_s: float, horizon_s: float,
           times_s: np.ndarray | Sequence[float]) -> np.ndarray:
        """
        Return one point of the forecast of a request (``now_s``, ``horizon_s``) at any times.

        The same values :meth:`forecast` gives on its times (the same draw), at ``times_s``
        [s] within [now, now + H]: a point with errors linear between the draw's hourly points,
        any other the truth.

        Raises
        ------
        ValueError
            As :meth:`forecast`, or for times outside [now, now + H].

        """
        self._check(now_s, horizon_s, 1.0, [point])
        times = np.asarray(times_s, dtype=float)
        if times.size and (times.min() < now_s or times.max() > now_s + horizon_s):
            raise ValueError(f'expected times within the request [{now_s:g}, '
                             f'{now_s + horizon_s:g}] s, got [{times.min():g}, '
                             f'{times.max():g}] s')
        if point not in self.uncertain_points:
            return np.asarray(self.truth(point, times), dtype=float)
        draw = self._current_draw(float(now_s), float(horizon_s))
        grid = draw.temperature if point == self.temperature_point else draw.solar
        return np.interp(times, draw.grid_s, grid)

    def _check(self, now_s: float, horizon_s: float, interval_s: float,
               names: list[str]) -> None:
        unknown = [n for n in names if n not in self.series]
        if unknown or not names or len(set(names)) != len(names):
            raise ValueError(f'expected distinct forecast points among {list(self.series)}, got '
                             f'{names}')
        for label, value in (('time', now_s), ('horizon', horizon_s),
                             ('interval', interval_s)):
            if not isinstance(value, numbers.Real) or isinstance(value, bool) \
                    or not math.isfinite(value):
                raise ValueError(f'expected a finite {label} [s], got {value!r}')
        if now_s < 0 or horizon_s < 0 or interval_s <= 0:
            raise ValueError(f'expected time >= 0, horizon >= 0 and interval > 0 [s], got '
                             f'{now_s:g}, {horizon_s:g} and {interval_s:g}')
        levels = self.uncertain_points
        problem = horizon_problem([levels[n] for n in names if n in levels], horizon_s)
        if problem:
            raise ValueError(f'{problem} (points {[n for n in names if n in levels]})')

    def _current_draw(self, now_s: float, horizon_s: float) -> _Draw:
        """Return the draw of this request: the kept one while start and start + H hold."""
        start = now_s - now_s % GRID_S
        stop = start + horizon_s
        kept = self._draw
        if kept is not None and kept.start_s == start and kept.stop_s == stop:
            return kept
        grid = hourly_grid(now_s, horizon_s)
        seed = draw_seed(self.errors.seed, now_s)
        levels = self.uncertain_points
        temperature = solar = None
        if self.temperature_point in levels:
            temperature = temperature_on_grid(self.truth(self.temperature_point, grid),
                                              levels[self.temperature_point], seed)
        if self.solar_point in levels:
            solar = solar_on_grid(self.truth(self.solar_point, grid), levels[self.solar_point],
                                  seed)
        self._draw = _Draw(start, stop, grid, temperature, solar)
        self.draws += 1
        logger.debug('forecast errors drawn at %g s (seed %d) for [%g, %g] s', now_s, seed,
                     grid[0], grid[-1])
        return self._draw


def truth_of_frame(frame: pd.DataFrame, clock: np.ndarray | None = None) -> Truth:
    """
    Return a truth over the columns of ``frame``: linear in time, held beyond its ends.

    Held beyond the last row as :func:`mshoot_core.scenario.forecast_window` repeats it.

    Parameters
    ----------
    frame : pd.DataFrame
        Columns of series; index: time [s] unless ``clock`` is given.
    clock : np.ndarray, optional
        The time of each row [s] (e.g. a scenario's ``fmu_time_s``).

    """
    times = np.asarray(frame.index if clock is None else clock, dtype=float)

    def truth(series: str, at_s: np.ndarray) -> np.ndarray:
        if series not in frame.columns:
            raise ValueError(f'unknown series {series!r}: expected one of {list(frame.columns)}')
        return np.interp(np.asarray(at_s, dtype=float), times,
                         frame[series].to_numpy(dtype=float))
    return truth


#: The forecast scenarios of a benchmark's MPC runs by default: perfect forecasts, BOPTEST's
#: ``high`` level (temperature and solar) with three seeds, ``low`` and ``medium`` with one
#: (:func:`uncertainty_runs`).
BENCHMARK_UNCERTAINTY = ('none', 'high=1,2,3', 'low=1', 'medium=1')


def uncertainty_runs(specs: Sequence[str]) -> list[ForecastErrorSettings]:
    """
    Return the forecast scenarios of ``specs``: ``LEVEL`` or ``LEVEL=SEED,SEED,...`` each.

    The level applies to both points (temperature and solar), as in the benchmark's scenarios;
    ``LEVEL`` alone is seed 1 (``none``: perfect, seed 0). Duplicates are dropped.

    Raises
    ------
    ValueError
        For an unknown level, a seed that is not a whole number in range, or no scenario.

    """
    runs: list[ForecastErrorSettings] = []
    for spec in specs:
        level, _, seeds = str(spec).partition('=')
        level = _level(level.strip(), 'forecast')
        if level == 'none':
            values = [0]
        else:
            try:
                values = [int(s) for s in seeds.split(',')] if seeds.strip() else [1]
            except ValueError as exc:
                raise ValueError(f'expected LEVEL or LEVEL=SEED,SEED,... (whole seeds), got '
                                 f'{spec!r}') from exc
        for seed in values:
            errors = ForecastErrorSettings(temperature_uncertainty=level,
                                           solar_uncertainty=level, seed=seed)
            if errors not in runs:
                runs.append(errors)
    if not runs:
        raise ValueError('expected at least one forecast scenario (e.g. none, high=1,2,3)')
    return runs


def scenario_fields(errors: ForecastErrorSettings | None) -> dict[str, object]:
    """
    Return a run record's forecast fields: ``uncertainty`` (the level) and ``seed``.

    None (a controller that reads no weather forecast): level ``none``, seed None; perfect
    forecasts: seed None too (no draw).
    """
    if errors is None or (errors.temperature_uncertainty == errors.solar_uncertainty == 'none'):
        return {'uncertainty': 'none', 'seed': None}
    levels = {errors.temperature_uncertainty, errors.solar_uncertainty}
    level = levels.pop() if len(levels) == 1 else (
        f'temperature {errors.temperature_uncertainty}, solar {errors.solar_uncertainty}')
    return {'uncertainty': level, 'seed': int(errors.seed)}


def scenario_suffix(errors: ForecastErrorSettings | None) -> str:
    """Return a run name's suffix of its forecast scenario: '' (perfect) or ``_high_s1``."""
    fields = scenario_fields(errors)
    if fields['seed'] is None:
        return ''
    return f'_{str(fields["uncertainty"]).replace(", ", "_").replace(" ", "-")}_s{fields["seed"]}'
