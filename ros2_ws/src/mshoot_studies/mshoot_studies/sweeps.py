"""
Sweeps of closed-loop runs: specification, execution, caching, local or Dask workers.

A :class:`RunSpec` names one 72 h (or shorter) MPC emulation of the OU44 case:
control model, horizon, FMU tolerance, evaluation mode, cost, comfort handling,
solver and emulator. A :class:`SweepRunner` executes lists of them once each
(results are cached by spec, so parts of a study share runs), longest first,
with a process pool from the standard library
(:class:`concurrent.futures.ProcessPoolExecutor`, one fresh process per run),
on a Dask cluster (:mod:`distributed`: a scheduler's address, or a
``LocalCluster`` the runner starts), or in the calling process.

Every run can be stopped at a deadline: its own wall-clock budget
(:attr:`RunSpec.budget_s`, part of what the run is) or the runner's per-run
``timeout_s`` (a guard over a whole sweep), whichever comes first. The run is
stopped where it is, in the middle of an MPC step if need be, keeps the steps
it finished, and is recorded with :attr:`RunOutcome.stop` ``'budget'`` or
``'timeout'``; the sweep goes on. A run checks its deadline before every
evaluation of its control model (many per MPC step: a :class:`StoppableModel`
wraps it) and after every step, so it stops between two evaluations with
nothing half-built, in any process or thread; a single evaluation that never
returns is not interrupted.

Data-driven control models are trained once, in the calling process, and
sent to the workers with the runs that use them.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import logging
import math
import pathlib
import time
from typing import Any, Iterable, Sequence

from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.models.registry import build_model, EMULATOR_TOLERANCE
from mshoot_core.scenario import reference_scenario
import pandas as pd

from mshoot_studies.case import DATA_DRIVEN, run_case
from mshoot_studies.worker_pool import process_pool

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
#: How a run ended (:attr:`RunOutcome.stop`).
STOPS = ('completed', 'budget', 'timeout')
#: Log line format of the commands, and of the worker processes a runner starts.
LOG_FORMAT = '%(asctime)s %(levelname)s %(name)s: %(message)s'
#: Modules the local pool's fork server imports once, so that each run's fresh process
#: starts with them loaded.
WORKER_PRELOAD = ('mshoot_studies.sweeps', 'mshoot_core.models.sklearn_model',
                  'mshoot_core.models.fmi')


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """
    One closed-loop MPC emulation of the OU44 case.

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
        Wall-clock budget [s] of the run (model set-up included): the run is
        stopped when it is spent, in the middle of a step if need be, and
        keeps the steps it finished. None: no budget.

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
        """Return a short human-readable name of the run."""
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
        """Return a rough relative run time, used to start long runs first."""
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
    """
    The records of one run.

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
        Control steps finished (``spec.hours`` unless the run was stopped).
    stop : {'completed', 'budget', 'timeout'}
        How the run ended: every step run, stopped by its budget
        (:attr:`RunSpec.budget_s`), or stopped by the runner's per-run timeout.

    """

    spec: RunSpec
    kpis: dict
    steps: pd.DataFrame
    fine: pd.DataFrame
    completed_steps: int
    stop: str = 'completed'

    @property
    def finished(self) -> bool:
        """Whether every requested step was run."""
        return self.completed_steps >= self.spec.hours

    @property
    def timed_out(self) -> bool:
        """Whether the runner's per-run timeout stopped the run."""
        return self.stop == 'timeout'


def train_control_model(kind: str, data: str | pathlib.Path) -> tuple[Model, dict]:
    """
    Train a data-driven control model as in Setup 2.

    Returns
    -------
    (model, report)
        The model and its :class:`~mshoot_studies.setup2.TrainingReport`
        fields as a dict (validation RMSEs [K], fit time [s], the validation
        table ``validation`` with ``T_true``, ``T_free_run`` [degC]).

    """
    from mshoot_studies.setup2 import train_setup2
    started = time.perf_counter()
    model, training = train_setup2(data, estimator=kind)
    report = {f.name: getattr(training, f.name) for f in dataclasses.fields(training)}
    report['train_wall_s'] = time.perf_counter() - started
    logger.info('trained %s: validation RMSE %.3f K free run, %.4f K one step (%.1f s)', kind,
                training.rmse_free_run_k, training.rmse_one_step_k, report['train_wall_s'])
    return model, report


