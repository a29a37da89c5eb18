"""
The supervisory controller on a BOPTEST plant, in the one period loop.

:class:`~mshoot_core.controller.Controller` as a controller of
:func:`mshoot_core.boptest.plant.run_period`.

Stable API::

    from mshoot_core.boptest.supervision import supervised_plant, SupervisedPlant
    policy = supervised_plant(case, plant_card, control_card, settings, price='dynamic')
    # or SupervisedPlant(controller, plant_card, forecast)
    run = run_period(case, period, policy, record=policy.recorded(case))
    policy.outcomes                                          # StepOutcome of every step

:func:`supervised_plant` builds it all from configuration: the control model of the control
card (:func:`~mshoot_core.models.card.build_model`), the controller of the settings
(:func:`~mshoot_core.controller.controller_for`) and the forecast of the control card's test
case source (:func:`~mshoot_core.boptest.forecasts.card_forecasts`: interval means, the tightest
band over each interval; the band's margin is the controller's, ``band_margin_k``).

The plant's card (kind ``boptest``, e.g. ``boptest_modulation.yaml``) maps the FMU's variables:
its states are the measured states, its outputs the measured outputs, its controls the overwrites.
At every control step from the warm-up's start (:meth:`SupervisedPlant.observe`), the controller
is offered what the emulator node publishes over ROS: the states at the step's end (the card's
canonical units) with the step means of the outputs as ``mean_<output>`` (the measured inputs
of the settings' ``measured_inputs`` come from them), and the forecast of ``forecast(t_s)`` (a
frame of the horizon's rows from ``t_s``, by series name); a warm-up step is observed like any
other. In the test period, each step's decision (:meth:`SupervisedPlant.__call__`) goes to the
plant as the card's overwrites piece by piece (the schedule within the step: settings
``actuation``), each model control sent as the plant's control of the settings'
``plant_controls``, then the band setpoints of the settings' ``band_setpoints`` (controls of
the card with overwrite switches, clipped to the card's limits: :meth:`StepOutcome.sent`); a
released control's overwrite is released (the building's own controller).
"""
from __future__ import annotations

import logging
import time
from typing import Any, Callable, Mapping

import numpy as np
import pandas as pd

from mshoot_core.boptest.card_plant import card_overwrites, card_values, record_means
from mshoot_core.boptest.plant import BoptestPlant, recorded_outputs
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.controller import Controller, MEAN_PREFIX, StepOutcome
from mshoot_core.units import NS_PER_S

logger = logging.getLogger(__name__)

#: Time tolerance [s].
_EPS_S = 1e-6


