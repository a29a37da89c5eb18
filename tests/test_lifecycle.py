"""
Lifecycle nodes, /diagnostics and the readiness check, in one process.

Real rclpy nodes in a private Context (``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``), one
SingleThreadedExecutor, lifecycle transitions through the real ``~/change_state`` and
``~/get_state`` services from a client node; every wait has a generous wall-clock guard
(a deadlock fails, a slow machine only waits longer).
"""
import time

from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from mshoot_msgs.msg import MpcStatus, Setpoint, ZoneState
from mshoot_nodes import contract
from mshoot_nodes.conversions import ns_to_stamp, setpoint_msg, stamp_to_ns
from mshoot_nodes.diagnostics import (DiagnosticsPublisher, format_value, Level, Report,
                                      status_values)
from mshoot_nodes.emulator_node import EmulatorNode
from mshoot_nodes.lifecycle import ERROR, FAILURE, ManagedNode, SUCCESS
from mshoot_nodes.readiness import (parse_requirement, parse_requirements, ReadinessGate,
                                    Requirement, run_requirements)
from mshoot_nodes.recorder_node import RecorderNode
from mshoot_testing.harness import ClosedLoop, malformed_setpoint
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

pytestmark = pytest.mark.ros
GUARD_S = 30.0
HOUR_NS = 3600 * 10 ** 9


class Rig:
    """An executor, a probe node and the nodes under test (destroyed by close)."""

    def __init__(self, context, *nodes):
        self.executor = SingleThreadedExecutor(context=context)
        self.probe = rclpy.create_node('probe', context=context)
        self.nodes = [self.probe, *nodes]
        for node in self.nodes:
            self.executor.add_node(node)

    def add(self, node):
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def spin_until(self, condition, what='the condition', timeout_s=GUARD_S):
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, f'{what} not reached within {timeout_s} s'
            self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, wall_s):
        end = time.monotonic() + wall_s
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def call(self, client, request):
        assert client.wait_for_service(timeout_sec=GUARD_S), f'{client.srv_name} not offered'
        future = client.call_async(request)
        self.spin_until(future.done, f'the answer of {client.srv_name}')
        return future.result()

    def close(self):
        self.executor.shutdown()
        for node in reversed(self.nodes):
            node.destroy_node()


class Lifecycle:
    """A lifecycle client of one node through its services."""

    def __init__(self, rig, node_name):
        self.rig = rig
        self.get = rig.probe.create_client(GetState, f'/{node_name}/get_state')
        self.change = rig.probe.create_client(ChangeState, f'/{node_name}/change_state')

    def state(self):
        return self.rig.call(self.get, GetState.Request()).current_state.label

    def transition(self, transition_id):
        request = ChangeState.Request(transition=Transition(id=transition_id))
        return self.rig.call(self.change, request).success


