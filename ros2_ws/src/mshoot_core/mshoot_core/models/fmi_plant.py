"""
An FMU model as a plant: one instance stepped forward for a whole run (:mod:`.fmi`).

The emulated building must behave like a building: every internal state of
its FMU (the ones the model maps and all others: wall temperatures, meters,
controllers, weather readers, schedules) carries over from one step to the
next. :class:`FmuPlant` gives :class:`~mshoot_core.models.fmi.FmiModel`:

- :meth:`FmuPlant.plant_start`: initialise once, at a time (caller's time
  base) with the mapped states and the first inputs;
- :meth:`FmuPlant.plant_step`: apply inputs (held over the step) and advance:
  Co-Simulation ``fmi2DoStep``; Model Exchange integrated on (CVode, events
  handled; an input change is an event). Never re-initialised;
- :meth:`FmuPlant.plant_get` / :meth:`FmuPlant.plant_set`: read any Real variable; set FMU
  variables that are not model inputs (Real or
  Boolean: an overwrite's value and its ``activate`` switch) from now on; in Model Exchange
  an event;
- :meth:`FmuPlant.plant_switches`: set overwrite switches (the fixed inputs, e.g. a
  card's ``activate`` ``X_activate``) from the next step on: 0 releases the overwrite, the
  building's own controller acts (an input event in Model Exchange);
- :meth:`FmuPlant.plant_save` / :meth:`FmuPlant.plant_restore`: the whole FMU
  state as bytes (``fmi2SerializeFMUstate``) with the plant's time and
  inputs, to resume a run where the FMU can serialise its state
  (:attr:`FmuPlant.can_save_plant`).

Any batch call of the model (``simulate``, ``simulate_intervals``,
``interval_jacobians``) re-initialises the instance and so ends the plant run:
use one model per role. Non-finite states or outputs raise
:class:`~mshoot_core.models.fmi_values.FmuValueError` naming the variable and
the FMU time.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import struct
from typing import Mapping, Sequence

import numpy as np

logger = logging.getLogger(__name__)

#: First bytes of a saved plant state.
PLANT_MAGIC = b'MSHOOT-PLANT\x01'


@dataclasses.dataclass
class _PlantRun:
    """Where the plant is: FMU time [s] and the inputs applied."""

    time: float
    inputs: np.ndarray


class FmuPlant:
    """
    The plant part of :class:`~mshoot_core.models.fmi.FmiModel` (a mixin, see the module).

    Keeps the run in ``_plant`` (None when no run is going on).
    """

    # -- the run -------------------------------------------------------------------------------
    @property
    def plant_time_s(self) -> float | None:
        """Return the current time of the plant run in the caller's time base [s], or None."""
        if self._plant is None:
            return None
        return self._plant.time + self.time_origin_s

    def _plant_inputs(self, u: Sequence[float]) -> np.ndarray:
        values = np.asarray(u, dtype=float).reshape(-1)
        if values.size != len(self.input_names) or not np.all(np.isfinite(values)):
            raise ValueError(f'plant inputs must be {len(self.input_names)} finite values '
                             f'({list(self.input_names)}), got {u}')
        return values

    def plant_start(self, x0: Sequence[float], t_s: float,
                    u: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """
        Initialise the plant at time ``t_s`` with states ``x0`` and inputs ``u``.

        Parameters
        ----------
        x0 : sequence of float, length nx
            Mapped states (the model's units), set before initialisation (and
            written into the continuous states in Model Exchange).
        t_s : float
            Start time [s], caller's time base (FMU time ``t_s - time_origin_s``).
        u : sequence of float, length nu
            Inputs during initialisation and the first step.

        Returns
        -------
        x, y : ndarray, shapes (nx,), (ny,)
            States and outputs after initialisation.

        """
        x0 = np.asarray(x0, dtype=float).reshape(-1)
        if x0.size != len(self.state_names) or not np.all(np.isfinite(x0)):
            raise ValueError(f'x0 must be {len(self.state_names)} finite values '
                             f'({list(self.state_names)}), got {x0}')
        if not math.isfinite(float(t_s)):
            raise ValueError(f't_s must be a finite time [s], got {t_s}')
        inputs = self._plant_inputs(u)
        self._plant = None
        time = float(t_s) - self.time_origin_s
        self._initialize(time, x0, inputs)  # (the switches as fixed: on)
        state = getattr(self, '_switch_state', None)
        if state:  # switched off before the start: from the first step on
            self._switch_pending = {n: v for n, v in state.items() if self.fixed_inputs[n] != v}
        self._plant = _PlantRun(time, inputs.copy())
        x, y = self._read()
        self._check_finite(x, y, time, ' (plant initialisation)')
        logger.debug('%s: plant started at FMU time %g s', self.fmu_path.name, time)
        return x, y

    def plant_switches(self, values: Mapping[str, bool]) -> None:
        """
        Set overwrite switches (fixed inputs of the model) from the next :meth:`plant_step` on.

        Parameters
        ----------
        values : mapping of str to bool
            Fixed input (an overwrite switch ``X_activate``) -> on (1, the overwrite applies)
            or off (0, released: the building's own controller acts).

        Raises
        ------
        ValueError
            For a name that is not a fixed input of the model.

        """
        unknown = [name for name in values if name not in self.fixed_inputs]
        if unknown:
            raise ValueError(f'{self.fmu_path.name}: {unknown} are not overwrite switches '
                             f'(fixed inputs) of the model: {sorted(self.fixed_inputs)}')
        current = getattr(self, '_switch_state', None) or dict(self.fixed_inputs)
        wanted = {**current, **{name: int(bool(on)) for name, on in values.items()}}
        if wanted != current:
            self._switch_pending = {n: v for n, v in wanted.items() if current.get(n) != v}
        self._switch_state = wanted

    @property
    def switch_state(self) -> dict[str, int]:
        """Return the overwrite switches (fixed inputs) as the plant applies them."""
        return dict(getattr(self, '_switch_state', None) or self.fixed_inputs)

    def _apply_switches(self, t: float, inputs: np.ndarray) -> bool:
        """Apply pending switches (and ``inputs``) at ``t``; return True when there were any."""
        pending = getattr(self, '_switch_pending', None)
        if not pending:
            return False
        fmu = self._fmu
        if self.is_model_exchange:
            fmu.enterEventMode()
        for name, value in pending.items():
            var = self._variables[name]
            kind = {'Enumeration': 'Integer'}.get(var.type, var.type)
            cast = {'Boolean': bool, 'Integer': int}.get(kind, float)
            getattr(fmu, f'set{kind}')([var.valueReference], [cast(value)])
        self._set_inputs(inputs)
        if self.is_model_exchange:
            self._event_iteration()
            fmu.enterContinuousTimeMode()
            self._ensure_solver(t)
        self._switch_pending = {}
        logger.info('%s: overwrite switches %s at FMU time %g s', self.fmu_path.name,
                    pending, t)
        return True

    def _require_plant(self) -> _PlantRun:
        if self._plant is None:
            raise RuntimeError(f'{self.fmu_path.name}: no plant run (call plant_start or '
                               'plant_restore; a simulate/simulate_intervals/'
                               'interval_jacobians call on this model ends a run)')
        return self._plant

    def plant_step(self, u: Sequence[float], dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """
        Hold inputs ``u`` for ``dt_s`` [s] and advance the plant; return the end values.

        Co-Simulation: one ``fmi2DoStep``. Model Exchange: integrated on from
        where the last step ended (an input change is an event); the solver
        is not re-started when the inputs stay the same.

        Returns
        -------
        x, y : ndarray, shapes (nx,), (ny,)
            States and outputs at the end of the step.

        Raises
        ------
        FmuValueError
            If a state or output is not finite (named with the FMU time); the
            run is then over: do not step the plant further.
        RuntimeError
            Without a plant run.

        """
        plant = self._require_plant()
        dt_s = float(dt_s)
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f'dt_s must be a positive number of seconds, got {dt_s}')
        inputs = self._plant_inputs(u)
        t, t_end = plant.time, plant.time + dt_s
        if self._apply_switches(t, inputs):
            plant.inputs = inputs.copy()
        elif not np.array_equal(inputs, plant.inputs):
            self._switch_inputs(t, inputs)
            plant.inputs = inputs.copy()
        self._advance_checked(t, t_end)
        plant.time = t_end
        x, y = self._read()
        self._check_finite(x, y, t_end, ' (plant step)')
        return x, y

    def plant_set(self, values: Mapping[str, float | bool]) -> None:
        """
        Set FMU variables that are not model inputs from now on (held until set again).

        Real variables take a float, Boolean ones a bool; in Model Exchange the change is an
        event at the plant's time (event mode, new discrete states, a solver re-start), in
        Co-Simulation it takes effect over the next step.

        Raises
        ------
        ValueError
            For an unknown variable, or one neither Real nor Boolean.
        RuntimeError
            Without a plant run.

        """
        plant = self._require_plant()
        groups: dict[str, tuple[list[int], list]] = {'Real': ([], []), 'Boolean': ([], [])}
        for name, value in values.items():
            variable = self._variables.get(name)
            if variable is None or variable.type not in groups:
                raise ValueError(f'{self.fmu_path.name}: {name!r} is not a Real or Boolean '
                                 'variable of the FMU')
            refs, numbers = groups[variable.type]
            refs.append(variable.valueReference)
            numbers.append(bool(value) if variable.type == 'Boolean' else float(value))
        if not any(refs for refs, _ in groups.values()):
            return
        fmu = self.fmu
        if self.is_model_exchange:
            fmu.enterEventMode()
        for kind, (refs, numbers) in groups.items():
            if refs:
                getattr(fmu, f'set{kind}')(refs, numbers)
        if self.is_model_exchange:
            self._event_iteration()
            fmu.enterContinuousTimeMode()
            self._ensure_solver(plant.time)

    def plant_get(self, names: Sequence[str]) -> dict[str, float]:
        """
        Return any Real variables of the FMU now (name -> value), mapped or not.

        Raises
        ------
        ValueError
            For a name that is not a Real variable of the FMU.
        RuntimeError
            Without a plant run.

        """
        self._require_plant()
        variables = [self._variables.get(name) for name in names]
        unknown = [n for n, v in zip(names, variables) if v is None or v.type != 'Real']
        if unknown:
            raise ValueError(f'{self.fmu_path.name}: not Real variables of the FMU: {unknown}')
        values = self.fmu.getReal([v.valueReference for v in variables])
        return {name: float(value) for name, value in zip(names, values)}

    def plant_read(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the plant's current (states, outputs)."""
        self._require_plant()
        return self._read()

    # -- save and restore ------------------------------------------------------------------------
    @property
    def can_save_plant(self) -> bool:
        """Whether the FMU can get, set and serialise its state (this interface)."""
        return bool(self._interface.canGetAndSetFMUstate
                    and self._interface.canSerializeFMUstate)

    def _plant_header(self) -> dict:
        return {'guid': self.model_description.guid, 'fmi_type': self.fmi_type,
                'inputs': list(self.input_names), 'states': list(self.state_names)}

    def plant_save(self) -> bytes:
        """
        Return the whole plant (FMU state, time, inputs) as bytes for :meth:`plant_restore`.

        Raises
        ------
        ValueError
            If the FMU cannot serialise its state (:attr:`can_save_plant`).
        RuntimeError
            Without a plant run.

        """
        plant = self._require_plant()
        if not self.can_save_plant:
            raise ValueError(f'{self.fmu_path.name} ({self.fmi_type}) cannot save its state '
                             '(canGetAndSetFMUstate and canSerializeFMUstate are needed): '
                             'restart it with a warm-up from the scenario start instead')
        fmu = self.fmu
        state = fmu.getFMUstate()
        try:
            data = fmu.serializeFMUstate(state)
        finally:
            fmu.freeFMUstate(state)
        header = dict(self._plant_header(), time=plant.time,
                      inputs_applied=[float(v) for v in plant.inputs],
                      next_event_time=getattr(self, '_next_event_time', None))
        text = json.dumps(header).encode()
        return PLANT_MAGIC + struct.pack('<I', len(text)) + text + data

    def plant_restore(self, saved: bytes) -> tuple[np.ndarray, np.ndarray]:
        """
        Resume a plant saved by :meth:`plant_save` (same FMU, same role); return (x, y).

        Raises
        ------
        ValueError
            If ``saved`` is not a plant state of this FMU and interface, or the
            FMU cannot restore its state.

        """
        if not isinstance(saved, (bytes, bytearray)) or not saved.startswith(PLANT_MAGIC):
            raise ValueError('not a saved plant state (expected the bytes of plant_save)')
        if not self.can_save_plant:
            raise ValueError(f'{self.fmu_path.name} ({self.fmi_type}) cannot restore a saved '
                             'state (canGetAndSetFMUstate and canSerializeFMUstate are needed)')
        offset = len(PLANT_MAGIC)
        (size,) = struct.unpack_from('<I', saved, offset)
        try:
            header = json.loads(bytes(saved[offset + 4:offset + 4 + size]))
        except ValueError as error:
            raise ValueError(f'a corrupt saved plant state ({error})') from error
        expected = self._plant_header()
        different = {k: (header.get(k), v) for k, v in expected.items() if header.get(k) != v}
        if different:
            raise ValueError(f'the saved plant state is not one of this model '
                             f'({self.fmu_path.name}): (saved, this model) differ in '
                             f'{different}')
        fmu = self.fmu
        self._plant = None
        state = fmu.deSerializeFMUstate(bytes(saved[offset + 4 + size:]))
        try:
            fmu.setFMUstate(state)
        finally:
            fmu.freeFMUstate(state)
        self._initialized_once = True  # a later initialisation resets first
        time = float(header['time'])
        if self.is_model_exchange:
            self._next_event_time = header.get('next_event_time')
            self._ensure_solver(time)
        self._plant = _PlantRun(time, np.asarray(header['inputs_applied'], dtype=float))
        x, y = self._read()
        self._check_finite(x, y, time, ' (restored plant)')
        logger.info('%s: plant restored at FMU time %g s', self.fmu_path.name, time)
        return x, y
