"""The MPC emulation loop: decide, apply the decision to the emulator, advance, repeat."""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Callable

import numpy as np
import pandas as pd

from mshoot_core.controller import Controller, StepOutcome
from mshoot_core.emulation import Emulator, StepRecord
from mshoot_core.estimation import Sensors
from mshoot_core.models.base import ModelValueError
from mshoot_core.mpc import MPC
from mshoot_core.period_loop import LoopRun, run_steps
from mshoot_core.scenario import forecast_rows
from mshoot_core.units import NS_PER_S

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class ClosedLoopResult(LoopRun):
    """
    Records of a closed-loop run: a :class:`~mshoot_core.period_loop.LoopRun` with its tables.

    Attributes
    ----------
    steps : DataFrame
        One row per control step: time, applied controls, emulated and
        predicted end states, solve time [s], solver status, success,
        iterations, max defect, relaxed.
    fine : DataFrame
        Emulated states, outputs, controls and comfort band on the fine grid.
    plans : list of DataFrame
        The plan of every step.
    step_wall_s : list of float
        Wall time of each step's decision [s] (:meth:`Controller.poll`, the solve's and the
        fallback's; keyword).
    wall_s : float
        Wall time of the whole loop [s] (keyword).

    """

    steps: pd.DataFrame
    fine: pd.DataFrame
    plans: list[pd.DataFrame]


class EmulationStopped(RuntimeError):
    """
    The emulated building failed (non-finite values): the run stopped early.

    Attributes
    ----------
    result : ClosedLoopResult or None
        The steps done before the failing one (None if it was the first).
    step : int
        Index of the failing step in the run (0-based).
    t_s : float
        Start time of the failing step [s].

    """

    def __init__(self, message: str, result: ClosedLoopResult | None, step: int,
                 t_s: float) -> None:
        super().__init__(message)
        self.result = result
        self.step = step
        self.t_s = t_s


def step_row(outcome: StepOutcome, record: StepRecord, state_names: tuple[str, ...],
             control_names: tuple[str, ...]) -> dict:
    """
    Return the per-step record of one loop iteration (shared with the ROS nodes' tools).

    Columns: ``time_s``, the applied controls, ``{state}_start``, ``{state}_end``,
    ``{state}_predicted`` (NaN for the safe setpoint), the solve's
    ``solve_time_s``, ``success``, ``status``, ``iterations``, ``objective``,
    ``max_defect``, ``relaxed``, ``model_evaluations`` (NaN or False without a
    solve result), and the decision's ``source`` ('optimum', 'plan', 'safe', 'released'),
    ``fallback``, ``fallback_code`` and ``fallback_reason``, ``released`` (the controls whose
    overwrite the plant released, separated by spaces; '' for none); with an estimated
    state, also ``{state}_estimate`` (the state the step was planned from) and
    ``{state}_std`` (its standard deviation [K]).
    """
    decision, result = outcome.decision, outcome.result
    row = {'time_s': record.t_start_s}
    for name, value in zip(control_names, record.controls):
        row[name] = float(value)
    predicted = (decision.predicted_state if decision.predicted_state is not None
                 else np.full(len(state_names), np.nan))
    for i, name in enumerate(state_names):
        row[f'{name}_start'] = float(record.x_start[i])
        row[f'{name}_end'] = float(record.x_end[i])
        row[f'{name}_predicted'] = float(predicted[i])
    if result is not None:
        row.update(solve_time_s=float(outcome.solve_time_s), success=bool(result.success),
                   status=int(result.status), iterations=int(result.nit),
                   objective=float(result.fun), max_defect=result.max_defect,
                   relaxed=bool(result.relaxed), model_evaluations=int(result.model_evaluations))
    else:
        row.update(solve_time_s=float(outcome.solve_time_s), success=False, status=-1,
                   iterations=0, objective=np.nan, max_defect=np.nan, relaxed=False,
                   model_evaluations=0)
    row.update(source=decision.source, fallback=bool(decision.fallback),
               fallback_code=decision.code, fallback_reason=decision.reason,
               released=' '.join(record.released))
    if outcome.x0_std is not None and outcome.x0 is not None:
        for i, name in enumerate(state_names):
            row[f'{name}_estimate'] = float(outcome.x0[i])
            row[f'{name}_std'] = float(outcome.x0_std[i])
    return row


