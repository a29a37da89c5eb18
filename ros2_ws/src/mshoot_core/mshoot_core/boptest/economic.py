"""
Economic MPC of the BOPTEST heat pump house: the price of electricity against comfort.

Stable API::

    from mshoot_core.boptest.economic import controller_settings, EconomicController, run_period
    config = controller_settings(case, price='dynamic', mode='modulation')
    config.settings, config.model, config.forecast_columns     # MpcSettings, model, names
    forecast = config.forecast(t_s)                            # N+1 rows from the test case data
    result = run_period(case, 'peak_heat_day', 'dynamic', mode='modulation')

The control model (the thermal network of the card ``boptest_house``, :func:`control_model`)
plans the heat pump's duty ``d`` per
control step (the fraction of the step it runs at full load: its COP and the fan's fixed power
make full load the cheapest way to deliver heat), minimising the cost 'output' of
:class:`~mshoot_core.shooting.ShootingProblem` (the sum of the model output ``cost`` =
price x electric power x step) plus a soft comfort band: a linear and a small quadratic
penalty on the zone temperature outside the test case's band (its lower edge raised by a
margin, as the plan sees only the step ends while BOPTEST integrates discomfort continuously).

The plan's first duty is dispatched by :class:`~mshoot_core.actuation.Actuator` (settings
``actuation`` 'burst') at the plant's 60 s sampling: a full-load burst of the planned length,
joined to the previous step's burst (fewer starts), with an optional minimum run time; the burst
reaches the building either as the heat pump's modulation ``oveHeaPumY_u`` (mode
``'modulation'``, direct control) or through the local loop's zone setpoint ``oveTSet_u`` (mode
``'setpoint'``: a setpoint above the zone temperature while the burst runs, below it
otherwise). Mode ``'tracking'`` sends the plan's zone
temperature at the end of the step as the setpoint (the supervisory setpoint of the design).

The unmeasured floor and envelope temperatures are estimated by the extended Kalman filter
:class:`~mshoot_core.estimation.StateEstimator` (settings ``estimation``) from the measured zone
temperature and the step's measured inputs (weather and the heat of the heat pump), every
control step from the start of the warm-up: a warm-up step is observed like any other. Its
noise (:data:`DEFAULTS`: measurement 0.07 K, model error 0.05 K per step of every state) was
tuned on the six BOPTEST runs: against 0.1 K for the measurement, it gave 0.1-0.3 % less cost
and 0.04 K h less discomfort in total on the typical heat period (peak: equal).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import pathlib
import time
from typing import Any, Callable, Mapping

import numpy as np
import pandas as pd

from mshoot_core.actuation import Actuator
from mshoot_core.boptest.forecasts import ForecastSpec, TestCaseForecasts
from mshoot_core.boptest.testcase import PRICE_SCENARIOS, TestCase
from mshoot_core.estimation import StateEstimator
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import KELVIN
from mshoot_core.mpc import MPC
from mshoot_core.settings import ForecastErrorSettings, MpcSettings
from mshoot_core.shooting import Scaling

logger = logging.getLogger(__name__)

#: Ways of sending the plan to the building.
MODES = ('modulation', 'setpoint', 'tracking')
#: Disturbance columns of the control model, in its input order.
DISTURBANCES = ('Tout', 'solar', 'gains', 'price')
#: Comfort band columns [degC] of the forecast (the MPC's zone state bounds).
BAND_COLUMNS = ('comfort_min', 'comfort_max')
#: The actuation settings of each mode (:mod:`mshoot_core.actuation`) and the overwrite the
#: schedule goes to.
ACTUATION = {'modulation': ({'actuation': 'burst', 'actuation_send': 'value'}, 'oveHeaPumY_u'),
             'setpoint': ({'actuation': 'burst', 'actuation_send': 'setpoint'}, 'oveTSet_u'),
             'tracking': ({'actuation': 'hold'}, 'oveTSet_u')}
#: Defaults of the economic MPC.
DEFAULTS: dict[str, Any] = {
    'horizon_steps': 36, 'step_s': 3600.0, 'cost': 'output', 'cost_output': 'cost',
    'control_min': 0.0, 'control_max': 1.0, 'comfort': 'soft',
    'soft_penalty': 100.0, 'soft_penalty_linear': 200.0, 'solver': 'ipopt',
    'solver_max_iter': 300, 'safe_value': 0.0, 'on_failure': 'plan',
    'measurement_noise_k': 0.07}

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


@dataclasses.dataclass
class EconomicConfig:
    """
    Everything an MPC (core or ROS node) needs to run the economic MPC on a test case.

    Attributes
    ----------
    settings : MpcSettings
        The MPC settings (control ``d`` in [0, 1], cost 'output' of the model output ``cost``,
        soft comfort band).
    model : Model
        The identified control model (:func:`control_model`).
    case : TestCase
    price : str
        The price scenario (``constant``, ``dynamic``, ``highly_dynamic``).
    mode : str
        One of :data:`MODES`.
    forecast_columns : tuple of str
        The forecast's columns: the disturbances, then the band [degC].

    """

    settings: MpcSettings
    model: Model
    case: TestCase
    price: str
    mode: str
    forecast_columns: tuple[str, ...] = (*DISTURBANCES, *BAND_COLUMNS)

    @property
    def margin_k(self) -> float:
        """Raise of the band's lower edge in the plan [K] (setting ``band_margin_k``)."""
        return self.settings.comfort.band_margin_k

    @property
    def min_run_s(self) -> float:
        """Minimum run time of the heat pump [s] (setting ``min_run_s``; 0: none)."""
        return self.settings.actuation.min_run_s

    def forecast(self, t_s: float, steps: int | None = None) -> pd.DataFrame:
        """Return the perfect forecast of ``steps`` (default: the horizon) steps from ``t_s``."""
        p = self.settings.problem
        return forecast_frame(self.case, t_s, p.horizon_steps if steps is None else steps,
                              p.step_s, self.price, self.margin_k)

    def mpc(self) -> MPC:
        """Return a new MPC of the model with the settings."""
        states = len(self.model.state_names)
        return MPC(self.model, self.settings,
                   state_bounds={'T': ('comfort_min', 'comfort_max', KELVIN)},
                   state_scaling=Scaling(np.full(states, 288.15), np.full(states, 10.0)))

    def dispatcher(self) -> Actuator:
        """Return a new actuator of the planned duties (its settings ``actuation``)."""
        p = self.settings.problem
        return Actuator(self.settings.actuation, p.control_bounds, p.step_s)


