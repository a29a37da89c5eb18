"""
Processes: an MPC killed mid-run and restarted picks up within one step.

Bad configuration ends a node at start-up with a clear line and a non-zero exit code.

The emulator and the forecaster run in this process (lockstep), the MPC as its own
process (``lib/mshoot_nodes/mpc``, what ``ros2 run`` runs), over DDS on this host.
"""
import os
import pathlib
import signal
import subprocess
import time

from mshoot_core.units import NS_PER_S
from mshoot_msgs.msg import MpcStatus
from mshoot_nodes import contract
from mshoot_nodes.conversions import stamp_to_ns
from mshoot_nodes.emulator_node import EmulatorNode
from mshoot_nodes.forecaster_node import ForecasterNode
from mshoot_nodes.processes import executable
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

pytestmark = [pytest.mark.ros, pytest.mark.host_discovery]
EPOCH_NS = 1522886400 * NS_PER_S
HOURS = 6


def _mpc_process(env, log):
    command = executable('mpc', 'mpc_node')
    assert pathlib.Path(command[0]).name == 'mpc', 'not installed: make setup'
    return subprocess.Popen(command + ['--ros-args', '-p', 'use_sim_time:=true', '-p',
                                       'model:=python', '-p', 'horizon_steps:=6'],
                            env=env, stdout=log, stderr=subprocess.STDOUT)


def test_mpc_killed_and_restarted_picks_up_within_one_step(tmp_path, monkeypatch):
    domain = 120 + (os.getpid() + 37) % 90
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    forecaster = ForecasterNode(context=context, parameter_overrides=[
        Parameter('hours', value=HOURS), Parameter('use_sim_time', value=True)])
    emulator = EmulatorNode(context=context, parameter_overrides=[
        Parameter('hours', value=HOURS), Parameter('model', value='python'),
        Parameter('start_delay_s', value=1.0), Parameter('heartbeat_period_s', value=0.2)])
    listener = rclpy.create_node('listener', context=context)
    statuses = []
    listener.create_subscription(MpcStatus, contract.STATUS, statuses.append, contract.DATA_QOS)
    executor = SingleThreadedExecutor(context=context)
    for node in (forecaster, emulator, listener):
        executor.add_node(node)
    logs = [open(tmp_path / f'mpc{k}.log', 'w') for k in range(2)]  # noqa: SIM115
    procs = [_mpc_process(env, logs[0])]

    def spin_until(condition, timeout_s, what):
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                text = '\n'.join(p.read_text()[-2000:] for p in tmp_path.glob('*.log'))
                pytest.fail(f'{what} not within {timeout_s} s\n{text}')
            executor.spin_once(timeout_sec=0.05)

    try:
        spin_until(lambda: len(emulator.records) >= 3, 30.0, '3 steps')
        procs[0].send_signal(signal.SIGKILL)  # a crash: no clean shutdown
        procs[0].wait(timeout=10)
        waiting_at = len(emulator.records)
        pause = time.monotonic() + 0.5
        while time.monotonic() < pause:  # (a killed participant stays in the graph for its
            executor.spin_once(timeout_sec=0.05)  # lease time: nothing to wait for here)
        assert len(emulator.records) == waiting_at  # lockstep: the building waits
        restarted = time.monotonic()
        procs.append(_mpc_process(env, logs[1]))
        spin_until(lambda: emulator.done, 60.0, 'the end of the run')
        picked_up_s = time.monotonic() - restarted
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        for log in logs:
            log.close()
        executor.shutdown()
        for node in (forecaster, emulator, listener):
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert not emulator.failed
    assert emulator.applied_sources == ['setpoint'] * HOURS
    # The new process solved the step the building was waiting at, from the latched
    # forecast and the emulator's heartbeat state, with no fallback (its log says so: the
    # listener here may match its publishers only after that first step).
    lines = [line for line in (tmp_path / 'mpc1.log').read_text().splitlines()
             if '] [mpc]: step ' in line]
    first = lines[0]
    assert f'step {(EPOCH_NS // NS_PER_S) + waiting_at * 3600} s: q = ' in first, first
    assert 'ok in' in first and 'fallback' not in first, first
    assert len(lines) == HOURS - waiting_at
    assert all(s.success and not s.fallback for s in statuses)
    assert {stamp_to_ns(s.header.stamp) for s in statuses} <= {
        EPOCH_NS + k * 3600 * NS_PER_S for k in range(HOURS)}
    assert picked_up_s < 30.0


