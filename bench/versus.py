"""
Versus: mshoot next to a CasADi/IPOPT multiple-shooting implementation of the same cases.

    python bench/versus.py [--repeats 5] [--zones 10 50 100 300] [--horizons 24] \
        [--horizon-zones 100] [--zone-steps 6] [--data PATH]

In one run (issue 16, part 1):

1. the reference case (OU44, 1 zone, H = 10 h, 72 h, FMU control model at its
   default tolerance) as a whole command, ours (``mshoot case``, the console
   script as a user runs it; SLSQP by default, and with ``--solver ipopt``) and
   ``bench/casadi_ref.py`` (RK4, exact derivatives, IPOPT) with ``--plot``: the
   same outputs as ours (KPIs, steps, the same figure, which the script draws
   in its process after the loop and ours in its plot worker meanwhile), each run
   ``--repeats`` times as a subprocess, interleaved, medians of wall and CPU
   time (CPU: the process and those it waited for, e.g. our plot worker); the
   CasADi script also with our IPOPT options
   (:data:`mshoot_core.solvers.IPOPT_DEFAULT_OPTIONS`), the peer of ours with
   ``--solver ipopt``; with the control loop, the median solve, the iterations
   and the KPIs of all (so a reader sees they solve the same problem);
2. the Z-zone scale problem of ``bench/scale.py`` (Z independent R1C1 zones,
   IPOPT) at Z = 10, 50, 100, 300 and H = 10 h, and at Z = 100 with H = 24 h,
   ours next to CasADi's formulation of the same zones (with IPOPT's defaults
   and with our IPOPT options), the loops stepping in turn: build, cold first
   solve, warm median per step (wall and CPU time), iterations, and the
   exponents of the time per step in Z and in H (least squares on the logs);
3. where the time of both whole commands goes: interpreter, imports, data,
   models, solves (ours: model evaluations vs glue; CasADi: its function
   evaluations vs IPOPT), plant, output, by timers (wall and CPU) wrapped
   around the functions of an instrumented run that starts as ``mshoot case``
   does (medians of ``--repeats``), the imports
   per package (``python -X importtime``), and a cProfile run of ours for
   the top functions inside the solves.

Prints the tables with ratios ours/CasADi and writes ``out/bench/versus.json``.
Needs ``casadi`` (``make bench-setup`` installs ``bench/requirements.txt``); ours runs CasADi's
IPOPT build too (``MSHOOT_IPOPT_BUILD``, default here ``casadi``).
"""
from __future__ import annotations

import argparse
import cProfile
import csv
import functools
import importlib
import importlib.util
import json
import os
import pathlib
import pstats
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any, Callable, Sequence

#: Ours runs IPOPT from CasADi's wheel, the build the CasADi script runs (same IPOPT, same MUMPS,
#: same options: the comparison is of the formulations); ``MSHOOT_IPOPT_BUILD=bundled`` measures
#: the build cyipopt bundles, the product's default (mshoot_core.solvers.import_cyipopt).
os.environ.setdefault('MSHOOT_IPOPT_BUILD', 'casadi')

#: The module of the case command (``mshoot case``): the instrumented breakdown times its
#: ``reference_scenario``, ``control_model``, ``run_case`` and ``write_outputs``.
CASE_MODULE = 'mshoot_studies.case'
BENCH = pathlib.Path(__file__).resolve().parent
ROOT = BENCH.parent
CASADI_SCRIPT = BENCH / 'casadi_ref.py'
HORIZON = 10


#: The OU44 measurements (``--data``; default ``../shared/data/ou44`` from the project root).
DATA = ROOT / '..' / 'shared' / 'data' / 'ou44' / 'measurements.csv'


def data_file() -> pathlib.Path:
    """Return the OU44 measurements (:data:`DATA`)."""
    path = pathlib.Path(DATA).resolve()
    if not path.is_file():
        raise SystemExit(f'benchmark data missing: {path}')
    return path


def case_arguments(out: pathlib.Path, *extra: str) -> list[str]:
    """Return our case command's arguments (the issue's command line), after ``mshoot case``."""
    return ['ou44', '--data', str(data_file()), '--horizon', str(HORIZON), '--control', 'fmu',
            '--out', str(out), *extra]


def mshoot_script() -> str:
    """Return the workspace's ``mshoot`` console script (``source env.sh`` puts it on PATH)."""
    path = shutil.which('mshoot')
    if path is None:
        raise SystemExit('mshoot not on PATH: source env.sh')
    return path


def ours_command(out: pathlib.Path, *extra: str, python_flags: Sequence[str] = ()) -> list[str]:
    """
    Return our whole command of the reference case, ``mshoot case ou44 ...``.

    As a user types it: the console script run by the interpreter, so that ``python_flags`` apply.
    """
    return [sys.executable, *python_flags, mshoot_script(), 'case', *case_arguments(out, *extra)]


def casadi_command(out: pathlib.Path, python_flags: Sequence[str] = (),
                   ipopt_options: dict | None = None, plot: bool = False) -> list[str]:
    """
    Return the CasADi script of the same case (IPOPT's defaults, or ``ipopt_options``).

    ``plot``: it draws our command's figure too (``--plot``: the same outputs as ours).
    """
    return [sys.executable, *python_flags, str(CASADI_SCRIPT), '--data', str(data_file()),
            '--horizon', str(HORIZON), '--out', str(out), *(['--plot'] if plot else []),
            *(f'--ipopt-option={key}={value}' for key, value in (ipopt_options or {}).items())]


def case_ipopt_options() -> dict:
    """Return the IPOPT options of ``mshoot case ... --solver ipopt`` beyond IPOPT's defaults."""
    from mshoot_core.solvers import IPOPT_DEFAULT_OPTIONS
    return dict(IPOPT_DEFAULT_OPTIONS)


def run_timed(command: list[str]) -> tuple[float, str, float, float, float]:
    """
    Run a subprocess (which must succeed) and time it.

    Return its wall time [s], its stderr, its launch and exit times (epoch [s]), and its CPU time
    [s] (user + system, with the processes it waited for, e.g. our plot worker).
    """
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    launched = time.time()
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - started
    exited = time.time()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode:
        raise SystemExit(f'{" ".join(command)} failed ({done.returncode}):\n{done.stderr}')
    return wall, done.stderr, launched, exited, cpu


