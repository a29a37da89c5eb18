"""
Soak: many simulated days over ROS 2 with faults injected at random (seeded).

    python bench/soak.py --days 30 --seed 1 [--out out/soak] [--fault-scale 1.0]

Emulator (the R1C1 FMU, lockstep; on a lockstep timeout it holds the last
setpoint, then the safe default), forecaster, MPC and the bag recorder run in
one process (:class:`mshoot_testing.harness.ClosedLoop`). Before every control
step a seeded generator may inject:

- a solver that fails (reports non-convergence) for 1-3 solves;
- a solve that overruns its time budget (the solver sleeps first);
- a model that raises (an FMU error) for 1-3 solves;
- a forecast that stops for 2-6 steps (the forecaster is paused);
- the MPC node killed and restarted after 0.2-3 s of wall time (when longer than
  the emulator's 2 s lockstep timeout, the building holds, then goes safe);
- a burst of malformed zone states, forecasts and setpoints (each must be
  rejected and counted).

Reported (and written to ``<out>/soak.json``): setpoints the MPC published
against the steps expected, their sources and fallback reasons, what the
building applied, malformed messages injected against rejections counted,
non-finite values seen on the setpoint and status topics, the process RSS over
the run (growth and slope per simulated day), and messages lost between the
publishers and the bag (after reading it back). Every rejected input is logged
(``<out>/rejections.json``: node, stream, kind, stamp, clock, injected or not);
legitimate ones are counted apart only by an exact rule: a setpoint published
after the building's lockstep timeout (late), and a state or forecast of a step
already over that reaches a restarted MPC before it took one of its stream
(stale, see :meth:`RejectionWatch.after_restart`). Exit code 1 when a step went
without a setpoint, a non-finite value was published, a rejection was not
counted, a legitimate input was rejected outside those rules or a message was
lost from the bag.
"""
from __future__ import annotations

import argparse
import collections
import json
import math
import os
import pathlib
import resource
import shutil
import sys
import time
import tracemalloc
from typing import Any

from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.solvers import make_solver
from mshoot_core.units import NS_PER_S
from mshoot_msgs.msg import Forecast, Setpoint, ZoneState
from mshoot_nodes import contract, sources
from mshoot_nodes.bags import read_bag
from mshoot_nodes.contract import message_class
from mshoot_nodes.conversions import stamp_to_ns
from mshoot_testing.faults import FaultyModel, FaultySolver
from mshoot_testing.harness import (ClosedLoop, FORECAST_DEFECTS, MALFORMED, malformed_forecast,
                                    malformed_setpoint, malformed_zone_state, SETPOINT_DEFECTS,
                                    STATE_DEFECTS)
import numpy as np
import rclpy
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message

from common import logger, setup_logging, write_json

STEP_NS = 3600 * NS_PER_S
#: Probability per control step of each fault (scaled by --fault-scale).
FAULT_RATES = {'solver_fail': 0.02, 'overrun': 0.01, 'model_raise': 0.02,
               'forecast_stop': 0.01, 'mpc_restart': 0.01, 'malformed_burst': 0.06}
#: Node parameters of the soak (short waits: faults cost seconds, not minutes).
MPC_PARAMS = {'model': 'python', 'time_budget_s': 2.0, 'input_wait_s': 0.3,
              'max_plan_age_steps': 3, 'safe_value': 0.0, 'history_length': 48,
              'reject_log_period_s': 30.0}
EMULATOR_TIMEOUT_S = 2.0


def rss_mb() -> float:
    """Resident set size of this process now [MB]."""
    with open('/proc/self/statm') as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 1e6


