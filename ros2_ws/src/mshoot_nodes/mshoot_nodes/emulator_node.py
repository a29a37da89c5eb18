"""The emulator node: the building, simulated by :class:`mshoot_core.emulation.Emulator`.

Publishes ``/clock`` (it drives simulated time), ``/zone/state`` and
``/zone/disturbances`` at every control step and applies the setpoints from
``/mpc/setpoint``, clipped to the actuator limits with a warning.

Modes (parameter ``mode``):

- ``lockstep`` (default): at each step the emulator waits for the setpoint
  stamped with that step, then advances at once. Simulated time runs as fast
  as the MPC answers and a ROS run reproduces the core-only loop
  (:func:`mshoot_core.closed_loop.run_closed_loop`) exactly. While it waits it
  re-publishes clock, state and disturbances every ``heartbeat_period_s`` (lost
  messages during discovery cannot stall the loop).
- ``free``: simulated time runs at ``speedup`` times the wall clock; at the
  end of each step the latest setpoint is applied (a stale one with a warning).

The node drives itself with STEADY_TIME timers (the node publishing /clock
must not wait on a simulated-time timer).
"""
from __future__ import annotations

import json
import pathlib
import sys
from typing import Any

from mshoot_core.emulation import Emulator, StepRecord
from mshoot_core.models.r1c1 import KELVIN
from mshoot_msgs.msg import Disturbances, Setpoint, ZoneState
import numpy as np
import pandas as pd
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg

from mshoot_nodes import contract, sources
from mshoot_nodes.conversions import (clock_msg, disturbances_msg, NS_PER_S, seconds_to_ns,
                                      setpoint_to_controls, stamp_to_ns, zone_state_msg)
from mshoot_nodes.logbridge import bridge_core_logging
from mshoot_nodes.params import declare, ordered, ParamSpec, values

PARAMS = (
    ParamSpec('scenario', 'synthetic', "the scenario: 'synthetic' (built in, no files), 'ou44' "
              '(the OU44 classroom data, see data) or a path to a CSV in the OU44 format',
              read_only=True),
    ParamSpec('data', '', "path of the OU44 measurements.csv for scenario 'ou44' "
              "('' = the default shared data folder)", read_only=True),
    ParamSpec('hours', 72, 'number of control steps to simulate [-]', low=1, high=1_000_000,
              read_only=True),
    ParamSpec('start_time', '', 'ROS time of the first scenario row, ISO date-time read as UTC '
              "('' = the scenario's own start date)", read_only=True),
    ParamSpec('model', 'fmu', "emulation model: 'fmu' (the built-in R1C1 FMU, Model Exchange), "
              "'fmu-cs' (Co-Simulation), 'python' (exact R1C1) or a path to an .fmu with the "
              "R1C1 zone's variables", read_only=True),
    ParamSpec('fmu_tolerance', 1e-10, 'relative tolerance of the FMU integrator [-]',
              low=1e-14, high=1e-2, read_only=True),
    ParamSpec('initial_temperature_c', 20.0, 'zone temperature at the first step [degC]',
              low=-50.0, high=80.0, read_only=True),
    ParamSpec('step_s', 3600.0, 'control step [s]', low=1.0, high=86400.0, read_only=True),
    ParamSpec('fine_step_s', 60.0, 'grid of the recorded fine trajectory [s]', low=1.0,
              high=86400.0, read_only=True),
    ParamSpec('heat_rate_min_w', -2000.0, 'actuator limit: largest cooling power, negative '
              '[W]', low=-1e7, high=1e7, read_only=True),
    ParamSpec('heat_rate_max_w', 2000.0, 'actuator limit: largest heating power [W]',
              low=-1e7, high=1e7, read_only=True),
    ParamSpec('mode', 'lockstep', 'lockstep: wait for the setpoint of every step (exact, '
              'as fast as the MPC); free: run at speedup times the wall clock',
              choices=('lockstep', 'free'), read_only=True),
    ParamSpec('speedup', 3600.0, 'free mode: simulated seconds per wall second [-]',
              low=1e-3, high=1e9),
    ParamSpec('clock_period_s', 0.02, 'free mode: wall time between /clock ticks [s]',
              low=1e-3, high=10.0, read_only=True),
    ParamSpec('heartbeat_period_s', 0.5, 'lockstep: wall time without a setpoint after which '
              'clock, state and disturbances are published again [s]', low=0.01, high=600.0,
              read_only=True),
    ParamSpec('min_state_subscribers', 1, 'start once /zone/state has this many subscribers '
              '(and, in lockstep, /mpc/setpoint a publisher) [-]', low=0, high=1000,
              read_only=True),
    ParamSpec('start_delay_s', 0.0, 'wall time to wait once the peers are found, so that they '
              'also find each other (separate processes) [s]', low=0.0, high=600.0,
              read_only=True),
    ParamSpec('output_dir', '', 'folder for trajectories.csv, applied.csv and run.json when '
              "the scenario ends ('' = write nothing)", read_only=True),
    ParamSpec('zone', 'zone', 'zone name (header.frame_id of the published messages)',
              read_only=True),
    ParamSpec('exit_when_done', True, 'stand-alone process: exit when the scenario ends',
              read_only=True),
)


