"""
Property-based tests (hypothesis): malformed input never crashes a node.

Malformed input never reaches the optimiser or the building, is always counted, and nothing
non-finite is published.

The core rules (:mod:`mshoot_core.safety`) are checked on arbitrary values; the MPC
and the emulator nodes get batches of malformed messages (one defect each, from
:mod:`mshoot_testing.harness`) mixed with valid ones, over real topics in one process
(a private context, SingleThreadedExecutor, wall-clock guards). Thousands of
malformed messages go in per run: the last test of the module checks the totals.
"""
import math
import time

from hypothesis import given, HealthCheck, settings, strategies as st
from hypothesis.extra import numpy as hnp
from mshoot_core.safety import (check_forecast, check_names, check_setpoint, check_zone_state,
                                FORECAST_SERIES, Limits, SetpointHold, SetpointSupervisor,
                                SOURCES, StampGate)
from mshoot_core.units import KELVIN, NS_PER_S
from mshoot_msgs.msg import Disturbances, Forecast, MpcStatus, Setpoint, ZoneState
from mshoot_nodes import contract
from mshoot_nodes.conversions import clock_msg, forecast_msg, setpoint_msg, zone_state_msg
from mshoot_nodes.emulator_node import EmulatorNode
from mshoot_nodes.mpc_node import MpcNode
from mshoot_testing.harness import (FORECAST_DEFECTS, malformed_forecast, malformed_setpoint,
                                    malformed_zone_state, SETPOINT_DEFECTS, STATE_DEFECTS)
import numpy as np
import pandas as pd
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock

from conftest import private_context

EPOCH_NS = 1522886400 * NS_PER_S
STEP_NS = 3600 * NS_PER_S
NODE_SETTINGS = settings(max_examples=200, deadline=None, database=None,
                         suppress_health_check=[HealthCheck.too_slow])
CORE_SETTINGS = settings(max_examples=150, deadline=None, database=None)
#: Malformed messages each node's property test throws at least (checked when its rig is torn
#: down, whatever else ran: the emulator gets 2 or more per example, the MPC about 5).
MIN_THROWN = {'mpc': NODE_SETTINGS.max_examples, 'emulator': 2 * NODE_SETTINGS.max_examples}


def _check_thrown(node: str, thrown: int) -> None:
    """Fail unless the property test of ``node`` threw its share of malformed messages."""
    print(f'malformed messages thrown at the {node}: {thrown}')
    assert thrown >= MIN_THROWN[node], (node, thrown)


floats = st.floats(allow_nan=True, allow_infinity=True, width=64)


# -- the core rules on arbitrary values ---------------------------------------------------
class _Result:

    def __init__(self, controls, states, success):
        self.controls, self.states, self.success, self.message = controls, states, success, ''


@CORE_SETTINGS
@given(n=st.integers(0, 6), nc=st.integers(0, 2), data=st.data(), success=st.booleans(),
       accept=st.booleans(), ages=st.lists(st.integers(-2, 8), max_size=6))
def test_supervisor_always_returns_a_finite_setpoint_within_bounds(
        n, nc, data, success, accept, ages):
    supervisor = SetpointSupervisor(((-2000.0, 2000.0),), 3600.0, (123.0,),
                                    max_plan_age_steps=3,
                                    state_range=((223.15,), (353.15,)))
    controls = data.draw(hnp.arrays(float, (n, nc), elements=floats))
    states = data.draw(hnp.arrays(float, (n + 1, 1), elements=floats))
    decisions = [supervisor.review(0.0, _Result(controls, states, success),
                                   accept_unconverged=accept)]
    decisions += [supervisor.fallback(age * 3600.0, 'budget', 'test') for age in ages]
    for decision in decisions:
        assert decision.source in SOURCES and decision.fallback == (decision.source != 'optimum')
        assert decision.controls.shape == (1,) and np.all(np.isfinite(decision.controls))
        assert -2000.0 <= decision.controls[0] <= 2000.0
        assert np.all(np.isfinite(decision.plan_controls))
        assert np.all(np.isfinite(decision.plan_states))
        if decision.predicted_state is not None:
            assert 223.15 <= decision.predicted_state[0] <= 353.15
        if decision.source == 'safe':
            assert decision.controls[0] == 123.0