def offer_scenario_inputs(controller: Controller, emulator: Emulator, now_ns: int,
                          sensors: Sensors | None = None,
                          applied: np.ndarray | None = None) -> None:
    """
    Give the controller the emulated state and a perfect forecast, as the nodes do.

    The forecast is the scenario's next N+1 rows (the series the controller knows), stamped at the
    emulator's time, as the emulator and forecaster nodes do. With ``sensors`` the controller gets
    what they read (the measured states, with their noise) and the controls ``applied`` over the
    last step, by name, as the emulator node publishes them.
    """
    _ScenarioInputs(controller, emulator).offer(now_ns, sensors, applied)


class _ScenarioInputs:
    """
    :func:`offer_scenario_inputs` for a whole run: the scenario's known series read once.

    The forecast of a step is rows ``index .. index + N`` of the scenario (the last row
    repeated past its end, as :func:`~mshoot_core.scenario.forecast_window`), taken from the
    series as arrays rather than through a frame per step.
    """

    def __init__(self, controller: Controller, emulator: Emulator) -> None:
        self.controller, self.emulator = controller, emulator
        known = controller.forecast_known
        scenario = emulator.scenario
        columns = [j for j, name in enumerate(scenario.columns) if name in known]
        self.names = [scenario.columns[j] for j in columns]
        self.table = scenario.to_numpy(dtype=float)[:, columns]

    def offer(self, now_ns: int, sensors: Sensors | None = None,
              applied: np.ndarray | None = None) -> None:
        controller, emulator = self.controller, self.emulator
        rows = forecast_rows(emulator.index, controller.mpc.horizon_steps, len(self.table))
        values = self.table[rows]
        series = {name: values[:, j] for j, name in enumerate(self.names)}
        if sensors is None:
            state = controller.offer_state(now_ns, emulator.x, now_ns)
        else:
            readings = sensors.read(emulator.x, emulator.index)
            controls = () if applied is None else emulator.control_names
            state = controller.offer_named_state(
                now_ns, list(readings), list(readings.values()), now_ns,
                control_names=list(controls), control_values=[] if applied is None else
                [float(v) for v in applied])
        for stream, rejection in (
                ('state', state),
                ('forecast', controller.offer_forecast(now_ns, emulator.step_s, series, now_ns))):
            if rejection:
                logger.warning('%s at %.0f s rejected [%s]: %s', stream, now_ns / NS_PER_S,
                               rejection.kind, rejection.reason)


