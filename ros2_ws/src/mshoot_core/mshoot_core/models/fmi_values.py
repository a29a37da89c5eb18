"""
Non-finite values of FMU models (:mod:`.fmi`): one clear error instead of a solver's.

An FMU that computes NaN or inf (a division by zero past some time, a table
read out of range) used to surface as whatever failed next: ``NaN`` in a
trajectory file, or a CVode "step size underflow" / "corrector convergence"
message. :class:`FmuValueError` names the variable and the FMU time instead:

- end values of intervals and plant steps are checked
  (:meth:`NonFiniteChecks._check_finite`);
- CVode's right-hand side notes the first non-finite derivative it gets
  (:meth:`NonFiniteChecks._derivatives_checked`, with the FMU time);
- when an integrator fails, that derivative, or else the FMU's states, their
  derivatives and the outputs at the failure point
  (:meth:`NonFiniteChecks._diagnose`), becomes the error (the integrator's
  message is chained).

In the control model the error ends the solve (the controller falls back:
``'solve_failed'``); in the emulator it stops the run (the case command writes
the outputs up to the last good step and exits 1).
"""
from __future__ import annotations

import math

import numpy as np

from mshoot_core.models.base import ModelValueError
from mshoot_core.models.fmi_drivers import double_pointer

__all__ = ['FmuValueError', 'NonFiniteChecks']


class FmuValueError(ModelValueError):
    """
    An FMU produced a non-finite state, derivative or output.

    Attributes
    ----------
    variable : str
        The FMU variable (e.g. ``heatCapacitor.T``, ``der(heatCapacitor.T)``).
    time_s : float or None
        FMU time [s] at which it was seen.
    fmu : str
        File name of the FMU.

    """

    def __init__(self, fmu: str, kind: str, variable: str, value: float, time_s: float | None,
                 model_name: str | None = None, where: str = '') -> None:
        role = 'of model state' if kind == 'derivative' else f'model {kind}'
        alias = f' ({role} {model_name!r})' if model_name and model_name != variable else ''
        when = f'at FMU time {time_s:.9g} s' if time_s is not None else 'at an unknown time'
        super().__init__(f'{fmu}: non-finite {kind} {variable!r}{alias} = {value} {when}'
                         f'{where}', variable=variable, time_s=time_s)
        self.fmu = fmu


class NonFiniteChecks:
    """
    Finite-value checks of :class:`~mshoot_core.models.fmi.FmiModel` (a mixin).

    Uses the model's variable lists; keeps the last time set by an integrator
    (``_fmu_time``) and the first non-finite derivative CVode met
    (``_non_finite_seen``: (FMU time, index, value) or None) so that a failure
    can be named and dated.
    """

    def _record_time(self, time: float) -> None:
        """``fmi2SetTime`` for the integrators, remembering the time (to date a failure)."""
        self._fmu_time = time
        self._fmu.setTime(time)

    def _derivatives_checked(self, buffer: object, size: int) -> None:
        """``fmi2GetDerivatives`` for CVode, noting the first non-finite derivative."""
        self._fmu.getDerivatives(buffer, size)
        if getattr(self, '_non_finite_seen', None) is None:
            values = np.ctypeslib.as_array(buffer, (size,))
            if not np.isfinite(values).all():
                i = int(np.flatnonzero(~np.isfinite(values))[0])
                self._non_finite_seen = (getattr(self, '_fmu_time', None), i, float(values[i]))

    def _check_finite(self, x_end: np.ndarray, y_end: np.ndarray,
                      t_end: np.ndarray | float | None, where: str = '') -> None:
        """
        Raise :class:`FmuValueError` for the earliest non-finite entry of the end values.

        Parameters
        ----------
        x_end, y_end : ndarray, shape (B, nx), (B, ny) or (nx,), (ny,)
            End states and outputs.
        t_end : ndarray, shape (B,), or float, or None
            FMU times of those values [s] (None: unknown).
        where : str
            Appended to the message (e.g. which interval).

        """
        if np.isfinite(x_end).all() and np.isfinite(y_end).all():
            return
        x_end, y_end = np.atleast_2d(x_end), np.atleast_2d(y_end)
        times = np.broadcast_to(np.asarray(math.nan if t_end is None else t_end, dtype=float),
                                (x_end.shape[0],))
        bad = ~(np.isfinite(x_end).all(axis=1) & np.isfinite(y_end).all(axis=1))
        rows = np.flatnonzero(bad)
        b = int(rows[np.argmin(np.nan_to_num(times[rows], nan=math.inf))])
        time = float(times[b]) if math.isfinite(times[b]) else None
        for kind, values, names, variables in (
                ('state', x_end[b], self.state_names, self._state_vars),
                ('output', y_end[b], self.output_names, self._output_vars)):
            for i, value in enumerate(values):
                if not math.isfinite(value):
                    raise FmuValueError(fmu_name(self), kind, variables[i].name, float(value),
                                        time, names[i], where)

    def _diagnose(self, error: Exception, where: str = '') -> None:
        """
        Raise :class:`FmuValueError` if the FMU holds non-finite values after a failure.

        After an integrator failed: raise :class:`FmuValueError` if the FMU now holds a non-finite
        state, derivative or output; else return (the caller re-raises).
        """
        fmu = self._fmu
        time = getattr(self, '_fmu_time', None)
        n = getattr(self, '_n_continuous', 0)
        seen, self._non_finite_seen = getattr(self, '_non_finite_seen', None), None
        if seen is not None:
            seen_time, i, value = seen
            var = self._continuous_states[i]
            model_name = next((m for m, v in zip(self.state_names, self._state_vars)
                               if v is var), None)
            raise FmuValueError(fmu_name(self), 'derivative', f'der({var.name})', value,
                                seen_time, model_name, where) from error
        try:
            if n:
                states, derivatives = np.zeros(n), np.zeros(n)
                fmu.getContinuousStates(double_pointer(states), n)
                fmu.getDerivatives(double_pointer(derivatives), n)
                for values, kind in ((states, 'state'), (derivatives, 'derivative')):
                    for i in np.flatnonzero(~np.isfinite(values)):
                        var = self._continuous_states[i]
                        name = var.name if kind == 'state' else f'der({var.name})'
                        model_name = next((m for m, v in zip(self.state_names, self._state_vars)
                                           if v is var), None)
                        raise FmuValueError(fmu_name(self), kind, name, float(values[i]), time,
                                            model_name, where) from error
            x, y = self._read()
        except FmuValueError:
            raise
        except Exception:  # noqa: BLE001 - the FMU cannot even be read: keep the first error
            return
        try:
            self._check_finite(x, y, time, where)
        except FmuValueError as non_finite:
            raise non_finite from error


def fmu_name(model: object) -> str:
    """Return the FMU's file name of an FMU model."""
    return model.fmu_path.name
