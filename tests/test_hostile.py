"""
Hostile peers: the attacks of issue 25 against the validation contract and the graph watch.

Each attack first against the decision in core (plain tests), then against real nodes in one
process (a private rclpy context, real DDS pub/sub): an off-grid setpoint (1), a zone state
from the future with junk fields (2), 10^6-element arrays (3), a second writer of a stream
(intruders), peers gone quiet (7: STALE on /diagnostics). The flood over DDS against the
three executables is ``bench/hostile.py``; its short version is the last test.
"""
import json
import math
import os
import re
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from mshoot_core.controller import controller_for
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.peers import format_gid, Peer, PeerWatch, Writer
from mshoot_core.safety import (check_history, check_lengths, check_on_grid, check_setpoint,
                                setpoint_caps, StampGate)
from mshoot_core.scenario import forecast_window, synthetic_scenario
from mshoot_core.settings import MpcSettings
from mshoot_core.units import KELVIN, NS_PER_S
from mshoot_msgs.msg import Forecast, MpcStatus, Setpoint, ZoneState
from mshoot_nodes import contract
from mshoot_nodes.conversions import clock_msg, forecast_msg, setpoint_msg, zone_state_msg
from mshoot_nodes.diagnostics import status_values
from mshoot_nodes.emulator_node import EmulatorNode
from mshoot_nodes.mpc_node import MpcNode
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from conftest import GUARD_S, ROOT

STEP_NS = 3600 * NS_PER_S
#: The synthetic scenario's start (2018-04-05 00:00 UTC): on the hour grid.
EPOCH_NS = 1522886400 * NS_PER_S
HUGE = 1_000_000


def spin_until(executor, condition, what, timeout_s=GUARD_S):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f'{what} not within {timeout_s} s'
        executor.spin_once(timeout_sec=0.02)


def spin_for(executor, wall_s):
    end = time.monotonic() + wall_s
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.02)


# -- the decisions in core ----------------------------------------------------------------
def test_a_stamp_off_the_step_grid_is_refused_and_moves_nothing():
    assert check_on_grid(EPOCH_NS + 3 * STEP_NS, STEP_NS, EPOCH_NS) is None
    off = check_on_grid(EPOCH_NS + 3 * STEP_NS + 1, STEP_NS, EPOCH_NS)
    assert off.kind == 'grid' and '1e-09 s past the start of its step' in off.reason
    gate = StampGate(STEP_NS, origin_ns=EPOCH_NS)
    now = EPOCH_NS + 2 * STEP_NS + 1800 * NS_PER_S  # mid-step (a free-running clock)
    assert gate.check(now, now).kind == 'grid'  # attack 1: a setpoint stamped at the clock
    assert gate.latest_ns is None
    assert gate.check(EPOCH_NS + 2 * STEP_NS, now) is None


def test_a_schedule_is_checked_with_the_rest_of_the_setpoint():
    """Attack 1, second half: a setpoint with a junk schedule is rejected whole."""
    base = ('q',), [100.0]
    assert check_setpoint(3600.0, *base, schedule_offsets_s=[0.0, 600.0],
                          schedule_values=[100.0, 0.0]) is None
    for offsets, values, kind in (([0.0, 600.0], [100.0, math.nan], 'non_finite'),
                                  ([0.0, 600.0], [100.0], 'length'),
                                  ([600.0, 0.0], [1.0, 2.0], 'out_of_range'),
                                  ([0.0, 4000.0], [1.0, 2.0], 'out_of_range')):
        rejection = check_setpoint(3600.0, *base, schedule_offsets_s=offsets,
                                   schedule_values=values)
        assert rejection is not None and rejection.kind == kind, (offsets, values, rejection)
    assert check_setpoint(3600.0, *base, schedule_offsets_s=[0.0], schedule_values=[1.0],
                          schedules=False).kind == 'length'


def _controller():
    return controller_for(R1C1Model(), MpcSettings.from_flat(horizon_steps=3),
                          assumed_inputs={'dpos': 0.0})


def _forecast(controller, k):
    window = forecast_window(synthetic_scenario(hours=12), k, controller.mpc.horizon_steps)
    return {c: window[c].to_numpy() for c in window.columns}


