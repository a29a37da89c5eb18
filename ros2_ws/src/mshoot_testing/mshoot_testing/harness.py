"""
An in-process closed loop to poke at: faults, restarts and malformed messages.

Test support (package mshoot_testing), used by the fault-injection tests and
the soak benchmark (``bench/soak.py``).
:class:`ClosedLoop` runs emulator, forecaster, MPC (and optionally the bag
recorder) in one SingleThreadedExecutor of a private context, like
:func:`mshoot_nodes.bringup.run_in_process`, but step by step, so a caller can
inject a fault before a step, stop and restart the MPC node, pause the
forecasts, or publish malformed messages, with a wall-clock guard on every
wait. The ``malformed_*`` functions build messages that the validation of
:mod:`mshoot_core.safety` must reject, one defect each (stamps "in the
future" are at least three steps ahead: still rejected if the receiver's clock
moves on by a step before it takes them).
"""
from __future__ import annotations

import time
from typing import Any, Callable, Sequence

from mshoot_core.models.base import Model
from mshoot_core.units import KELVIN, NS_PER_S
from mshoot_msgs.msg import Forecast, MpcStatus, Setpoint, ZoneState
from mshoot_nodes.conversions import forecast_msg, ns_to_stamp, setpoint_msg, zone_state_msg
from mshoot_nodes.emulator_node import EmulatorNode
from mshoot_nodes.forecaster_node import ForecasterNode
from mshoot_nodes.mpc_node import MpcNode
from mshoot_nodes.readiness import run_requirements
from mshoot_nodes.recorder_node import RecorderNode
import numpy as np
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

#: ``header.frame_id`` of the malformed messages (tells them apart in a bag).
MALFORMED = 'malformed'
#: Defects of the malformed messages, per input stream.
STATE_DEFECTS = ('nan_temperature', 'inf_heat_rate', 'hot', 'cold', 'bad_nanosec', 'future',
                 'backwards', 'unknown_state', 'missing_state', 'duplicate_state',
                 'values_length', 'nan_output', 'unknown_control')
FORECAST_DEFECTS = ('nan', 'inf', 'lengths', 'empty', 'inverted_band', 'negative_sun',
                    'step', 'future', 'backwards', 'unknown_series', 'missing_series',
                    'duplicate_series', 'flat_length', 'nan_price', 'price_length')
SETPOINT_DEFECTS = ('nan_heat_rate', 'inf_temperature', 'absurd_heat_rate', 'step', 'plan_lengths',
                    'nan_plan', 'future', 'backwards', 'bad_nanosec', 'unknown_control',
                    'missing_control', 'duplicate_control', 'no_control', 'values_length')


def _overrides(values: dict[str, Any]) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items() if value is not None]


# -- malformed messages -------------------------------------------------------------------
def malformed_zone_state(defect: str, now_ns: int, latest_ns: int, step_ns: int,
                         rng: np.random.Generator, states: Sequence[str] = ('T',),
                         controls: Sequence[str] = ('q',)) -> ZoneState:
    """
    Build a zone state the MPC must reject for ``defect`` (:data:`STATE_DEFECTS`).

    ``now_ns`` is the receiver's clock, ``latest_ns`` the newest state it
    accepted (> 0), ``step_ns`` the control step; ``states`` and ``controls``
    the receiver model's names (every state a zone temperature [K]).
    """
    stamp = now_ns
    names = list(states)
    values = (KELVIN + rng.uniform(15.0, 25.0, len(names))).tolist()
    outputs = {'T': values[0] - KELVIN}
    applied = {name: float(rng.uniform(-2000.0, 2000.0)) for name in controls}
    k = int(rng.integers(0, len(names)))
    if defect == 'nan_temperature':
        values[k] = float('nan')
    elif defect == 'inf_heat_rate':
        applied[str(rng.choice(list(controls)))] = float(rng.choice([np.inf, -np.inf]))
    elif defect == 'hot':
        values[k] = KELVIN + float(rng.uniform(81.0, 1e6))
    elif defect == 'cold':
        values[k] = KELVIN - float(rng.uniform(51.0, 273.0))
    elif defect == 'future':
        stamp = now_ns + int(rng.integers(3, 100)) * step_ns
    elif defect == 'backwards':
        stamp = latest_ns - int(rng.integers(1, 5)) * step_ns - int(rng.integers(0, step_ns))
    elif defect == 'unknown_state':
        names[k] = names[k] + '_unknown'
    elif defect == 'missing_state':
        del names[k], values[k]
    elif defect == 'duplicate_state':
        names.append(names[k])
        values.append(values[k])
    elif defect == 'nan_output':
        outputs['T'] = float(rng.choice([np.nan, np.inf]))
    elif defect == 'unknown_control':
        applied['not_a_control'] = 0.0
    msg = zone_state_msg(max(stamp, 0), {}, outputs, applied, MALFORMED)
    msg.state_names, msg.state_values = names, values
    if defect == 'values_length':
        msg.state_values = values + [KELVIN + 20.0]
    elif defect == 'bad_nanosec':
        msg.header.stamp.nanosec = int(rng.integers(NS_PER_S, 2 ** 32))
    return msg


