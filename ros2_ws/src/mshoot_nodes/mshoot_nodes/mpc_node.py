"""The MPC node: every control step, solve the multiple-shooting MPC and publish a setpoint.

Inputs: ``/zone/state`` (the measured zone, a building's or the emulator's)
and ``/forecast`` (disturbances and comfort band over the horizon). Outputs:
``/mpc/setpoint`` (the first planned heat rate, the predicted zone
temperature usable as the HVAC's own setpoint, and the whole plan) and
``/mpc/status``, both stamped with the step they are for.

When a step is due (the step of the node clock, simulated time with
use_sim_time; a timer on whole steps and every incoming message check it), the
node waits until it has a state stamped within the step (or at most
``max_state_age_s`` before it) and a forecast starting at the step (or at most
``max_forecast_age_s`` before it, then shifted), and solves once for the step
with :meth:`mshoot_core.mpc.MPC.solve`. The solve runs in a worker thread, so
the node keeps taking messages and parameter changes; the result is published
from the executor thread.

Safety (the rules are in :mod:`mshoot_core.safety`):

- every input is validated (finite, plausible ranges, consistent arrays and
  comfort band, the control step, stamps neither in the future, stale nor
  going backwards); a rejected message is counted (``rejected_states``,
  ``rejected_forecasts`` in the status) and logged one line each, rate-limited;
- a step always gets a setpoint: when the solve fails or raises (a model
  error), returns an unusable plan, does not converge (``on_failure``
  'fallback'), overruns ``time_budget_s``, or the inputs stay missing or stale
  for ``input_wait_s`` of wall time or ``input_deadline_s`` of node-clock time,
  the :class:`~mshoot_core.safety.SetpointSupervisor` publishes the next
  interval of the last good plan (at most ``max_plan_age_steps`` old), else the
  safe setpoint ``safe_heat_rate_w`` / ``safe_temperature_c``; ``fallback``,
  ``source``, ``fallback_reason`` and the reason in ``message`` say so in
  ``/mpc/status``. No published number is ever non-finite.
- restarted mid-run, the node picks up from the latched forecast and the next
  zone state (the emulator's heartbeat in lockstep) within one step.
"""
from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
from typing import Any

from mshoot_core.closed_loop import forecast_window
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import KELVIN
from mshoot_core.mpc import MPC, MpcResult
from mshoot_core.safety import (check_forecast, check_setpoint, check_stamp_fields,
                                check_zone_state, Decision, InputWait, LIMITS, Rejection,
                                SetpointSupervisor, StampGate)
from mshoot_core.solvers import make_solver, SOLVERS
from mshoot_msgs.msg import Forecast, MpcStatus, Setpoint, ZoneState
import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.timer import Timer

from mshoot_nodes import contract, sources
from mshoot_nodes.conversions import (decision_setpoint_msg, decision_status_msg,
                                      floor_to_step, forecast_series, forecast_to_frame,
                                      NS_PER_S, seconds_to_ns, stamp_to_ns, zone_state_to_x)
from mshoot_nodes.params import declare, ordered, ParamSpec, values
from mshoot_nodes.startup import run_node
from mshoot_nodes.validation import RejectionLog