# -- the emulator's lifecycle -------------------------------------------------------------------
def test_emulator_lifecycle_through_its_services(context):
    emulator = EmulatorNode(context=context, parameter_overrides=[
        Parameter('autostart', value=False), Parameter('hours', value=4),
        Parameter('model', value='fmu'), Parameter('ready_endpoints', value=['']),
        Parameter('heartbeat_period_s', value=0.1)])
    rig = Rig(context, emulator)
    states = []
    rig.probe.create_subscription(ZoneState, contract.ZONE_STATE, states.append,
                                  contract.DATA_QOS)
    setpoints = rig.probe.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)
    lifecycle = Lifecycle(rig, 'emulator')
    graph = rig.probe

    def answer_last_state():
        """Send the setpoint of the newest state (as the MPC would)."""
        setpoints.publish(setpoint_msg(stamp_to_ns(states[-1].header.stamp), 3600.0,
                                       {'q': 100.0}, {'T': 21.0}))

    def run_until_steps(steps):
        def advanced():
            if states and emulator.steps_done < steps and \
                    stamp_to_ns(states[-1].header.stamp) == emulator.stamp_ns:
                answer_last_state()
            return emulator.steps_done >= steps
        rig.spin_until(advanced, f'{steps} steps')

    try:
        assert lifecycle.state() == 'unconfigured'
        assert emulator.emulator is None and graph.count_publishers(contract.ZONE_STATE) == 0

        assert lifecycle.transition(Transition.TRANSITION_CONFIGURE)
        assert lifecycle.state() == 'inactive'
        fmu = emulator.emulator.model
        assert fmu._fmu is not None  # noqa: SLF001 - the FMU instance is loaded
        rig.spin_until(lambda: graph.count_publishers(contract.ZONE_STATE) == 1, 'publishers')
        assert graph.count_subscribers(contract.SETPOINT) == 0  # no subscription yet
        rig.spin_for(0.3)
        assert not states and not emulator.started  # inactive: nothing published

        assert lifecycle.transition(Transition.TRANSITION_ACTIVATE)
        assert lifecycle.state() == 'active'
        assert graph.count_subscribers(contract.SETPOINT) == 1
        run_until_steps(2)

        assert lifecycle.transition(Transition.TRANSITION_DEACTIVATE)
        assert lifecycle.state() == 'inactive'
        assert graph.count_subscribers(contract.SETPOINT) == 0
        published = len(states)
        answer_last_state()
        rig.spin_for(0.5)  # no heartbeats, no steps while inactive
        assert len(states) == published and emulator.steps_done == 2

        assert lifecycle.transition(Transition.TRANSITION_ACTIVATE)  # resumes the run
        run_until_steps(4)
        assert emulator.done and not emulator.failed
        assert emulator.applied_sources == ['setpoint'] * 4

        assert lifecycle.transition(Transition.TRANSITION_DEACTIVATE)
        assert lifecycle.transition(Transition.TRANSITION_CLEANUP)
        assert lifecycle.state() == 'unconfigured'
        assert fmu._fmu is None  # noqa: SLF001 - the FMU instance is freed
        rig.spin_until(lambda: graph.count_publishers(contract.ZONE_STATE) == 0, 'no publisher')
        assert len(emulator.applied_frame()) == 4  # the records stay readable

        assert lifecycle.transition(Transition.TRANSITION_CONFIGURE)  # a fresh run
        assert emulator.steps_done == 0 and not emulator.records and not emulator.done
        assert emulator.emulator.model is not fmu
        assert not lifecycle.transition(Transition.TRANSITION_CONFIGURE)  # not from inactive
        assert lifecycle.state() == 'inactive'
    finally:
        rig.close()


def test_autostart_and_a_failed_configure(context, tmp_path):
    emulator = EmulatorNode(context=context, parameter_overrides=[
        Parameter('hours', value=2), Parameter('model', value='python')])
    assert emulator.lifecycle_state == 'active'  # autostart: configured and active at once
    emulator.destroy_node()

    broken = tmp_path / 'broken.fmu'
    broken.write_bytes(b'not a zip archive')
    with pytest.raises(Exception) as info:  # what `ros2 run` reports with exit code 2
        EmulatorNode(context=context, parameter_overrides=[Parameter('model', value=str(broken))])
    assert 'zip' in str(info.value).lower()

    managed = EmulatorNode(context=context, parameter_overrides=[
        Parameter('model', value=str(broken)), Parameter('autostart', value=False)])
    rig = Rig(context, managed)
    try:
        lifecycle = Lifecycle(rig, 'emulator')
        assert not lifecycle.transition(Transition.TRANSITION_CONFIGURE)
        assert lifecycle.state() == 'unconfigured'
        assert managed.transition_error is not None and not managed.is_configured
    finally:
        rig.close()


# -- the base class ----------------------------------------------------------------------------
class Toy(ManagedNode):
    """A managed node that records its hooks and can be told to fail in one."""

    def __init__(self, fail_in=(), **kwargs):
        super().__init__('toy', **kwargs)
        self.calls, self.fail_in, self.ticks = [], set(fail_in), 0
        self.late_timer = None
        self.autostart()

    def _hook(self, name):
        self.calls.append(name)
        if name in self.fail_in:
            raise ValueError(f'{name} refused')

    def configure(self):
        self.out = self.create_lifecycle_publisher(String, '/toy/out', 10)
        self._hook('configure')

    def activate(self):
        self.tick_timer = self.create_timer(3600.0, self._tick)  # simulated hours
        self._hook('activate')

    def _tick(self):
        self.ticks += 1
        if self.late_timer is None:  # created while active: owned by the activation
            self.late_timer = self.create_timer(1000.0, lambda: None)

    def deactivate(self):
        self.out.publish(String(data='last words'))
        self._hook('deactivate')

    def cleanup(self):
        self._hook('cleanup')


