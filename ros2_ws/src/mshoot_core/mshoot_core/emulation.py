"""
The emulated building: advances a model one control step at a time.

Both the offline MPC loop and the ROS emulator node drive an :class:`Emulator`,
so a ROS run and a core-only run of the same scenario produce the same
trajectory.
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Sequence

import numpy as np
import pandas as pd

from mshoot_core.models.base import Model
from mshoot_core.scenario import DISTURBANCE_COLUMNS, validate_scenario

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class StepRecord:
    """
    What the emulator did over one control step.

    Attributes
    ----------
    t_start_s : float
        Start of the step [s].
    controls : ndarray, shape (nc,)
        Control inputs applied (after clipping).
    x_start, x_end : ndarray, shape (nx,)
        States at the start and end of the step.
    fine : DataFrame
        States and outputs on the fine grid over [t_start, t_start + step], with
        the comfort band; index time [s].

    """

    t_start_s: float
    controls: np.ndarray
    x_start: np.ndarray
    x_end: np.ndarray
    fine: pd.DataFrame


class Emulator:
    """
    Steps a model through a scenario with controls given step by step.

    Parameters
    ----------
    model : Model
        The emulation model (e.g. the R1C1 FMU or :class:`R1C1Model`).
    scenario : DataFrame
        Disturbances and comfort band (see :mod:`mshoot_core.scenario`).
    x0 : sequence of float
        State at the first scenario time.
    control_names : sequence of str
        Model inputs set by the controller (default ``('q',)``).
    control_bounds : sequence of (float, float)
        Actuator limits per control; values outside are clipped with a warning.
    step_s : float
        Control step [s].
    fine_step_s : float
        Grid of the recorded fine trajectory [s] (60 s: the 1-minute KPI grid).
    start_index : int
        Scenario row to start from (restarts mid-run).

    """

    def __init__(self, model: Model, scenario: pd.DataFrame, x0: Sequence[float], *,
                 control_names: Sequence[str] = ('q',),
                 control_bounds: Sequence[tuple[float, float]] = ((-2000.0, 2000.0),),
                 step_s: float = 3600.0, fine_step_s: float = 60.0,
                 start_index: int = 0) -> None:
        validate_scenario(scenario)
        unknown = [c for c in control_names if c not in model.input_names]
        if unknown:
            raise ValueError(f'controls {unknown} are not inputs of the model '
                             f'{list(model.input_names)}')
        if len(control_bounds) != len(control_names):
            raise ValueError(f'need one (min, max) per control, got {len(control_bounds)} for '
                             f'{len(control_names)} controls')
        for lo, hi in control_bounds:
            if not lo <= hi:
                raise ValueError(f'control bounds must have min <= max, got ({lo}, {hi})')
        if step_s <= 0 or fine_step_s <= 0 or step_s % fine_step_s:
            raise ValueError(f'step_s ({step_s}) must be a positive multiple of fine_step_s '
                             f'({fine_step_s})')
        dt = np.diff(np.asarray(scenario.index, dtype=float))
        if not np.allclose(dt, step_s):
            raise ValueError(f'scenario rows must be step_s = {step_s} s apart')
        if not 0 <= start_index < len(scenario) - 1:
            raise ValueError(f'start_index must be in [0, {len(scenario) - 2}], got {start_index}')
        self.model = model
        self.scenario = scenario
        self.control_names = tuple(control_names)
        self.control_bounds = np.asarray(control_bounds, dtype=float)
        self.step_s = float(step_s)
        self.fine_step_s = float(fine_step_s)
        self.index = start_index
        self.x = np.asarray(x0, dtype=float).reshape(-1)
        if self.x.size != len(model.state_names) or not np.all(np.isfinite(self.x)):
            raise ValueError(f'x0 must be {len(model.state_names)} finite values, got {x0}')

    @property
    def t_s(self) -> float:
        """Return the current time [s]."""
        return float(self.scenario.index[self.index])

    @property
    def steps_left(self) -> int:
        """Return the number of control steps left in the scenario."""
        return len(self.scenario) - 1 - self.index

    def disturbances(self) -> pd.Series:
        """Disturbances of the current step (the scenario row at :attr:`t_s`)."""
        return self.scenario.iloc[self.index][list(DISTURBANCE_COLUMNS)]

    def clip(self, controls: Sequence[float]) -> np.ndarray:
        """Clip controls to the actuator limits, warning when anything changes."""
        u = np.asarray(controls, dtype=float).reshape(-1)
        if u.size != len(self.control_names):
            raise ValueError(f'expected {len(self.control_names)} controls '
                             f'{list(self.control_names)}, got {u.size}')
        if not np.all(np.isfinite(u)):
            raise ValueError(f'controls must be finite, got {u}')
        clipped = np.clip(u, self.control_bounds[:, 0], self.control_bounds[:, 1])
        if np.any(clipped != u):
            logger.warning('controls %s clipped to the actuator limits: %s', u, clipped)
        return clipped

    def advance(self, controls: Sequence[float]) -> StepRecord:
        """Apply ``controls`` over the current step and move to the next one."""
        if self.steps_left <= 0:
            raise RuntimeError('the scenario is over: no step left to emulate')
        u = self.clip(controls)
        row = self.scenario.iloc[self.index]
        n_fine = int(round(self.step_s / self.fine_step_s))
        times = self.t_s + np.arange(n_fine + 1) * self.fine_step_s
        inputs = {}
        for name in self.model.input_names:
            if name in self.control_names:
                inputs[name] = np.full(n_fine + 1, u[self.control_names.index(name)])
            elif name in row.index:
                inputs[name] = np.full(n_fine + 1, float(row[name]))
            else:
                raise ValueError(f'model input {name!r} is neither a control nor a scenario '
                                 f'column ({list(row.index)})')
        udf = pd.DataFrame(inputs, index=pd.Index(times, name='time_s'))
        ydf, xdf = self.model.simulate(udf, self.x)
        fine = pd.concat([xdf.add_prefix('x_'), ydf.add_prefix('y_')], axis=1)
        fine['comfort_min'] = float(row['comfort_min'])
        fine['comfort_max'] = float(row['comfort_max'])
        for name, value in zip(self.control_names, u):
            fine[name] = value
        record = StepRecord(self.t_s, u, self.x.copy(), xdf.to_numpy()[-1].copy(), fine)
        self.x = record.x_end.copy()
        self.index += 1
        return record
