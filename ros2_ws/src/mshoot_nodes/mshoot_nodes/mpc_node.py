"""
The MPC node: every control step, publish the setpoint the core controller decides.

Inputs: ``/zone/state`` (the measured zones, a building's or the emulator's:
the model's states by name) and ``/forecast`` (the model's disturbances by
name, the comfort band and the energy price over the horizon). Outputs:
``/mpc/setpoint`` (every control of the model by name, the predicted
temperature of every zone usable as the setpoint of the building's own loop,
and the whole plan) and ``/mpc/status``, both stamped with the step they are
for. Any model of the registry runs, with one or several controls and zones
(:func:`mshoot_core.controller.controller_for`: e.g. ``model:=r1c1x2``, two
zones with controls ``q_0``, ``q_1``).

Every decision is made by :class:`mshoot_core.controller.Controller`, the one
the offline loop uses: which inputs are valid and fresh enough, when a step is
due, when it waits and when it falls back, the time budget, the fallback chain
(the optimum, else the last good plan's interval, else the safe setpoint).
This node only converts: messages to plain values (and the message-format
checks of :mod:`mshoot_core.safety`), parameters to
:class:`mshoot_core.settings.MpcSettings` (one table: :data:`PARAMS`), and
clocks (the node clock, simulated time with use_sim_time; a steady clock for
waits and budgets). Solves run in a worker thread, so the node keeps taking
messages and parameter changes; the controller is polled from the executor
thread on whole steps, on every input, every 50 ms and when a solve finishes.

- every message is checked whole before any of it is used or copied (array
  lengths within the model's dimensions first, then every field; stamps on the
  step grid, at most ``max_future_s`` ahead of the clock); a rejected message
  moves nothing, is counted (``rejected_states``, ``rejected_forecasts`` in the
  status) and logged one line each, rate-limited;
- a second publisher of ``/zone/state`` or ``/forecast`` (any node but
  ``state_writer``, ``forecast_writer``) is reported as an intruder on
  /diagnostics, and each peer (state, forecast, with use_sim_time the clock) as
  STALE when not heard from for ``peer_timeout_s`` (:mod:`mshoot_nodes.peers`);
- a step always gets a setpoint; ``fallback``, ``source``,
  ``fallback_reason`` and the reason in ``message`` say where it came from. No
  published number is ever non-finite.
- a model whose states are not all measured (e.g. ``model:=r2c2``: the
  envelope temperature is not) gets them estimated by the controller from the
  measured ones of ``/zone/state`` (settings ``estimation``,
  ``measured_states``, ``measurement_noise_k``, ...; unmeasured states in the
  message are ignored); the state every step was planned from and the
  standard deviation of its estimate are in the status (``state_names``,
  ``state_values``, ``state_std``) and on /diagnostics;
- restarted mid-run, the node picks up from the latched forecast and the next
  zone state (the emulator's heartbeat in lockstep) within one step.
"""
from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
from typing import Any

from mshoot_core.controller import Controller, controller_for, StepOutcome
from mshoot_core.models.base import Model
from mshoot_core.models.registry import card_controls, MODEL_PARAMETERS, ModelSettings
from mshoot_core.mpc import MpcResult
from mshoot_core.peers import Peer
from mshoot_core.safety import (check_lengths, check_setpoint, check_stamp_fields,
                                forecast_caps, Rejection)
from mshoot_core.settings import MpcSettings, PARAMETERS, SettingsError
from mshoot_core.units import NS_PER_S
from mshoot_msgs.msg import Forecast, MpcStatus, Setpoint, ZoneState
from rclpy.logging import LoggingSeverity
from rosgraph_msgs.msg import Clock as ClockMsg

from mshoot_nodes import contract
from mshoot_nodes.conversions import (decision_setpoint_msg, decision_status_msg, field_lengths,
                                      forecast_series, stamp_to_ns)
from mshoot_nodes.diagnostics import DiagnosticsPublisher, Level, Report
from mshoot_nodes.lifecycle import ManagedNode
from mshoot_nodes.params import declare, ParamSpec, values
from mshoot_nodes.peers import PeerMonitor
from mshoot_nodes.startup import run_node
from mshoot_nodes.validation import RejectionLog

