"""
The emulator node: the building, simulated by :class:`mshoot_core.emulation.Emulator`.

Publishes ``/clock`` (it drives simulated time), ``/zone/state`` (the model's
states, its outputs after the last step and the controls applied, as named
vectors) and ``/zone/disturbances`` (the model's disturbance inputs of the
step, by name) at every control step and applies the setpoints from
``/mpc/setpoint`` (every control of the model, by name), clipped to the
actuator limits with a warning. Any model of the registry runs, with one or
several controls and zones (e.g. ``model:=r1c1x2``: two zones, controls
``q_0``, ``q_1``); every control has the actuator limits of the model's card
(:mod:`mshoot_core.controls`), narrowed by ``control_min``, ``control_max``.

Modes (parameter ``mode``):

- ``lockstep`` (default): at each step the emulator waits for the setpoint
  stamped with that step, then advances at once. Simulated time runs as fast
  as the MPC answers and a ROS run reproduces the core-only loop
  (:func:`mshoot_core.closed_loop.run_closed_loop`) exactly. While it waits it
  re-publishes clock, state and disturbances every ``heartbeat_period_s`` (lost
  messages during discovery cannot stall the loop).
- ``free``: simulated time runs at ``speedup`` times the wall clock; at the
  end of each step the setpoint of the step is applied. While it has not come,
  state and disturbances are re-published every ``heartbeat_period_s`` (a
  message lost, e.g. displaced from a reader's queue by a flood, is sent again;
  the MPC answers a repeated state with its setpoint again).

Safety (the rules are in :mod:`mshoot_core.safety`):

- every setpoint is validated whole before any of it is used (array lengths
  within the model's dimensions before anything is converted, exactly the
  model's controls by name, finite, plausible, the control step, consistent
  plan and schedule arrays, stamped with a step start, neither for a future
  step nor going backwards, nor, in lockstep, for a step already done;
  :func:`mshoot_core.safety.check_setpoint`); a rejected one is
  counted (``rejections``, ``run.json``) and logged one line each,
  rate-limited, never reaches the building and moves nothing (the newest
  stamp, the held setpoint);
- a second publisher of ``/mpc/setpoint`` (any node but ``setpoint_writer``)
  is reported as an intruder on /diagnostics (:mod:`mshoot_nodes.peers`), and
  the MPC as STALE when no setpoint came for ``peer_timeout_s``;
- when a step has no setpoint (free mode, or lockstep after
  ``lockstep_timeout_s`` of wall time with ``on_lockstep_timeout`` 'hold'),
  the last setpoint is held for ``hold_s`` of simulated time, then the safe
  values (the card's, or ``safe_value``) are applied
  (:class:`~mshoot_core.safety.SetpointHold`); with 'stop' (default) the run
  ends with a clear error instead of waiting forever (exit code 1);
- a model that raises or returns non-finite states ends the run with an
  error; nothing non-finite is ever published;
- ``start_step`` and ``initial_temperature_c`` restart a run mid-scenario
  from a given time and state (``initial_states`` sets single states apart,
  e.g. the envelope of an R2C2).

Sensors (:class:`mshoot_core.estimation.Sensors`): ``/zone/state`` carries the
``measured_states`` only (default: all), with seeded Gaussian noise of
``measurement_noise_k`` (the same per step as the offline loop's
``run_closed_loop(..., sensors=...)``, re-published heartbeats included); the
records (``trajectories.csv``) keep the true states.

Lifecycle (:mod:`mshoot_nodes.lifecycle`; ``autostart`` true by default, so a
plain ``ros2 run`` configures and activates at once): *configure* loads the
scenario and the model (the FMU) and creates the publishers; *activate*
subscribes to the setpoints and opens the start gate, or resumes a paused run;
*deactivate* pauses the run (no clock, no steps); *cleanup* frees the FMU (the
records stay readable; a new configure starts a fresh run).

Start gate (:mod:`mshoot_nodes.readiness`): the scenario starts once the ROS
graph shows every endpoint of ``ready_endpoints`` (by default a subscriber of
``/zone/state`` and a publisher of ``/mpc/setpoint``; the bring-ups add the
forecaster and the recorder), then ``start_delay_s`` later; after
``ready_timeout_s`` it stops with an error naming what is missing (exit code 1).

Health on ``/diagnostics`` (``mshoot/emulator``): step, applied sources
(setpoint, held, safe), rejected setpoints, lockstep waits and timeouts.

The node drives itself with STEADY_TIME timers (the node publishing /clock
must not wait on a simulated-time timer).
"""
from __future__ import annotations

import collections
import json
import logging
import math
import pathlib
import sys
from typing import Any

from mshoot_core.controls import model_controls, narrowed, safe_values
from mshoot_core.emulation import Emulator, initial_state, StepRecord
from mshoot_core.estimation import Sensors
from mshoot_core.models.card import time_origin_seconds
from mshoot_core.models.registry import (control_interface, ControlInterface,
                                         EMULATOR_TOLERANCE)
from mshoot_core.peers import Peer
from mshoot_core.safety import (check_lengths, check_setpoint, check_stamp_fields, Rejection,
                                reorder, setpoint_caps, SetpointHold, StampGate)
