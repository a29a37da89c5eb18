"""
Hostile flood: a publisher nobody here wrote, against the three executables over DDS.

    python bench/hostile.py [--seconds 45] [--rate 1500] [--speedup 1800] [--out out/hostile]

Forecaster, MPC and emulator run as separate processes (their installed executables, as
:mod:`mshoot_nodes.processes` starts them), the emulator free-running (``--speedup``
simulated seconds per wall second: a step every 2 s by default), on a private
``ROS_DOMAIN_ID`` on this host. Once the run has started, a node named ``hostile`` in this
process floods every data topic they read or write (``/zone/state``, ``/zone/disturbances``,
``/forecast``, ``/mpc/setpoint``, ``/mpc/status``; not ``/clock``, see ``docs/security.md``)
for ``--seconds`` at about ``--rate`` messages per second with: the malformed messages of
:mod:`mshoot_testing.harness` (one defect each), messages stamped off the step grid (at the
receivers' clock), from the future (on and off the grid), with junk fields (an output of
1e300, an applied heat rate of 9.9e6 W, a broken warm-up history), and once a second on each
topic a message with 10^6-element arrays.

Printed (and written to ``<out>/hostile.json``):

- steps where the emulator applied the MPC's setpoint (the one the MPC published for that step)
  against held or safe defaults;
- steps the MPC planned from an injected state (the state in its status differs from the
  emulator's state at the step start);
- invalid setpoints the MPC published (:func:`mshoot_core.safety.check_setpoint`, non-finite);
- nodes alive at the end of the flood, and the intruder each reported on /diagnostics;
- RSS of every node [MB] before the flood, at its end and ``--settle`` seconds later, and the
  growth.

Exit code 1 when a step did not apply the MPC's setpoint, a step was planned from an injected
state, an invalid setpoint was published, a node died or a node's RSS grew by more than
``--max-growth-mb``.
"""
from __future__ import annotations

import argparse
import array
import collections
import functools
import json
import math
import multiprocessing
import os
import pathlib
import queue
import random
import signal
import subprocess
import sys
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from mshoot_core.safety import check_setpoint
from mshoot_core.units import KELVIN, NS_PER_S
from mshoot_msgs.msg import Disturbances, Forecast, MpcStatus, Setpoint, ZoneState
from mshoot_nodes import contract
from mshoot_nodes.conversions import disturbances_msg, setpoint_msg, stamp_to_ns, zone_state_msg
from mshoot_nodes.diagnostics import status_values
from mshoot_nodes.processes import executable
from mshoot_nodes.readiness import run_requirements
from mshoot_testing.harness import (FORECAST_DEFECTS, malformed_forecast, malformed_setpoint,
                                    malformed_zone_state, SETPOINT_DEFECTS, STATE_DEFECTS)
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock

STEP_NS = 3600 * NS_PER_S
HUGE = 1_000_000
#: frame_id of everything the flood sends.
HOSTILE = 'hostile'
#: Larger setpoints and statuses are the flood's (the MPC's hold a plan of a few steps).
MAX_OBSERVED_BYTES = 1_000_000
#: The executables, in start order.
NODES = (('forecaster', 'forecaster_node'), ('mpc', 'mpc_node'), ('emulator', 'emulator_node'))


def rss_mb(pid: int) -> float:
    """Resident set size of a process [MB] (NaN once it is gone)."""
    try:
        for line in pathlib.Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


