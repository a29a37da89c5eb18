"""
Bring-up as separate processes: emulator, forecaster, MPC and recorder, one process each.

    bringup_processes --hours 24 --out out/processes

What ``ros2 launch mshoot_nodes closed_loop.launch.py`` does on a ROS 2 install,
without the launch package: every node runs from its installed executable
(``lib/mshoot_nodes/<exe>``, what ``ros2 run`` runs) with the YAML files of
``config/`` and ``-p`` overrides, talking over DDS on this host
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a private ``ROS_DOMAIN_ID``).
All four start at once; the emulator's start gate waits until the ROS graph
shows the MPC, the forecaster and the recorder's ``/recorder/ready`` (published
once the recorder has matched every publisher: no setpoint is missing from the
bag), the same readiness check as the other bring-ups
(:mod:`mshoot_nodes.readiness`); it then runs the scenario in lockstep and
exits; the others then get SIGINT (the recorder closes its bag). The outputs are
rebuilt from the emulator's files and the bag: ``kpis.json``, ``steps.csv``,
``trajectories.csv``, ``plot.png``, ``bag/``, ``emulator/``, ``logs/``.

A node that cannot start (its configuration: exit code 2) ends the run at once
with its one-line reason and exit code 2; a run that fails later exits with 1.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import random
import signal
import subprocess
import sys
import time
from typing import Sequence

from ament_index_python.packages import get_package_prefix, PackageNotFoundError

from mshoot_nodes.config import add_model_options, default_params_files
from mshoot_nodes.readiness import run_requirements
from mshoot_nodes.startup import EXIT_CONFIG

#: Executable and module of every process, in start order (the emulator last).
PROCESSES = (('recorder', 'recorder_node'), ('forecaster', 'forecaster_node'),
             ('mpc', 'mpc_node'), ('emulator', 'emulator_node'))


def executable(name: str, module: str) -> list[str]:
    """Command of a node: the installed console script, else ``python -m``."""
    try:
        path = pathlib.Path(get_package_prefix('mshoot_nodes')) / 'lib' / 'mshoot_nodes' / name
        if path.is_file() and os.access(path, os.X_OK):
            return [str(path)]
    except PackageNotFoundError:
        pass
    return [sys.executable, '-m', f'mshoot_nodes.{module}']


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='bringup_processes', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scenario', default='synthetic',
                        help="'synthetic' (default), 'ou44' or an OU44-format CSV")
    parser.add_argument('--data', default='', help="OU44 measurements.csv for 'ou44'")
    parser.add_argument('--hours', type=int, default=72, help='control steps (default 72)')
    add_model_options(parser)
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    parser.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/processes'))
    parser.add_argument('--timeout', type=float, default=600.0,
                        help='wall-clock limit of the run [s] (default 600)')
    parser.add_argument('--ready-timeout', type=float, default=60.0,
                        help='wall time the emulator waits for the other nodes (and the '
                             "recorder's /recorder/ready) before it gives up [s] (default 60)")
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS_DOMAIN_ID (default: a random one in 1..100)')
    return parser


def _stop(procs: dict[str, subprocess.Popen], grace_s: float = 10.0) -> None:
    """SIGINT every running process (reverse start order), kill what does not stop."""
    for name in reversed(list(procs)):
        if procs[name].poll() is None:
            procs[name].send_signal(signal.SIGINT)
    deadline = time.monotonic() + grace_s
    for proc in procs.values():
        try:
            proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def last_error(log: pathlib.Path) -> str:
    """Return the last ERROR or FATAL line of a node's log ('' when there is none)."""
    lines = log.read_text(errors='replace').splitlines() if log.exists() else []
    errors = [line for line in lines if '[ERROR]' in line or '[FATAL]' in line]
    return errors[-1] if errors else ''


