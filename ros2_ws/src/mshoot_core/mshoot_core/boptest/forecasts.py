"""
A control model's forecast from a BOPTEST test case folder: interval means, bands and prices.

Stable API::

    from mshoot_core.boptest.forecasts import TestCaseForecasts, ForecastSpec
    spec = ForecastSpec.from_card('path/or/card.yaml')    # the card's testcase_forecast section
    source = TestCaseForecasts(case, spec, price='dynamic', errors=ForecastErrorSettings(...))
    frame = source.frame(t_s, steps=36, step_s=3600.0)  # index time_s [s from 1 January]
    source.columns                                       # ('Tout', ..., 'comfort_min', ...)

Which test case columns feed which series of the control model is data: the control card's
``testcase_forecast`` section (the card names the disturbances its model needs; the section says
where each comes from in a test case folder)::

    testcase_forecast:
      series:
        Tout: {columns: [TDryBul], offset: -273.15}            # sum of columns + offset
        occupied: {columns: ['LowerSetp[1]'], lead_s: 3600}    # an hour ahead of the column
        pumps: {columns: [...], lead_s: 3600, rest_s: 129600, rest_lead_s: 10800}  # see below
        gains: {columns: ['InternalGainsCon[1]', 'InternalGainsRad[1]']}
        price: {price: {constant: PriceElectricPowerConstant, dynamic: ...}}  # per scenario
      bands:
        '1': {lower: 'LowerSetp[1]', upper: 'UpperSetp[1]'}    # offset -273.15 by default
      data_step_s: 900                                         # optional

Row k of :meth:`TestCaseForecasts.frame` (time ``t_s + k step_s``, k = 0..steps) holds

- every series: its interval mean over [t_k, t_k + step_s): the mean of the series at the
  midpoints of the interval's ``n = round(step_s / data_step_s)`` sub-intervals, each column
  forward-filled between its rows (:meth:`TestCase.lookup`), exact on the data's grid; a sum of
  columns is the sum of their means, plus the offset; a price series is the column its card entry
  names for the price scenario; a series with a lead (``lead_s``) runs that much ahead of its
  columns, and with ``rest_s`` and ``rest_lead_s`` it runs ``rest_lead_s`` ahead in the rows whose
  interval [t_k + lead_s, t_k + rest_lead_s + step_s) holds a rise of the series (above 0, after
  the offset, on the data's grid) after at least ``rest_s`` at or below 0: a building's schedule
  that starts earlier after a weekend;
- the comfort band of each zone [degC with the default offset] over the interval ending at the
  row, (t_{k-1}, t_k] on the data's grid (row 0: t_0 alone): the highest lower edge and the
  lowest upper edge (the tightest band), the upper edge never below the lower one
  (:func:`interval_band`, also the band of a test period's scenario). The first zone
  of ``bands`` is ``comfort_min``/``comfort_max`` (the MPC's band); with several zones every zone
  is also ``comfort_min_<zone>``/``comfort_max_<zone>``.

With forecast errors (:class:`~mshoot_core.settings.ForecastErrorSettings`), the test case's
temperature and solar points (BOPTEST's ``TDryBul`` and ``HGloHor``,
:mod:`mshoot_core.forecast`) are replaced by the forecast a request at ``t_s`` with the
horizon ``(steps + 1) step_s`` gets (BOPTEST's errors on its hourly grid, linear between its
points) before the interval means are taken; every other column stays exact. The band is the
raw data: margins are the controller's (setting ``band_margin_k``).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import pathlib
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core.boptest.testcase import TestCase
from mshoot_core.forecast import ForecastSource
from mshoot_core.safety import COMFORT_SERIES, zone_band_series
from mshoot_core.settings import ForecastErrorSettings
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)

#: The card section of a control model's test case forecast.
SECTION = 'testcase_forecast'


@dataclasses.dataclass(frozen=True)
class SeriesSource:
    """
    Where one series of the forecast comes from in a test case's data.

    Attributes
    ----------
    columns : tuple of str
        Columns whose interval means are summed (empty for a price series).
    offset : float
        Added to the sum (e.g. -273.15 for K to degC).
    prices : dict of str -> str
        For a price series: price scenario -> its column [EUR/kWh] (else empty).
    lead_s : float
        The series runs this much ahead of its columns [s]: row k holds the columns' means
        over [t_k + lead_s, t_k + step + lead_s) (e.g. a building's schedule that starts an
        hour before the band it is derived from: 3600).
    rest_s, rest_lead_s : float
        The lead before a rise of the series (above 0) that follows at least ``rest_s`` at or
        below 0 [s], instead of ``lead_s`` (0, 0: none; e.g. a schedule that starts 3 h before
        the band after a weekend: 129600, 10800).

    """

    columns: tuple[str, ...] = ()
    offset: float = 0.0
    prices: Mapping[str, str] = dataclasses.field(default_factory=dict)
    lead_s: float = 0.0
    rest_s: float = 0.0
    rest_lead_s: float = 0.0

    def columns_for(self, price: str, name: str, where: str) -> tuple[str, ...]:
        """Return the columns of the series under a price scenario (ValueError if none)."""
        if not self.prices:
            return self.columns
        if price not in self.prices:
            raise ValueError(f'{where}: series {name!r} has no price column for the price '
                             f'scenario {price!r}: expected one of {sorted(self.prices)}')
        return (self.prices[price],)


@dataclasses.dataclass(frozen=True)
class BandSource:
    """The columns of one zone's comfort band edges and the offset added to both."""

    lower: str
    upper: str
    offset: float = -KELVIN