# -- the instrumented run of our command (a subprocess of its own) --------------------------------
class Timers:
    """
    Wall-time and CPU-time totals [s] and call counts of wrapped functions, by group.

    The CPU time is the process's.

    Nested calls within one group count once (the outermost call), so a batch
    function calling another batch function is not counted twice.
    """

    def __init__(self) -> None:
        self.total: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._depth: dict[str, int] = {}

    def wrap(self, group: str, function: Callable) -> Callable:
        self.total.setdefault(group, 0.0)
        self.cpu.setdefault(group, 0.0)
        self.calls.setdefault(group, 0)
        self._depth.setdefault(group, 0)

        @functools.wraps(function)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._depth[group]:
                return function(*args, **kwargs)
            self._depth[group] += 1
            started, cpu = time.perf_counter(), time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                self.total[group] += time.perf_counter() - started
                self.cpu[group] += time.process_time() - cpu
                self.calls[group] += 1
                self._depth[group] -= 1
        return timed

    def patch(self, owner: Any, name: str, group: str) -> bool:
        """Replace ``owner.name`` by its timed version; False if ``owner`` has no ``name``."""
        function = getattr(owner, name, None)
        if function is None:
            return False
        setattr(owner, name, self.wrap(group, function))
        return True


def timed_drivers(timers: Timers) -> None:
    """
    Time the compiled batch drivers' C entry points (native integration).

    Each driver's ``_batch`` (the ctypes function of ``mshoot_cs_batch`` / ``mshoot_me_batch``) is
    wrapped when the driver is bound, so 'native' is the C call alone, without the Python argument
    preparation of ``run``.
    """
    from mshoot_core.models import fmi_drivers
    for cls in (fmi_drivers.CsBatchDriver, fmi_drivers.MeBatchDriver):
        init = cls.__init__

        def bound(self: Any, *args: Any, _init: Callable = init, **kwargs: Any) -> None:
            _init(self, *args, **kwargs)
            self._batch = timers.wrap('native', self._batch)
        cls.__init__ = bound


def batch_classes() -> list[type]:
    """Return the interval-batch classes whose ``jacobians`` evaluate a model's batch."""
    classes = []
    for module, name in (('mshoot_core.models.base', 'IntervalBatch'),
                         ('mshoot_core.models.fmi_sensitivities', '_DriverBatch')):
        cls = getattr(importlib.import_module(module), name, None)
        if cls is not None:
            classes.append(cls)
    return classes


def instrumented_case(argv: list[str], report: pathlib.Path, profile: bool) -> int:
    """
    Run our case command as ``mshoot case`` runs it, with timers or cProfile.

    As ``mshoot case`` runs it: its verb environment, its plot worker started first,
    ``mshoot_studies.cli.main``, the fast exit; with timers (or with cProfile on inside the
    solves). Write the figures to ``report``.
    """
    script_start_epoch = time.time()
    # as the mshoot command starts: its environment for the verb, its plot worker first
    started = time.perf_counter()
    cli = importlib.import_module('mshoot_studies.cli')
    for name, value in getattr(cli, 'VERB_ENVIRONMENT', {}).get('case', {}).items():
        os.environ.setdefault(name, value)
    worker = None
    if 'case' in getattr(cli, 'FIGURE_VERBS', ()):
        from mshoot_core.plotting import PlotWorker
        worker = PlotWorker()
    start_s = time.perf_counter() - started
    started, cpu = time.perf_counter(), time.process_time()
    import_verb = getattr(cli, 'import_verb', None)  # as the command imports it (no GC)
    if import_verb is not None:
        import_verb('case')
    module = importlib.import_module(CASE_MODULE)
    imports_s = time.perf_counter() - started
    imports_cpu_s = time.process_time() - cpu
    from mshoot_core.emulation import Emulator
    from mshoot_core.mpc import MPC
    started = time.perf_counter()  # (the command imports it when it builds an FMU model: here
    from mshoot_core.models import fmi  # before, to time it; counted with the models)
    fmi_import_s = time.perf_counter() - started
    timers = Timers()
    profiler = cProfile.Profile()
    if profile:
        solve = MPC.solve

        def profiled_solve(*args: Any, **kwargs: Any) -> Any:
            return profiler.runcall(solve, *args, **kwargs)
        MPC.solve = profiled_solve
        patched = {}
    else:
        patched = {name: timers.patch(module, name, group) for name, group in (
            ('reference_scenario', 'data'), ('control_model', 'models'),
            ('run_case', 'loop'), ('write_outputs', 'output'))}
        timers.patch(MPC, 'solve', 'solves')
        timers.patch(Emulator, 'advance', 'plant')
        for name in ('simulate_intervals', 'interval_jacobians',  # the FMU control model's
                     'simulate_chains'):                           # (inherited ones too)
            timers.patch(fmi.FmiModel, name, 'simulations')
        for batch in batch_classes():  # its interval batches (Model.interval_batch)
            timers.patch(batch, 'jacobians', 'simulations')
        timed_drivers(timers)
    started = time.perf_counter()
    code = (cli.main(['case', *argv], plot_worker=worker) if worker is not None
            else module.main(argv))
    main_s = time.perf_counter() - started
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    figures = {'imports_s': imports_s, 'main_s': main_s, 'code': code, 'patched': patched,
               'start_s': start_s, 'fmi_import_s': fmi_import_s,
               'total_s': timers.total, 'calls': timers.calls,
               'script_start_epoch': script_start_epoch,
               'imports_cpu_s': imports_cpu_s, 'cpu_s': timers.cpu,
               'process_cpu_s': time.process_time(),  # since the interpreter started
               'children_cpu_s': children.ru_utime + children.ru_stime}  # the plot worker
    if profile:
        figures['profile'] = profile_figures(pstats.Stats(profiler))
    figures['main_end_epoch'] = time.time()
    report.write_text(json.dumps(figures, indent=2))
    exit_now = getattr(importlib.import_module('mshoot_studies.cli'), 'exit_now', None)
    if exit_now is not None:  # end as the mshoot command does
        exit_now(code)
    return code


