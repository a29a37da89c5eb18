"""
The emulated building: advances a model one control step at a time.

Both the offline MPC loop and the ROS emulator node drive an :class:`Emulator`,
so a ROS run and a core-only run of the same scenario produce the same
trajectory.

A model that offers a plant (``plant_start``/``plant_step``, e.g.
:class:`~mshoot_core.models.fmi.FmiModel`) is one FMU instance stepped forward
for the whole run and never re-initialised, so every internal state of the
building carries over (e.g. the R1C1 FMU's energy meter ``Qr`` keeps counting);
its time is the scenario's (seconds since the first row), which the model maps
to FMU time with its time origin. Other models (the exact Python R1C1) are
simulated step by step from the state, which is all they have.

A restart mid-run (``start_index`` > 0) resumes a plant from a saved state
(``plant_state``, from :meth:`Emulator.save_plant_state`, where the FMU can
serialise its state), or replays the run from the scenario start (``warmup``:
the first state and the controls applied so far), or else starts the plant at
that row from the given state (its other states then start from their start
values).

Non-finite states or outputs stop the emulation with a
:class:`~mshoot_core.models.base.ModelValueError` (for FMUs an
:class:`~mshoot_core.models.fmi_values.FmuValueError`) naming the variable and
the time; the step is not recorded.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Sequence

import numpy as np
import pandas as pd

from mshoot_core.controls import model_controls
from mshoot_core.models.base import Model, ModelValueError
from mshoot_core.scenario import COMFORT_COLUMNS, validate_scenario
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Warmup:
    """
    A replay from the scenario start that brings a restarted emulator to its start row.

    Attributes
    ----------
    x0 : sequence of float
        The state at the first scenario row (the interrupted run's initial state).
    controls : array, shape (start_index, nc)
        The controls applied at steps 0 .. start_index - 1 (e.g. from ``steps.csv``).

    """

    x0: Sequence[float]
    controls: np.ndarray


def initial_state(state_names: Sequence[str], temperature_c: float,
                  overrides: str = '') -> np.ndarray:
    """
    Return a zone model's initial state [K]: every state at ``temperature_c``, but those named.

    Parameters
    ----------
    state_names : sequence of str
        The model's states (temperatures in K).
    temperature_c : float
        Temperature of every state not overridden [degC].
    overrides : str
        Comma-separated ``name=temperature`` [degC], e.g. ``'Tw=18'`` (an envelope 3 K
        below the air at 21 degC); '' for none.

    Raises
    ------
    ValueError
        On a malformed item, an unknown or repeated state or a non-finite temperature.

    """
    names = tuple(state_names)
    x = np.full(len(names), float(temperature_c) + KELVIN)
    seen = set()
    for item in (i.strip() for i in overrides.split(',') if i.strip()):
        name, _, value = (part.strip() for part in item.partition('='))
        try:
            temperature = float(value)
        except ValueError:
            temperature = math.nan
        if name not in names or name in seen or not _ or not math.isfinite(temperature):
            raise ValueError(f"initial states must be 'name=degC' items of the states "
                             f'{list(names)}, each once, got {item!r}')
        seen.add(name)
        x[names.index(name)] = temperature + KELVIN
    return x


def is_plant(model: Model) -> bool:
    """Whether ``model`` offers a persistent plant (``plant_start`` and ``plant_step``)."""
    return all(callable(getattr(type(model), name, None))
               for name in ('plant_start', 'plant_step'))


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
        the comfort band, the controls and the overwrite switches of the controls that have
        one (by the switch's name, e.g. ``X_activate``: 1 applied, 0 released);
        index time [s].
    released : tuple of str
        The controls whose overwrite was released over the step (the building's own
        controller acted).

    """

    t_start_s: float
    controls: np.ndarray
    x_start: np.ndarray
    x_end: np.ndarray
    fine: pd.DataFrame
    released: tuple[str, ...] = ()


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
    control_bounds : sequence of (float, float), optional
        Actuator limits per control; values outside are clipped with a warning (default:
        the model's, from its card: :func:`mshoot_core.controls.model_controls`).
    step_s : float
        Control step [s].
    fine_step_s : float
        Grid of the recorded fine trajectory [s] (60 s: the 1-minute KPI grid).
    start_index : int
        Scenario row to start from (restarts mid-run); ``x0`` is the state there.
    plant_state : bytes, optional
        A plant saved by :meth:`save_plant_state` at row ``start_index``: the
        plant resumes from it (every internal state, the FMU's time).
    warmup : Warmup, optional
        Instead, replay the run from the scenario start to ``start_index``
        (first state and applied controls): every internal state as in the
        interrupted run, for any model.

    Raises
    ------
    ValueError
        On bad arguments, a ``plant_state`` of another model or time, or one
        for a model that cannot restore it.

    """

    def __init__(self, model: Model, scenario: pd.DataFrame, x0: Sequence[float], *,
                 control_names: Sequence[str] = ('q',),
                 control_bounds: Sequence[tuple[float, float]] | None = None,
                 step_s: float = 3600.0, fine_step_s: float = 60.0,
                 start_index: int = 0, plant_state: bytes | None = None,
                 warmup: Warmup | None = None) -> None:
        validate_scenario(scenario)
        unknown = [c for c in control_names if c not in model.input_names]
        if unknown:
            raise ValueError(f'controls {unknown} are not inputs of the model '
                             f'{list(model.input_names)}')
        #: The controls as the model's card describes them (units, limits, safe values).
        self.control_specs = model_controls(model, tuple(control_names))
        if control_bounds is None:  # (a side the card leaves open is not clipped)
            control_bounds = [(-math.inf if math.isnan(c.min) else c.min,
                               math.inf if math.isnan(c.max) else c.max)
                              for c in self.control_specs]
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
        #: Whether the model is stepped as a persistent plant.
        self.plant = is_plant(model)
        self._plant_running = False
        self._y: np.ndarray | None = None  # the plant's outputs at the current time
        if plant_state is not None and warmup is not None:
            raise ValueError('give either plant_state or warmup, not both')
        if plant_state is not None:
            self._restore(plant_state)
        elif warmup is not None:
            self._warm_up(warmup)
        elif self.plant and start_index > 0:
            logger.info('emulator restarts at row %d without a saved plant state or a warm-up: '
                        'the plant starts there from x0, its other states from their start '
                        'values', start_index)

    def _restore(self, plant_state: bytes) -> None:
        """Resume the plant saved at this row (see :meth:`save_plant_state`)."""
        if not self.plant or not callable(getattr(self.model, 'plant_restore', None)):
            raise ValueError(f'plant_state needs a model with a persistent plant (an FMU), got '
                             f'{type(self.model).__name__}')
        x, y = self.model.plant_restore(plant_state)
        saved_t = self.model.plant_time_s
        if saved_t is None or abs(saved_t - self.t_s) > 1e-6 * max(1.0, abs(self.t_s)):
            raise ValueError(f'the saved plant state is at t = {saved_t} s, the restart at row '
                             f'{self.index} (t = {self.t_s} s)')
        if not np.allclose(x, self.x, rtol=1e-9, atol=1e-9):
            logger.warning('restored plant state %s differs from x0 %s: the saved state wins',
                           x, self.x)
        self.x, self._y, self._plant_running = np.asarray(x, dtype=float), y, True

    def _warm_up(self, warmup: Warmup) -> None:
        """Replay steps 0 .. start_index - 1 from the scenario start (records dropped)."""
        target, x_target, nc = self.index, self.x.copy(), len(self.control_names)
        controls = np.asarray(warmup.controls, dtype=float)
        if controls.size != target * nc:
            raise ValueError(f'warmup.controls must be ({target}, {nc}): the controls of the '
                             f'{target} steps before start_index, got shape {controls.shape}')
        controls = controls.reshape(target, nc)
        x0 = np.asarray(warmup.x0, dtype=float).reshape(-1)
        if x0.size != self.x.size or not np.all(np.isfinite(x0)):
            raise ValueError(f'warmup.x0 must be {self.x.size} finite values, got {warmup.x0}')
        self.index, self.x = 0, x0
        for u in controls:
            self.advance(u)
        if not np.allclose(self.x, x_target, rtol=1e-6, atol=1e-6):
            logger.warning('after the warm-up the state is %s, not x0 %s: the warm-up wins',
                           self.x, x_target)
        logger.info('emulator warmed up over %d steps to row %d', target, self.index)

    @property
    def t_s(self) -> float:
        """Return the current time [s]."""
        return float(self.scenario.index[self.index])

    def _set_switches(self, released: Sequence[bool]) -> dict[str, int]:
        """
        Set the plant's overwrite switches for the step: off for the released controls.

        Returns the switch -> on (1) / off (0) of the controls that have one on this plant.
        """
        flags = tuple(bool(r) for r in released)
        if flags and len(flags) != len(self.control_names):
            raise ValueError(f'released must have one flag per control '
                             f'{list(self.control_names)}, got {list(flags)}')
        setter = getattr(self.model, 'plant_switches', None) if self.plant else None
        values = {c.switch: int(not (flags and flags[i]))
                  for i, c in enumerate(self.control_specs) if c.switch}
        if setter is None or not values:
            if any(flags):
                logger.debug('released controls without an overwrite switch on %s: their '
                             'safe values apply', type(self.model).__name__)
            return {}
        setter(values)
        return values

    @property
    def steps_left(self) -> int:
        """Return the number of control steps left in the scenario."""
        return len(self.scenario) - 1 - self.index

    def disturbances(self) -> pd.Series:
        """Disturbances of the current step (the scenario row at :attr:`t_s`)."""
        row = self.scenario.iloc[self.index]
        return row[[c for c in self.scenario.columns if c not in COMFORT_COLUMNS]]

    def clip(self, controls: Sequence[float], quiet: bool = False) -> np.ndarray:
        """Clip controls to the actuator limits, warning when anything changes (unless quiet)."""
        u = np.asarray(controls, dtype=float).reshape(-1)
        if u.size != len(self.control_names):
            raise ValueError(f'expected {len(self.control_names)} controls '
                             f'{list(self.control_names)}, got {u.size}')
        if not np.all(np.isfinite(u)):
            raise ValueError(f'controls must be finite, got {u}')
        clipped = np.clip(u, self.control_bounds[:, 0], self.control_bounds[:, 1])
        if not quiet and np.any(clipped != u):
            logger.warning('controls %s clipped to the actuator limits: %s', u, clipped)
        return clipped

    def save_plant_state(self) -> bytes:
        """
        Save the plant at the current row, for ``Emulator(..., start_index, plant_state=...)``.

        Raises
        ------
        ValueError
            If the model has no plant or cannot save its state.
        RuntimeError
            Before the first step (nothing to save yet: restart from x0).

        """
        if not self.plant or not callable(getattr(self.model, 'plant_save', None)):
            raise ValueError(f'{type(self.model).__name__} has no plant state to save: restart '
                             'it from its state x0')
        if not self._plant_running:
            raise RuntimeError('the plant has not started yet: nothing to save')
        return self.model.plant_save()

    def _step_inputs(self, u: np.ndarray, row: pd.Series) -> np.ndarray:
        """Return the model's inputs over the step: the controls and the scenario row's columns."""
        values = np.empty(len(self.model.input_names))
        for i, name in enumerate(self.model.input_names):
            if name in self.control_names:
                values[i] = u[self.control_names.index(name)]
            elif name in row.index:
                values[i] = float(row[name])
            else:
                raise ValueError(f'model input {name!r} is neither a control nor a scenario '
                                 f'column ({list(row.index)})')
        return values

    def start_plant(self, controls: Sequence[float]) -> None:
        """
        Start the plant now (not at the first step): its state becomes the current state.

        For plants that do something before their first step (a BOPTEST warm-up), so that the
        first published state is the plant's. ``controls`` only has to be valid (the first
        step's controls are applied by :meth:`advance`; they are clipped to the limits without a
        warning). Nothing happens for other models or a running plant.
        """
        if not self.plant or self._plant_running:
            return
        inputs = self._step_inputs(self.clip(controls, quiet=True), self.scenario.iloc[self.index])
        x, y = self.model.plant_start(self.x, self.t_s, inputs)
        self.x, self._y = np.asarray(x, dtype=float).reshape(-1), y
        self._plant_running = True

    def _plant_step(self, inputs: np.ndarray,
                    times: np.ndarray) -> tuple[pd.DataFrame, pd.DataFrame]:
        """
        Simulate the plant over one control step on the fine grid ``times``.

        ``inputs``: one row of inputs per fine interval (shape (n_fine, n_inputs)).
        """
        model = self.model
        if not self._plant_running:
            x, y = model.plant_start(self.x, self.t_s, inputs[0])
            self._plant_running = True
        else:
            x, y = self.x, self._y
        states, outputs = [x], [y]
        for k in range(times.size - 1):
            x, y = model.plant_step(inputs[k], self.fine_step_s)
            states.append(x)
            outputs.append(y)
        index = pd.Index(times, name='time_s')
        return (pd.DataFrame(np.array(outputs), index=index, columns=list(model.output_names)),
                pd.DataFrame(np.array(states), index=index, columns=list(model.state_names)))

    def _check_finite(self, ydf: pd.DataFrame, xdf: pd.DataFrame) -> None:
        """Raise ModelValueError for the first non-finite state or output of a step."""
        for kind, frame in (('state', xdf), ('output', ydf)):
            values = frame.to_numpy(dtype=float)
            bad = np.argwhere(~np.isfinite(values))
            if bad.size:
                row, col = bad[0]
                name, time = frame.columns[col], float(frame.index[row])
                raise ModelValueError(f'{type(self.model).__name__}: non-finite {kind} '
                                      f'{name!r} = {values[row, col]} at t = {time:.9g} s',
                                      variable=str(name), time_s=time)

    def advance(self, controls: Sequence[float],
                schedule: Sequence[tuple[float, Sequence[float]]] | None = None,
                released: Sequence[bool] = ()) -> StepRecord:
        """
        Apply ``controls`` over the current step and move to the next one.

        ``released``: per control (or empty: none), whether its overwrite is released over the
        step: a plant with the control's overwrite switch (the card's ``activate``) turns it
        off, so the building's own controller acts; a control without a switch gets its value
        in ``controls`` (the safe value of a released setpoint).

        ``schedule``: optional pieces within the step, ``(offset [s] from the step's start,
        controls from there on)`` with increasing offsets, the first 0, each a multiple of
        ``fine_step_s`` (a plant only): the controls then change within the step; ``controls``
        is what the step's record reports (e.g. the first piece's).

        Raises
        ------
        ModelValueError
            If the model produced a non-finite state or output (an FMU's
            :class:`~mshoot_core.models.fmi_values.FmuValueError` names the FMU
            time): the step is not taken, the emulation cannot go on.

        """
        if self.steps_left <= 0:
            raise RuntimeError('the scenario is over: no step left to emulate')
        u = self.clip(controls)
        switches = self._set_switches(released)
        row = self.scenario.iloc[self.index]
        n_fine = int(round(self.step_s / self.fine_step_s))
        times = self.t_s + np.arange(n_fine + 1) * self.fine_step_s
        inputs = self._step_inputs(u, row)
        fine_controls = np.tile(u, (n_fine, 1))
        if schedule:
            if not self.plant:
                raise ValueError('a schedule within the step needs a model with a plant')
            offsets = [float(o) for o, _ in schedule]
            if (offsets[0] != 0.0 or any(b <= a for a, b in zip(offsets, offsets[1:]))
                    or offsets[-1] >= self.step_s
                    or any(abs(o / self.fine_step_s - round(o / self.fine_step_s)) > 1e-9
                           for o in offsets)):
                raise ValueError(f'schedule offsets must start at 0, increase, stay within the '
                                 f'step and be multiples of {self.fine_step_s:g} s, got {offsets}')
            for offset, values in schedule:
                fine_controls[int(round(offset / self.fine_step_s)):] = self.clip(values)
        if self.plant:
            rows = np.array([self._step_inputs(c, row) for c in fine_controls])
            ydf, xdf = self._plant_step(rows, times)
        else:
            udf = pd.DataFrame(np.tile(inputs, (n_fine + 1, 1)),
                               index=pd.Index(times, name='time_s'),
                               columns=list(self.model.input_names))
            ydf, xdf = self.model.simulate(udf, self.x)
        self._check_finite(ydf, xdf)
        self._y = ydf.to_numpy()[-1].copy()
        fine = pd.concat([xdf.add_prefix('x_'), ydf.add_prefix('y_')], axis=1)
        fine['comfort_min'] = float(row['comfort_min'])
        fine['comfort_max'] = float(row['comfort_max'])
        for i, name in enumerate(self.control_names):
            fine[name] = np.append(fine_controls[:, i], fine_controls[-1, i])
        for switch, on in switches.items():
            fine[switch] = on
        record = StepRecord(self.t_s, u, self.x.copy(), xdf.to_numpy()[-1].copy(), fine,
                            tuple(n for n, c in zip(self.control_names, self.control_specs)
                                  if c.switch and not switches.get(c.switch, 1)))
        self.x = record.x_end.copy()
        self.index += 1
        return record