#: Names a message may carry: the model's, unknown ones, and bad ones.
NAMES = st.sampled_from(['Tout', 'solrad', 'occ', 'dpos', 'price', 'comfort_min', 'comfort_max',
                         'Tsky', '', 'q_0', 'q_1', 'q', 'T_0', 'T_1'])
KNOWN = ('dpos', 'price')


@CORE_SETTINGS
@given(step_s=floats, lengths=st.lists(st.integers(0, 4), min_size=5, max_size=5),
       extra=st.dictionaries(NAMES, st.integers(0, 4), max_size=3), data=st.data())
def test_check_forecast_accepts_only_sane_forecasts(step_s, lengths, extra, data):
    series = {name: data.draw(st.lists(floats, min_size=k, max_size=k))
              for name, k in [*zip(FORECAST_SERIES, lengths), *extra.items()]}
    rejection = check_forecast(step_s, series, expected_step_s=3600.0, known=KNOWN)
    if rejection is None:
        limits = Limits()
        lengths = {len(values) for values in series.values()}
        assert step_s == pytest.approx(3600.0) and len(lengths) == 1 and min(lengths) >= 1
        assert set(series) <= {*FORECAST_SERIES, *KNOWN}
        for name, values in series.items():
            low, high = limits.forecast_ranges[name]
            assert all(math.isfinite(x) and low <= x <= high for x in values)
        assert all(a <= b for a, b in zip(series['comfort_min'], series['comfort_max']))
    else:
        assert rejection.reason and rejection.kind in ('non_finite', 'out_of_range', 'length',
                                                       'band', 'step', 'names')


@CORE_SETTINGS
@given(step_s=floats, controls=st.lists(st.tuples(NAMES, floats), max_size=3),
       zones=st.lists(st.tuples(NAMES, floats), max_size=3),
       plan_q=st.lists(floats, max_size=7), plan_t=st.lists(floats, max_size=7),
       expected=st.booleans())
def test_check_setpoint_accepts_only_finite_plausible_setpoints(step_s, controls, zones, plan_q,
                                                                plan_t, expected):
    names = [n for n, _ in controls]
    zone_names = [n for n, _ in zones]
    if check_setpoint(step_s, names, [v for _, v in controls], zone_names,
                      [v for _, v in zones], plan_q, plan_t, expected_step_s=3600.0,
                      expected_controls=('q_0', 'q_1') if expected else None) is None:
        values = [v for _, v in controls + zones]
        assert all(math.isfinite(x) for x in (*values, *plan_q, *plan_t))
        assert names and all(names) and len(set(names)) == len(names)
        assert all(zone_names) and len(set(zone_names)) == len(zone_names)
        assert not expected or sorted(names) == ['q_0', 'q_1']
        m = len(plan_q) // len(names)
        assert len(plan_q) == m * len(names) and len(plan_t) == m * len(zones)
        assert step_s == pytest.approx(3600.0)
        assert all(abs(v) <= 1e7 for _, v in controls) and all(-50.0 <= v <= 80.0
                                                               for _, v in zones)


@CORE_SETTINGS
@given(states=st.lists(st.tuples(NAMES, floats), max_size=3),
       applied=st.lists(st.tuples(NAMES, floats), max_size=3),
       outputs=st.lists(floats, max_size=2), extra_value=st.booleans())
def test_check_zone_state_takes_only_the_models_states_by_name(states, applied, outputs,
                                                               extra_value):
    names = [n for n, _ in states]
    values = [v for _, v in states] + ([1.0] if extra_value else [])
    rejection = check_zone_state(names, values, [f'y{k}' for k in range(len(outputs))],
                                 outputs, [n for n, _ in applied], [v for _, v in applied],
                                 expected_states=('T_1', 'T_0'), allowed_controls=('q_0', 'q_1'))
    if rejection is None:
        assert sorted(names) == ['T_0', 'T_1'] and len(values) == 2
        assert all(math.isfinite(v) for v in (*values, *outputs))
        assert {n for n, _ in applied} <= {'q_0', 'q_1'} and len(applied) == len(
            {n for n, _ in applied})
        assert all(abs(v) <= 1e7 for _, v in applied)
    else:
        assert rejection.kind in ('names', 'length', 'non_finite', 'out_of_range')
    assert check_names('x', ['a', 'b'], expected=['b', 'a']) is None


