"""
ROS 2 nodes in one process: the closed loop over topics equals the core-only loop.

One 24 h lockstep run (emulator, forecaster, MPC and bag recorder in one
SingleThreadedExecutor, a private rclpy Context) is shared by the tests of this
module; tests that spin nodes of their own get a Context of their own.
Every spin loop has a wall-clock guard, so a deadlock fails instead of hanging.
"""
import math
import time

from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.controller import controller_for
from mshoot_core.emulation import Emulator
from mshoot_core.models.fmi import r1c1_fmi_model
from mshoot_core.models.multizone import MultiZoneModel
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.scenario import synthetic_scenario
from mshoot_core.units import KELVIN, NS_PER_S
from mshoot_msgs.msg import Setpoint
from mshoot_nodes import contract
from mshoot_nodes.bags import read_bag, read_messages
from mshoot_nodes.bringup import run_in_process
from mshoot_nodes.conversions import setpoint_plan, stamp_to_ns
from mshoot_nodes.emulator_node import EmulatorNode
from mshoot_nodes.forecaster_node import ForecasterNode
from mshoot_nodes.mpc_node import MpcNode
from mshoot_nodes.recorder_node import RecorderNode
from mshoot_nodes.replayer_node import ReplayerNode
import numpy as np
import pytest
import rclpy
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from conftest import private_context, spin_until

pytestmark = pytest.mark.ros
HOURS = 24
EPOCH_NS = 1522886400 * NS_PER_S  # 2018-04-05T00:00Z, the synthetic scenario's start


@pytest.fixture(scope='module')
def ros_run(tmp_path_factory):
    """Run 24 h in lockstep over ROS with a bag, and the core-only loop of the same case."""
    bag = tmp_path_factory.mktemp('ros_run') / 'bag'
    ctx = private_context()
    try:
        run = run_in_process(ctx, {
            'emulator': {'hours': HOURS},  # the default emulator: the R1C1 FMU
            'forecaster': {'hours': HOURS, 'use_sim_time': True},
            'mpc': {'model': 'python', 'use_sim_time': True},
            'recorder': {'bag_path': str(bag)},
        }, timeout_s=60.0)
    finally:
        rclpy.try_shutdown(context=ctx)
    mpc = MPC(R1C1Model(), horizon_steps=10)
    emulator = Emulator(r1c1_fmi_model(fmi_type='ModelExchange', tolerance=1e-10),
                        synthetic_scenario(hours=HOURS + 1), [20.0 + KELVIN])
    core = run_closed_loop(mpc, emulator, steps=HOURS, log_every=0)
    return run, core, bag


def test_ros_closed_loop_equals_core_loop(ros_run):
    run, core, _ = ros_run
    applied = run.emulator.applied_frame()
    assert len(applied) == HOURS
    np.testing.assert_allclose(applied.index.to_numpy(), core.steps.index.to_numpy())
    assert np.max(np.abs(applied['T_end'].to_numpy() - core.steps['T_end'].to_numpy())) < 1e-9
    assert np.max(np.abs(applied['q'].to_numpy() - core.steps['q'].to_numpy())) < 1e-6
    fine = run.emulator.fine_frame()
    assert fine.shape[0] == core.fine.shape[0] == HOURS * 60 + 1
    assert np.max(np.abs(fine['y_T'].to_numpy() - core.fine['y_T'].to_numpy())) < 1e-9


def test_a_setpoint_for_every_step(ros_run):
    run, core, _ = ros_run
    stamps = [stamp_to_ns(setpoint.header.stamp) for setpoint, _ in run.mpc.history]
    assert stamps == [EPOCH_NS + k * 3600 * NS_PER_S for k in range(HOURS)]
    statuses = [status for _, status in run.mpc.history]
    assert all(s.success and not s.fallback for s in statuses)
    first = run.mpc.history[0][0]
    assert list(first.control_names) == ['q'] and list(first.temperature_names) == ['T']
    assert len(first.plan_controls) == len(first.plan_temperatures_c) == 10
    assert first.control_values[0] == pytest.approx(core.steps['q'].iloc[0], abs=1e-6)
    assert first.temperature_setpoints_c[0] == pytest.approx(
        core.steps['T_predicted'].iloc[0] - KELVIN, abs=1e-9)
    assert run.forecaster.published == HOURS