def controller_settings(case: TestCase | None = None, price: str = 'constant',
                        mode: str = 'modulation', parameters: Any = None,
                        margin_k: float = 0.5, min_run_h: float = 0.0,
                        **options: Any) -> EconomicConfig:
    """
    Return the economic MPC of the test case for a price scenario and a mode.

    Parameters
    ----------
    case : TestCase, optional
        The test case (default :meth:`TestCase.load`).
    price : str
        A key of :data:`~mshoot_core.boptest.testcase.PRICE_SCENARIOS`.
    mode : str
        One of :data:`MODES`.
    parameters : optional
        The control model's parameters over the card's (:func:`control_model`).
    margin_k : float
        Raise of the comfort band's lower edge in the plan [K], >= 0.
    min_run_h : float
        Minimum run time of the heat pump [h], >= 0 (0: none).
    **options
        Flat MPC settings over :data:`DEFAULTS` (e.g. ``horizon_steps=24``).

    Raises
    ------
    ValueError
        For an unknown price scenario or mode, a negative margin or run time, bad settings.

    """
    case = case if case is not None else TestCase.load()
    if price not in PRICE_SCENARIOS:
        raise ValueError(f'unknown price scenario {price!r}: expected one of '
                         f'{list(PRICE_SCENARIOS)}')
    if mode not in MODES:
        raise ValueError(f'unknown mode {mode!r}: expected one of {list(MODES)}')
    if not (math.isfinite(margin_k) and margin_k >= 0):
        raise ValueError(f'margin_k must be >= 0 K, got {margin_k!r}')
    if not (math.isfinite(min_run_h) and 0 <= min_run_h <= 24):
        raise ValueError(f'min_run_h must be in [0, 24] h, got {min_run_h!r}')
    model = control_model(parameters)
    settings = MpcSettings.from_flat({**DEFAULTS, **ACTUATION[mode][0], **options},
                                     control_names=('d',), band_margin_k=float(margin_k),
                                     min_run_s=float(min_run_h) * 3600.0)
    return EconomicConfig(settings, model, case, price, mode)


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