class SupervisedPlant:
    """
    A :class:`Controller` driving a BOPTEST plant through its card (see the module).

    Parameters
    ----------
    controller : Controller
        The controller (its model's controls sent through ``plant_controls``).
    card : ModelCard
        The plant's card (kind ``boptest``).
    forecast : callable
        ``forecast(t_s) -> DataFrame``: the forecast from ``t_s`` [FMU time, s], one row per
        control step (the horizon's and one more), columns by series name.

    Raises
    ------
    ValueError
        If a model control or a band setpoint is sent as a control the card does not have, or
        without an overwrite switch.

    """

    def __init__(self, controller: Controller, card: Any,
                 forecast: Callable[[float], pd.DataFrame]) -> None:
        self.controller = controller
        self.card = card
        self.forecast = forecast
        settings = controller.settings
        names = settings.actuation.plant_names
        self.step_s = float(settings.problem.step_s)

        def overwrite(plant: str, what: str) -> Any:
            spec = card.controls.get(plant)
            if spec is None or spec.activate is None:
                raise ValueError(f'{what}: expected a control of the card with an overwrite '
                                 f'switch, got {sorted(card.controls)}')
            return spec

        self._sent = {control: overwrite(
            names.get(control, control),
            f'control {control!r} is sent as {names.get(control, control)!r} (plant_controls '
            f'{settings.actuation.plant_controls!r})')
            for control in settings.problem.control_names}
        bands = {plant: overwrite(plant, f'band setpoint {plant!r} (band_setpoints '
                                         f'{settings.actuation.band_setpoints!r})')
                 for plant, *_ in controller.band_setpoints}
        controller.limit_band_setpoints({plant: (spec.min, spec.max)
                                         for plant, spec in bands.items()})
        #: What is sent, in the order of :meth:`StepOutcome.sent`: the card's controls.
        self._specs = [*self._sent.values(), *bands.values()]
        self.outcomes: list[StepOutcome] = []
        self._last_s: float | None = None

    def recorded(self, case: TestCase) -> list[str]:
        """Return the outputs a run records: those of ``kpis.json`` and the card's."""
        return recorded_outputs(case, [v.variable for v in (*self.card.states.values(),
                                                            *self.card.outputs.values())])

    # -- measuring ----------------------------------------------------------------------------
    def measurements(self, plant: BoptestPlant) -> tuple[dict[str, float], dict[str, float]]:
        """
        Return the states now and the step means of the outputs since the last observation.

        Both in the card's canonical units, by name; the means as ``mean_<output>`` (none at
        the first observation).
        """
        t = float(plant.time_s)
        states = dict(zip(self.card.states, card_values(plant, list(self.card.states.values()))))
        outputs: dict[str, float] = {}
        if self._last_s is not None:
            means = record_means(plant, list(self.card.outputs.values()), self._last_s, t)
            outputs = {MEAN_PREFIX + name: value for name, value in zip(self.card.outputs, means)}
        return states, outputs

    def observe(self, plant: BoptestPlant) -> None:
        """Offer the controller the measurements and the forecast at the plant's time."""
        t = float(plant.time_s)
        stamp = int(round(t * NS_PER_S))
        states, outputs = self.measurements(plant)
        self._last_s = t
        c = self.controller
        rejection = c.offer_named_state(stamp, list(states), list(states.values()), stamp,
                                        output_names=list(outputs),
                                        output_values=list(outputs.values()))
        if rejection is not None:
            logger.warning('state at %.0f s rejected: %s', t, rejection.reason)
        frame = self.forecast(t)
        rejection = c.offer_forecast(stamp, self.step_s, {name: frame[name].to_numpy()
                                                          for name in frame.columns}, stamp)
        if rejection is not None:
            logger.warning('forecast at %.0f s rejected: %s', t, rejection.reason)

    # -- deciding -----------------------------------------------------------------------------
    def __call__(self, t_s: float, outputs: Mapping[str, float]
                 ) -> list[tuple[float, dict[str, float | None]]]:
        """
        Return the step's overwrites piece by piece: (end time [s], overwrites).

        A step whose inputs are missing gets the controller's fallback at once (its input wait
        is not waited for: the plant waits for nobody).
        """
        c = self.controller
        now = int(round(float(t_s) * NS_PER_S))
        steady = time.monotonic_ns()
        outcomes = c.poll(now, steady)
        if not outcomes:
            wait = c.settings.inputs.input_wait_s
            outcomes = c.poll(now, steady + int((wait + 1.0) * NS_PER_S))
        if not outcomes:
            raise RuntimeError(f'the controller decided nothing at {t_s:.0f} s')
        outcome = outcomes[-1]
        self.outcomes.append(outcome)
        return self.pieces(outcome)

    def pieces(self, outcome: StepOutcome) -> list[tuple[float, dict[str, float | None]]]:
        """
        Return a step's overwrites piece by piece (see :meth:`__call__`).

        What :meth:`StepOutcome.sent` sends: the decision's controls, then the band setpoints.
        """
        decision, schedule = outcome.sent()
        released = decision.released or (False,) * len(self._specs)
        if schedule is None:
            offsets = np.zeros(1)
            values = np.asarray(decision.controls, dtype=float).reshape(1, -1)
        else:
            offsets, values = schedule.offsets_s, schedule.values
        ends = [*(outcome.t_s + offsets[1:]), outcome.t_s + self.step_s]
        sent = self._specs
        return [(float(end), card_overwrites(sent, row, released))
                for end, row in zip(ends, values)]


def supervised_plant(case: TestCase, plant_card: Any, control_card: Any, settings: Any,
                     price: str = 'constant', errors: Any = None) -> SupervisedPlant:
    """
    Return the controller of a control card and settings on a test case (see the module).

    Parameters
    ----------
    case : TestCase
        The test case.
    plant_card, control_card : ModelCard or path
        The plant's card (kind ``boptest``) and the control model's (with a
        ``testcase_forecast`` section).
    settings : MpcSettings
        The controller's settings.
    price : str
        The price scenario of the forecast.
    errors : ForecastErrorSettings, optional
        The forecast's errors (default: none, the test case's data).

    """
    from mshoot_core.boptest.forecasts import card_forecasts
    from mshoot_core.controller import controller_for
    from mshoot_core.models.card import build_model, load_card
    plant_card = plant_card if hasattr(plant_card, 'controls') else load_card(plant_card)
    control_card = control_card if hasattr(control_card, 'controls') else load_card(control_card)
    controller = controller_for(build_model(control_card), settings)
    source = card_forecasts(case, control_card, price, errors)
    horizon, step = controller.mpc.horizon_steps, controller.settings.problem.step_s
    return SupervisedPlant(controller, plant_card, lambda t_s: source.frame(t_s, horizon, step))