@dataclasses.dataclass(frozen=True)
class ForecastSpec:
    """
    The card section ``testcase_forecast`` (module docstring), parsed.

    Attributes
    ----------
    series : dict of str -> SeriesSource
        Series name -> its source, in the card's order (the frame's column order).
    bands : dict of str -> BandSource
        Zone -> its band's columns, in the card's order.
    data_step_s : float or None
        Sampling step of the interval means [s] (None: the data's smallest row spacing).
    where : str
        Where the section was read (for messages).

    """

    series: Mapping[str, SeriesSource]
    bands: Mapping[str, BandSource] = dataclasses.field(default_factory=dict)
    data_step_s: float | None = None
    where: str = SECTION

    @classmethod
    def from_section(cls, section: Mapping[str, Any], where: str = SECTION) -> ForecastSpec:
        """
        Parse a ``testcase_forecast`` section (as validated by the card schema).

        Raises
        ------
        ValueError
            For a section without series, or entries of the wrong shape.

        """
        if not isinstance(section, Mapping) or not isinstance(section.get('series'), Mapping) \
                or not section['series']:
            raise ValueError(f'{where}: expected a mapping with a non-empty "series", got '
                             f'{section!r}')
        series = {}
        for name, entry in section['series'].items():
            if isinstance(entry, Mapping) and isinstance(entry.get('price'), Mapping):
                series[str(name)] = SeriesSource(prices={str(k): str(v) for k, v
                                                         in entry['price'].items()})
            elif isinstance(entry, Mapping) and entry.get('columns'):
                source = SeriesSource(tuple(str(c) for c in entry['columns']),
                                      float(entry.get('offset', 0.0)),
                                      lead_s=float(entry.get('lead_s', 0.0)),
                                      rest_s=float(entry.get('rest_s', 0.0)),
                                      rest_lead_s=float(entry.get('rest_lead_s', 0.0)))
                if ('rest_s' in entry) != ('rest_lead_s' in entry) or (
                        'rest_s' in entry and not (source.rest_s > 0
                                                   and source.rest_lead_s >= source.lead_s)):
                    raise ValueError(f'{where}: series {name!r}: rest_s and rest_lead_s go '
                                     f'together, with rest_s > 0 and rest_lead_s >= lead_s '
                                     f'({source.lead_s:g}), got {entry!r}')
                series[str(name)] = source
            else:
                raise ValueError(f'{where}: series {name!r} must be {{columns: [...], '
                                 f'offset: x}} or {{price: {{scenario: column}}}}, got {entry!r}')
        bands = {}
        for zone, entry in (section.get('bands') or {}).items():
            if not (isinstance(entry, Mapping) and entry.get('lower') and entry.get('upper')):
                raise ValueError(f'{where}: band of zone {zone!r} must be {{lower: column, '
                                 f'upper: column}}, got {entry!r}')
            bands[str(zone)] = BandSource(str(entry['lower']), str(entry['upper']),
                                          float(entry.get('offset', -KELVIN)))
        step = section.get('data_step_s')
        if step is not None and not (math.isfinite(float(step)) and float(step) > 0):
            raise ValueError(f'{where}: data_step_s must be > 0 s, got {step!r}')
        return cls(series, bands, None if step is None else float(step), where)

    @classmethod
    def from_card(cls, card: Any) -> ForecastSpec:
        """
        Return the spec of a control model card (a loaded card, a path or a built-in name).

        Raises
        ------
        ValueError
            For a card without a ``testcase_forecast`` section.

        """
        from mshoot_core.models import card as cards
        if isinstance(card, (str, pathlib.Path)):
            path = pathlib.Path(card)
            card = cards.load_card(path if path.suffix in ('.yaml', '.yml')
                                   else cards.builtin_card(str(card)))
        section = getattr(card, 'testcase_forecast', None)
        if section is None:
            raise ValueError(f'card {card.path} has no {SECTION!r} section: it does not say '
                             'where its forecast comes from in a test case folder')
        return cls.from_section(section, f'{card.path}: {SECTION}')

    def band_columns(self) -> tuple[str, ...]:
        """Return the band columns of the frame: the first zone's, then per zone if several."""
        if not self.bands:
            return ()
        per_zone = [c for zone in self.bands for c in zone_band_series(zone)] \
            if len(self.bands) > 1 else []
        return (*COMFORT_SERIES, *per_zone)