def wait_for_emulator(procs: dict[str, subprocess.Popen],
                      timeout_s: float) -> tuple[str, int] | None:
    """
    Wait until the emulator exits, or another node exits at start-up with a configuration error.

    Return (name, exit code) of the process that ended, None after ``timeout_s``.
    """
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for name, proc in procs.items():
            code = proc.poll()
            if code is not None and (name == 'emulator' or code == EXIT_CONFIG):
                return name, code
        time.sleep(0.1)
    return None


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    out = args.out.resolve()
    logs, emulator_dir, bag = out / 'logs', out / 'emulator', out / 'bag'
    logs.mkdir(parents=True, exist_ok=True)
    domain = args.domain_id if args.domain_id is not None else random.randint(1, 100)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    params_files = default_params_files(args.scenario)
    scenario = [f'scenario:={args.scenario}', f'hours:={args.hours}']
    if args.data:
        scenario.append(f'data:={args.data}')
    overrides = {
        'recorder': [f'bag_path:={bag}', 'overwrite:=true', f'storage:={args.storage}'],
        'forecaster': scenario,
        'mpc': [f'model:={args.control_model}'] if args.control_model else [],
        'emulator': scenario + ([f'model:={args.emulator_model}'] if args.emulator_model
                                else []) + [f'output_dir:={emulator_dir}', 'exit_when_done:=true',
                                            f'ready_endpoints:={run_requirements("mshoot")!r}',
                                            f'ready_timeout_s:={args.ready_timeout}',
                                            # the recorder's is the gate; slack for the others
                                            'start_delay_s:=0.5'],
    }
    print(f'[processes] ROS_DOMAIN_ID={domain}, logs in {logs}', flush=True)
    started = time.perf_counter()
    procs: dict[str, subprocess.Popen] = {}
    try:
        for name, module in PROCESSES:
            command = executable(name, module) + ['--ros-args']
            for path in params_files:
                command += ['--params-file', str(path)]
            for item in overrides[name]:
                command += ['-p', item]
            log = open(logs / f'{name}.log', 'w')  # noqa: SIM115 - closed with the process
            procs[name] = subprocess.Popen(command, env=env, stdout=log,
                                           stderr=subprocess.STDOUT)
            print(f'[processes] started {name} (pid {procs[name].pid})', flush=True)
        ended = wait_for_emulator(procs, args.timeout)
        if ended is None:
            print(f'[processes] error: no result within {args.timeout:.0f} s; see {logs}',
                  file=sys.stderr)
            return 1
        name, code = ended
        if code != 0:
            why = last_error(logs / f'{name}.log')
            if code == EXIT_CONFIG:
                print(f'[processes] error: {name}: cannot start: '
                      f"{why.split('cannot start: ', 1)[-1] or f'see {logs}'}", file=sys.stderr)
                return EXIT_CONFIG
            print(f'[processes] error: the {name} exited with {code}; see {logs}'
                  + (f'\n  {why}' if why else ''), file=sys.stderr)
            return 1
    except KeyboardInterrupt:
        return 130
    finally:
        _stop(procs)
    total_s = time.perf_counter() - started
    failed = {name: p.returncode for name, p in procs.items() if p.returncode not in (0, None)}
    if failed:
        print(f'[processes] warning: exit codes {failed}; see {logs}', file=sys.stderr)

    # Imported only now: the nodes start faster without this process competing for the CPU.
    import pandas as pd

    from mshoot_nodes import contract
    from mshoot_nodes.bags import read_messages
    from mshoot_nodes.conversions import mpc_records_frame
    from mshoot_nodes.results import kpi_summary, run_outputs

    run = json.loads((emulator_dir / 'run.json').read_text())
    applied = pd.read_csv(emulator_dir / 'applied.csv', index_col='time_s')
    fine = pd.read_csv(emulator_dir / 'trajectories.csv', index_col='time_s')
    records = mpc_records_frame(read_messages(bag, contract.SETPOINT),
                                read_messages(bag, contract.STATUS), run['epoch_ns'])
    kpis = run_outputs(out, applied, fine, records, run['step_s'], run['wall_s'],
                       f'{args.scenario} over ROS 2 (separate processes)',
                       controls=run.get('controls', ['q']), zones=run.get('zone_temperatures'),
                       scenario=args.scenario, emulator=run['model'],
                       transport='ros2 processes', total_wall_s=total_s, bag=str(bag))
    print(f'[processes] {kpi_summary(kpis)}')
    print(f'[processes] total {total_s:.1f} s wall including start-up; wrote {out}/')
    return 0


if __name__ == '__main__':
    sys.exit(main())
