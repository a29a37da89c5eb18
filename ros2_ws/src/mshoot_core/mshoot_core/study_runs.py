"""Closed-loop runs of the reference study: specification, execution, caching, parallel workers.

A :class:`RunSpec` names one 72 h (or shorter) MPC emulation of the OU44 case:
control model, horizon, FMU tolerance, evaluation mode, cost, comfort handling,
solver and emulator. :class:`StudyRunner` executes lists of them once each
(results are cached by spec, so parts of the study share runs), either in the
calling process or in forked worker processes, at most ``jobs`` at a time,
longest first. A run may carry a wall-clock budget: in a worker it is stopped
when the budget is spent and keeps the control steps it finished (the naive
reproduction of the ancestor can need minutes per step).

Data-driven control models are trained once, in the parent process, before
any worker is forked, so every worker inherits them.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import multiprocessing
import os
import pathlib
import pickle
import tempfile
import time
import traceback
from typing import Any, Iterable, Sequence

import pandas as pd

from mshoot_core.case import DATA_DRIVEN, r1c1_fmu_model, reference_scenario, run_case
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import R1C1Model

logger = logging.getLogger(__name__)

#: Control models a run can use: the exact Python R1C1, the R1C1 FMU (Model Exchange) and
#: the scikit-learn models of Setup 2.
CONTROLS = ('python', 'fmu') + DATA_DRIVEN
#: Emulators: the exact Python R1C1 or the R1C1 FMU in Co-Simulation (exact step).
EMULATORS = ('python', 'fmu-cs')
#: Initial zone temperature of the reference case [degC].
INITIAL_C = 20.0
#: Control step of the reference case [s].
STEP_S = 3600.0


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One closed-loop MPC emulation of the OU44 case.

    Attributes
    ----------
    control : str
        Control model, one of :data:`CONTROLS`.
    horizon : int
        MPC horizon [h] (= number of 1 h shooting intervals).
    hours : int
        Simulated period [h] from 2018-04-05 00:00 (72: the reference case).
    tolerance : float
        Relative integrator tolerance of the FMU control model (set to 0 for
        the other models, so equal runs compare equal).
    mode : {'fast', 'naive'}
        Our evaluation or the naive reproduction of the ancestor's algorithm.
    cost : {'quadratic', 'energy'}
    comfort : {'hard', 'soft'}
    soft_penalty : float
        Weight of the quadratic penalty on normalised slack (soft comfort only;
        set to 0 for hard comfort).
    solver : {'slsqp', 'ipopt', 'trust-constr'}
    emulator : str
        Emulation model, one of :data:`EMULATORS`.
    budget_s : float or None
        Wall-clock budget [s]; a run in a worker process is stopped when it is
        spent and keeps its finished steps (in-process runs check it between
        steps). None: no budget.
    """

    control: str
    horizon: int
    hours: int = 72
    tolerance: float = 0.0
    mode: str = 'fast'
    cost: str = 'quadratic'
    comfort: str = 'hard'
    soft_penalty: float = 0.0
    solver: str = 'slsqp'
    emulator: str = 'python'
    budget_s: float | None = None

    def __post_init__(self) -> None:
        if self.control not in CONTROLS:
            raise ValueError(f'control must be one of {CONTROLS}, got {self.control!r}')
        if self.emulator not in EMULATORS:
            raise ValueError(f'emulator must be one of {EMULATORS}, got {self.emulator!r}')
        if int(self.horizon) != self.horizon or self.horizon < 1:
            raise ValueError(f'horizon must be a positive integer [h], got {self.horizon}')
        if int(self.hours) != self.hours or self.hours < 1:
            raise ValueError(f'hours must be a positive integer, got {self.hours}')
        if self.mode not in ('fast', 'naive'):
            raise ValueError(f"mode must be 'fast' or 'naive', got {self.mode!r}")
        if self.cost not in ('quadratic', 'energy'):
            raise ValueError(f"cost must be 'quadratic' or 'energy', got {self.cost!r}")
        if self.comfort not in ('hard', 'soft'):
            raise ValueError(f"comfort must be 'hard' or 'soft', got {self.comfort!r}")
        if self.control == 'fmu' and not self.tolerance > 0:
            raise ValueError(f'the FMU control model needs a tolerance > 0, got {self.tolerance}')
        if self.comfort == 'soft' and not self.soft_penalty > 0:
            raise ValueError(f'soft comfort needs soft_penalty > 0, got {self.soft_penalty}')
        if self.budget_s is not None and not self.budget_s > 0:
            raise ValueError(f'budget_s must be > 0 or None, got {self.budget_s}')
        if self.control != 'fmu':
            object.__setattr__(self, 'tolerance', 0.0)
        if self.comfort == 'hard':
            object.__setattr__(self, 'soft_penalty', 0.0)

    @property
    def label(self) -> str:
        """A short human-readable name of the run."""
        parts = [self.control]
        if self.control == 'fmu':
            parts.append(f'tol {self.tolerance:.0e}')
        parts.append(f'H={self.horizon}')
        if self.mode != 'fast':
            parts.append(self.mode)
        if self.cost != 'quadratic':
            parts.append(f'{self.cost} cost')
        if self.comfort == 'soft':
            parts.append(f'soft {self.soft_penalty:g}')
        if self.solver != 'slsqp':
            parts.append(self.solver)
        parts.append(f'{self.hours} h')
        return ' '.join(parts)

    def estimated_cost(self) -> float:
        """A rough relative run time, used to start long runs first."""
        factor = {'python': 1.0, 'fmu': 25.0, 'svr': 3.0, 'linear': 5.0, 'ridge': 2.0,
                  'knn': 40.0, 'random_forest': 35.0, 'mlp': 2.0}[self.control]
        if self.solver == 'ipopt':
            factor *= 0.5
        cost = factor * self.horizon * self.hours
        if self.mode == 'naive':
            cost *= 100.0
        if self.budget_s is not None:
            cost = min(cost, 1.0 * self.budget_s * 20.0)
        return cost