def profile_figures(stats: pstats.Stats, top: int = 12) -> dict:
    """
    Return the solve and batch totals and the top functions of a cProfile run.

    Totals of the solve and the model's batch functions, and the top functions by own time
    (tottime) [s].
    """
    def label(key: tuple) -> str:
        path, line, name = key
        return f'{pathlib.Path(path).name}:{line}({name})' if line else name

    batch = {'simulate_intervals', 'interval_jacobians', 'simulate_chains', 'jacobians'}
    totals = {'solves_s': 0.0, 'simulations_s': 0.0, 'simulation_calls': 0}
    rows = []
    for key, (calls, primitive, tottime, cumtime, _) in stats.stats.items():
        path, _, name = key
        if name == 'solve' and path.endswith('mpc.py'):
            totals['solves_s'] += cumtime
        if name in batch and path.endswith(('fmi.py', 'fmi_sensitivities.py', 'base.py',
                                            'r1c1.py', 'multizone.py')):
            totals['simulations_s'] += cumtime
            totals['simulation_calls'] += primitive
        rows.append((tottime, calls, cumtime, label(key)))
    rows.sort(reverse=True)
    totals['top_tottime'] = [{'function': f, 'tottime_s': t, 'calls': c, 'cumtime_s': cum}
                             for t, c, cum, f in rows[:top]]
    return totals


# -- the whole commands ---------------------------------------------------------------------------
def whole_commands(repeats: int, tmp: pathlib.Path) -> dict:
    """Both whole commands ``repeats`` times, interleaved; walls and each run's figures."""
    runs: dict[str, list] = {'ours': [], 'ours_ipopt': [], 'casadi': [], 'casadi_same': []}
    for repeat in range(repeats):
        for name, command in (('ours', ours_command(tmp / 'ours')),
                              ('ours_ipopt', ours_command(tmp / 'ours_ipopt', '--solver',
                                                          'ipopt')),
                              ('casadi', casadi_command(tmp / 'casadi', plot=True)),
                              ('casadi_same', casadi_command(
                                  tmp / 'casadi_same', ipopt_options=case_ipopt_options(),
                                  plot=True))):
            wall, _, _, _, cpu = run_timed(command)
            kpis = json.loads((tmp / name / 'kpis.json').read_text())
            with open(tmp / name / 'steps.csv', newline='') as steps:
                rows = list(csv.DictReader(steps))
            kpis['step_iterations'] = [int(row['iterations']) for row in rows]
            kpis['iterations'] = sum(kpis['step_iterations'])
            if 'relaxed' in rows[0]:  # ours: the steps whose band was out of reach
                kpis['step_relaxed'] = [row['relaxed'] == 'True' for row in rows]
            runs[name].append({'wall_s': wall, 'cpu_s': cpu, 'loop_s': kpis['wall_s'],
                               'solve_s_median': kpis['solve_s_median'],
                               'solve_s_total': kpis['solve_s_total'], 'kpis': kpis})
    summary = {}
    for name, items in runs.items():
        kpis = items[-1]['kpis']
        summary[name] = {
            'walls_s': [r['wall_s'] for r in items],
            'wall_s': statistics.median(r['wall_s'] for r in items),
            'cpus_s': [r['cpu_s'] for r in items],
            'cpu_s': statistics.median(r['cpu_s'] for r in items),
            'loop_s': statistics.median(r['loop_s'] for r in items),
            'solve_s_median': statistics.median(r['solve_s_median'] for r in items),
            'solve_s_total': statistics.median(r['solve_s_total'] for r in items),
            'iterations': kpis.get('iterations'),
            'step_iterations': kpis['step_iterations'],
            'step_relaxed': kpis.get('step_relaxed'),
            **{k: kpis[k] for k in ('energy_kwh', 'heating_kwh', 'cooling_kwh', 'discomfort_kh',
                                    'discomfort_kh_hourly', 'solver_failures')}}
    return summary


def interpreter_s(repeats: int) -> float:
    """Median wall time [s] of ``python -c pass`` (interpreter start and exit)."""
    return statistics.median(run_timed([sys.executable, '-c', 'pass'])[0]
                             for _ in range(max(repeats, 3)))


def import_packages(stderr: str, floor_s: float = 0.005) -> dict[str, float]:
    """
    Return the import time [s] per top-level package from ``-X importtime`` output.

    Own times are summed, so packages add up to the whole import time; packages under ``floor_s``
    count as 'other'.
    """
    per_package: dict[str, float] = {}
    for line in stderr.splitlines():
        if not line.startswith('import time:') or 'self [us]' in line:
            continue
        self_us, _, name = line[len('import time:'):].split('|')
        root = name.strip().split('.')[0]
        per_package[root] = per_package.get(root, 0.0) + int(self_us) * 1e-6
    packages = dict(sorted(per_package.items(), key=lambda kv: -kv[1]))
    out = {k: v for k, v in packages.items() if v >= floor_s}
    out['other'] = sum(v for v in packages.values() if v < floor_s)
    out['total'] = sum(packages.values())
    return out