@CORE_SETTINGS
@given(events=st.lists(st.tuples(st.integers(-10, 10), st.integers(0, 10)), max_size=30))
def test_stamp_gate_never_accepts_time_going_backwards_or_far_ahead(events):
    gate = StampGate(STEP_NS, max_age_ns=0, max_future_ns=STEP_NS)
    now = EPOCH_NS
    accepted = []
    for offset, advance in events:
        now += advance * STEP_NS // 4
        stamp = now + offset * STEP_NS // 2
        if gate.check(stamp, now) is None:
            if not accepted or stamp != accepted[-1]:  # a repeat of the newest is fine
                assert (now // STEP_NS) * STEP_NS <= stamp <= now + STEP_NS
            gate.accept(stamp, now)
            accepted.append(stamp)
    assert accepted == sorted(accepted)


@CORE_SETTINGS
@given(offers=st.lists(st.tuples(st.integers(0, 10), floats), max_size=10),
       hold_s=st.floats(0.0, 1e5), ask=st.integers(0, 12))
def test_hold_applies_a_finite_setpoint_it_was_offered_or_the_safe_one(offers, hold_s, ask):
    hold = SetpointHold((-50.0,), hold_s)
    offered = set()
    for step, value in offers:
        if math.isfinite(value):
            hold.offer(step * 3600.0, [value])
            offered.add(value)
        else:
            with pytest.raises(ValueError):
                hold.offer(step * 3600.0, [value])
    decision = hold.controls_for(ask * 3600.0)
    assert np.all(np.isfinite(decision.controls))
    if decision.source == 'safe':
        assert decision.controls[0] == -50.0
    else:
        assert decision.controls[0] in offered and 0 <= decision.age_s <= hold_s + 1e-6


# -- the nodes ----------------------------------------------------------------------------
def _finite(*values):
    return all(math.isfinite(float(v)) for v in values)


class Probe:
    """A test node: publishes to a node under test and keeps everything it publishes."""

    def __init__(self, context, nodes, outputs):
        self.node = rclpy.create_node('probe', context=context,
                                      start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=context)
        for node in (*nodes, self.node):
            self.executor.add_node(node)
        self.nodes = nodes
        self.received = []
        for cls, topic, qos in outputs:  # what the nodes under test publish
            self.node.create_subscription(cls, topic, self.received.append, qos)

    def spin_until(self, condition, timeout_s=10.0, what='condition'):
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, f'{what} not reached within {timeout_s} s'
            self.executor.spin_once(timeout_sec=0.01)

    def settle(self, turns=2):
        for _ in range(turns):
            self.executor.spin_once(timeout_sec=0.0)

    def check_published_finite(self):
        for msg in self.received:
            if isinstance(msg, Setpoint):
                assert _finite(*msg.control_values, *msg.temperature_setpoints_c, msg.step_s,
                               *msg.plan_controls, *msg.plan_temperatures_c)
                assert len(msg.control_names) == len(msg.control_values) >= 1
            elif isinstance(msg, MpcStatus):
                assert _finite(msg.solve_time_s, msg.objective, msg.max_defect)
            elif isinstance(msg, ZoneState):
                assert _finite(*msg.state_values, *msg.output_values, *msg.control_values)
                assert len(msg.state_names) == len(msg.state_values) >= 1
            elif isinstance(msg, Disturbances):
                assert _finite(*msg.values) and len(msg.names) == len(msg.values) >= 1
        self.received.clear()

    def close(self):
        self.executor.shutdown()
        for node in (*self.nodes, self.node):
            node.destroy_node()


def _valid_window(rng, rows):
    low = rng.uniform(18.0, 22.0, rows)
    return pd.DataFrame({'Tout': rng.uniform(-10, 20, rows), 'solrad': rng.uniform(0, 600, rows),
                         'occ': rng.integers(0, 30, rows).astype(float), 'comfort_min': low,
                         'comfort_max': low + rng.uniform(0.5, 4.0, rows)})


@pytest.fixture(scope='module')
def mpc_rig():
    """Yield an MPC node on simulated time and a probe that drives its clock and inputs."""
    context = private_context()
    mpc = MpcNode(context=context, parameter_overrides=[
        Parameter('use_sim_time', value=True), Parameter('model', value='python'),
        Parameter('horizon_steps', value=4), Parameter('reject_log_period_s', value=60.0),
        Parameter('input_wait_s', value=600.0)])
    probe = Probe(context, [mpc], [(Setpoint, contract.SETPOINT, contract.DATA_QOS),
                                   (MpcStatus, contract.STATUS, contract.DATA_QOS)])
    rig = {'mpc': mpc, 'probe': probe, 'now': EPOCH_NS,
           'clock': probe.node.create_publisher(Clock, contract.CLOCK, contract.CLOCK_QOS),
           'state': probe.node.create_publisher(ZoneState, contract.ZONE_STATE,
                                                contract.DATA_QOS),
           'forecast': probe.node.create_publisher(Forecast, contract.FORECAST,
                                                   contract.LATCHED_QOS)}
    probe.spin_until(lambda: probe.node.count_subscribers(contract.ZONE_STATE) > 0)
    _advance_mpc_clock(rig, EPOCH_NS)
    rng = np.random.default_rng(0)
    _send_valid_mpc_inputs(rig, rng)
    probe.spin_until(lambda: len(mpc.history) == 1, what='the first solve')
    rig['thrown'] = 0
    yield rig
    probe.close()
    rclpy.try_shutdown(context=context)
    _check_thrown('mpc', rig['thrown'])


def _advance_mpc_clock(rig, now):
    rig['now'] = now
    mpc, probe = rig['mpc'], rig['probe']
    deadline = time.monotonic() + 10.0
    while mpc.get_clock().now().nanoseconds != now:  # best effort, depth 1: repeat
        assert time.monotonic() < deadline, 'the MPC clock did not follow'
        rig['clock'].publish(clock_msg(now))
        probe.settle(3)


def _send_valid_mpc_inputs(rig, rng):
    now = rig['now']
    rig['state'].publish(zone_state_msg(now, {'T': KELVIN + rng.uniform(15, 26)}, {},
                                        {'q': rng.uniform(-2e3, 2e3)}))
    rig['forecast'].publish(forecast_msg(now, 3600.0, _valid_window(rng, 5)))
    rig['latest'] = now


@NODE_SETTINGS
@given(states=st.lists(st.sampled_from((None,) + STATE_DEFECTS), min_size=2, max_size=10),
       forecasts=st.lists(st.sampled_from((None,) + FORECAST_DEFECTS), max_size=6),
       advance=st.booleans(), seed=st.integers(0, 2 ** 32 - 1))
def test_mpc_rejects_and_counts_every_malformed_input(mpc_rig, states, forecasts, advance,
                                                      seed):
    rig, rng = mpc_rig, np.random.default_rng(seed)
    mpc, probe = rig['mpc'], rig['probe']
    expected = {'state': mpc.rejections.total('state') + sum(d is not None for d in states),
                'forecast': mpc.rejections.total('forecast')
                + sum(d is not None for d in forecasts)}
    if advance:  # a new step: the MPC solves it (before the batch: queues are 10 deep)
        _advance_mpc_clock(rig, rig['now'] + STEP_NS)
        _send_valid_mpc_inputs(rig, rng)
        probe.spin_until(lambda: mpc.history[-1][0].header.stamp.sec
                         == rig['now'] // NS_PER_S, what='the step solved')
    now, latest = rig['now'], rig['latest']
    for defect in states:
        if defect is None:  # a valid repeat of the current state: accepted
            rig['state'].publish(zone_state_msg(now, {'T': KELVIN + rng.uniform(15, 26)}))
        else:
            rig['state'].publish(malformed_zone_state(defect, now, latest, STEP_NS, rng))
    for defect in forecasts:
        if defect is None:
            rig['forecast'].publish(forecast_msg(now, 3600.0, _valid_window(rng, 5)))
        else:
            rig['forecast'].publish(malformed_forecast(defect, now, latest, STEP_NS, rng, 5))
    probe.spin_until(lambda: all(mpc.rejections.total(s) >= n for s, n in expected.items()),
                     what=f'{expected} rejections')
    probe.settle()
    assert {s: mpc.rejections.total(s) for s in expected} == expected
    rig['thrown'] += sum(d is not None for d in states + forecasts)
    probe.check_published_finite()
    status = mpc.history[-1][1]
    assert 0 <= status.rejected_states <= expected['state']
    assert 0 <= status.rejected_forecasts <= expected['forecast']


@pytest.fixture(scope='module')
def emulator_rig():
    """Yield a lockstep emulator (python R1C1) and a probe that sends it setpoints."""
    context = private_context()
    emulator = EmulatorNode(context=context, parameter_overrides=[
        Parameter('hours', value=2000), Parameter('model', value='python'),
        Parameter('ready_endpoints', value=['']), Parameter('reject_log_period_s', value=60.0),
        Parameter('lockstep_timeout_s', value=600.0)])
    probe = Probe(context, [emulator], [
        (ZoneState, contract.ZONE_STATE, contract.DATA_QOS),
        (Disturbances, contract.ZONE_DISTURBANCES, contract.DATA_QOS),
        (Clock, contract.CLOCK, contract.CLOCK_QOS)])
    rig = {'emulator': emulator, 'probe': probe,
           'setpoint': probe.node.create_publisher(Setpoint, contract.SETPOINT,
                                                   contract.DATA_QOS)}
    probe.spin_until(lambda: emulator.started and emulator.count_subscribers(
        contract.ZONE_STATE) > 0 and probe.node.count_subscribers(contract.SETPOINT) > 0)
    rig['setpoint'].publish(setpoint_msg(emulator.stamp_ns, 3600.0, {'q': 0.0}, {'T': 20.0}))
    probe.spin_until(lambda: len(emulator.records) == 1, what='the first step')
    rig['thrown'] = 0
    yield rig
    probe.close()
    rclpy.try_shutdown(context=context)
    _check_thrown('emulator', rig['thrown'])


@NODE_SETTINGS
@given(defects=st.lists(st.sampled_from(SETPOINT_DEFECTS), min_size=2, max_size=9),
       valid=st.booleans(), heat_rate=st.floats(-5000.0, 5000.0),
       seed=st.integers(0, 2 ** 32 - 1))
def test_emulator_rejects_and_counts_every_malformed_setpoint(emulator_rig, defects, valid,
                                                              heat_rate, seed):
    rig, rng = emulator_rig, np.random.default_rng(seed)
    emulator, probe = rig['emulator'], rig['probe']
    expected = emulator.rejections.total() + len(defects)
    steps = len(emulator.records)
    now = emulator.stamp_ns
    for defect in defects:
        rig['setpoint'].publish(malformed_setpoint(defect, now, now - STEP_NS, STEP_NS, rng))
    if valid:  # last: processed after the malformed ones (one topic, in order)
        rig['setpoint'].publish(setpoint_msg(now, 3600.0, {'q': heat_rate}, {'T': 21.0},
                                             {'q': [heat_rate]}, {'T': [21.0]}))
    probe.spin_until(lambda: emulator.rejections.total() >= expected
                     and len(emulator.records) == steps + valid, what='the batch')
    probe.settle()
    assert emulator.rejections.total() == expected
    assert len(emulator.records) == steps + valid
    rig['thrown'] += len(defects)
    if valid:  # applied, clipped to the actuator limits
        assert emulator.records[-1].controls[0] == float(np.clip(heat_rate, -2000.0, 2000.0))
        assert emulator.stamp_ns == now + STEP_NS
    assert np.all(np.isfinite(emulator.emulator.x))
    probe.check_published_finite()
