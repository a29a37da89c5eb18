"""
The ROS loop beside the core loop: wall and CPU time, and the ROS overhead per step by phase.

    python bench/rosloop.py [--runs 3] [--hours 72] [--no-phases] [--no-bag]

The demo's run (``make demo DEMO_ARGS=--compare-core``: the synthetic scenario, the FMU
emulator in lockstep, the MPC, the forecaster and the bag recorder in one process,
:func:`mshoot_nodes.bringup.run_in_process`) and the core-only loop with the same
parameters (:func:`mshoot_nodes.bringup.core_only`), interleaved ``--runs`` times: the
loop's wall and CPU time of each (process CPU, every thread: the DDS threads and the
solver thread too), their medians and the ratios ROS / core (issue 26: the ROS loop at
most 1.3x the core loop).

Then one more run of each, instrumented: timers of the calling thread's CPU time wrapped
around the functions of every phase (exclusive time: a phase called inside another is
counted in its own line only), printed per step side by side (CPU time: under load, wall
time goes to whichever phase was running when the process lost its core):

- the core's work, in both loops: the emulation (``Emulator.advance``), the MPC solve
  (``MPC.solve``; with ``--async-solve`` on the MPC node's solver thread), the controller's
  bookkeeping (``Controller.poll`` and its ``offer_*``);
- the ROS loop's own: conversions (message <-> values, :mod:`mshoot_nodes.conversions`),
  message checks (:mod:`mshoot_core.safety`, called by the nodes), publishing
  (serialisation, the DDS write and the in-process delivery), the bag recorder's writes, the
  rest of the node callbacks (every subscription, timer and task callback of the nodes), and
  what is left of the loop: rclpy's executor (``EventsExecutor``, in C++: waiting for the
  middleware's events, taking and deserialising the messages, dispatching), with the
  callbacks per step.

The instrumentation costs time of its own (a few microseconds per wrapped call): the
phases say where the overhead goes, the first table how large it is.
"""
from __future__ import annotations

import argparse
import collections
import functools
import inspect
import os
import pathlib
import statistics
import sys
import tempfile
import threading
import time
from typing import Any

BENCH = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'OFF')

from mshoot_core import closed_loop, controller, emulation, mpc  # noqa: E402
from mshoot_nodes import (bringup, emulator_node, forecaster_node, mpc_node,  # noqa: E402
                          recorder_node)
from mshoot_nodes.config import default_params_files, ros_args  # noqa: E402
import rclpy  # noqa: E402
from rclpy import node, publisher  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.logging import LoggingSeverity  # noqa: E402

#: Wrapped functions: (owner, attribute, phase).
CORE_PHASES = (
    (emulation.Emulator, 'advance', 'emulation (core)'),
    (mpc.MPC, 'solve', 'MPC solve (core)'),
    (controller.Controller, 'poll', 'controller bookkeeping (core)'),
    (controller.Controller, 'offer_named_state', 'controller bookkeeping (core)'),
    (controller.Controller, 'offer_forecast', 'controller bookkeeping (core)'),
    (closed_loop._ScenarioInputs, 'offer', 'controller bookkeeping (core)'),
)
ROS_PHASES = (
    *((emulator_node, name, 'conversions') for name in ('clock_msg', 'disturbances_msg',
                                                        'zone_state_msg', 'field_lengths')),
    *((mpc_node, name, 'conversions') for name in ('decision_setpoint_msg',
                                                   'decision_status_msg', 'forecast_series',
                                                   'field_lengths')),
    (forecaster_node, 'forecast_msg', 'conversions'),
    (bringup, 'mpc_records_frame', 'conversions'),
    *((module, name, 'message checks (core safety)') for module in (emulator_node, mpc_node)
      for name in ('check_lengths', 'check_setpoint', 'check_stamp_fields')),
    (publisher.Publisher, 'publish', 'publish (serialise, DDS write)'),
    (recorder_node.RecorderNode, '_write', 'bag recorder (write)'),
)
CALLBACKS = 'node callbacks (the rest)'
ORDER = ('emulation (core)', 'MPC solve (core)', 'controller bookkeeping (core)',
         'conversions', 'message checks (core safety)', 'publish (serialise, DDS write)',
         'bag recorder (write)', CALLBACKS)