def test_bag_has_every_topic_and_count(ros_run):
    run, _, bag = ros_run
    contents = read_bag(bag)
    assert contents.storage == 'mcap'
    assert set(contents.topics) == set(contract.RECORDED_TOPICS)
    for topic, (msgtype, qos) in contents.topics.items():
        assert msgtype == contract.TOPIC_TYPES[topic]
        assert qos, f'{topic}: no offered QoS in the metadata'
    assert contents.topics[contract.FORECAST][1][0].durability.name == 'TRANSIENT_LOCAL'
    assert contents.counts == run.recorder.counts
    assert sum(contents.counts.values()) == len(contents.messages)
    unique = {topic: len({(m.timestamp_ns, m.rawdata) for m in contents.messages
                          if m.topic == topic}) for topic in contents.topics}
    # Lockstep: one state/disturbances/clock per step plus the final one, one forecast,
    # setpoint and status per control step (heartbeats may add repeats, never new stamps).
    states = read_messages(bag, contract.ZONE_STATE)
    assert len({stamp_to_ns(m.header.stamp) for m in states}) == HOURS + 1
    for topic, expected in ((contract.CLOCK, HOURS + 1), (contract.ZONE_DISTURBANCES, HOURS + 1),
                            (contract.FORECAST, HOURS), (contract.SETPOINT, HOURS),
                            (contract.STATUS, HOURS)):
        assert contents.counts[topic] >= expected, topic
        assert unique[topic] >= expected, topic
    setpoints = read_messages(bag, contract.SETPOINT)
    assert [list(s.control_values) for s in setpoints][:HOURS] == \
        [list(s.control_values) for s, _ in run.mpc.history]
    # The states carry the model's states, outputs and the controls applied (by name).
    last = states[-1]
    assert list(last.state_names) == ['T'] and list(last.output_names) == ['T', 'Qr']
    assert last.state_values[0] == pytest.approx(run.emulator.emulator.x[0], abs=0)
    assert list(last.control_names) == ['q']
    assert last.control_values[0] == run.emulator.records[-1].controls[0]
    assert list(states[0].control_names) == []  # nothing applied before the first step
    disturbances = read_messages(bag, contract.ZONE_DISTURBANCES)
    assert list(disturbances[0].names) == ['solrad', 'Tout', 'occ', 'dpos']


def test_replayed_bag_drives_a_fresh_mpc_to_the_recorded_setpoints(ros_run, context):
    _, _, bag = ros_run
    recorded = read_messages(bag, contract.SETPOINT)
    contents = read_bag(bag)
    t0 = contents.messages[0].timestamp_ns
    setpoint_offsets = [m.timestamp_ns - t0 for m in contents.messages
                        if m.topic == contract.SETPOINT]
    replayer = ReplayerNode(context=context, parameter_overrides=[
        Parameter('bag_path', value=str(bag)), Parameter('autostart', value=False),
        Parameter('exclude_topics', value=[contract.SETPOINT, contract.STATUS])])
    fresh = MpcNode(context=context, parameter_overrides=[Parameter('use_sim_time', value=True)])
    executor = SingleThreadedExecutor(context=context)
    for node in (replayer, fresh):
        executor.add_node(node)
    spin_until(executor, lambda: fresh.count_publishers(contract.ZONE_STATE) > 0, 30.0)
    for k, offset in enumerate(setpoint_offsets):
        # Everything the original MPC had received when it published setpoint k.
        replayer.publish_until(offset - 1)
        spin_until(executor, lambda: len(fresh.history) > k)
    replayer.publish_until(2 ** 62)
    assert replayer.done
    replayed = [s for s, _ in fresh.history]
    assert [stamp_to_ns(s.header.stamp) for s in replayed] == \
        [stamp_to_ns(s.header.stamp) for s in recorded]
    np.testing.assert_allclose([s.control_values for s in replayed],
                               [s.control_values for s in recorded], rtol=0, atol=1e-9)
    np.testing.assert_allclose([s.plan_temperatures_c for s in replayed],
                               [s.plan_temperatures_c for s in recorded], rtol=0, atol=1e-9)
    executor.shutdown()
    for node in (replayer, fresh):
        node.destroy_node()


