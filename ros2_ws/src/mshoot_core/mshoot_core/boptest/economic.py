"""
The heat pump house's control model and its forecast from the test case's data.

Stable API::

    from mshoot_core.boptest.economic import control_model, forecast_frame
    model = control_model()                                    # the card boptest_house
    frame = forecast_frame(case, t_s, 36, 3600.0, 'dynamic')   # N+1 rows from the test case

The control model (the thermal network of the card ``boptest_house``, :func:`control_model`)
plans the heat pump's duty ``d`` per control step (the fraction of the step it runs at full
load). The economic MPC of the house is the general
:class:`~mshoot_core.controller.Controller` with the packaged settings ``boptest_house``
(``MpcSettings.from_file('boptest_house')``), on a BOPTEST plant through
:func:`mshoot_core.boptest.supervision.supervised_plant` (in core) or the MPC node (over ROS).
"""
from __future__ import annotations

import functools
import json
import pathlib
from typing import Mapping

import numpy as np
import pandas as pd

from mshoot_core.boptest.forecasts import ForecastSpec, TestCaseForecasts
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.models.base import Model
from mshoot_core.settings import ForecastErrorSettings

#: Disturbance columns of the control model, in its input order.
DISTURBANCES = ('Tout', 'solar', 'gains', 'price')
#: Comfort band columns [degC] of the forecast (the MPC's zone state bounds).
BAND_COLUMNS = ('comfort_min', 'comfort_max')
#: The built-in card of the control model (mshoot_core/cards/boptest_house.yaml).
CARD = 'boptest_house'


def control_model(parameters: Mapping[str, float] | str | pathlib.Path | None = None) -> Model:
    """
    Return the control model: the thermal network of the card :data:`CARD`.

    Parameters
    ----------
    parameters : mapping or path, optional
        Parameter values over the card's: a mapping, or a JSON file of a mapping (or of
        ``{'parameters': mapping}``); None for the card's (the packaged identification).

    Raises
    ------
    ValueError
        For a name that is not a parameter of the card's network.

    """
    from mshoot_core.calibration import NetworkBuilder
    from mshoot_core.models import card as cards
    if isinstance(parameters, (str, pathlib.Path)):
        data = json.loads(pathlib.Path(parameters).read_text())
        parameters = data.get('parameters', data)
    card = cards.load_card(cards.builtin_card(CARD))
    return NetworkBuilder(card)(dict(parameters or {}))


def _interval_means(case: TestCase, column: str, t_s: np.ndarray, step_s: float) -> np.ndarray:
    """Mean of a data column over [t, t + step) for every t (:mod:`.forecasts`)."""
    return _card_forecasts(case, 'constant').interval_means(column, t_s, step_s)


@functools.lru_cache(maxsize=8)
def _card_forecasts(case: TestCase, price: str,
                    errors: ForecastErrorSettings | None = None) -> TestCaseForecasts:
    """Return the test case forecasts of the card :data:`CARD` (its ``testcase_forecast``)."""
    return TestCaseForecasts(case, ForecastSpec.from_card(CARD), price, errors)


def forecast_frame(case: TestCase, t_s: float, steps: int, step_s: float, price: str,
                   margin_k: float = 0.0, upper_margin_k: float = 0.0,
                   errors: ForecastErrorSettings | None = None) -> pd.DataFrame:
    """
    Return the forecast of the control model from the test case's data.

    :meth:`~mshoot_core.boptest.forecasts.TestCaseForecasts.frame` of the card :data:`CARD`
    (its ``testcase_forecast`` section): row k (time t_s + k step_s, k = 0..steps) holds the
    interval means of ``Tout`` [degC], ``solar`` [W/m2], ``gains`` [W] and ``price``
    [EUR/kWh], and the tightest comfort band [degC] over the interval ending there, its lower
    edge raised by ``margin_k`` and its upper one lowered by ``upper_margin_k``; with
    ``errors``, BOPTEST's forecast errors on the temperature and solar before the means.
    """
    frame = _card_forecasts(case, price, errors).frame(t_s, steps, step_s)
    if margin_k or upper_margin_k:
        frame['comfort_min'] = frame['comfort_min'] + margin_k
        frame['comfort_max'] = np.maximum(frame['comfort_max'] - upper_margin_k,
                                          frame['comfort_min'])
    return frame
