"""The MPC emulation loop: plan, apply the first step to the emulator, advance, repeat."""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Callable

import numpy as np
import pandas as pd

from mshoot_core.emulation import Emulator, StepRecord
from mshoot_core.mpc import MPC, MpcResult

logger = logging.getLogger(__name__)


def forecast_window(scenario: pd.DataFrame, index: int, horizon_steps: int) -> pd.DataFrame:
    """Rows ``index .. index + horizon_steps`` of ``scenario`` (N+1 rows).

    Past the end of the scenario the last row is repeated (a persistence
    forecast), so the controller can plan the final hours of a run.
    """
    if not 0 <= index < len(scenario):
        raise ValueError(f'index must be in [0, {len(scenario) - 1}], got {index}')
    rows = np.minimum(np.arange(index, index + horizon_steps + 1), len(scenario) - 1)
    window = scenario.iloc[rows].copy()
    step = float(scenario.index[1] - scenario.index[0]) if len(scenario) > 1 else 3600.0
    window.index = pd.Index(float(scenario.index[index]) + np.arange(horizon_steps + 1) * step,
                            name=scenario.index.name)
    return window


@dataclasses.dataclass
class ClosedLoopResult:
    """Records of a closed-loop run.

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
    wall_s : float
        Wall time of the whole loop [s].
    """

    steps: pd.DataFrame
    fine: pd.DataFrame
    plans: list[pd.DataFrame]
    wall_s: float


def step_row(result: MpcResult, record: StepRecord, state_names: tuple[str, ...],
             control_names: tuple[str, ...]) -> dict:
    """The per-step record of one loop iteration (shared with the ROS nodes' tools)."""
    row = {'time_s': record.t_start_s}
    for name, value in zip(control_names, record.controls):
        row[name] = float(value)
    for i, name in enumerate(state_names):
        row[f'{name}_start'] = float(record.x_start[i])
        row[f'{name}_end'] = float(record.x_end[i])
        row[f'{name}_predicted'] = float(result.states[1, i])
    row.update(solve_time_s=result.solve_time_s, success=bool(result.success),
               status=int(result.status), iterations=int(result.nit),
               objective=float(result.fun), max_defect=result.max_defect,
               relaxed=bool(result.relaxed), model_evaluations=int(result.model_evaluations))
    return row


def run_closed_loop(mpc: MPC, emulator: Emulator, steps: int | None = None,
                    progress: Callable[[list[dict], list[pd.DataFrame]], None] | None = None,
                    log_every: int = 12, budget_s: float | None = None) -> ClosedLoopResult:
    """Run MPC against the emulator for ``steps`` control steps (default: to the end).

    Parameters
    ----------
    mpc : MPC
        The controller; its step must equal the emulator's.
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
        Wall-time budget [s]: no step is started once it is spent, and the
        result holds the steps done (at least one).
    """
    if abs(mpc.step_s - emulator.step_s) > 1e-9:
        raise ValueError(f'MPC step {mpc.step_s} s differs from the emulator step '
                         f'{emulator.step_s} s')
    total = emulator.steps_left if steps is None else int(steps)
    if not 0 < total <= emulator.steps_left:
        raise ValueError(f'steps must be in [1, {emulator.steps_left}], got {steps}')
    rows, fines, plans = [], [], []
    started = time.perf_counter()
    for k in range(total):
        if k and budget_s is not None and time.perf_counter() - started > budget_s:
            logger.info('budget of %.0f s spent after %d/%d steps', budget_s, k, total)
            break
        forecast = forecast_window(emulator.scenario, emulator.index, mpc.horizon_steps)
        result = mpc.solve(emulator.x, emulator.t_s, forecast)
        record = emulator.advance(result.controls[0])
        row = step_row(result, record, mpc.model.state_names, mpc.problem.control_names)
        rows.append(row)
        fines.append(record.fine if k == 0 else record.fine.iloc[1:])
        plans.append(result.plan)
        if progress is not None:
            progress(rows, fines)
        if log_every and ((k + 1) % log_every == 0 or k + 1 == total):
            logger.info('step %d/%d (t = %.0f h): solve %.3f s, %s', k + 1, total,
                        row['time_s'] / 3600.0, row['solve_time_s'],
                        'ok' if row['success'] else 'not converged')
    steps_df = pd.DataFrame(rows).set_index('time_s')
    fine = pd.concat(fines)
    return ClosedLoopResult(steps_df, fine, plans, time.perf_counter() - started)
