"""
How far forecast errors can move a plan's states: the comfort margin of an uncertain forecast.

A forecast with BOPTEST's errors (:mod:`mshoot_core.forecast`) differs from the truth by an AR(1)
error per point: ``e[0]`` with standard deviation ``s0``, ``e[k+1] = a e[k] + w`` with ``w`` of
standard deviation ``s``. Its variance at lead ``k`` is known from the level's parameters
(:func:`error_processes`). Along a plan, the states' deviation from the plan that these errors
cause is linear in them to first order:

    dx[k+1] = A_k dx[k] + B_k g_k e[k],     dx[0] = 0

with ``A_k`` and ``B_k`` the model's derivatives of one interval's end state with respect to its
start state and to the inputs with errors, along the prediction with the inputs as forecast
(controls as assumed), and ``g_k`` how much of the error the input can carry (1 for a
temperature; for an irradiance, clipped by BOPTEST to [0.2, 2] x the truth, at most the forecast
value over the error's std, so none at night). The errors being correlated over the horizon, the
state and the errors are propagated together (:func:`forecast_error_std`): the covariance of
``[dx, e]`` with ``M_k = [[A_k, B_k G_k], [0, diag(a)]]``,
``P[k+1] = M_k P[k] M_k' + diag(0, s**2)``, ``P[0] = diag(0, s0**2)``; the result is the
standard deviation of every state at every row.

The controller narrows the comfort band on each side by ``forecast_margin_std`` of these
standard deviations of the zone temperature (an error can leave the zone too cold or, with more
sun than forecast on a slab heated ahead, too warm) (settings ``forecast_error_inputs``,
``forecast_uncertainty``: :class:`~mshoot_core.settings.ComfortSettings`).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Mapping, Sequence

import numpy as np

from mshoot_core.forecast import SOLAR_ERRORS, TEMPERATURE_ERRORS
from mshoot_core.models.base import accepts_start_times, Model, ModelValueError

logger = logging.getLogger(__name__)

#: The kinds of forecast error of ``forecast_error_inputs``: BOPTEST's two error models.
ERROR_KINDS = ('temperature', 'solar')
#: Relative finite-difference step of the fallback derivatives [-].
FD_STEP = 1e-6


@dataclasses.dataclass(frozen=True)
class ErrorProcess:
    """
    The AR(1) forecast error of one model input.

    Attributes
    ----------
    index : int
        The input's column in the model's inputs.
    first_std : float
        Standard deviation of the error at lead 0 [input unit].
    coefficient : float
        Autocorrelation from one grid point to the next [-].
    innovation_std : float
        Standard deviation of the innovation [input unit].
    bounded : bool
        The error is at most the forecast value (an irradiance: none at night).

    """

    index: int
    first_std: float
    coefficient: float
    innovation_std: float
    bounded: bool = False

    def std(self, lead: int) -> float:
        """Return the error's standard deviation at lead ``lead`` (grid points) [input unit]."""
        a2 = self.coefficient ** 2
        var = self.first_std ** 2
        for _ in range(int(lead)):
            var = a2 * var + self.innovation_std ** 2
        return math.sqrt(var)


def error_processes(kinds: Mapping[str, str], level: str,
                    input_names: Sequence[str]) -> list[ErrorProcess]:
    """
    Return the error processes of the inputs in ``kinds`` at BOPTEST's ``level``.

    Parameters
    ----------
    kinds : dict of str -> str
        Model input -> its error kind (:data:`ERROR_KINDS`).
    level : str
        A level of :data:`mshoot_core.settings.UNCERTAINTY_LEVELS` ('none': no process).
    input_names : sequence of str
        The model's inputs.

    Raises
    ------
    ValueError
        For an input the model does not have or an unknown kind or level.

    """
    if level == 'none':
        return []
    if level not in TEMPERATURE_ERRORS:
        raise ValueError(f'forecast_uncertainty: unknown level {level!r}')
    out = []
    for name, kind in kinds.items():
        if name not in input_names:
            raise ValueError(f'forecast_error_inputs: {name!r} is not an input of the model '
                             f'{list(input_names)}')
        if kind == 'temperature':
            t = TEMPERATURE_ERRORS[level]
            out.append(ErrorProcess(list(input_names).index(name), t.K0, t.F, t.K))
        elif kind == 'solar':  # Laplace scale b: standard deviation sqrt(2) b
            s = SOLAR_ERRORS[level]
            out.append(ErrorProcess(list(input_names).index(name), math.sqrt(2.0) * s.bg0,
                                    s.phi, math.sqrt(2.0) * s.bg, bounded=True))
        else:
            raise ValueError(f'forecast_error_inputs: kind of {name!r} must be one of '
                             f'{list(ERROR_KINDS)}, got {kind!r}')
    return out