#: The node's parameters: the model, every controller setting (one table, from
#: :mod:`mshoot_core.settings`), and what only the node has.
PARAMS = (
    *(ParamSpec.from_setting(f) for f in MODEL_PARAMETERS),
    *(ParamSpec.from_setting(f) for f in PARAMETERS),
    ParamSpec('reject_log_period_s', 5.0, 'at most one log line per kind of rejected input '
              'in this wall time [s]', low=0.0, high=3600.0, read_only=True),
    ParamSpec('history_length', 1000, 'published setpoints and solve results kept in memory '
              '(attributes history, results) [-]', low=1, high=10_000_000, read_only=True),
    ParamSpec('ventilation_dpos', 0.0, 'ventilation damper position assumed over the horizon '
              '(forecasts carry none) [%]', low=0.0, high=100.0),
    ParamSpec('async_solve', True, 'solve in a worker thread (the node stays responsive)',
              read_only=True),
    ParamSpec('zone', 'zone', 'zone name (header.frame_id of the setpoints)', read_only=True),
    ParamSpec('state_writer', 'emulator', 'name of the one node expected to publish '
              '/zone/state (and, with use_sim_time, /clock): any other is reported as an '
              'intruder on /diagnostics',
              read_only=True),
    ParamSpec('forecast_writer', 'forecaster', 'name of the one node expected to publish '
              '/forecast: any other is reported as an intruder on /diagnostics',
              read_only=True),
    ParamSpec('peer_timeout_s', 30.0, 'wall time without a zone state, forecast or (with '
              'use_sim_time) clock after which that peer is reported STALE on /diagnostics '
              '[s]', low=0.1, high=1e6, read_only=True),
)
SETTING_NAMES = tuple(f.name for f in PARAMETERS)
DEFAULTS = {spec.name: spec.default for spec in PARAMS}


def settings_from(p: dict[str, Any]) -> MpcSettings:
    """
    Return the controller settings of the node's parameter values ``p``.

    With the controls of the model's card (units, limits, safe values), where ``model`` is a
    card, so the settings are checked against them.
    """
    controls = card_controls(p['model'])
    extra = {'control_names': [c.name for c in controls], 'controls': controls} if controls \
        else {}
    return MpcSettings.from_flat({**{name: p[name] for name in SETTING_NAMES}, **extra})


def _check(proposed: dict[str, Any]) -> str | None:
    """
    Return every problem of the proposed parameter values at once, or None.

    Parameters not declared yet count with their defaults.
    """
    v = {**DEFAULTS, **proposed}
    problems = ModelSettings(v['model'], v['fmu_tolerance']).problems()
    try:
        settings_from(v)
    except SettingsError as exc:
        problems += exc.problems
    return '; '.join(problems) or None


