"""
The generic model interface every zone model implements.

A model maps inputs held constant over intervals (zero-order hold) and an
initial state vector to state and output trajectories. The one required
method is :meth:`Model.simulate`; the batch path
:meth:`Model.simulate_intervals` and the optional analytic derivatives
:meth:`Model.interval_jacobians` are what the multiple-shooting optimiser
calls, and have generic defaults built on ``simulate``.
"""
from __future__ import annotations

import abc
import dataclasses
import functools
import inspect
import logging
import math
from typing import Sequence

import numpy as np
import pandas as pd

logger = logging.getLogger(__name__)


class ModelValueError(ValueError):
    """
    A model produced non-finite states or outputs (NaN or inf).

    Ends a solve (the controller falls back: 'solve_failed') and stops an
    emulation; it is not an input error of the caller.

    Attributes
    ----------
    variable : str
        The model variable (state or output name) that is not finite.
    time_s : float or None
        When, in the model's own time [s] (for FMUs: FMU time), where known.

    """

    def __init__(self, message: str, variable: str = '', time_s: float | None = None) -> None:
        super().__init__(message)
        self.variable = variable
        self.time_s = time_s


def interval_start_times(t_start_s: Sequence[float] | np.ndarray | None,
                         batch: int) -> np.ndarray | None:
    """
    ``t_start_s`` as a finite float array of shape (batch,), or None.

    Raises
    ------
    ValueError
        On a wrong shape or a non-finite time.

    """
    if t_start_s is None:
        return None
    times = np.ascontiguousarray(t_start_s, dtype=np.float64)  # (no copy if it is one)
    if times.shape != (batch,):
        times = times.reshape(-1)
        if times.shape != (batch,):
            raise ValueError(f't_start_s must hold one start time [s] per interval ({batch}), '
                             f'got shape {np.shape(t_start_s)}')
    if not math.isfinite(np.add.reduce(times)):
        raise ValueError('t_start_s must be finite times [s]')
    return times


def check_parameters(parameters: object, label: str, *, positive: Sequence[str] = (),
                     nonnegative: Sequence[str] = (), arrays: bool = False) -> None:
    """
    Check the fields of a model's parameters dataclass: finite, and signs where physics wants.

    Parameters
    ----------
    parameters : dataclass instance
        The parameters (fields in their own units).
    label : str
        The model's name in the messages (e.g. 'R1C1').
    positive, nonnegative : sequence of str
        Fields that must be > 0 (capacities, resistances) or >= 0 (gains).
    arrays : bool
        Whether a field may hold an array (every element checked); else each must be a real
        number (not a bool).

    Raises
    ------
    ValueError
        Naming the first field that is not finite, not a number, or of the wrong sign.

    """
    for field in dataclasses.fields(parameters):
        value = getattr(parameters, field.name)
        if arrays:
            if not np.all(np.isfinite(value)):
                raise ValueError(f'{label} parameter {field.name} must be finite, got {value}')
        elif (not isinstance(value, (int, float, np.floating)) or isinstance(value, bool)
              or not math.isfinite(value)):
            raise ValueError(f'{label} parameter {field.name} must be a finite number, got '
                             f'{value!r}')
    for names, fails, wording in ((positive, np.less_equal, '> 0'),
                                  (nonnegative, np.less, '>= 0')):
        for name in names:
            value = getattr(parameters, name)
            if np.any(fails(np.asarray(value), 0.0)):
                raise ValueError(f'{label} parameter {name} must be {wording}, got {value}')


@functools.lru_cache(maxsize=64)
def _takes_start_times(method: object) -> bool:
    try:
        parameters = inspect.signature(method).parameters
    except (TypeError, ValueError):
        return False
    return 't_start_s' in parameters or any(
        p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values())


def accepts_start_times(model: 'Model') -> bool:
    """
    Whether ``model``'s batch methods take ``t_start_s`` (models written before it did not).

    The optimiser passes interval start times only to models that accept them;
    others are time-invariant by construction.
    """
    cls = type(model)
    return all(_takes_start_times(getattr(cls, name))
               for name in ('simulate_intervals', 'interval_jacobians'))


