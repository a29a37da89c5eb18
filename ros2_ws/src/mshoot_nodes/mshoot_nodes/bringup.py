"""
Bring-up in one process: emulator, forecaster, MPC and the bag recorder in one executor.

    bringup --scenario synthetic --hours 72 --out out/demo        # the demo (make demo)
    bringup --scenario ou44 --data ../shared/data/ou44/measurements.csv

The fast path: the four nodes share one rclpy context and one executor, rclpy's
``EventsExecutor`` (:func:`in_process_executor`); the emulator runs in lockstep, so simulated
time goes as fast as the MPC solves and the run equals the core-only loop. With
``--discovery OFF`` (the default) no other process can reach the nodes, so they start
without rclpy's services (parameters, type descriptions, lifecycle transitions). Writes to
``--out``: ``bag/`` (rosbag2, mcap by default), ``kpis.json`` (the keys of
``mshoot case``), ``steps.csv``, ``trajectories.csv`` and
``plot.png``; prints progress and the KPIs. Parameters come from the YAML
files in the package's ``config/`` (or ``--params-file``), then the flags.

Exit codes: 0 done; 1 the run failed or stopped; 2 bad configuration; 3 the run ended but
more than ``max_fallback_share`` of its steps fell back (a WARNING line says how many).
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import pathlib
import sys
import time
from typing import Any, Callable, Sequence

from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.controller import controller_for
from mshoot_core.kpis import FALLBACK_EXIT, fallback_problem
from mshoot_core.scenario import PUBLISHED
import rclpy
from rclpy.context import Context
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import Executor
from rclpy.experimental import EventsExecutor
from rclpy.lifecycle import LifecycleNode
from rclpy.logging import LoggingSeverity
from rclpy.parameter import Parameter

from mshoot_nodes import contract, sources
from mshoot_nodes.config import add_model_options, default_params_files, ros_args
from mshoot_nodes.conversions import mpc_records_frame
from mshoot_nodes.emulator_node import build_emulator, EmulatorNode
from mshoot_nodes.forecaster_node import ForecasterNode
from mshoot_nodes.logbridge import bridge_core_logging
from mshoot_nodes.mpc_node import MpcNode, settings_from
from mshoot_nodes.readiness import run_requirements
from mshoot_nodes.recorder_node import RecorderNode
from mshoot_nodes.results import kpi_summary, run_outputs
from mshoot_nodes.signals import StopSignals
from mshoot_nodes.sources import build_model
from mshoot_nodes.startup import EXIT_CONFIG, startup_reason, StartupError

NODE_NAMES = ('emulator', 'forecaster', 'mpc', 'recorder')


def overrides(values: dict[str, Any]) -> list[Parameter]:
    """Parameter overrides from a dict, skipping None (= keep the YAML/default value)."""
    return [Parameter(name, value=value) for name, value in values.items() if value is not None]


def in_process_executor(context: Context) -> Executor:
    """
    Return the executor of an in-process run: rclpy's ``EventsExecutor`` (experimental in Jazzy).

    It dispatches in C++ from a queue of middleware events, in the order they came: no wait set
    rebuilt from every entity of every node at each wake-up, no Python task per callback (the
    ``SingleThreadedExecutor`` spent about as much time dispatching as the nodes spent in their
    callbacks, ``bench/rosloop.py``). What it does not support, the nodes do not use: guard
    conditions (the MPC node polls after a solve through ``executor.create_task``) and
    subscription callbacks taking the ``MessageInfo`` (the recorder, built with
    ``message_info=False``, stamps with its clock at the callback: in the order of arrival).
    """
    return EventsExecutor(context=context)


def private_node_options(cls: type) -> dict[str, Any]:
    """
    Return the constructor options of a node that no other process can reach.

    No parameter services, no lifecycle services (nothing could call them; the nodes
    autostart) and, with the parameter override of :func:`private_overrides`, no type
    description service.
    """
    options: dict[str, Any] = {'start_parameter_services': False}
    if issubclass(cls, LifecycleNode):
        options['enable_communication_interface'] = False
    return options


def private_overrides() -> list[Parameter]:
    """Return the parameter overrides of a node that no other process can reach."""
    return [Parameter('start_type_description_service', value=False)]


@dataclasses.dataclass
class RosRun:
    """The nodes of an in-process run, after it ended."""

    emulator: EmulatorNode
    forecaster: ForecasterNode
    mpc: MpcNode
    recorder: RecorderNode | None
    wall_s: float
    cpu_s: float = 0.0


def run_in_process(context: Context, node_params: dict[str, dict[str, Any]], *,
                   record: bool = True, services: bool = False, timeout_s: float = 600.0,
                   progress: Callable[[EmulatorNode], None] | None = None,
                   stop: Callable[[], bool] | None = None) -> RosRun:
    """
    Run the closed loop over ROS in one executor until the emulator's scenario ends.

    Parameters
    ----------
    context : Context
        An initialised rclpy context (its arguments may carry ``--params-file``).
    node_params : dict
        Node name ('emulator', 'forecaster', 'mpc', 'recorder') -> parameter
        overrides (None values are skipped).
    record : bool
        Also run the bag recorder.
    services : bool
        Give the nodes rclpy's services (parameters, lifecycle, type descriptions), for
        runs that other processes can discover; without them (the default) the nodes
        have fewer entities (nothing could call them).
    timeout_s : float
        Wall-clock guard [s]: TimeoutError when the run takes longer.
    progress : callable, optional
        Called with the emulator node after every executor turn that advanced it.
    stop : callable, optional
        Polled between executor turns; True ends the run early with
        InterruptedError (e.g. on SIGTERM: the nodes are still destroyed, the bag
        closed with everything received).

    The emulator starts once the graph shows the MPC, the forecaster and (with
    ``record``) the recorder's ``/recorder/ready``: the same readiness check as
    the other bring-ups (:func:`mshoot_nodes.readiness.run_requirements`), unless
    ``node_params['emulator']`` sets ``ready_endpoints``. In lockstep the MPC solves in the
    executor's thread (``async_solve`` false) unless ``node_params['mpc']`` says otherwise:
    nothing else is due while it solves.

    The nodes are destroyed before returning (the recorder's bag is closed);
    their records stay readable.

    Raises
    ------
    StartupError
        A node could not be built from its parameters (a bad value, model file
        or scenario): one line naming the node and the reason.

    """
    nodes: list[Any] = []
    node_params = {name: dict(values) for name, values in node_params.items()}
    node_params.setdefault('emulator', {}).setdefault(
        'ready_endpoints', run_requirements('mshoot' if record else 'none'))

    def make(cls: type, name: str, **options: Any) -> Any:
        options.update({} if services else private_node_options(cls))
        extra = [] if services else private_overrides()
        try:
            node = cls(context=context,
                       parameter_overrides=extra + overrides(node_params.get(name, {})),
                       **options)
        except Exception as exc:  # noqa: BLE001 - whatever fails at start-up: one clear line
            raise StartupError(f'{name}: cannot start: {startup_reason(exc)}') from exc
        nodes.append(node)  # destroyed below even if a later node fails to start
        executor.add_node(node)
        return node

    executor = in_process_executor(context)
    try:
        recorder = make(RecorderNode, 'recorder', message_info=False) if record else None
        forecaster = make(ForecasterNode, 'forecaster')
        emulator = make(EmulatorNode, 'emulator')
        # Lockstep: nothing is due while the MPC solves (the emulator waits for its setpoint),
        # so the solve runs in the executor's thread, without a hand-over to a solver thread.
        node_params.setdefault('mpc', {}).setdefault(
            'async_solve', emulator.params['mode'] != 'lockstep')
        mpc = make(MpcNode, 'mpc')
        problem = mismatch(emulator, mpc)
        if problem:
            raise StartupError(problem)
        started, cpu_started = time.perf_counter(), time.process_time()
        steps_seen = 0
        while not emulator.done:
            executor.spin_once(timeout_sec=0.1)
            if progress is not None and emulator.steps_done != steps_seen:
                steps_seen = emulator.steps_done
                progress(emulator)
            if time.perf_counter() - started > timeout_s:
                raise TimeoutError(f'the ROS run did not finish within {timeout_s:.0f} s '
                                   f'({emulator.steps_done} steps done)')
            if stop is not None and stop():
                if recorder is not None:
                    recorder.drain(executor)
                raise InterruptedError(f'stopped after {emulator.steps_done} steps')
        wall_s, cpu_s = time.perf_counter() - started, time.process_time() - cpu_started
        # Let the last messages reach the recorder (bounded: 2 s).
        drained = time.perf_counter()
        while recorder is not None and time.perf_counter() - drained < 2.0 and (
                recorder.counts.get(recorder.resolve_topic_name(contract.STATUS), 0)
                < len(mpc.history)
                or recorder.counts.get(recorder.resolve_topic_name(contract.ZONE_STATE), 0)
                < emulator.steps_done + 1):
            executor.spin_once(timeout_sec=0.01)
        for _ in range(10):
            executor.spin_once(timeout_sec=0.0)
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
    return RosRun(emulator, forecaster, mpc, recorder, wall_s, cpu_s)


def mismatch(emulator: EmulatorNode, mpc: MpcNode) -> str | None:
    """
    Say why the MPC's model cannot control the emulated building, or return None.

    Other states or controls: every state and setpoint would be rejected. None also before a
    configure.
    """
    if emulator.emulator is None or mpc.controller is None:
        return None
    building = (tuple(emulator.emulator.model.state_names), emulator.emulator.control_names)
    interface = mpc.controller.interface
    control = (interface.state_names, interface.control_names)
    if sorted(building[0]) == sorted(control[0]) and sorted(building[1]) == sorted(control[1]):
        return None
    return (f"the MPC's model {mpc.params['model']!r} (states {list(control[0])}, controls "
            f"{list(control[1])}) does not match the emulator's {emulator.params['model']!r} "
            f'(states {list(building[0])}, controls {list(building[1])})')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='bringup', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--scenario', default=None,
                        help="'synthetic' (default, built in), 'ou44' or an OU44-format CSV")
    parser.add_argument('--data', default=None, help="OU44 measurements.csv for 'ou44'")
    parser.add_argument('--hours', type=int, default=None, help='control steps (default 72)')
    parser.add_argument('--horizon', type=int, default=None, help='MPC horizon [steps]')
    add_model_options(parser)
    parser.add_argument('--cost', choices=('quadratic', 'energy'), default=None)
    parser.add_argument('--comfort', choices=('hard', 'soft'), default=None)
    parser.add_argument('--solver', default=None, help='slsqp, trust-constr or ipopt')
    parser.add_argument('--mode', choices=('lockstep', 'free'), default=None,
                        help='emulator mode (default lockstep)')
    parser.add_argument('--speedup', type=float, default=None,
                        help='free mode: simulated seconds per wall second')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default=None,
                        help='bag storage (default mcap)')
    parser.add_argument('--no-bag', action='store_true', help='do not record a bag')
    parser.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/demo'),
                        help='output folder (default out/demo)')
    parser.add_argument('--params-file', type=pathlib.Path, action='append', default=None,
                        help='YAML parameter file (repeatable; default: the config/ files)')
    parser.add_argument('--timeout', type=float, default=900.0,
                        help='wall-clock limit of the run [s] (default 900)')
    parser.add_argument('--progress-every', type=int, default=12,
                        help='print a progress line every so many steps (0: never)')
    parser.add_argument('--compare-core', action='store_true',
                        help='also run the core-only loop and report the ROS overhead')
    parser.add_argument('--discovery', choices=('OFF', 'LOCALHOST', 'SUBNET'), default='OFF',
                        help='ROS_AUTOMATIC_DISCOVERY_RANGE of this process (default OFF: '
                             'isolated from other processes)')
    parser.add_argument('-v', '--verbose', action='store_true', help='node logs at INFO')
    return parser


def node_params_from_args(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """Per-node parameter overrides from the command-line flags."""
    out = args.out
    scenario = {'scenario': args.scenario, 'data': args.data, 'hours': args.hours}
    return {
        'emulator': {**scenario, 'model': args.emulator_model, 'mode': args.mode,
                     'speedup': args.speedup},
        'forecaster': {**scenario, 'horizon_steps': args.horizon,
                       'series': sources.card_series(args.control_model)},
        'mpc': {'horizon_steps': args.horizon, 'model': args.control_model, 'cost': args.cost,
                'comfort': args.comfort, 'solver': args.solver},
        'recorder': {'bag_path': str(out / 'bag'), 'overwrite': True, 'storage': args.storage},
    }


@dataclasses.dataclass
class CoreRun:
    """The core-only loop run beside a ROS run: its times and how far its states are."""

    wall_s: float
    cpu_s: float
    max_abs_diff_k: float


def core_only(emulator: EmulatorNode, mpc: MpcNode) -> CoreRun:
    """
    Run the core-only loop with the same parameters as a ROS run's nodes.

    Return its wall and CPU time [s] (the loop, as :attr:`RosRun.wall_s`) and the max
    |x_ros - x_core| over every state of every step [K]. The models are built afresh, the
    scenario is the emulator node's own.
    """
    core_emulator = build_emulator(emulator.params)
    controller = controller_for(build_model(mpc.params['model'], mpc.params['fmu_tolerance']),
                                settings_from(mpc.params))
    cpu_started = time.process_time()
    result = run_closed_loop(controller, core_emulator, steps=len(emulator.records),
                             log_every=0)
    cpu_s = time.process_time() - cpu_started
    columns = [f'{name}_end' for name in core_emulator.model.state_names]
    ros_x = emulator.applied_frame()[columns].to_numpy()
    core_x = result.steps[columns].to_numpy()
    return CoreRun(result.wall_s, cpu_s, float(abs(ros_x - core_x).max()))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = args.discovery
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    params_files = args.params_file or default_params_files(args.scenario)
    missing = [str(path) for path in params_files if not pathlib.Path(path).is_file()]
    if missing:
        print(f'[demo] error: parameter file(s) {missing} not found', file=sys.stderr)
        return EXIT_CONFIG
    context = Context()
    try:
        rclpy.init(args=ros_args(params_files), context=context)
    except Exception as exc:  # noqa: BLE001 - e.g. a YAML file rcl cannot parse
        print(f'[demo] error: {startup_reason(exc)}', file=sys.stderr)
        return EXIT_CONFIG
    if not args.verbose:
        for name in NODE_NAMES:
            rclpy.logging.set_logger_level(name, LoggingSeverity.WARN)
    bridge_core_logging(rclpy.logging.get_logger('mshoot_core'))
    started = time.perf_counter()

    def progress(emulator: EmulatorNode) -> None:
        done = len(emulator.records)
        total = done + emulator.emulator.steps_left
        if args.progress_every and (done % args.progress_every == 0 or done == total):
            record = emulator.records[-1]
            temperatures = ', '.join(
                f'{name} = {value:6.2f} degC' for name, value in zip(
                    emulator.interface.temperature_names,
                    emulator.interface.temperatures_c(record.x_end)))
            controls = ', '.join(f'{name} = {value:+8.1f} W' for name, value in zip(
                emulator.emulator.control_names, record.controls))
            print(f'[demo] step {done:3d}/{total} (t = {record.t_start_s / 3600 + 1:5.1f} h): '
                  f'{temperatures}, {controls}, wall {time.perf_counter() - started:6.2f} s',
                  flush=True)

    try:
        with StopSignals() as signals:  # SIGINT/SIGTERM: stop cleanly, the bag is closed
            run = run_in_process(context, node_params_from_args(args), record=not args.no_bag,
                                 services=args.discovery != 'OFF', timeout_s=args.timeout,
                                 progress=progress, stop=lambda: signals.requested)
    except StartupError as exc:  # the configuration: nothing ran
        print(f'[demo] error: {exc}', file=sys.stderr)
        rclpy.try_shutdown(context=context)
        return EXIT_CONFIG
    except (InvalidParameterValueException, ValueError, FileNotFoundError) as exc:
        print(f'[demo] error: the run failed: {startup_reason(exc)}', file=sys.stderr)
        rclpy.try_shutdown(context=context)
        return 1
    except (TimeoutError, KeyboardInterrupt, InterruptedError) as exc:
        why = f'{signals.received}: ' if signals.received else ''
        print(f'[demo] stopped: {why}{exc or "interrupted"}', file=sys.stderr)
        rclpy.try_shutdown(context=context)
        return 1
    rclpy.try_shutdown(context=context)
    if run.emulator.failed:
        print(f'[demo] error: the run stopped early: {run.emulator.failed}', file=sys.stderr)
        return 1

    emulator, mpc = run.emulator, run.mpc
    p_emu, p_mpc = emulator.params, mpc.params
    records = mpc_records_frame([s for s, _ in mpc.history], [s for _, s in mpc.history],
                                emulator.epoch_ns)
    extra: dict[str, Any] = {
        'scenario': p_emu['scenario'], 'control': p_mpc['model'], 'emulator': p_emu['model'],
        'tolerance': p_mpc['fmu_tolerance'],
        'horizon_h': p_mpc['horizon_steps'] * p_mpc['step_s'] / 3600.0, 'cost': p_mpc['cost'],
        'solver': p_mpc['solver'], 'comfort': p_mpc['comfort'], 'setup_s': 0.0,
        'transport': 'ros2 in-process', 'mode': p_emu['mode']}
    hours = len(emulator.records)
    if p_emu['scenario'] == 'ou44' and hours == 72 and p_mpc['horizon_steps'] in PUBLISHED:
        extra['published'] = PUBLISHED[p_mpc['horizon_steps']]
    if run.recorder is not None:
        extra['bag'] = str(run.recorder.path)
        extra['bag_messages'] = dict(run.recorder.counts)
    if args.compare_core:
        core = core_only(emulator, mpc)
        extra.update(core_wall_s=core.wall_s, ros_overhead_s=run.wall_s - core.wall_s,
                     ros_over_core=run.wall_s / core.wall_s,
                     max_abs_diff_vs_core_k=core.max_abs_diff_k)
    title = (f"{p_emu['scenario']} over ROS 2: H = {p_mpc['horizon_steps']} steps, control "
             f"{p_mpc['model']}, emulator {p_emu['model']}, {p_mpc['cost']} cost")
    kpis = run_outputs(args.out, emulator.applied_frame(), emulator.fine_frame(), records,
                       p_emu['step_s'], run.wall_s, title,
                       controls=emulator.emulator.control_names,
                       zones=emulator.zone_temperature_columns(), **extra)
    print(f'[demo] {kpi_summary(kpis)}')
    if args.compare_core:
        print(f"[demo] core-only loop: {kpis['core_wall_s']:.2f} s wall; ROS overhead "
              f"{kpis['ros_overhead_s']:+.2f} s ({kpis['ros_over_core']:.2f}x); "
              'max |x_ros - x_core| = '
              f"{kpis['max_abs_diff_vs_core_k']:.2e} K")
    print(f'[demo] wrote {args.out}/: kpis.json, steps.csv, trajectories.csv, plot.png'
          + (', bag/' if run.recorder is not None else ''))
    too_few = fallback_problem(kpis.get('fallbacks', 0), kpis['steps'],
                               p_mpc['max_fallback_share'])
    if too_few:
        print(f'[demo] WARNING: {too_few}; exit code {FALLBACK_EXIT}', file=sys.stderr)
        return FALLBACK_EXIT
    return 0


if __name__ == '__main__':
    sys.exit(main())