class TestCaseForecasts:
    """
    The forecasts of a control model from a test case folder (module docstring).

    Parameters
    ----------
    case : TestCase
        The test case.
    spec : ForecastSpec
        Which columns feed which series (the control card's section).
    price : str
        The price scenario (a key of each price series' columns).
    errors : ForecastErrorSettings, optional
        BOPTEST's forecast errors on the temperature and solar points (default: none).

    Raises
    ------
    ValueError
        For a column the test case does not have (named with the folder and the files
        searched), or a price scenario without a column.

    """

    __test__ = False  # not a pytest class (its name starts with "Test")

    def __init__(self, case: TestCase, spec: ForecastSpec, price: str = 'constant',
                 errors: ForecastErrorSettings | None = None) -> None:
        self.case = case
        self.spec = spec
        self.price = str(price)
        self.errors = errors if errors is not None else ForecastErrorSettings()
        self._columns = {name: source.columns_for(self.price, name, spec.where)
                         for name, source in spec.series.items()}
        used = [c for columns in self._columns.values() for c in columns]
        used += [c for band in spec.bands.values() for c in (band.lower, band.upper)]
        self._check_columns(used)
        self.data_step_s = spec.data_step_s if spec.data_step_s is not None else min(
            float(np.min(np.diff(case.row_times(c)))) for c in dict.fromkeys(used))
        #: The test case's forecasts with errors (keeps its draw, as BOPTEST's forecaster).
        self.source = ForecastSource.from_test_case(case, self.errors)
        self._uncertain = self.source.uncertain_points

    def _check_columns(self, columns: Sequence[str]) -> None:
        missing = [c for c in dict.fromkeys(columns) if c not in self.case.columns]
        if missing:
            files = [str(self.case.directory / 'Resources' / f) for f in self.case.resource_files]
            raise ValueError(
                f'{self.spec.where}: the test case {self.case.directory} lacks the column'
                f'{"s" if len(missing) > 1 else ""} {missing}; searched {files}')

    @property
    def columns(self) -> tuple[str, ...]:
        """Return the frame's columns: the series in the card's order, then the bands."""
        return (*self.spec.series, *self.spec.band_columns())

    def _sub_steps(self, step_s: float) -> int:
        return max(1, int(round(step_s / self.data_step_s)))

    def interval_means(self, column: str, t_s: np.ndarray, step_s: float,
                       now_s: float | None = None, horizon_s: float = 0.0) -> np.ndarray:
        """
        Return the mean of a column over [t, t + step_s) for every t (module docstring).

        Parameters
        ----------
        column : str
            A test case column.
        t_s : np.ndarray
            Interval starts [s from 1 January].
        step_s : float
            Interval length [s].
        now_s, horizon_s : float, optional
            The forecast request (time, horizon [s]) whose errors a temperature or solar
            point gets; None: the data, exact.

        """
        t_s = np.asarray(t_s, dtype=float).reshape(-1)
        n_sub = self._sub_steps(step_s)
        offsets = (np.arange(n_sub) + 0.5) * step_s / n_sub
        times = (t_s[:, None] + offsets[None, :]).reshape(-1)
        if now_s is not None and column in self._uncertain:
            values = self.source.at(column, now_s, horizon_s, times)
        else:
            values = self.case.lookup(column, times)
        return values.reshape(t_s.size, n_sub).mean(axis=1)

    def series_at(self, name: str, times_s: np.ndarray, step_s: float) -> np.ndarray:
        """
        Return a series at the given times, exact: its columns at each time plus its lead.

        Parameters
        ----------
        name : str
            A series of the spec.
        times_s : np.ndarray
            Times [s from 1 January], e.g. a plant's records'.
        step_s : float
            Spacing of the times [s]: each time leads as the row of an interval of this length
            (``rest_s``, ``rest_lead_s``).

        Returns
        -------
        np.ndarray
            The sum of the columns at ``t + lead`` (forward-filled), plus the offset.

        """
        times = np.asarray(times_s, dtype=float).reshape(-1)
        at = self._lead_times(name, times, step_s)
        return sum(self.case.lookup(c, at) for c in self._columns[name]) + \
            self.spec.series[name].offset

    def _lead_times(self, name: str, times: np.ndarray, step_s: float) -> np.ndarray:
        """Return each row's time plus the series' lead (``lead_s`` or ``rest_lead_s``)."""
        source = self.spec.series[name]
        at = times + source.lead_s
        if source.rest_s > 0:
            at = np.where(self._after_rest(name, times, step_s), times + source.rest_lead_s, at)
        return at

    def _after_rest(self, name: str, times: np.ndarray, step_s: float) -> np.ndarray:
        """
        Return the rows that lead by ``rest_lead_s`` (:class:`SeriesSource`).

        Their interval [t_k + lead_s, t_k + rest_lead_s + step_s) holds a rise after
        ``rest_s`` at rest.
        """
        source, grid_s = self.spec.series[name], self.data_step_s
        first = max(0.0, float(times[0]) + source.lead_s - source.rest_s - grid_s)
        count = int(math.ceil((float(times[-1]) + source.rest_lead_s + step_s - first)
                              / grid_s)) + 1
        grid = first + grid_s * np.arange(count)
        values = sum(self.case.lookup(c, grid) for c in self._columns[name]) + source.offset
        rises = grid[rises_after_rest(values, int(math.ceil(source.rest_s / grid_s)))]
        begin, end = times + source.lead_s, times + source.rest_lead_s + step_s
        return np.searchsorted(rises, begin) < np.searchsorted(rises, end)  # one in [begin, end)

    def frame(self, t_s: float, steps: int, step_s: float) -> pd.DataFrame:
        """
        Return the forecast of ``steps`` intervals of ``step_s`` [s] from ``t_s`` (N+1 rows).

        Raises
        ------
        ValueError
            For bad arguments, times outside the data, or a horizon ``(steps + 1) step_s``
            over 48 h with errors.

        """
        steps, step_s = int(steps), float(step_s)
        if steps < 0 or not (math.isfinite(step_s) and step_s > 0):
            raise ValueError(f'expected steps >= 0 and step_s > 0 s, got {steps} and {step_s}')
        times = float(t_s) + np.arange(steps + 1) * step_s
        frame = pd.DataFrame(index=pd.Index(times, name='time_s'))
        horizon = (steps + 1) * step_s
        for name, columns in self._columns.items():
            at = self._lead_times(name, times, step_s)
            total = self.interval_means(columns[0], at, step_s, float(t_s), horizon)
            for column in columns[1:]:
                total = total + self.interval_means(column, at, step_s, float(t_s), horizon)
            offset = self.spec.series[name].offset
            frame[name] = total + offset if offset else total
        several = len(self.spec.bands) > 1
        for i, (zone, band) in enumerate(self.spec.bands.items()):
            lo, hi = interval_band(self.case, band, times, step_s, self.data_step_s)
            if i == 0:
                frame[COMFORT_SERIES[0]], frame[COMFORT_SERIES[1]] = lo, hi
            if several:
                frame[zone_band_series(zone)[0]], frame[zone_band_series(zone)[1]] = lo, hi
        return frame