def test_a_state_from_the_future_with_junk_fields_is_rejected_and_locks_nothing_out():
    """
    Attack 2 in core: stamped at the next step + 1 s, plausible T, junk fields.

    Each junk field alone gets the state rejected, and the real state of the next step is then
    taken (not 'backwards') and planned from.
    """
    controller = _controller()
    now = 2 * STEP_NS + 1800 * NS_PER_S  # mid-step: the injected stamp is within max_future_s
    assert controller.offer_state(2 * STEP_NS, [20.0 + KELVIN], now) is None
    junk = {'off grid': {'stamp': 3 * STEP_NS + NS_PER_S},
            'output': {'output_names': ['T'], 'output_values': [1e300]},
            'applied': {'control_names': ['q'], 'control_values': [9.9e6]},
            'history': {'history': ([-60.0, 0.0], [293.0], ['T'], [math.nan, 20.0])},
            'history inf': {'history': ([-60.0, 0.0], [293.0, 293.0], ['T'],
                                        [math.nan, math.inf])}}
    for what, fields in junk.items():
        stamp = fields.pop('stamp', 3 * STEP_NS)
        rejection = controller.offer_named_state(stamp, ['T'], [21.0 + KELVIN], now, **fields)
        assert rejection is not None, what
    assert controller.rejections.by_kind() == {'grid': 1, 'out_of_range': 2, 'length': 1,
                                               'non_finite': 1}
    assert controller.offer_forecast(3 * STEP_NS, 3600.0, _forecast(controller, 3),
                                     3 * STEP_NS) is None
    real = 19.5 + KELVIN
    assert controller.offer_named_state(3 * STEP_NS, ['T'], [real], 3 * STEP_NS,
                                        output_names=['T', 'Qr'], output_values=[19.5, 3.6e6],
                                        control_names=['q'], control_values=[150.0]) is None
    [outcome] = controller.poll(3 * STEP_NS)
    assert outcome.decision.source == 'optimum'
    np.testing.assert_array_equal(outcome.x0, [real])


def test_a_warm_up_history_is_checked_field_by_field():
    assert check_history(['T'], [-120.0, -60.0, 0.0], [290.0, 291.0, 292.0], ['T'],
                         [math.nan, 17.0, 18.0]) is None
    assert check_history(['T'], [-60.0, 0.0], [290.0], ['T'], [1.0, 2.0]).kind == 'length'
    assert check_history(['T'], [0.0, 60.0], [290.0, 291.0], [], []).kind == 'out_of_range'
    assert check_history(['T'], [0.0, -60.0], [290.0, 291.0], [], []).kind == 'out_of_range'
    assert check_history(['T'], [-60.0, 0.0], [290.0, math.inf], [], []).kind == 'non_finite'


def test_huge_arrays_are_refused_by_their_length_before_anything_is_converted():
    """Attack 3 in core: 10^6 elements against the caps of the model's dimensions."""
    caps = setpoint_caps(1)
    lengths = {field: HUGE for field in caps}
    rejection = check_lengths('setpoint', lengths, caps)
    assert rejection.kind == 'length' and 'control_names has 1000000 elements, at most 1' \
        in rejection.reason
    controller = _controller()
    for fields in ({'state_names': ['T'] * HUGE, 'state_values': np.full(HUGE, 293.0)},
                   {'state_names': ['T'], 'state_values': [293.0],
                    'history': (np.zeros(HUGE), [], [], [])},
                   {'state_names': ['T'], 'state_values': [293.0], 'output_names': ['T'],
                    'output_values': np.zeros(HUGE)}):
        rejection = controller.offer_named_state(0, now_ns=0, **fields)
        assert rejection.kind == 'length' and 'at most' in rejection.reason
    assert controller.rejections.total('state') == 3 and not controller._states  # noqa: SLF001


def test_a_second_writer_of_a_stream_is_an_intruder():
    mpc = Writer('/mpc', format_gid(bytes(range(1, 17)) + bytes(8)))
    assert mpc.gid == '01.02.03.04.05.06.07.08.09.0a.0b.0c.0d.0e.0f.10'
    hostile = Writer('/hostile', '02')
    twin = Writer('/other_ns/mpc', '03')
    from mshoot_core.peers import intruders
    assert intruders([mpc], 'mpc') == []
    assert intruders([mpc, hostile], 'mpc') == [hostile]
    assert intruders([mpc, twin], 'mpc') == [mpc, twin]  # which one is ours? both reported
    assert intruders([hostile], 'mpc') == [hostile]
    watch = PeerWatch([Peer('setpoint', '/mpc/setpoint', 'mpc', 5.0)])
    assert watch.writers('setpoint', [mpc, hostile]) == [hostile]
    assert watch.writers('setpoint', [mpc, hostile]) == []  # logged once
    watch.heard('setpoint', 0)
    status = watch.status('setpoint', NS_PER_S)
    assert status.level == 'ERROR' and '/hostile (gid 02)' in status.message
    watch.writers('setpoint', [mpc])
    assert watch.status('setpoint', NS_PER_S).level == 'OK'


