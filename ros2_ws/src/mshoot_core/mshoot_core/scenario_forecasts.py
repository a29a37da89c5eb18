"""
A scenario's step forecasts as a building gets them: BOPTEST's errors, or a control card's source.

:class:`ScenarioForecasts` is what the forecaster node serves each step: the scenario's rows
with BOPTEST's forecast errors (:mod:`mshoot_core.forecast`) on its temperature and solar
series, or, for a BOPTEST test period and a control card with a ``testcase_forecast`` section,
the card's test case source (:mod:`mshoot_core.boptest.forecasts`). It sits above both, so
neither imports the other's user.
"""
from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from mshoot_core.forecast import ForecastSource, GRID_S, horizon_problem, truth_of_frame
from mshoot_core.safety import COMFORT_SERIES, PRICE_SERIES
from mshoot_core.scenario import forecast_rows, forecast_window
from mshoot_core.settings import ForecastErrorSettings

logger = logging.getLogger(__name__)


class ScenarioForecasts:
    """
    The forecasts of a scenario's control steps: its rows, the weather with BOPTEST's errors.

    Every step's forecast is :func:`mshoot_core.scenario.forecast_window` (the rows of the step
    and the ``horizon_steps`` after it); with an uncertainty level, the weather columns are
    replaced by a :class:`ForecastSource`'s forecast at the step's time (horizon
    ``horizon_steps`` x the row spacing, interval the row spacing):

    - a BOPTEST test period (``attrs['boptest']`` of
      :func:`mshoot_core.boptest.period_scenario.period_scenario`): the test case folder's
      series at the FMU time of the step (seconds from 1 January, BOPTEST's clock and seed), each
      scenario column from the test case column and offset in ``attrs['boptest']['weather']``;
    - any other scenario: its own ``Tout`` [degC] and ``solrad`` [W/m2] columns (linear
      between rows) at the scenario's time [s since its start].

    With no errors the forecast is the scenario's rows, unchanged.

    With a control card that has a ``testcase_forecast`` section and a BOPTEST test period, the
    step's forecast is instead the card's :class:`~mshoot_core.boptest.forecasts.TestCaseForecasts`
    frame at the step's FMU time (interval means of the series the card names, the tightest band
    per zone, the price of the scenario's price column; the errors on the temperature and solar
    points before the means), on the scenario's time.

    Parameters
    ----------
    scenario : pd.DataFrame
        The scenario (:mod:`mshoot_core.scenario`).
    errors : ForecastErrorSettings, optional
        Uncertainty levels and seed.
    card : ModelCard or path, optional
        The control model's card (used for a BOPTEST test period if it has a
        ``testcase_forecast`` section).

    Attributes
    ----------
    testcase : TestCaseForecasts or None
        The card's test case source, when it serves the forecasts.

    """

    #: The scenario's weather columns (:mod:`mshoot_core.scenario`): temperature, solar.
    WEATHER = ('Tout', 'solrad')

    def __init__(self, scenario: pd.DataFrame, errors: ForecastErrorSettings | None = None,
                 card: object = None) -> None:
        self.scenario = scenario
        self.testcase = None
        self.errors = errors if errors is not None else ForecastErrorSettings()
        times = np.asarray(scenario.index, dtype=float)
        self.step_s = float(times[1] - times[0]) if times.size > 1 else GRID_S
        boptest = scenario.attrs.get('boptest')
        temperature, solar = self.WEATHER
        if boptest:
            from mshoot_core.boptest.testcase import TestCase
            #: Scenario column -> (source series, offset added to it).
            self.weather = {str(k): (str(v[0]), float(v[1]))
                            for k, v in boptest['weather'].items()}
            self.clock = scenario['fmu_time_s'].to_numpy(dtype=float)
            case = TestCase.load(boptest['test_case'])
            self.source = ForecastSource.from_test_case(
                case, self.errors, self.weather[temperature][0], self.weather[solar][0])
            self.testcase = _card_source(card, case, str(boptest['price']), self.errors)
        else:
            self.weather = {temperature: (temperature, 0.0), solar: (solar, 0.0)}
            self.clock = times - times[0]
            self.source = ForecastSource(truth_of_frame(scenario[list(self.WEATHER)],
                                                        self.clock),
                                         self.WEATHER, self.errors, temperature, solar)

    @property
    def series(self) -> tuple[str, ...] | None:
        """Return the disturbance series of the card's test case source (None: the rows')."""
        if self.testcase is None:
            return None
        return tuple(c for c in self.testcase.columns
                     if c not in (*COMFORT_SERIES, PRICE_SERIES))

    def check_horizon(self, horizon_steps: int) -> None:
        """Raise ValueError if ``horizon_steps`` rows are too long a horizon for the errors."""
        # a test case source's last row is a mean over one more step
        steps = horizon_steps + (self.testcase is not None)
        problem = horizon_problem(list(self.source.uncertain_points.values()),
                                  steps * self.step_s)
        if problem:
            raise ValueError(f'{problem} ({horizon_steps} steps of {self.step_s:g} s)')

    def history(self, index: int, steps: int) -> pd.DataFrame:
        """
        Return the ``steps`` rows before step ``index`` (e.g. over a warm-up before the scenario).

        Each row as the forecast of its own step would have it first (an interval mean from the
        card's test case source), so that a state's history is observed with the inputs a
        step-by-step run had.

        Raises
        ------
        ValueError
            Without a card's test case source, or for ``steps`` < 1.

        """
        if self.testcase is None or int(steps) < 1:
            raise ValueError(f'a history needs a test case source (a card with a '
                             f'testcase_forecast section) and steps >= 1, got '
                             f'{self.testcase is not None} and {steps!r}')
        steps = int(steps)
        t0 = float(self.clock[index])
        rows = [self.testcase.frame(t0 - k * self.step_s, 0, self.step_s).iloc[:1]
                for k in range(steps, 0, -1)]
        frame = pd.concat(rows)
        frame.index = pd.Index(float(self.scenario.index[index])
                               - np.arange(steps, 0, -1) * self.step_s,
                               name=self.scenario.index.name)
        return frame

    def window(self, index: int, horizon_steps: int) -> pd.DataFrame:
        """
        Return the forecast of step ``index``: ``horizon_steps + 1`` rows (class docstring).

        Raises
        ------
        ValueError
            For a bad index, or a horizon over 48 h with errors.

        """
        if self.testcase is not None:
            self.check_horizon(horizon_steps)
            forecast_rows(index, horizon_steps, len(self.scenario))  # checks the index
            frame = self.testcase.frame(float(self.clock[index]), horizon_steps, self.step_s)
            frame.index = pd.Index(float(self.scenario.index[index])
                                   + np.arange(horizon_steps + 1) * self.step_s,
                                   name=self.scenario.index.name)
            return frame
        window = forecast_window(self.scenario, index, horizon_steps)
        uncertain = self.source.uncertain_points
        if not uncertain:
            return window
        self.check_horizon(horizon_steps)
        points = {column: self.weather[column] for column in self.WEATHER
                  if self.weather[column][0] in uncertain and column in window.columns}
        forecast = self.source.forecast(float(self.clock[index]),
                                        horizon_steps * self.step_s, self.step_s,
                                        [point for point, _ in points.values()])
        window = window.copy()
        for column, (point, offset) in points.items():
            window[column] = forecast[point].to_numpy() + offset
        return window


def _card_source(card: object, case: object, price: str,
                 errors: ForecastErrorSettings) -> object:
    """Return the test case source of a control card with a section, else None."""
    if card is None or card == '':
        return None
    from mshoot_core.boptest.forecasts import card_forecasts, SECTION
    from mshoot_core.models import card as cards
    loaded = cards.load_card(card) if not hasattr(card, 'testcase_forecast') else card
    if getattr(loaded, SECTION, None) is None:
        return None
    return card_forecasts(case, loaded, price, errors)