def malformed_forecast(defect: str, now_ns: int, latest_ns: int, step_ns: int,
                       rng: np.random.Generator, samples: int = 11) -> Forecast:
    """
    Build a forecast the MPC must reject for ``defect`` (:data:`FORECAST_DEFECTS`).

    The MPC's model needs Tout, solrad and occ, and may assume dpos.
    """
    import pandas as pd
    n = max(int(samples), 1)
    window = pd.DataFrame({'Tout': rng.uniform(-5, 15, n), 'solrad': rng.uniform(0, 500, n),
                           'occ': rng.integers(0, 30, n).astype(float),
                           'comfort_min': np.full(n, 21.0), 'comfort_max': np.full(n, 22.0),
                           'price': rng.uniform(0.1, 0.5, n)})
    series = ['Tout', 'solrad', 'occ']
    stamp, step_s = now_ns, step_ns / NS_PER_S
    k = int(rng.integers(0, n))
    if defect == 'nan':
        window.loc[k, str(rng.choice(['Tout', 'solrad', 'occ', 'comfort_min']))] = np.nan
    elif defect == 'inf':
        window.loc[k, 'Tout'] = np.inf
    elif defect == 'inverted_band':
        window.loc[k, 'comfort_min'] = 23.5
    elif defect == 'negative_sun':
        window.loc[k, 'solrad'] = -float(rng.uniform(1.0, 1e3))
    elif defect == 'step':
        step_s = float(rng.choice([0.0, -step_s, step_s / 2, np.nan]))
    elif defect == 'future':
        stamp = now_ns + int(rng.integers(3, 100)) * step_ns
    elif defect == 'backwards':
        stamp = latest_ns - int(rng.integers(1, 5)) * step_ns
    elif defect == 'unknown_series':
        window['Tsky'] = rng.uniform(-20, 0, n)
        series.append('Tsky')
    elif defect == 'missing_series':
        series.remove(str(rng.choice(series)))
    elif defect == 'nan_price':
        window.loc[k, 'price'] = float(rng.choice([np.nan, np.inf, 1e9]))
    msg = forecast_msg(max(stamp, 0), 1.0, window, series, MALFORMED)
    msg.step_s = step_s
    if defect == 'lengths':
        msg.comfort_max_c = list(msg.comfort_max_c)[:-1] if n > 1 else []
    elif defect == 'empty':
        msg.series_values, msg.comfort_min_c, msg.comfort_max_c, msg.price_per_kwh = \
            [], [], [], []
    elif defect == 'duplicate_series':
        msg.series_names = list(msg.series_names[:-1]) + [msg.series_names[0]]
    elif defect == 'flat_length':
        msg.series_values = list(msg.series_values)[:-int(rng.integers(1, n + 1))]
    elif defect == 'price_length':
        msg.price_per_kwh = list(msg.price_per_kwh) + [0.3]
    return msg


