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
from the executor thread. With ``time_budget_s`` > 0 a fallback setpoint (the
previous plan's next interval, else the last heat rate) goes out when the solve
overruns its budget.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import sys
from typing import Any

from mshoot_core.closed_loop import forecast_window
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import KELVIN
from mshoot_core.mpc import MPC, MpcResult
from mshoot_core.solvers import make_solver, SOLVERS
from mshoot_msgs.msg import Forecast, MpcStatus, Setpoint, ZoneState
import numpy as np
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.timer import Timer

from mshoot_nodes import contract, sources
from mshoot_nodes.conversions import (fallback_setpoint_msg, floor_to_step, forecast_length,
                                      forecast_to_frame, NS_PER_S, seconds_to_ns,
                                      setpoint_msg, stamp_to_ns, status_msg, zone_state_to_x)
from mshoot_nodes.logbridge import bridge_core_logging
from mshoot_nodes.params import declare, ordered, ParamSpec, values

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
              "best plan (as the core loop does), 'fallback' the previous plan's next interval",
              choices=('plan', 'fallback')),
    ParamSpec('max_state_age_s', 0.0, 'oldest zone state accepted for a step, before the step '
              'start [s]', low=0.0, high=86400.0),
    ParamSpec('max_forecast_age_s', 0.0, 'oldest forecast accepted for a step (shifted to the '
              'step) [s]', low=0.0, high=7 * 86400.0),
    ParamSpec('ventilation_dpos', 0.0, 'ventilation damper position assumed over the horizon '
              '(forecasts carry none) [%]', low=0.0, high=100.0),
    ParamSpec('async_solve', True, 'solve in a worker thread (the node stays responsive)',
              read_only=True),
    ParamSpec('zone', 'zone', 'zone name (header.frame_id of the setpoints)', read_only=True),
)
#: Parameters whose change rebuilds the MPC (the warm start is lost).
REBUILD = {'horizon_steps', 'cost', 'heat_rate_min_w', 'heat_rate_max_w', 'soft_penalty_linear'}
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
    return None


