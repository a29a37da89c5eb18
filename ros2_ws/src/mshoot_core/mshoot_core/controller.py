"""
The supervisory controller: every per-step decision of the MPC, in one place.

A :class:`Controller` owns the MPC, the validation and staleness rules of its
inputs, the due-step logic, the solve in flight and its time budget, and the
fallback chain (:class:`~mshoot_core.safety.SetpointSupervisor`). It is driven
by plain values and clocks, so the offline loop
(:func:`mshoot_core.closed_loop.run_closed_loop`) and the ROS MPC node make
the same decisions through the same code:

- :meth:`Controller.offer_state` and :meth:`Controller.offer_forecast` take a
  measured state or a forecast with its stamp; a rejected one gets a
  :class:`~mshoot_core.safety.Rejection` (counted) and never reaches the
  optimiser; :meth:`Controller.offer_named_state` takes the state as named
  values (the form of a ``ZoneState`` message);
- when the control model's states are not all measured (its
  ``measured_states``, or the settings' ``measured_states``), the controller
  estimates the others (:class:`~mshoot_core.estimation.StateEstimator`, an
  extended Kalman filter; setting ``estimation``): every measurement is
  corrected against the prediction over the last interval, with the controls
  decided (or, from a ``ZoneState``, applied) and the disturbances of the
  forecast that covered it; the estimate is what the step is planned from
  (:attr:`Controller.estimate`, :attr:`StepOutcome.x0_std`). Offered
  unmeasured states are ignored;
- :meth:`Controller.poll` is called whenever something may have changed (a new
  input, a timer, a finished solve) with the controller's clock ``now_ns``
  (simulated or real time) and a steady wall clock ``steady_ns``; it returns
  the :class:`StepOutcome` of every step decided since the last call, with the step's band
  setpoints (settings ``band_setpoints``: plant controls at a comfort band's edge, not
  planned, :meth:`Controller.band_setpoint_values`) and what is sent (:meth:`StepOutcome.sent`).

A step is due when the clock enters it. It is solved once, from the newest
state stamped within the step (or at most ``max_state_age_s`` before it) and
the newest forecast starting at or before the step (at most
``max_forecast_age_s`` before it, then shifted). A step gets a fallback (the
last good plan's interval, else the safe setpoint) when its inputs stay missing
for ``input_wait_s`` of wall time or ``input_deadline_s`` of clock time, when
its solve raises (a model error), returns an unusable plan, does not converge
(with ``on_failure='fallback'``), or overruns ``time_budget_s`` (the solver
itself stops at the budget; a solve that still runs past it, e.g. in a hung
model call, gets its fallback on the next poll and its late result only warms
the next start).

Solves run inline (the offline loop, tests) or on an executor (a
:class:`concurrent.futures.Executor`; the ROS node uses one worker thread so it
keeps taking messages): then :meth:`poll` returns the outcome of a solve on
the first call after it finished (``on_solve_done`` tells when).
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import math
import time
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import numpy as np
import pandas as pd

from mshoot_core.actuation import Actuator, Schedule
from mshoot_core.controls import model_controls
from mshoot_core.estimation import Estimate, estimation_needed, StateEstimator
from mshoot_core.models.base import Model, ModelValueError
from mshoot_core.models.registry import control_interface, ControlInterface
from mshoot_core.mpc import MPC, MpcResult
from mshoot_core.safety import (applied_control_ranges, check_forecast, check_history,
                                check_lengths, check_named, check_series, check_zone_state,
                                COMFORT_SERIES, Decision, InputWait, LIMITS, PRICE_SERIES,
                                Rejection, RejectionCounter, reorder, SetpointSupervisor,
                                StampGate, zone_band_series, zone_state_caps)
from mshoot_core.scenario import column_labels, forecast_window
from mshoot_core.settings import BY_NAME, MpcSettings
from mshoot_core.shooting import Scaling
from mshoot_core.units import NS_PER_S

logger = logging.getLogger(__name__)

#: Input streams of the controller (keys of its rejection counts).
STREAMS = ('state', 'forecast')
#: States and forecasts kept, by stamp.
KEEP_INPUTS = 8
#: A capped setpoint this close to its zone's planned temperature at an interval's end, or
#: above it, heats in that interval (settings ``supply_floors``, ``cooling_mode_margin_k``)
#: [K].
HEATING_TOLERANCE_K = 0.05
#: Prefix of an output's mean over the last step in a zone state (``mean_<output>``); a
#: history's outputs are such means, named by output.
MEAN_PREFIX = 'mean_'


@dataclasses.dataclass(frozen=True)
class StepOutcome:
    """
    The decision of one control step, with what led to it.

    Attributes
    ----------
    step_ns : int
        Start of the step on the controller's clock [ns].
    decision : Decision
        What to apply (controls, source, fallback code and reason, plan).
    result : MpcResult or None
        The step's solve result, when it has one (also when it was not used).
    solve_time_s : float
        Wall time of the solve, or of the wait that ended in a fallback [s].
    x0 : ndarray or None
        The state the step was solved from (measured, or estimated).
    x0_std : ndarray or None
        Standard deviation of every state of an estimated ``x0`` [K] (None when
        the state is measured or there is none).
    schedule : Schedule or None
        What is sent within the step (:class:`~mshoot_core.actuation.Actuator`, settings
        ``actuation``): the decision's controls held (one piece), or bursts; None when the
        decision's controls are sent as they are.
    band_values : ndarray or None
        The band setpoints (settings ``band_setpoints``, in that order; None: none), shape
        (max(m, 1), nb): row 0 the step's, row k the k-th interval's of the decision's plan of
        m intervals [the band's unit, degC]; see :meth:`Controller.band_setpoint_values`.
    band_released : bool
        The band setpoints' overwrites released: no forecast covers the step (its values are
        then ``safe_temperature_c``); :meth:`sent` also releases them with the decision's
        overwrites (source 'released').

    """

    step_ns: int
    decision: Decision
    result: MpcResult | None
    solve_time_s: float
    x0: np.ndarray | None
    x0_std: np.ndarray | None = None
    schedule: Schedule | None = None
    band_values: np.ndarray | None = None
    band_released: bool = False

    @property
    def t_s(self) -> float:
        """Start of the step [s]."""
        return self.step_ns / NS_PER_S

    def sent(self) -> tuple[Decision, Schedule | None]:
        """
        Return the decision and the schedule as sent: the band setpoints after the controls.

        What the plant gets (:attr:`Controller.sent_control_names`, in that order): the
        decision's controls, plan and release flags with the band setpoints appended (held over
        the step's pieces; the plan's intervals each with its own); released with the
        decision's overwrites (source 'released') or when :attr:`band_released`. Without band
        setpoints, the decision and schedule as they are.
        """
        bands = self.band_values
        if bands is None:
            return self.decision, self.schedule
        d = self.decision
        bands = np.asarray(bands, dtype=float).reshape(-1, np.shape(bands)[-1])
        nc, nb = np.asarray(d.controls).size, bands.shape[1]
        release = self.band_released or d.source == 'released'
        plan = np.asarray(d.plan_controls, dtype=float).reshape(-1, nc)
        m = plan.shape[0]
        decision = dataclasses.replace(
            d, controls=np.concatenate([np.asarray(d.controls, dtype=float).reshape(-1),
                                        bands[0]]),
            plan_controls=np.hstack([plan, bands[np.minimum(np.arange(m), len(bands) - 1)]]),
            released=((tuple(d.released) or (False,) * nc) + (release,) * nb
                      if d.released or release else ()))
        schedule = self.schedule
        if schedule is not None:
            n = schedule.offsets_s.size
            schedule = Schedule(schedule.offsets_s,
                                np.hstack([schedule.values, np.tile(bands[0], (n, 1))]))
        return decision, schedule


@dataclasses.dataclass
class _Solve:
    """A solve in flight."""

    step_ns: int
    x0: np.ndarray
    started_ns: int
    future: concurrent.futures.Future
    fallback_given: bool = False
    x0_std: np.ndarray | None = None


class Controller:
    """
    Supervisory MPC: inputs in, one decision per control step out (see the module).

    Parameters
    ----------
    model : Model
        The control model.
    settings : MpcSettings, optional
        Every setting (default: the defaults).
    mpc : MPC, optional
        A configured MPC to use instead of building one from ``model`` and
        ``settings`` (its settings are then the controller's).
    executor : Executor, optional
        Where solves run (default: inline, inside :meth:`poll`).
    state_bounds : dict, optional
        Passed to :class:`~mshoot_core.mpc.MPC`.
    assumed_inputs : mapping, optional
        Model inputs that forecasts do not carry, held constant over the
        horizon (e.g. ``{'dpos': 0.0}``: ventilation off).
    on_solve_done : callable, optional
        Called (from the executor's thread) when a solve finishes: the owner
        should then call :meth:`poll`.
    initial_state : sequence of float, optional
        With estimation: the first estimate's unmeasured states (default: the
        mean of the measured ones, see :func:`~mshoot_core.estimation.initial_guess`).

    Attributes
    ----------
    mpc : MPC
    supervisor : SetpointSupervisor
    rejections : RejectionCounter
        Rejected inputs by stream ('state', 'forecast') and kind.
    results : dict
        Step stamp [ns] -> MpcResult of the latest steps (late ones included).
    estimator : StateEstimator or None
        The state estimator, when the states are estimated (see the module).

    Raises
    ------
    ValueError
        If the measured states are not states of the model, or ``estimation``
        is 'off' while some are not measured.

    """

    def __init__(self, model: Model | None = None, settings: MpcSettings | None = None, *,
                 mpc: MPC | None = None, executor: concurrent.futures.Executor | None = None,
                 state_bounds: dict | None = None,
                 assumed_inputs: Mapping[str, float] | None = None,
                 on_solve_done: Callable[[], None] | None = None,
                 history_length: int = 1000,
                 initial_state: Sequence[float] | None = None) -> None:
        if mpc is None:
            if model is None:
                raise TypeError('Controller needs a model or an MPC')
            mpc = MPC(model, settings, state_bounds=state_bounds,
                      state_scaling=state_scaling(settings, len(model.state_names)))
        elif settings is not None:
            mpc.update(settings)
        self.mpc = mpc
        self.executor = executor
        self.assumed_inputs = dict(assumed_inputs or {})
        self.on_solve_done = on_solve_done
        self.history_length = int(history_length)
        self.rejections = RejectionCounter()
        self.results: dict[int, MpcResult] = {}
        step_ns = int(round(self.settings.problem.step_s * NS_PER_S))
        self.step_ns = step_ns
        # States and forecasts are stamped with the start of the step they are for.
        self._state_gate = StampGate(step_ns, origin_ns=0)
        self._forecast_gate = StampGate(step_ns, origin_ns=0)
        self._states: dict[int, np.ndarray] = {}
        self._forecasts: dict[int, pd.DataFrame] = {}
        self._last_step_ns: int | None = None
        self._inflight: _Solve | None = None
        self._due_since: tuple[int, int, int] | None = None
        self._pending: MpcSettings | None = None
        self._decided: dict[int, np.ndarray] = {}
        self._estimates: dict[int, Estimate] = {}
        #: A first state's warm-up not observed yet (no forecast covered it yet).
        self._history: _History | None = None
        self.estimator: StateEstimator | None = None
        if estimation_needed(self.model, self.settings.estimation):
            self.estimator = StateEstimator.from_settings(
                self.model, self.settings.estimation, self.settings.problem.step_s,
                initial_state=initial_state)
        self.supervisor = self._build_supervisor()
        self._configure_inputs()
        self.actuator = self._build_actuator()
        self.measured_inputs = self._check_measured_inputs()
        self._error_processes  # noqa: B018 - bad forecast_error_inputs fail here
        #: The band setpoints (settings ``band_setpoints``): (plant control, edge, lower
        #: series, upper series) each.
        self.band_setpoints = self._check_band_setpoints()
        self._band_ranges: dict[str, tuple[float, float]] = {}
        #: The capped setpoints (settings ``setpoint_caps``): (control index, zone state
        #: index, the zone's lower band series, its offset [K]) each.
        self.setpoint_caps = self._check_setpoint_caps()
        #: The supply floors (settings ``supply_floors``): (control index, floor) each.
        self.supply_floors = self._check_supply_floors()

    # -- configuration --------------------------------------------------------------------
    @property
    def settings(self) -> MpcSettings:
        return self.mpc.settings

    @property
    def model(self) -> Model:
        return self.mpc.model

    @property
    def interface(self) -> ControlInterface:
        """
        Return the controls and the zone temperatures this controller works with.

        The controls are the settings' ``control_names``, the zone temperatures the MPC's
        comfort-bounded states.
        """
        return ControlInterface(tuple(self.settings.problem.control_names),
                                tuple(self.model.state_names), dict(self.mpc.state_bounds))

    def state_range(self) -> tuple[np.ndarray, np.ndarray]:
        """
        Return plausible (lower, upper) values of the states (physical units).

        Zone temperatures (the states bounded by a comfort band) lie within
        :data:`~mshoot_core.safety.LIMITS`; the other states are unbounded.
        """
        names = self.model.state_names
        low, high = np.full(len(names), -np.inf), np.full(len(names), np.inf)
        for name, (_, _, offset) in self.mpc.state_bounds.items():
            i = names.index(name)
            low[i] = LIMITS.zone_temperature_c[0] + offset
            high[i] = LIMITS.zone_temperature_c[1] + offset
        return low, high

    def _check_measured_inputs(self) -> dict[str, tuple[str, str]]:
        """Return the settings' ``measured_inputs``, checked against the model."""
        measured = self.settings.estimation.input_measurements
        model, controls = self.model, self.settings.problem.control_names
        for name, (_, output) in measured.items():
            if name not in model.input_names:
                raise ValueError(f'measured_inputs: {name!r} is not an input of the model '
                                 f'{list(model.input_names)}')
            if output and (name not in controls or output not in model.output_names):
                raise ValueError(f'measured_inputs: {name}=.../{output} needs a control (got '
                                 f'{name!r}, controls {list(controls)}) and a model output '
                                 f'(got {output!r}, outputs {list(model.output_names)})')
        if measured and self.estimator is None:
            raise ValueError('measured_inputs needs a state estimate (estimation on, or '
                             'unmeasured states)')
        return measured

    def _check_band_setpoints(self) -> tuple[tuple[str, str, str, str], ...]:
        """Return the settings' ``band_setpoints`` with their band series, checked."""
        bands = {(lower, upper) for lower, upper, _ in self.mpc.state_bounds.values()}
        zones = sorted(lower[len(COMFORT_SERIES[0]) + 1:] if lower != COMFORT_SERIES[0]
                       else "'' (comfort_min, comfort_max)" for lower, _ in bands)
        out = []
        for control, edge, zone in self.settings.actuation.band_items:
            pair = zone_band_series(zone) if zone else COMFORT_SERIES
            if pair not in bands:
                raise ValueError(f'band_setpoints: {control}={edge}{":" if zone else ""}{zone} '
                                 f'names the band of zone {zone!r} ({pair[0]}, {pair[1]}), '
                                 f"which the controller's forecast does not carry: its bands "
                                 f'are those of the zones {zones}')
            if control in self.plant_control_names:
                raise ValueError(f'band_setpoints: {control!r} is also sent as a model '
                                 f'control ({list(self.plant_control_names)})')
            out.append((control, edge, *pair))
        return tuple(out)

    def _check_setpoint_caps(self) -> tuple[tuple[int, int, str, float], ...]:
        """Return the settings' ``setpoint_caps``, checked: (control, state, lower, offset)."""
        controls = list(self.settings.problem.control_names)
        states = list(self.model.state_names)
        out = []
        for control, state in self.settings.actuation.cap_items.items():
            if control not in controls:
                raise ValueError(f'setpoint_caps: {control!r} is not a control of the MPC '
                                 f'{controls}')
            if state not in self.mpc.state_bounds:
                raise ValueError(f'setpoint_caps: {control}={state} names no zone temperature '
                                 f'with a comfort band (those are '
                                 f'{sorted(self.mpc.state_bounds)})')
            lower, _, offset = self.mpc.state_bounds[state]
            out.append((controls.index(control), states.index(state), lower, float(offset)))
        return tuple(out)

    def _check_supply_floors(self) -> tuple[tuple[int, float], ...]:
        """Return the settings' ``supply_floors``, checked: (control index, floor) each."""
        controls = list(self.settings.problem.control_names)
        bounds = self.settings.problem.control_bounds
        out = []
        for control, floor in self.settings.actuation.supply_floor_items.items():
            if control not in controls:
                raise ValueError(f'supply_floors: {control!r} is not a control of the MPC '
                                 f'{controls}')
            low, high = bounds[controls.index(control)]
            if not low <= floor <= high:
                raise ValueError(f'supply_floors: {control}={floor:g} is outside the '
                                 f"control's limits [{low:g}, {high:g}]")
            out.append((controls.index(control), floor))
        return tuple(out)

    def capped(self, decision: Decision, step_ns: int) -> Decision:
        """
        Return the decision with its zone setpoints between the band and the plan's temperature.

        Settings ``setpoint_caps``, for a decided plan (source 'optimum' or 'plan'): a capped
        control is at most its zone's predicted temperature at the step's end (the state less
        the band's offset, in the band's unit), or the zone's band's lower edge there raised by
        ``band_margin_k`` where the plan expects to fall short of it, and at least that raised
        lower edge at the step's start (the newest forecast for the step's rows, as
        :meth:`band_setpoint_values`): the loop stops where the plan does, still goes for the
        band where the plan expects to miss it, and keeps the band the step starts in as the
        building's own loop would. Every planned interval likewise. Other decisions are
        returned as they are.

        Settings ``supply_floors``: in an interval where a capped setpoint heats (it is at or
        above its zone's planned temperature at the interval's end less
        :data:`HEATING_TOLERANCE_K`: the loop holds or raises the zone), each floored control
        (the loops' supply temperature) is at least its floor.
        """
        found = self._capped_plan(decision)
        if found is None:
            return decision
        plan, states, rows = found
        controls = np.array(decision.controls, dtype=float).reshape(-1)
        found = self._forecast_rows(step_ns, max(rows, 1) + 1, first=0)
        raise_k = self.settings.comfort.band_margin_k
        for control, state, lower, offset in self.setpoint_caps:
            edge = (found[0][lower].to_numpy(dtype=float)[found[1]] + raise_k
                    if found is not None else np.full(max(rows, 1) + 1, -math.inf))
            start, end = edge[:-1], edge[1:]  # each interval's start and end rows
            controls[control] = max(start[0], min(controls[control], max(
                float(decision.predicted_state[state]) - offset, end[0])))
            if rows:
                plan[:, control] = np.maximum(start, np.minimum(
                    plan[:, control], np.maximum(states[:, state] - offset, end)))
        heats = self._heating(controls[None], np.asarray(decision.predicted_state)[None])[0]
        plan_heats = self._heating(plan, states) if rows else np.zeros(0, dtype=bool)
        for control, floor in self.supply_floors:
            if heats:
                controls[control] = max(controls[control], floor)
            plan[plan_heats, control] = np.maximum(plan[plan_heats, control], floor)
        low, high = np.asarray(self.settings.problem.control_bounds, dtype=float).T
        return dataclasses.replace(decision, controls=np.clip(controls, low, high),
                                   plan_controls=np.clip(plan, low, high) if rows else plan)

    def _capped_plan(self, decision: Decision) -> tuple[np.ndarray, np.ndarray, int] | None:
        """
        Return a decision's plan (controls, states) and its rows, where the caps apply.

        None without ``setpoint_caps``, for a decision other than a decided plan (source
        'optimum' or 'plan') and without a predicted state; rows 0 where the plan's controls
        and states do not align (the step alone is capped).
        """
        if not self.setpoint_caps or decision.source not in ('optimum', 'plan') or \
                decision.predicted_state is None:
            return None
        plan = np.array(decision.plan_controls, dtype=float)
        states = np.asarray(decision.plan_states, dtype=float)
        aligned = plan.ndim == 2 and states.ndim == 2 and plan.shape[0] == states.shape[0]
        return plan, states, plan.shape[0] if aligned else 0

    def _heating(self, controls: np.ndarray, states: np.ndarray) -> np.ndarray:
        """
        Return, per row, whether a capped setpoint heats: at least its zone's temperature.

        ``controls`` (rows, nu) capped, ``states`` (rows, nx) the planned states at each
        interval's end; a setpoint within :data:`HEATING_TOLERANCE_K` below its zone's
        temperature (less the band's offset) heats: its loop holds or raises the zone.
        """
        out = np.zeros(len(controls), dtype=bool)
        for control, state, _, offset in self.setpoint_caps:
            out |= controls[:, control] >= states[:, state] - offset - HEATING_TOLERANCE_K
        return out

    def heats_ahead(self, decision: Decision) -> bool | None:
        """
        Return whether a decided plan heats this step or in any planned interval after it.

        With ``setpoint_caps`` and a capped decision (:meth:`capped`, source 'optimum' or
        'plan'): a capped setpoint heats (:meth:`_heating`) this step or in any interval of
        the plan; otherwise None (not known).
        """
        found = self._capped_plan(decision)
        if found is None:
            return None
        plan, states, rows = found
        controls = np.array(decision.controls, dtype=float).reshape(1, -1)
        heats = bool(self._heating(controls, np.asarray(decision.predicted_state)[None])[0])
        return heats or bool(rows and self._heating(plan, states).any())

    def _forecast_rows(self, step_ns: int, rows: int, first: int = 1
                       ) -> tuple[pd.DataFrame, np.ndarray] | None:
        """
        Return the newest forecast for a step and its rows from the step's end (``first`` 1).

        ``first`` 0: from the step's start.
        """
        forecast = self._forecast_for(int(step_ns))
        if forecast is None:
            return None
        stamp, frame = forecast
        index = np.minimum((int(step_ns) - stamp) // self.step_ns + first + np.arange(rows),
                           len(frame) - 1)
        return frame, index

    @property
    def sent_control_names(self) -> tuple[str, ...]:
        """
        Return the names of everything sent every step, as the plant names them.

        :attr:`plant_control_names`, then the band setpoints (settings ``band_setpoints``): the
        order of :meth:`StepOutcome.sent`.
        """
        return (*self.plant_control_names, *(b[0] for b in self.band_setpoints))

    def limit_band_setpoints(self, ranges: Mapping[str, tuple[float | None, float | None]]
                             ) -> None:
        """
        Clip the band setpoints to their plant controls' ranges from now on.

        Parameters
        ----------
        ranges : mapping
            Band setpoint (plant control) -> (min, max) [degC, the band's unit] (None or NaN:
            open), e.g. the plant card's limits; every band setpoint needs one.

        Raises
        ------
        ValueError
            For a band setpoint without a range, or an empty range.

        """
        out = {}
        for control, *_ in self.band_setpoints:
            if control not in ranges:
                raise ValueError(f'band setpoint {control!r} has no range (got ranges of '
                                 f'{sorted(ranges)})')
            low, high = (default if v is None or math.isnan(v) else float(v)
                         for v, default in zip(ranges[control], (-math.inf, math.inf)))
            if not low < high:
                raise ValueError(f'band setpoint {control!r}: empty range [{low:g}, {high:g}]')
            out[control] = (low, high)
        self._band_ranges = out

    def band_setpoint_values(self, step_ns: int, rows: int = 1, heats: bool | None = None
                             ) -> tuple[np.ndarray | None, bool]:
        """
        Return the band setpoints of a step and of the intervals after it, and if released.

        Setting ``band_setpoints``: for a step, the band of the newest forecast for the step
        (:meth:`offer_forecast`) at the row of the step's end (a test case's forecast holds
        there the tightest band over the step), its upper edge less ``band_setpoint_margin_k``
        ('max') or its lower edge plus the margin ('min'), at most to the band's middle,
        clipped to the plant control's range (:meth:`limit_band_setpoints`); the margin
        ``cooling_mode_margin_k`` instead (when set) in cooling mode, a decided plan that heats
        nowhere (``heats`` False). Without a forecast for the step: ``safe_temperature_c``
        (clipped), released.

        Parameters
        ----------
        step_ns : int
            Start of the step [ns].
        rows : int
            The step and the intervals after it (e.g. a plan's).
        heats : bool or None
            Whether the step's plan heats this step or later (:meth:`heats_ahead`; None: not
            known, as heating).

        Returns
        -------
        (ndarray or None, bool)
            Shape (rows, nb) [degC] in the order of the settings (None without band
            setpoints), and whether they are released.

        """
        if not self.band_setpoints:
            return None, False
        ranges = [self._band_ranges.get(b[0], (-math.inf, math.inf))
                  for b in self.band_setpoints]
        low, high = np.array(ranges, dtype=float).T
        found = self._forecast_rows(step_ns, rows)
        if found is None:
            safe = self.settings.supervisor.safe_temperature_c
            return np.clip(np.full((rows, len(ranges)), safe), low, high), True
        frame, index = found
        actuation = self.settings.actuation
        margin = (actuation.cooling_mode_margin_k
                  if heats is False and math.isfinite(actuation.cooling_mode_margin_k)
                  else actuation.band_setpoint_margin_k)
        columns = []
        for _, edge, lower, upper in self.band_setpoints:
            lo = frame[lower].to_numpy(dtype=float)[index]
            hi = frame[upper].to_numpy(dtype=float)[index]
            inward = np.minimum(margin, np.maximum(0.5 * (hi - lo), 0.0))
            columns.append(hi - inward if edge == 'max' else lo + inward)
        return np.clip(np.column_stack(columns), low, high), False

    def _build_supervisor(self) -> SetpointSupervisor:
        p, s = self.settings.problem, self.settings.supervisor
        return SetpointSupervisor(p.control_bounds, p.step_s, self.settings.safe_values,
                                  released=self.settings.released,
                                  max_plan_age_steps=s.max_plan_age_steps,
                                  state_range=self.state_range())

    def _build_actuator(self) -> Actuator:
        p = self.settings.problem
        return Actuator(self.settings.actuation, p.control_bounds, p.step_s)

    def _configure_inputs(self, settings: MpcSettings | None = None) -> None:
        i = (settings or self.settings).inputs
        self._state_gate.max_age_ns = _ns(i.max_state_age_s)
        self._forecast_gate.max_age_ns = _ns(i.max_forecast_age_s)
        for gate in (self._state_gate, self._forecast_gate):
            gate.max_future_ns = _ns(i.max_future_s)
        self._input_wait = InputWait(i.input_wait_s, i.input_deadline_s)

    def update(self, settings: MpcSettings) -> str:
        """
        Apply new settings between solves (deferred while one runs).

        Returns
        -------
        str
            What it took: 'unchanged', 'deferred', or the MPC's 'updated' /
            'rebuilt', with '+supervisor' when the fallback chain was rebuilt
            (the last good plan forgotten).

        Raises
        ------
        ValueError
            If a setting fixed once running changes (see :meth:`MPC.update`).

        """
        fixed = self.settings.fixed_changes(settings)
        if fixed:
            raise ValueError(f'{fixed} cannot change once the controller runs')
        if self._inflight is not None:
            self._pending = settings
            self._configure_inputs(settings)
            return 'deferred'
        return self._apply(settings)

    def _apply(self, settings: MpcSettings) -> str:
        changed = self.settings.changed(settings)
        what = self.mpc.update(settings)
        self._configure_inputs()
        if self.estimator is not None:
            e = self.settings.estimation
            self.estimator.configure(e.measurement_noise_k, e.process_noise_k, e.initial_std_k)
        if any('supervisor' in BY_NAME[n].applies for n in changed if n in BY_NAME):
            self.supervisor = self._build_supervisor()
            what += '+supervisor'
        if any(n == 'control_names' or n in BY_NAME and (BY_NAME[n].group == 'actuation'
                                                         or 'supervisor' in BY_NAME[n].applies)
               for n in changed):
            self.actuator = self._build_actuator()  # (bursts in progress forgotten)
        return what

    # -- inputs ---------------------------------------------------------------------------
    def reject(self, stream: str, rejection: Rejection) -> Rejection:
        """Count a rejection found outside the controller (e.g. a malformed message)."""
        self.rejections.add(stream, rejection)
        return rejection

    def offer_state(self, stamp_ns: int, x: Sequence[float], now_ns: int) -> Rejection | None:
        """
        Offer a measured state (physical units, e.g. [K]) stamped ``stamp_ns``.

        Returns
        -------
        Rejection or None
            Why it was refused (non-finite, implausible, wrong length, stamp
            stale, in the future or backwards), or None when it was taken.

        """
        names = self.model.state_names
        values = np.asarray(x, dtype=float).reshape(-1)
        if values.size != len(names):
            return self.reject('state', Rejection('length', f'state has {values.size} values, '
                                                  f'expected {len(names)} ({list(names)})'))
        if self.estimator is not None:  # only the measured states count
            return self._measure(stamp_ns, {n: float(values[names.index(n)])
                                            for n in self.estimator.measured}, now_ns)
        rejection = self._range_rejection(dict(zip(names, values)))
        rejection = rejection or self._state_gate.check(stamp_ns, now_ns)
        if rejection:
            return self.reject('state', rejection)
        self._state_gate.accept(stamp_ns, now_ns)
        self._states[int(stamp_ns)] = values.copy()
        _trim(self._states)
        return None

    def _range_rejection(self, values: Mapping[str, float]) -> Rejection | None:
        """Return the first state outside its plausible range (:meth:`state_range`)."""
        names = self.model.state_names
        low, high = self.state_range()
        return next((r for r in (check_series(name, [value], low[names.index(name)],
                                              high[names.index(name)])
                                 for name, value in values.items()) if r), None)

    def _measure(self, stamp_ns: int, measured: Mapping[str, float], now_ns: int,
                 applied: Mapping[str, float] | None = None,
                 outputs: Mapping[str, float] | None = None) -> Rejection | None:
        """
        Correct the state estimate with the measured states at ``stamp_ns``.

        ``outputs`` are the measured outputs of the last step (by name): the model inputs of
        the settings' ``measured_inputs`` come from them.
        """
        rejection = (self._range_rejection(measured)
                     or self._state_gate.check(stamp_ns, now_ns))
        if rejection:
            return self.reject('state', rejection)
        stamp_ns = int(stamp_ns)
        estimator = self.estimator
        last = estimator.estimate
        if last is not None and _ns(last.t_s) == stamp_ns:
            self._state_gate.accept(stamp_ns, now_ns)  # a repeat (heartbeat): taken already
            return None
        inputs = None
        if last is not None:
            inputs, why = self._inputs_between(_ns(last.t_s), stamp_ns, applied or {},
                                               outputs or {}, last.x)
            if inputs is None:
                logger.warning('state estimate restarted at %.0f s: %s', stamp_ns / NS_PER_S,
                               why)
                estimator.reset()
        try:
            estimate = estimator.update(stamp_ns / NS_PER_S, measured, inputs)
        except ModelValueError as exc:
            logger.warning('state estimate restarted at %.0f s: the prediction failed (%s)',
                           stamp_ns / NS_PER_S, exc)
            estimator.reset()
            estimate = estimator.update(stamp_ns / NS_PER_S, measured)
        self._state_gate.accept(stamp_ns, now_ns)
        self._states[stamp_ns] = estimate.x.copy()
        self._estimates[stamp_ns] = estimate
        _trim(self._states)
        _trim(self._estimates)
        return None

    def _observe_history(self, force: bool = False) -> None:
        """
        Observe a first state's warm-up step by step, then the state itself.

        Each history time is observed as a later state would be: the measured states at that
        time, the model inputs over the interval before it from the outputs measured over it
        (the history's means, as ``mean_<output>``: settings ``measured_inputs``) and the
        forecast that covers it. Waits for a forecast that covers the whole warm-up (its
        history samples: :meth:`offer_forecast`), unless ``force``d (then an interval not
        covered restarts the estimate, logged).
        """
        h = self._history
        times = [h.measure.stamp_ns + _ns(o) for o in h.offsets_s]
        covered = all(any(s <= t and (t - s) // self.step_ns < len(f)
                          for s, f in self._forecasts.items()) for t in times[:-1])
        if not covered and not force:
            return
        self._history = None
        estimator = self.estimator
        measured = estimator.measured
        names = list(h.state_names)
        m = len(times)
        states = np.asarray(h.state_values, dtype=float).reshape(len(names), m)
        means = np.asarray(h.output_values, dtype=float).reshape(len(h.output_names), m)
        stamp, outputs_now = h.measure.stamp_ns, h.measure.outputs
        if times[-1] == stamp and not outputs_now:  # the state's step: the history's last
            outputs_now = {MEAN_PREFIX + n: float(means[j, -1])
                           for j, n in enumerate(h.output_names)}
        for k, t in enumerate(times):
            if t >= stamp:  # (the state itself: below)
                break
            values = {n: float(states[names.index(n), k]) for n in measured}
            last = estimator.estimate
            inputs = None
            if last is not None and _ns(last.t_s) < t:
                outputs = {MEAN_PREFIX + n: float(means[j, k])
                           for j, n in enumerate(h.output_names)}
                inputs, why = self._inputs_between(_ns(last.t_s), t, {}, outputs, last.x)
                if inputs is None:
                    logger.warning('state estimate restarted at %.0f s of the warm-up: %s',
                                   t / NS_PER_S, why)
                    estimator.reset()
            elif last is not None:
                continue
            estimator.update(t / NS_PER_S, values, inputs)
        self._measure(*h.measure._replace(outputs=outputs_now))

    def _inputs_between(self, t0_ns: int, t1_ns: int, applied: Mapping[str, float],
                        outputs: Mapping[str, float] | None = None,
                        x0: np.ndarray | None = None) -> tuple[pd.DataFrame | None, str]:
        """
        Return the model inputs over [t0, t1) by interval start [s], or None and why not.

        One interval per control step touched: the controls decided for the step (the applied
        ones of a ``ZoneState`` for the last step), the disturbances of the newest forecast that
        covered the step; for the last step, the inputs measured by ``outputs`` (settings
        ``measured_inputs``; a control measured through a model output is found from the model
        at ``x0`` and the interval's other inputs).
        """
        controls = self.settings.problem.control_names
        starts = [t0_ns] + list(range((t0_ns // self.step_ns + 1) * self.step_ns, t1_ns,
                                      self.step_ns))
        outputs = outputs or {}
        measured = self._measured_values(outputs)
        by_effect = [n for n, (o, model_output) in self.measured_inputs.items()
                     if model_output and o in outputs]  # (found once the others are known)
        rows = []
        for k, start in enumerate(starts):
            step = (start // self.step_ns) * self.step_ns
            last = k == len(starts) - 1
            if last and (measured or by_effect) and all(n in measured or n in by_effect
                                                        for n in controls):
                u = {n: measured[n] for n in controls if n in measured}
            elif last and applied and set(applied) == set(controls):
                u = dict(applied)
            elif step in self._decided:
                u = dict(zip(controls, self._decided[step]))
            else:
                return None, f'no control decided for the step at {step / NS_PER_S:.0f} s'
            if last:
                u.update({n: v for n, v in measured.items() if n not in controls})
            stamps = [s for s in self._forecasts
                      if s <= start and (start - s) // self.step_ns < len(self._forecasts[s])]
            if not stamps:
                return None, f'no forecast covered the step at {step / NS_PER_S:.0f} s'
            frame = self._forecasts[max(stamps)]
            row = frame.iloc[int((start - max(stamps)) // self.step_ns)]
            missing = [n for n in self.model.input_names if n not in u and n not in row.index
                       and not (last and n in by_effect)]
            if missing:
                return None, f'the forecast lacks the model inputs {missing}'
            values = [float(u[n]) if n in u else float(row[n]) if n in row.index else math.nan
                      for n in self.model.input_names]
            if last and by_effect:
                values = self._controls_by_effect(values, outputs, x0, (t1_ns - start) / NS_PER_S)
            rows.append(values)
        return pd.DataFrame(rows, columns=list(self.model.input_names),
                            index=pd.Index([s / NS_PER_S for s in starts], name='time_s')), ''

    def _measured_values(self, outputs: Mapping[str, float]) -> dict[str, float]:
        """Return the inputs measured directly by ``outputs`` (``input=output`` items)."""
        return {n: float(outputs[o]) for n, (o, effect) in self.measured_inputs.items()
                if not effect and o in outputs}

    def _controls_by_effect(self, values: list[float], outputs: Mapping[str, float],
                            x0: np.ndarray | None, span_s: float) -> list[float]:
        """
        Return the inputs with the controls measured through a model output filled in.

        The model output is taken linear in the control over the interval: the control is where
        its value at the control's bounds, interpolated, meets the measured output (at least the
        lower bound; not capped above).
        """
        names = self.model.input_names
        x = (np.asarray(x0, dtype=float).reshape(1, -1) if x0 is not None
             else np.zeros((1, len(self.model.state_names))))
        bounds = dict(zip(self.settings.problem.control_names,
                          self.settings.problem.control_bounds))
        out = list(values)
        for name, (output, model_output) in self.measured_inputs.items():
            if not model_output or output not in outputs:
                continue
            low, high = bounds[name]
            j = names.index(name)
            ends = []
            for value in (low, high):
                u = np.array(out, dtype=float)
                u[j] = value
                u = np.nan_to_num(u)  # (other controls by effect: not in this output)
                _, y = self.model.simulate_intervals(x, u[None, :], span_s)
                ends.append(float(y[0, self.model.output_names.index(model_output)]))
            gain = ends[1] - ends[0]
            share = (float(outputs[output]) - ends[0]) / gain if gain else 0.0
            out[j] = low + max(share, 0.0) * (high - low)
        return out

    @property
    def estimate(self) -> Estimate | None:
        """Return the newest state estimate, or None (no estimation, or none yet)."""
        return None if self.estimator is None else self.estimator.estimate

    @property
    def measured_states(self) -> tuple[str, ...]:
        """Return the states taken from measurements (all of them without estimation)."""
        return (self.estimator.measured if self.estimator is not None
                else tuple(self.model.state_names))

    @property
    def plant_control_names(self) -> tuple[str, ...]:
        """
        Return the controls as the plant names them, in the model's order.

        Settings ``plant_controls`` (e.g. ``d=Y``: the model's duty ``d`` is the plant's
        modulation ``Y``); a control not named there keeps its model name. Setpoints go out
        with these names; the applied controls of a zone state may come with them.
        """
        names = self.settings.actuation.plant_names
        return tuple(names.get(c, c) for c in self.settings.problem.control_names)

    def offer_named_state(self, stamp_ns: int, state_names: Sequence[str],
                          state_values: Sequence[float], now_ns: int, *,
                          output_names: Sequence[str] = (), output_values: Sequence[float] = (),
                          control_names: Sequence[str] = (),
                          control_values: Sequence[float] = (),
                          history: Sequence[Sequence[Any]] = ((), (), (), ())
                          ) -> Rejection | None:
        """
        Offer a measured state as named values, with the measured outputs and applied controls.

        Names in any order, states in SI units (e.g. [K]); the controls are those applied over the
        last step, by model or plant name (:attr:`plant_control_names`); ``history`` the
        warm-up a first state may carry (offsets [s], state values, output names, output
        values: the fields of a ``ZoneState``): with estimation, it is observed step by step
        like later states, once a forecast covers it (its ``history_steps``,
        :meth:`offer_forecast`).

        The whole message is checked before any of it is used or copied: the array lengths
        against the model's dimensions (:func:`~mshoot_core.safety.zone_state_caps`), the names
        and values (:func:`~mshoot_core.safety.check_zone_state`: exactly the model's states,
        finite plausible outputs, applied controls among the controller's and near its bounds),
        the history (:func:`~mshoot_core.safety.check_history`); then the state goes to
        :meth:`offer_state` in the model's order. With estimation the states must be
        among the model's and hold the measured ones (the others are ignored); the applied
        controls enter the prediction over the last step. The applied band setpoints (settings
        ``band_setpoints``: sent, not model inputs) may come with them and are left out.
        """
        controls = self.settings.problem.control_names
        model_names = dict(zip(self.plant_control_names, controls))
        control_names = [model_names.get(n, n) for n in control_names]
        sent = len(controls) + len(self.band_setpoints)
        fields = dict(zip(('state_names', 'state_values', 'output_names', 'output_values',
                           'control_names', 'control_values', 'history_offsets_s',
                           'history_state_values', 'history_output_names',
                           'history_output_values'),
                          (state_names, state_values, output_names, output_values,
                           control_names, control_values, *history)))
        rejection = check_lengths('zone state', {k: len(v) for k, v in fields.items()},
                                  zone_state_caps(len(self.model.state_names), sent))
        if rejection:
            return self.reject('state', rejection)
        bands = {b[0] for b in self.band_setpoints}
        if bands and len(control_names) == len(control_values):  # else check_zone_state says
            kept = [k for k, name in enumerate(control_names) if name not in bands]
            control_names = [control_names[k] for k in kept]
            control_values = [control_values[k] for k in kept]
        ranges = applied_control_ranges(controls, self.settings.problem.control_bounds)
        if self.estimator is not None:
            measured = self.estimator.measured
            rejection = (check_named('state', state_names, state_values,
                                     allowed=self.model.state_names)
                         or check_zone_state((), (), output_names, output_values,
                                             control_names, control_values,
                                             allowed_controls=controls, control_ranges=ranges)
                         or check_history(state_names, *history))
            missing = [n for n in measured if n not in state_names]
            if rejection is None and missing:
                rejection = Rejection('names', f'state: the measured states {missing} are '
                                      f'missing (got {list(state_names)})')
            if rejection:
                return self.reject('state', rejection)
            values = dict(zip(state_names, map(float, state_values)))
            measure = _Measurement(int(stamp_ns), {n: values[n] for n in measured}, int(now_ns),
                                   dict(zip(control_names, map(float, control_values))),
                                   dict(zip(output_names, map(float, output_values))))
            if self._history is not None:  # a later state: the warm-up as far as covered
                self._observe_history(force=True)
            if len(history[0]) and self.estimator.estimate is None:
                rejection = self._range_rejection(measure.measured) or self._state_gate.check(
                    stamp_ns, now_ns)
                if rejection:
                    return self.reject('state', rejection)
                self._history = _History(measure, state_names, *history)
                self._observe_history()
                return None
            return self._measure(*measure)
        rejection = (check_zone_state(state_names, state_values, output_names, output_values,
                                      control_names, control_values,
                                      expected_states=self.model.state_names,
                                      allowed_controls=controls, control_ranges=ranges)
                     or check_history(state_names, *history))
        if rejection:
            return self.reject('state', rejection)
        return self.offer_state(stamp_ns, reorder(state_names, state_values,
                                                  self.model.state_names), now_ns)

    def is_repeat_of_decided_step(self, stamp_ns: int) -> bool:
        """
        Return True when a state stamped ``stamp_ns`` was already taken and its step decided.

        Such a state is a heartbeat of the same state (the decision may have been lost: send it
        again).
        """
        return (int(stamp_ns) in self._states and self._last_step_ns == int(stamp_ns)
                and self._inflight is None)

    @property
    def forecast_required(self) -> tuple[str, ...]:
        """
        Series a forecast must carry.

        The model's disturbances (but those assumed, see ``assumed_inputs``) and the comfort band.
        """
        return tuple(c for c in self.mpc.forecast_columns if c not in self.assumed_inputs)

    @property
    def forecast_known(self) -> tuple[str, ...]:
        """
        Every series name a forecast may carry.

        The required ones, the assumed inputs, the comfort band and the energy price (``price``
        [currency/kWh]).
        """
        return self._known_with(self.forecast_required)

    def _known_with(self, required: tuple[str, ...]) -> tuple[str, ...]:
        """:attr:`forecast_known` given :attr:`forecast_required`."""
        names = [*required, *self.assumed_inputs, *COMFORT_SERIES, PRICE_SERIES]
        return tuple(dict.fromkeys(names))

    def offer_forecast(self, stamp_ns: int, step_s: float,
                       series: Mapping[str, Sequence[float]], now_ns: int,
                       history_steps: int = 0) -> Rejection | None:
        """
        Offer a forecast: samples every ``step_s`` [s] from ``stamp_ns`` on, by name.

        The series are the model's disturbances (e.g. Tout [degC], solrad [W/m2], occ),
        comfort_min, comfort_max [degC] and optionally price [currency/kWh]
        (:attr:`forecast_required`, :attr:`forecast_known`). Its first ``history_steps``
        samples lie before ``stamp_ns`` (a warm-up's: the inputs a first state's history is
        observed with, see :meth:`offer_named_state`); the stamp is the forecast's.

        Returns
        -------
        Rejection or None
            Why it was refused, or None when it was taken.

        """
        required = self.forecast_required  # (once: forecast_known takes it too)
        known = self._known_with(required)
        samples = len(next(iter(series.values()), ()))
        if not 0 <= int(history_steps) < max(samples, 1):
            return self.reject('forecast', Rejection(
                'out_of_range', f'history_steps must be >= 0 and below the {samples} samples, '
                f'got {history_steps}'))
        history_steps = int(history_steps)
        rejection = (check_forecast(step_s, series,
                                    expected_step_s=self.settings.problem.step_s,
                                    required=required, known=known)
                     or self._forecast_gate.check(stamp_ns, now_ns))
        if rejection is None:
            names = list(series)
            n = len(series[names[0]])
            try:
                values = np.column_stack([np.asarray(series[name], dtype=float).reshape(n)
                                          for name in names])
            except ValueError:
                rejection = Rejection('length', f'forecast series differ in length from the '
                                      f'{n} samples of {names[0]!r}')
            else:
                bad = [names[j] for j in np.flatnonzero(~np.isfinite(values).all(axis=0))]
                if bad:
                    rejection = Rejection('non_finite', f'forecast series {bad} hold '
                                          'non-finite values')
        if rejection:
            return self.reject('forecast', rejection)
        extra = [name for name in self.assumed_inputs if name not in series]
        if extra:
            values = np.column_stack([values] + [np.full(n, float(self.assumed_inputs[name]))
                                                 for name in extra])
        first_ns = int(stamp_ns) - history_steps * self.step_ns
        frame = pd.DataFrame(values, columns=column_labels((*names, *extra)), index=pd.Index(
            first_ns / NS_PER_S + np.arange(n) * float(step_s), name='time_s'))
        self._forecast_gate.accept(stamp_ns, now_ns)
        self._forecasts[int(stamp_ns)] = frame.iloc[history_steps:]
        if history_steps:  # (the past: for observing a history, never for planning)
            self._forecasts[first_ns] = frame
        _trim(self._forecasts)
        if self._history is not None:
            self._observe_history()
        return None

    def _state_stamp(self, step_ns: int) -> int | None:
        """Return the stamp [ns] of the (newest fresh) state a step is planned from, or None."""
        oldest = step_ns - self._state_gate.max_age_ns
        stamps = [s for s in self._states if oldest <= s < step_ns + self.step_ns]
        return max(stamps) if stamps else None

    def _forecast_for(self, step_ns: int) -> tuple[int, pd.DataFrame] | None:
        oldest = step_ns - self._forecast_gate.max_age_ns
        stamps = [s for s in self._forecasts if oldest <= s <= step_ns]
        return (max(stamps), self._forecasts[max(stamps)]) if stamps else None

    def _missing(self, step_ns: int, state: Any, forecast: Any) -> str:
        """One sentence on which input of a step is missing or stale."""
        parts = []
        i = self.settings.inputs
        for name, have, stamps, age in (
                ('zone state', state, self._states, i.max_state_age_s),
                ('forecast', forecast, self._forecasts, i.max_forecast_age_s)):
            if have is not None:
                continue
            older = [s for s in stamps if s < step_ns]
            if older:
                parts.append(f'the {name} is stale (newest {(step_ns - max(older)) / NS_PER_S:g}'
                             f' s before the step, max age {age:g} s)')
            else:
                parts.append(f'no {name} for the step')
        return ' and '.join(parts)

    # -- deciding -------------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        """Return True while a solve runs."""
        return self._inflight is not None

    @property
    def last_step_ns(self) -> int | None:
        """Return the newest step decided or being solved [ns] (None before the first)."""
        return self._last_step_ns

    def poll(self, now_ns: int, steady_ns: int | None = None) -> list[StepOutcome]:
        """
        Decide what is due at ``now_ns`` (see the module docstring).

        Parameters
        ----------
        now_ns : int
            The controller's clock [ns] (simulated or real time).
        steady_ns : int, optional
            A steady wall clock [ns] (default :func:`time.monotonic_ns`):
            waits and budgets are measured on it.

        Returns
        -------
        list of StepOutcome
            The steps decided by this call, in order (usually none or one).

        """
        outcomes = self._poll(int(now_ns), time.monotonic_ns() if steady_ns is None
                              else int(steady_ns))
        for outcome in outcomes:  # what the building gets: the prediction of the estimate
            self._decided[outcome.step_ns] = np.asarray(outcome.decision.controls,
                                                        dtype=float).reshape(-1)
        _trim(self._decided)
        return outcomes

    def _poll(self, now_ns: int, steady_ns: int) -> list[StepOutcome]:
        outcomes: list[StepOutcome] = []
        self._collect(outcomes, steady_ns)
        job = self._inflight
        budget = self.settings.supervisor.time_budget_s
        if job is not None and not job.fallback_given and budget > 0:
            elapsed = (steady_ns - job.started_ns) / NS_PER_S
            if elapsed >= budget:  # the solver did not stop at its deadline (e.g. a hung model)
                job.fallback_given = True
                outcomes.append(self._fallback(job.step_ns, 'budget', f'time budget exceeded '
                                               f'({budget:g} s)', elapsed, job.x0,
                                               x0_std=job.x0_std))
        step = (now_ns // self.step_ns) * self.step_ns
        last = self._last_step_ns
        if last is not None and step < last and job is None:
            self._clock_went_back(step)
            last = None
        if last is not None and step <= last:
            return outcomes
        waited_s, waited_clock_s = self._due(step, now_ns, steady_ns)
        if job is not None:
            elapsed = (steady_ns - job.started_ns) / NS_PER_S
            limit = budget or self.settings.inputs.input_wait_s
            if job.fallback_given and waited_s >= limit and step > job.step_ns:
                self._last_step_ns = step
                outcomes.append(self._fallback(
                    step, 'budget', f'the solve for {job.step_ns / NS_PER_S:.0f} s is still '
                    f'running after {elapsed:.3f} s', waited_s, None))
            return outcomes
        if self._pending is not None:
            self._apply(self._pending)
            self._pending = None
        state_stamp = self._state_stamp(step)
        state = None if state_stamp is None else self._states[state_stamp]
        forecast = self._forecast_for(step)
        if state is None or forecast is None:
            if self._input_wait.overdue(waited_s, waited_clock_s):
                self._last_step_ns = step
                outcomes.append(self._fallback(
                    step, 'inputs_missing',
                    f'{self._missing(step, state, forecast)} after {waited_s:.2f} s',
                    waited_s, None))
            return outcomes
        stamp, frame = forecast
        offset = (step - stamp) // self.step_ns
        horizon = self.mpc.horizon_steps
        if len(frame) < offset + horizon + 1:
            logger.debug('forecast covers %d of the %d samples needed: the last one is '
                         'repeated', len(frame) - offset, horizon + 1)
        window = (frame if offset == 0 and len(frame) == horizon + 1 else
                  forecast_window(frame, int(min(offset, len(frame) - 1)), horizon))
        self._last_step_ns = step
        estimate = self._estimates.get(state_stamp)  # None: the states are not estimated
        std = None if estimate is None else estimate.std
        self._dispatch(step, state, self._with_margin(step, window, estimate, state),
                       steady_ns, std)
        self._collect(outcomes, time.monotonic_ns())
        return outcomes

    def _with_margin(self, step_ns: int, window: pd.DataFrame, estimate: Estimate | None,
                     state: np.ndarray | None = None) -> pd.DataFrame:
        """
        Return the forecast window with the comfort band narrowed for an uncertain state.

        Every band the plan keeps (:meth:`_bands`: the one band, or each zone's own) is
        narrowed alike, by the margins of the states it bounds (the largest of them). The
        lower edge raised by ``band_margin_k``; then, with a ``forecast_uncertainty``,
        both edges moved in by ``forecast_margin_std`` standard deviations of the largest
        bounded state that the forecast errors cause along the plan from ``state``
        (:func:`mshoot_core.forecast_margin.forecast_error_std`, controls held as below), at
        most to the band's middle: an error can leave the zone too cold or too warm.

        Back-off by ``comfort_margin_std`` standard deviations of the predicted zone
        temperatures (the largest bounded state's) at each row: the estimate's covariance
        propagated over the horizon (:meth:`StateEstimator.predicted_std`, controls held at the
        last decided ones, disturbances as forecast), on each side, at most to the band's
        middle. Row 0 is the estimate's own std; the unmeasured states' uncertainty reaches the
        zone temperature from row 1 on. If the model's prediction fails (non-finite), the
        estimate's own std at every row, with a logged warning.
        """
        bands = self._bands(window)
        if not bands:
            return window
        raise_k = self.settings.comfort.band_margin_k
        if raise_k > 0:  # the lower edges raised
            window = window.copy()
            for lower, upper in bands:
                window[lower] = window[lower] + raise_k
                window[upper] = np.maximum(window[upper], window[lower])
        if self._error_processes and state is not None:
            window = self._with_forecast_margin(step_ns, window, state, bands)
        z = self.settings.estimation.comfort_margin_std
        if estimate is None or z <= 0:
            return window
        try:
            std = self.estimator.predicted_std(self._held_inputs(step_ns, window),
                                               estimate=estimate)
        except ModelValueError as exc:  # the estimate's own std over the whole horizon
            logger.warning("comfort back-off at %.0f s from the estimate's std only: the "
                           'prediction failed (%s)', step_ns / NS_PER_S, exc)
            std = estimate.std[None, :]
        return _narrowed(window, bands, z * std)

    def _bands(self, window: pd.DataFrame) -> dict[tuple[str, str], list[int]]:
        """
        Return the comfort bands the plan keeps: (lower, upper) series -> the states they bound.

        One band for every zone temperature, or a zone's own (the MPC's ``state_bounds``);
        those the window carries.
        """
        names = self.model.state_names
        bands: dict[tuple[str, str], list[int]] = {}
        for state, (lower, upper, _) in self.mpc.state_bounds.items():
            if lower in window and upper in window:
                bands.setdefault((lower, upper), []).append(names.index(state))
        return bands

    @property
    def _error_processes(self) -> list:
        """Return the forecast errors the plan allows for (settings; empty: none)."""
        from mshoot_core.forecast_margin import error_processes
        c = self.settings.comfort
        if c.forecast_uncertainty == 'none' or c.forecast_margin_std <= 0:
            return []
        return error_processes(c.error_kinds, c.forecast_uncertainty, self.model.input_names)

    def _with_forecast_margin(self, step_ns: int, window: pd.DataFrame, state: np.ndarray,
                              bands: dict[tuple[str, str], list[int]]) -> pd.DataFrame:
        """Return the window with the band narrowed for the forecast errors."""
        from mshoot_core.forecast_margin import forecast_error_std
        try:
            std = forecast_error_std(self.model, state, self._held_inputs(step_ns, window),
                                     self.settings.problem.step_s, self._error_processes,
                                     step_ns / NS_PER_S)
        except ModelValueError as exc:
            logger.warning('no forecast margin at %.0f s: the prediction failed (%s)',
                           step_ns / NS_PER_S, exc)
            return window
        return _narrowed(window, bands, self.settings.comfort.forecast_margin_std * std)

    def _held_inputs(self, step_ns: int, window: pd.DataFrame) -> np.ndarray:
        """
        Return the model inputs over the window's intervals, shape (H, nu).

        Disturbances from the window; controls held at the last decided ones (before the
        first decision, at their lower bounds).
        """
        problem = self.settings.problem
        earlier = [s for s in self._decided if s < step_ns]
        held = (self._decided[max(earlier)] if earlier else
                np.array([lo for lo, _ in problem.control_bounds], dtype=float))
        controls = dict(zip(problem.control_names, held))
        rows = len(window) - 1
        return np.column_stack([np.full(rows, float(controls[n])) if n in controls
                                else window[n].to_numpy(dtype=float)[:rows]
                                for n in self.model.input_names])

    def _due(self, step: int, now_ns: int, steady_ns: int) -> tuple[float, float]:
        """How long the step has been due: (wall time, clock time) [s]."""
        if self._due_since is None or self._due_since[0] != step:
            self._due_since = (step, steady_ns, now_ns)
        return ((steady_ns - self._due_since[1]) / NS_PER_S,
                (now_ns - self._due_since[2]) / NS_PER_S)

    def _clock_went_back(self, step: int) -> None:
        logger.warning('the clock went back from step %.0f s to %.0f s (a restarted '
                       'simulation?): inputs, plan and warm start forgotten',
                       (self._last_step_ns or 0) / NS_PER_S, step / NS_PER_S)
        self._states.clear()
        self._forecasts.clear()
        self._decided.clear()
        self._estimates.clear()
        if self.estimator is not None:
            self.estimator.reset()
        for gate in (self._state_gate, self._forecast_gate):
            gate.reset()
        self.supervisor.reset()
        self.mpc.reset()
        self._last_step_ns = None

    def _dispatch(self, step_ns: int, x0: np.ndarray, window: pd.DataFrame,
                  steady_ns: int, x0_std: np.ndarray | None = None) -> None:
        budget = self.settings.supervisor.time_budget_s
        deadline = time.perf_counter() + budget if budget > 0 else None
        t_s = step_ns / NS_PER_S
        if self.executor is None:
            future: concurrent.futures.Future = concurrent.futures.Future()
            self._inflight = _Solve(step_ns, x0.copy(), steady_ns, future, x0_std=x0_std)
            try:
                future.set_result(self.mpc.solve(x0, t_s, window, deadline=deadline))
            except Exception as exc:  # noqa: BLE001 - a failed solve is a decision
                future.set_exception(exc)
            return
        future = self.executor.submit(self.mpc.solve, x0, t_s, window, deadline)
        self._inflight = _Solve(step_ns, x0.copy(), steady_ns, future, x0_std=x0_std)
        if self.on_solve_done is not None:
            callback = self.on_solve_done
            future.add_done_callback(lambda _: callback())

    def _collect(self, outcomes: list[StepOutcome], steady_ns: int) -> None:
        """Collect the outcome of a finished solve, if there is one."""
        job = self._inflight
        if job is None or not job.future.done():
            return
        self._inflight = None
        elapsed = (steady_ns - job.started_ns) / NS_PER_S
        step_s = job.step_ns / NS_PER_S
        try:
            result = job.future.result()
        except Exception as exc:  # noqa: BLE001 - a model error is a fallback, not a crash
            if job.fallback_given:
                logger.error('solve for %.0f s failed after its fallback was given: %s: %s',
                             step_s, type(exc).__name__, exc)
            else:
                outcomes.append(self._fallback(job.step_ns, 'solve_failed', f'solve failed: '
                                               f'{type(exc).__name__}: {exc}', elapsed, job.x0,
                                               x0_std=job.x0_std))
            return
        self.results[job.step_ns] = result
        _trim(self.results, self.history_length)
        budget = self.settings.supervisor.time_budget_s
        if job.fallback_given:
            logger.warning('solve for %.0f s finished after its time budget (%.3f s): result '
                           'not used, warm start kept', step_s, result.solve_time_s)
            return
        if getattr(result, 'budget_exceeded', False) or (budget > 0 and
                                                         result.solve_time_s > budget):
            outcomes.append(self._fallback(job.step_ns, 'budget', f'time budget exceeded '
                                           f'({budget:g} s): solver stopped after '
                                           f'{result.nit} iterations', result.solve_time_s,
                                           job.x0, result, x0_std=job.x0_std))
            return
        decision = self.supervisor.review(
            step_s, result, accept_unconverged=self.settings.supervisor.on_failure == 'plan')
        outcomes.append(self._actuate(StepOutcome(job.step_ns, decision, result,
                                                  result.solve_time_s, job.x0, job.x0_std)))

    def _actuate(self, outcome: StepOutcome) -> StepOutcome:
        """
        Return the outcome with its schedule within the step (settings ``actuation``).

        The decision's zone setpoints are capped first (:meth:`capped`, settings
        ``setpoint_caps``). A decided plan (this step's or the last good one's) goes through
        the actuator, with the plan's next controls and the zone temperature the step started
        from; a safe setpoint is held, and the bursts in progress are forgotten. Without a zone
        temperature a setpoint cannot be sent: the decision's controls are held (logged).
        """
        decision = self.capped(outcome.decision, outcome.step_ns)
        bands, released = self.band_setpoint_values(
            outcome.step_ns, max(np.shape(decision.plan_controls)[0], 1),
            self.heats_ahead(decision))
        outcome = dataclasses.replace(outcome, decision=decision, band_values=bands,
                                      band_released=released)
        controls = np.asarray(decision.controls, dtype=float).reshape(-1)
        zones = [self.model.state_names.index(s) for s in self.mpc.state_bounds]
        zone_k = (float(outcome.x0[zones[0]]) if outcome.x0 is not None and zones else None)
        if decision.source == 'safe' or (self.settings.actuation.actuation_send == 'setpoint'
                                         and zone_k is None):
            if decision.source != 'safe':
                logger.warning('step %.0f s: no zone temperature to send a setpoint from: the '
                               'controls are held', outcome.t_s)
            self.actuator.reset()
            return dataclasses.replace(outcome, schedule=Schedule(np.zeros(1), controls[None]))
        plan = np.asarray(decision.plan_controls, dtype=float)
        following = plan[1] if plan.ndim == 2 and plan.shape[0] > 1 else None
        return dataclasses.replace(outcome, schedule=self.actuator.schedule(
            controls, following, zone_k))

    def _fallback(self, step_ns: int, code: str, reason: str, waited_s: float,
                  x0: np.ndarray | None, result: MpcResult | None = None, *,
                  x0_std: np.ndarray | None = None) -> StepOutcome:
        decision = self.supervisor.fallback(step_ns / NS_PER_S, code, reason)
        return self._actuate(StepOutcome(step_ns, decision, result, waited_s, x0, x0_std))

    def hand_back(self, now_ns: int) -> StepOutcome:
        """
        Return the safe setpoint for the current step, when the controller stops controlling.

        The controller hands the building back to its own control; no further steps are decided
        until the clock passes this one.
        """
        step = (int(now_ns) // self.step_ns) * self.step_ns
        self._last_step_ns = max(step, self._last_step_ns or step)
        if self._inflight is not None:  # its result will only warm the next start
            self._inflight.fallback_given = True
        decision = self.supervisor.safe(step / NS_PER_S, 'deactivated', 'the controller was '
                                        f'deactivated: {self.supervisor.last_link}, then no '
                                        'more setpoints (the building is back on its own '
                                        'control)')
        return self._actuate(StepOutcome(step, decision, None, 0.0, None))

    def close(self) -> None:
        """Wait for a solve in flight and drop it."""
        if self._inflight is not None:
            concurrent.futures.wait([self._inflight.future])
            self._inflight = None


def controller_for(model: Model, settings: MpcSettings | None = None,
                   **kwargs: Any) -> Controller:
    """
    Build a controller of ``model`` with its controls and zone temperatures.

    See :func:`~mshoot_core.models.registry.control_interface`: the settings' ``control_names``
    and ``controls`` (units, limits, safe values, switches: :mod:`mshoot_core.controls`) and the
    MPC's comfort-bounded states follow the model.

    Parameters
    ----------
    model : Model
        The control model.
    settings : MpcSettings, optional
        Every other setting (default: the defaults).
    **kwargs
        Passed to :class:`Controller` (executor, assumed_inputs, ...).

    """
    interface = control_interface(model)
    settings = (settings or MpcSettings()).replace(
        control_names=interface.control_names,
        controls=model_controls(model, interface.control_names))
    return Controller(model, settings, state_bounds=interface.state_bounds, **kwargs)


def state_scaling(settings: MpcSettings | None, states: int) -> Scaling | None:
    """Return the states' fixed normalisation of the settings, or None (from the bounds)."""
    p = (settings or MpcSettings()).problem
    if math.isnan(p.state_offset):
        return None
    return Scaling(np.full(states, p.state_offset), np.full(states, p.state_scale))


def _ns(seconds: float) -> int:
    return int(round(float(seconds) * NS_PER_S))


def _narrowed(window: pd.DataFrame, bands: Mapping[tuple[str, str], Sequence[int]],
              std: np.ndarray) -> pd.DataFrame:
    """
    Return a copy of the window with each band's edges moved in by a margin [K] per row.

    ``std`` holds a margin per row and state, shape (rows or 1, states): a band's margin is the
    largest of the states it bounds. At most to the band's middle.
    """
    out = window.copy()
    std = np.asarray(std, dtype=float)
    for (lower, upper), states in bands.items():
        margin = std[:, list(states)].max(axis=1)
        half = 0.5 * (out[upper] - out[lower]).to_numpy()
        out[lower] = out[lower] + np.minimum(margin, half)
        out[upper] = out[upper] - np.minimum(margin, half)
    return out


class _Measurement(NamedTuple):
    """
    A state's measurement: the arguments of ``Controller._measure``.

    Its stamp and the time it came [ns], the measured states, the controls applied over the
    last step and the outputs measured over it (by name, physical units).
    """

    stamp_ns: int
    measured: Mapping[str, float]
    now_ns: int
    applied: Mapping[str, float]
    outputs: Mapping[str, float]


@dataclasses.dataclass
class _History:
    """A first state (its measurement) and its warm-up."""

    measure: _Measurement
    state_names: Sequence[str]
    offsets_s: Sequence[float]
    state_values: Sequence[float]
    output_names: Sequence[str] = ()
    output_values: Sequence[float] = ()


def _trim(items: dict[int, Any], keep: int = KEEP_INPUTS) -> None:
    for stamp in sorted(items)[:-keep]:
        del items[stamp]