def malformed_setpoint(defect: str, now_ns: int, latest_ns: int, step_ns: int,
                       rng: np.random.Generator, controls: Sequence[str] = ('q',),
                       temperatures: Sequence[str] = ('T',)) -> Setpoint:
    """
    Build a setpoint the emulator must reject for ``defect`` (:data:`SETPOINT_DEFECTS`).

    ``now_ns`` is the emulator's current step, ``latest_ns`` the newest
    setpoint it accepted (or the step before ``now_ns``); ``controls`` and
    ``temperatures`` the emulator model's names.
    """
    stamp, step_s = now_ns, step_ns / NS_PER_S
    names = list(controls)
    values = rng.uniform(-2000, 2000, len(names)).tolist()
    zones = {name: float(rng.uniform(18, 24)) for name in temperatures}
    plan_q = {name: rng.uniform(-2000, 2000, 5).tolist() for name in names}
    plan_t = {name: rng.uniform(18, 24, 5).tolist() for name in temperatures}
    k = int(rng.integers(0, len(names)))
    if defect == 'nan_heat_rate':
        values[k] = float('nan')
    elif defect == 'inf_temperature':
        zones[str(rng.choice(list(temperatures)))] = float('inf')
    elif defect == 'absurd_heat_rate':
        values[k] = float(rng.choice([-1.0, 1.0])) * float(rng.uniform(1.01e7, 1e12))
    elif defect == 'step':
        step_s = float(rng.choice([0.0, step_s * 2, np.inf]))
    elif defect == 'plan_lengths':
        first = next(iter(plan_t))
        plan_t[first] = plan_t[first][:-1]
    elif defect == 'nan_plan':
        plan_q[names[k]][int(rng.integers(0, 5))] = float('nan')
    elif defect == 'future':
        stamp = now_ns + int(rng.integers(3, 100)) * step_ns
    elif defect == 'backwards':
        stamp = latest_ns - int(rng.integers(1, 5)) * step_ns
    elif defect == 'unknown_control':
        plan_q[names[k] + '_unknown'] = plan_q.pop(names[k])
        names[k] = names[k] + '_unknown'
    elif defect == 'missing_control':
        plan_q.pop(names[k])
        del names[k], values[k]
    msg = setpoint_msg(max(stamp, 0), step_s, dict(zip(names, values)), zones, plan_q or None,
                       plan_t, MALFORMED)
    if defect == 'missing_control' and not names:  # a single control: none left
        msg.plan_controls = []
    if defect == 'duplicate_control':
        msg.control_names = list(msg.control_names) + [names[k]]
        msg.control_values = list(msg.control_values) + [values[k]]
    elif defect == 'no_control':
        msg.control_names, msg.control_values, msg.plan_controls = [], [], []
    elif defect == 'values_length':
        msg.control_values = list(msg.control_values) + [0.0]
    elif defect == 'bad_nanosec':
        msg.header.stamp = ns_to_stamp(stamp)
        msg.header.stamp.nanosec = int(rng.integers(NS_PER_S, 2 ** 32))
    return msg