# -- stopping a run at its deadline -----------------------------------------------------------
class RunStopped(BaseException):
    """
    Raised inside a run when its deadline has passed.

    A BaseException, like KeyboardInterrupt, so that no ``except Exception`` on the way swallows
    it.
    """


class Deadline:
    """A wall-clock deadline ``seconds`` [s] after :meth:`start` (None: never)."""

    def __init__(self, seconds: float | None) -> None:
        if seconds is not None and not seconds > 0:
            raise ValueError(f'a deadline must be > 0 s or None, got {seconds}')
        self.seconds = seconds
        self._end = math.inf

    def start(self) -> 'Deadline':
        """Start the clock; return self."""
        if self.seconds is not None:
            self._end = time.perf_counter() + self.seconds
        return self

    @property
    def expired(self) -> bool:
        """Whether the deadline has passed."""
        return time.perf_counter() > self._end

    def check(self) -> None:
        """Raise :class:`RunStopped` if the deadline has passed."""
        if self.expired:
            raise RunStopped(f'deadline of {self.seconds} s passed')


class StoppableModel(Model):
    """
    A control model that stops its run at the first evaluation after a deadline.

    Every model evaluation of an MPC step (a simulation, a batch of intervals,
    their Jacobians) first checks ``deadline``, so a run stops in the middle of
    a step, between two evaluations, with nothing half-built. Everything else
    is the wrapped model's.

    Parameters
    ----------
    model : Model
        The control model.
    deadline : Deadline

    """

    def __init__(self, model: Model, deadline: Deadline) -> None:
        if not isinstance(model, Model):
            raise TypeError(f'model must be a mshoot_core Model, got {type(model).__name__}')
        self._model = model
        self._deadline = deadline

    def __repr__(self) -> str:
        return f'{type(self).__name__}({self._model!r}, {self._deadline.seconds} s)'

    @property
    def input_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return self._model.input_names

    @property
    def state_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return self._model.state_names

    @property
    def output_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return self._model.output_names

    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        self._deadline.check()
        return self._model.simulate(udf, x0)

    def simulate_intervals(self, *args: Any, **kwargs: Any) -> Any:
        self._deadline.check()
        return self._model.simulate_intervals(*args, **kwargs)

    def interval_jacobians(self, *args: Any, **kwargs: Any) -> Any:
        self._deadline.check()
        return self._model.interval_jacobians(*args, **kwargs)

    def jacobian_sparsity(self, wrt_inputs: Sequence[int]) -> Any:
        return self._model.jacobian_sparsity(wrt_inputs)

    def check_inputs(self, *args: Any, **kwargs: Any) -> Any:
        return self._model.check_inputs(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        """
        Return the wrapped model's other attributes; its other methods check the deadline too.

        E.g. the naive evaluation's ``simulate_fresh``.
        """
        if name in ('_model', '_deadline') or name.startswith('__'):
            raise AttributeError(name)
        value = getattr(self._model, name)
        if not callable(value):
            return value

        @functools.wraps(value)
        def checked(*args: Any, **kwargs: Any) -> Any:
            self._deadline.check()
            return value(*args, **kwargs)
        return checked


# -- one run ----------------------------------------------------------------------------------
def execute(spec: RunSpec, scenario: pd.DataFrame, control: Model | None = None,
            timeout_s: float | None = None) -> RunOutcome:
    """
    Run one closed-loop emulation, stopped at its budget or ``timeout_s``.

    Parameters
    ----------
    spec : RunSpec
        What to run: models, settings, period and budget.
    scenario : DataFrame
        The OU44 scenario of ``spec.hours`` steps
        (:func:`mshoot_core.scenario.reference_scenario`).
    control : Model, optional
        The control model; needed for the data-driven kinds (trained by the
        caller), built here for 'python' and 'fmu' when None.
    timeout_s : float, optional
        Wall-clock limit [s] of the run, on top of ``spec.budget_s``.

    Returns
    -------
    RunOutcome
        With the steps finished before a stop (:attr:`RunOutcome.stop`).

    """
    limits = [(s, why) for s, why in ((spec.budget_s, 'budget'), (timeout_s, 'timeout'))
              if s is not None]
    deadline_s, reason = min(limits, key=lambda item: item[0]) if limits else (None, 'completed')
    deadline = Deadline(deadline_s).start()
    records: list[tuple[list[dict], list[pd.DataFrame]]] = [([], [])]

    def keep(rows: list[dict], fines: list[pd.DataFrame]) -> None:
        records[0] = (list(rows), list(fines))
        deadline.check()  # between steps too

    started = time.perf_counter()
    if spec.control == 'python':
        control = R1C1Model()
    elif spec.control == 'fmu':
        control = build_model('fmu', spec.tolerance)
    elif control is None:
        raise ValueError(f'{spec.control} runs need their trained control model')
    emulator_model = (R1C1Model() if spec.emulator == 'python'
                      else build_model('fmu-cs', EMULATOR_TOLERANCE))
    try:
        result, kpis = run_case(
            scenario, StoppableModel(control, deadline), emulator_model, horizon=spec.horizon,
            cost=spec.cost, solver=spec.solver, comfort=spec.comfort,
            soft_penalty=spec.soft_penalty if spec.comfort == 'soft' else 1e3,
            initial_c=INITIAL_C, mode=spec.mode, steps=spec.hours, log_every=0, progress=keep)
    except RunStopped:
        rows, fines = records[0]
        wall_s = time.perf_counter() - started
        stop = 'completed' if len(rows) >= spec.hours else reason
        logger.info('%s stopped by its %s of %.0f s: %d/%d steps kept', spec.label, reason,
                    deadline_s, len(rows), spec.hours)
        return outcome_from_records(spec, rows, fines, wall_s, stop)
    return RunOutcome(spec, kpis, result.steps, result.fine, len(result.steps))


def outcome_from_records(spec: RunSpec, rows: list[dict], fines: list[pd.DataFrame],
                         wall_s: float, stop: str = 'completed') -> RunOutcome:
    """Assemble a :class:`RunOutcome` (KPIs included) from per-step records."""
    if stop not in STOPS:
        raise ValueError(f'stop must be one of {STOPS}, got {stop!r}')
    if not rows:
        empty = pd.DataFrame(columns=['q', 'solve_time_s', 'success'],
                             index=pd.Index([], name='time_s'))
        kpis = {key: math.nan for key in ('energy_kwh', 'heating_kwh', 'cooling_kwh',
                                          'discomfort_kh', 'discomfort_kh_hourly',
                                          'solve_s_total', 'solve_s_median', 'solve_s_max',
                                          'solve_per_control_step')}
        kpis.update(steps=0, wall_s=float(wall_s), solver_failures=0)
        return RunOutcome(spec, kpis, empty, pd.DataFrame(), 0, stop)
    steps = pd.DataFrame(rows).set_index('time_s')
    fine = pd.concat(fines)
    kpis = closed_loop_kpis(steps, fine, STEP_S, wall_s)
    return RunOutcome(spec, kpis, steps, fine, len(rows), stop)


def _configure_logging(root_level: int, levels: dict[str, int]) -> None:
    """Log like the calling process: its root level, format and per-logger levels."""
    logging.basicConfig(level=root_level, format=LOG_FORMAT)
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)