def run_closed_loop(controller: Controller | MPC, emulator: Emulator, steps: int | None = None,
                    progress: Callable[[list[dict], list[pd.DataFrame]], None] | None = None,
                    log_every: int = 12, budget_s: float | None = None,
                    sensors: Sensors | None = None) -> ClosedLoopResult:
    """
    Run the controller against the emulator for ``steps`` control steps (default: to the end).

    Every step the controller gets the emulated state and a perfect forecast
    and decides (:meth:`Controller.poll`): its optimum, or a fallback (the last
    good plan, the safe setpoint) when the solve fails, raises or overruns its
    time budget; the emulator applies the decision. The steps go through the one period loop
    (:func:`mshoot_core.period_loop.run_steps`: observe, decide, apply; its wall times).

    Parameters
    ----------
    controller : Controller or MPC
        The controller (an MPC gets a :class:`Controller` with its settings);
        its step must equal the emulator's.
    emulator : Emulator
        The emulated building, positioned at the first step.
    steps : int, optional
        Number of control steps (default: what is left of the scenario).
    progress : callable, optional
        Called as ``progress(rows, fines)`` after every step with the records
        so far (the :func:`step_row` of every step, and the fine-grid frames
        whose concatenation is :attr:`ClosedLoopResult.fine`), e.g. to
        checkpoint a long run.
    log_every : int
        Log a progress line every so many steps (0: never).
    budget_s : float, optional
        Wall-time budget of the whole run [s]: no step is started once it is
        spent, and the result holds the steps done (at least one).
    sensors : Sensors, optional
        What the controller is given of the emulated state: the measured states
        with their noise (default: every state, exactly).

    Raises
    ------
    EmulationStopped
        If the emulator produced non-finite values (a
        :class:`~mshoot_core.models.base.ModelValueError`, chained): carries
        the records of the steps done before (``result``).

    """
    if isinstance(controller, MPC):
        controller = Controller(mpc=controller)
    if controller.executor is not None:
        raise ValueError('run_closed_loop solves inline: give it a Controller without an '
                         'executor')
    mpc = controller.mpc
    if abs(mpc.step_s - emulator.step_s) > 1e-9:
        raise ValueError(f'MPC step {mpc.step_s} s differs from the emulator step '
                         f'{emulator.step_s} s')
    total = emulator.steps_left if steps is None else int(steps)
    if not 0 < total <= emulator.steps_left:
        raise ValueError(f'steps must be in [1, {emulator.steps_left}], got {steps}')
    rows: list[dict] = []
    fines: list[pd.DataFrame] = []
    plans: list[pd.DataFrame] = []
    started = time.perf_counter()
    inputs = _ScenarioInputs(controller, emulator)

    def stamp() -> int:
        return int(round(emulator.t_s * NS_PER_S))  # the scenario row's time, as the nodes'

    def observe(t_s: float) -> None:
        applied = (np.array([rows[-1][n] for n in emulator.control_names]) if rows else None)
        inputs.offer(stamp(), sensors, applied)

    def decide(t_s: float) -> StepOutcome:
        now_ns = stamp()
        outcomes = controller.poll(now_ns)
        if len(outcomes) != 1 or outcomes[0].step_ns != now_ns:
            raise RuntimeError(f'the controller decided {[o.step_ns for o in outcomes]} at '
                               f'{now_ns} ns: expected exactly that step')
        return outcomes[0]

    def apply(t_s: float, end_s: float, outcome: StepOutcome) -> None:
        k = len(rows)
        try:
            record = emulator.advance(outcome.decision.controls,
                                      released=outcome.decision.released)
        except ModelValueError as error:
            done = (ClosedLoopResult(pd.DataFrame(rows).set_index('time_s'), pd.concat(fines),
                                     plans, step_wall_s=[], wall_s=time.perf_counter() - started)
                    if rows else None)
            raise EmulationStopped(f'emulation stopped at step {k + 1}/{total} (t = '
                                   f'{emulator.t_s:.0f} s, {len(rows)} steps done): {error}',
                                   done, k, emulator.t_s) from error
        row = step_row(outcome, record, mpc.model.state_names, mpc.problem.control_names)
        rows.append(row)
        fines.append(record.fine if k == 0 else record.fine.iloc[1:])
        plans.append(_plan_frame(outcome, mpc))
        if progress is not None:
            progress(rows, fines)
        _log_step(k, total, row, outcome, log_every)

    start = emulator.t_s
    loop = run_steps(start, start + total * emulator.step_s, emulator.step_s, apply,
                     decide=decide, observe=observe, budget_s=budget_s, label='closed loop')
    return ClosedLoopResult(pd.DataFrame(rows).set_index('time_s'), pd.concat(fines), plans,
                            step_wall_s=loop.step_wall_s, wall_s=loop.wall_s)


def _log_step(k: int, total: int, row: dict, outcome: StepOutcome, log_every: int) -> None:
    """Log step ``k``'s line every ``log_every`` steps (0: never), and every fallback."""
    if log_every and ((k + 1) % log_every == 0 or k + 1 == total):
        logger.info('step %d/%d (t = %.0f h): solve %.3f s, %s', k + 1, total,
                    row['time_s'] / 3600.0, row['solve_time_s'],
                    'ok' if row['success'] else f"{row['source']} ({row['fallback_code']})"
                    if row['fallback'] else 'not converged')
    elif outcome.decision.fallback:
        logger.info('step %d/%d (t = %.0f h): fallback %s: %s', k + 1, total,
                    row['time_s'] / 3600.0, outcome.decision.source, outcome.decision.reason)


def _plan_frame(outcome: StepOutcome, mpc: MPC) -> pd.DataFrame:
    """Return the plan of a decision (controls and predicted end states by interval start)."""
    d = outcome.decision
    if outcome.result is not None and not d.fallback:
        return outcome.result.plan
    times = outcome.t_s + np.arange(len(d.plan_controls)) * mpc.step_s
    names = mpc.problem.control_names
    plan = pd.DataFrame(np.asarray(d.plan_controls, dtype=float).reshape(-1, len(names)),
                        columns=list(names), index=pd.Index(times, name='time_s'))
    states = np.asarray(d.plan_states, dtype=float)
    for i, name in enumerate(mpc.model.state_names):
        plan[f'{name}_end'] = states[:, i] if states.size else np.nan
    return plan