def test_replayer_keeps_the_recorded_timing_scaled(ros_run, context):
    _, _, bag = ros_run
    contents = read_bag(bag)
    span_s = (contents.messages[-1].timestamp_ns - contents.messages[0].timestamp_ns) / 1e9
    rate = span_s / 0.5  # the whole bag in 0.5 s
    replayer = ReplayerNode(context=context, parameter_overrides=[
        Parameter('bag_path', value=str(bag)), Parameter('rate', value=rate),
        Parameter('start_delay_s', value=0.2)])
    listener = rclpy.create_node('listener', context=context)
    received = []
    listener.create_subscription(Setpoint, contract.SETPOINT,
                                 lambda m: received.append(time.monotonic()), 100)
    executor = SingleThreadedExecutor(context=context)
    for node in (replayer, listener):
        executor.add_node(node)
    spin_until(executor, lambda: replayer.done and len(received) == contents.counts[
        contract.SETPOINT], 10.0)
    # Setpoints were recorded over most of the run: they arrive spread over ~0.5 s.
    assert 0.2 < received[-1] - received[0] < 3.0
    executor.shutdown()
    for node in (replayer, listener):
        node.destroy_node()


def test_solve_overrunning_its_budget_gets_a_fallback(context, tmp_path):
    """The solve runs in a worker thread: the node publishes a fallback while it runs."""
    run = run_in_process(context, {
        'emulator': {'hours': 3},
        'forecaster': {'hours': 3, 'use_sim_time': True},
        'mpc': {'use_sim_time': True, 'time_budget_s': 1e-4},
    }, record=False, timeout_s=30.0)
    # (the MPC may also decide the step of the emulator's final state: not applied)
    statuses = [status for _, status in run.mpc.history][:3]
    assert len(statuses) == 3 and all(s.fallback for s in statuses)
    assert 'time budget exceeded' in statuses[0].message
    assert run.emulator.applied_frame()['q'].tolist() == [0.0, 0.0, 0.0]


def test_free_running_emulator_completes(context):
    run = run_in_process(context, {
        'emulator': {'hours': 3, 'mode': 'free', 'speedup': 3600.0 / 0.5,
                     'clock_period_s': 0.01},
        'forecaster': {'hours': 3, 'use_sim_time': True},
        'mpc': {'use_sim_time': True},
    }, record=False, timeout_s=30.0)
    assert len(run.emulator.records) == 3
    # Each step applies the newest setpoint (0 W before the first one): never anything else.
    published = {setpoint.control_values[0] for setpoint, _ in run.mpc.history}
    assert published
    assert set(run.emulator.applied_frame()['q']) <= published | {0.0}


ZONES_HOURS = 12


@pytest.fixture(scope='module')
def two_zone_run(tmp_path_factory):
    """
    Run two R1C1 zones in lockstep over ROS with a price forecast, and the core-only loop.

    Controls q_0, q_1 (registry name 'r1c1x2'); the core-only loop runs the same case.
    """
    bag = tmp_path_factory.mktemp('two_zones') / 'bag'
    ctx = private_context()
    try:
        run = run_in_process(ctx, {
            'emulator': {'hours': ZONES_HOURS, 'model': 'r1c1x2'},
            'forecaster': {'hours': ZONES_HOURS, 'use_sim_time': True, 'send_price': True,
                           'price_per_kwh': [0.2] * 8 + [0.4] * 12 + [0.2] * 4},
            'mpc': {'model': 'r1c1x2', 'use_sim_time': True},
            'recorder': {'bag_path': str(bag)},
        }, timeout_s=60.0)
    finally:
        rclpy.try_shutdown(context=ctx)
    model = MultiZoneModel(2, seed=0)
    controller = controller_for(model)
    emulator = Emulator(MultiZoneModel(2, seed=0), synthetic_scenario(hours=ZONES_HOURS + 1),
                        [20.0 + KELVIN] * 2, control_names=('q_0', 'q_1'),
                        control_bounds=((-2000.0, 2000.0),) * 2)
    core = run_closed_loop(controller, emulator, steps=ZONES_HOURS, log_every=0)
    return run, core, bag