def test_a_peer_not_heard_from_within_its_timeout_is_stale():
    watch = PeerWatch([Peer('state', '/zone/state', 'emulator', 2.0),
                       Peer('clock', '/clock', '', 2.0)])
    first = watch.statuses(0)
    assert [(s.peer.name, s.level) for s in first] == [('state', 'STALE'), ('clock', 'STALE')]
    assert first[0].message == 'nothing heard on /zone/state yet'
    watch.heard('state', 10 * NS_PER_S)
    watch.heard('clock', 10 * NS_PER_S)
    assert {s.level for s in watch.statuses(12 * NS_PER_S)} == {'OK'}
    watch.heard('clock', 12 * NS_PER_S)
    late = watch.statuses(int(12.5 * NS_PER_S))
    assert [s.level for s in late] == ['STALE', 'OK']
    assert 'nothing heard on /zone/state for 2.5 s (timeout 2 s)' == late[0].message
    with pytest.raises(ValueError, match='timeout_s'):
        Peer('state', '/zone/state', 'emulator', 0.0)


# -- real nodes, one process ----------------------------------------------------------------
@pytest.fixture
def rig(context):
    """Yield an executor on the private context; every node added is destroyed after the test."""
    executor = SingleThreadedExecutor(context=context)
    nodes = []

    def add(node):
        nodes.append(node)
        executor.add_node(node)
        return node
    executor.nodes_made = nodes
    executor.add = add
    yield executor
    executor.shutdown()
    for node in nodes:
        node.destroy_node()


def test_off_grid_setpoints_do_not_displace_the_mpcs_in_free_mode(context, rig):
    """
    Attack 1: every clock tick, a setpoint stamped at the clock (mid-step, valid fields).

    The 'mpc' answers each state with its setpoint; every step applies it, none the safe
    default, and the off-grid ones are rejected with kind 'grid'.
    """
    hours = 5
    emulator = rig.add(EmulatorNode(context=context, parameter_overrides=[
        Parameter('hours', value=hours), Parameter('model', value='python'),
        Parameter('mode', value='free'), Parameter('speedup', value=18000.0),
        Parameter('ready_endpoints', value=[f'{contract.SETPOINT} publishers>=2',
                                            f'{contract.ZONE_STATE} subscribers>=1']),
        Parameter('start_delay_s', value=0.3)]))
    mpc = rig.add(rclpy.create_node('mpc', context=context))
    hostile = rig.add(rclpy.create_node('hostile', context=context))
    answer = mpc.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)
    attack = hostile.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)
    mpc.create_subscription(ZoneState, contract.ZONE_STATE, lambda m: answer.publish(
        setpoint_msg(m.header.stamp.sec * NS_PER_S + m.header.stamp.nanosec, 3600.0,
                     {'q': 750.0})), contract.DATA_QOS)

    def on_clock(msg):
        now = msg.clock.sec * NS_PER_S + msg.clock.nanosec
        if (now - EPOCH_NS) % STEP_NS:
            attack.publish(setpoint_msg(now, 3600.0, {'q': -1500.0}, zone='hostile'))
    hostile.create_subscription(type(clock_msg(0)), contract.CLOCK, on_clock,
                                contract.CLOCK_QOS)
    spin_until(rig, lambda: emulator.done, 'the end of the run')
    assert not emulator.failed
    assert emulator.applied_sources == ['setpoint'] * hours
    assert emulator.applied_frame()['q'].tolist() == [750.0] * hours
    assert emulator.rejections.counter.by_kind().get('grid', 0) >= hours