def test_managed_node_hooks_ownership_and_simulated_time(context):
    toy = Toy(context=context, parameter_overrides=[Parameter('use_sim_time', value=True)])
    rig = Rig(context, toy)
    heard = []
    rig.probe.create_subscription(String, '/toy/out', lambda m: heard.append(m.data), 10)
    clock = rig.probe.create_publisher(Clock, contract.CLOCK, contract.CLOCK_QOS)
    try:
        # Autostart with use_sim_time and no /clock yet: active at once, nothing fired.
        assert toy.lifecycle_state == 'active' and toy.calls == ['configure', 'activate']
        rig.spin_for(0.2)
        assert toy.ticks == 0
        rig.spin_until(lambda: rig.probe.count_subscribers(contract.CLOCK) >= 1, '/clock')
        rig.spin_until(lambda: clock.publish(Clock(clock=ns_to_stamp(7 * HOUR_NS))) or
                       toy.ticks >= 1, 'a tick on simulated time')
        assert toy.late_timer in list(toy.timers)
        rig.spin_until(lambda: rig.probe.count_publishers('/toy/out') == 1, 'the publisher')

        assert toy.trigger_deactivate() == SUCCESS
        assert toy.tick_timer not in list(toy.timers) and toy.late_timer not in list(toy.timers)
        rig.spin_until(lambda: heard == ['last words'], 'the message sent in deactivate')
        toy.out.publish(String(data='while inactive'))  # a lifecycle publisher: dropped
        rig.spin_for(0.3)
        assert heard == ['last words']

        assert toy.trigger_cleanup() == SUCCESS
        assert toy.out not in list(toy.publishers)
        # A hook that raises: FAILURE, the node stays where it was, what it made is gone.
        toy.fail_in = {'activate'}
        assert toy.trigger_configure() == SUCCESS
        assert toy.trigger_activate() == FAILURE
        assert toy.lifecycle_state == 'inactive'
        assert 'activate refused' in str(toy.transition_error)
        assert not any(t.timer_period_ns == 3600 * 10 ** 9 for t in toy.timers)
        toy.fail_in = set()
        assert toy.trigger_activate() == SUCCESS
        # deactivate raising: error processing releases everything, the node is unconfigured.
        toy.fail_in, toy.calls = {'deactivate'}, []
        assert toy.trigger_deactivate() == ERROR
        assert toy.lifecycle_state == 'unconfigured' and toy.calls == ['deactivate', 'cleanup']
        assert not toy.is_configured and toy.out not in list(toy.publishers)
        toy.fail_in = set()
        assert toy.trigger_configure() == SUCCESS and toy.trigger_activate() == SUCCESS
        toy.calls.clear()
        assert toy.trigger_shutdown() == SUCCESS
        assert toy.calls == ['deactivate', 'cleanup'] and toy.lifecycle_state == 'finalized'
    finally:
        rig.close()

    with pytest.raises(ValueError, match='configure refused'):
        Toy(fail_in={'configure'}, context=context)
    waiting = Toy(context=context, parameter_overrides=[Parameter('autostart', value=False)])
    assert waiting.lifecycle_state == 'unconfigured' and waiting.calls == []
    waiting.destroy_node()


# -- /diagnostics ------------------------------------------------------------------------------
def test_every_node_reports_on_diagnostics(context, tmp_path):
    hours = 4
    loop = ClosedLoop(context, {
        'emulator': {'hours': hours, 'model': 'python'},
        'forecaster': {'hours': hours},
        'mpc': {'model': 'python', 'horizon_steps': 4},
        'recorder': {'bag_path': str(tmp_path / 'bag')}}, record=True)
    listener = rclpy.create_node('listener', context=context)
    loop._add(listener)  # noqa: SLF001 - destroyed with the loop
    latest = {}
    listener.create_subscription(
        DiagnosticArray, '/diagnostics',
        lambda m: latest.update({s.name: s for s in m.status}), 50)
    chaos = listener.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)
    try:
        loop.run_steps(2)
        emulator = loop.emulator
        rng = np.random.default_rng(0)
        chaos.publish(malformed_setpoint('nan_heat_rate', emulator.stamp_ns, emulator.stamp_ns,
                                         HOUR_NS, rng))
        loop.spin_until(lambda: emulator.rejections.total() == 1, GUARD_S, 'the rejection')
        loop.run_to_end()
        recorder = loop.recorder

        def reported():
            values = {name: status_values(status) for name, status in latest.items()}
            return (values.get('mshoot/emulator', {}).get('step') == str(hours)
                    and values.get('mshoot/forecaster', {}).get('forecasts_published')
                    == str(hours)
                    and values.get('mshoot/recorder', {}).get(f'messages {contract.STATUS}')
                    == str(recorder.counts[contract.STATUS])
                    and int(values.get('mshoot/mpc', {}).get('decisions', 0)) >= hours)
        loop.spin_until(reported, GUARD_S, 'the final reports')

        emu = latest['mshoot/emulator']
        values = status_values(emu)
        assert emu.level == Level.OK.to_msg() and emu.message == f'scenario over: {hours} steps'
        assert emu.hardware_id == 'zone'
        assert values['lifecycle_state'] == 'active'
        assert values['applied_setpoint'] == str(hours) and values['applied_safe'] == '0'
        assert values['rejected_setpoints'] == '1'
        assert values['lockstep_timeouts'] == '0'
        assert int(values['lockstep_waits']) >= 0
        assert status_values(latest['mshoot/recorder'])['ready'] == 'true'
        mpc = status_values(latest['mshoot/mpc'])
        assert mpc['lifecycle_state'] == 'active' and int(mpc['optimum']) >= hours
        assert mpc['safe'] == '0' and mpc['rejected_states'] == '0'
        assert float(mpc['last_solve_s']) > 0
        assert recorder.counts[contract.STATUS] >= hours

        loop.forecaster.set_parameters([Parameter('enabled', value=False)])
        paused = loop.forecaster.diagnostics.publish().status[0]
        assert paused.level == Level.WARN.to_msg() and 'paused' in paused.message
    finally:
        loop.close()