def breakdown(repeats: int, tmp: pathlib.Path) -> dict:
    """
    Where the time of both whole commands goes (medians of ``repeats`` runs) [s].

    interpreter: a bare ``python -c pass`` (start and exit); start: ours, what the ``mshoot``
    command does before it imports the verb (its cli module, the plot worker's start);
    imports: ours, the import of :data:`CASE_MODULE` timed inside the run; CasADi's, from
    launch to its ``main`` less the bare interpreter; models: ours with the import of fmpy
    (``mshoot_core.models.fmi``, which the command imports when it builds the FMU model and
    the instrumented run before, to patch it); exit: from the end of ``main`` to the end of
    the process; other: the rest (argparse, the option checks, logging, and for ours the
    instrumenting driver's own imports).
    """
    python_s = interpreter_s(repeats)
    this = str(pathlib.Path(__file__).resolve())
    ours_runs, casadi_runs = [], []
    for repeat in range(repeats):
        report = tmp / f'instrumented_{repeat}.json'
        wall, _, _, exited, _ = run_timed([sys.executable, this, '--instrument', str(report),
                                           '--', *case_arguments(tmp / 'instrumented')])
        figures = json.loads(report.read_text())
        missing = [name for name, ok in figures['patched'].items() if not ok]
        if missing:
            raise SystemExit(f'{CASE_MODULE} has no {missing}: update instrumented_case()')
        t, c = figures['total_s'], figures['calls']
        run = {'total': wall, 'interpreter': python_s, 'start': figures.get('start_s', 0.0),
               'imports': figures['imports_s'], 'data': t['data'],
               'models': t['models'] + figures.get('fmi_import_s', 0.0), 'loop': t['loop'],
               'solves': t['solves'], 'simulations': t['simulations'],
               'native': t.get('native', 0.0),
               'glue': t['solves'] - t['simulations'], 'plant': t['plant'],
               'loop_other': t['loop'] - t['solves'] - t['plant'], 'output': t['output'],
               'exit': exited - figures['main_end_epoch'],
               'simulation_calls': c['simulations'], 'solve_calls': c['solves']}
        run['other'] = wall - sum(run[k] for k in ('interpreter', 'start', 'imports', 'data',
                                                   'models', 'loop', 'output', 'exit'))
        t = figures['cpu_s']
        cpu = {'imports': figures['imports_cpu_s'], 'data': t['data'], 'models': t['models'],
               'loop': t['loop'], 'solves': t['solves'], 'simulations': t['simulations'],
               'native': t.get('native', 0.0), 'glue': t['solves'] - t['simulations'],
               'plant': t['plant'], 'loop_other': t['loop'] - t['solves'] - t['plant'],
               'output': t['output'], 'main_process': figures['process_cpu_s'],
               'plot_worker': figures['children_cpu_s']}
        cpu['other'] = cpu['main_process'] - sum(cpu[k] for k in ('imports', 'data', 'models',
                                                                  'loop', 'output'))
        run.update({f'cpu_{key}': value for key, value in cpu.items()})
        ours_runs.append(run)
        wall, _, launched, exited, _ = run_timed(casadi_command(tmp / 'casadi_instrumented'))
        t = json.loads((tmp / 'casadi_instrumented' / 'kpis.json').read_text())['timing']
        run = {'total': wall, 'interpreter': python_s, 'start': 0.0,
               'imports': t['main_start_epoch'] - launched - python_s, 'data': t['data_s'],
               'models': t['build_s'], 'loop': t['loop_s'] + t['kpis_s'],
               'solves': t['solves_s'], 'simulations': t['function_evaluations_s'],
               'glue': t['solves_s'] - t['function_evaluations_s'], 'plant': t['plant_s'],
               'loop_other': t['loop_s'] + t['kpis_s'] - t['solves_s'] - t['plant_s'],
               'output': t['output_s'], 'exit': exited - t['main_end_epoch']}
        run['other'] = wall - sum(run[k] for k in ('interpreter', 'imports', 'data', 'models',
                                                   'loop', 'output', 'exit'))
        cpu = {'imports': t['main_start_cpu_s'], 'data': t['data_cpu_s'],
               'models': t['build_cpu_s'], 'loop': t['loop_cpu_s'] + t['kpis_cpu_s'],
               'solves': t['solves_cpu_s'], 'glue': t['solves_cpu_s'],
               'plant': t['plant_cpu_s'],
               'loop_other': t['loop_cpu_s'] + t['kpis_cpu_s'] - t['solves_cpu_s']
               - t['plant_cpu_s'], 'output': t['output_cpu_s'],
               'main_process': t['main_end_cpu_s'], 'plot_worker': 0.0}
        cpu['other'] = cpu['main_process'] - sum(cpu[k] for k in ('imports', 'data', 'models',
                                                                  'loop', 'output'))
        run.update({f'cpu_{key}': value for key, value in cpu.items()})
        casadi_runs.append(run)
    result = {name: {key: statistics.median(run[key] for run in runs) for key in runs[0]}
              for name, runs in (('ours', ours_runs), ('casadi', casadi_runs))}
    ours = result['ours']
    ours['glue_per_simulation_call_us'] = ours['glue'] / max(ours['simulation_calls'], 1) * 1e6
    # imports per package, over the whole run (lazy imports included: fmpy, matplotlib, ...)
    stderr = run_timed(ours_command(tmp / 'importtime', python_flags=('-X', 'importtime')))[1]
    result['ours_imports_by_package'] = import_packages(stderr)
    stderr = run_timed(casadi_command(tmp / 'importtime_casadi',
                                      python_flags=('-X', 'importtime')))[1]
    result['casadi_imports_by_package'] = import_packages(stderr)
    # cProfile of ours inside the solves: totals of the batch functions, the top functions
    report = tmp / 'profiled.json'
    run_timed([sys.executable, this, '--instrument', str(report), '--profile', '--',
               *case_arguments(tmp / 'profiled')])
    result['ours_cprofile'] = json.loads(report.read_text())['profile']
    return result


# -- the Z-zone scale problem (in this process) ---------------------------------------------------
def zone_figures(controls_w: list, states_k: list, scenario: Any, kelvin: float) -> dict:
    """Energy [kWh] of the applied heat rates and discomfort [Kh] of the hourly end states."""
    import numpy as np
    q = np.array(controls_w)
    x = np.array(states_k) - kelvin
    rows = np.arange(1, len(x) + 1)
    lower = scenario['comfort_min'].to_numpy()[rows][:, None]
    upper = scenario['comfort_max'].to_numpy()[rows][:, None]
    violation = np.maximum(lower - x, 0.0) + np.maximum(x - upper, 0.0)
    return {'energy_kwh': float(np.abs(q).sum() / 1000.0),
            'discomfort_kh': float(violation.sum())}


class ZoneLoop:
    """
    A closed loop on the scale problem, one MPC step at a time, with its records.

    Subclasses set ``build_s`` and ``variables`` and implement :meth:`solve`; the plant is
    the exact multi-zone model (``MultiZoneModel.simulate_intervals``), as in ``scale.py``.
    """

    def __init__(self, n_zones: int, steps: int, horizon: int = HORIZON) -> None:
        from scale import zone_case
        self.horizon = horizon
        self.model, self.mpc, self.scenario, self.x = zone_case(n_zones, horizon, 'ipopt',
                                                                steps + 1)
        self.times_s: list[float] = []
        self.cpus_s: list[float] = []
        self.model_s: list[float] = []
        self.solver_cpu_s: list[float] = []
        self.iterations: list[int] = []
        self.failures = 0
        self.controls_w: list = []
        self.states_k: list = []

    def solve(self, k: int) -> tuple[Any, int, bool, float, float]:
        """
        Plan step k from ``self.x``.

        Return the applied heat rates [W] (Z,), the iterations, success, the model or function
        evaluation time [s] and the CPU time of the NLP solver's call less that of the
        evaluations [s] (ours: ``IpoptSolver.solve`` less the model's batch calls, so that our
        callbacks count with IPOPT; CasADi's: ``CasadiMpc.solve`` less its ``t_proc``
        evaluation times).
        """
        raise NotImplementedError

    def step(self, k: int) -> None:
        import numpy as np
        started, cpu = time.perf_counter(), time.process_time()
        q, iterations, success, model_s, solver_cpu_s = self.solve(k)
        self.times_s.append(time.perf_counter() - started)
        self.cpus_s.append(time.process_time() - cpu)
        self.model_s.append(model_s)
        self.solver_cpu_s.append(solver_cpu_s)
        self.iterations.append(iterations)
        self.failures += not success
        inputs = np.concatenate([self.scenario[['solrad', 'Tout', 'occ', 'dpos']].to_numpy(
            dtype=float)[k], q])[None, :]
        self.x = self.model.simulate_intervals(self.x[None, :], inputs, 3600.0)[0][0]
        self.controls_w.append(q)
        self.states_k.append(self.x)

    def summary(self) -> dict:
        import numpy as np
        from mshoot_core.units import KELVIN
        return {'variables': self.variables, 'build_s': self.build_s,
                'first_s': self.times_s[0], 'warm_s': float(np.median(self.times_s[1:])),
                'warm_cpu_s': float(np.median(self.cpus_s[1:])), 'cpus_s': self.cpus_s,
                'iterations': float(np.mean(self.iterations[1:])),
                'model_warm_s': float(np.median(self.model_s[1:])),
                # IPOPT itself per iteration (CPU; ours with our callbacks' glue)
                'solver_cpu_per_iteration_s': float(np.median(
                    [s / max(i, 1) for s, i in zip(self.solver_cpu_s[1:], self.iterations[1:])])),
                'failures': self.failures, 'times_s': self.times_s,
                **zone_figures(self.controls_w, self.states_k, self.scenario, KELVIN)}