from mshoot_core.settings import BY_NAME
from mshoot_core.units import NS_PER_S
from mshoot_msgs.msg import Disturbances, Setpoint, ZoneState
import numpy as np
import pandas as pd
from rclpy.logging import LoggingSeverity
from rosgraph_msgs.msg import Clock as ClockMsg

from mshoot_nodes import contract, sources
from mshoot_nodes.conversions import (clock_msg, disturbances_msg, field_lengths, seconds_to_ns,
                                      stamp_to_ns, zone_state_msg)
from mshoot_nodes.diagnostics import DiagnosticsPublisher, Level, Report
from mshoot_nodes.lifecycle import ManagedNode
from mshoot_nodes.params import declare, ParamSpec, values
from mshoot_nodes.peers import PeerMonitor
from mshoot_nodes.readiness import check_requirements, parse_requirements, ReadinessGate
from mshoot_nodes.startup import run_node
from mshoot_nodes.validation import RejectionLog

logger = logging.getLogger(__name__)
PARAMS = (
    ParamSpec('scenario', 'synthetic', "the scenario: 'synthetic' (built in, no files), 'ou44' "
              "(the OU44 classroom data, see data), 'boptest:<period>[:<price>]' (a BOPTEST "
              'test period, with a boptest model card) or a path to a CSV in the OU44 format',
              read_only=True),
    ParamSpec('data', '', "path of the OU44 measurements.csv for scenario 'ou44', of the "
              "test case folder for a BOPTEST scenario ('' = the default shared data folder)",
              read_only=True),
    ParamSpec('hours', 72, 'number of control steps to simulate [-]', low=1, high=1_000_000,
              read_only=True),
    ParamSpec('start_time', '', 'ROS time of the first scenario row, ISO date-time read as UTC '
              "('' = the scenario's own start date)", read_only=True),
    ParamSpec('model', 'fmu', "emulation model: 'fmu' (the built-in R1C1 FMU, Model Exchange), "
              "'fmu-cs' (Co-Simulation), 'python' (exact R1C1), 'r1c1x2' (two R1C1 zones, "
              "controls q_0, q_1), a path to an .fmu with the R1C1 zone's variables, or a path "
              'to a model card (.yaml)', read_only=True),
    ParamSpec('fmu_tolerance', EMULATOR_TOLERANCE, 'relative tolerance of the FMU integrator [-]',
              low=1e-14, high=1e-2, read_only=True),
    ParamSpec('initial_temperature_c', 20.0, 'zone temperature at the first step: every '
              'state of the model starts at it (in K) [degC]', low=-50.0, high=80.0,
              read_only=True),
    ParamSpec('initial_states', '', 'states starting elsewhere than initial_temperature_c, '
              "comma-separated 'name=degC' (e.g. 'Tw=18': the envelope of model r2c2) [degC]",
              read_only=True),
    ParamSpec('measured_states', '', "states published on /zone/state, comma-separated ('' = "
              'all: the sensors of the building)', read_only=True),
    ParamSpec('measurement_noise_k', 0.0, 'standard deviation of the Gaussian noise on the '
              'published states (0 = exact) [K]', low=0.0, high=100.0, read_only=True),
    ParamSpec('noise_seed', 0, 'seed of the measurement noise (the same per step as the '
              'offline loop with that seed) [-]', low=0, high=2 ** 31 - 1, read_only=True),
    ParamSpec('start_step', 0, 'scenario step to start at (a restart mid-run, with '
              'initial_temperature_c the state then) [-]', low=0, high=1_000_000,
              read_only=True),
    ParamSpec('step_s', 3600.0, 'control step [s]', low=1.0, high=86400.0, read_only=True),
    ParamSpec('fine_step_s', 60.0, 'grid of the recorded fine trajectory [s]', low=1.0,
              high=86400.0, read_only=True),
    ParamSpec('control_min', math.nan, BY_NAME['control_min'].description, read_only=True),
    ParamSpec('control_max', math.nan, BY_NAME['control_max'].description, read_only=True),
    ParamSpec('mode', 'lockstep', 'lockstep: wait for the setpoint of every step (exact, '
              'as fast as the MPC); free: run at speedup times the wall clock',
              choices=('lockstep', 'free'), read_only=True),
    ParamSpec('speedup', 3600.0, 'free mode: simulated seconds per wall second [-]',
              low=1e-3, high=1e9),
    ParamSpec('clock_period_s', 0.02, 'free mode: wall time between /clock ticks [s]',
              low=1e-3, high=10.0, read_only=True),
    ParamSpec('heartbeat_period_s', 0.5, 'wall time without the setpoint of the step after '
              'which state and disturbances (and, in lockstep, the clock) are published again '
              '[s]', low=0.01, high=600.0, read_only=True),
    ParamSpec('lockstep_timeout_s', 60.0, 'lockstep: wall time a step waits for its setpoint '
              'before on_lockstep_timeout applies [s]', low=0.01, high=86400.0),
    ParamSpec('on_lockstep_timeout', 'stop', "lockstep, no setpoint in time: 'stop' ends the "
              "run with an error, 'hold' applies the held or safe setpoint and goes on",
              choices=('stop', 'hold')),
    ParamSpec('hold_s', 3600.0, 'a step without its setpoint applies the last one while it is '
              'at most this old (simulated time), else the safe default [s]', low=0.0,
              high=1e7),
    ParamSpec('safe_value', math.nan, 'safe value of every control when no setpoint can be '
              "held, overriding the card's safe (NaN: the card's, else 0 within the limits) "
              "[the control's unit]"),
    ParamSpec('reject_log_period_s', 5.0, 'at most one log line per kind of rejected '
              'setpoint in this wall time [s]', low=0.0, high=3600.0, read_only=True),
    ParamSpec('ready_endpoints', [f'{contract.ZONE_STATE} subscribers>=1',
                                  f'{contract.SETPOINT} publishers>=1'],
              "start once the ROS graph shows these endpoints ('TOPIC publishers>=N', "
              "'TOPIC subscribers>=N'; [''] = start at once)", read_only=True),
    ParamSpec('ready_timeout_s', 120.0, 'wall time the start gate waits for ready_endpoints '
              'before the run stops with an error naming the missing ones (0 = forever) [s]',
              low=0.0, high=86400.0, read_only=True),
    ParamSpec('start_delay_s', 0.0, 'wall time to wait once the endpoints are there, so that '
              'the peers also find each other (separate processes) [s]', low=0.0, high=600.0,
              read_only=True),
    ParamSpec('setpoint_writer', 'mpc', 'name of the one node expected to publish '
              '/mpc/setpoint: any other is reported as an intruder on /diagnostics',
              read_only=True),
    ParamSpec('peer_timeout_s', 30.0, 'wall time without a setpoint after which the MPC is '
              'reported STALE on /diagnostics [s]', low=0.1, high=1e6, read_only=True),
    ParamSpec('output_dir', '', 'folder for trajectories.csv, applied.csv and run.json when '
              "the scenario ends ('' = write nothing)", read_only=True),
    ParamSpec('plant_state_file', '', 'file of the FMU plant state: saved after every step '
              '(where the FMU can serialise its state); a run with start_step > 0 resumes '
              "from it when it holds that step ('' = none)", read_only=True),
    ParamSpec('records_kept', 0, 'step records kept in memory (0 = all; the outputs cover the '
              'kept ones: a bound for long runs) [-]', low=0, high=100_000_000, read_only=True),
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
    if {'start_step', 'hours'} <= v.keys() and v['start_step'] >= v['hours']:
        return (f"start_step must be < hours (steps 0 to {v['hours'] - 1}), got "
                f"{v['start_step']}")
    if {'control_min', 'control_max'} <= v.keys() and not (
            math.isnan(v['control_min']) or math.isnan(v['control_max'])
            or v['control_min'] < v['control_max']):
        return (f"control_min must be < control_max, got {v['control_min']} and "
                f"{v['control_max']}")
    if 'ready_endpoints' in v and (reason := check_requirements(v['ready_endpoints'])):
        return f'ready_endpoints: {reason}'
    return None


def build_emulator(p: dict[str, Any]) -> Emulator:
    """
    Build the core emulator configured by the node's parameter values ``p``.

    The model's controls (:func:`~mshoot_core.models.registry.control_interface`) within the
    actuator limits, every state starting at ``initial_temperature_c`` (in K).
    """
    scenario = sources.load_scenario(p['scenario'], p['data'], p['hours'])
    model = sources.build_model(p['model'], p['fmu_tolerance'], role='emulator')
    card = getattr(model, 'card', None)  # a plant built from a card (a BOPTEST test case)
    if card is not None:
        model.time_origin_s = time_origin_seconds(card, scenario.attrs.get('start'))
    controls = control_interface(model).control_names
    specs = model_controls(model, controls)  # the card's units, limits and safe values
    bounds = tuple(narrowed((-math.inf if math.isnan(c.min) else c.min,  # open: not clipped
                             math.inf if math.isnan(c.max) else c.max),
                            p['control_min'], p['control_max']) for c in specs)
    wrong = [c.label() for c, (low, high) in zip(specs, bounds) if not low < high]
    if wrong:
        raise ValueError(f'controls {wrong} have no range within the limits {list(bounds)} '
                         "(the card's, narrowed by control_min, control_max)")
    start = p.get('start_step', 0)
    saved = p.get('plant_state_file', '')
    plant_state = None
    if start > 0 and saved and pathlib.Path(saved).is_file():
        plant_state = pathlib.Path(saved).read_bytes()  # its time is checked on restore
        logger.info('resuming the plant at step %d from %s', start, saved)
    return Emulator(model, scenario, initial_state(
        model.state_names, p['initial_temperature_c'], p.get('initial_states', '')),
        control_names=controls, control_bounds=bounds,
        step_s=p['step_s'], fine_step_s=p['fine_step_s'], start_index=start,
        plant_state=plant_state)


class EmulatorNode(ManagedNode):
    """
    The emulated building (see the module docstring).

    Attributes
    ----------
    emulator : Emulator or None
        The core emulator (None before the first configure); the node only
        converts and times.
    records : list of StepRecord
        What every step did (controls, start and end states, fine trajectory);
        the last ``records_kept`` when that is set.
    steps_done : int
        Steps applied so far.
    started : bool
        True once the start gate opened.
    done : bool
        True once the scenario is over (or the run failed).
    failed : str
        '' or why the run stopped early (a lockstep timeout, a model error, peers
        not ready in time).
    rejections : RejectionLog
        Rejected setpoints by kind.
    applied_sources : list of str
        Per step: 'setpoint', 'held' or 'safe' (see SetpointHold).
    lockstep_waits : int
        Times a step was published again because its setpoint had not come.
    lockstep_timeouts : int
        Steps that went on without their setpoint (on_lockstep_timeout 'hold').
    setpoint_waits_s : list of float
        Lockstep: wall time from the start of each step (its publication) to its accepted
        setpoint [s]: the controller's time between two advances (BOPTEST's ``time_rat``).
    gate : ReadinessGate or None
        The start gate while it waits.
    diagnostics : DiagnosticsPublisher
        Publishes :meth:`health` on /diagnostics.

    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('emulator', **kwargs)
        declare(self, PARAMS, [_check_sources])
        self.params = values(self, PARAMS)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        p = self.params
        self.emulator: Emulator | None = None
        self.interface: ControlInterface | None = None
        self.epoch_ns = 0
        self.step_ns = seconds_to_ns(p['step_s'])
        self._speedup = float(p['speedup'])
        self._steady = self.steady_clock
        self.gate: ReadinessGate | None = None
        self._run_timer = None
        self._reset_run()
        self.peers = PeerMonitor(self, [Peer('setpoint', contract.SETPOINT, p['setpoint_writer'],
                                             p['peer_timeout_s'])])
        self.diagnostics = DiagnosticsPublisher(self, self.health, hardware_id=p['zone'],
                                                peers=self.peers)
        self.autostart()

    def _reset_run(self) -> None:
        """Fresh run state (at construction and at every configure)."""
        p = self.params
        self.records: list[StepRecord] = []
        self.steps_done = 0
        self.done = False
        self.failed = ''
        self._plant_unsaveable = False
        self.started = False
        self.rejections = RejectionLog(self, p['reject_log_period_s'])
        self.applied_sources: list[str] = []
        self.lockstep_waits = 0
        self.lockstep_timeouts = 0
        self.setpoint_waits_s: list[float] = []
        self._reported_rejections = 0
        self._hold = SetpointHold(self._safe_controls(), p['hold_s'],
                                  [c.releasable for c in self.emulator.control_specs]
                                  if self.emulator is not None else ())
        self._setpoint_gate = StampGate(self.step_ns, max_age_ns=(
            0 if p['mode'] == 'lockstep' else seconds_to_ns(p['hold_s'])),
            origin_ns=self.epoch_ns)  # setpoints are stamped with their step's start
        self._sim_ns = self.stamp_ns if self.emulator is not None else 0
        self._last_publish_ns = 0
        self._step_started_ns = 0
        self._last_wait_warning_ns = 0
        self._run_started_ns = 0
        self.wall_s = 0.0

    # -- lifecycle --------------------------------------------------------------------------
    def configure(self) -> None:
        """Load the scenario and the model (the FMU), create the publishers."""
        p = self.params
        self.emulator = build_emulator(p)
        if getattr(self.emulator.model, 'history_step_s', 0.0) > 0:
            # a BOPTEST plant whose warm-up the controller observes: warm up now, so that the
            # first state is the warmed-up building's and carries the warm-up's history
            self.emulator.start_plant(self._safe_controls())
        self.interface = control_interface(self.emulator.model)
        # The disturbances it publishes, as an array (a pandas row per step costs more than
        # the message).
        self._disturbance_names = [name for name in self.emulator.model.input_names
                                   if name not in self.emulator.control_names]
        scenario = self.emulator.scenario
        self._disturbance_table = np.column_stack(
            [scenario[name].to_numpy(dtype=float) for name in self._disturbance_names]
        ) if self._disturbance_names else np.empty((len(scenario), 0))
        self.sensors = Sensors(self.emulator.model.state_names,
                               [n.strip() for n in p['measured_states'].split(',') if n.strip()],
                               p['measurement_noise_k'], p['noise_seed'])
        self.epoch_ns = sources.start_ns(self.emulator.scenario, p['start_time'])
        self._reset_run()
        self._clock_pub = self.create_lifecycle_publisher(ClockMsg, contract.CLOCK,
                                                          contract.CLOCK_QOS)
        self._state_pub = self.create_lifecycle_publisher(ZoneState, contract.ZONE_STATE,
                                                          contract.DATA_QOS)
        self._disturbance_pub = self.create_lifecycle_publisher(
            Disturbances, contract.ZONE_DISTURBANCES, contract.DATA_QOS)
        self.get_logger().info(
            f"{p['scenario']} scenario, {p['hours']} steps of {p['step_s']:.0f} s from "
            f"{pd.Timestamp(self.epoch_ns, tz='UTC').isoformat()}, model {p['model']}, "
            f"{p['mode']} mode; T0 = {p['initial_temperature_c']:.2f} degC, controls: "
            + ', '.join(f'{name} within [{low:g}, {high:g}]' for name, (low, high) in zip(
                self.emulator.control_names, self.emulator.control_bounds)))

    def activate(self) -> None:
        """Take setpoints; open the start gate, or resume a paused run."""
        p = self.params
        self._setpoint_sub = self.create_subscription(Setpoint, contract.SETPOINT,
                                                      self._on_setpoint, contract.DATA_QOS)
        if self.done:
            return
        if not self.started:
            self.gate = ReadinessGate(
                self, parse_requirements(p['ready_endpoints']), on_ready=self._start,
                on_timeout=self._not_ready, timeout_s=p['ready_timeout_s'],
                settle_s=p['start_delay_s'])
            return
        self.get_logger().info(f'resuming at step {self.steps_done + 1} '
                               f'({self.stamp_ns / NS_PER_S:.0f} s)')
        self._step_started_ns = self._steady_ns()
        self._publish_step()
        self._start_run_timer()

    def deactivate(self) -> None:
        """Pause: no more clock, steps or setpoints (resumed by activate)."""
        if self.started and not self.done:
            self.get_logger().info(f'paused before step {self.steps_done + 1} '
                                   f'({self.stamp_ns / NS_PER_S:.0f} s)')
        self.gate = None
        self._run_timer = None  # destroyed with what the activation created

    def cleanup(self) -> None:
        """Free the model (an FMU instance); the records stay readable."""
        self.gate = None
        self._run_timer = None
        close = getattr(getattr(self.emulator, 'model', None), 'close', None)
        if close is not None:
            close()

    # -- health -----------------------------------------------------------------------------
    def health(self) -> Report:
        """Return the emulator's status for /diagnostics."""
        sources_count = collections.Counter(self.applied_sources)
        rejected = self.rejections.total()
        values_ = {
            'mode': self.params['mode'],
            'step': self.steps_done,
            'steps_total': (self.steps_done + self.emulator.steps_left
                            if self.emulator is not None else self.params['hours']),
            'sim_time': (pd.Timestamp(self.stamp_ns, tz='UTC').isoformat()
                         if self.emulator is not None else ''),
            'applied_setpoint': sources_count['setpoint'],
            'applied_held': sources_count['held'],
            'applied_safe': sources_count['safe'],
            'rejected_setpoints': rejected,
            'rejected_by_kind': self.rejections.counter.by_kind() or 'none',
            'lockstep_waits': self.lockstep_waits,
            'lockstep_timeouts': self.lockstep_timeouts,
        }
        new_rejections, self._reported_rejections = (rejected - self._reported_rejections,
                                                     rejected)
        if self.failed:
            return Report(Level.ERROR, f'run stopped: {self.failed}', values_)
        if self.done:
            return Report(Level.OK, f'scenario over: {self.steps_done} steps', values_)
        if not self.is_configured:
            return Report(Level.OK, 'unconfigured', values_)
        if not self.is_active:
            if self.started:
                return Report(Level.WARN, f'paused before step {self.steps_done + 1}', values_)
            return Report(Level.OK, 'inactive', values_)
        if not self.started:
            missing = self.gate.missing if self.gate is not None else []
            values_['waiting_for'] = missing or 'none'
            text = f": {'; '.join(missing)}" if missing else ''
            return Report(Level.OK, f'waiting for peers{text}', values_)
        message = f'step {self.steps_done + 1} of {values_["steps_total"]}'
        if self.applied_sources and self.applied_sources[-1] != 'setpoint':
            return Report(Level.WARN, f'{message}: the last step applied the '
                          f'{self.applied_sources[-1]} setpoint', values_)
        if new_rejections:
            return Report(Level.WARN, f'{message}: {new_rejections} setpoints rejected since '
                          'the last report', values_)
        waited_s = (self._steady_ns() - self._step_started_ns) / NS_PER_S
        if self.params['mode'] == 'lockstep' and waited_s > 10.0:
            return Report(Level.WARN, f'{message}: waiting {waited_s:.0f} s for its setpoint',
                          values_)
        return Report(Level.OK, message, values_)

    # -- time -----------------------------------------------------------------------------
    @property
    def stamp_ns(self) -> int:
        """ROS time of the current step [ns]."""
        return self.epoch_ns + seconds_to_ns(self.emulator.t_s)

    def _steady_ns(self) -> int:
        return self._steady.now().nanoseconds

    def _safe_controls(self) -> tuple[float, ...]:
        """Return the safe value of every model control (0 before the first configure)."""
        if self.emulator is None:
            return (0.0,)
        e = self.emulator
        return safe_values(e.control_specs, e.control_bounds, self.params['safe_value'])

    # -- parameters -----------------------------------------------------------------------
    def _on_parameters_set(self, params: list) -> None:
        self.params = values(self, PARAMS)
        for param in params:
            if param.name == 'speedup':
                self._speedup = float(param.value)
                self.get_logger().info(f'speed-up set to {self._speedup:g}')
            elif param.name in ('hold_s', 'safe_value'):
                self._hold.hold_s = float(self.params['hold_s'])
                self._hold.safe_controls = np.array(self._safe_controls())
                if self.params['mode'] != 'lockstep':
                    self._setpoint_gate.max_age_ns = seconds_to_ns(self.params['hold_s'])

    # -- start ----------------------------------------------------------------------------
    def _start(self) -> None:
        """Start once the start gate opened: publish the first step and start the run timer."""
        self.gate = None
        self.started = True
        self._run_started_ns = self._step_started_ns = self._steady_ns()
        self.get_logger().info(f'starting the scenario at {self.stamp_ns / NS_PER_S:.0f} s '
                               'ROS time')
        self._publish_step()
        self._start_run_timer()

    def _start_run_timer(self) -> None:
        if self.params['mode'] == 'lockstep':
            self._run_timer = self.create_timer(self.params['heartbeat_period_s'],
                                                self._heartbeat, clock=self._steady)
        else:
            self._run_timer = self.create_timer(self.params['clock_period_s'], self._tick,
                                                clock=self._steady)

    def _not_ready(self, reason: str) -> None:
        self.gate = None
        self._fail(f'{reason} (ready_endpoints, ready_timeout_s = '
                   f"{self.params['ready_timeout_s']:g} s): are the other nodes running?")

    # -- publishing -----------------------------------------------------------------------
    def _publish_step(self) -> None:
        """Publish clock, disturbances and state of the current step."""
        self._clock_pub.publish(clock_msg(self.stamp_ns))
        self._sim_ns = self.stamp_ns
        self._publish_state()

    def _publish_state(self) -> None:
        """Publish disturbances and state of the current step."""
        stamp = self.stamp_ns
        zone = self.params['zone']
        emulator = self.emulator
        self._disturbance_pub.publish(disturbances_msg(stamp, dict(zip(
            self._disturbance_names, self._disturbance_table[emulator.index].tolist())), zone))
        last = self.records[-1] if self.records else None
        outputs = {}
        if last is not None:  # the outputs at the step's end (one array, not a pandas row)
            end = last.fine.to_numpy(dtype=float)[-1]
            position = {name: k for k, name in enumerate(last.fine.columns)}
            outputs = {name: float(end[position[f'y_{name}']])
                       for name in emulator.model.output_names}
        controls = ({} if last is None else
                    dict(zip(emulator.control_names, map(float, last.controls))))
        means = tuple(getattr(emulator.model, 'step_mean_outputs', ()))
        if last is not None and means:  # BOPTEST: the step means too (the KPIs' 60 s samples)
            step_means = emulator.model.step_means(float(last.t_start_s),
                                                   float(last.t_start_s) + emulator.step_s)
            outputs.update({f'mean_{name}': step_means[name] for name in means})
        msg = zone_state_msg(stamp, self.sensors.read(emulator.x, emulator.index), outputs,
                             controls, zone)
        history = getattr(emulator.model, 'history', None)
        if last is None and history is not None:  # the warm-up, with the first state only
            times, states, output_means = history
            msg.history_offsets_s = [float(t) for t in times - emulator.t_s]
            msg.history_state_values = [float(v) for v in states.T.reshape(-1)]
            msg.history_output_names = list(emulator.model.output_names)
            msg.history_output_values = [float(v) for v in output_means.T.reshape(-1)]
        self._state_pub.publish(msg)
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
        if step_waited >= seconds_to_ns(self.params['lockstep_timeout_s']):
            self._lockstep_timeout(step_waited / NS_PER_S)
            return
        if step_waited > 10 * NS_PER_S and now - self._last_wait_warning_ns > 10 * NS_PER_S:
            self.get_logger().warning(
                f'no setpoint stamped {self.stamp_ns / NS_PER_S:.0f} s after '
                f'{step_waited / NS_PER_S:.0f} s (step {self.steps_done + 1}/'
                f'{self.steps_done + self.emulator.steps_left}): is the MPC running?')
            self._last_wait_warning_ns = now
        self.get_logger().debug('no setpoint yet: publishing the step again')
        self.lockstep_waits += 1
        self._publish_step()

    # -- stepping -------------------------------------------------------------------------
    def _lockstep_timeout(self, waited_s: float) -> None:
        """Lockstep: the step's setpoint did not come within lockstep_timeout_s."""
        step = f'{self.stamp_ns / NS_PER_S:.0f} s (step {self.steps_done + 1})'
        if self.params['on_lockstep_timeout'] == 'stop':
            self._fail(f'no setpoint for {step} within lockstep_timeout_s = '
                       f"{self.params['lockstep_timeout_s']:g} s: is the MPC running? Stopping "
                       '(on_lockstep_timeout:=hold goes on with held or safe setpoints)')
            return
        self.lockstep_timeouts += 1
        decision = self._hold.controls_for(self._scenario_s(self.stamp_ns))
        self.get_logger().error(f'no setpoint for {step} after {waited_s:.1f} s (lockstep '
                                f'timeout): {decision.reason}')
        self._advance(decision.controls, decision.source, released=decision.released)

    def _scenario_s(self, stamp_ns: int) -> float:
        """Scenario time [s] of a ROS stamp."""
        return (stamp_ns - self.epoch_ns) / NS_PER_S

    def _on_setpoint(self, msg: Setpoint) -> None:
        if self.done:
            return
        stamp = stamp_to_ns(msg.header.stamp)
        lockstep = self.params['mode'] == 'lockstep'
        now = self.stamp_ns if lockstep else max(self._sim_ns, self.stamp_ns)
        controls = self.emulator.control_names
        # The whole message is checked (lengths first, before anything is converted) before
        # any of it moves a stamp or a held setpoint.
        caps = setpoint_caps(len(controls))
        rejection = (check_stamp_fields(msg.header.stamp.sec, msg.header.stamp.nanosec)
                     or check_lengths('setpoint', field_lengths(msg, caps), caps)
                     or check_setpoint(msg.step_s, msg.control_names, msg.control_values,
                                       msg.temperature_names, msg.temperature_setpoints_c,
                                       msg.plan_controls, msg.plan_temperatures_c,
                                       expected_step_s=self.params['step_s'],
                                       expected_controls=controls,
                                       schedule_offsets_s=msg.schedule_offsets_s,
                                       schedule_values=msg.schedule_values, schedules=lockstep,
                                       released=msg.released)
                     or self._setpoint_gate.check(stamp, now))
        if rejection:
            self._reject(stamp, rejection)
            return
        if stamp == self._setpoint_gate.latest_ns:
            self.peers.heard('setpoint')
            return  # a repeat (the MPC answers a heartbeat with its last setpoint)
        if not self.started:
            return
        if lockstep and stamp != self.stamp_ns:  # a step other than the current one
            self._reject(stamp, Rejection('stale', f'stamp {stamp / NS_PER_S:.3f} s is not '
                                          f'the current step {self.stamp_ns / NS_PER_S:.3f} s'))
            return
        applied = reorder(msg.control_names, msg.control_values, controls)
        released = (tuple(bool(r) for r in reorder(msg.control_names, msg.released, controls))
                    if len(msg.released) else ())
        schedule = None
        if len(msg.schedule_offsets_s):
            n = len(msg.schedule_offsets_s)
            per_control = np.asarray(msg.schedule_values, dtype=float).reshape(
                len(msg.control_names), n)
            schedule = [(float(offset), reorder(msg.control_names, per_control[:, k], controls))
                        for k, offset in enumerate(msg.schedule_offsets_s)]
        self._setpoint_gate.accept(stamp, now)
        self.peers.heard('setpoint')
        self._hold.offer(self._scenario_s(stamp), applied, released)
        if lockstep:
            self.setpoint_waits_s.append((self._steady_ns() - self._step_started_ns) / NS_PER_S)
            self._advance(applied, 'setpoint', schedule, released)

    def _reject(self, stamp_ns: int, rejection: Rejection) -> None:
        self.rejections.reject('setpoint', self.resolve_topic_name(contract.SETPOINT), stamp_ns,
                               rejection)

    def _tick(self) -> None:
        """Free mode: advance simulated time by ``clock_period_s * speedup``."""
        if self.done:
            return
        self._sim_ns += int(self.params['clock_period_s'] * self._speedup * NS_PER_S)
        if self._sim_ns < self.stamp_ns + self.step_ns:
            self._clock_pub.publish(clock_msg(self._sim_ns))
            if (self._setpoint_gate.latest_ns != self.stamp_ns and self._steady_ns()
                    - self._last_publish_ns >= seconds_to_ns(self.params['heartbeat_period_s'])):
                self._publish_state()  # no setpoint yet: the state again (it may have been lost)
            return
        decision = self._hold.controls_for(self._scenario_s(self.stamp_ns))
        if decision.source != 'setpoint':
            self.get_logger().warning(f'step {self.stamp_ns / NS_PER_S:.0f} s: '
                                      f'{decision.reason}')
        self._advance(decision.controls, decision.source, released=decision.released)

    def _advance(self, controls: np.ndarray, source: str = 'setpoint',
                 schedule: list | None = None, released: tuple[bool, ...] = ()) -> None:
        """
        Apply ``controls`` (or a ``schedule`` within the step) over the step, go on.

        ``released``: per control, its overwrite released (the building's own controller).
        """
        bounds = self.emulator.control_bounds
        clipped = np.clip(controls, bounds[:, 0], bounds[:, 1])
        names = self.emulator.control_names
        for k in np.flatnonzero(clipped != controls):
            self.get_logger().warning(
                f'setpoint {names[k]} = {controls[k]:g} at {self.stamp_ns / NS_PER_S:.0f} s '
                f'is outside the actuator limits [{bounds[k, 0]:g}, {bounds[k, 1]:g}]: '
                f'applying {clipped[k]:g}')
        try:
            record = self.emulator.advance(clipped, schedule, released)
        except Exception as exc:  # noqa: BLE001 - the building model failed: stop, clearly
            self._fail(f'the emulation model failed at {self.stamp_ns / NS_PER_S:.0f} s: '
                       f'{type(exc).__name__}: {exc}')
            return
        if not np.all(np.isfinite(record.x_end)):
            self._fail(f'the emulation model returned non-finite states {record.x_end} at '
                       f'{self.stamp_ns / NS_PER_S:.0f} s')
            return
        self._step_started_ns = self._steady_ns()
        self.records.append(record)
        self.steps_done += 1
        self._save_plant_state()
        if self.params['records_kept'] and len(self.records) > self.params['records_kept']:
            del self.records[:-self.params['records_kept']]
        self.applied_sources.append(source)
        if self.get_logger().is_enabled_for(LoggingSeverity.DEBUG):  # (the line costs)
            self.get_logger().debug(
                f'step {self.steps_done}: '
                + ', '.join(f'{n} = {v:.1f}' for n, v in zip(names, record.controls))
                + f', states {np.round(record.x_start, 3).tolist()} -> '
                f'{np.round(record.x_end, 3).tolist()}')
        self._publish_step()
        if self.emulator.steps_left == 0:
            self._finish()

    def _save_plant_state(self) -> None:
        """Write the plant state after a step (``plant_state_file``; atomically)."""
        path = self.params['plant_state_file']
        if not path or self._plant_unsaveable:
            return
        try:
            data = self.emulator.save_plant_state()
        except (ValueError, RuntimeError) as exc:
            self._plant_unsaveable = True
            self.get_logger().warning(f'plant state not saved ({exc}): a restart starts from '
                                      'initial_temperature_c')
            return
        target = pathlib.Path(path)
        staged = target.with_name(f'.{target.name}.tmp')
        staged.write_bytes(data)
        staged.replace(target)

    def _fail(self, reason: str) -> None:
        """End the run early with an error (the process exits with code 1)."""
        self.failed = reason
        self.get_logger().error(reason)
        self._finish()

    def _finish(self) -> None:
        self.done = True
        self.wall_s = ((self._steady_ns() - self._run_started_ns) / NS_PER_S
                       if self._run_started_ns else 0.0)
        if self._run_timer is not None:
            self._run_timer.cancel()
        temps = [t for r in self.records for t in self.interface.temperatures_c(r.x_end)]
        temps = temps or [float('nan')]
        applied = dict(collections.Counter(self.applied_sources))
        rejected = self.rejections.total()
        self.get_logger().info(
            f"{'run stopped' if self.failed else 'scenario over'}: {self.steps_done} steps in "
            f'{self.wall_s:.2f} s wall, zone temperature {min(temps):.2f} to {max(temps):.2f} '
            f'degC; applied {applied}; {rejected} setpoints rejected')
        if self.params['output_dir']:
            self.write_outputs(pathlib.Path(self.params['output_dir']))
        self.diagnostics.publish()

    # -- records --------------------------------------------------------------------------
    def fine_frame(self) -> pd.DataFrame:
        """Return the fine-grid trajectory of all steps so far (as the core loop builds it)."""
        if not self.records:
            return pd.DataFrame()
        return pd.concat([r.fine if k == 0 else r.fine.iloc[1:]
                          for k, r in enumerate(self.records)])

    def applied_frame(self) -> pd.DataFrame:
        """
        One row per step: ROS stamp [ns], applied controls, start and end states.

        Index ``time_s`` (scenario time [s]); columns ``stamp_ns``, every
        control (``q``, or ``q_0``, ``q_1``, ...; each in its unit), ``<state>_start``,
        ``<state>_end``, ``released`` (the controls whose overwrite was released, separated
        by spaces; '' for none).
        """
        rows = []
        if not self.records:
            return pd.DataFrame(rows, index=pd.Index([], name='time_s', dtype=float))
        for record in self.records:
            row = {'time_s': record.t_start_s,
                   'stamp_ns': self.epoch_ns + seconds_to_ns(record.t_start_s)}
            for name, value in zip(self.emulator.control_names, record.controls):
                row[name] = float(value)
            for i, name in enumerate(self.emulator.model.state_names):
                row[f'{name}_start'] = float(record.x_start[i])
                row[f'{name}_end'] = float(record.x_end[i])
            row['released'] = ' '.join(record.released)
            rows.append(row)
        return pd.DataFrame(rows).set_index('time_s')

    def zone_temperature_columns(self) -> dict[str, str]:
        """
        Return the column of the fine trajectory holding each zone temperature state in degC.

        The model's output of the same name (``y_T`` for the R1C1 zone), else the state (``x_T_0``,
        in K: see :func:`mshoot_nodes.results.zone_temperatures_c`).
        """
        outputs = self.emulator.model.output_names
        return {name: f'y_{name}' if name in outputs else f'x_{name}'
                for name in self.interface.temperature_names}

    def write_outputs(self, out: pathlib.Path) -> None:
        """Write trajectories.csv, applied.csv, run.json (and boptest_records.csv) to ``out``."""
        out.mkdir(parents=True, exist_ok=True)
        self.fine_frame().to_csv(out / 'trajectories.csv', index_label='time_s')
        self.applied_frame().to_csv(out / 'applied.csv', index_label='time_s')
        boptest_records = getattr(self.emulator.model, 'boptest_records', None)
        if boptest_records is not None:  # a BOPTEST plant: its 60 s outputs, for the KPIs
            boptest_records().to_csv(out / 'boptest_records.csv', index=False)
        keys = ('scenario', 'data', 'hours', 'model', 'mode', 'initial_temperature_c', 'step_s')
        run = {key: self.params[key] for key in keys}
        run.update(epoch_ns=self.epoch_ns, steps=self.steps_done, wall_s=self.wall_s,
                   start_step=self.params['start_step'], failed=self.failed,
                   controls=list(self.emulator.control_names),
                   zone_temperatures=self.zone_temperature_columns(),
                   applied_sources=dict(collections.Counter(self.applied_sources)),
                   rejected_setpoints=self.rejections.counter.by_kind())
        (out / 'run.json').write_text(json.dumps(run, indent=2) + '\n')
        self.get_logger().info(f'wrote {out}/trajectories.csv, applied.csv, run.json')


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes emulator``: run until the scenario ends (or Ctrl-C)."""
    node = run_node(EmulatorNode, 'emulator', args, until_done=True, bridge_logging=True)
    if node is not None and node.failed:
        sys.exit(1)


if __name__ == '__main__':
    main()