def test_a_rejected_setpoint_moves_no_stamp_in_lockstep(context, rig):
    """
    Attack 1, second half: a setpoint with a junk schedule, then the valid one of that step.

    Checked whole, the junk one records no stamp: the valid one that follows is applied (on
    today's code it was taken for a repeat and the step waited for ever).
    """
    hours = 3
    emulator = rig.add(EmulatorNode(context=context, parameter_overrides=[
        Parameter('hours', value=hours), Parameter('model', value='python'),
        Parameter('ready_endpoints', value=[f'{contract.SETPOINT} publishers>=1']),
        Parameter('heartbeat_period_s', value=0.2), Parameter('lockstep_timeout_s', value=20.0)]))
    mpc = rig.add(rclpy.create_node('mpc', context=context))
    answer = mpc.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)

    def on_state(msg):
        stamp = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        junk = setpoint_msg(stamp, 3600.0, {'q': 100.0})
        junk.schedule_offsets_s, junk.schedule_values = [0.0, 600.0], [100.0, math.nan]
        answer.publish(junk)
        answer.publish(setpoint_msg(stamp, 3600.0, {'q': 250.0}))
    mpc.create_subscription(ZoneState, contract.ZONE_STATE, on_state, contract.DATA_QOS)
    spin_until(rig, lambda: emulator.done, 'the end of the run')
    assert not emulator.failed, emulator.failed
    assert emulator.applied_sources == ['setpoint'] * hours
    assert emulator.applied_frame()['q'].tolist() == [250.0] * hours
    assert emulator.rejections.counter.by_kind() == {'non_finite': hours}


def _latest_statuses(node):
    latest = {}
    node.create_subscription(DiagnosticArray, '/diagnostics',
                             lambda m: latest.update({s.name: s for s in m.status}), 50)
    return latest


def test_mpc_plans_from_the_real_state_reports_intruders_and_stale_peers(context, rig):
    """
    Attacks 2, 3 and 7 and the graph watch against a real MPC node.

    A writer 'emulator' sends clock and states, a writer 'forecaster' forecasts; a writer
    'hostile' sends, mid-step, a state stamped at the next step + 1 s with junk fields and one
    on the grid with a 10^6-sample warm-up history. The next step is planned from the real
    state; /diagnostics names the intruder (node and GID) on the state stream; once the peers
    fall silent, state and clock are STALE, each in an entry of its own.
    """
    scenario = synthetic_scenario(hours=12)
    mpc = rig.add(MpcNode(context=context, parameter_overrides=[
        Parameter('model', value='python'), Parameter('horizon_steps', value=3),
        Parameter('use_sim_time', value=True), Parameter('peer_timeout_s', value=1.0)]))
    emulator = rig.add(rclpy.create_node('emulator', context=context))
    forecaster = rig.add(rclpy.create_node('forecaster', context=context))
    hostile = rig.add(rclpy.create_node('hostile', context=context))
    clock = emulator.create_publisher(type(clock_msg(0)), contract.CLOCK, contract.CLOCK_QOS)
    state = emulator.create_publisher(ZoneState, contract.ZONE_STATE, contract.DATA_QOS)
    forecast = forecaster.create_publisher(Forecast, contract.FORECAST, contract.LATCHED_QOS)
    attack = hostile.create_publisher(ZoneState, contract.ZONE_STATE, contract.DATA_QOS)
    statuses = {}
    listener = rig.add(rclpy.create_node('listener', context=context))
    listener.create_subscription(MpcStatus, contract.STATUS, lambda m: statuses.update(
        {m.header.stamp.sec * NS_PER_S + m.header.stamp.nanosec: m}), contract.DATA_QOS)
    latest = _latest_statuses(listener)
    spin_until(rig, lambda: mpc.is_active and mpc.count_subscribers(contract.CLOCK) >= 2
               and state.get_subscription_count() >= 1, 'the MPC')
    t2, t3 = EPOCH_NS + 2 * STEP_NS, EPOCH_NS + 3 * STEP_NS

    def step(k, now_ns, temperature_c):
        clock.publish(clock_msg(now_ns))
        forecast.publish(forecast_msg(EPOCH_NS + k * STEP_NS, 3600.0,
                                      forecast_window(scenario, k, 3)))
        state.publish(zone_state_msg(EPOCH_NS + k * STEP_NS, {'T': temperature_c + KELVIN},
                                     {'T': temperature_c}))
        spin_until(rig, lambda: EPOCH_NS + k * STEP_NS in statuses, f'the status of step {k}')

    step(2, t2, 20.0)
    clock.publish(clock_msg(t2 + 1800 * NS_PER_S))  # mid-step: the clock runs
    spin_for(rig, 0.2)
    future = zone_state_msg(t3 + NS_PER_S, {'T': 21.0 + KELVIN}, {'T': 1e300, 'Qr': 0.0},
                            {'q': 9.9e6}, 'hostile')
    future.history_offsets_s, future.history_state_values = [-60.0, 0.0], [1.0]
    huge = zone_state_msg(t3, {'T': 22.0 + KELVIN}, {'T': 22.0}, {'q': 0.0}, 'hostile')
    huge.history_offsets_s = np.linspace(-1e6, 0.0, HUGE)
    huge.history_state_values = np.full(HUGE, 293.0)
    for msg in (future, huge):
        attack.publish(msg)
    spin_until(rig, lambda: mpc.rejections.total('state') >= 2, 'the rejections')
    assert mpc.rejections.counter.by_kind('state') == {'out_of_range': 1, 'length': 1}
    step(3, t3, 19.5)
    planned = statuses[t3]
    assert list(planned.state_names) == ['T'] and not planned.fallback
    assert planned.state_values[0] == pytest.approx(19.5 + KELVIN, abs=1e-9)

    # The intruder on /zone/state, by node and GID, while it is in the graph.
    spin_until(rig, lambda: 'mshoot/mpc/peer/state' in latest
               and latest['mshoot/mpc/peer/state'].level == bytes([2]), 'the intruder report')
    report = latest['mshoot/mpc/peer/state']
    gid = status_values(report)['intruder /hostile']
    assert re.fullmatch(r'[0-9a-f]{2}(\.[0-9a-f]{2}){7,}', gid), gid
    assert f'/hostile (gid {gid})' in report.message and 'expected only emulator' in \
        report.message
    assert latest['mshoot/mpc/peer/forecast'].level != bytes([2])  # no intruder there

    # Attack 7: the peers fall silent (the intruder leaves): each is STALE, by name.
    rig.remove_node(hostile)
    rig.nodes_made.remove(hostile)
    hostile.destroy_node()
    silent = time.monotonic()
    spin_until(rig, lambda: all(
        name in latest and latest[name].level == bytes([3])
        for name in ('mshoot/mpc/peer/state', 'mshoot/mpc/peer/clock',
                     'mshoot/mpc/peer/forecast')) and time.monotonic() - silent > 1.0,
               'the STALE reports')
    assert 'nothing heard on /zone/state for' in latest['mshoot/mpc/peer/state'].message
    assert latest['mshoot/mpc'].name == 'mshoot/mpc'  # the node's own entry stays first