class OurZones(ZoneLoop):
    """Ours: ``bench/scale.py``'s MPC (IPOPT); model time = our model's batch functions."""

    def __init__(self, n_zones: int, steps: int, horizon: int = HORIZON) -> None:
        started = time.perf_counter()
        super().__init__(n_zones, steps, horizon)
        self.build_s = time.perf_counter() - started
        self.variables = self.mpc.problem.index.size
        self.timers = Timers()
        self._plant = self.model.simulate_intervals
        for name in ('simulate_intervals', 'interval_jacobians'):  # on the instance only
            setattr(self.model, name, self.timers.wrap('simulations', getattr(self.model,
                                                                              name)))
        interval_batch = self.model.interval_batch

        def timed_batch(*args: Any, **kwargs: Any) -> Any:  # its batches' evaluations too
            batch = interval_batch(*args, **kwargs)
            batch.jacobians = self.timers.wrap('simulations', batch.jacobians)
            return batch
        self.model.interval_batch = timed_batch
        solver = self.mpc.solver  # (the instance's: the class's method stays untimed)
        solver.solve = self.timers.wrap('solver', solver.solve)

    def solve(self, k: int) -> tuple[Any, int, bool, float, float]:
        from mshoot_core.scenario import forecast_window
        cpu = self.timers.cpu
        before = self.timers.total['simulations']
        cpu_before = cpu['solver'] - cpu['simulations']
        result = self.mpc.solve(self.x, self.scenario.index[k],
                                forecast_window(self.scenario, k, self.horizon))
        model_s = self.timers.total['simulations'] - before
        return (result.controls[0], result.nit, result.success, model_s,
                cpu['solver'] - cpu['simulations'] - cpu_before)

    def step(self, k: int) -> None:
        timed, self.model.simulate_intervals = self.model.simulate_intervals, self._plant
        try:
            super().step(k)  # the plant's simulation is not the MPC's
        finally:
            self.model.simulate_intervals = timed

    def profile_step(self, k: int) -> list[dict]:
        """Profile one more (warm) step with cProfile: the top functions by own time."""
        from mshoot_core.scenario import forecast_window
        profiler = cProfile.Profile()
        profiler.runcall(self.mpc.solve, self.x, self.scenario.index[k],
                         forecast_window(self.scenario, k, self.horizon))
        return profile_figures(pstats.Stats(profiler))['top_tottime']


def our_ipopt_options(mpc: Any) -> dict:
    """
    Return the IPOPT options our scale problem runs with, in CasADi's spelling.

    The solver's own (``IpoptSolver``: adaptive barrier update) and ``multizone_mpc_options``'
    (Mehrotra).
    """
    from mshoot_core.solvers import IPOPT_DEFAULT_OPTIONS
    return {f'ipopt.{key}': value
            for key, value in {**IPOPT_DEFAULT_OPTIONS, **mpc.solver.options}.items()}


class CasadiZones(ZoneLoop):
    """
    CasADi's formulation of the same zones, scenario, band and initial state.

    With IPOPT's defaults, or (``tuned``) with our IPOPT options; model time = its function
    evaluations.
    """

    def __init__(self, n_zones: int, steps: int, tuned: bool, horizon: int = HORIZON) -> None:
        from casadi_ref import CasadiMpc, ZoneParameters
        super().__init__(n_zones, steps, horizon)
        self.ipopt_options = our_ipopt_options(self.mpc) if tuned else {}
        started = time.perf_counter()
        self.casadi = CasadiMpc(ZoneParameters.from_multizone(self.model), horizon,
                                ipopt_options=self.ipopt_options)
        self.build_s = time.perf_counter() - started
        self.variables = 3 * n_zones * horizon
        self.disturbances = self.scenario[['solrad', 'Tout', 'occ', 'dpos']].to_numpy(float)
        self.band = self.scenario[['comfort_min', 'comfort_max']].to_numpy(dtype=float)

    def solve(self, k: int) -> tuple[Any, int, bool, float, float]:
        import numpy as np
        from casadi_ref import function_time_s
        from mshoot_core.units import KELVIN
        rows = np.arange(k, k + self.horizon + 1)
        zones = self.x.size
        started = time.process_time()
        plan = self.casadi.solve(self.x - KELVIN, self.disturbances[rows[:-1]],
                                 np.repeat(self.band[rows[1:], :1], zones, axis=1),
                                 np.repeat(self.band[rows[1:], 1:], zones, axis=1))
        return (plan['q'][0], plan['iterations'], plan['success'],
                function_time_s(plan['stats']),
                time.process_time() - started - function_time_s(plan['stats'], clock='proc'))


