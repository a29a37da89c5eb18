"""
The economic node: BOPTEST's economic MPC over ROS (every decision in core).

Answers every zone state on ``/zone/state`` with a setpoint on ``/mpc/setpoint`` stamped like
the state. The decision is :class:`mshoot_core.boptest.economic.EconomicController`'s (state
estimator, MPC and dispatcher of the planned duty); the node only converts:

- the first state carries the warm-up (``history_*`` fields of ZoneState: the emulator's
  ``boptest`` card with ``history_step_s``): the state estimate starts from its first zone
  temperature and observes each of its steps like any later step;
- every later state: the zone temperature ``T`` [K] and the step means of the outputs
  ``mean_Tout`` [degC], ``mean_solrad`` [W/m2] and ``mean_Q_hp`` [W] (the heat pump's
  condenser heat) over the step just run, observed as
  :meth:`~mshoot_core.boptest.economic.EconomicController.observe` does in the core run;
- the step's overwrite pieces (full-load bursts at 60 s resolution) go out as the setpoint's
  schedule within the step (``schedule_offsets_s``, ``schedule_values``; ``control_values``
  = the first piece's), the plan's zone temperature at the step's end as the zone's
  temperature setpoint.

Forecasts: the node does not read ``/forecast``. It plans on the perfect forecast the core run
uses (:meth:`~mshoot_core.boptest.economic.EconomicConfig.forecast`: interval means of the
test case's files, the same files the forecaster node serves as hourly point values), so that
a ROS run equals the core run.

The scenario parameters are the emulator's (``boptest:<period>[:<price>]``): both place the
test period at the same ROS time. Publishes its health on ``/diagnostics``.
"""
from __future__ import annotations

from typing import Any

from mshoot_core.boptest.economic import (controller_settings, EconomicController, KELVIN,
                                          MODES)
from mshoot_core.boptest.testcase import PRICE_SCENARIOS, TestCase
from mshoot_msgs.msg import Setpoint, ZoneState
import numpy as np
import pandas as pd

from mshoot_nodes import contract, sources
from mshoot_nodes.conversions import NS_PER_S, setpoint_msg, stamp_to_ns
from mshoot_nodes.diagnostics import DiagnosticsPublisher, Level, Report
from mshoot_nodes.lifecycle import ManagedNode
from mshoot_nodes.params import declare, ParamSpec, values
from mshoot_nodes.startup import run_node

#: FMU overwrite -> (card control, offset from the FMU's unit to the card's).
OVERWRITE_CONTROLS = {'oveHeaPumY_u': ('Y', 0.0), 'oveTSet_u': ('TSet', -KELVIN)}
#: ZoneState outputs the state estimator reads (step means) -> the plant record columns they
#: stand for and the offset from the output's unit to the record's.
MEASURED = {'mean_Tout': ('weaSta_reaWeaTDryBul_y', KELVIN),
            'mean_solrad': ('weaSta_reaWeaHGloHor_y', 0.0),
            'mean_Q_hp': ('reaQHeaPumCon_y', 0.0)}

PARAMS = (
    ParamSpec('scenario', 'boptest:peak_heat_day:constant', "the emulator's scenario: "
              "'boptest:<period>[:<price>]' (its price is the MPC's)", read_only=True),
    *sources.BOPTEST_SCENARIO_PARAMS,
    ParamSpec('mode', 'modulation', "how the plan reaches the building: 'modulation' "
              "(oveHeaPumY_u, card control Y), 'setpoint' or 'tracking' (oveTSet_u, TSet)",
              choices=MODES, read_only=True),
    ParamSpec('margin_k', 0.5, "raise of the band's lower edge in the plan [K]", low=0.0,
              high=5.0, read_only=True),
    ParamSpec('min_run_h', 0.0, "the heat pump's minimum run time [h] (0: none)", low=0.0,
              high=24.0, read_only=True),
    ParamSpec('horizon_steps', 36, 'MPC horizon [steps of 1 h]', low=1, high=1000,
              read_only=True),
    ParamSpec('zone_temperature', 'T', 'name of the zone temperature state and setpoint',
              read_only=True),
    ParamSpec('zone', 'zone', 'zone name (header.frame_id)', read_only=True),
)


def _frame(t1_s: float, outputs: dict[str, float]) -> pd.DataFrame:
    """One record row at ``t1_s`` [s] holding the step means in the plant's columns."""
    missing = [name for name in MEASURED if name not in outputs]
    if missing:
        raise ValueError(f'the zone state lacks the step means {missing}: the emulator needs '
                         'a boptest card with history_step_s (boptest_modulation.yaml)')
    row = {'time': float(t1_s)}
    row.update({column: float(outputs[name]) + offset
                for name, (column, offset) in MEASURED.items()})
    return pd.DataFrame([row])