@dataclasses.dataclass
class PeriodResult:
    """
    One closed-loop run of a test period.

    Attributes
    ----------
    records : DataFrame
        The plant's records from the warm-up's start (:meth:`BoptestPlant.records`).
    steps : DataFrame
        One row per control step: ``time_s``, ``duty``, ``Tz_measured`` [degC],
        ``Tz_planned_end`` [degC], ``Tf_est``, ``Te_est`` [degC], ``solve_s``,
        ``wall_s`` (controller wall time of the step), ``success``.
    start_s, end_s : float
        The test period [s].
    wall_s : float
        Wall time of the whole run [s].

    """

    records: pd.DataFrame
    steps: pd.DataFrame
    start_s: float
    end_s: float
    wall_s: float


def hourly_inputs(records: pd.DataFrame, case: TestCase, t0_s: float, t1_s: float,
                  price: str, model: Model) -> np.ndarray:
    """
    Return the model inputs measured over [t0, t1): means of the plant's records.

    Outdoor temperature and irradiance from the building's weather outputs, gains and price
    from the data, and the duty equivalent of the measured condenser heat (mean heat over the
    model's heat ``Q`` at full duty and the mean outdoor temperature).
    """
    window = records[(records['time'] > t0_s) & (records['time'] <= t1_s + 1e-6)]
    if window.empty:
        raise ValueError(f'no records in ({t0_s:g}, {t1_s:g}] s')
    tout = float(window['weaSta_reaWeaTDryBul_y'].mean()) - KELVIN
    solar = float(window['weaSta_reaWeaHGloHor_y'].mean())
    step = t1_s - t0_s
    gains = float(_interval_means(case, 'InternalGainsCon[1]', np.array([t0_s]), step)[0]
                  + _interval_means(case, 'InternalGainsRad[1]', np.array([t0_s]), step)[0])
    cost = float(_interval_means(case, case.price_column(price), np.array([t0_s]), step)[0])
    u = np.array([tout, solar, gains, cost, 1.0])
    x = np.full((1, len(model.state_names)), 293.15)
    _, y = model.simulate_intervals(x, u[None, :], step)
    full = float(y[0, model.output_names.index('Q')])
    u[4] = max(float(window['reaQHeaPumCon_y'].mean()) / full, 0.0)
    return u


class EconomicController:
    """
    One run of the economic MPC: the state estimator, the MPC and the actuator, step by step.

    Usage, every control step of length ``step_s`` starting at ``t``::

        controller.start(t0, tz_k)                            # once, at the plant's start
        pieces, result = controller.decide(t)                 # the step's overwrites
        ...advance the plant through the pieces...
        controller.observe(records, t, t + step_s, tz_k)      # the step's measurements

    Steps under the building's own control (the warm-up) are only observed.

    Parameters
    ----------
    config : EconomicConfig
        From :func:`controller_settings`.

    """

    def __init__(self, config: EconomicConfig) -> None:
        self.config = config
        self.step_s = config.settings.problem.step_s
        self.estimator = StateEstimator.from_settings(config.model, config.settings.estimation,
                                                      self.step_s)
        self.zone = self.estimator.measured[0]
        self.mpc = config.mpc()
        self.dispatcher = config.dispatcher()

    def start(self, t_s: float, tz_k: float) -> None:
        """Start the estimate from the zone temperature [K] measured at ``t_s`` [s]."""
        self.estimator.reset()
        self.estimator.update(float(t_s), {self.zone: float(tz_k)})

    @property
    def state(self) -> np.ndarray:
        """Return the estimated states (Tz, Tf, Te) [K]."""
        if self.estimator.estimate is None:
            raise RuntimeError('call start() first')
        return self.estimator.estimate.x.copy()

    def observe(self, records: pd.DataFrame, t0_s: float, t1_s: float,
                tz_k: float) -> np.ndarray:
        """
        Update the state with the measurements of the step [t0, t1] (plant records).

        Returns the measured model inputs of the step (:func:`hourly_inputs`).
        """
        c = self.config
        u = hourly_inputs(records, c.case, t0_s, t1_s, c.price, c.model)
        self.estimator.update(float(t1_s), {self.zone: float(tz_k)}, u)
        return u

    def decide(self, t_s: float) -> tuple[list[tuple[float, dict[str, float]]], Any]:
        """
        Plan from the estimated state at ``t_s``; return the step's overwrite pieces and plan.

        The pieces are (end time [s], overwrites) in order (the schedule of
        :meth:`Actuator.schedule`); the plan is the :class:`~mshoot_core.mpc.MpcResult`.
        """
        x0 = self.state
        result = self.mpc.solve(x0, t_s, self.config.forecast(t_s))
        end = t_s + self.step_s
        overwrite = ACTUATION[self.config.mode][1]
        if self.config.mode == 'tracking':
            planned = float(np.clip(result.states[1, 0], 278.15, 308.15))
            return [(end, {overwrite: planned})], result
        controls = result.controls[0] if np.all(np.isfinite(result.controls)) else np.zeros(1)
        following = result.controls[1] if len(result.controls) > 1 else None
        schedule = self.dispatcher.schedule(controls, following, float(x0[0]))
        ends = [*(t_s + schedule.offsets_s[1:]), end]
        return ([(e, {overwrite: float(v[0])}) for e, v in zip(ends, schedule.values)],
                result)