class Flood:
    """The hostile node: what it sends, built fresh from the receivers' clock."""

    def __init__(self, node: Any, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.pubs = {topic: node.create_publisher(cls, topic, contract.TOPIC_QOS[topic])
                     for topic, cls in ((contract.ZONE_STATE, ZoneState),
                                        (contract.ZONE_DISTURBANCES, Disturbances),
                                        (contract.FORECAST, Forecast),
                                        (contract.SETPOINT, Setpoint),
                                        (contract.STATUS, MpcStatus))}
        self.sent: collections.Counter[str] = collections.Counter()
        #: Wall time spent publishing, by topic [s].
        self.publish_s: collections.Counter[str] = collections.Counter()
        self._batches: dict[int, list[tuple[str, bytes]]] = {}
        self._huge: list[tuple[str, bytes]] = []
        self._values = array.array('d', np.full(HUGE, 20.0).tobytes())  # (taken as it is)

    def stamps(self, now_ns: int) -> dict[str, int]:
        """Off-grid (the clock itself, or near a step start), future on and off the grid."""
        step = (now_ns // STEP_NS) * STEP_NS
        ahead = int(self.rng.integers(2, 100))
        return {'clock': now_ns + (0 if now_ns % STEP_NS else 1),
                'next_plus_1s': step + STEP_NS + NS_PER_S,
                'off_grid': step + int(self.rng.integers(1, STEP_NS)),
                'future': step + ahead * STEP_NS,
                'future_off_grid': step + ahead * STEP_NS + int(self.rng.integers(1, STEP_NS))}

    def batch(self, now_ns: int) -> list[tuple[str, Any]]:
        """
        One message of every kind, stamped from the receivers' clock ``now_ns``.

        Those of the step are built once per step (the malformed ones take milliseconds each);
        those stamped at the clock itself anew.
        """
        step = (now_ns // STEP_NS) * STEP_NS
        if step not in self._batches:
            self._batches = {step: serialized(self._step_batch(step))}
        t = float(self.rng.uniform(15.0, 25.0))
        stamp = now_ns + (0 if now_ns % STEP_NS else 1)
        return self._batches[step] + serialized([
            (contract.ZONE_STATE, zone_state_msg(stamp, {'T': t + KELVIN}, {'T': t, 'Qr': 0.0},
                                                 {'q': 0.0}, HOSTILE)),
            (contract.SETPOINT, setpoint_msg(stamp, 3600.0, {'q': -1500.0}, {'T': t}, None,
                                             None, HOSTILE))])

    def _step_batch(self, now_ns: int) -> list[tuple[str, Any]]:
        rng, step = self.rng, (now_ns // STEP_NS) * STEP_NS
        out: list[tuple[str, Any]] = []
        for defect in STATE_DEFECTS:
            out.append((contract.ZONE_STATE, malformed_zone_state(defect, step, step - STEP_NS,
                                                                  STEP_NS, rng)))
        for defect in FORECAST_DEFECTS:
            out.append((contract.FORECAST, malformed_forecast(defect, step, step - STEP_NS,
                                                              STEP_NS, rng, 11)))
        for defect in SETPOINT_DEFECTS:
            out.append((contract.SETPOINT, malformed_setpoint(defect, step, step - STEP_NS,
                                                              STEP_NS, rng)))
        for stamp in self.stamps(now_ns).values():  # valid fields, stamps that are not
            t = float(rng.uniform(15.0, 25.0))
            out.append((contract.ZONE_STATE, zone_state_msg(
                stamp, {'T': t + KELVIN}, {'T': t, 'Qr': 0.0}, {'q': 0.0}, HOSTILE)))
            out.append((contract.SETPOINT, setpoint_msg(
                stamp, 3600.0, {'q': float(rng.uniform(-2000, 2000))}, {'T': t}, None, None,
                HOSTILE)))
            out.append((contract.ZONE_DISTURBANCES, disturbances_msg(
                stamp, {'Tout': 5.0, 'solrad': 100.0, 'occ': 0.0, 'dpos': 0.0}, HOSTILE)))
            status = MpcStatus(source='optimum', message=HOSTILE)
            status.header.stamp.sec, status.header.frame_id = stamp // NS_PER_S, HOSTILE
            out.append((contract.STATUS, status))
        # Junk fields on a plausible state, at the step start and at the next step + 1 s.
        for stamp in (step, step + STEP_NS + NS_PER_S):
            junk = zone_state_msg(stamp, {'T': 21.0 + KELVIN}, {'T': 1e300, 'Qr': 0.0},
                                  {'q': 9.9e6}, HOSTILE)
            junk.history_offsets_s, junk.history_state_values = [-60.0, 0.0], [293.0]
            out.append((contract.ZONE_STATE, junk))
            history = zone_state_msg(stamp, {'T': 21.0 + KELVIN}, {'T': 21.0, 'Qr': 0.0},
                                     {'q': 0.0}, HOSTILE)
            history.history_offsets_s, history.history_state_values = [0.0, -60.0], [1.0, 2.0]
            out.append((contract.ZONE_STATE, history))
            schedule = setpoint_msg(stamp, 3600.0, {'q': 500.0}, {'T': 21.0}, None, None,
                                    HOSTILE)
            schedule.schedule_offsets_s, schedule.schedule_values = [0.0, 60.0], [1.0, math.nan]
            out.append((contract.SETPOINT, schedule))
        return out

    def huge(self, now_ns: int) -> list[tuple[str, bytes]]:
        """One message with 10^6-element arrays per topic (stamped with the first step)."""
        if not self._huge:
            self._huge = serialized(self._build_huge((now_ns // STEP_NS) * STEP_NS))
        return self._huge

    def _build_huge(self, step: int) -> list[tuple[str, Any]]:
        values = self._values
        state = zone_state_msg(step, {'T': 21.0 + KELVIN}, {'T': 21.0}, {'q': 0.0}, HOSTILE)
        state.state_values = values
        state.history_offsets_s = array.array('d', np.linspace(-1e6, 0, HUGE).tobytes())
        state.history_state_values = values
        forecast = Forecast(step_s=3600.0, series_names=['Tout'], series_values=values,
                            comfort_min_c=values, comfort_max_c=values)
        forecast.header.stamp.sec, forecast.header.frame_id = step // NS_PER_S, HOSTILE
        setpoint = setpoint_msg(step, 3600.0, {'q': 0.0}, {'T': 21.0}, None, None, HOSTILE)
        setpoint.plan_controls = setpoint.schedule_values = values
        setpoint.plan_temperatures_c = setpoint.schedule_offsets_s = values
        disturbances = Disturbances(values=values)
        disturbances.header.frame_id = HOSTILE
        return [(contract.ZONE_STATE, state), (contract.FORECAST, forecast),
                (contract.SETPOINT, setpoint), (contract.ZONE_DISTURBANCES, disturbances)]

    def send(self, messages: list[tuple[str, bytes]]) -> None:
        for topic, data in messages:
            started = time.perf_counter()
            self.pubs[topic].publish(data)
            self.publish_s[topic] += time.perf_counter() - started
            self.sent[topic] += 1


def serialized(messages: list[tuple[str, Any]]) -> list[tuple[str, bytes]]:
    """Serialise once (rclpy publishes bytes as they are: the flood costs no conversion)."""
    return [(topic, serialize_message(msg)) for topic, msg in messages]


class Observer:
    """
    What the MPC publishes and /diagnostics, taken in a process of its own (:func:`observe`).

    The flood must not make it drop the MPC's messages (nor slow the flood down). The MPC's
    messages are those with its frame_id ('zone' for setpoints, '' for statuses): the flood
    sends 'hostile' and 'malformed'; a writer that imitates the MPC's frame_id is beyond what
    this counts.
    """

    def __init__(self, domain: int) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node('observer', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.setpoints: dict[int, dict[str, Any]] = {}
        self.statuses: dict[int, dict[str, Any]] = {}
        self.states: dict[int, dict[str, Any]] = {}
        #: Status name -> the message of its last ERROR, and the latest key values.
        self.errors: dict[str, str] = {}
        self.latest: dict[str, dict[str, str]] = {}
        node = self.node
        for topic, cls, frame, taken in ((contract.SETPOINT, Setpoint, 'zone', self.setpoints),
                                         (contract.STATUS, MpcStatus, '', self.statuses),
                                         (contract.ZONE_STATE, ZoneState, 'zone', self.states)):
            node.create_subscription(cls, topic, functools.partial(
                self._on_raw, cls, frame, taken), 1000, raw=True)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 100)

    @staticmethod
    def _on_raw(cls: type, frame: str, taken: dict[int, Any], data: bytes) -> None:
        """Keep the MPC's message of every stamp (the flood's huge ones are not even read)."""
        if len(data) > MAX_OBSERVED_BYTES:
            return
        msg = deserialize_message(data, cls)
        if msg.header.frame_id != frame:
            return
        fields = ('step_s', 'control_names', 'control_values', 'temperature_names',
                  'temperature_setpoints_c', 'plan_controls', 'plan_temperatures_c',
                  'state_values', 'source')  # (a ZoneState's control_values: applied)
        taken.setdefault(stamp_to_ns(msg.header.stamp), {
            f: (getattr(msg, f) if isinstance(getattr(msg, f), (str, float))
                else list(getattr(msg, f))) for f in fields if hasattr(msg, f)})

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            level = status.level[0] if isinstance(status.level, bytes) else int(status.level)
            if level == 2:
                self.errors[status.name] = status.message
            self.latest[status.name] = status_values(status)


def observe(domain: int, results: Any, started: Any, stop: Any) -> None:
    """Run an :class:`Observer` until ``stop`` is set; put what it saw on ``results``."""
    watcher = Observer(domain)
    while not stop.is_set():
        watcher.executor.spin_once(timeout_sec=0.05)
        if watcher.statuses and not started.is_set():
            started.set()
    results.put({'setpoints': watcher.setpoints, 'statuses': watcher.statuses,
                 'states': watcher.states,
                 'errors': watcher.errors, 'latest': watcher.latest})
    watcher.executor.shutdown()
    watcher.node.destroy_node()
    rclpy.try_shutdown(context=watcher.context)


def start_nodes(args: argparse.Namespace, env: dict, hours: int,
                out: pathlib.Path) -> dict[str, subprocess.Popen]:
    scenario = ['scenario:=synthetic', f'hours:={hours}']
    params = {
        'forecaster': scenario + ['use_sim_time:=true'],
        'mpc': ['use_sim_time:=true', 'model:=python', f'horizon_steps:={args.horizon}'],
        'emulator': scenario + [
            'model:=python', f'mode:={args.mode}', f'speedup:={args.speedup}',
            'exit_when_done:=true', 'on_lockstep_timeout:=hold',
            f'ready_endpoints:={run_requirements("none")!r}',
            'ready_timeout_s:=120.0', 'start_delay_s:=1.0'],
    }
    procs = {}
    for name, module in NODES:
        command = executable(name, module) + ['--ros-args']
        for item in params[name]:
            command += ['-p', item]
        log = open(out / f'{name}.log', 'w')  # noqa: SIM115 - closed with the process
        procs[name] = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
    return procs


def stop_nodes(procs: dict[str, subprocess.Popen]) -> None:
    for proc in procs.values():
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    for proc in procs.values():
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def evaluate(seen: dict[str, Any]) -> dict[str, Any]:
    """
    Return what the flood did to the loop, from the messages of the MPC and the emulator.

    Step k applied the MPC's setpoint when the emulator's state of step k + 1 says it applied
    (``control_values``) the MPC's setpoint of step k (clipped to the actuator limits); it was
    planned from an injected state when the state in the MPC's status of step k is not the
    emulator's state of step k.
    """
    setpoints, statuses, states = seen['setpoints'], seen['statuses'], seen['states']
    mpc_applied = other = unseen = injected = 0
    for stamp in sorted(setpoints):
        after = states.get(stamp + STEP_NS)
        if after is None or not after['control_values']:
            unseen += 1
        elif abs(after['control_values'][0] - float(np.clip(
                setpoints[stamp]['control_values'][0], -2000, 2000))) < 1e-9:
            mpc_applied += 1
        else:
            other += 1
        status, state = statuses.get(stamp), states.get(stamp)
        if status is not None and state is not None and len(status['state_values']) and abs(
                status['state_values'][0] - state['state_values'][0]) > 1e-6:
            injected += 1
    invalid = sum(1 for m in setpoints.values() if check_setpoint(
        m['step_s'], m['control_names'], m['control_values'], m['temperature_names'],
        m['temperature_setpoints_c'], m['plan_controls'], m['plan_temperatures_c'],
        expected_step_s=3600.0, expected_controls=['q']) is not None)
    emulator = seen['latest'].get('mshoot/emulator', {})
    steps = int(emulator.get('step', 0))
    return {'steps': steps, 'applied_mpc_setpoint': mpc_applied,
            'applied_other': other, 'not_observed': max(unseen, steps - mpc_applied - other),
            'applied_sources': {k: int(emulator.get(f'applied_{k}', 0))
                                for k in ('setpoint', 'held', 'safe')},
            'planned_from_injected_state': injected, 'mpc_setpoints': len(setpoints),
            'invalid_setpoints': invalid,
            'rejected_by_emulator': emulator.get('rejected_by_kind', '')}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=45.0, help='flood duration [s]')
    parser.add_argument('--rate', type=float, default=1500.0,
                        help='messages per second, about (default 1500)')
    parser.add_argument('--mode', choices=('free', 'lockstep'), default='free',
                        help="the emulator's mode (default free: the clock runs on whatever "
                             'comes; lockstep: each step waits for its setpoint)')
    parser.add_argument('--speedup', type=float, default=1800.0,
                        help='free mode: simulated seconds per wall second (default 1800: a '
                             '2 s step)')
    parser.add_argument('--horizon', type=int, default=6, help='MPC horizon steps')
    parser.add_argument('--settle', type=float, default=10.0,
                        help='wall time after the flood before the last RSS reading [s]')
    parser.add_argument('--max-growth-mb', type=float, default=10.0)
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/hostile'))
    args = parser.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    domain = random.randint(1, 100)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    step_wall_s = 3600.0 / args.speedup
    # Long enough to outlast flood and settling (lockstep runs as fast as the MPC answers).
    hours = (int(math.ceil((args.seconds + args.settle + 8.0) / step_wall_s)) + 2
             if args.mode == 'free' else 5000)
    spawn = multiprocessing.get_context('spawn')
    results, started, stop = spawn.Queue(), spawn.Event(), spawn.Event()
    observer = spawn.Process(target=observe, args=(domain, results, started, stop))
    observer.start()
    flood_context = rclpy.Context()
    rclpy.init(context=flood_context, domain_id=domain)
    hostile = rclpy.create_node('hostile', context=flood_context)
    executor = SingleThreadedExecutor(context=flood_context)
    executor.add_node(hostile)
    clock = {'ns': 0}
    hostile.create_subscription(Clock, contract.CLOCK, lambda m: clock.update(
        ns=stamp_to_ns(m.clock)), contract.CLOCK_QOS)
    procs = start_nodes(args, env, hours, out)
    print(f'[hostile] ROS_DOMAIN_ID={domain}; emulator {args.mode}'
          + (f' at {step_wall_s:g} s wall per step' if args.mode == 'free' else '')
          + f'; logs in {out}', flush=True)
    report: dict[str, Any] = {'seconds': args.seconds, 'rate': args.rate, 'mode': args.mode,
                              'speedup': args.speedup}
    seen: dict[str, Any] = {}
    try:
        deadline = time.monotonic() + 180.0
        while clock['ns'] == 0 or not started.is_set():  # started: the MPC answers
            if time.monotonic() > deadline or any(p.poll() is not None for p in procs.values()):
                print('[hostile] error: the run did not start; see the logs', file=sys.stderr)
                return 1
            executor.spin_once(timeout_sec=0.05)
        flood = Flood(hostile, args.seed)  # its publishers appear in the graph only now
        executor.spin_once(timeout_sec=0.5)
        rss_before = {name: rss_mb(p.pid) for name, p in procs.items()}
        started_s = time.monotonic()
        loop_s: collections.Counter[str] = collections.Counter()
        next_huge = started_s
        sent_at = started_s
        while (now := time.monotonic()) < started_s + args.seconds:
            if now >= next_huge:
                flood.send(flood.huge(clock['ns']))
                next_huge += 1.0
            t0 = time.perf_counter()
            batch = flood.batch(clock['ns'])
            t1 = time.perf_counter()
            flood.send(batch)
            t2 = time.perf_counter()
            sent_at += len(batch) / args.rate
            executor.spin_once(timeout_sec=max(0.0, sent_at - time.monotonic()))
            loop_s['build'] += t1 - t0
            loop_s['send'] += t2 - t1
            loop_s['spin'] += time.perf_counter() - t2
        flood_s = time.monotonic() - started_s
        rss_end = {name: rss_mb(p.pid) for name, p in procs.items()}
        alive = {name: p.poll() is None for name, p in procs.items()}
        executor.remove_node(hostile)
        hostile.destroy_node()
        time.sleep(args.settle)
        rss_settled = {name: rss_mb(p.pid) for name, p in procs.items()}
        alive_after = {name: p.poll() is None for name, p in procs.items()}
    finally:
        stop_nodes(procs)
        stop.set()
        try:
            seen = results.get(timeout=30.0)
        except queue.Empty:
            seen = {}
        observer.join(timeout=10.0)
        executor.shutdown()
        rclpy.try_shutdown(context=flood_context)
    intruders = {name: message for name, message in seen.get('errors', {}).items()
                 if '/peer/' in name}
    final = seen.get('latest', {})
    growth = {name: max(rss_end[name], rss_settled[name]) - rss_before[name] for name in procs}
    report.update(flood_s=flood_s, sent=dict(flood.sent), sent_total=sum(flood.sent.values()),
                  publish_s={k: round(v, 3) for k, v in flood.publish_s.items()},
                  loop_s={k: round(v, 3) for k, v in loop_s.items()},
                  nodes_alive_at_flood_end=alive, nodes_alive_after_settling=alive_after,
                  rss_before_mb=rss_before, rss_flood_end_mb=rss_end,
                  rss_settled_mb=rss_settled, rss_growth_mb=growth,
                  intruders_reported=intruders,
                  mpc_rejections={k: v for k, v in final.get('mshoot/mpc', {}).items()
                                  if k.startswith('rejected')})
    if seen:
        report.update(evaluate(seen))
    (out / 'hostile.json').write_text(json.dumps(report, indent=2, default=str) + '\n')
    print_report(report)
    ok = (all(alive.values()) and all(alive_after.values())
          and report.get('applied_sources', {}).get('setpoint') == report.get('steps')
          and report.get('applied_other', 1) == 0
          and report.get('planned_from_injected_state', 1) == 0
          and report.get('invalid_setpoints', 1) == 0
          and max(growth.values()) <= args.max_growth_mb)
    return 0 if ok else 1


def print_report(r: dict[str, Any]) -> None:
    print(f"[hostile] flood: {r['sent_total']} messages in {r['flood_s']:.1f} s "
          f"({r['sent_total'] / max(r['flood_s'], 1e-9):.0f}/s): {r['sent']}")
    if 'steps' in r:
        print(f"[hostile] steps: {r['steps']}; the emulator applied the MPC's setpoint on "
              f"{r['applied_mpc_setpoint']}, something else on {r['applied_other']}, not "
              f"observed {r['not_observed']} (the emulator's own count: {r['applied_sources']})")
        print('[hostile] steps planned from an injected state: '
              f"{r['planned_from_injected_state']}; invalid setpoints published by the MPC: "
              f"{r['invalid_setpoints']} of {r['mpc_setpoints']}")
        print(f"[hostile] rejected by the emulator: {r['rejected_by_emulator']}; by the MPC: "
              f"{r['mpc_rejections']}")
    else:
        print('[hostile] nothing observed')
    print(f"[hostile] nodes alive at the end of the flood: {r['nodes_alive_at_flood_end']}, "
          f"after settling: {r['nodes_alive_after_settling']}")
    print('[hostile] intruders reported on /diagnostics: '
          + ('; '.join(f'{k}: {v}' for k, v in r['intruders_reported'].items()) or 'none'))
    for name in r['rss_growth_mb']:
        print(f"[hostile] RSS {name}: {r['rss_before_mb'][name]:.1f} MB before, "
              f"{r['rss_flood_end_mb'][name]:.1f} at the flood's end, "
              f"{r['rss_settled_mb'][name]:.1f} after settling: growth "
              f"{r['rss_growth_mb'][name]:+.1f} MB")


if __name__ == '__main__':
    sys.exit(main())