def build_mpc(model: Model, p: dict[str, Any]) -> MPC:
    """The core MPC configured by the node's parameter values ``p``."""
    return MPC(model, horizon_steps=p['horizon_steps'], step_s=p['step_s'],
               control_names=('q',),
               control_bounds=((p['heat_rate_min_w'], p['heat_rate_max_w']),),
               cost=p['cost'], solver=p['solver'], soft_bounds=p['comfort'] == 'soft',
               soft_penalty=p['soft_penalty'], solver_options=_solver_options(p),
               soft_penalty_linear=p['soft_penalty_linear'])


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

    Attributes
    ----------
    mpc : MPC
        The core controller.
    history : list of (Setpoint, MpcStatus)
        Everything published, in order.
    results : dict
        Step stamp [ns] -> the MpcResult of that step's solve.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('mpc', **kwargs)
        declare(self, PARAMS, [ordered('heat_rate_min_w', 'heat_rate_max_w'), _check])
        self.params = values(self, PARAMS)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        p = self.params
        self.model = sources.build_model(p['model'], p['fmu_tolerance'])
        self.mpc = build_mpc(self.model, self.params)
        self.step_ns = seconds_to_ns(p['step_s'])
        self.history: list[tuple[Setpoint, MpcStatus]] = []
        self.results: dict[int, MpcResult] = {}
        self._states: dict[int, ZoneState] = {}
        self._forecasts: dict[int, Forecast] = {}
        self._last_step_ns = -1
        self._last_setpoint: Setpoint | None = None
        self._pending: set[str] = set()
        self._inflight: _Solve | None = None
        self._due_since: tuple[int, int] | None = None
        self._warned_step = -1
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
                                 contract.LATCHED_QOS)
        # On whole (simulated) steps; the clock is read, never assumed, in try_solve.
        self.create_timer(p['step_s'], self.try_solve)
        self.create_timer(1.0, self._watchdog, clock=self._steady)
        self.get_logger().info(
            f"model {p['model']}, horizon {p['horizon_steps']} x {p['step_s']:.0f} s, cost "
            f"{p['cost']}, comfort {p['comfort']}, solver {p['solver']}, heat rate "
            f"[{p['heat_rate_min_w']:.0f}, {p['heat_rate_max_w']:.0f}] W, time budget "
            f"{p['time_budget_s'] or 'none'}")

    # -- configuration --------------------------------------------------------------------
    def _on_parameters_set(self, params: list) -> None:
        """Post-set: remember what changed; applied between solves."""
        self.params = values(self, PARAMS)
        self._pending |= {p.name for p in params}
        names = ', '.join(f'{p.name} = {p.value}' for p in params)
        self.get_logger().info(f'parameters changed: {names}')
        if self._inflight is None:
            self._apply_pending()

    def _apply_pending(self) -> None:
        pending, self._pending = self._pending, set()
        p = self.params
        if pending & REBUILD:
            self.mpc = build_mpc(self.model, self.params)
            self.get_logger().info('MPC rebuilt (warm start reset)')
            return
        if pending & SOLVER:
            self.mpc.set_solver(p['solver'], **_solver_options(p))
        if pending & COMFORT:
            self.mpc.set_soft_bounds(p['comfort'] == 'soft', p['soft_penalty'])

    # -- inputs ---------------------------------------------------------------------------
    def _on_state(self, msg: ZoneState) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        if stamp in self._states and stamp == self._last_step_ns and self._last_setpoint \
                is not None and stamp_to_ns(self._last_setpoint.header.stamp) == stamp:
            # The same state again (an emulator heartbeat): our setpoint may have been lost.
            self._setpoint_pub.publish(self._last_setpoint)
            return
        self._states[stamp] = msg
        _trim(self._states)
        self.try_solve()

    def _on_forecast(self, msg: Forecast) -> None:
        try:
            forecast_length(msg)
        except ValueError as exc:
            self.get_logger().error(f'forecast rejected: {exc}')
            return
        self._forecasts[stamp_to_ns(msg.header.stamp)] = msg
        _trim(self._forecasts)
        self.try_solve()

    def _state_for(self, step_ns: int) -> ZoneState | None:
        oldest = step_ns - seconds_to_ns(self.params['max_state_age_s'])
        stamps = [s for s in self._states if oldest <= s < step_ns + self.step_ns]
        return self._states[max(stamps)] if stamps else None

    def _forecast_for(self, step_ns: int) -> Forecast | None:
        oldest = step_ns - seconds_to_ns(self.params['max_forecast_age_s'])
        stamps = [s for s in self._forecasts if oldest <= s <= step_ns]
        return self._forecasts[max(stamps)] if stamps else None

    # -- solving --------------------------------------------------------------------------
    def try_solve(self) -> None:
        """Solve the due step if it is new and its state and forecast are there."""
        if self._inflight is not None:
            return
        if self._pending:
            self._apply_pending()
        now = self.get_clock().now().nanoseconds
        step = floor_to_step(now, self.step_ns)
        if step <= self._last_step_ns:
            return
        if self._due_since is None or self._due_since[0] != step:
            self._due_since = (step, self._steady.now().nanoseconds)
        state = self._state_for(step)
        forecast = self._forecast_for(step)
        if state is None or forecast is None:
            return
        if abs(forecast.step_s - self.params['step_s']) > 1e-9:
            self.get_logger().error(
                f'forecast step {forecast.step_s} s differs from step_s '
                f"{self.params['step_s']} s: cannot plan", throttle_duration_sec=60.0)
            return
        frame = forecast_to_frame(forecast, self.params['ventilation_dpos'])
        offset = (step - stamp_to_ns(forecast.header.stamp)) // self.step_ns
        horizon = self.mpc.horizon_steps
        if len(frame) < offset + horizon + 1:
            self.get_logger().warning(
                f'forecast covers {len(frame) - offset} of the {horizon + 1} samples needed: '
                'the last one is repeated', throttle_duration_sec=60.0)
        window = forecast_window(frame, int(offset), horizon)
        self._last_step_ns = step
        self._dispatch(step, zone_state_to_x(state), window)

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
        try:
            result = job.future.result()
        except Exception as exc:  # noqa: BLE001 - a failed solve is a status, not a crash
            self.get_logger().error(f'MPC solve for {step_s:.0f} s failed: {exc}')
            if not job.fallback_sent:
                self._publish_fallback(job, f'solve failed: {exc}')
            self.try_solve()
            return
        self.results[job.step_ns] = result
        if job.fallback_sent:
            self.get_logger().warning(
                f'solve for {step_s:.0f} s finished after its time budget '
                f'({result.solve_time_s:.3f} s): result not published, warm start kept')
        elif not result.success and self.params['on_failure'] == 'fallback':
            self._publish_fallback(job, f'solver did not converge: {result.message}', result)
        else:
            self._publish(job.step_ns, setpoint_msg(job.step_ns, result, self.params['step_s'],
                                                    self.params['zone']),
                          status_msg(job.step_ns, result))
            level = self.get_logger().info if result.success else self.get_logger().warning
            level(f'step {step_s:.0f} s: q = {result.controls[0, 0]:.1f} W, T '
                  f'{job.x0[0] - KELVIN:.2f} -> {result.states[1, 0] - KELVIN:.2f} degC, '
                  f"{'ok' if result.success else 'NOT CONVERGED'} in {result.nit} it, "
                  f'{result.solve_time_s:.3f} s')
        if self._pending:
            self._apply_pending()
        self.try_solve()

    def _on_budget_expired(self) -> None:
        job = self._inflight
        if job is None or job.fallback_sent:
            return
        if job.budget_timer is not None:
            job.budget_timer.cancel()
        self.get_logger().warning(
            f'solve for {job.step_ns / NS_PER_S:.0f} s exceeded its time budget '
            f"({self.params['time_budget_s']} s): publishing a fallback")
        self._publish_fallback(job, 'time budget exceeded')

    def _publish_fallback(self, job: _Solve, reason: str, result: MpcResult | None = None) -> None:
        """Publish the previous plan's next interval (or the last heat rate, or 0 W)."""
        job.fallback_sent = True
        p = self.params
        last = self._last_setpoint
        temperature_c = float(job.x0[0] - KELVIN)
        plan_q: list[float] = []
        plan_t: list[float] = []
        if last is not None and stamp_to_ns(last.header.stamp) == job.step_ns - self.step_ns \
                and len(last.plan_heat_rate_w) > 1:
            plan_q = list(last.plan_heat_rate_w[1:])
            plan_t = list(last.plan_temperature_c[1:])
            heat_rate, temperature_c, source = plan_q[0], plan_t[0], 'previous plan'
        elif last is not None:
            heat_rate, source = last.heat_rate_w, 'last heat rate held'
        else:
            heat_rate, source = 0.0, 'no plan yet: 0 W'
        heat_rate = float(np.clip(heat_rate, p['heat_rate_min_w'], p['heat_rate_max_w']))
        setpoint = fallback_setpoint_msg(job.step_ns, heat_rate, temperature_c, p['step_s'],
                                         plan_q, plan_t, p['zone'])
        elapsed = (self._steady.now().nanoseconds - job.started_ns) / NS_PER_S
        status = status_msg(job.step_ns, result, fallback=True,
                            message=f'{reason}; fallback: {source}', solve_time_s=elapsed)
        self._publish(job.step_ns, setpoint, status)
        self.get_logger().warning(f'step {job.step_ns / NS_PER_S:.0f} s: fallback '
                                  f'{heat_rate:.1f} W ({source}; {reason})')

    def _publish(self, step_ns: int, setpoint: Setpoint, status: MpcStatus) -> None:
        self._setpoint_pub.publish(setpoint)
        self._status_pub.publish(status)
        self._last_setpoint = setpoint
        self.history.append((setpoint, status))

    def _watchdog(self) -> None:
        """Warn when a due step waits for its inputs for more than 5 s of wall time."""
        if self._due_since is None or self._inflight is not None:
            return
        step, since = self._due_since
        if step <= self._last_step_ns or step == self._warned_step:
            return
        if self._steady.now().nanoseconds - since > 5 * NS_PER_S:
            missing = [name for name, ok in (('zone state', self._state_for(step)),
                                             ('forecast', self._forecast_for(step))) if not ok]
            if missing:
                self.get_logger().warning(f'step {step / NS_PER_S:.0f} s is due but the '
                                          f"{' and '.join(missing)} for it has not arrived")
            self._warned_step = step

    def destroy_node(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        close = getattr(self.model, 'close', None)
        if close is not None:  # an FMU instance
            close()
        super().destroy_node()


def _trim(messages: dict[int, Any]) -> None:
    for stamp in sorted(messages)[:-KEEP_MESSAGES]:
        del messages[stamp]


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes mpc`` (set use_sim_time:=true against the emulator)."""
    rclpy.init(args=args)
    node = None
    try:
        node = MpcNode()
        bridge_core_logging(node.get_logger())
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (InvalidParameterValueException, ValueError, FileNotFoundError) as exc:
        rclpy.logging.get_logger('mpc').fatal(f'cannot start: {exc}')
        sys.exit(2)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