def zone_rows(cases: Sequence[tuple[int, int]], steps: int) -> list[dict]:
    """
    Return one row per case (Z zones, horizon H [h]): ours and CasADi's with both options.

    Each row holds build, cold first solve, warm median per step, iterations and model time of
    ours, CasADi with IPOPT's defaults ('casadi') and with our IPOPT options ('casadi_tuned'); the
    three loops step in turn, so load on the machine hits them alike.
    """
    import warnings

    import numpy as np
    for loop in (OurZones(1, 1), CasadiZones(1, 1, tuned=False)):  # one-time imports, plugins
        loop.step(0)
    rows = []
    largest = max(cases)
    for n_zones, horizon in cases:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter('always')
            loops = {'ours': OurZones(n_zones, steps, horizon),
                     'casadi': CasadiZones(n_zones, steps, tuned=False, horizon=horizon),
                     'casadi_tuned': CasadiZones(n_zones, steps, tuned=True, horizon=horizon)}
            for k in range(steps):
                for loop in loops.values():
                    loop.step(k)
            profile = (loops['ours'].profile_step(steps) if (n_zones, horizon) == largest
                       else [])
        row = {'zones': n_zones, 'horizon_h': horizon, 'steps': steps,
               'casadi_tuned_ipopt_options': loops['casadi_tuned'].ipopt_options,
               'ours_profile_top': profile,
               'ours_warnings': sorted({f'{w.category.__name__} at '
                                        f'{pathlib.Path(w.filename).name}:{w.lineno}: '
                                        f'{str(w.message).split(".")[0]}' for w in caught})}
        for name, loop in loops.items():
            row.update({f'{name}_{key}': value for key, value in loop.summary().items()})
            if name != 'ours':
                row[f'{name}_first_step_max_dq_w'] = float(np.max(np.abs(
                    loops['ours'].controls_w[0] - loop.controls_w[0])))
                row[f'{name}_warm_ratio'] = row['ours_warm_s'] / row[f'{name}_warm_s']
                row[f'{name}_warm_cpu_ratio'] = (row['ours_warm_cpu_s']
                                                 / row[f'{name}_warm_cpu_s'])
                row[f'{name}_first_ratio'] = row['ours_first_s'] / row[f'{name}_first_s']
        rows.append(row)
    return rows


def growth_exponents(rows: list[dict]) -> list[dict]:
    """
    Return how the warm time per step grows: the exponent p of time ~ Z^p (at each H) and H^p.

    One row per (what, at, loop), for ours and both CasADi options, wall and CPU time: p from
    a least-squares line through log(time) against log(Z) at each horizon with two or more zone
    counts (Z > 1), and against log(H) at each zone count with two or more horizons.
    """
    import numpy as np
    out = []
    for what, key, other in (('Z', 'zones', 'horizon_h'), ('H', 'horizon_h', 'zones')):
        for at in sorted({row[other] for row in rows}):
            chosen = sorted((row for row in rows if row[other] == at and row['zones'] > 1),
                            key=lambda row: row[key])
            if len({row[key] for row in chosen}) < 2:
                continue
            sizes = np.log([row[key] for row in chosen])
            fitted = {'what': what, 'at': f'{"H" if what == "Z" else "Z"} = {at}',
                      'points': ' '.join(str(row[key]) for row in chosen)}
            for loop in ('ours', 'casadi', 'casadi_tuned'):
                for time_key, label in (('warm_s', ''), ('warm_cpu_s', '_cpu')):
                    fitted[f'{loop}{label}'] = float(np.polyfit(
                        sizes, np.log([row[f'{loop}_{time_key}'] for row in chosen]), 1)[0])
            out.append(fitted)
    return out