class Phases:
    """Exclusive time per phase and thread, from wrappers installed on functions."""

    def __init__(self) -> None:
        self.seconds: dict[tuple[str, str], float] = collections.defaultdict(float)
        self.calls: collections.Counter = collections.Counter()
        self._local = threading.local()
        self._restore: list[tuple[Any, str, Any]] = []

    def _stack(self) -> list:
        if not hasattr(self._local, 'stack'):
            self._local.stack = []
        return self._local.stack

    def enter(self, phase: str) -> None:
        stack, now = self._stack(), time.thread_time()
        if stack:
            self._add(stack[-1][0], now - stack[-1][1])
        stack.append([phase, now])

    def leave(self) -> None:
        stack, now = self._stack(), time.thread_time()
        phase, since = stack.pop()
        self._add(phase, now - since)
        self.calls[phase] += 1
        if stack:
            stack[-1][1] = now

    def _add(self, phase: str, seconds: float) -> None:
        thread = 'main' if threading.current_thread() is threading.main_thread() else 'worker'
        self.seconds[(thread, phase)] += seconds

    def wrap(self, owner: Any, name: str, phase: str) -> None:
        original = inspect.getattr_static(owner, name)
        function = original.__func__ if isinstance(original, staticmethod) else original
        enter, leave = self.enter, self.leave
        if inspect.iscoroutinefunction(function):
            async def timed(*args: Any, **kwargs: Any) -> Any:
                enter(phase)
                try:
                    return await function(*args, **kwargs)
                finally:
                    leave()
        else:
            def timed(*args: Any, **kwargs: Any) -> Any:
                enter(phase)
                try:
                    return function(*args, **kwargs)
                finally:
                    leave()
        setattr(owner, name, staticmethod(timed) if isinstance(original, staticmethod)
                else timed)
        self._restore.append((owner, name, original))

    def install(self, specs: tuple) -> None:
        for owner, name, phase in specs:
            self.wrap(owner, name, phase)

    def time_callbacks(self) -> None:
        """Time every subscription, timer and task callback of the nodes built from now on."""
        enter, leave = self.enter, self.leave

        def timed(callback: Any) -> Any:
            @functools.wraps(callback)  # the same signature: rclpy inspects it
            def timed_callback(*args: Any, **kwargs: Any) -> Any:
                enter(CALLBACKS)
                try:
                    return callback(*args, **kwargs)
                finally:
                    leave()
            return timed_callback

        real_subscription = node.Node.create_subscription
        real_timer = node.Node.create_timer

        def create_subscription(self: Any, msg_type: Any, topic: str, callback: Any,
                                *args: Any, **kwargs: Any) -> Any:
            return real_subscription(self, msg_type, topic, timed(callback), *args, **kwargs)

        def create_timer(self: Any, period: float, callback: Any, *args: Any,
                         **kwargs: Any) -> Any:
            return real_timer(self, period, timed(callback), *args, **kwargs)

        node.Node.create_subscription = create_subscription
        node.Node.create_timer = create_timer
        self._restore += [(node.Node, 'create_subscription', real_subscription),
                          (node.Node, 'create_timer', real_timer)]

    def remove(self) -> None:
        for owner, name, original in reversed(self._restore):
            setattr(owner, name, original)
        self._restore.clear()


def ros_run(hours: int, record: bool, out: pathlib.Path, phases: Phases | None = None,
            async_solve: bool | None = None) -> bringup.RosRun:
    """Run the demo's ROS loop in a fresh context (the nodes' logs at WARN)."""
    args = bringup.build_parser().parse_args(['--out', str(out), '--hours', str(hours)])
    node_params = bringup.node_params_from_args(args)
    if async_solve is not None:
        node_params['mpc']['async_solve'] = async_solve
    context = Context()
    rclpy.init(args=ros_args(default_params_files(None)), context=context)
    for name in bringup.NODE_NAMES:
        rclpy.logging.set_logger_level(name, LoggingSeverity.WARN)
    try:
        if phases is not None:
            phases.install(ROS_PHASES)
            phases.time_callbacks()
        return bringup.run_in_process(context, node_params, record=record)
    finally:
        if phases is not None:
            phases.remove()
        rclpy.try_shutdown(context=context)


def core_run(run: bringup.RosRun) -> bringup.CoreRun:
    """Run the core-only loop with the parameters of a ROS run's nodes."""
    return bringup.core_only(run.emulator, run.mpc)


def median(values: list[float]) -> float:
    return statistics.median(values) if values else float('nan')