def test_two_zones_over_ros_equal_the_core_loop(two_zone_run):
    run, core, _ = two_zone_run
    applied = run.emulator.applied_frame()
    assert len(applied) == ZONES_HOURS
    assert list(core.steps.columns[:2]) == ['q_0', 'q_1']
    for state in ('T_0', 'T_1'):
        assert np.max(np.abs(applied[f'{state}_end'].to_numpy()
                             - core.steps[f'{state}_end'].to_numpy())) < 1e-9
    for control in ('q_0', 'q_1'):
        assert np.max(np.abs(applied[control].to_numpy() - core.steps[control].to_numpy())) \
            < 1e-6
    # The zones differ (their own sizes, sun and occupancy): two controls, not one copied.
    assert np.max(np.abs(applied['q_0'].to_numpy() - applied['q_1'].to_numpy())) > 1.0
    fine = run.emulator.fine_frame()
    for output in ('y_Tc_0', 'y_Tc_1'):
        assert np.max(np.abs(fine[output].to_numpy() - core.fine[output].to_numpy())) < 1e-9


def test_two_zone_setpoints_name_every_control_and_zone(two_zone_run):
    run, core, bag = two_zone_run
    history = list(run.mpc.history)
    assert [stamp_to_ns(s.header.stamp) for s, _ in history] == \
        [EPOCH_NS + k * 3600 * NS_PER_S for k in range(ZONES_HOURS)]
    assert all(status.success and not status.fallback for _, status in history)
    for k, (setpoint, _) in enumerate(history):
        assert list(setpoint.control_names) == ['q_0', 'q_1']
        assert list(setpoint.temperature_names) == ['T_0', 'T_1']
        np.testing.assert_allclose(setpoint.control_values,
                                   core.steps[['q_0', 'q_1']].iloc[k], rtol=0, atol=1e-6)
        np.testing.assert_allclose(
            setpoint.temperature_setpoints_c,
            core.steps[['T_0_predicted', 'T_1_predicted']].iloc[k] - KELVIN, rtol=0, atol=1e-9)
        controls, temperatures = setpoint_plan(setpoint)
        np.testing.assert_allclose(controls['q_1'], core.plans[k]['q_1'], rtol=0, atol=1e-6)
        np.testing.assert_allclose(temperatures['T_1'], core.plans[k]['T_1_end'] - KELVIN,
                                   rtol=0, atol=1e-9)
    # The forecasts carried the price (by hour of the day) and the MPC took them all.
    forecasts = read_messages(bag, contract.FORECAST)
    assert len(forecasts) == ZONES_HOURS
    assert list(forecasts[0].price_per_kwh) == [0.2] * 8 + [0.4] * 3
    assert list(forecasts[8].price_per_kwh) == [0.4] * 11
    assert run.mpc.rejections.total() == 0
    assert {(s.rejected_states, s.rejected_forecasts) for _, s in history} == {(0, 0)}
    # The states: both zones by name, their outputs and the controls applied.
    state = read_messages(bag, contract.ZONE_STATE)[-1]
    assert list(state.state_names) == ['T_0', 'T_1']
    np.testing.assert_allclose(state.state_values, core.steps[['T_0_end', 'T_1_end']].iloc[-1],
                               rtol=0, atol=1e-9)
    assert list(state.output_names) == ['Tc_0', 'Tc_1']
    assert list(state.control_names) == ['q_0', 'q_1']