# -- the flood over DDS, short ------------------------------------------------------------
@pytest.mark.ros
@pytest.mark.host_discovery
def test_a_short_hostile_flood_against_the_three_executables(tmp_path):
    """
    ``bench/hostile.py`` for a few seconds: separate processes, DDS on this host, lockstep.

    Every step applies the MPC's setpoint (the emulator's count; and every step observed
    applied the value the MPC sent), none is planned from an injected state, the MPC publishes
    no invalid setpoint, every node survives and the intruder is reported, by node and GID.
    """
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    done = subprocess.run([sys.executable, str(ROOT / 'bench' / 'hostile.py'), '--seconds', '4',
                           '--settle', '3', '--mode', 'lockstep', '--rate', '500',
                           '--max-growth-mb', '1000', '--out', str(tmp_path)],
                          env=env, capture_output=True, text=True, timeout=300)
    logs = '\n'.join(p.read_text()[-1500:] for p in tmp_path.glob('*.log'))
    assert (tmp_path / 'hostile.json').is_file(), f'{done.stdout}\n{done.stderr}\n{logs}'
    report = json.loads((tmp_path / 'hostile.json').read_text())
    assert report['sent_total'] > 100, report
    assert report['steps'] >= 3 and report['applied_sources'] == {
        'setpoint': report['steps'], 'held': 0, 'safe': 0}, report
    assert report['applied_mpc_setpoint'] >= 1 and report['applied_other'] == 0, report
    assert report['planned_from_injected_state'] == 0 and report['invalid_setpoints'] == 0
    assert all(report['nodes_alive_at_flood_end'].values())
    assert all(report['nodes_alive_after_settling'].values())
    assert re.search(r'/hostile \(gid [0-9a-f.]+\)', report['intruders_reported'].get(
        'mshoot/emulator/peer/setpoint', '')), report['intruders_reported']
    assert 'rejected_states' in report['mpc_rejections']
    assert int(report['mpc_rejections']['rejected_states']) > 0