# -- report ---------------------------------------------------------------------------------------
def report(whole: dict, zones: list[dict], growth: list[dict], parts: dict) -> None:
    from common import logger, print_table
    ours, ipopt, theirs = whole['ours'], whole['ours_ipopt'], whole['casadi']
    same = whole['casadi_same']
    logger.info('\n== 1 zone, H = %d h, 72 h (OU44): whole command and control loop, medians '
                'of %d runs ==', HORIZON, len(ours['walls_s']))
    logger.info("casadi: IPOPT's defaults; casadi same: with our IPOPT options (%s); ratio: "
                'ours (slsqp) / casadi; ratio ipopt: ours (ipopt) / casadi same; every command '
                'writes the KPIs, the steps and the same figure (casadi: --plot, drawn after '
                'its loop; ours: in its plot worker meanwhile)',
                ', '.join(f'{k}={v}' for k, v in case_ipopt_options().items()))
    width = 24
    logger.info('%s %14s %14s %14s %14s %10s %11s', 'what'.ljust(width), 'ours (slsqp)',
                'ours (ipopt)', 'casadi', 'casadi same', 'ratio', 'ratio ipopt')
    for label, key, fmt, scale, ratio in (
            ('whole command [s]', 'wall_s', '.3f', 1.0, True),
            ('  its CPU time [s]', 'cpu_s', '.3f', 1.0, True),
            ('control loop [s]', 'loop_s', '.3f', 1.0, True),
            ('solves, total [s]', 'solve_s_total', '.3f', 1.0, True),
            ('median solve [ms]', 'solve_s_median', '.2f', 1e3, True),
            ('IPOPT/SLSQP iterations', 'iterations', '', None, False),
            ('energy [kWh]', 'energy_kwh', '.3f', 1.0, False),
            ('discomfort [Kh]', 'discomfort_kh', '.3f', 1.0, False),
            ('discomfort hourly [Kh]', 'discomfort_kh_hourly', '.3f', 1.0, False),
            ('solver failures', 'solver_failures', '', None, False)):
        cells = ['-' if run.get(key) is None else
                 format(run[key] if scale is None else run[key] * scale, fmt)
                 for run in (ours, ipopt, theirs, same)]
        ratios = [f'{run[key] / peer[key]:.2f}' if ratio else ''
                  for run, peer in ((ours, theirs), (ipopt, same))]
        logger.info('%s %14s %14s %14s %14s %10s %11s', label.ljust(width), *cells, *ratios)
    relaxed = ipopt.get('step_relaxed')
    if relaxed and len(relaxed) == len(same['step_iterations']):
        for label, chosen in (('band out of reach (ours relaxed)', True), ('band kept', False)):
            picked = [k for k, r in enumerate(relaxed) if r == chosen]
            logger.info('IPOPT iterations in the %d steps with the %s: ours (ipopt) %d, casadi '
                        'same %d', len(picked), label,
                        sum(ipopt['step_iterations'][k] for k in picked),
                        sum(same['step_iterations'][k] for k in picked))
    for key, what in (('walls_s', 'wall'), ('cpus_s', 'CPU')):
        logger.info('whole command, ratio of each run (%s; runs interleaved): slsqp/casadi %s, '
                    'ipopt/casadi same %s', what,
                    ' '.join(f'{a / b:.2f}' for a, b in zip(ours[key], theirs[key])),
                    ' '.join(f'{a / b:.2f}' for a, b in zip(ipopt[key], same[key])))

    logger.info('\n== Z zones, H hours, IPOPT: seconds per MPC step (first: cold; warm: '
                'median of the others) ==')
    print_table(zones, [('zones', 'Z', 'd'), ('horizon_h', 'H', 'd'),
                        ('ours_build_s', 'ours build', '.3f'),
                        ('ours_first_s', 'ours first', '.3f'),
                        ('ours_warm_s', 'ours warm', '.3f'),
                        ('ours_iterations', 'ours iters', '.1f'),
                        ('ours_model_warm_s', 'ours model', '.3f'),
                        ('casadi_build_s', 'casadi build', '.3f'),
                        ('casadi_first_s', 'casadi first', '.3f'),
                        ('casadi_warm_s', 'casadi warm', '.3f'),
                        ('casadi_iterations', 'casadi iters', '.1f'),
                        ('casadi_model_warm_s', 'casadi evals', '.3f'),
                        ('casadi_first_ratio', 'ratio first', '.2f'),
                        ('casadi_warm_ratio', 'ratio warm', '.2f')])
    logger.info('the same, CPU time per warm step (the process, all threads; less sensitive to '
                'other load on the machine than the wall time) [s]:')
    print_table(zones, [('zones', 'Z', 'd'), ('horizon_h', 'H', 'd'),
                        ('ours_warm_cpu_s', 'ours cpu', '.3f'),
                        ('casadi_warm_cpu_s', 'casadi cpu', '.3f'),
                        ('casadi_warm_cpu_ratio', 'ratio cpu', '.2f'),
                        ('casadi_tuned_warm_cpu_s', 'tuned cpu', '.3f'),
                        ('casadi_tuned_warm_cpu_ratio', 'ratio tuned cpu', '.2f')])
    logger.info('CasADi with our IPOPT options (%s):', ', '.join(
        f'{k}={v}' for k, v in zones[0]['casadi_tuned_ipopt_options'].items()))
    print_table(zones, [('zones', 'Z', 'd'), ('horizon_h', 'H', 'd'),
                        ('ours_iterations', 'ours iters', '.1f'),
                        ('casadi_tuned_first_s', 'tuned first', '.3f'),
                        ('casadi_tuned_warm_s', 'tuned warm', '.3f'),
                        ('casadi_tuned_iterations', 'tuned iters', '.1f'),
                        ('casadi_tuned_model_warm_s', 'tuned evals', '.3f'),
                        ('casadi_tuned_first_ratio', 'ratio first', '.2f'),
                        ('casadi_tuned_warm_ratio', 'ratio warm', '.2f'),
                        ('casadi_tuned_warm_cpu_ratio', 'ratio cpu', '.2f')])
    logger.info('IPOPT itself per iteration of a warm step, CPU [ms]: the solver call less the '
                'evaluations (ours: IpoptSolver.solve less the model, our callbacks counted '
                "with IPOPT; CasADi's: CasadiMpc.solve less its function evaluations):")
    print_table([{**row, **{key: row[key] * 1e3 for key in (
        'ours_solver_cpu_per_iteration_s', 'casadi_tuned_solver_cpu_per_iteration_s')}}
        for row in zones],
        [('zones', 'Z', 'd'), ('horizon_h', 'H', 'd'),
         ('ours_solver_cpu_per_iteration_s', 'ours', '.2f'),
         ('casadi_tuned_solver_cpu_per_iteration_s', 'casadi same', '.2f'),
         ('ours_iterations', 'ours iters', '.1f'),
         ('casadi_tuned_iterations', 'casadi same iters', '.1f')])
    if growth:
        logger.info('growth of the warm time per step: exponent p of time ~ Z^p or H^p '
                    '(least squares on the logs; wall, and cpu):')
        print_table(growth, [('what', 'in', 's'), ('at', 'at', 's'), ('points', 'points', 's'),
                             ('ours', 'ours', '.2f'), ('ours_cpu', 'ours cpu', '.2f'),
                             ('casadi', 'casadi', '.2f'), ('casadi_cpu', 'casadi cpu', '.2f'),
                             ('casadi_tuned', 'tuned', '.2f'),
                             ('casadi_tuned_cpu', 'tuned cpu', '.2f')])
    logger.info('the same problem: energy of the applied heat rates [kWh], discomfort of the '
                'hourly states [Kh], largest difference of the first applied heat rates [W]')
    print_table(zones, [('zones', 'Z', 'd'), ('horizon_h', 'H', 'd'),
                        ('ours_energy_kwh', 'ours kWh', '.2f'),
                        ('casadi_energy_kwh', 'casadi kWh', '.2f'),
                        ('casadi_tuned_energy_kwh', 'tuned kWh', '.2f'),
                        ('ours_discomfort_kh', 'ours Kh', '.3f'),
                        ('casadi_discomfort_kh', 'casadi Kh', '.3f'),
                        ('casadi_first_step_max_dq_w', 'max dq0 [W]', '.3f'),
                        ('ours_failures', 'ours fails', 'd'),
                        ('casadi_failures', 'casadi fails', 'd'),
                        ('casadi_tuned_failures', 'tuned fails', 'd')])

    logger.info("'model' / 'evals': time per warm step in our model's batch functions / in "
                "CasADi's function and derivative evaluations [s]")
    for row in zones:
        for warning in row['ours_warnings']:
            logger.info('ours, Z = %d: %s', row['zones'], warning)
    largest = max(zones, key=lambda row: (row['zones'], row['horizon_h']))
    if largest['ours_profile_top']:
        logger.info('cProfile of one warm step of ours at Z = %d, H = %d, top own times:',
                    largest['zones'], largest['horizon_h'])
        for item in largest['ours_profile_top'][:10]:
            logger.info('  %8.3f s %8d calls  %s', item['tottime_s'], item['calls'],
                        item['function'])

    ours_b, theirs_b = parts['ours'], parts['casadi']
    logger.info('\n== Where the whole command goes (1 zone, H = %d h, 72 h; medians) [s] ==',
                HORIZON)
    lines = (('interpreter start + exit', 'interpreter', ''),
             ('command start (cli, plot worker)', 'start', ''),
             ('imports (before main)', 'imports', ''),
             ('data (scenario)', 'data', ''),
             ('models (ours: with fmpy import)', 'models', ''),
             ('control loop', 'loop', ''),
             ('  solves', 'solves', '  '),
             ('    model evaluations', 'simulations', '    '),
             ('      (native C integration)', 'native', '      '),
             ('    glue / solver', 'glue', '    '),
             ('  plant (emulator)', 'plant', '  '),
             ('  loop other', 'loop_other', '  '),
             ('output (files, figure)', 'output', ''),
             ('exit (after main)', 'exit', ''),
             ('other (argparse, checks, logging)', 'other', ''),
             ('total (instrumented run)', 'total', ''))
    logger.info('%s %10s %7s %10s %7s %9s %9s', 'phase'.ljust(34), 'ours', '%', 'casadi', '%',
                'ours cpu', 'casadi cpu')
    cpu_keys = {'imports': 'imports', 'data': 'data', 'models': 'models', 'loop': 'loop',
                'solves': 'solves', 'simulations': 'simulations', 'native': 'native',
                'glue': 'glue', 'plant': 'plant', 'loop_other': 'loop_other',
                'output': 'output', 'other': 'other', 'total': 'main_process'}
    for label, key, _ in lines:
        ours_v = ours_b.get(key)
        theirs_v = theirs_b.get(key)
        cpus = [run.get(f'cpu_{cpu_keys[key]}') if key in cpu_keys else None
                for run in (ours_b, theirs_b)]
        logger.info('%s %10s %7s %10s %7s %9s %9s', label.ljust(34),
                    '-' if ours_v is None else f'{ours_v:.3f}',
                    '-' if ours_v is None else f'{100 * ours_v / ours_b["total"]:.0f}',
                    '-' if theirs_v is None else f'{theirs_v:.3f}',
                    '-' if theirs_v is None else f'{100 * theirs_v / theirs_b["total"]:.0f}',
                    *('-' if v is None else f'{v:.3f}' for v in cpus))
    logger.info('cpu: CPU time of the main process [s] (less sensitive to other load than the '
                'wall time); "other" includes the interpreter start, "total" the whole main '
                'process; our plot worker (a process of its own, in parallel): %.3f s',
                ours_b['cpu_plot_worker'])
    logger.info('ours: %d solves, %d batched model calls, glue %.0f us per model call; '
                'casadi: model evaluations = its function/derivative evaluations, glue = IPOPT '
                'and the call', ours_b['solve_calls'], ours_b['simulation_calls'],
                ours_b['glue_per_simulation_call_us'])
    for name in ('ours', 'casadi'):
        packages = parts[f'{name}_imports_by_package']
        logger.info('imports of %s by package (-X importtime, whole run, lazy imports '
                    'included): %s', name, ', '.join(f'{k} {v:.3f}' for k, v in
                                                     packages.items()))
    prof = parts['ours_cprofile']
    logger.info('cProfile of ours inside the solves (its overhead inflates Python-heavy code): '
                'solves %.3f s, model batch functions %.3f s in %d calls; top own times:',
                prof['solves_s'], prof['simulations_s'], prof['simulation_calls'])
    for item in prof['top_tottime'][:10]:
        logger.info('  %8.3f s %8d calls  %s', item['tottime_s'], item['calls'],
                    item['function'])