class EconomicNode(ManagedNode):
    """Answers zone states with the economic MPC's setpoints (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('economic', **kwargs)
        declare(self, PARAMS, [sources.check_boptest_parameters])
        self.params = p = values(self, PARAMS)
        self.controller: EconomicController | None = None
        self.answered = 0
        self.steps: list[dict[str, Any]] = []
        self._last: tuple[int, Setpoint] | None = None
        self._observed_ns: int | None = None
        self._last_error = ''
        self.diagnostics = DiagnosticsPublisher(self, self.health, hardware_id=p['zone'])
        self.autostart()

    # -- lifecycle ------------------------------------------------------------------------
    def configure(self) -> None:
        """Load the scenario and the test case; build the core controller."""
        p = self.params
        scenario = sources.load_scenario(p['scenario'], p['data'], p['hours'])
        self.epoch_ns = sources.start_ns(scenario, p['start_time'])
        spec = scenario.attrs['boptest']
        self.start_fmu_s = float(spec['start_s'])
        price = spec.get('price', 'constant')
        if price not in PRICE_SCENARIOS:
            raise ValueError(f'unknown price scenario {price!r}')
        case = TestCase.load(p['data'] or None)
        self.config = controller_settings(case, price, p['mode'], margin_k=p['margin_k'],
                                          min_run_h=p['min_run_h'],
                                          horizon_steps=p['horizon_steps'])
        self.step_s = float(self.config.settings.problem.step_s)
        self.controller = EconomicController(self.config)
        self._setpoint_pub = self.create_lifecycle_publisher(Setpoint, contract.SETPOINT,
                                                             contract.DATA_QOS)
        self.get_logger().info(
            f"economic MPC on {p['scenario']}: mode {p['mode']}, margin {p['margin_k']:g} K, "
            f"minimum run {p['min_run_h']:g} h, horizon {p['horizon_steps']} h")

    def activate(self) -> None:
        """Answer zone states."""
        self.create_subscription(ZoneState, contract.ZONE_STATE, self._on_state,
                                 contract.DATA_QOS)

    def deactivate(self) -> None:
        """Nothing to hand back: the emulator holds or falls back on its own."""

    def cleanup(self) -> None:
        """Drop the controller."""
        self.controller = None

    # -- health ---------------------------------------------------------------------------
    def health(self) -> Report:
        """Return the node's health for /diagnostics."""
        values_ = {'answered': self.answered}
        if self.steps:
            last = self.steps[-1]
            values_.update(last_solve_s=last['solve_s'], last_success=last['success'])
        if self._last_error:
            return Report(Level.ERROR, self._last_error, values_)
        if self.controller is None:
            return Report(Level.OK, 'unconfigured', values_)
        if not self.steps:
            return Report(Level.OK, 'waiting for the first step', values_)
        if not self.steps[-1]['success']:
            return Report(Level.WARN, 'the last solve did not converge', values_)
        return Report(Level.OK, 'running', values_)

    # -- conversion -----------------------------------------------------------------------
    def fmu_time(self, stamp_ns: int) -> float:
        """Return the FMU time [s from 1 January] of a ROS stamp [ns]."""
        return self.start_fmu_s + (stamp_ns - self.epoch_ns) / NS_PER_S

    def _observe_history(self, msg: ZoneState, t_s: float) -> None:
        """Estimate the state from the warm-up carried by the first state, step by step."""
        m = len(msg.history_offsets_s)
        names = list(msg.state_names)
        zone = self.params['zone_temperature']
        if m < 1 or zone not in names:
            raise ValueError('the first zone state carries no warm-up history (the emulator '
                             'needs a boptest card with history_step_s)')
        states = np.asarray(msg.history_state_values, dtype=float).reshape(len(names), m)
        means = np.asarray(msg.history_output_values, dtype=float).reshape(
            len(msg.history_output_names), m)
        times = t_s + np.asarray(msg.history_offsets_s, dtype=float)
        tz = states[names.index(zone)]
        self.controller.start(times[0], tz[0])
        for k in range(1, m):
            outputs = {f'mean_{name}': float(means[j, k])
                       for j, name in enumerate(msg.history_output_names)}
            self.controller.observe(_frame(times[k], outputs), times[k - 1], times[k], tz[k])

    def _on_state(self, msg: ZoneState) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        if self._last is not None and stamp == self._last[0]:
            self._setpoint_pub.publish(self._last[1])  # a heartbeat: the same answer
            return
        if self.controller is None:
            return
        t = self.fmu_time(stamp)
        p = self.params
        try:
            if self._observed_ns != stamp:  # once per step (a failed decision is retried)
                states = dict(zip(msg.state_names, msg.state_values))
                if self._last is None:
                    self._observe_history(msg, t)
                else:
                    outputs = dict(zip(msg.output_names, msg.output_values))
                    self.controller.observe(_frame(t, outputs), t - self.step_s, t,
                                            states[p['zone_temperature']])
                self._observed_ns = stamp
            pieces, result = self.controller.decide(t)
        except (ValueError, KeyError, RuntimeError) as exc:
            self._last_error = f'cannot decide at {t:.0f} s: {exc}'
            self.get_logger().error(self._last_error)
            return
        self.steps.append({'time_s': t, 'solve_s': float(result.solve_time_s),
                           'success': bool(result.success)})
        out = self.setpoint(stamp, t, pieces, float(result.states[1, 0]) - KELVIN)
        self._last = (stamp, out)
        self._setpoint_pub.publish(out)
        self.answered += 1

    def setpoint(self, stamp_ns: int, t_s: float, pieces: list[tuple[float, dict[str, float]]],
                 planned_c: float) -> Setpoint:
        """Return the setpoint of a step's overwrite pieces (module docstring)."""
        starts = [t_s] + [end for end, _ in pieces[:-1]]
        names: list[str] = []
        columns: list[list[float]] = []
        for key in pieces[0][1]:
            if key not in OVERWRITE_CONTROLS:
                raise ValueError(f'no card control for the overwrite {key!r}')
            control, offset = OVERWRITE_CONTROLS[key]
            names.append(control)
            columns.append([float(piece[key]) + offset for _, piece in pieces])
        p = self.params
        msg = setpoint_msg(stamp_ns, self.step_s,
                           {name: column[0] for name, column in zip(names, columns)},
                           {p['zone_temperature']: planned_c}, zone=p['zone'])
        if len(pieces) > 1:
            msg.schedule_offsets_s = [float(s - t_s) for s in starts]
            msg.schedule_values = [v for column in columns for v in column]
        return msg


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes economic``: answer zone states until Ctrl-C."""
    run_node(EconomicNode, 'economic', args)


if __name__ == '__main__':
    main()