def _logging_setup() -> tuple[int, dict[str, int]]:
    """Return the root level and the explicitly set levels of this process's loggers."""
    levels = {name: item.level for name, item in logging.root.manager.loggerDict.items()
              if isinstance(item, logging.Logger) and item.level != logging.NOTSET}
    return logging.getLogger().getEffectiveLevel(), levels


# -- the runner -------------------------------------------------------------------------------
class SweepRunner:
    """
    Executes :class:`RunSpec` lists once each and caches the outcomes.

    Parameters
    ----------
    data : path-like
        The OU44 ``measurements.csv``.
    jobs : int
        Runs at a time: worker processes of the local pool (0: every run in
        this process, one after the other), or the workers of the
        ``LocalCluster`` with ``dask='local'``.
    timeout_s : float, optional
        Wall-clock limit [s] of every run (model set-up included); a run over
        it is stopped, keeps its finished steps and is recorded as timed out
        (:attr:`RunOutcome.stop` ``'timeout'``), and the sweep goes on.
    dask : str, optional
        Run on a Dask cluster instead: the scheduler's address (e.g.
        ``'tcp://10.0.0.5:8786'``; the workers need mshoot installed and the
        runs' data travel with them), or ``'local'`` for a ``LocalCluster`` of
        ``jobs`` single-threaded worker processes on this machine.

    The pool, cluster or client is started on first use and ended by
    :meth:`close` (or leaving a ``with`` block).

    """

    def __init__(self, data: str | pathlib.Path, jobs: int = 2, *,
                 timeout_s: float | None = None, dask: str | None = None) -> None:
        if int(jobs) != jobs or jobs < 0:
            raise ValueError(f'jobs must be an integer >= 0, got {jobs}')
        if timeout_s is not None and not timeout_s > 0:
            raise ValueError(f'timeout_s must be > 0 or None, got {timeout_s}')
        if dask is not None and (not isinstance(dask, str) or not dask):
            raise ValueError(f"dask must be a scheduler address or 'local', got {dask!r}")
        self.data = pathlib.Path(data)
        if not self.data.is_file():
            raise FileNotFoundError(f'OU44 data not found at {self.data}')
        self.jobs = int(jobs)
        self.timeout_s = timeout_s
        self.dask = dask
        self.cache: dict[RunSpec, RunOutcome] = {}
        self.trained: dict[str, Model] = {}
        self.training_reports: dict[str, dict] = {}
        self.runs_done = 0
        self._scenarios: dict[int, pd.DataFrame] = {}
        self._executor: concurrent.futures.Executor | None = None
        self._client: Any = None
        self._cluster: Any = None

    # -- life cycle ------------------------------------------------------------------------
    def __enter__(self) -> 'SweepRunner':
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def close(self) -> None:
        """End the worker pool, or the Dask client (and the cluster the runner started)."""
        executor, self._executor = self._executor, None
        if isinstance(executor, concurrent.futures.ProcessPoolExecutor):
            executor.shutdown(wait=True, cancel_futures=True)
        elif executor is not None:
            executor.shutdown(wait=True)
        client, self._client = self._client, None
        if client is not None:
            client.close()
        cluster, self._cluster = self._cluster, None
        if cluster is not None:
            cluster.close()

    @property
    def parallel_runs(self) -> int:
        """Return how many runs execute at a time (1 in process; the cluster's threads on Dask)."""
        if self.dask is not None:
            self._start()
            return max(1, sum(self._client.nthreads().values()))
        return max(1, self.jobs)

    @property
    def description(self) -> str:
        """Where the runs go, for logs and reports."""
        if self.dask == 'local':
            return f'a Dask LocalCluster of {self.parallel_runs} worker processes'
        if self.dask is not None:
            return f'the Dask cluster at {self.dask} ({self.parallel_runs} worker threads)'
        if self.jobs == 0:
            return 'this process'
        return f'{self.jobs} worker processes'

    def _start(self) -> concurrent.futures.Executor:
        """Return the executor runs are submitted to (started on first use)."""
        if self._executor is not None:
            return self._executor
        root_level, levels = _logging_setup()
        if self.dask is None:
            # One fresh process per run (max_tasks_per_child=1), as isolated as the forked
            # processes of old: no run inherits the memory, caches or FMU instances of the
            # last. The runner never queues more runs than workers, so the pool never holds
            # the backlog that CPython 3.11's worker replacement can stall on (gh-115634).
            self._executor = process_pool(
                self.jobs, 'forkserver', _configure_logging, (root_level, levels),
                preload=WORKER_PRELOAD, max_tasks_per_child=1)
            return self._executor
        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:
            raise ValueError(f'running on Dask needs the distributed package ({exc})') from exc
        if self.dask == 'local':
            self._cluster = LocalCluster(n_workers=max(1, self.jobs), threads_per_worker=1,
                                         processes=True, dashboard_address=':0')
            self._client = Client(self._cluster)
        else:
            self._client = Client(self.dask)
        self._client.run(_configure_logging, root_level, levels)
        self._executor = self._client.get_executor(pure=False)
        logger.info('runs go to %s', self.description)
        return self._executor

    # -- inputs of the runs ----------------------------------------------------------------
    def training(self, kind: str) -> tuple[Model, dict]:
        """Return the trained data-driven model ``kind`` and its report (trained once)."""
        if kind not in self.trained:
            self.trained[kind], self.training_reports[kind] = train_control_model(kind,
                                                                                  self.data)
        return self.trained[kind], self.training_reports[kind]

    def scenario(self, hours: int) -> pd.DataFrame:
        """Return the OU44 scenario of ``hours`` control steps (loaded once)."""
        if hours not in self._scenarios:
            self._scenarios[hours] = reference_scenario('ou44', self.data, hours=hours)
        return self._scenarios[hours]

    def _arguments(self, spec: RunSpec) -> tuple:
        control = self.trained[spec.control] if spec.control in DATA_DRIVEN else None
        return spec, self.scenario(spec.hours), control, self.timeout_s

    # -- running ---------------------------------------------------------------------------
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
            logger.info('%d runs to do (%d requested, the rest shared or cached), in %s',
                        len(pending), len(specs), self.description)
        if self.jobs == 0 and self.dask is None:
            for i, spec in enumerate(pending):
                logger.info('run %d/%d: %s', i + 1, len(pending), spec.label)
                self._store(execute(*self._arguments(spec)), i + 1, len(pending))
        elif pending:
            self._run_parallel(pending)
        return [self.cache[spec] for spec in specs]

    def _run_parallel(self, pending: Sequence[RunSpec]) -> None:
        executor = self._start()
        slots = self.parallel_runs
        queue = list(pending)
        running: dict[concurrent.futures.Future, RunSpec] = {}
        submitted = finished = 0
        try:
            while queue or running:
                while queue and len(running) < slots:
                    spec = queue.pop(0)
                    submitted += 1
                    running[executor.submit(execute, *self._arguments(spec))] = spec
                    logger.info('run %d/%d started: %s', submitted, len(pending), spec.label)
                done, _ = concurrent.futures.wait(
                    running, return_when=concurrent.futures.FIRST_COMPLETED)
                for future in done:
                    spec = running.pop(future)
                    finished += 1
                    try:
                        outcome = future.result()
                    except Exception as exc:  # noqa: B902 - any failure of a run ends the sweep
                        raise RuntimeError(f'run {spec.label} failed: {exc!r}') from exc
                    self._store(outcome, finished, len(pending))
        except BaseException:
            for future in running:
                future.cancel()
            if self.dask is None and self._executor is not None:
                # a failed pool may be broken: let its runs end on their own, start anew next
                self._executor.shutdown(wait=False, cancel_futures=True)
                self._executor = None
            raise

    def _store(self, outcome: RunOutcome, i: int, total: int) -> None:
        self.cache[outcome.spec] = outcome
        self.runs_done += 1
        k = outcome.kpis
        cut = '' if outcome.stop == 'completed' else (
            f' (stopped by its {outcome.stop}: {outcome.completed_steps}/'
            f'{outcome.spec.hours} steps)')
        logger.info('done %d/%d: %s: %.2f kWh, %.2f Kh, wall %.1f s, %d solver failures%s', i,
                    total, outcome.spec.label, k['energy_kwh'], k['discomfort_kh'], k['wall_s'],
                    k['solver_failures'], cut)