def timed_rounds(runs: int, hours: int, record: bool, out: pathlib.Path,
                 async_solve: bool | None) -> None:
    """Interleave ROS and core runs; print wall and CPU time and ratios."""
    rows = []
    print(f'{runs} runs of {hours} steps, ROS loop (in one process, '
          f"{'with' if record else 'without'} the bag recorder) and core loop interleaved;"
          ' the loops only (no start-up); CPU: the whole process, every thread')
    print(f"{'run':>4} {'ROS wall':>9} {'core wall':>9} {'ratio':>6} {'ROS CPU':>9} "
          f"{'core CPU':>9} {'ratio':>6} {'max |dx|':>9}")
    for k in range(runs):
        run = ros_run(hours, record, out, async_solve=async_solve)
        core = core_run(run)
        rows.append((run.wall_s, core.wall_s, run.cpu_s, core.cpu_s))
        print(f'{k + 1:4d} {run.wall_s:8.3f}s {core.wall_s:8.3f}s {run.wall_s / core.wall_s:6.2f}'
              f' {run.cpu_s:8.3f}s {core.cpu_s:8.3f}s {run.cpu_s / core.cpu_s:6.2f}'
              f' {core.max_abs_diff_k:9.1e}', flush=True)
    ros_wall, core_wall, ros_cpu, core_cpu = (median([r[i] for r in rows]) for i in range(4))
    print(f"{'med':>4} {ros_wall:8.3f}s {core_wall:8.3f}s {ros_wall / core_wall:6.2f} "
          f'{ros_cpu:8.3f}s {core_cpu:8.3f}s {ros_cpu / core_cpu:6.2f}')
    print(f'ROS overhead per step (medians): {1e3 * (ros_wall - core_wall) / hours:+.2f} ms '
          f'wall, {1e3 * (ros_cpu - core_cpu) / hours:+.2f} ms CPU; median of the per-run '
          f'ratios: {median([r[0] / r[1] for r in rows]):.2f} wall, '
          f'{median([r[2] / r[3] for r in rows]):.2f} CPU')


def phase_table(hours: int, record: bool, out: pathlib.Path,
                async_solve: bool | None) -> None:
    """One instrumented run of each loop: ms per step by phase."""
    ros_phases, core_phases = Phases(), Phases()
    ros_phases.install(CORE_PHASES)
    try:
        run = ros_run(hours, record, out, ros_phases, async_solve)
    finally:
        ros_phases.remove()
    core_phases.install(CORE_PHASES)
    try:
        core = core_run(run)
    finally:
        core_phases.remove()
    steps = run.emulator.steps_done

    def main_ms(phases: Phases, phase: str) -> float:
        return 1e3 * phases.seconds.get(('main', phase), 0.0) / steps

    print(f'\nBy phase, one instrumented run of each ({steps} steps): CPU ms per step on the '
          'executor thread (exclusive times)')
    print(f"{'phase':40s} {'ROS':>8} {'core':>8} {'calls/step':>10}")
    ros_total = core_total = 0.0
    for phase in ORDER:
        ros_ms, core_ms = main_ms(ros_phases, phase), main_ms(core_phases, phase)
        ros_total, core_total = ros_total + ros_ms, core_total + core_ms
        print(f'{phase:40s} {ros_ms:8.2f} {core_ms:8.2f} '
              f'{ros_phases.calls[phase] / steps:10.1f}')
    ros_rest = 1e3 * run.cpu_s / steps - ros_total
    core_rest = 1e3 * core.cpu_s / steps - core_total
    print(f"{'the rest: executor, DDS threads / loop':40s} {ros_rest:8.2f} {core_rest:8.2f}")
    print(f"{'CPU per step (the process)':40s} {1e3 * run.cpu_s / steps:8.2f} "
          f'{1e3 * core.cpu_s / steps:8.2f}')
    print(f"{'wall per step':40s} {1e3 * run.wall_s / steps:8.2f} "
          f'{1e3 * core.wall_s / steps:8.2f}')
    worker = {phase: 1e3 * seconds / steps for (thread, phase), seconds
              in ros_phases.seconds.items() if thread == 'worker'}
    if worker:
        print("on the MPC node's solver thread (CPU ms per step): "
              + ', '.join(f'{phase} {ms:.2f}' for phase, ms in sorted(worker.items())))
    print(f'{ros_phases.calls[CALLBACKS] / steps:.1f} node callbacks per step; the emulator '
          f'waited {1e3 * median(run.emulator.setpoint_waits_s):.2f} ms (median) from '
          'publishing a step to its setpoint')


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=3, help='interleaved runs of each (3)')
    parser.add_argument('--hours', type=int, default=72, help='control steps (72)')
    parser.add_argument('--no-bag', action='store_true', help='without the bag recorder')
    parser.add_argument('--no-phases', action='store_true', help='skip the phase table')
    parser.add_argument('--async-solve', action='store_true',
                        help="the MPC solves on its solver thread (the node's default; the "
                             'in-process lockstep run solves in the executor thread)')
    args = parser.parse_args(argv)
    record = not args.no_bag
    with tempfile.TemporaryDirectory(prefix='rosloop_') as folder:
        out = pathlib.Path(folder)
        if args.runs:
            timed_rounds(args.runs, args.hours, record, out, args.async_solve or None)
        if not args.no_phases:
            phase_table(args.hours, record, out, args.async_solve or None)


if __name__ == '__main__':
    main()