def _interval(model: Model, x: np.ndarray, u: np.ndarray, dt_s: float, wrt: list[int],
              t_s: float, times: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the end state and its derivatives w.r.t. the start state and inputs ``wrt``."""
    kwargs = {'t_start_s': np.array([t_s])} if times else {}
    jac = model.interval_jacobians(x[None], u[None], dt_s, wrt, **kwargs)
    if jac is not None:
        return (np.asarray(jac.x_end[0], dtype=float), np.asarray(jac.dx_dx0[0], dtype=float),
                np.asarray(jac.dx_du[0], dtype=float).reshape(x.size, len(wrt)))
    nx = x.size
    dx = FD_STEP * np.maximum(1.0, np.abs(x))
    du = FD_STEP * np.maximum(1.0, np.abs(u[wrt]))
    starts = np.vstack([x, x + np.diag(dx), np.tile(x, (len(wrt), 1))])
    inputs = np.tile(u, (1 + nx + len(wrt), 1))
    for k, j in enumerate(wrt):
        inputs[1 + nx + k, j] += du[k]
    kwargs = {'t_start_s': np.full(len(starts), t_s)} if times else {}
    ends, _ = model.simulate_intervals(starts, inputs, dt_s, **kwargs)
    return (ends[0], ((ends[1:nx + 1] - ends[0]) / dx[:, None]).T,
            ((ends[nx + 1:] - ends[0]) / du[:, None]).T)


def forecast_error_std(model: Model, x0: np.ndarray, inputs: np.ndarray, dt_s: float,
                       processes: Sequence[ErrorProcess], t0_s: float = 0.0) -> np.ndarray:
    """
    Return the standard deviation of every state along a prediction from forecast errors.

    Parameters
    ----------
    model : Model
        The control model.
    x0 : ndarray, shape (nx,)
        The start state (taken as known).
    inputs : ndarray, shape (n, nu)
        The inputs over each of ``n`` intervals (controls as assumed, disturbances as
        forecast).
    dt_s : float
        Interval length [s].
    processes : sequence of ErrorProcess
        The inputs' forecast errors (:func:`error_processes`); none: zeros.
    t0_s : float
        Start time [s] (for models with time-dependent inputs).

    Returns
    -------
    ndarray, shape (n + 1, nx)
        Row 0 zeros, row ``k`` the std at the end of interval ``k`` [state units].

    Raises
    ------
    ModelValueError
        If the model's prediction is not finite.

    """
    x = np.asarray(x0, dtype=float).copy()
    inputs = np.asarray(inputs, dtype=float).reshape(-1, len(model.input_names))
    nx, m = x.size, len(processes)
    out = np.zeros((len(inputs) + 1, nx))
    if m == 0:
        return out
    wrt = [p.index for p in processes]
    phi = np.diag([p.coefficient for p in processes])
    q = np.zeros((nx + m, nx + m))
    q[nx:, nx:] = np.diag([p.innovation_std ** 2 for p in processes])
    cov = np.zeros((nx + m, nx + m))
    cov[nx:, nx:] = np.diag([p.first_std ** 2 for p in processes])
    times = accepts_start_times(model)
    for k, u in enumerate(inputs):
        x_end, a, b = _interval(model, x, u, dt_s, wrt, t0_s + k * dt_s, times)
        if not (np.all(np.isfinite(x_end)) and np.all(np.isfinite(a))
                and np.all(np.isfinite(b))):
            raise ModelValueError(f'{type(model).__name__}: non-finite prediction {x_end} from '
                                  f'{x} at {t0_s + k * dt_s:g} s', time_s=t0_s + k * dt_s)
        gain = np.ones(m)
        for i, p in enumerate(processes):
            if p.bounded:
                std = p.std(k)
                gain[i] = min(1.0, max(0.0, float(u[p.index])) / std) if std > 0 else 0.0
        step = np.zeros((nx + m, nx + m))
        step[:nx, :nx] = a
        step[:nx, nx:] = b * gain[None, :]
        step[nx:, nx:] = phi
        cov = step @ cov @ step.T + q
        out[k + 1] = np.sqrt(np.clip(np.diag(cov)[:nx], 0.0, None))
        x = x_end
    return out


def allowance(errors: object) -> dict[str, str]:
    """
    Return the flat MPC settings of a plan that allows for a forecast's errors.

    ``forecast_uncertainty`` = the forecast's level (the higher of the temperature's and the
    solar's): the controller is told the published level of the forecasts it gets, as a
    building's operator knows the quality of a weather service. None or perfect forecasts:
    nothing (the settings' own).

    Parameters
    ----------
    errors : ForecastErrorSettings or None
        The forecast's errors.

    """
    from mshoot_core.settings import UNCERTAINTY_LEVELS
    if errors is None:
        return {}
    level = max(errors.temperature_uncertainty, errors.solar_uncertainty,
                key=UNCERTAINTY_LEVELS.index)
    return {} if level == 'none' else {'forecast_uncertainty': level}