def test_bad_configuration_exits_non_zero_with_the_reason(tmp_path, r2c2_fmu):
    bad_csv = tmp_path / 'bad.csv'
    bad_csv.write_text('datetime,T,solrad\n2018-04-05 00:00,20,0\n')
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='OFF')
    cases = {  # executable, arguments, what the log line must say
        'typo': ('mpc', ['horizon:=3'], "unknown parameter(s) ['horizon'] for node 'mpc'"),
        'csv': ('emulator', [f'scenario:={bad_csv}'], 'bad.csv: no comfort band; expected '
                "columns ['comfort_min', 'comfort_max']"),
        'fmu': ('mpc', [f'model:={r2c2_fmu}'], "invalid inputs ['solrad', 'Tout'"),
        'safe': ('mpc', ['safe_value:=5000.0'], 'safe_value of q [W] must be within'),
    }
    procs = {}
    for name, (exe, params, _) in cases.items():
        command = executable(exe, f'{exe}_node') + ['--ros-args']
        for item in params:
            command += ['-p', item]
        procs[name] = subprocess.Popen(command, env=env, stdout=subprocess.PIPE,
                                       stderr=subprocess.STDOUT, text=True)
    for name, (_, _, expected) in cases.items():
        output, _ = procs[name].communicate(timeout=60)
        assert procs[name].returncode == 2, f'{name}: {output}'
        assert 'cannot start: ' in output and expected in output, f'{name}: {output}'
        assert 'Traceback' not in output, f'{name}: {output}'


def test_bringups_exit_2_with_one_line_on_a_bad_configuration(tmp_path):
    """
    Bad FMUs, models, parameter files and scenarios: the bring-ups exit 2 with one line.

    A bad FMU, a missing one, models that do not fit together, a bad parameter file, a bad
    scenario: the bring-ups say why in one line and exit 2 (no traceback), as the node executables
    do.
    """
    bad_fmu = tmp_path / 'zone.fmu'
    bad_fmu.write_text('not a zip archive')
    bad_csv = tmp_path / 'bad.csv'
    bad_csv.write_text('datetime,T,solrad\n2018-04-05 00:00,20,0\n')
    bad_yaml = tmp_path / 'bad.yaml'
    bad_yaml.write_text('mpc: [unclosed\n')
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='OFF')
    bringup = executable('bringup', 'bringup')
    common = ['--hours', '2', '--no-bag', '--out', str(tmp_path / 'out')]
    cases = {  # command, what the error line must say
        'bad_fmu': (bringup + common + ['--emulator-model', str(bad_fmu)],
                    f'emulator: cannot start: {bad_fmu} is not an FMU: not a ZIP archive'),
        'missing_fmu': (bringup + common + ['--control-model', str(tmp_path / 'none.fmu')],
                        f"mpc: cannot start: FMU file '{tmp_path / 'none.fmu'}' not found"),
        'mismatch': (bringup + common + ['--control-model', 'r1c1x2', '--emulator-model',
                                         'python'],
                     "the MPC's model 'r1c1x2' (states ['T_0', 'T_1'], controls ['q_0', "
                     "'q_1']) does not match the emulator's 'python' (states ['T'], controls "
                     "['q'])"),
        'params_file': (bringup + common + ['--params-file', str(tmp_path / 'none.yaml')],
                        f"parameter file(s) ['{tmp_path / 'none.yaml'}'] not found"),
        'bad_yaml': (bringup + common + ['--params-file', str(bad_yaml)],
                     "Couldn't parse params file"),
        'processes': (executable('bringup_processes', 'processes')
                      + ['--scenario', str(bad_csv), '--hours', '2', '--out',
                         str(tmp_path / 'processes')],
                      'cannot start: ' + str(bad_csv) + ': no comfort band; expected columns '
                      "['comfort_min', 'comfort_max']"),
    }
    procs = {name: subprocess.Popen(command, env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True)
             for name, (command, _) in cases.items()}
    for name, (_, expected) in cases.items():
        output, errors = procs[name].communicate(timeout=120)
        assert procs[name].returncode == 2, f'{name}: {output}{errors}'
        lines = [line for line in errors.splitlines() if 'error: ' in line]
        assert len(lines) == 1 and expected in lines[0], f'{name}: {output}{errors}'
        assert 'Traceback' not in output + errors, f'{name}: {output}{errors}'