def main(argv: list[str] | None = None) -> int:
    global DATA
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--repeats', type=int, default=5,
                        help='runs of each whole command (default 5; medians)')
    parser.add_argument('--zones', nargs='+', type=int, default=[10, 50, 100, 300],
                        help='zone counts of the scale problem at H = 10 h')
    parser.add_argument('--horizons', nargs='+', type=int, default=[24],
                        help='further horizons [h] of the scale problem at --horizon-zones')
    parser.add_argument('--horizon-zones', type=int, default=100,
                        help='the zone count of the further horizons (default 100)')
    parser.add_argument('--data', type=pathlib.Path, default=DATA,
                        help=f'the OU44 measurements (default {DATA})')
    parser.add_argument('--zone-steps', type=int, default=6,
                        help='MPC steps per zone count (default 6: one cold, five warm)')
    parser.add_argument('--instrument', type=pathlib.Path, help=argparse.SUPPRESS)
    parser.add_argument('--profile', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('case_argv', nargs='*', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.instrument is not None:
        return instrumented_case(args.case_argv, args.instrument, args.profile)
    DATA = args.data  # (the whole commands' data file; the instrumented run's is on its argv)
    if (args.repeats < 1 or args.zone_steps < 2 or min(args.zones) < 1
            or min(args.horizons, default=1) < 1 or args.horizon_zones < 1):
        parser.error('--repeats >= 1, --zone-steps >= 2, --zones, --horizons and '
                     '--horizon-zones >= 1 expected')
    try:
        import casadi
    except ImportError:
        parser.exit(2, 'bench/versus.py needs casadi: make bench-setup\n')
    sys.path.insert(0, str(BENCH))
    from common import logger, setup_logging, write_json
    setup_logging()
    with tempfile.TemporaryDirectory(prefix='versus-') as tmp_name:
        tmp = pathlib.Path(tmp_name)
        logger.info('whole commands (%d runs each) ...', args.repeats)
        whole = whole_commands(args.repeats, tmp)
        logger.info('breakdown (%d instrumented runs each, importtime, cProfile) ...',
                    args.repeats)
        parts = breakdown(args.repeats, tmp)
    logger.info('Z-zone problem (%d steps each) ...', args.zone_steps)
    cases = [(z, HORIZON) for z in args.zones] + [
        (args.horizon_zones, h) for h in args.horizons if (args.horizon_zones, h) not in {
            (z, HORIZON) for z in args.zones}]
    if (args.horizon_zones, HORIZON) not in cases and args.horizons:
        cases.append((args.horizon_zones, HORIZON))  # (the horizons' reference point)
    zones = zone_rows(cases, args.zone_steps)
    growth = growth_exponents(zones)
    report(whole, zones, growth, parts)
    cached = importlib.util.find_spec(CASE_MODULE).cached
    byte_compiled = bool(cached) and pathlib.Path(cached).is_file()
    logger.info('%s byte-compiled (__pycache__): %s; PYTHONDONTWRITEBYTECODE=%s', CASE_MODULE,
                byte_compiled, os.environ.get('PYTHONDONTWRITEBYTECODE', ''))
    logger.info('our IPOPT build: %s (MSHOOT_IPOPT_BUILD)', os.environ['MSHOOT_IPOPT_BUILD'])
    write_json('versus', {'case_module': CASE_MODULE, 'casadi': casadi.__version__,
                          'ours_ipopt_build': os.environ['MSHOOT_IPOPT_BUILD'],
                          'case_module_byte_compiled': byte_compiled,
                          'repeats': args.repeats, 'whole': whole, 'zones': [
                              {k: v for k, v in row.items() if not k.endswith('controls_w')}
                              for row in zones], 'growth': growth, 'breakdown': parts})
    return 0


if __name__ == '__main__':
    sys.exit(main())
