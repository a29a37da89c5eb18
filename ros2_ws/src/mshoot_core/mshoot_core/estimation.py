"""
State estimation: the control model's full state from the states a sensor measures.

A richer zone model has states no sensor measures (the envelope temperature
``Tw`` of :class:`~mshoot_core.models.r2c2.R2C2Model`), which the MPC needs at
every step. :class:`StateEstimator` is an extended Kalman filter on any
:class:`~mshoot_core.models.base.Model`:

- *predict* over the interval since the last measurement with the inputs that
  were applied (controls and disturbances, held constant per interval, as the
  model simulates them): ``x = f(x, u)`` by the model itself,
  ``P = F P F' + Q dt/step`` with ``F = dx_end/dx_start`` from the model's
  :meth:`~mshoot_core.models.base.Model.interval_jacobians` (finite differences
  over :meth:`~mshoot_core.models.base.Model.simulate_intervals` for models
  without them);
- *correct* with the measured states ``z = H x + v``, ``H`` the rows of the
  measured states, ``v ~ N(0, R)``, in Joseph form (the covariance stays
  symmetric positive semi-definite).

``Q = diag(process_noise_k^2)`` per control step [K^2], ``R =
diag(measurement_noise_k^2)`` [K^2]; the first estimate takes the measured states
as measured and the others from a guess (:func:`initial_guess`) with the standard
deviation ``initial_std_k``.

Which states are measured is the model's to say (an attribute
``measured_states``; every state when it has none), or the settings'
(:class:`~mshoot_core.settings.EstimationSettings`, ``measured_states``);
:func:`estimation_needed` says when a controller estimates
(:class:`~mshoot_core.controller.Controller` does so by itself).

:class:`Sensors` turns an emulated state into what a sensor reads (the measured
states with seeded Gaussian noise, reproducible per step), for the offline loop
and the emulator node alike.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core.models.base import accepts_start_times, Model, ModelValueError
from mshoot_core.settings import EstimationSettings

logger = logging.getLogger(__name__)

#: Relative step of the finite-difference F of a model without interval_jacobians [-].
FD_STEP = 1e-6


def measured_states(model: Model, settings: EstimationSettings | None = None) -> tuple[str, ...]:
    """
    Return the states of ``model`` a sensor measures, in the model's state order.

    The settings' ``measured_states`` when set, else the model's attribute
    ``measured_states``, else every state.

    Raises
    ------
    ValueError
        If a named state is not a state of the model, or none is named.

    """
    states = tuple(model.state_names)
    named = settings.measured if settings is not None else ()
    if not named:
        named = tuple(getattr(model, 'measured_states', None) or states)
    unknown = [n for n in named if n not in states]
    if unknown or not named:
        raise ValueError(f'measured_states {list(named)} must be states of the model '
                         f'{list(states)} (unknown: {unknown})')
    return tuple(s for s in states if s in named)


def estimation_needed(model: Model, settings: EstimationSettings) -> bool:
    """
    Return True when a controller of ``model`` estimates its state (see the settings).

    Raises
    ------
    ValueError
        With ``estimation`` 'off' when the model's states are not all measured.

    """
    measured = measured_states(model, settings)
    partial = len(measured) < len(model.state_names)
    if settings.estimation == 'off' and partial:
        missing = [s for s in model.state_names if s not in measured]
        raise ValueError(f"estimation 'off' needs every state measured: {missing} are not "
                         "(use 'auto' or 'ekf')")
    return settings.estimation == 'ekf' or (settings.estimation == 'auto' and partial)


def initial_guess(model: Model, measured: Mapping[str, float]) -> np.ndarray:
    """
    Return a first guess of the full state from the measured states.

    Measured states as measured; an unmeasured one the mean of the measured
    ones (the states of a zone model are temperatures [K]: the envelope starts
    at the air temperature).
    """
    mean = float(np.mean(list(measured.values())))
    return np.array([float(measured.get(name, mean)) for name in model.state_names])


@dataclasses.dataclass(frozen=True)
class Estimate:
    """
    A state estimate with its uncertainty.

    Attributes
    ----------
    t_s : float
        Time of the estimate [s].
    state_names : tuple of str
        The model's states (the order of ``x``).
    x : ndarray, shape (nx,)
        The estimated state (the model's units, [K]).
    covariance : ndarray, shape (nx, nx)
        Its covariance [K^2].
    innovation : ndarray, shape (nm,)
        Measured minus predicted measured states [K] (zeros for a first estimate).
    measured : tuple of str
        The measured states (the order of ``innovation``).

    """

    t_s: float
    state_names: tuple[str, ...]
    x: np.ndarray
    covariance: np.ndarray
    innovation: np.ndarray
    measured: tuple[str, ...]

    @property
    def std(self) -> np.ndarray:
        """Return the standard deviation of every state [K]."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def __iter__(self):  # noqa: D105 (x_hat, P = estimate)
        return iter((self.x, self.covariance))


class StateEstimator:
    """
    Extended Kalman filter of a model's state from its measured states (see the module).

    Parameters
    ----------
    model : Model
        The model (the controller's).
    measured : sequence of str
        The measured states (default: :func:`measured_states`).
    step_s : float
        The control step [s]: ``process_noise_k`` is per step.
    measurement_noise_k : float
        Standard deviation of a measured state [K] (> 0).
    process_noise_k : float
        Standard deviation of the model error of every state over one step [K] (>= 0).
    initial_std_k : float
        Standard deviation of the first estimate of an unmeasured state [K] (> 0).
    initial_state : sequence of float, optional
        The first estimate's unmeasured states (default: :func:`initial_guess`).

    Raises
    ------
    ValueError
        On an unknown or empty set of measured states, a non-positive step or a
        negative or non-finite noise.

    """

    def __init__(self, model: Model, measured: Sequence[str] | None = None, *,
                 step_s: float = 3600.0, measurement_noise_k: float = 0.1,
                 process_noise_k: float = 0.05, initial_std_k: float = 3.0,
                 initial_state: Sequence[float] | None = None) -> None:
        self.model = model
        names = tuple(model.state_names)
        chosen = measured_states(model) if measured is None else tuple(measured)
        unknown = [n for n in chosen if n not in names]
        if not chosen or unknown or len(set(chosen)) != len(chosen):
            raise ValueError(f'measured states must be distinct states of the model '
                             f'{list(names)}, got {list(chosen)}')
        self.measured = tuple(n for n in names if n in chosen)
        self._rows = np.array([names.index(n) for n in self.measured])
        if not (math.isfinite(step_s) and step_s > 0):
            raise ValueError(f'step_s must be > 0 [s], got {step_s}')
        self.step_s = float(step_s)
        self.configure(measurement_noise_k, process_noise_k, initial_std_k)
        self.initial_state = None
        if initial_state is not None:
            guess = np.asarray(initial_state, dtype=float).reshape(-1)
            if guess.size != len(names) or not np.all(np.isfinite(guess)):
                raise ValueError(f'initial_state must be {len(names)} finite values '
                                 f'({list(names)}), got {initial_state}')
            self.initial_state = guess
        self._times = accepts_start_times(model)
        self.estimate: Estimate | None = None
        self.updates = 0
        self.resets = 0

    @classmethod
    def from_settings(cls, model: Model, settings: EstimationSettings, step_s: float,
                      initial_state: Sequence[float] | None = None) -> StateEstimator:
        """Build the estimator ``settings`` describe (see :class:`EstimationSettings`)."""
        return cls(model, measured_states(model, settings), step_s=step_s,
                   measurement_noise_k=settings.measurement_noise_k,
                   process_noise_k=settings.process_noise_k,
                   initial_std_k=settings.initial_std_k, initial_state=initial_state)

    def configure(self, measurement_noise_k: float, process_noise_k: float,
                  initial_std_k: float) -> None:
        """
        Set the noise levels (applied from the next update on).

        Raises
        ------
        ValueError
            On a negative or non-finite value, or a zero measurement or initial noise.

        """
        for name, value, positive in (('measurement_noise_k', measurement_noise_k, True),
                                      ('process_noise_k', process_noise_k, False),
                                      ('initial_std_k', initial_std_k, True)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value) or value < 0 or (positive and value == 0):
                raise ValueError(f'{name} must be a finite standard deviation '
                                 f"{'> 0' if positive else '>= 0'} [K], got {value!r}")
        self.measurement_noise_k = float(measurement_noise_k)
        self.process_noise_k = float(process_noise_k)
        self.initial_std_k = float(initial_std_k)

    @property
    def t_s(self) -> float | None:
        """Time of the current estimate [s] (None before the first)."""
        return None if self.estimate is None else self.estimate.t_s

    def reset(self) -> None:
        """Forget the estimate: the next update starts afresh from its measurement."""
        if self.estimate is not None:
            self.resets += 1
        self.estimate = None

    # -- checks ---------------------------------------------------------------------------
    def _measurement(self, measurements: Mapping[str, float]) -> np.ndarray:
        if not isinstance(measurements, Mapping):
            raise TypeError(f'measurements must be a mapping of state name -> value [K], got '
                            f'{type(measurements).__name__}')
        unknown = [n for n in measurements if n not in self.measured]
        missing = [n for n in self.measured if n not in measurements]
        if unknown or missing:
            raise ValueError(f'measurements must be the measured states {list(self.measured)}'
                             f' by name, got {list(measurements)} (unknown {unknown}, '
                             f'missing {missing})')
        z = np.array([measurements[n] for n in self.measured], dtype=float)
        if not np.all(np.isfinite(z)):
            raise ValueError(f'measurements must be finite, got {dict(measurements)}')
        return z

    def _intervals(self, t_s: float, inputs: pd.DataFrame | Sequence[float]
                   ) -> list[tuple[float, float, np.ndarray]]:
        """Return (start [s], length [s], inputs (nu,)) of every interval since the estimate."""
        t0 = self.estimate.t_s
        names = list(self.model.input_names)
        if isinstance(inputs, pd.DataFrame):
            missing = [n for n in names if n not in inputs.columns]
            if missing:
                raise ValueError(f'inputs lack the model inputs {missing} (expected {names})')
            starts = np.asarray(inputs.index, dtype=float)
            values = inputs[names].to_numpy(dtype=float)
            if starts.size == 0 or abs(starts[0] - t0) > 1e-6 * max(1.0, abs(t0)) or \
                    np.any(np.diff(starts) <= 0) or starts[-1] >= t_s:
                raise ValueError(f'inputs must be indexed by increasing interval start times '
                                 f'[s] from the last estimate at {t0:g} s to before {t_s:g} s, '
                                 f'got {starts.tolist()}')
        else:
            values = np.asarray(inputs, dtype=float).reshape(1, -1)
            if values.shape[1] != len(names):
                raise ValueError(f'inputs must hold the {len(names)} model inputs {names}, got '
                                 f'{values.shape[1]} values')
            starts = np.array([t0])
        if not np.all(np.isfinite(values)):
            raise ValueError('inputs must be finite')
        ends = np.append(starts[1:], t_s)
        return [(float(s), float(e - s), v) for s, e, v in zip(starts, ends, values)]

    # -- the filter -----------------------------------------------------------------------
    def _process_noise(self, dt: float) -> np.ndarray:
        """Return Q of an interval of ``dt`` [s] (``process_noise_k^2`` per step) [K^2]."""
        return np.eye(len(self.model.state_names)) * self.process_noise_k ** 2 * dt / self.step_s

    def _transition(self, x: np.ndarray, u: np.ndarray, t0: float,
                    dt: float) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the end state and F = dx_end/dx_start of one interval.

        Raises
        ------
        ModelValueError
            If either is not finite.

        """
        kwargs = {'t_start_s': np.array([t0])} if self._times else {}
        jac = self.model.interval_jacobians(x[None], u[None], dt, [], **kwargs)
        if jac is not None:
            x_end = np.asarray(jac.x_end[0], dtype=float)
            f = np.asarray(jac.dx_dx0[0], dtype=float)
        else:
            nx = x.size
            steps = FD_STEP * np.maximum(1.0, np.abs(x))
            starts = np.vstack([x, x + np.diag(steps)])
            kwargs = {'t_start_s': np.full(nx + 1, t0)} if self._times else {}
            ends, _ = self.model.simulate_intervals(starts, np.tile(u, (nx + 1, 1)), dt,
                                                    **kwargs)
            x_end, f = ends[0], ((ends[1:] - ends[0]) / steps[:, None]).T
        if not (np.all(np.isfinite(x_end)) and np.all(np.isfinite(f))):
            raise ModelValueError(f'{type(self.model).__name__}: non-finite prediction {x_end} '
                                  f'from {x} over [{t0:g}, {t0 + dt:g}] s', time_s=t0)
        return x_end, f

    def update(self, t_s: float, measurements: Mapping[str, float],
               inputs: pd.DataFrame | Sequence[float] | None = None) -> Estimate:
        """
        Take the measured states at ``t_s``; return the estimate of the full state then.

        Parameters
        ----------
        t_s : float
            Time of the measurement [s], after the last estimate's.
        measurements : mapping
            Measured state name -> value (the model's units, [K]): exactly :attr:`measured`.
        inputs : DataFrame or sequence of float, optional
            The model's inputs since the last estimate: a DataFrame indexed by
            interval start times [s] (the first the last estimate's time, each row
            held to the next or to ``t_s``), columns the model's inputs; or one
            row of inputs held over the whole interval. Not needed for the first
            estimate (or after :meth:`reset`).

        Returns
        -------
        Estimate
            ``x_hat, P = estimator.update(...)`` unpacks it.

        Raises
        ------
        ValueError
            On unknown, missing or non-finite measurements; a time not after the
            last estimate's; missing inputs after the first estimate; inputs that
            miss a model input, are not finite or do not cover the interval.
        ModelValueError
            If the model produced non-finite values (the estimate is kept).

        """
        t_s = float(t_s)
        if not math.isfinite(t_s):
            raise ValueError(f't_s must be a finite time [s], got {t_s}')
        z = self._measurement(measurements)
        r = np.eye(z.size) * self.measurement_noise_k ** 2
        if self.estimate is None:
            guess = (self.initial_state.copy() if self.initial_state is not None
                     else initial_guess(self.model, dict(zip(self.measured, z))))
            guess[self._rows] = z
            variances = np.full(guess.size, self.initial_std_k ** 2)
            variances[self._rows] = self.measurement_noise_k ** 2
            self.estimate = Estimate(t_s, tuple(self.model.state_names), guess,
                                     np.diag(variances), np.zeros(z.size), self.measured)
            self.updates += 1
            return self.estimate
        if not t_s > self.estimate.t_s:
            raise ValueError(f'a measurement at {t_s:g} s is not after the last estimate at '
                             f'{self.estimate.t_s:g} s')
        if inputs is None:
            raise ValueError(f'the inputs since the last estimate at {self.estimate.t_s:g} s '
                             'are needed (or reset() the estimator)')
        x, p = self.estimate.x.copy(), self.estimate.covariance.copy()
        for t0, dt, u in self._intervals(t_s, inputs):
            x, f = self._transition(x, u, t0, dt)
            p = f @ p @ f.T + self._process_noise(dt)
        h = np.zeros((z.size, x.size))
        h[np.arange(z.size), self._rows] = 1.0
        innovation = z - h @ x
        s = h @ p @ h.T + r
        gain = np.linalg.solve(s, h @ p).T  # P H' S^-1 (S and P symmetric)
        x = x + gain @ innovation
        keep = np.eye(x.size) - gain @ h
        p = keep @ p @ keep.T + gain @ r @ gain.T
        self.estimate = Estimate(t_s, tuple(self.model.state_names), x, 0.5 * (p + p.T),
                                 innovation, self.measured)
        self.updates += 1
        return self.estimate

    def predicted_std(self, inputs: np.ndarray, step_s: float | None = None,
                      estimate: Estimate | None = None) -> np.ndarray:
        """
        Return the standard deviation of every state along a prediction from the estimate.

        The covariance propagated as between two updates, with no measurement:
        ``P_j+1 = F_j P_j F_j' + Q`` along the model's prediction with ``inputs``
        (what a plan's state will be uncertain by, for constraint back-off).

        Parameters
        ----------
        inputs : ndarray, shape (n, nu)
            The model's inputs over each of ``n`` intervals from the estimate's
            time (controls as assumed, disturbances as forecast).
        step_s : float, optional
            Length of an interval [s] (default: the control step).
        estimate : Estimate, optional
            The estimate to predict from (default: the newest).

        Returns
        -------
        ndarray, shape (n + 1, nx)
            Row 0 the estimate's std, row ``j`` the std at the end of interval ``j`` [K].

        Raises
        ------
        RuntimeError
            Before the first estimate.
        ModelValueError
            If the model's prediction is not finite.

        """
        estimate = self.estimate if estimate is None else estimate
        if estimate is None:
            raise RuntimeError('no estimate yet: update() first')
        dt = self.step_s if step_s is None else float(step_s)
        inputs = np.asarray(inputs, dtype=float).reshape(-1, len(self.model.input_names))
        x, p = estimate.x.copy(), estimate.covariance.copy()
        q = self._process_noise(dt)
        out = [np.diag(p)]
        for j, u in enumerate(inputs):
            x, f = self._transition(x, u, estimate.t_s + j * dt, dt)
            p = f @ p @ f.T + q
            out.append(np.diag(p))
        return np.sqrt(np.clip(np.array(out), 0.0, None))


class Sensors:
    """
    What a building's sensors read of an emulated state: the measured states, with noise.

    Parameters
    ----------
    state_names : sequence of str
        The emulated model's states.
    measured : sequence of str
        The measured ones (default: all).
    noise_std_k : float
        Standard deviation of the Gaussian sensor noise [K] (0: exact).
    seed : int
        Seed of the noise: the noise of step ``k`` depends on (seed, k) only, so
        a re-read (a heartbeat) reads the same and a ROS run the core run's.

    """

    def __init__(self, state_names: Sequence[str], measured: Sequence[str] | None = None,
                 noise_std_k: float = 0.0, seed: int = 0) -> None:
        self.state_names = tuple(state_names)
        chosen = self.state_names if not measured else tuple(measured)
        unknown = [n for n in chosen if n not in self.state_names]
        if unknown or len(set(chosen)) != len(chosen):
            raise ValueError(f'measured states must be distinct states {list(self.state_names)}'
                             f', got {list(chosen)}')
        if isinstance(noise_std_k, bool) or not isinstance(noise_std_k, (int, float)) \
                or not math.isfinite(noise_std_k) or noise_std_k < 0:
            raise ValueError(f'noise_std_k must be a finite standard deviation >= 0 [K], got '
                             f'{noise_std_k!r}')
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f'seed must be an int >= 0, got {seed!r}')
        self.measured = tuple(n for n in self.state_names if n in chosen)
        self.noise_std_k = float(noise_std_k)
        self.seed = int(seed)

    def read(self, x: Sequence[float], step: int) -> dict[str, float]:
        """Return the measured states of ``x`` (in state order) at step ``step``, with noise."""
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.size != len(self.state_names):
            raise ValueError(f'x must hold the {len(self.state_names)} states '
                             f'{list(self.state_names)}, got {x.size} values')
        noise = np.zeros(len(self.measured))
        if self.noise_std_k > 0:
            rng = np.random.default_rng([self.seed, int(step)])
            noise = rng.normal(0.0, self.noise_std_k, len(self.measured))
        return {name: float(x[self.state_names.index(name)] + e)
                for name, e in zip(self.measured, noise)}