@dataclasses.dataclass
class RunOutcome:
    """The records of one run.

    Attributes
    ----------
    spec : RunSpec
    kpis : dict
        :func:`mshoot_core.kpis.closed_loop_kpis` over the finished steps
        (energy [kWh], discomfort [K h], wall and solve times [s], failures).
    steps : DataFrame
        One row per finished control step (index: time [s]), with the applied
        heat rate ``q`` [W] and the solver records.
    fine : DataFrame
        The emulated trajectory on the 1-minute grid (index: time [s]) with
        ``y_T`` [degC], ``comfort_min``/``comfort_max`` [degC] and ``q`` [W].
    completed_steps : int
        Control steps finished (``spec.hours`` unless the budget ran out).
    """

    spec: RunSpec
    kpis: dict
    steps: pd.DataFrame
    fine: pd.DataFrame
    completed_steps: int

    @property
    def finished(self) -> bool:
        """Whether every requested step was run."""
        return self.completed_steps >= self.spec.hours


def train_control_model(kind: str, data: str | pathlib.Path) -> tuple[Model, dict]:
    """Train a data-driven control model as in Setup 2.

    Returns
    -------
    (model, report)
        The model and its :class:`~mshoot_core.models.sklearn_model.TrainingReport`
        fields as a dict (validation RMSEs [K], fit time [s], the validation
        table ``validation`` with ``T_true``, ``T_free_run`` [degC]).
    """
    from mshoot_core.models.sklearn_model import train_setup2
    started = time.perf_counter()
    model, training = train_setup2(data, estimator=kind)
    report = {f.name: getattr(training, f.name) for f in dataclasses.fields(training)}
    report['train_wall_s'] = time.perf_counter() - started
    logger.info('trained %s: validation RMSE %.3f K free run, %.4f K one step (%.1f s)', kind,
                training.rmse_free_run_k, training.rmse_one_step_k, report['train_wall_s'])
    return model, report