def test_invalid_parameters_are_rejected_with_a_reason(context, tmp_path):
    def rejected(cls, **params):
        with pytest.raises(InvalidParameterValueException) as info:
            cls(context=context, parameter_overrides=[Parameter(k, value=v)
                                                      for k, v in params.items()])
        return str(info.value)

    assert "cost must be one of ['quadratic', 'energy', 'output'], got 'cubic'" in rejected(
        MpcNode, cost='cubic')
    assert 'horizon_steps must be in [1, 1000], got 0' in rejected(MpcNode, horizon_steps=0)
    # every problem of the start-up values at once
    reason = rejected(MpcNode, horizon_steps=0, soft_penalty=-1.0, time_budget_s=-2.0)
    assert all(text in reason for text in ('horizon_steps must be', 'soft_penalty must be',
                                           'time_budget_s must be')), reason
    assert 'control_min must be < control_max' in rejected(
        MpcNode, control_min=500.0, control_max=100.0)
    assert 'solver must be one of' in rejected(MpcNode, solver='newton')
    assert 'not found' in rejected(MpcNode, model='/nowhere/zone.fmu')
    assert 'not found' in rejected(EmulatorNode, scenario='/nowhere/data.csv')
    assert "mode must be one of ['lockstep', 'free']" in rejected(EmulatorNode, mode='fast')
    assert 'step_s must be a multiple of fine_step_s' in rejected(EmulatorNode, fine_step_s=7.0)
    assert 'start_time must be after 1970' in rejected(EmulatorNode, start_time='1960-01-01')
    assert 'temperature_uncertainty must be one of' in rejected(
        ForecasterNode, temperature_uncertainty='gauss')
    assert 'horizon <= 172800 s (48 h)' in rejected(ForecasterNode, solar_uncertainty='high',
                                                    horizon_steps=49)
    assert "storage must be one of ['mcap', 'sqlite3']" in rejected(
        RecorderNode, storage='zip', bag_path=str(tmp_path / 'b'))
    assert 'exists (set overwrite:=true' in rejected(RecorderNode, bag_path=str(tmp_path))

    # At run time: rejected changes keep the old value, valid ones rebuild the MPC.
    mpc = MpcNode(context=context)
    result = mpc.set_parameters([Parameter('control_min', value=3000.0)])[0]
    assert not result.successful and 'control_max' in result.reason
    result = mpc.set_parameters([Parameter('model', value='fmu')])[0]
    assert not result.successful and 'read-only' in result.reason
    result = mpc.set_parameters([Parameter('comfort', value='lukewarm')])[0]
    assert not result.successful and "'hard', 'soft'" in result.reason
    assert math.isnan(mpc.get_parameter('control_min').value)
    assert mpc.set_parameters([Parameter('horizon_steps', value=6)])[0].successful
    assert mpc.mpc.horizon_steps == 6
    assert mpc.set_parameters([Parameter('comfort', value='soft')])[0].successful
    assert mpc.mpc.problem.soft_bounds
    mpc.destroy_node()
    # A model of several controls keeps them through run-time changes.
    zones = MpcNode(context=context, parameter_overrides=[Parameter('model', value='r1c1x2')])
    assert zones.set_parameters([Parameter('horizon_steps', value=4)])[0].successful
    assert zones.mpc.horizon_steps == 4
    assert zones.controller.settings.problem.control_names == ('q_0', 'q_1')
    zones.destroy_node()


def test_mpc_yaml_documents_every_parameter_with_valid_values():
    """
    Every parameter of the node is in config/mpc.yaml, and its values make valid settings.

    The settings table is included.
    """
    import yaml
    from mshoot_nodes.config import config_dir
    from mshoot_nodes.mpc_node import DEFAULTS, PARAMS, settings_from
    values = yaml.safe_load((config_dir() / 'mpc.yaml').read_text())['mpc']['ros__parameters']
    declared = {spec.name for spec in PARAMS} | {'use_sim_time', 'autostart'}
    assert set(values) == declared, (set(values) ^ declared)
    settings = settings_from({**DEFAULTS, **values})
    assert settings.problem.horizon_steps == values['horizon_steps']