@dataclasses.dataclass(frozen=True)
class IntervalJacobians:
    """
    End values of B independent intervals and their derivatives.

    Attributes
    ----------
    x_end : ndarray, shape (B, nx)
        States at the end of each interval.
    y_end : ndarray, shape (B, ny)
        Outputs at the end of each interval.
    dx_dx0 : ndarray, shape (B, nx, nx)
        d x_end / d x_start.
    dx_du : ndarray, shape (B, nx, len(wrt_inputs))
        d x_end / d u for the requested input columns.
    dy_dx0 : ndarray, shape (B, ny, nx)
        d y_end / d x_start.
    dy_du : ndarray, shape (B, ny, len(wrt_inputs))
        d y_end / d u for the requested input columns.

    """

    x_end: np.ndarray
    y_end: np.ndarray
    dx_dx0: np.ndarray
    dx_du: np.ndarray
    dy_dx0: np.ndarray
    dy_du: np.ndarray


class IntervalBatch:
    """
    B intervals of a model evaluated again and again with new start states and inputs.

    The optimiser's inner loop: it writes the start states into :attr:`x_start`
    (B, nx) and the inputs into :attr:`u` (B, nu, columns in the model's
    :attr:`~Model.input_names` order) in place, then calls :meth:`jacobians`; the
    interval length, the columns differentiated and the start times stay those given
    here. This default calls :meth:`Model.interval_jacobians` (on copies of the
    buffers); a model whose batch has work to do only once (an FMU's compiled driver
    bound to its buffers) returns its own from :meth:`Model.interval_batch`.

    Parameters
    ----------
    model : Model
    batch : int
        B, the intervals.
    dt_s : float
        Interval length [s].
    wrt_inputs : sequence of int
        Columns of ``u`` to differentiate with respect to.
    t_start_s : ndarray, shape (B,), optional
        Start time of each interval [s] (passed to models whose batch methods take it).

    """

    def __init__(self, model: 'Model', batch: int, dt_s: float, wrt_inputs: Sequence[int],
                 t_start_s: np.ndarray | None = None) -> None:
        self.model = model
        self.dt_s = float(dt_s)
        self.wrt_inputs = list(wrt_inputs)
        self.x_start = np.zeros((int(batch), len(model.state_names)))
        self.u = np.zeros((int(batch), len(model.input_names)))
        self.t_start_s = interval_start_times(t_start_s, int(batch))
        self._times = ({'t_start_s': self.t_start_s}
                       if self.t_start_s is not None and accepts_start_times(model) else {})

    def jacobians(self) -> IntervalJacobians | None:
        """End values and derivatives at the buffers' starts and inputs (None: no analytic)."""
        return self.model.interval_jacobians(self.x_start.copy(), self.u.copy(), self.dt_s,
                                             self.wrt_inputs, **self._times)