class MpcNode(ManagedNode):
    """
    Supervisory MPC over topics (see the module docstring); a lifecycle node.

    Configure builds the model, the controller and the publishers; activate
    subscribes and starts the step timers; deactivate publishes the safe
    setpoint once and stops controlling (the building is back on its own
    control); cleanup frees the model (an FMU) and the solver thread. With
    ``autostart`` (default true) the node configures and activates itself.

    Parameters
    ----------
    model : Model, optional
        The control model instance (default: built from the ``model``
        parameter on configure). For embedding and fault-injection tests.
    **kwargs
        Passed to :class:`rclpy.node.Node` (context, parameter_overrides, ...).

    Attributes
    ----------
    controller : Controller or None
        The core controller: every decision (None while unconfigured).
    rejections : RejectionLog
        Rejected inputs by stream ('state', 'forecast') and kind.
    history : deque of (Setpoint, MpcStatus)
        Everything published, in order (the last ``history_length``).
    diagnostics : DiagnosticsPublisher
        Publishes :meth:`health` on /diagnostics.

    """

    def __init__(self, model: Model | None = None, **kwargs: Any) -> None:
        super().__init__('mpc', **kwargs)
        declare(self, PARAMS, [_check])
        self.params = p = values(self, PARAMS)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        self._given_model = model
        self.model: Model | None = None
        self.controller: Controller | None = None
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self.history: collections.deque[tuple[Setpoint, MpcStatus]] = collections.deque(
            maxlen=p['history_length'])
        self.rejections = RejectionLog(self, p['reject_log_period_s'])
        self._last_setpoint: Setpoint | None = None
        self._steady = self.steady_clock
        timeout = p['peer_timeout_s']
        peers = [Peer('state', contract.ZONE_STATE, p['state_writer'], timeout),
                 Peer('forecast', contract.FORECAST, p['forecast_writer'], timeout)]
        if self.get_parameter('use_sim_time').value:
            peers.append(Peer('clock', contract.CLOCK, p['state_writer'], timeout))
            self.create_subscription(ClockMsg, contract.CLOCK,
                                     lambda _: self.peers.heard('clock'), contract.CLOCK_QOS)
        self.peers = PeerMonitor(self, peers)
        self.diagnostics = DiagnosticsPublisher(self, self.health, hardware_id=p['zone'],
                                                peers=self.peers)
        self.autostart()

    # -- lifecycle ------------------------------------------------------------------------
    def configure(self) -> None:
        """Build the model (unless given), the controller and the publishers."""
        p = self.params
        self.model = (self._given_model if self._given_model is not None
                      else ModelSettings(p['model'], p['fmu_tolerance']).build())
        self._pool = (concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix='mpc_solve')
                      if p['async_solve'] else None)
        self.controller = controller_for(self.model, settings_from(p), executor=self._pool,
                                         assumed_inputs={'dpos': p['ventilation_dpos']},
                                         on_solve_done=self._solve_done,
                                         history_length=p['history_length'])
        self.rejections = RejectionLog(self, p['reject_log_period_s'],
                                       self.controller.rejections)
        self._setpoint_pub = self.create_lifecycle_publisher(Setpoint, contract.SETPOINT,
                                                             contract.DATA_QOS)
        self._status_pub = self.create_lifecycle_publisher(MpcStatus, contract.STATUS,
                                                           contract.DATA_QOS)
        s = self.controller.settings
        self.get_logger().info(
            f"model {p['model'] if self._given_model is None else type(self.model).__name__}, "
            f"horizon {p['horizon_steps']} x {p['step_s']:.0f} s, cost {p['cost']}, comfort "
            f"{p['comfort']}, solver {p['solver']}, controls "
            + ', '.join(f'{c.label()} in [{low:g}, {high:g}] safe {safe:g}'
                        + (' (released)' if released else '')
                        for c, (low, high), safe, released in zip(
                            s.problem.control_specs, s.problem.control_bounds, s.safe_values,
                            s.released))
            + f', zone temperatures {list(self.controller.interface.temperature_names)}, '
            f"time budget {p['time_budget_s'] or 'none'}, safe zone setpoint "
            f"{p['safe_temperature_c']:.1f} degC")

    def _solve_done(self) -> None:
        """From the solver thread: poll the controller in the executor's thread at once."""
        executor = self.executor
        if executor is not None:
            executor.create_task(self.try_solve)

    def activate(self) -> None:
        """Take inputs and decide on whole steps and every 50 ms of wall time."""
        self.create_subscription(ZoneState, contract.ZONE_STATE, self._on_state,
                                 contract.DATA_QOS)
        self.create_subscription(Forecast, contract.FORECAST, self._on_forecast,
                                 contract.LATCHED_READER_QOS)
        # On whole (simulated) steps; the clock is read, never assumed, in try_solve.
        self.create_timer(self.params['step_s'], self.try_solve)
        # Wall-clock checks of steps waiting for inputs or for a busy solver.
        self.create_timer(0.05, self.try_solve, clock=self._steady)

    def deactivate(self) -> None:
        """Publish the safe setpoint once and stop controlling."""
        now = self._now_ns()
        if now > 0 and self.controller is not None:
            self._publish(self.controller.hand_back(now))

    def cleanup(self) -> None:
        """Free the solver thread and the model this node built (an FMU instance)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._given_model is None:
            close = getattr(self.model, 'close', None)
            if close is not None:
                close()
        self.controller = None
        self.model = None

    @property
    def mpc(self) -> Any:
        """Return the controller's MPC (None while unconfigured)."""
        return None if self.controller is None else self.controller.mpc

    @property
    def results(self) -> dict[int, MpcResult]:
        """Step stamp [ns] -> MpcResult of the latest solves."""
        return {} if self.controller is None else self.controller.results

    # -- health ---------------------------------------------------------------------------
    def health(self) -> Report:
        """Return the MPC's status for /diagnostics."""
        c = self.controller
        if c is None:
            return Report(Level.OK, 'unconfigured', {'model': self.params['model']})
        last_step = c.last_step_ns
        now = self._now_ns()
        behind = (0 if last_step is None or now <= 0
                  else max(0, (now - last_step) // c.step_ns))
        last = self.history[-1][1] if self.history else None
        sources = c.supervisor.sources
        values_ = {
            'step': '' if last_step is None else f'{last_step / NS_PER_S:.0f}',
            'steps_behind': behind,
            'decisions': sum(sources.values()),
            'optimum': sources['optimum'], 'plan': sources['plan'], 'safe': sources['safe'],
            'released': sources['released'],
            'consecutive_fallbacks': c.supervisor.consecutive_fallbacks,
            'rejected_states': c.rejections.total('state'),
            'rejected_forecasts': c.rejections.total('forecast'),
            'last_solve_s': '' if last is None else last.solve_time_s,
            'solving': c.busy,
            'horizon_steps': c.mpc.horizon_steps, 'solver': c.mpc.solver.name,
            'measured_states': ','.join(c.measured_states),
        }
        estimate = c.estimate
        if c.estimator is not None:
            values_['estimate_updates'] = c.estimator.updates
            values_['estimate_restarts'] = c.estimator.resets
            values_['estimate_time'] = '' if estimate is None else f'{estimate.t_s:.0f}'
            for i, name in enumerate(c.model.state_names):  # [K]
                values_[f'estimate_{name}'] = '' if estimate is None else float(estimate.x[i])
                values_[f'std_{name}'] = '' if estimate is None else float(estimate.std[i])
        if last is None:
            return Report(Level.OK, 'waiting for the first step', values_)
        if last.fallback:
            return Report(Level.WARN, f'fallback ({last.source}, {last.fallback_reason}): '
                          f'{last.message}', values_)
        return Report(Level.OK, f'{last.source}, {last.iterations} iterations', values_)

    # -- configuration --------------------------------------------------------------------
    def _on_parameters_set(self, params: list) -> None:
        """Post-set: hand the new settings to the controller (applied between solves)."""
        self.params = values(self, PARAMS)
        names = ', '.join(f'{p.name} = {p.value}' for p in params)
        self.get_logger().info(f'parameters changed: {names}')
        if self.controller is None:  # applied on configure
            return
        self.controller.assumed_inputs['dpos'] = float(self.params['ventilation_dpos'])
        what = self.controller.update(settings_from(self.params).replace(
            control_names=self.controller.interface.control_names,
            controls=self.controller.settings.problem.controls))
        if what not in ('unchanged', 'updated'):
            self.get_logger().info(f'controller {what} (rebuilt: warm start reset; supervisor:'
                                   ' last good plan forgotten)')

    # -- inputs ---------------------------------------------------------------------------
    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _on_state(self, msg: ZoneState) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        problem = check_stamp_fields(msg.header.stamp.sec, msg.header.stamp.nanosec)
        repeat = problem is None and self.controller.is_repeat_of_decided_step(stamp)
        if self._rejected('state', contract.ZONE_STATE, stamp, problem, lambda: (
                self.controller.offer_named_state(
                    stamp, msg.state_names, msg.state_values, self._now_ns(),
                    output_names=msg.output_names, output_values=msg.output_values,
                    control_names=msg.control_names, control_values=msg.control_values,
                    history=(msg.history_offsets_s, msg.history_state_values,
                             msg.history_output_names, msg.history_output_values)))):
            return
        self.peers.heard('state')
        last = self._last_setpoint
        if repeat and last is not None and stamp_to_ns(last.header.stamp) == stamp:
            # The same state again (an emulator heartbeat): our setpoint may have been lost.
            self._setpoint_pub.publish(last)
            return
        self.try_solve()

    def _on_forecast(self, msg: Forecast) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        caps = forecast_caps(len(self.controller.forecast_known))
        problem = (check_stamp_fields(msg.header.stamp.sec, msg.header.stamp.nanosec)
                   or check_lengths('forecast', field_lengths(msg, caps), caps))
        series, problem = ({}, problem) if problem else forecast_series(msg)
        if self._rejected('forecast', contract.FORECAST, stamp, problem, lambda: (
                self.controller.offer_forecast(stamp, msg.step_s, series, self._now_ns(),
                                               msg.history_steps))):
            return
        self.peers.heard('forecast')
        self.try_solve()

    def _rejected(self, stream: str, topic: str, stamp_ns: int, problem: Rejection | None,
                  offer: Any) -> bool:
        """Offer an input whose message passed its format checks; log a rejection."""
        if problem is not None:
            self.controller.reject(stream, problem)
        else:
            problem = offer()
        if problem is not None:
            self.rejections.log(stream, self.resolve_topic_name(topic), stamp_ns, problem)
            return True
        return False

    # -- deciding -------------------------------------------------------------------------
    def try_solve(self) -> None:
        """Let the controller decide what is due; publish its decisions."""
        now = self._now_ns()
        if now <= 0 or not self.is_active:  # no /clock yet, or not controlling
            return
        for outcome in self.controller.poll(now, self._steady.now().nanoseconds):
            self._publish(outcome)

    def _publish(self, outcome: StepOutcome) -> None:
        """Publish the setpoint and status of a step (a last finiteness check included)."""
        p = self.params
        interface = self.controller.interface
        step_ns, result = outcome.step_ns, outcome.result
        sent = self.controller.sent_control_names  # (the band setpoints after the controls)
        decision, schedule = outcome.sent()
        setpoint = decision_setpoint_msg(step_ns, decision, p['step_s'], interface,
                                         p['safe_temperature_c'], p['zone'], schedule, sent)
        problem = check_setpoint(setpoint.step_s, setpoint.control_names,
                                 setpoint.control_values, setpoint.temperature_names,
                                 setpoint.temperature_setpoints_c, setpoint.plan_controls,
                                 setpoint.plan_temperatures_c, expected_controls=sent)
        if problem:  # cannot happen unless the supervisor has a bug: never publish it
            self.get_logger().error(f'setpoint for {step_ns / NS_PER_S:.0f} s failed its final '
                                    f'check ({problem.reason}): publishing the safe setpoint')
            decision, _ = dataclasses.replace(outcome, decision=self.controller.supervisor.safe(
                step_ns / NS_PER_S, 'invalid_plan', f'{problem.reason}; fallback: the safe '
                'setpoint'), schedule=None).sent()
            setpoint = decision_setpoint_msg(step_ns, decision, p['step_s'], interface,
                                             p['safe_temperature_c'], p['zone'],
                                             control_names=sent)
        status = decision_status_msg(
            step_ns, decision, result, solve_time_s=outcome.solve_time_s,
            rejected_states=self.rejections.total('state'),
            rejected_forecasts=self.rejections.total('forecast'),
            consecutive_fallbacks=self.controller.supervisor.consecutive_fallbacks,
            state=(None if outcome.x0 is None else
                   dict(zip(self.controller.model.state_names, map(float, outcome.x0)))),
            state_std=outcome.x0_std)
        self._setpoint_pub.publish(setpoint)
        self._status_pub.publish(status)
        self._last_setpoint = setpoint
        self.history.append((setpoint, status))
        if decision.fallback or result is None:
            self.get_logger().warning(f'step {step_ns / NS_PER_S:.0f} s: fallback '
                                      f'{self._controls_text(setpoint)} W ({decision.source}): '
                                      f'{decision.reason}')
        elif not result.success:
            self.get_logger().warning(self._step_line(step_ns, setpoint, outcome))
        elif self.get_logger().is_enabled_for(LoggingSeverity.INFO):  # (the line costs)
            self.get_logger().info(self._step_line(step_ns, setpoint, outcome))

    @staticmethod
    def _controls_text(setpoint: Setpoint) -> str:
        return ', '.join(f'{name} = {value:.1f}' for name, value in
                         zip(setpoint.control_names, setpoint.control_values))

    def _step_line(self, step_ns: int, setpoint: Setpoint, outcome: StepOutcome) -> str:
        """Return the log line of a solved step: controls, zone temperatures, the solve."""
        result, x0 = outcome.result, outcome.x0
        starts = (self.controller.interface.temperatures_c(x0) if x0 is not None
                  else [None] * len(setpoint.temperature_names))
        zones = ', '.join(
            f'{name} {"" if start is None else f"{start:.2f} -> "}{end:.2f} degC'
            for name, start, end in zip(setpoint.temperature_names, starts,
                                        setpoint.temperature_setpoints_c))
        return (f'step {step_ns / NS_PER_S:.0f} s: {self._controls_text(setpoint)} W, {zones}, '
                f"{'ok' if result.success else 'NOT CONVERGED'} in {result.nit} it, "
                f'{result.solve_time_s:.3f} s')


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes mpc`` (set use_sim_time:=true against the emulator)."""
    run_node(MpcNode, 'mpc', args, bridge_logging=True)


if __name__ == '__main__':
    main()