PARAMS = (
    ParamSpec('model', 'python', "control model: 'python' (exact R1C1), 'fmu' (the R1C1 FMU, "
              "Model Exchange), 'fmu-cs' (Co-Simulation) or a path to an .fmu with the R1C1 "
              'zone interface', read_only=True),
    ParamSpec('fmu_tolerance', 1e-6, 'relative tolerance of the FMU integrator [-]',
              low=1e-14, high=1e-2, read_only=True),
    ParamSpec('step_s', 3600.0, 'control step [s]', low=1.0, high=86400.0, read_only=True),
    ParamSpec('horizon_steps', 10, 'horizon N in control steps [-]', low=1, high=1000),
    ParamSpec('cost', 'quadratic', "'quadratic': sum (q/q_nom)^2; 'energy': sum |q/q_nom|",
              choices=('quadratic', 'energy')),
    ParamSpec('comfort', 'hard', "'hard': the band as bounds, relaxed where unreachable; "
              "'soft': slack with penalty", choices=('hard', 'soft')),
    ParamSpec('soft_penalty', 1e3, 'weight of the quadratic penalty on normalised slack '
              "(comfort 'soft') [-]", low=1e-9, high=1e12),
    ParamSpec('soft_penalty_linear', 0.0, 'weight of the linear penalty on normalised slack '
              "(comfort 'soft') [-]", low=0.0, high=1e12),
    ParamSpec('heat_rate_min_w', -2000.0, 'lower bound of the heat rate (largest cooling) [W]',
              low=-1e7, high=1e7),
    ParamSpec('heat_rate_max_w', 2000.0, 'upper bound of the heat rate (largest heating) [W]',
              low=-1e7, high=1e7),
    ParamSpec('solver', 'slsqp', 'NLP solver', choices=tuple(sorted(SOLVERS))),
    ParamSpec('solver_max_iter', 200, 'iteration limit of the solver [-]', low=1,
              high=1_000_000),
    ParamSpec('solver_tol', 0.0, "solver tolerance (0 = the solver's default) [-]", low=0.0,
              high=1.0),
    ParamSpec('time_budget_s', 0.0, 'wall time allowed per solve; on overrun the step gets a '
              'fallback setpoint (0 = no budget) [s]', low=0.0, high=86400.0),
    ParamSpec('on_failure', 'plan', "when the solver does not converge: 'plan' publishes its "
              "best plan (as the core loop does) if it is sane, 'fallback' the fallback chain",
              choices=('plan', 'fallback')),
    ParamSpec('safe_heat_rate_w', 0.0, 'the safe setpoint: heat rate published when no good '
              'plan is left to fall back on [W]', low=-1e7, high=1e7),
    ParamSpec('safe_temperature_c', 21.0, 'temperature setpoint published with the safe heat '
              'rate (for the HVAC loop) [degC]', low=-50.0, high=80.0),
    ParamSpec('max_plan_age_steps', 4, 'a failed step falls back on the last good plan while '
              'it is at most this many steps old, then on the safe setpoint [-]', low=0,
              high=10_000),
    ParamSpec('input_wait_s', 5.0, 'wall time a due step waits for a missing or stale zone '
              'state or forecast before its fallback [s]', low=0.001, high=86400.0),
    ParamSpec('input_deadline_s', 1800.0, 'node-clock time a due step waits for a missing or '
              'stale input before its fallback (free-running simulated time or real time; 0 = '
              'only input_wait_s) [s]', low=0.0, high=86400.0),
    ParamSpec('max_state_age_s', 0.0, 'oldest zone state accepted for a step, before the step '
              'start [s]', low=0.0, high=86400.0),
    ParamSpec('max_forecast_age_s', 0.0, 'oldest forecast accepted for a step (shifted to the '
              'step) [s]', low=0.0, high=7 * 86400.0),
    ParamSpec('max_future_s', 3600.0, 'inputs stamped further ahead of the node clock are '
              'rejected (data and /clock are not ordered: allow a step) [s]', low=0.0,
              high=86400.0),
    ParamSpec('reject_log_period_s', 5.0, 'at most one log line per kind of rejected input '
              'in this wall time [s]', low=0.0, high=3600.0, read_only=True),
    ParamSpec('history_length', 1000, 'published setpoints and solve results kept in memory '
              '(attributes history, results) [-]', low=1, high=10_000_000, read_only=True),
    ParamSpec('ventilation_dpos', 0.0, 'ventilation damper position assumed over the horizon '
              '(forecasts carry none) [%]', low=0.0, high=100.0),
    ParamSpec('async_solve', True, 'solve in a worker thread (the node stays responsive)',
              read_only=True),
    ParamSpec('zone', 'zone', 'zone name (header.frame_id of the setpoints)', read_only=True),
)
#: Parameters whose change rebuilds the MPC (the warm start is lost).
REBUILD = {'horizon_steps', 'cost', 'heat_rate_min_w', 'heat_rate_max_w', 'soft_penalty_linear'}
#: Parameters of the fallback chain (the supervisor is rebuilt: the last good plan is lost).
SUPERVISOR = {'heat_rate_min_w', 'heat_rate_max_w', 'safe_heat_rate_w', 'max_plan_age_steps'}
#: Parameters applied through MPC.set_solver / MPC.set_soft_bounds (warm start kept).
SOLVER = {'solver', 'solver_max_iter', 'solver_tol'}
COMFORT = {'comfort', 'soft_penalty'}
#: States and forecasts kept, by stamp.
KEEP_MESSAGES = 8