def rises_after_rest(values: np.ndarray, rest_rows: int) -> np.ndarray:
    """Return where a series rises above 0 after at least ``rest_rows`` rows at or below 0."""
    active = np.asarray(values) > 0
    idle = np.concatenate([[0], np.cumsum(~active)])  # rows at rest before each row
    rows = np.arange(active.size)
    return active & (rows >= rest_rows) & (idle[rows] - idle[np.maximum(rows - rest_rows, 0)]
                                           == rest_rows)


def interval_band(case: TestCase, band: BandSource, times_s: np.ndarray, step_s: float,
                  data_step_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the comfort band of each row over the interval ending there: (lower, upper).

    The one definition of a test case's band over a control interval (the forecast's and the
    scenario's, :func:`~mshoot_core.boptest.period_scenario.period_scenario`): at row time
    t_k, the highest lower edge and the lowest upper edge (the tightest band) over
    (t_k - step_s, t_k] sampled on the data's grid (row 0: t_0 alone), the upper edge never
    below the lower one, each plus the band's offset.

    Parameters
    ----------
    case : TestCase
        The test case.
    band : BandSource
        The band's columns and offset.
    times_s : np.ndarray
        Row times [s from 1 January], increasing.
    step_s : float
        Interval length [s].
    data_step_s : float, optional
        Sampling step [s] (default: the smaller row spacing of the two columns).

    """
    times = np.asarray(times_s, dtype=float).reshape(-1)
    if data_step_s is None:
        data_step_s = min(float(np.min(np.diff(case.row_times(c))))
                          for c in (band.lower, band.upper))
    n_sub = max(1, int(round(step_s / data_step_s)))
    ends = (times[:, None] - np.arange(n_sub)[None, :] * step_s / n_sub).reshape(-1)
    ends = np.maximum(ends, times[0])  # (t_k-1, t_k] on the data's grid, end included
    lower = case.lookup(band.lower, ends).reshape(-1, n_sub)
    upper = case.lookup(band.upper, ends).reshape(-1, n_sub)
    lo = lower.max(axis=1) + band.offset
    return lo, np.maximum(upper.min(axis=1) + band.offset, lo)


def card_forecasts(case: TestCase, card: Any, price: str = 'constant',
                   errors: ForecastErrorSettings | None = None) -> TestCaseForecasts:
    """Return the forecasts of a control card (loaded, path or built-in name) on a test case."""
    return TestCaseForecasts(case, ForecastSpec.from_card(card), price, errors)
