"""Bring-up as separate processes: emulator, forecaster, MPC and recorder, one process each.

    bringup_processes --hours 24 --out out/processes

What ``ros2 launch mshoot_nodes closed_loop.launch.py`` does on a ROS 2 install,
without the launch package: every node runs from its installed executable
(``lib/mshoot_nodes/<exe>``, what ``ros2 run`` runs) with the YAML files of
``config/`` and ``-p`` overrides, talking over DDS on this host
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a private ``ROS_DOMAIN_ID``).
The emulator is started once the recorder has matched the publishers of the
other nodes (so that no setpoint is missing from the bag); it waits for its
peers, runs the scenario in lockstep and exits;
the others then get SIGINT (the recorder closes its bag). The outputs are
rebuilt from the emulator's files and the bag: ``kpis.json``, ``steps.csv``,
``trajectories.csv``, ``plot.png``, ``bag/``, ``emulator/``, ``logs/``.
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

from mshoot_nodes.config import default_params_files

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
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    parser.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/processes'))
    parser.add_argument('--timeout', type=float, default=600.0,
                        help='wall-clock limit of the run [s] (default 600)')
    parser.add_argument('--match-timeout', type=float, default=30.0,
                        help='wall time the recorder may take to match the forecaster and '
                             'the MPC before the emulator starts [s] (default 30)')
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


def wait_for_recorder(log: pathlib.Path, recorder: subprocess.Popen,
                       timeout_s: float) -> str | None:
    """Wait until the recorder has matched the forecaster's and the MPC's publishers.

    Reads the recorder's log for its ``matched TOPIC`` lines. Returns None when
    every topic is matched, else the reason it is not (timeout, recorder exited).
    """
    from mshoot_nodes import contract

    topics = (contract.FORECAST, contract.SETPOINT, contract.STATUS)
    needles = {t: contract.RECORDER_MATCHED.format(topic=t) for t in topics}
    deadline = time.monotonic() + timeout_s
    while True:
        text = log.read_text() if log.exists() else ''
        missing = [t for t, needle in needles.items() if needle not in text]
        if not missing:
            return None
        if recorder.poll() is not None:
            return f'the recorder exited with {recorder.returncode}; see {log}'
        if time.monotonic() > deadline:
            return (f'the recorder matched no publisher of {", ".join(missing)} within '
                    f'{timeout_s:.0f} s; see {log}')
        time.sleep(0.05)


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
        'mpc': [],
        'emulator': scenario + [f'output_dir:={emulator_dir}', 'exit_when_done:=true',
                                # the MPC and the recorder, then time for them to match
                                'min_state_subscribers:=2', 'start_delay_s:=1.0'],
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
            if name == 'emulator':
                problem = wait_for_recorder(logs / 'recorder.log', procs['recorder'],
                                             args.match_timeout)
                if problem:
                    print(f'[processes] error: {problem}', file=sys.stderr)
                    return 1
            log = open(logs / f'{name}.log', 'w')  # noqa: SIM115 - closed with the process
            procs[name] = subprocess.Popen(command, env=env, stdout=log,
                                           stderr=subprocess.STDOUT)
            print(f'[processes] started {name} (pid {procs[name].pid})', flush=True)
        try:
            code = procs['emulator'].wait(timeout=args.timeout)
        except subprocess.TimeoutExpired:
            print(f'[processes] error: no result within {args.timeout:.0f} s; see {logs}',
                  file=sys.stderr)
            return 1
        if code != 0:
            print(f'[processes] error: the emulator exited with {code}; see {logs}',
                  file=sys.stderr)
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
                       scenario=args.scenario, emulator=run['model'],
                       transport='ros2 processes', total_wall_s=total_s, bag=str(bag))
    print(f'[processes] {kpi_summary(kpis)}')
    print(f'[processes] total {total_s:.1f} s wall including start-up; wrote {out}/')
    return 0


if __name__ == '__main__':
    sys.exit(main())