def _solver_options(v: dict[str, Any]) -> dict[str, Any]:
    options: dict[str, Any] = {'max_iter': int(v['solver_max_iter'])}
    if v['solver_tol'] > 0:
        options['tol'] = float(v['solver_tol'])
    return options


def _check(v: dict[str, Any]) -> str | None:
    if 'model' in v and (reason := sources.check_model(v['model'])):
        return reason
    if {'solver', 'solver_max_iter', 'solver_tol'} <= v.keys():
        try:
            make_solver(v['solver'], **_solver_options(v))
        except ValueError as exc:
            return f"solver {v['solver']!r} cannot be used: {exc}"
    if {'safe_heat_rate_w', 'heat_rate_min_w', 'heat_rate_max_w'} <= v.keys() and not (
            v['heat_rate_min_w'] <= v['safe_heat_rate_w'] <= v['heat_rate_max_w']):
        return ('safe_heat_rate_w must be within [heat_rate_min_w, heat_rate_max_w] = '
                f"[{v['heat_rate_min_w']}, {v['heat_rate_max_w']}], got {v['safe_heat_rate_w']}")
    return None


def build_mpc(model: Model, p: dict[str, Any]) -> MPC:
    """The core MPC configured by the node's parameter values ``p``."""
    return MPC(model, horizon_steps=p['horizon_steps'], step_s=p['step_s'],
               control_names=('q',),
               control_bounds=((p['heat_rate_min_w'], p['heat_rate_max_w']),),
               cost=p['cost'], solver=p['solver'], soft_bounds=p['comfort'] == 'soft',
               soft_penalty=p['soft_penalty'], solver_options=_solver_options(p),
               soft_penalty_linear=p['soft_penalty_linear'])


def build_supervisor(p: dict[str, Any]) -> SetpointSupervisor:
    """The fallback chain configured by the node's parameter values ``p``."""
    low, high = LIMITS.zone_temperature_c
    return SetpointSupervisor(((p['heat_rate_min_w'], p['heat_rate_max_w']),), p['step_s'],
                              (p['safe_heat_rate_w'],),
                              max_plan_age_steps=p['max_plan_age_steps'],
                              state_range=((low + KELVIN,), (high + KELVIN,)))


@dataclasses.dataclass
class _Solve:
    """A solve in flight."""

    step_ns: int
    x0: np.ndarray
    started_ns: int
    future: concurrent.futures.Future | None = None
    fallback_sent: bool = False
    budget_timer: Timer | None = None


