"""
Separate processes over DDS on this host.

The four-process bring-up completes a 24 h run with every setpoint in the bag; a node executable
started alone is a lifecycle node (its ``~/get_state`` and ``~/change_state`` services) reporting
on ``/diagnostics``; the start gate ends a run without peers with an error naming the missing
endpoints.
"""
import json
import os
import pathlib
import subprocess
import time

from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.emulation import Emulator
from mshoot_core.models.fmi import r1c1_fmi_model
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.scenario import synthetic_scenario
from mshoot_core.units import KELVIN
from mshoot_nodes import contract
from mshoot_nodes.bags import read_bag
from mshoot_nodes.diagnostics import status_values
from mshoot_nodes.processes import executable
import numpy as np
import pandas as pd
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor

HOURS = 24
pytestmark = pytest.mark.host_discovery


@pytest.mark.ros
def test_separate_processes_complete_a_24_h_run(tmp_path):
    out = tmp_path / 'processes'
    command = executable('bringup_processes', 'processes')
    assert pathlib.Path(command[0]).name == 'bringup_processes', \
        'the console script is not installed (make setup)'
    done = subprocess.run(command + ['--hours', str(HOURS), '--out', str(out),
                                     '--timeout', '120'],
                          capture_output=True, text=True, timeout=180)
    logs = '\n'.join(f'--- {p.name}\n{p.read_text()[-2000:]}'
                     for p in sorted((out / 'logs').glob('*.log')))
    assert done.returncode == 0, f'{done.stdout}\n{done.stderr}\n{logs}'
    kpis = json.loads((out / 'kpis.json').read_text())
    assert kpis['steps'] == HOURS and kpis['solver_failures'] == 0
    assert kpis['transport'] == 'ros2 processes'
    steps = pd.read_csv(out / 'steps.csv', index_col='time_s')
    bad = steps[~steps['success'].astype(bool) | steps['fallback'].astype(bool)]
    assert bad.empty, f'steps without a successful solve:\n{bad.to_string()}\n{logs}'

    core = run_closed_loop(MPC(R1C1Model(), horizon_steps=10),
                           Emulator(r1c1_fmi_model(fmi_type='ModelExchange', tolerance=1e-10),
                                    synthetic_scenario(hours=HOURS + 1), [20.0 + KELVIN]),
                           steps=HOURS, log_every=0)
    # Lockstep across processes reproduces the core-only loop too.
    assert np.max(np.abs(steps['T_end'].to_numpy() - core.steps['T_end'].to_numpy())) < 1e-9

    # The start gate waited for the recorder's /recorder/ready: every setpoint is in the bag.
    bag = read_bag(out / 'bag')
    counts = bag.counts
    assert counts[contract.SETPOINT] >= HOURS and counts[contract.STATUS] >= HOURS
    assert counts[contract.ZONE_STATE] >= HOURS + 1
    recorded = {m.rawdata for m in bag.messages if m.topic == contract.SETPOINT}
    assert len(recorded) == HOURS, 'a setpoint is missing from the bag'
    assert (out / 'plot.png').stat().st_size > 0


@pytest.fixture
def graph(monkeypatch):
    """Yield a private domain over DDS on this host: (environment for processes, context)."""
    domain = 120 + (os.getpid() + 11) % 90
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    yield env, context
    rclpy.try_shutdown(context=context)


def _call(executor, client, request, timeout_s=30.0, resend_s=None):
    """
    Call a service and spin until its answer (or fail after ``timeout_s``).

    ``resend_s``: for an idempotent request (get_state), send it again after that long without
    an answer. ``wait_for_service`` sees the server's request reader only: a response sent
    before the server has discovered this client's response reader is lost (DDS discovery
    race, e.g. ros2/rclpy#1191), which a loaded machine makes likely for a process just started.
    """
    assert client.wait_for_service(timeout_sec=timeout_s), f'{client.srv_name} not offered'
    future = client.call_async(request)
    deadline = time.monotonic() + timeout_s
    sent = time.monotonic()
    while not future.done():
        now = time.monotonic()
        assert now < deadline, f'no answer from {client.srv_name}'
        if resend_s is not None and now - sent > resend_s:
            client.remove_pending_request(future)
            future, sent = client.call_async(request), now
        executor.spin_once(timeout_sec=0.05)
    return future.result()


#: Lifecycle executables started alone: their parameters, what their active status says and a
#: topic they publish once configured ({ns}: the test's namespace). The MPC joins the table
#: once it is a lifecycle node (the same pattern).
ALONE = {
    'emulator': (['model:=python', 'ready_timeout_s:=0.0',
                  "ready_endpoints:=['{ns}/never publishers>=1']"],
                 'waiting for peers: {ns}/never: 0 of 1 publishers', contract.ZONE_STATE),
    'mpc': (['model:=python'], 'waiting for the first step', contract.SETPOINT),
}