def execute(spec: RunSpec, data: str | pathlib.Path, trained: dict[str, Model] | None = None,
            checkpoint: pathlib.Path | None = None) -> RunOutcome:
    """Run one closed-loop emulation.

    Parameters
    ----------
    spec : RunSpec
    data : path-like
        The OU44 ``measurements.csv``.
    trained : dict, optional
        Trained data-driven models by kind (trained here when missing).
    checkpoint : path, optional
        Pickle file rewritten after every step with the records so far (lets a
        parent keep the finished steps of a run it had to stop).
    """
    scenario = reference_scenario('ou44', data, hours=spec.hours)
    if spec.control == 'python':
        control: Model = R1C1Model()
    elif spec.control == 'fmu':
        control = r1c1_fmu_model(spec.tolerance, 'ModelExchange')
    elif trained is not None and spec.control in trained:
        control = trained[spec.control]
    else:
        control = train_control_model(spec.control, data)[0]
    emulator_model = (R1C1Model() if spec.emulator == 'python'
                      else r1c1_fmu_model(1e-10, 'CoSimulation'))
    started = time.perf_counter()

    def save(rows: list[dict], fines: list[pd.DataFrame]) -> None:
        _write_pickle(checkpoint, {'rows': rows, 'fines': fines,
                                   'wall_s': time.perf_counter() - started})

    result, kpis = run_case(scenario, control, emulator_model, horizon=spec.horizon,
                            cost=spec.cost, solver=spec.solver, comfort=spec.comfort,
                            soft_penalty=spec.soft_penalty if spec.comfort == 'soft' else 1e3,
                            initial_c=INITIAL_C, mode=spec.mode,
                            steps=spec.hours, log_every=0, budget_s=spec.budget_s,
                            progress=None if checkpoint is None else save)
    return RunOutcome(spec, kpis, result.steps, result.fine, len(result.steps))


def outcome_from_records(spec: RunSpec, rows: list[dict], fines: list[pd.DataFrame],
                         wall_s: float) -> RunOutcome:
    """Assemble a :class:`RunOutcome` (KPIs included) from per-step records."""
    if not rows:
        empty = pd.DataFrame(columns=['q', 'solve_time_s', 'success'],
                             index=pd.Index([], name='time_s'))
        kpis = {key: math.nan for key in ('energy_kwh', 'heating_kwh', 'cooling_kwh',
                                          'discomfort_kh', 'discomfort_kh_hourly',
                                          'solve_s_total', 'solve_s_median', 'solve_s_max',
                                          'solve_per_control_step')}
        kpis.update(steps=0, wall_s=float(wall_s), solver_failures=0)
        return RunOutcome(spec, kpis, empty, pd.DataFrame(), 0)
    steps = pd.DataFrame(rows).set_index('time_s')
    fine = pd.concat(fines)
    kpis = closed_loop_kpis(steps, fine, STEP_S, wall_s)
    return RunOutcome(spec, kpis, steps, fine, len(rows))


def _write_pickle(path: pathlib.Path, payload: Any) -> None:
    tmp = path.with_suffix('.tmp')
    with open(tmp, 'wb') as handle:
        pickle.dump(payload, handle, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, path)


def _worker(spec: RunSpec, data: str, trained: dict[str, Model], checkpoint: str,
            result_path: str) -> None:
    """Body of a worker process: run, write the outcome (or the error) to ``result_path``."""
    try:
        outcome = execute(spec, data, trained, pathlib.Path(checkpoint))
        _write_pickle(pathlib.Path(result_path), {'outcome': outcome})
    except BaseException:  # noqa: B902 - report anything to the parent
        _write_pickle(pathlib.Path(result_path), {'error': traceback.format_exc()})
        raise


@dataclasses.dataclass
class _Running:
    spec: RunSpec
    process: multiprocessing.process.BaseProcess
    started: float
    checkpoint: pathlib.Path
    result: pathlib.Path