def _check_sources(v: dict[str, Any]) -> str | None:
    if 'scenario' in v:
        reason = sources.check_scenario(v['scenario'], v.get('data', ''))
        if reason:
            return reason
    if 'model' in v and (reason := sources.check_model(v['model'])):
        return reason
    if 'start_time' in v and (reason := sources.check_start_time(v['start_time'])):
        return reason
    if 'step_s' in v and 'fine_step_s' in v and v['step_s'] % v['fine_step_s']:
        return (f"step_s must be a multiple of fine_step_s, got {v['step_s']} and "
                f"{v['fine_step_s']}")
    return None


def build_emulator(p: dict[str, Any]) -> Emulator:
    """The core emulator configured by the node's parameter values ``p``."""
    scenario = sources.load_scenario(p['scenario'], p['data'], p['hours'])
    model = sources.build_model(p['model'], p['fmu_tolerance'])
    return Emulator(model, scenario, [p['initial_temperature_c'] + KELVIN], control_names=('q',),
                    control_bounds=((p['heat_rate_min_w'], p['heat_rate_max_w']),),
                    step_s=p['step_s'], fine_step_s=p['fine_step_s'])


class EmulatorNode(Node):
    """The emulated building (see the module docstring).

    Attributes
    ----------
    emulator : Emulator
        The core emulator; the node only converts and times.
    records : list of StepRecord
        What every step did (controls, start and end states, fine trajectory).
    done : bool
        True once the scenario is over.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('emulator', **kwargs)
        declare(self, PARAMS, [ordered('heat_rate_min_w', 'heat_rate_max_w'), _check_sources])
        self.params = values(self, PARAMS)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        p = self.params
        self.emulator = build_emulator(p)
        self.epoch_ns = sources.start_ns(self.emulator.scenario, p['start_time'])
        self.step_ns = seconds_to_ns(p['step_s'])
        self.records: list[StepRecord] = []
        self.done = False
        self.started = False
        self._speedup = float(p['speedup'])
        self._last_heat_rate_w = 0.0
        self._latest_setpoint: Setpoint | None = None
        self._sim_ns = self.stamp_ns
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._last_publish_ns = 0
        self._wait_started_ns = 0
        self._peers_found_ns = 0
        self._step_started_ns = 0
        self._last_wait_warning_ns = 0
        self._run_started_ns = 0
        self.wall_s = 0.0

        self._clock_pub = self.create_publisher(ClockMsg, contract.CLOCK, contract.CLOCK_QOS)
        self._state_pub = self.create_publisher(ZoneState, contract.ZONE_STATE,
                                                contract.DATA_QOS)
        self._disturbance_pub = self.create_publisher(Disturbances, contract.ZONE_DISTURBANCES,
                                                      contract.DATA_QOS)
        self._setpoint_sub = self.create_subscription(Setpoint, contract.SETPOINT,
                                                      self._on_setpoint, contract.DATA_QOS)
        self._start_timer = self.create_timer(0.05, self._try_start, clock=self._steady)
        self._run_timer = None
        self.get_logger().info(
            f"{p['scenario']} scenario, {p['hours']} steps of {p['step_s']:.0f} s from "
            f"{pd.Timestamp(self.epoch_ns, tz='UTC').isoformat()}, model {p['model']}, "
            f"{p['mode']} mode; T0 = {p['initial_temperature_c']:.2f} degC, actuator "
            f"[{p['heat_rate_min_w']:.0f}, {p['heat_rate_max_w']:.0f}] W")

    # -- time -----------------------------------------------------------------------------
    @property
    def stamp_ns(self) -> int:
        """ROS time of the current step [ns]."""
        return self.epoch_ns + seconds_to_ns(self.emulator.t_s)

    def _steady_ns(self) -> int:
        return self._steady.now().nanoseconds

    # -- parameters -----------------------------------------------------------------------
    def _on_parameters_set(self, params: list) -> None:
        for param in params:
            if param.name == 'speedup':
                self._speedup = float(param.value)
                self.get_logger().info(f'speed-up set to {self._speedup:g}')

    # -- start ----------------------------------------------------------------------------
    def _try_start(self) -> None:
        """Start once the peers are there (polled on a steady timer)."""
        wanted = self.params['min_state_subscribers']
        have = self.count_subscribers(self._state_pub.topic_name)
        mpc_ok = (self.params['mode'] != 'lockstep' or wanted == 0
                  or self.count_publishers(self._setpoint_sub.topic_name) > 0)
        now = self._steady_ns()
        if not self._wait_started_ns:
            self._wait_started_ns = now
        if have < wanted or not mpc_ok:
            self._peers_found_ns = 0
            if now - self._last_wait_warning_ns > 5 * NS_PER_S:
                if self._last_wait_warning_ns:
                    self.get_logger().warning(
                        f'waiting for peers: {have}/{wanted} subscribers of '
                        f'{self._state_pub.topic_name}, setpoint publisher '
                        f"{'found' if mpc_ok else 'missing'}")
                self._last_wait_warning_ns = now
            return
        if not self._peers_found_ns:
            self._peers_found_ns = now
        if now - self._peers_found_ns < seconds_to_ns(self.params['start_delay_s']):
            return
        self._start_timer.cancel()
        self.destroy_timer(self._start_timer)
        self.started = True
        self._run_started_ns = self._step_started_ns = now
        self.get_logger().info(f'starting the scenario at {self.stamp_ns / NS_PER_S:.0f} s '
                               'ROS time')
        self._publish_step()
        if self.params['mode'] == 'lockstep':
            self._run_timer = self.create_timer(self.params['heartbeat_period_s'],
                                                self._heartbeat, clock=self._steady)
        else:
            self._run_timer = self.create_timer(self.params['clock_period_s'], self._tick,
                                                clock=self._steady)

    # -- publishing -----------------------------------------------------------------------
    def _publish_step(self) -> None:
        """Publish clock, disturbances and state of the current step."""
        stamp = self.stamp_ns
        zone = self.params['zone']
        self._clock_pub.publish(clock_msg(stamp))
        self._sim_ns = stamp
        self._disturbance_pub.publish(disturbances_msg(stamp, self.emulator.disturbances(),
                                                       zone))
        self._state_pub.publish(zone_state_msg(stamp, self.emulator.x[0], self._last_heat_rate_w,
                                               zone))
        self._last_publish_ns = self._steady_ns()

    def _heartbeat(self) -> None:
        """Lockstep: re-publish the current step while no setpoint comes."""
        if self.done:
            return
        now = self._steady_ns()
        waited = now - self._last_publish_ns
        if waited < seconds_to_ns(self.params['heartbeat_period_s']):
            return
        step_waited = now - self._step_started_ns
        if step_waited > 10 * NS_PER_S and now - self._last_wait_warning_ns > 10 * NS_PER_S:
            self.get_logger().warning(
                f'no setpoint stamped {self.stamp_ns / NS_PER_S:.0f} s after '
                f'{step_waited / NS_PER_S:.0f} s (step {len(self.records) + 1}/'
                f'{len(self.records) + self.emulator.steps_left}): is the MPC running?')
            self._last_wait_warning_ns = now
        self.get_logger().debug('no setpoint yet: publishing the step again')
        self._publish_step()

    # -- stepping -------------------------------------------------------------------------
    def _on_setpoint(self, msg: Setpoint) -> None:
        if self.done:
            return
        if self.params['mode'] != 'lockstep':
            self._latest_setpoint = msg
            return
        if not self.started:
            return
        stamp = stamp_to_ns(msg.header.stamp)
        if stamp != self.stamp_ns:
            if stamp > self.stamp_ns:
                self.get_logger().warning(
                    f'setpoint for a future step ({stamp / NS_PER_S:.0f} s) while at '
                    f'{self.stamp_ns / NS_PER_S:.0f} s: ignored')
            return
        self._advance(setpoint_to_controls(msg))

    def _tick(self) -> None:
        """Free mode: advance simulated time by ``clock_period_s * speedup``."""
        if self.done:
            return
        self._sim_ns += int(self.params['clock_period_s'] * self._speedup * NS_PER_S)
        if self._sim_ns < self.stamp_ns + self.step_ns:
            self._clock_pub.publish(clock_msg(self._sim_ns))
            return
        setpoint = self._latest_setpoint
        if setpoint is None:
            self.get_logger().warning(f'no setpoint received for step '
                                      f'{self.stamp_ns / NS_PER_S:.0f} s: applying 0 W')
            controls = np.zeros(1)
        else:
            stamp = stamp_to_ns(setpoint.header.stamp)
            if stamp != self.stamp_ns:
                self.get_logger().warning(
                    f'no setpoint for step {self.stamp_ns / NS_PER_S:.0f} s: holding the one '
                    f'stamped {stamp / NS_PER_S:.0f} s ({setpoint.heat_rate_w:.1f} W)')
            controls = setpoint_to_controls(setpoint)
        self._advance(controls)

    def _advance(self, controls: np.ndarray) -> None:
        """Apply ``controls`` over the current step, publish the next one."""
        bounds = self.emulator.control_bounds
        clipped = np.clip(controls, bounds[:, 0], bounds[:, 1])
        if np.any(clipped != controls):
            self.get_logger().warning(
                f'setpoint {controls[0]:.1f} W at {self.stamp_ns / NS_PER_S:.0f} s is outside '
                f'the actuator limits [{bounds[0, 0]:.0f}, {bounds[0, 1]:.0f}] W: applying '
                f'{clipped[0]:.1f} W')
        record = self.emulator.advance(clipped)
        self._step_started_ns = self._steady_ns()
        self.records.append(record)
        self._last_heat_rate_w = float(record.controls[0])
        self.get_logger().debug(
            f'step {len(self.records)}: q = {record.controls[0]:.1f} W, T '
            f'{record.x_start[0] - KELVIN:.3f} -> {record.x_end[0] - KELVIN:.3f} degC')
        self._publish_step()
        if self.emulator.steps_left == 0:
            self._finish()

    def _finish(self) -> None:
        self.done = True
        self.wall_s = (self._steady_ns() - self._run_started_ns) / NS_PER_S
        if self._run_timer is not None:
            self._run_timer.cancel()
        temps = [r.x_end[0] - KELVIN for r in self.records]
        self.get_logger().info(
            f'scenario over: {len(self.records)} steps in {self.wall_s:.2f} s wall, zone '
            f'temperature {min(temps):.2f} to {max(temps):.2f} degC')
        if self.params['output_dir']:
            self.write_outputs(pathlib.Path(self.params['output_dir']))

    # -- records --------------------------------------------------------------------------
    def fine_frame(self) -> pd.DataFrame:
        """The fine-grid trajectory of all steps so far (as the core loop builds it)."""
        if not self.records:
            return pd.DataFrame()
        return pd.concat([r.fine if k == 0 else r.fine.iloc[1:]
                          for k, r in enumerate(self.records)])

    def applied_frame(self) -> pd.DataFrame:
        """One row per step: ROS stamp [ns], applied controls [W], start and end states.

        Index ``time_s`` (scenario time [s]); columns ``stamp_ns``, ``q``,
        ``<state>_start``, ``<state>_end``.
        """
        rows = []
        for record in self.records:
            row = {'time_s': record.t_start_s,
                   'stamp_ns': self.epoch_ns + seconds_to_ns(record.t_start_s)}
            for name, value in zip(self.emulator.control_names, record.controls):
                row[name] = float(value)
            for i, name in enumerate(self.emulator.model.state_names):
                row[f'{name}_start'] = float(record.x_start[i])
                row[f'{name}_end'] = float(record.x_end[i])
            rows.append(row)
        return pd.DataFrame(rows).set_index('time_s')

    def destroy_node(self) -> None:
        close = getattr(self.emulator.model, 'close', None)
        if close is not None:  # an FMU instance
            close()
        super().destroy_node()

    def write_outputs(self, out: pathlib.Path) -> None:
        """Write trajectories.csv, applied.csv and run.json to ``out``."""
        out.mkdir(parents=True, exist_ok=True)
        self.fine_frame().to_csv(out / 'trajectories.csv', index_label='time_s')
        self.applied_frame().to_csv(out / 'applied.csv', index_label='time_s')
        keys = ('scenario', 'data', 'hours', 'model', 'mode', 'initial_temperature_c', 'step_s')
        run = {key: self.params[key] for key in keys}
        run.update(epoch_ns=self.epoch_ns, steps=len(self.records), wall_s=self.wall_s)
        (out / 'run.json').write_text(json.dumps(run, indent=2) + '\n')
        self.get_logger().info(f'wrote {out}/trajectories.csv, applied.csv, run.json')


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes emulator``: run until the scenario ends (or Ctrl-C)."""
    rclpy.init(args=args)
    node = None
    try:
        node = EmulatorNode()
        bridge_core_logging(node.get_logger())
        while rclpy.ok() and not (node.done and node.params['exit_when_done']):
            rclpy.spin_once(node, timeout_sec=0.5)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (InvalidParameterValueException, ValueError, FileNotFoundError) as exc:
        rclpy.logging.get_logger('emulator').fatal(f'cannot start: {exc}')
        sys.exit(2)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