class MpcNode(Node):
    """Supervisory MPC over topics (see the module docstring).

    Parameters
    ----------
    model : Model, optional
        The control model instance (default: built from the ``model``
        parameter). For embedding and fault-injection tests.
    **kwargs
        Passed to :class:`rclpy.node.Node` (context, parameter_overrides, ...).

    Attributes
    ----------
    mpc : MPC
        The core controller.
    supervisor : SetpointSupervisor
        The fallback chain.
    rejections : RejectionLog
        Rejected inputs by stream ('state', 'forecast') and kind.
    history : deque of (Setpoint, MpcStatus)
        Everything published, in order (the last ``history_length``).
    results : dict
        Step stamp [ns] -> the MpcResult of that step's solve (the last
        ``history_length``).
    """

    def __init__(self, model: Model | None = None, **kwargs: Any) -> None:
        super().__init__('mpc', **kwargs)
        declare(self, PARAMS, [ordered('heat_rate_min_w', 'heat_rate_max_w'), _check])
        self.params = values(self, PARAMS)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        p = self.params
        self.model = (model if model is not None
                      else sources.build_model(p['model'], p['fmu_tolerance']))
        self.mpc = build_mpc(self.model, self.params)
        self.supervisor = build_supervisor(p)
        self.step_ns = seconds_to_ns(p['step_s'])
        self.history: collections.deque[tuple[Setpoint, MpcStatus]] = collections.deque(
            maxlen=p['history_length'])
        self.results: dict[int, MpcResult] = {}
        self.rejections = RejectionLog(self, p['reject_log_period_s'])
        self._state_gate = StampGate(self.step_ns)
        self._forecast_gate = StampGate(self.step_ns)
        self._input_wait = InputWait()
        self._configure_inputs()
        self._states: dict[int, ZoneState] = {}
        self._forecasts: dict[int, Forecast] = {}
        self._last_step_ns = -1
        self._last_setpoint: Setpoint | None = None
        self._pending: set[str] = set()
        self._inflight: _Solve | None = None
        self._due_since: tuple[int, int, int] | None = None
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._pool = (concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix='mpc_solve')
                      if p['async_solve'] else None)
        self._done_gc = self.create_guard_condition(self._on_solve_done)

        self._setpoint_pub = self.create_publisher(Setpoint, contract.SETPOINT,
                                                   contract.DATA_QOS)
        self._status_pub = self.create_publisher(MpcStatus, contract.STATUS, contract.DATA_QOS)
        self.create_subscription(ZoneState, contract.ZONE_STATE, self._on_state,
                                 contract.DATA_QOS)
        self.create_subscription(Forecast, contract.FORECAST, self._on_forecast,
                                 contract.LATCHED_READER_QOS)
        # On whole (simulated) steps; the clock is read, never assumed, in try_solve.
        self.create_timer(p['step_s'], self.try_solve)
        # Wall-clock checks of steps waiting for inputs or for a busy solver.
        self.create_timer(0.05, self.try_solve, clock=self._steady)
        self.get_logger().info(
            f"model {p['model'] if model is None else type(model).__name__}, horizon "
            f"{p['horizon_steps']} x {p['step_s']:.0f} s, cost {p['cost']}, comfort "
            f"{p['comfort']}, solver {p['solver']}, heat rate [{p['heat_rate_min_w']:.0f}, "
            f"{p['heat_rate_max_w']:.0f}] W, time budget {p['time_budget_s'] or 'none'}, "
            f"safe setpoint {p['safe_heat_rate_w']:.0f} W / {p['safe_temperature_c']:.1f} degC")

    # -- configuration --------------------------------------------------------------------
    def _configure_inputs(self) -> None:
        p = self.params
        self._state_gate.max_age_ns = seconds_to_ns(p['max_state_age_s'])
        self._forecast_gate.max_age_ns = seconds_to_ns(p['max_forecast_age_s'])
        for gate in (self._state_gate, self._forecast_gate):
            gate.max_future_ns = seconds_to_ns(p['max_future_s'])
        self._input_wait = InputWait(p['input_wait_s'], p['input_deadline_s'])

    def _on_parameters_set(self, params: list) -> None:
        """Post-set: remember what changed; applied between solves."""
        self.params = values(self, PARAMS)
        self._pending |= {p.name for p in params}
        names = ', '.join(f'{p.name} = {p.value}' for p in params)
        self.get_logger().info(f'parameters changed: {names}')
        self._configure_inputs()
        if self._inflight is None:
            self._apply_pending()

    def _apply_pending(self) -> None:
        pending, self._pending = self._pending, set()
        p = self.params
        if pending & SUPERVISOR:
            self.supervisor = build_supervisor(p)
            self.get_logger().info('fallback chain reconfigured (last good plan forgotten)')
        if pending & REBUILD:
            self.mpc = build_mpc(self.model, self.params)
            self.get_logger().info('MPC rebuilt (warm start reset)')
            return
        if pending & SOLVER:
            self.mpc.set_solver(p['solver'], **_solver_options(p))
        if pending & COMFORT:
            self.mpc.set_soft_bounds(p['comfort'] == 'soft', p['soft_penalty'])

    # -- inputs ---------------------------------------------------------------------------
    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _on_state(self, msg: ZoneState) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        now = self._now_ns()
        rejection = (check_stamp_fields(msg.header.stamp.sec, msg.header.stamp.nanosec)
                     or check_zone_state(msg.temperature_c, msg.heat_rate_w)
                     or self._state_gate.check(stamp, now))
        if rejection:
            self._reject('state', contract.ZONE_STATE, stamp, rejection)
            return
        self._state_gate.accept(stamp, now)
        if stamp in self._states and stamp == self._last_step_ns and self._last_setpoint \
                is not None and stamp_to_ns(self._last_setpoint.header.stamp) == stamp:
            # The same state again (an emulator heartbeat): our setpoint may have been lost.
            self._setpoint_pub.publish(self._last_setpoint)
            return
        self._states[stamp] = msg
        _trim(self._states)
        self.try_solve()

    def _on_forecast(self, msg: Forecast) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        now = self._now_ns()
        rejection = (check_stamp_fields(msg.header.stamp.sec, msg.header.stamp.nanosec)
                     or check_forecast(msg.step_s, forecast_series(msg),
                                       expected_step_s=self.params['step_s'])
                     or self._forecast_gate.check(stamp, now))
        if rejection:
            self._reject('forecast', contract.FORECAST, stamp, rejection)
            return
        self._forecast_gate.accept(stamp, now)
        self._forecasts[stamp] = msg
        _trim(self._forecasts)
        self.try_solve()

    def _reject(self, stream: str, topic: str, stamp_ns: int, rejection: Rejection) -> None:
        self.rejections.reject(stream, self.resolve_topic_name(topic), stamp_ns, rejection)

    def _state_for(self, step_ns: int) -> ZoneState | None:
        oldest = step_ns - seconds_to_ns(self.params['max_state_age_s'])
        stamps = [s for s in self._states if oldest <= s < step_ns + self.step_ns]
        return self._states[max(stamps)] if stamps else None

    def _forecast_for(self, step_ns: int) -> Forecast | None:
        oldest = step_ns - seconds_to_ns(self.params['max_forecast_age_s'])
        stamps = [s for s in self._forecasts if oldest <= s <= step_ns]
        return self._forecasts[max(stamps)] if stamps else None

    def _missing(self, step_ns: int, state: ZoneState | None,
                 forecast: Forecast | None) -> str:
        """One sentence on which input of a step is missing or stale."""
        parts = []
        for name, have, stamps, age in (
                ('zone state', state, self._states, self.params['max_state_age_s']),
                ('forecast', forecast, self._forecasts, self.params['max_forecast_age_s'])):
            if have is not None:
                continue
            older = [s for s in stamps if s < step_ns]
            if older:
                parts.append(f'the {name} is stale (newest {(step_ns - max(older)) / NS_PER_S:g}'
                             f' s before the step, max age {age:g} s)')
            else:
                parts.append(f'no {name} for the step')
        return ' and '.join(parts)

    # -- solving --------------------------------------------------------------------------
    def _due(self, step: int, now: int) -> tuple[float, float]:
        """How long the step has been due: (wall time, node-clock time) [s], counted from
        the first call for the step."""
        steady = self._steady.now().nanoseconds
        if self._due_since is None or self._due_since[0] != step:
            self._due_since = (step, steady, now)
        return (steady - self._due_since[1]) / NS_PER_S, (now - self._due_since[2]) / NS_PER_S

    def try_solve(self) -> None:
        """Solve the due step if it is new and its inputs are there; fall back when they
        stay missing, or when the previous solve still runs, for too long."""
        now = self._now_ns()
        if now <= 0:  # simulated time before the first /clock
            return
        step = floor_to_step(now, self.step_ns)
        if step < self._last_step_ns and self._inflight is None:
            self._clock_went_back(step)
        if step <= self._last_step_ns:
            return
        waited_s, waited_clock_s = self._due(step, now)
        if self._inflight is not None:
            job = self._inflight
            limit = self.params['time_budget_s'] or self.params['input_wait_s']
            if job.fallback_sent and waited_s >= limit:
                self._last_step_ns = step
                self._publish_decision(step, self.supervisor.fallback(
                    step / NS_PER_S, 'budget',
                    f'the solve for {job.step_ns / NS_PER_S:.0f} s is still running after '
                    f'{(self._steady.now().nanoseconds - job.started_ns) / NS_PER_S:.3f} s'),
                    None, waited_s)
            return
        if self._pending:
            self._apply_pending()
        state = self._state_for(step)
        forecast = self._forecast_for(step)
        if state is None or forecast is None:
            if self._input_wait.overdue(waited_s, waited_clock_s):
                self._last_step_ns = step
                self._publish_decision(step, self.supervisor.fallback(
                    step / NS_PER_S, 'inputs_missing',
                    f'{self._missing(step, state, forecast)} after {waited_s:.2f} s'),
                    None, waited_s)
            return
        frame = forecast_to_frame(forecast, self.params['ventilation_dpos'])
        offset = (step - stamp_to_ns(forecast.header.stamp)) // self.step_ns
        horizon = self.mpc.horizon_steps
        if len(frame) < offset + horizon + 1:
            self.get_logger().warning(
                f'forecast covers {len(frame) - offset} of the {horizon + 1} samples needed: '
                'the last one is repeated', throttle_duration_sec=60.0)
        window = forecast_window(frame, int(min(offset, len(frame) - 1)), horizon)
        self._last_step_ns = step
        self._dispatch(step, zone_state_to_x(state), window)

    def _clock_went_back(self, step: int) -> None:
        self.get_logger().warning(
            f'the clock went back from step {self._last_step_ns / NS_PER_S:.0f} s to '
            f'{step / NS_PER_S:.0f} s (a restarted simulation?): inputs, plan and warm start '
            'forgotten')
        self._states.clear()
        self._forecasts.clear()
        for gate in (self._state_gate, self._forecast_gate):
            gate.reset()
        self.supervisor.reset()
        self.mpc.reset()
        self._last_step_ns = -1
        self._last_setpoint = None

    def _dispatch(self, step_ns: int, x0: np.ndarray, window: Any) -> None:
        job = _Solve(step_ns, x0, self._steady.now().nanoseconds)
        self._inflight = job
        budget = self.params['time_budget_s']
        if budget > 0:
            job.budget_timer = self.create_timer(budget, self._on_budget_expired,
                                                 clock=self._steady)
        t_s = step_ns / NS_PER_S
        if self._pool is None:
            job.future = concurrent.futures.Future()
            try:
                job.future.set_result(self.mpc.solve(x0, t_s, window))
            except Exception as exc:  # noqa: BLE001 - reported as a status
                job.future.set_exception(exc)
            self._on_solve_done()
            return
        job.future = self._pool.submit(self.mpc.solve, x0, t_s, window)
        job.future.add_done_callback(lambda _: self._done_gc.trigger())

    def _on_solve_done(self) -> None:
        job = self._inflight
        if job is None or job.future is None or not job.future.done():
            return
        self._inflight = None
        if job.budget_timer is not None:
            self.destroy_timer(job.budget_timer)
        step_s = job.step_ns / NS_PER_S
        elapsed = (self._steady.now().nanoseconds - job.started_ns) / NS_PER_S
        try:
            result = job.future.result()
        except Exception as exc:  # noqa: BLE001 - a failed solve is a status, not a crash
            if job.fallback_sent:
                self.get_logger().error(f'solve for {step_s:.0f} s failed after its fallback '
                                        f'was published: {type(exc).__name__}: {exc}')
            else:
                self._publish_decision(job.step_ns, self.supervisor.fallback(
                    step_s, 'solve_failed', f'solve failed: {type(exc).__name__}: {exc}'),
                    None, elapsed, job.x0)
            self.try_solve()
            return
        self.results[job.step_ns] = result
        _trim(self.results, self.params['history_length'])
        if job.fallback_sent:
            self.get_logger().warning(
                f'solve for {step_s:.0f} s finished after its time budget '
                f'({result.solve_time_s:.3f} s): result not published, warm start kept')
        else:
            decision = self.supervisor.review(
                step_s, result, accept_unconverged=self.params['on_failure'] == 'plan')
            self._publish_decision(job.step_ns, decision, result, result.solve_time_s, job.x0)
        if self._pending:
            self._apply_pending()
        self.try_solve()

    def _on_budget_expired(self) -> None:
        job = self._inflight
        if job is None or job.fallback_sent:
            return
        if job.budget_timer is not None:
            job.budget_timer.cancel()
        budget = self.params['time_budget_s']
        elapsed = (self._steady.now().nanoseconds - job.started_ns) / NS_PER_S
        self._publish_decision(job.step_ns, self.supervisor.fallback(
            job.step_ns / NS_PER_S, 'budget', f'time budget exceeded ({budget:g} s)'),
            None, elapsed, job.x0)

    def _publish_decision(self, step_ns: int, decision: Decision, result: MpcResult | None,
                          solve_time_s: float, x0: np.ndarray | None = None) -> None:
        """Publish the setpoint and status of a step (a last finiteness check included)."""
        if self._inflight is not None and self._inflight.step_ns == step_ns:
            self._inflight.fallback_sent = True
        p = self.params
        setpoint = decision_setpoint_msg(step_ns, decision, p['step_s'], p['safe_temperature_c'],
                                         p['zone'])
        problem = check_setpoint(setpoint.heat_rate_w, setpoint.temperature_setpoint_c,
                                 setpoint.step_s, setpoint.plan_heat_rate_w,
                                 setpoint.plan_temperature_c)
        if problem:  # cannot happen unless the supervisor has a bug: never publish it
            self.get_logger().error(f'setpoint for {step_ns / NS_PER_S:.0f} s failed its final '
                                    f'check ({problem.reason}): publishing the safe setpoint')
            decision = self.supervisor.safe(step_ns / NS_PER_S, 'invalid_plan',
                                            f'{problem.reason}; fallback: the safe setpoint')
            setpoint = decision_setpoint_msg(step_ns, decision, p['step_s'],
                                             p['safe_temperature_c'], p['zone'])
        status = decision_status_msg(
            step_ns, decision, result, solve_time_s=solve_time_s,
            rejected_states=self.rejections.total('state'),
            rejected_forecasts=self.rejections.total('forecast'),
            consecutive_fallbacks=self.supervisor.consecutive_fallbacks)
        self._setpoint_pub.publish(setpoint)
        self._status_pub.publish(status)
        self._last_setpoint = setpoint
        self.history.append((setpoint, status))
        step_s = step_ns / NS_PER_S
        if not decision.fallback and result is not None:
            start = '' if x0 is None else f'{x0[0] - KELVIN:.2f} -> '
            line = (f'step {step_s:.0f} s: q = {setpoint.heat_rate_w:.1f} W, T {start}'
                    f'{setpoint.temperature_setpoint_c:.2f} degC, '
                    f"{'ok' if result.success else 'NOT CONVERGED'} in {result.nit} it, "
                    f'{result.solve_time_s:.3f} s')
            # One call site per severity (rclpy keeps a severity per call site).
            if result.success:
                self.get_logger().info(line)
            else:
                self.get_logger().warning(line)
        else:
            self.get_logger().warning(f'step {step_s:.0f} s: fallback {setpoint.heat_rate_w:.1f} '
                                      f'W ({decision.source}): {decision.reason}')

    def destroy_node(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        close = getattr(self.model, 'close', None)
        if close is not None:  # an FMU instance
            close()
        super().destroy_node()


def _trim(messages: dict[int, Any], keep: int = KEEP_MESSAGES) -> None:
    for stamp in sorted(messages)[:-keep]:
        del messages[stamp]


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes mpc`` (set use_sim_time:=true against the emulator)."""
    run_node(MpcNode, 'mpc', args, bridge_logging=True)


if __name__ == '__main__':
    main()