@pytest.mark.ros
@pytest.mark.parametrize('exe', sorted(ALONE))
def test_executable_alone_is_a_lifecycle_node_on_diagnostics(exe, graph, tmp_path):
    env, context = graph
    command = executable(exe, f'{exe}_node')
    assert pathlib.Path(command[0]).name == exe, 'not installed: make setup'
    # A namespace of its own (services, status name) and a start gate nothing opens: other
    # processes on this host and domain cannot be mistaken for it, nor start it.
    namespace = f'/test_{os.getpid()}'
    params, message, topic = ALONE[exe]
    command += ['--ros-args', '-r', f'__ns:={namespace}', '-p', 'autostart:=false']
    for param in params:
        command += ['-p', param.format(ns=namespace)]
    log = open(tmp_path / f'{exe}.log', 'w')  # noqa: SIM115 - closed below
    proc = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
    probe = rclpy.create_node('probe', context=context)
    statuses = []
    probe.create_subscription(DiagnosticArray, '/diagnostics',
                              lambda m: statuses.extend(m.status), 10)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    get_state = probe.create_client(GetState, f'{namespace}/{exe}/get_state')
    change_state = probe.create_client(ChangeState, f'{namespace}/{exe}/change_state')
    name = f'mshoot{namespace}/{exe}'

    def latest(state, timeout_s=30.0):
        """Return the node's newest status once it reports ``state`` (seconds: a 1 Hz timer)."""
        deadline = time.monotonic() + timeout_s
        while True:
            mine = [s for s in statuses if s.name == name]
            if mine and status_values(mine[-1]).get('lifecycle_state') == state:
                return mine[-1]
            assert proc.poll() is None, (tmp_path / f'{exe}.log').read_text()
            assert time.monotonic() < deadline, f'no {state!r} status of {name} on /diagnostics'
            executor.spin_once(timeout_sec=0.05)

    try:
        assert _call(executor, get_state, GetState.Request(), resend_s=2.0).current_state.id == \
            State.PRIMARY_STATE_UNCONFIGURED
        latest('unconfigured')
        for transition, state in ((Transition.TRANSITION_CONFIGURE, 'inactive'),
                                  (Transition.TRANSITION_ACTIVATE, 'active')):
            request = ChangeState.Request(transition=Transition(id=transition))
            assert _call(executor, change_state, request).success
        assert _call(executor, get_state, GetState.Request()).current_state.label == 'active'
        status = latest('active')
        assert status.hardware_id and status.level == bytes([0])
        assert status.message == message.format(ns=namespace)
        assert probe.count_publishers(topic) >= 1  # configured: its publishers
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        log.close()
        executor.shutdown()
        probe.destroy_node()


@pytest.mark.ros
def test_emulator_without_peers_stops_naming_the_missing_endpoints(graph, tmp_path):
    env, _ = graph
    prefix = f'/test_{os.getpid()}'  # topics no other process on this host has
    done = subprocess.run(executable('emulator', 'emulator_node') + [
        '--ros-args', '-p', 'model:=python', '-p', 'ready_timeout_s:=1.0', '-p',
        f"ready_endpoints:=['{prefix}/state subscribers>=1', '{prefix}/setpoint publishers>=1']",
        '-p', f'output_dir:={tmp_path}'], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stdout + done.stderr
    text = done.stdout + done.stderr
    assert 'not ready after' in text
    assert f'{prefix}/state: 0 of 1 subscribers' in text
    assert f'{prefix}/setpoint: 0 of 1 publishers' in text
    run = json.loads((tmp_path / 'run.json').read_text())
    assert run['steps'] == 0 and 'not ready' in run['failed']


def _run_processes(out: pathlib.Path, *options: str) -> dict:
    command = executable('bringup_processes', 'processes')
    done = subprocess.run(command + ['--hours', '12', '--out', str(out), '--timeout', '120',
                                     *options], capture_output=True, text=True, timeout=180)
    logs = '\n'.join(f'--- {p.name}\n{p.read_text()[-2000:]}'
                     for p in sorted((out / 'logs').glob('*.log')))
    assert done.returncode == 0, f'{done.stdout}\n{done.stderr}\n{logs}'
    return json.loads((out / 'kpis.json').read_text())


@pytest.mark.ros
def test_fmu_with_other_names_runs_over_dds_from_its_card_alone(tmp_path):
    """
    An R1C1 FMU with names of its own, described by a card: the KPIs of the built-in FMU.

    State cair.T, no dpos; as the MPC's control model and as the emulated building, each its own
    process over DDS.
    """
    from card_fmus import build_test_fmu
    from test_cards import write_card, ZONE_CARD
    card = write_card(tmp_path / 'card', 'zone.yaml', ZONE_CARD, build_test_fmu('zone'))
    builtin = _run_processes(tmp_path / 'builtin', '--control-model', 'fmu',
                             '--emulator-model', 'fmu')
    carded = _run_processes(tmp_path / 'card_run', '--control-model', str(card),
                            '--emulator-model', str(card))
    assert carded['steps'] == builtin['steps'] == 12 and carded['fallbacks'] == 0
    for key in ('energy_kwh', 'discomfort_kh', 'discomfort_kh_hourly'):
        assert carded[key] == pytest.approx(builtin[key], rel=1e-6, abs=1e-9), key