def run_period(case: TestCase, period: str, price: str, mode: str = 'modulation',
               config: EconomicConfig | None = None, warmup_days: float = 7.0,
               length_days: float = 14.0, progress: Callable[[str], None] | None = None,
               **options: Any) -> PeriodResult:
    """
    Run the economic MPC on a test period of the plant (core, no ROS).

    The warm-up runs under the building's own control while the estimator follows it; every
    control step of the test period the estimated state and the perfect forecast from the
    test case's data go to the MPC, and the plan's first duty to the plant through the
    :class:`~mshoot_core.actuation.Actuator`.

    Parameters
    ----------
    case : TestCase
        The test case.
    period : str
        ``peak_heat_day`` or ``typical_heat_day`` (a key of the test case's days).
    price, mode : str
        See :func:`controller_settings`.
    config : EconomicConfig, optional
        Default ``controller_settings(case, price, mode, **options)``.
    warmup_days, length_days : float
        The warm-up and the length of the test period [days].
    progress : callable, optional
        Called with a line of progress once a simulated day.

    """
    from mshoot_core.boptest.plant import run_period as run_plant
    config = config if config is not None else controller_settings(case, price, mode,
                                                                   **options)
    policy = _EconomicPolicy(EconomicController(config), period, progress, length_days)
    run = run_plant(case, period, policy, warmup_days, length_days,
                    control_step_s=config.settings.problem.step_s)
    return PeriodResult(run.records, pd.DataFrame(policy.rows), run.start_s, run.end_s,
                        run.wall_s)


class _EconomicPolicy:
    """:class:`EconomicController` in the one period loop (:func:`plant.run_period`)."""

    def __init__(self, controller: EconomicController, period: str,
                 progress: Callable[[str], None] | None, length_days: float) -> None:
        self.controller = controller
        self.period, self.progress, self.length_days = period, progress, length_days
        self.step = controller.step_s
        self.rows: list[dict[str, Any]] = []
        self._last: tuple[float, np.ndarray, Any, float] | None = None
        self._start_s: float | None = None
        self._last_day: int | None = None

    def observe(self, plant: Any) -> None:
        t, tz = float(plant.time_s), plant.outputs['reaTZon_y']
        if self._start_s is None:
            self._start_s = t
            self.controller.start(t, tz)
            return
        u = self.controller.observe(plant.records(t - self.step, t), t - self.step, t, tz)
        if self._last is None:
            return
        t0, x0, result, wall = self._last
        self._last = None
        self.rows.append({'time_s': t0, 'duty': float(result.controls[0, 0]), 'duty_run': u[4],
                          'Tz_measured_end': tz - KELVIN,
                          'Tz_planned_end': float(result.states[1, 0]) - KELVIN,
                          'Tf_est': x0[1] - KELVIN, 'Te_est': x0[2] - KELVIN,
                          'solve_s': float(result.solve_time_s), 'wall_s': wall,
                          'success': bool(result.success), 'objective': float(result.fun)})
        day = len(self.rows) * self.step // 86400.0
        if self.progress is not None and day != self._last_day and \
                (len(self.rows) * self.step) % 86400.0 < self.step:
            self._last_day = day
            self.progress(f'{self.period} {self.controller.config.price} '
                          f'{self.controller.config.mode}: day {day:g}/{self.length_days:g}, '
                          f'zone {tz - KELVIN:.2f} degC, mean solve '
                          f'{np.mean([r["solve_s"] for r in self.rows]):.3f} s')

    def __call__(self, t_s: float, outputs: Mapping[str, float]) -> list:
        began = time.perf_counter()
        x0 = self.controller.state
        pieces, result = self.controller.decide(t_s)
        self._last = (t_s, x0, result, time.perf_counter() - began)
        return pieces