# -- the loop -----------------------------------------------------------------------------
class ClosedLoop:
    """
    Emulator, forecaster, MPC (and recorder) in one executor, advanced step by step.

    Parameters
    ----------
    context : Context
        An initialised rclpy context (the caller shuts it down).
    node_params : dict
        Node name ('emulator', 'forecaster', 'mpc', 'recorder') -> parameter
        overrides; ``use_sim_time`` is set for forecaster and MPC.
    record : bool
        Also run the bag recorder (needs ``node_params['recorder']['bag_path']``).
    mpc_model : Model, optional
        The MPC's control model instance (e.g. a :class:`~mshoot_testing.faults.FaultyModel`).

    Attributes
    ----------
    emulator, forecaster, mpc, recorder : nodes
        ``mpc`` is None while the MPC is stopped.
    retired : list of MpcNode
        Earlier MPC incarnations (destroyed; their ``history`` and counters stay).

    """

    def __init__(self, context: Context, node_params: dict[str, dict[str, Any]], *,
                 record: bool = False, mpc_model: Model | None = None) -> None:
        self.context = context
        self.node_params = {name: dict(values) for name, values in node_params.items()}
        for name in ('forecaster', 'mpc'):
            self.node_params.setdefault(name, {}).setdefault('use_sim_time', True)
        # The bring-ups' readiness check: the MPC, the forecaster (and the recorder's ready).
        self.node_params.setdefault('emulator', {}).setdefault(
            'ready_endpoints', run_requirements('mshoot' if record else 'none'))
        self.executor = SingleThreadedExecutor(context=context)
        self.retired: list[MpcNode] = []
        self._nodes: list[Node] = []
        self.mpc_model = mpc_model
        self.recorder: RecorderNode | None = None
        self.mpc: MpcNode | None = None
        try:
            if record:
                self.recorder = self._add(RecorderNode(
                    context=context, parameter_overrides=_overrides(
                        self.node_params.get('recorder', {}))))
            self.forecaster = self._add(ForecasterNode(
                context=context, parameter_overrides=_overrides(self.node_params['forecaster'])))
            self.start_mpc()
            self.emulator = self._add(EmulatorNode(
                context=context, parameter_overrides=_overrides(
                    self.node_params.get('emulator', {}))))
        except Exception:
            self.close()
            raise

    def _add(self, node: Node) -> Any:
        self._nodes.append(node)
        self.executor.add_node(node)
        return node

    # -- spinning -------------------------------------------------------------------------
    def spin_until(self, condition: Callable[[], bool], timeout_s: float,
                   what: str = 'the condition') -> float:
        """
        Spin until ``condition()``; TimeoutError after ``timeout_s`` of wall time.

        Returns the wall time it took [s].
        """
        started = time.monotonic()
        while not condition():
            if time.monotonic() - started > timeout_s:
                raise TimeoutError(f'{what} not reached within {timeout_s:g} s '
                                   f'({self.steps_done} steps done)')
            self.executor.spin_once(timeout_sec=0.02)
        return time.monotonic() - started

    def spin_for(self, wall_s: float) -> None:
        """Spin for ``wall_s`` of wall time."""
        end = time.monotonic() + wall_s
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=min(0.02, max(end - time.monotonic(), 0.0)))

    @property
    def steps_done(self) -> int:
        """Return the steps the emulator has applied."""
        return self.emulator.steps_done if hasattr(self, 'emulator') else 0

    def run_steps(self, steps: int, timeout_s: float = 60.0) -> None:
        """Spin until ``steps`` more steps are applied (or the scenario ends)."""
        target = self.steps_done + int(steps)
        self.spin_until(lambda: self.steps_done >= target or self.emulator.done, timeout_s,
                        f'step {target}')

    def run_to_end(self, timeout_s: float = 120.0) -> None:
        """Spin until the emulator's scenario is over."""
        self.spin_until(lambda: self.emulator.done, timeout_s, 'the end of the scenario')

    # -- the MPC --------------------------------------------------------------------------
    def start_mpc(self, model: Model | None = None, **params: Any) -> MpcNode:
        """Start an MPC node (``params`` update the MPC's overrides from now on)."""
        if self.mpc is not None:
            raise RuntimeError('the MPC node is running: stop_mpc() first')
        self.node_params['mpc'].update(params)
        self.mpc = self._add(MpcNode(model=model if model is not None else self.mpc_model,
                                     context=self.context,
                                     parameter_overrides=_overrides(self.node_params['mpc'])))
        return self.mpc

    def stop_mpc(self) -> MpcNode:
        """Destroy the MPC node as a crash would end it (its records stay readable)."""
        node, self.mpc = self.mpc, None
        if node is None:
            raise RuntimeError('the MPC node is not running')
        self.executor.remove_node(node)
        self._nodes.remove(node)
        node.destroy_node()
        self.retired.append(node)
        return node

    def mpc_history(self) -> list[tuple[Setpoint, MpcStatus]]:
        """Everything every MPC incarnation published, in order."""
        nodes = self.retired + ([self.mpc] if self.mpc is not None else [])
        return [item for node in nodes for item in node.history]

    def mpc_rejections(self, stream: str | None = None) -> int:
        """Return the inputs rejected by every MPC incarnation."""
        nodes = self.retired + ([self.mpc] if self.mpc is not None else [])
        return sum(node.rejections.total(stream) for node in nodes)

    def drain_recorder(self, timeout_s: float = 2.0) -> None:
        """Let the recorder take what is still queued (before closing)."""
        if self.recorder is not None:
            self.recorder.drain(self.executor, limit_s=timeout_s)

    def close(self) -> None:
        """Destroy every node (the recorder closes its bag) and the executor."""
        self.executor.shutdown()
        for node in self._nodes:
            node.destroy_node()
        self._nodes.clear()