class PublishCounter:
    """Counts what the nodes publish on the recorded topics (wraps their publishers)."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()

    def watch(self, node: Any) -> None:
        for publisher in node.publishers:
            topic = publisher.topic_name
            if topic in contract.TOPIC_TYPES and not getattr(publisher, '_soak_counted', False):
                publisher._soak_counted = True
                publish = publisher.publish

                def counted(msg: Any, _publish: Any = publish, _topic: str = topic) -> None:
                    _publish(msg)
                    self.counts[_topic] += 1
                publisher.publish = counted


class RejectionWatch:
    """
    Logs every input a node rejects: stream, kind, stamp, injected or legitimate.

    Wraps the callbacks of the node's subscriptions to the input topics; a message
    counted as a rejection during its callback is one row. A message is injected when
    the chaos node marked it (``frame_id`` :data:`MALFORMED`), legitimate otherwise.
    """

    STREAMS = {contract.ZONE_STATE: 'state', contract.FORECAST: 'forecast',
               contract.SETPOINT: 'setpoint'}

    def __init__(self) -> None:
        self.rows: list[dict] = []
        #: (node, stream) -> injected messages rejected.
        self.injected: collections.Counter[tuple[str, str]] = collections.Counter()
        #: Injected messages a node took (must stay empty): node, stream, stamp.
        self.injected_taken: list[dict] = []

    def watch(self, node: Any, name: str, step: int) -> None:
        """Log the rejections of ``node`` (``name``, started before control step ``step``)."""
        counts = node.rejections.counter.counts
        received: collections.Counter[str] = collections.Counter()
        taken: collections.Counter[str] = collections.Counter()
        for subscription in node.subscriptions:
            stream = self.STREAMS.get(subscription.topic_name)
            if stream is None:
                continue

            def logged(msg: Any, _callback: Any = subscription.callback,
                       _stream: str = stream) -> None:
                before = dict(counts)
                _callback(msg)
                kinds = [k for (s, k), n in counts.items() if n > before.get((s, k), 0)]
                clock_ns = (getattr(node, 'stamp_ns', None)  # the emulator's: its step
                            or node.get_clock().now().nanoseconds)
                injected = msg.header.frame_id == MALFORMED
                if injected and not kinds:
                    self.injected_taken.append({'node': name, 'stream': _stream,
                                                'stamp_s': stamp_to_ns(msg.header.stamp)
                                                / NS_PER_S})
                self.injected[(name, _stream)] += injected and bool(kinds)
                for kind in kinds:
                    self.rows.append({
                        'node': name, 'started_step': step, 'stream': _stream, 'kind': kind,
                        'stamp_s': stamp_to_ns(msg.header.stamp) / NS_PER_S,
                        'clock_s': clock_ns / NS_PER_S,
                        'injected': injected,
                        'received_before': received[_stream], 'taken_before': taken[_stream]})
                received[_stream] += 1
                taken[_stream] += not kinds
            subscription.callback = logged

    def legitimate(self) -> list[dict]:
        """Return the rejected messages that were not injected."""
        return [r for r in self.rows if not r['injected']]

    @staticmethod
    def after_restart(row: dict) -> bool:
        """
        Whether a rejection is that of a legitimate input of a step already over at a restart.

        A restarted MPC has no newest stamp yet, so the repeat rule (a stamp equal to the
        newest accepted one is taken) does not cover what reaches it first: the forecaster's
        latched forecast of a step already over (re-delivered to a new reader while the
        forecaster is paused or has not yet published for the step), or the emulator's state
        of the step the building gave up on (lockstep timeout) when the new MPC takes it
        after the next step's /clock.
        Stale by ``max_state_age_s`` / ``max_forecast_age_s``, rightly rejected; the rule:
        not injected, kind 'stale', an MPC started by a restart, before that MPC took any
        message of the stream.
        """
        return (not row['injected'] and row['node'] == 'mpc' and row['started_step'] > 0
                and row['kind'] == 'stale' and row['taken_before'] == 0)


class Soak:
    """The run: a closed loop, its fault injector and the bookkeeping."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.rng = np.random.default_rng(args.seed)
        self.hours = int(args.days * 24)
        self.out = pathlib.Path(args.out)
        if self.out.exists():
            shutil.rmtree(self.out)
        self.out.mkdir(parents=True)
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'OFF'
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=os.getpid() % 100 + 1)
        emulator_model = 'fmu' if sources.fmu_available() else 'python'
        self.model = FaultyModel(R1C1Model())
        self.solver = FaultySolver(make_solver('slsqp'))
        self.loop = ClosedLoop(self.context, {
            'emulator': {'hours': self.hours, 'model': emulator_model, 'mode': 'lockstep',
                         'lockstep_timeout_s': EMULATOR_TIMEOUT_S,
                         'on_lockstep_timeout': 'hold', 'hold_s': 3600.0,
                         'heartbeat_period_s': 0.1, 'reject_log_period_s': 30.0,
                         'records_kept': 48},
            'forecaster': {'hours': self.hours},
            'mpc': dict(MPC_PARAMS),
            'recorder': {'bag_path': str(self.out / 'bag'), 'overwrite': True},
        }, record=True, mpc_model=self.model)
        self.loop.mpc.mpc.set_solver(self.solver)
        self.emulator_model = emulator_model
        self.chaos = rclpy.create_node('chaos', context=self.context,
                                       start_parameter_services=False)
        self.loop.executor.add_node(self.chaos)
        self.chaos_state = self.chaos.create_publisher(ZoneState, contract.ZONE_STATE,
                                                       contract.DATA_QOS)
        self.chaos_setpoint = self.chaos.create_publisher(Setpoint, contract.SETPOINT,
                                                          contract.DATA_QOS)
        self.published = PublishCounter()
        for node in (self.loop.emulator, self.loop.forecaster, self.loop.mpc, self.chaos):
            self.published.watch(node)
        self.rejections = RejectionWatch()
        self.rejections.watch(self.loop.emulator, 'emulator', 0)
        self.rejections.watch(self.loop.mpc, 'mpc', 0)
        self.faults: collections.Counter[str] = collections.Counter()
        self.injected: collections.Counter[str] = collections.Counter()
        self.resume_forecasts_at = -1
        self.rss: list[tuple[int, float]] = []

    # -- faults ---------------------------------------------------------------------------
    def inject(self, step: int) -> None:
        """Draw and inject the faults of the coming step."""
        scale = self.args.fault_scale
        draw = {name: self.rng.random() < rate * scale for name, rate in FAULT_RATES.items()}
        # Let forecaster and MPC see the new step's /clock first: a forecaster resumed while
        # its clock still shows the previous step would publish a stale forecast (rightly
        # rejected, but not one of the malformed messages counted here).
        step_ns = self.loop.emulator.stamp_ns
        nodes = [n for n in (self.loop.forecaster, self.loop.mpc) if n is not None]
        self.loop.spin_until(lambda: all(n.get_clock().now().nanoseconds >= step_ns
                                         for n in nodes), 5.0, 'the clocks to follow')
        if step == self.resume_forecasts_at:
            self.loop.forecaster.set_parameters([Parameter('enabled', value=True)])
        if draw['solver_fail']:
            self.solver.faults.arm('fail', times=int(self.rng.integers(1, 4)))
            self.faults['solver_fail'] += 1
        if draw['overrun']:
            self.solver.faults.arm('overrun', delay_s=MPC_PARAMS['time_budget_s'] + 0.5)
            self.faults['overrun'] += 1
        if draw['model_raise']:
            self.model.faults.arm('raise', times=int(self.rng.integers(1, 4)))
            self.faults['model_raise'] += 1
        if draw['forecast_stop'] and self.resume_forecasts_at < step:
            self.loop.forecaster.set_parameters([Parameter('enabled', value=False)])
            self.resume_forecasts_at = step + int(self.rng.integers(2, 7))
            self.faults['forecast_stop'] += 1
        if draw['malformed_burst'] and self.loop.mpc is not None:
            self.malformed_burst()
            self.faults['malformed_burst'] += 1
        if draw['mpc_restart'] and self.loop.mpc is not None:
            self.restart_mpc(float(self.rng.uniform(0.2, 3.0)))
            self.faults['mpc_restart'] += 1

    def restart_mpc(self, down_s: float) -> None:
        """Kill the MPC node, leave the building without it for ``down_s``, restart it."""
        retired = self.loop.stop_mpc()
        retired.results.clear()  # the soak needs only its counters; the solve results go
        self.loop.spin_for(down_s)
        mpc = self.loop.start_mpc()
        mpc.mpc.set_solver(self.solver)
        self.published.watch(mpc)
        self.rejections.watch(mpc, 'mpc', self.loop.steps_done)

    def malformed_burst(self) -> None:
        """1-5 malformed states, forecasts and setpoints; wait until all are counted."""
        mpc, emulator, rng = self.loop.mpc, self.loop.emulator, self.rng
        # Counted by the watch, injected ones only: a legitimate rejection in the meantime
        # (e.g. a restarted MPC's first forecast, stale) must not stand in for one of these.
        counted = self.rejections.injected
        want = {key: counted[key] for key in (('mpc', 'state'), ('mpc', 'forecast'),
                                              ('emulator', 'setpoint'))}
        now = mpc.get_clock().now().nanoseconds
        floor = (now // STEP_NS) * STEP_NS
        latest = mpc.controller._state_gate.latest_ns or floor  # noqa: SLF001 - the soak knows it
        for _ in range(int(rng.integers(1, 6))):
            defect = str(rng.choice(STATE_DEFECTS))
            self.chaos_state.publish(malformed_zone_state(defect, now, latest, STEP_NS, rng))
            want[('mpc', 'state')] += 1
            self.injected['state'] += 1
        # A latched publisher of its own, destroyed after use: a restarted MPC must not get
        # these again (they would be counted twice).
        forecasts = self.chaos.create_publisher(Forecast, contract.FORECAST,
                                                contract.LATCHED_QOS)
        self.published.watch(self.chaos)
        self.loop.spin_until(lambda: forecasts.get_subscription_count() >= 2, 5.0,
                             'the chaos forecast publisher to match')
        latest_forecast = mpc.controller._forecast_gate.latest_ns or floor  # noqa: SLF001
        for _ in range(int(rng.integers(1, 4))):
            defect = str(rng.choice(FORECAST_DEFECTS))
            forecasts.publish(malformed_forecast(defect, now, latest_forecast, STEP_NS, rng))
            want[('mpc', 'forecast')] += 1
            self.injected['forecast'] += 1
        step = emulator.stamp_ns
        last = emulator._setpoint_gate.latest_ns or step - STEP_NS  # noqa: SLF001
        for _ in range(int(rng.integers(1, 6))):
            defect = str(rng.choice(SETPOINT_DEFECTS))
            self.chaos_setpoint.publish(malformed_setpoint(defect, step, last, STEP_NS, rng))
            want[('emulator', 'setpoint')] += 1
            self.injected['setpoint'] += 1
        self.loop.spin_until(lambda: all(counted[key] >= n for key, n in want.items()), 10.0,
                             'the burst to be counted')
        self.chaos.destroy_publisher(forecasts)

    # -- the run --------------------------------------------------------------------------
    def run(self) -> dict:
        started = time.perf_counter()
        self.rss.append((0, rss_mb()))
        last_report = started
        while not self.loop.emulator.done:
            step = self.loop.steps_done
            if step > 0:
                self.inject(step)
            self.loop.run_steps(1, timeout_s=120.0)
            done = self.loop.steps_done
            if done % 24 == 0:
                self.rss.append((done // 24, rss_mb()))
                if done == 48 and self.args.tracemalloc:
                    self.snapshot = tracemalloc.take_snapshot()
            if time.perf_counter() - last_report > 10.0 or self.loop.emulator.done:
                last_report = time.perf_counter()
                logger.info('[soak] day %5.1f/%g: %d steps, %.0f s wall, RSS %.1f MB',
                            done / 24, self.args.days, done, last_report - started, rss_mb())
        wall_s = time.perf_counter() - started
        if self.args.tracemalloc and getattr(self, 'snapshot', None) is not None:
            growth = tracemalloc.take_snapshot().compare_to(self.snapshot, 'lineno')
            logger.info('[soak] Python allocations grown since day 2 (top 12):')
            for stat in growth[:12]:
                logger.info('[soak]   %s', stat)
        self.loop.drain_recorder()
        recorder_counts = dict(self.loop.recorder.counts)
        mpcs = self.loop.retired + ([self.loop.mpc] if self.loop.mpc is not None else [])
        self.rejected_kinds = {'mpc': sum((collections.Counter(m.rejections.counter.counts)
                                           for m in mpcs), collections.Counter()),
                               'emulator': self.loop.emulator.rejections.counter.counts}
        rejected = {'state': sum(m.rejections.total('state') for m in mpcs),
                    'forecast': sum(m.rejections.total('forecast') for m in mpcs),
                    'setpoint': self.loop.emulator.rejections.total()}
        emulator = self.loop.emulator
        records_mb = sum(r.fine.memory_usage(deep=True).sum() for r in emulator.records) / 1e6
        applied = collections.Counter(emulator.applied_sources)
        failed = emulator.failed
        self.loop.close()
        rclpy.try_shutdown(context=self.context)
        return self.report(wall_s, recorder_counts, rejected, applied, records_mb, failed)

    def report(self, wall_s: float, recorder_counts: dict, rejected: dict,
               applied: collections.Counter, records_mb: float, failed: str) -> dict:
        bag = read_bag(self.out / 'bag')
        (self.out / 'rejections.json').write_text(json.dumps(self.rejections.rows, indent=1)
                                                  + '\n')
        setpoints, statuses = [], []
        for message in bag.messages:
            if message.topic in (contract.SETPOINT, contract.STATUS):
                msg = deserialize_message(message.rawdata, message_class(message.msgtype))
                (setpoints if message.topic == contract.SETPOINT else statuses).append(msg)
        # The MPC's own setpoints: the chaos node's malformed ones are on the topic too.
        setpoints = [s for s in setpoints if s.header.frame_id != MALFORMED]
        non_finite = 0
        first_status: dict[int, Any] = {}
        for msg in statuses:
            values = (msg.solve_time_s, msg.objective, msg.max_defect)
            non_finite += not all(math.isfinite(v) for v in values)
            first_status.setdefault(stamp_to_ns(msg.header.stamp), msg)
        for msg in setpoints:
            values = (*msg.control_values, *msg.temperature_setpoints_c, *msg.plan_controls,
                      *msg.plan_temperatures_c)
            non_finite += not all(math.isfinite(v) for v in values)
        sources = collections.Counter(s.source for s in first_status.values())
        solve_s = np.array([s.solve_time_s for s in first_status.values()
                            if s.source == 'optimum'])
        reasons = collections.Counter(s.fallback_reason for s in first_status.values()
                                      if s.fallback)
        published = dict(self.published.counts)
        lost = {topic: published.get(topic, 0) - bag.counts.get(topic, 0)
                for topic in contract.TOPIC_TYPES}
        legitimate = self.rejections.legitimate()
        after_restart = {stream: sum(r['stream'] == stream and self.rejections.after_restart(r)
                                     for r in legitimate) for stream in ('state', 'forecast')}
        unexplained = [r for r in legitimate if r['node'] == 'mpc'
                       and not self.rejections.after_restart(r)]
        days = [d for d, _ in self.rss]
        mb = [m for _, m in self.rss]
        tail = [(d, m) for d, m in self.rss if d >= 2]
        slope = (float(np.polyfit([d for d, _ in tail], [m for _, m in tail], 1)[0])
                 if len(tail) >= 3 else float('nan'))
        summary = {
            'days': self.args.days, 'seed': self.args.seed, 'fault_scale': self.args.fault_scale,
            'emulator_model': self.emulator_model, 'wall_s': wall_s,
            'steps_expected': self.hours, 'steps_applied': sum(applied.values()),
            'setpoints_published': len(first_status),
            'setpoint_sources': dict(sources), 'fallback_reasons': dict(reasons),
            'solve_s': {'median': float(np.median(solve_s)) if solve_s.size else float('nan'),
                        'p95': float(np.percentile(solve_s, 95)) if solve_s.size
                        else float('nan'),
                        'max': float(solve_s.max()) if solve_s.size else float('nan')},
            'applied_sources': dict(applied), 'emulator_failed': failed,
            'faults_injected': dict(self.faults),
            'solver_faults_taken': dict(self.solver.faults.injected),
            'model_faults_taken': dict(self.model.faults.injected),
            'malformed_injected': dict(self.injected), 'malformed_rejected': rejected,
            'rejected_by_kind': {node: {f'{stream}/{kind}': n for (stream, kind), n in
                                        counts.items()}
                                 for node, counts in self.rejected_kinds.items()},
            'rejected_after_restart': after_restart, 'rejected_legitimate': legitimate,
            'injected_taken': self.rejections.injected_taken,
            'non_finite_published': non_finite,
            'rss_mb': {'start': mb[0], 'day_2': dict(self.rss).get(2, float('nan')),
                       'end': mb[-1], 'growth_after_day_2': mb[-1] - dict(self.rss).get(
                           2, mb[0]), 'slope_mb_per_day': slope,
                       'emulator_step_records_mb': records_mb,
                       'by_day': dict(zip(days, mb))},
            'bag': {'published': published, 'in_bag': bag.counts,
                    'recorder_counted': recorder_counts, 'lost': lost,
                    'messages': len(bag.messages)},
        }
        # A setpoint the MPC published after the building's lockstep timeout (it was down
        # or restarting) is stale when it arrives: rejected by the building, not applied.
        late = len(first_status) - applied.get('setpoint', 0)
        summary['setpoints_late'] = late
        summary['ok'] = bool(
            not failed and summary['steps_applied'] == self.hours and late >= 0
            and non_finite == 0
            and not unexplained and not self.rejections.injected_taken
            and rejected['state'] == self.injected.get('state', 0) + after_restart['state']
            and rejected['forecast'] == (self.injected.get('forecast', 0)
                                         + after_restart['forecast'])
            and rejected['setpoint'] == self.injected.get('setpoint', 0) + late
            and not any(lost.values()))
        return summary


def print_summary(s: dict) -> None:
    log = logger.info
    log('')
    log('soak: %g simulated days, seed %d, emulator %s, %.1f s wall (%.1f steps/s)',
        s['days'], s['seed'], s['emulator_model'], s['wall_s'],
        s['steps_applied'] / s['wall_s'])
    log('  setpoints published by the MPC: %d for %d steps expected (%d too late: after the '
        "building's lockstep timeout); the building applied %s", s['setpoints_published'],
        s['steps_expected'], s['setpoints_late'], s['applied_sources'])
    log('  setpoint sources %s; fallback reasons %s', s['setpoint_sources'],
        s['fallback_reasons'])
    log('  solve time of the optima: median %.3f s, 95th percentile %.3f s, max %.3f s '
        '(time budget %.1f s)', s['solve_s']['median'], s['solve_s']['p95'],
        s['solve_s']['max'], MPC_PARAMS['time_budget_s'])
    log('  faults injected %s (solver faults taken %s, model faults taken %s)',
        s['faults_injected'], s['solver_faults_taken'], s['model_faults_taken'])
    log('  malformed messages injected %s, rejected and counted %s (setpoints: plus the %d '
        'late ones)', s['malformed_injected'], s['malformed_rejected'], s['setpoints_late'])
    log('  state and forecast rejected after an MPC restart (legitimate, of a step already '
        'over: stale) %s', s['rejected_after_restart'])
    for row in s['rejected_legitimate']:
        log('    legitimate %s rejected by the %s (started at step %d): %s, stamp %.0f s, '
            'clock %.0f s, %d taken before', row['stream'], row['node'], row['started_step'],
            row['kind'], row['stamp_s'], row['clock_s'], row['taken_before'])
    log('  injected messages taken by a node (must be none): %s', s['injected_taken'] or 'none')
    log('  non-finite values published: %d', s['non_finite_published'])
    r = s['rss_mb']
    log('  RSS %.1f MB at start, %.1f MB after day 2, %.1f MB at the end: %+.1f MB after '
        "day 2, %+.3f MB per simulated day (the emulator's last 48 step records: %.1f MB)",
        r['start'], r['day_2'], r['end'], r['growth_after_day_2'], r['slope_mb_per_day'],
        r['emulator_step_records_mb'])
    b = s['bag']
    log('  bag: %d messages; lost between publishers and bag %s', b['messages'], b['lost'])
    log('  verdict: %s', 'OK' if s['ok'] else 'FAILED')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--days', type=float, default=30.0, help='simulated days (default 30)')
    parser.add_argument('--seed', type=int, default=1, help='seed of the faults (default 1)')
    parser.add_argument('--fault-scale', type=float, default=1.0,
                        help='multiply every fault rate (default 1)')
    parser.add_argument('--out', default='out/soak', help='output folder (default out/soak)')
    parser.add_argument('--log-level', default='error', choices=('info', 'warn', 'error'),
                        help='level of the node logs (default error)')
    parser.add_argument('--tracemalloc', action='store_true',
                        help='list the Python allocations that grew after day 2 (slower)')
    args = parser.parse_args(argv)
    if args.tracemalloc:
        tracemalloc.start(1)
    if not args.days * 24 >= 2:
        parser.error('--days must cover at least 2 hours')
    setup_logging()
    for name in ('emulator', 'forecaster', 'mpc', 'recorder', 'chaos'):
        rclpy.logging.set_logger_level(name, getattr(rclpy.logging.LoggingSeverity,
                                                     args.log_level.upper()))
    summary = Soak(args).run()
    write_json('soak', summary)
    (pathlib.Path(args.out) / 'soak.json').write_text(json.dumps(summary, indent=2,
                                                                 default=float) + '\n')
    print_summary(summary)
    return 0 if summary['ok'] else 1


if __name__ == '__main__':
    sys.exit(main())