def test_diagnostics_publisher_levels_and_failures(context):
    node = rclpy.create_node('plain', context=context)
    reports = iter([Report(Level.STALE, 'no data', {'age_s': 12.5, 'ok': False}),
                    RuntimeError('sensor gone')])

    def report():
        item = next(reports)
        if isinstance(item, Exception):
            raise item
        return item

    try:
        diagnostics = DiagnosticsPublisher(node, report, period_s=0.0, hardware_id='zone 1')
        first = diagnostics.publish().status[0]
        assert first.name == 'mshoot/plain' and first.hardware_id == 'zone 1'
        assert first.level == bytes([3])
        assert status_values(first) == {'age_s': '12.5', 'ok': 'false'}
        second = diagnostics.publish().status[0]
        assert second.level == bytes([2]) and 'sensor gone' in second.message
        assert format_value(float('nan')) == 'nan' and format_value({'a': 1}) == 'a: 1'
        with pytest.raises(ValueError, match='period_s'):
            DiagnosticsPublisher(node, report, period_s=-1.0)
    finally:
        node.destroy_node()


# -- readiness from the graph ------------------------------------------------------------------
def test_requirements_parse_and_reject_bad_text():
    assert parse_requirement('/a publishers>=1 subscribers>=2') == Requirement('/a', 1, 2)
    assert str(Requirement('/a', 0, 2)) == '/a subscribers>=2'
    assert parse_requirements(['', '  ']) == []
    for bad in ('/a', '/a pubs>=1', '/a publishers>=1 publishers>=2', '/a publishers>1',
                'not a topic publishers>=1', '1a publishers>=1'):
        with pytest.raises(ValueError, match='readiness requirement'):
            parse_requirement(bad)
    assert f'{contract.RECORDER_READY} publishers>=1' in run_requirements('mshoot')
    assert all(contract.RECORDER_READY not in r for r in run_requirements('rosbag2'))
    with pytest.raises(ValueError, match='recorder must be one of'):
        run_requirements('tape')


def test_gate_opens_only_when_the_endpoints_exist(context):
    rig = Rig(context)
    opened, timeouts = [], []
    try:
        gate = ReadinessGate(rig.probe, parse_requirements(
            ['/gate/a publishers>=1', '/gate/b subscribers>=2']),
            on_ready=lambda: opened.append(True), on_timeout=timeouts.append)
        rig.spin_for(0.3)
        assert not gate.ready and gate.missing == ['/gate/a: 0 of 1 publishers',
                                                   '/gate/b: 0 of 2 subscribers']
        other = rig.add(rclpy.create_node('other', context=context))
        other.create_publisher(String, '/gate/a', 10)
        other.create_subscription(String, '/gate/b', lambda m: None, 10)
        rig.spin_until(lambda: gate.missing == ['/gate/b: 1 of 2 subscribers'], 'one missing')
        assert not opened
        other.create_subscription(String, '/gate/b', lambda m: None, 10)
        rig.spin_until(lambda: gate.ready, 'the gate to open')
        rig.spin_for(0.2)
        assert opened == [True] and not timeouts

        late = ReadinessGate(rig.probe, parse_requirements(['/gate/c publishers>=1']),
                             on_ready=lambda: opened.append(False),
                             on_timeout=timeouts.append, timeout_s=0.3)
        rig.spin_until(lambda: timeouts, 'the timeout')
        assert not late.ready and opened == [True]
        assert 'not ready after' in timeouts[0] and '/gate/c: 0 of 1 publishers' in timeouts[0]
    finally:
        rig.close()