class StudyRunner:
    """Executes :class:`RunSpec` lists once each and caches the outcomes.

    Parameters
    ----------
    data : path-like
        The OU44 ``measurements.csv``.
    jobs : int
        Worker processes run at once; 0 runs everything in this process
        (budgets then only apply between control steps).
    """

    def __init__(self, data: str | pathlib.Path, jobs: int = 2) -> None:
        if int(jobs) != jobs or jobs < 0:
            raise ValueError(f'jobs must be an integer >= 0, got {jobs}')
        self.data = pathlib.Path(data)
        if not self.data.is_file():
            raise FileNotFoundError(f'OU44 data not found at {self.data}')
        self.jobs = int(jobs)
        self.cache: dict[RunSpec, RunOutcome] = {}
        self.trained: dict[str, Model] = {}
        self.training_reports: dict[str, dict] = {}
        self.runs_done = 0

    def training(self, kind: str) -> tuple[Model, dict]:
        """The trained data-driven model ``kind`` and its report (trained once)."""
        if kind not in self.trained:
            self.trained[kind], self.training_reports[kind] = train_control_model(kind,
                                                                                  self.data)
        return self.trained[kind], self.training_reports[kind]

    def run(self, specs: Iterable[RunSpec]) -> list[RunOutcome]:
        """Outcomes of ``specs`` in order, running those not cached yet."""
        specs = list(specs)
        pending: list[RunSpec] = []
        for spec in specs:
            if spec not in self.cache and spec not in pending:
                pending.append(spec)
        for kind in sorted({s.control for s in pending if s.control in DATA_DRIVEN}):
            self.training(kind)
        pending.sort(key=lambda s: -s.estimated_cost())
        if pending:
            logger.info('%d runs to do (%d requested, the rest shared or cached), %s',
                        len(pending), len(specs),
                        f'{self.jobs} worker processes' if self.jobs else 'in process')
        if self.jobs == 0:
            for i, spec in enumerate(pending):
                logger.info('run %d/%d: %s', i + 1, len(pending), spec.label)
                self._store(execute(spec, self.data, self.trained), i + 1, len(pending))
        else:
            self._run_parallel(pending)
        return [self.cache[spec] for spec in specs]

    def _store(self, outcome: RunOutcome, i: int, total: int) -> None:
        self.cache[outcome.spec] = outcome
        self.runs_done += 1
        k = outcome.kpis
        cut = '' if outcome.finished else (f' (budget spent: {outcome.completed_steps}/'
                                           f'{outcome.spec.hours} steps)')
        logger.info('done %d/%d: %s: %.2f kWh, %.2f Kh, wall %.1f s, %d solver failures%s', i,
                    total, outcome.spec.label, k['energy_kwh'], k['discomfort_kh'], k['wall_s'],
                    k['solver_failures'], cut)

    def _run_parallel(self, pending: Sequence[RunSpec]) -> None:
        context = multiprocessing.get_context('fork')
        queue = list(pending)
        running: list[_Running] = []
        finished = 0
        with tempfile.TemporaryDirectory(prefix='mshoot-study-') as tmp:
            workdir = pathlib.Path(tmp)
            while queue or running:
                while queue and len(running) < self.jobs:
                    spec = queue.pop(0)
                    n = finished + len(running) + 1
                    checkpoint = workdir / f'run{n}.checkpoint.pkl'
                    result = workdir / f'run{n}.result.pkl'
                    process = context.Process(
                        target=_worker, name=f'study-run-{n}',
                        args=(spec, str(self.data), self.trained, str(checkpoint), str(result)))
                    process.start()
                    logger.info('run %d/%d started: %s', n, len(pending), spec.label)
                    running.append(_Running(spec, process, time.perf_counter(), checkpoint,
                                            result))
                time.sleep(0.05)
                for item in list(running):
                    elapsed = time.perf_counter() - item.started
                    over_budget = item.spec.budget_s is not None and elapsed > item.spec.budget_s
                    if item.process.is_alive() and not over_budget:
                        continue
                    if item.process.is_alive():
                        item.process.terminate()
                    item.process.join()
                    running.remove(item)
                    finished += 1
                    self._store(self._collect(item, elapsed), finished, len(pending))

    def _collect(self, item: _Running, elapsed: float) -> RunOutcome:
        if item.result.is_file():
            with open(item.result, 'rb') as handle:
                payload = pickle.load(handle)
            if 'error' in payload:
                raise RuntimeError(f'run {item.spec.label} failed:\n{payload["error"]}')
            return payload['outcome']
        if item.process.exitcode not in (None, 0) and item.spec.budget_s is None:
            raise RuntimeError(f'run {item.spec.label} died with exit code '
                               f'{item.process.exitcode}')
        rows: list[dict] = []
        fines: list[pd.DataFrame] = []
        if item.checkpoint.is_file():
            with open(item.checkpoint, 'rb') as handle:
                payload = pickle.load(handle)
            rows, fines = payload['rows'], payload['fines']
        logger.info('%s stopped after its budget of %.0f s: %d/%d steps kept', item.spec.label,
                    item.spec.budget_s or math.nan, len(rows), item.spec.hours)
        return outcome_from_records(item.spec, rows, fines, elapsed)