class Model(abc.ABC):
    """
    A dynamic zone model with named inputs, states and outputs.

    Subclasses set :attr:`input_names`, :attr:`state_names` and
    :attr:`output_names` and implement :meth:`simulate`. Units are the
    model's own (the R1C1 zone: states in K, outputs in degC and J).
    """

    #: Names of the inputs, the column order of ``udf`` and of ``u`` arrays.
    input_names: tuple[str, ...] = ()
    #: Names of the states, the order of ``x0`` and of state arrays.
    state_names: tuple[str, ...] = ()
    #: Names of the outputs, the order of output arrays.
    output_names: tuple[str, ...] = ()
    #: Inputs in which the model is a monotone system: the end states of every interval
    #: are nondecreasing in its start states and in each of these inputs, as a thermal RC
    #: network's temperatures are in its start temperatures and its heat rates. Empty (the
    #: default): no such claim. Where every control is one of them, the MPC tests before it
    #: solves whether the comfort band can be kept at all
    #: (:meth:`~mshoot_core.shooting.ShootingProblem.infeasible_band`).
    monotone_inputs: tuple[str, ...] = ()

    @abc.abstractmethod
    def simulate(self, udf: pd.DataFrame, x0: Sequence[float]) -> tuple[pd.DataFrame,
                                                                        pd.DataFrame]:
        """
        Simulate from ``x0`` over the time index of ``udf``.

        Parameters
        ----------
        udf : DataFrame, shape (T, nu)
            Inputs indexed by time [s] (strictly increasing), one column per
            name in :attr:`input_names`. Row i is held constant over
            [t_i, t_{i+1}); the last row only marks the end time.
        x0 : sequence of float, length nx
            Initial state at ``udf.index[0]``.

        Returns
        -------
        ydf : DataFrame, shape (T, ny)
            Outputs at the times of ``udf.index``.
        xdf : DataFrame, shape (T, nx)
            States at the times of ``udf.index``; the first row equals ``x0``.

        """

    # -- helpers shared by all models -------------------------------------------------------
    def check_inputs(self, udf: pd.DataFrame, x0: Sequence[float]) -> tuple[np.ndarray,
                                                                            np.ndarray,
                                                                            np.ndarray]:
        """
        Validate ``udf`` and ``x0``; return times [s], inputs (T, nu) and x0 (nx,).

        Raises
        ------
        ValueError
            If columns are missing, the index is not strictly increasing,
            values are not finite, or ``x0`` has the wrong length.

        """
        if not isinstance(udf, pd.DataFrame):
            raise TypeError(f'udf must be a pandas DataFrame, got {type(udf).__name__}')
        missing = [n for n in self.input_names if n not in udf.columns]
        if missing:
            raise ValueError(f'udf lacks input columns {missing}; expected '
                             f'{list(self.input_names)}, got {list(udf.columns)}')
        t = np.asarray(udf.index, dtype=float)
        if t.size < 2 or np.any(np.diff(t) <= 0):
            raise ValueError('udf index must be at least two strictly increasing times [s]')
        u = udf[list(self.input_names)].to_numpy(dtype=float)
        if not np.all(np.isfinite(u)):
            raise ValueError('udf holds non-finite input values')
        x0_arr = np.asarray(x0, dtype=float).reshape(-1)
        if x0_arr.size != len(self.state_names):
            raise ValueError(f'x0 must have {len(self.state_names)} values '
                             f'({list(self.state_names)}), got {x0_arr.size}')
        if not np.all(np.isfinite(x0_arr)):
            raise ValueError(f'x0 holds non-finite values: {x0_arr}')
        return t, u, x0_arr

    def _check_batch(self, x_start: np.ndarray,
                     u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        ``x_start`` (B, nx) and ``u`` (B, nu) of a batch as finite float arrays.

        Raises
        ------
        ValueError
            On a wrong shape or a non-finite value, naming the model's variables.

        """
        x_start = np.asarray(x_start, dtype=float)
        if x_start.ndim != 2:
            x_start = np.atleast_2d(x_start)
        u = np.asarray(u, dtype=float)
        if u.ndim != 2:
            u = np.atleast_2d(u)
        nx, nu = len(self.state_names), len(self.input_names)
        if x_start.ndim != 2 or x_start.shape[1] != nx:
            raise ValueError(f'x_start must have shape (B, {nx}) for states '
                             f'{list(self.state_names)}, got {x_start.shape}')
        if u.ndim != 2 or u.shape != (x_start.shape[0], nu):
            raise ValueError(f'u must have shape ({x_start.shape[0]}, {nu}) for inputs '
                             f'{list(self.input_names)}, got {u.shape}')
        # one sum for the usual case; element-wise only when it is not finite (a sum of
        # finite values can overflow)
        if not math.isfinite(np.add.reduce(x_start, None) + np.add.reduce(u, None)) and not (
                np.all(np.isfinite(x_start)) and np.all(np.isfinite(u))):
            raise ValueError('x_start and u must be finite')
        return x_start, u

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """
        Simulate B independent intervals of length ``dt_s`` (the batch path).

        Each interval starts from its own state with its own constant inputs.
        The default calls :meth:`simulate` once per interval; fast models
        override it (vectorised numpy, one ``predict`` call, a reused FMU).

        Parameters
        ----------
        x_start : ndarray, shape (B, nx)
            Start state of each interval.
        u : ndarray, shape (B, nu)
            Inputs of each interval, columns in :attr:`input_names` order.
        dt_s : float
            Interval length [s].
        t_start_s : ndarray, shape (B,), optional
            Start time of each interval [s], in the caller's time base (the
            MPC's: scenario-relative seconds). Time-invariant models ignore
            it; time-dependent ones (an FMU with schedules) simulate each
            interval at its own time. None: every interval starts at t = 0.

        Returns
        -------
        x_end : ndarray, shape (B, nx)
        y_end : ndarray, shape (B, ny)

        """
        x_start = np.atleast_2d(np.asarray(x_start, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        times = interval_start_times(t_start_s, x_start.shape[0])
        x_end = np.empty_like(x_start)
        y_end = np.empty((x_start.shape[0], len(self.output_names)))
        for b in range(x_start.shape[0]):
            t0 = 0.0 if times is None else float(times[b])
            udf = pd.DataFrame(np.vstack([u[b], u[b]]), index=[t0, t0 + float(dt_s)],
                               columns=list(self.input_names))
            ydf, xdf = self.simulate(udf, x_start[b])
            x_end[b] = xdf.to_numpy()[-1]
            y_end[b] = ydf.to_numpy()[-1]
        return x_end, y_end

    def simulate_chains(self, x0: np.ndarray, u: np.ndarray, dt_s: float,
                        t_start_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """
        Simulate C trajectories of N consecutive intervals of ``dt_s`` [s] each.

        Interval k of trajectory c starts from the end state of its interval k - 1 (from
        ``x0[c]`` for k = 0), with its own inputs ``u[k, c]``: what N calls of
        :meth:`simulate_intervals` on C intervals give, which is this default. Models
        that can run the whole set in one batch override it (an FMU's compiled driver).

        Parameters
        ----------
        x0 : ndarray, shape (C, nx)
            Start state of each trajectory.
        u : ndarray, shape (N, C, nu)
            Inputs of interval k of trajectory c, columns in :attr:`input_names` order.
        dt_s : float
            Interval length [s].
        t_start_s : ndarray, shape (N, C), optional
            Start time of each interval [s] (see :meth:`simulate_intervals`; only passed
            to a model whose batch methods take it).

        Returns
        -------
        x_end : ndarray, shape (N, C, nx)
        y_end : ndarray, shape (N, C, ny)

        """
        x = np.atleast_2d(np.asarray(x0, dtype=float))
        u = np.asarray(u, dtype=float)
        x_end = np.empty((u.shape[0], *x.shape))
        y_end = np.empty((u.shape[0], x.shape[0], len(self.output_names)))
        for k in range(u.shape[0]):
            times = {} if t_start_s is None else {'t_start_s': np.asarray(t_start_s)[k]}
            x, y_end[k] = self.simulate_intervals(x, u[k], dt_s, **times)
            x_end[k] = x
        return x_end, y_end

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int],
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians | None:
        """
        Analytic end values and derivatives of B intervals, or None.

        Models with analytic (or forward-sensitivity) derivatives override
        this; the default returns None and the optimiser falls back to
        finite differences over :meth:`simulate_intervals`.

        Parameters
        ----------
        x_start : ndarray, shape (B, nx)
            Start state of each interval.
        u : ndarray, shape (B, nu)
            Inputs of each interval, columns in :attr:`input_names` order.
        dt_s : float
            Interval length [s].
        wrt_inputs : sequence of int
            Column indices of ``u`` to differentiate with respect to.
        t_start_s : ndarray, shape (B,), optional
            Start time of each interval [s] (see :meth:`simulate_intervals`).

        """
        return None

    def interval_batch(self, batch: int, dt_s: float, wrt_inputs: Sequence[int],
                       t_start_s: np.ndarray | None = None) -> IntervalBatch:
        """
        Return an :class:`IntervalBatch` of ``batch`` intervals of this model.

        For the optimiser's inner loop: buffers written in place, evaluated many times
        (:meth:`IntervalBatch.jacobians` gives what :meth:`interval_jacobians` gives).
        """
        return IntervalBatch(self, batch, dt_s, wrt_inputs, t_start_s)

    def jacobian_sparsity(self, wrt_inputs: Sequence[int]) -> np.ndarray | None:
        """
        Structure of one interval's Jacobian, or None for dense.

        Returns
        -------
        ndarray of bool, shape (nx + ny, nx + len(wrt_inputs)), or None
            True where d(x_end, y_end)/d(x_start, u[wrt_inputs]) may be
            non-zero. Models of weakly coupled parts (e.g. independent zones)
            declare it so finite differences perturb many columns at once.

        """
        return None