def test_recorder_is_ready_once_its_subscriptions_matched(context, tmp_path):
    recorder = RecorderNode(context=context, parameter_overrides=[
        Parameter('bag_path', value=str(tmp_path / 'bag')),
        Parameter('topics', value=[contract.SETPOINT, contract.STATUS])])
    rig = Rig(context, recorder)
    ready = []
    try:
        rig.spin_for(0.3)
        assert not recorder.ready and rig.probe.count_publishers(contract.RECORDER_READY) == 0
        rig.probe.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)
        rig.spin_until(lambda: contract.SETPOINT in recorder.matched, 'the setpoint match')
        rig.spin_for(0.2)
        assert rig.probe.count_publishers(contract.RECORDER_READY) == 0  # status unmatched
        rig.probe.create_publisher(MpcStatus, contract.STATUS, contract.DATA_QOS)
        rig.spin_until(lambda: rig.probe.count_publishers(contract.RECORDER_READY) == 1,
                       '/recorder/ready in the graph')
        rig.probe.create_subscription(String, contract.RECORDER_READY,
                                      lambda m: ready.append(m.data), contract.LATCHED_QOS)
        rig.spin_until(lambda: ready, 'the latched ready message')
        assert ready == [f'matched: {contract.SETPOINT}, {contract.STATUS}']
    finally:
        rig.close()


def test_emulator_gate_waits_for_the_run_and_times_out_naming_what_is_missing(context):
    emulator = EmulatorNode(context=context, parameter_overrides=[
        Parameter('hours', value=2), Parameter('model', value='python'),
        Parameter('ready_endpoints', value=run_requirements('mshoot')),
        Parameter('ready_timeout_s', value=1.0)])
    rig = Rig(context, emulator)
    try:
        rig.probe.create_subscription(ZoneState, contract.ZONE_STATE, lambda m: None,
                                      contract.DATA_QOS)
        rig.probe.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)
        rig.spin_until(lambda: emulator.done, 'the start gate to give up')
        assert not emulator.started and emulator.steps_done == 0
        failed = emulator.failed
        assert 'not ready after' in failed
        assert f'{contract.ZONE_STATE}: 1 of 2 subscribers' in failed
        assert f'{contract.FORECAST}: 0 of 1 publishers' in failed
        assert f'{contract.RECORDER_READY}: 0 of 1 publishers' in failed
        assert contract.SETPOINT not in failed  # that one was there
        report = emulator.health()
        assert report.level == Level.ERROR and 'not ready' in report.message
    finally:
        rig.close()


# -- the MPC's lifecycle ------------------------------------------------------------------------
def test_mpc_deactivate_hands_the_building_back_with_one_safe_setpoint(context):
    hours = 6
    loop = ClosedLoop(context, {
        'emulator': {'hours': hours, 'model': 'python', 'lockstep_timeout_s': 60.0},
        'forecaster': {'hours': hours},
        'mpc': {'model': 'python', 'horizon_steps': 4, 'safe_value': 300.0}})
    try:
        loop.run_steps(2)
        mpc = loop.mpc
        assert mpc.lifecycle_state == 'active'
        before = len(mpc.history)
        assert mpc.trigger_deactivate() == SUCCESS
        assert len(mpc.history) == before + 1
        setpoint, status = mpc.history[-1]
        assert status.source == 'safe' and status.fallback
        assert status.fallback_reason == 'deactivated' and 'deactivated' in status.message
        assert list(setpoint.control_values) == [300.0] and list(setpoint.plan_controls) == []
        health = mpc.diagnostics.publish().status[0]
        assert status_values(health)['lifecycle_state'] == 'inactive'
        loop.spin_for(0.5)  # inactive: the emulator's heartbeats get no answer
        assert len(mpc.history) == before + 1
        assert mpc.trigger_activate() == SUCCESS
        loop.run_to_end()
        after = [s.source for _, s in list(mpc.history)[before + 1:]]
        assert after and set(after) == {'optimum'}
        assert loop.emulator.steps_done == hours
        assert mpc.trigger_deactivate() == SUCCESS and mpc.trigger_cleanup() == SUCCESS
        assert mpc.controller is None and mpc.lifecycle_state == 'unconfigured'
    finally:
        loop.close()
