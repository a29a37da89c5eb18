"""
Multiple shooting: the horizon as N intervals, each simulated from its own start state.

Decision variables (normalised, see :class:`NlpIndex`):

- ``u[k]``: the controls of interval k (held constant), k = 0..N-1;
- ``x[k]``: the state at the end of interval k (= start of interval k+1),
  k = 0..N-1; the start state of interval 0 is the measured x0;
- ``s[k]``: slack of the state bounds at the end of interval k (soft bounds only).

Continuity constraints F(x_start_k, u_k) - x[k] = 0 tie the intervals together.
Interval k starts at ``t0_s + k * step_s`` when the solve is given its start
time ``t0_s`` (time-dependent models, e.g. an FMU with schedules, simulate it
there); finite-difference perturbations keep the time of their interval.
Because interval k depends only on its own start state and control, the
constraint Jacobian is block-bidiagonal; all intervals (and, for finite
differences, all their perturbations) are evaluated in one batched model call,
and the evaluation at a point is shared between cost and constraints.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import time
from typing import Any, Callable, Sequence, TYPE_CHECKING

import numpy as np
import pandas as pd

from mshoot_core.models.base import (accepts_start_times, IntervalJacobians, Model,
                                     ModelValueError)
from mshoot_core.sensitivities import finite_difference_jacobians
from mshoot_core.settings import ComfortSettings, ProblemSettings, SettingsError
from mshoot_core.solvers import Nlp, Solver, SolverResult, SparseJacobian

if TYPE_CHECKING:
    from scipy import sparse

logger = logging.getLogger(__name__)

#: Penalties of the least-violation phase on normalised slack: linear (dominant) and
#: quadratic (keeps the phase-1 problem well posed).
LEAST_VIOLATION_LINEAR = 1e3
LEAST_VIOLATION_QUADRATIC = 1e1
#: How far (scaled state units) the band's feasible tube must miss a bound for
#: :meth:`ShootingProblem.infeasible_band` to call the band infeasible: above the constraint
#: violation an NLP solver accepts (SLSQP's 1e-10, summed; IPOPT's 1e-4), so that a band it
#: calls infeasible is one the hard NLP would fail on (IPOPT's 'acceptable' level, 1e-2, may
#: pass a band missed by less than that: the least-violation phase then plans it instead).
TUBE_MARGIN = 1e-3
#: User cost: cost(x_hat (N, nx), y_hat (N, ny), u_hat (N, nc)) -> float.
CostFunction = Callable[[np.ndarray, np.ndarray, np.ndarray], float]


@dataclasses.dataclass(frozen=True)
class NlpIndex:
    """
    Named views into the NLP vector (no stride arithmetic elsewhere).

    Layout: ``[u (N, nc) | x (N, nx) | s (N, nx) if soft]``, row-major.
    """

    n_intervals: int
    n_controls: int
    n_states: int
    soft: bool = False

    # (computed once per layout: the optimiser's callbacks take these views thousands of times)
    @functools.cached_property
    def size(self) -> int:
        """Length of the NLP vector."""
        return self.n_intervals * (self.n_controls + self.n_states * (2 if self.soft else 1))

    @functools.cached_property
    def u_slice(self) -> slice:
        return slice(0, self.n_intervals * self.n_controls)

    @functools.cached_property
    def x_slice(self) -> slice:
        start = self.u_slice.stop
        return slice(start, start + self.n_intervals * self.n_states)

    @functools.cached_property
    def s_slice(self) -> slice:
        start = self.x_slice.stop
        return slice(start, start + (self.n_intervals * self.n_states if self.soft else 0))

    def u(self, z: np.ndarray) -> np.ndarray:
        """Return the controls, shape (N, nc) (a view)."""
        return z[self.u_slice].reshape(self.n_intervals, self.n_controls)

    def x(self, z: np.ndarray) -> np.ndarray:
        """Interval end states, shape (N, nx) (a view)."""
        return z[self.x_slice].reshape(self.n_intervals, self.n_states)

    def s(self, z: np.ndarray) -> np.ndarray:
        """Slacks, shape (N, nx) (a view; empty unless soft)."""
        return z[self.s_slice].reshape(self.n_intervals, self.n_states if self.soft else 0)

    def pack(self, u: np.ndarray, x: np.ndarray, s: np.ndarray | None = None) -> np.ndarray:
        """Assemble an NLP vector from its blocks."""
        z = np.zeros(self.size)
        self.u(z)[:] = u
        self.x(z)[:] = x
        if self.soft:
            self.s(z)[:] = 0.0 if s is None else s
        return z


@dataclasses.dataclass(frozen=True)
class Scaling:
    """Affine normalisation v_hat = (v - offset) / scale, per column."""

    offset: np.ndarray
    scale: np.ndarray

    def __post_init__(self) -> None:
        if (~np.isfinite(self.scale)).any() or (self.scale <= 0).any():
            raise ValueError(f'scales must be finite and > 0, got {self.scale}')

    def to_hat(self, v: np.ndarray) -> np.ndarray:
        return (v - self.offset) / self.scale

    def from_hat(self, v_hat: np.ndarray) -> np.ndarray:
        return v_hat * self.scale + self.offset


class ShootingResult(SolverResult):
    """
    Result of one multiple-shooting solve (a :class:`~mshoot_core.slsqp.SolverResult`).

    The fields of :class:`scipy.optimize.OptimizeResult`, as a dict whose keys are attributes
    (not a subclass of SciPy's: ``scipy.optimize`` is not imported for it).

    Keys beyond SciPy's (success, status, message, fun, nit, nfev, x):
    ``controls`` (N, nc) physical plan; ``states`` (N+1, nx) predicted states
    (x0, then the interval end states of the solution); ``outputs`` (N, ny)
    predicted outputs at interval ends; ``slacks`` (N, nx) physical slack of the
    bounds; ``solve_time_s``; ``max_defect`` the largest continuity defect in
    physical state units; ``relaxed`` whether state bounds were relaxed;
    ``model_evaluations`` interval simulations spent; ``budget_exceeded`` whether
    the solver was stopped at its deadline.
    """


class ShootingProblem:
    """
    A multiple-shooting optimal control problem over one horizon.

    Parameters
    ----------
    model : Model
        The control model.
    problem : ProblemSettings, optional
        The horizon (``horizon_steps`` intervals N of ``step_s`` [s]), the
        optimised inputs ``control_names`` and their bounds, the cost, the
        evaluation ``mode`` and the ``relaxation`` of unreachable bounds (see
        :class:`mshoot_core.settings.ProblemSettings`). The cost 'quadratic' is
        the sum over intervals of sum over controls (u/u_nom)^2 (the reference);
        'energy' the sum of |u/u_nom| made smooth as sqrt((u/u_nom)^2 + eps^2) -
        eps; 'output' the sum over intervals of the model output ``cost_output``
        at each interval's end (e.g. the interval's electricity cost: price x
        power, with the price a disturbance of the forecast), differentiated
        with the model's own output sensitivities (its Hessian taken as zero:
        exact for outputs affine in states and controls). Relaxation
        'two-phase' minimises the violation, relaxes the bounds to it and solves
        the hard problem again (not where a solver that certifies the KKT
        conditions converged on the first: the same plan, see
        :meth:`_solve_least_violation`); 'exact-penalty' always solves once with slack
        and a large linear penalty on the violation (the same plan up to the
        solver tolerance, in one solve; suits IPOPT on large
        problems, where a failing hard solve costs as much as a solve). Mode
        'fast': batched, cached, structured sensitivities (analytic where the
        model has them); 'naive': the ancestor's algorithm, kept as a
        side-by-side baseline: every objective and constraint evaluation
        simulates all intervals one by one through ``simulate`` (DataFrames in
        the loop, nothing cached, objective and constraints simulated
        separately), and the solver estimates dense Jacobians over all
        variables with SciPy's default finite differences.
    comfort : ComfortSettings, optional
        Hard bounds, or slack with the penalty w2 * sum(s_hat^2) + w1 *
        sum(s_hat) on normalised slacks (``soft_penalty`` w2,
        ``soft_penalty_linear`` w1: with w1 large the solver first minimises
        the summed violation, then the cost).
    cost_function : callable, optional
        ``cost(x_hat, y_hat, u_hat) -> float`` on normalised quantities,
        replacing the settings' cost.
    control_nominal : sequence of float, optional
        u_nom per control (default: the largest absolute bound).
    state_scaling : Scaling, optional
        Normalisation of the states (default: the model's ``state_scaling``
        attribute when it declares one, else offset and range of the bounds
        passed at each solve, falling back to offset 0 and scale 1).
    output_nominal : sequence of float, optional
        Output nominal values for y_hat = y / y_nom (default 1).
    energy_epsilon : float
        Smoothing of the energy cost, in normalised control units.
    fd_step : float, optional
        Finite-difference step on normalised variables (default from the
        model's ``tolerance`` attribute: max(1e-7, sqrt(tolerance))).

    """

    def __init__(self, model: Model, problem: ProblemSettings | None = None,
                 comfort: ComfortSettings | None = None, *,
                 cost_function: CostFunction | None = None,
                 control_nominal: Sequence[float] | None = None,
                 state_scaling: Scaling | None = None,
                 output_nominal: Sequence[float] | None = None,
                 energy_epsilon: float = 1e-3, fd_step: float | None = None) -> None:
        if not isinstance(model, Model):
            raise TypeError(f'model must be a mshoot_core Model, got {type(model).__name__}')
        problem = ProblemSettings() if problem is None else problem
        comfort = ComfortSettings() if comfort is None else comfort
        problems = problem.problems() + comfort.problems()
        if problems:
            raise SettingsError(problems)
        control_names = problem.control_names
        unknown = [c for c in control_names if c not in model.input_names]
        if unknown:
            raise ValueError(f'controls must be model inputs {list(model.input_names)}, '
                             f'got {list(control_names)}')
        if cost_function is not None and not callable(cost_function):
            raise TypeError(f'cost_function must be callable, got '
                            f'{type(cost_function).__name__}')
        self.settings = problem
        self.relaxation = problem.relaxation
        self.mode = problem.mode
        self.model = model
        self.control_names = tuple(control_names)
        self.control_cols = [model.input_names.index(c) for c in self.control_names]
        self.disturbance_names = tuple(n for n in model.input_names
                                       if n not in self.control_names)
        self.disturbance_cols = [model.input_names.index(c) for c in self.disturbance_names]
        # the same columns as index arrays: a list index is converted at every batch
        self._control_index = np.array(self.control_cols, dtype=np.intp)
        self._disturbance_index = np.array(self.disturbance_cols, dtype=np.intp)
        bounds = np.asarray(problem.control_bounds, dtype=float)
        self.control_bounds = bounds
        nominal = (np.abs(bounds).max(axis=1) if control_nominal is None
                   else np.asarray(control_nominal, dtype=float))
        self.control_scaling = Scaling(np.zeros(len(control_names)), nominal)
        self.n_intervals = problem.horizon_steps
        self.step_s = problem.step_s
        self.cost: str | CostFunction = problem.cost if cost_function is None else cost_function
        self.cost_output_index = -1
        if self.cost == 'output':
            if problem.cost_output not in model.output_names:
                raise ValueError(f"cost 'output' sums a model output: cost_output must be one of "
                                 f'{list(model.output_names)}, got {problem.cost_output!r}')
            self.cost_output_index = model.output_names.index(problem.cost_output)
        model_scaling = getattr(model, 'state_scaling', None)
        self.state_scaling = (state_scaling if state_scaling is not None or not isinstance(
            model_scaling, Scaling) else model_scaling)
        ny = len(model.output_names)
        self.output_nominal = (np.ones(ny) if output_nominal is None
                               else np.asarray(output_nominal, dtype=float))
        if self.output_nominal.shape != (ny,) or np.any(self.output_nominal == 0):
            raise ValueError(f'output_nominal must be {ny} non-zero values')
        self.soft_bounds = comfort.soft
        self.soft_penalty = comfort.soft_penalty
        self.soft_penalty_linear = comfort.soft_penalty_linear
        self.energy_epsilon = float(energy_epsilon)
        tol = getattr(model, 'tolerance', None)
        self.fd_step = float(fd_step) if fd_step is not None else (
            max(1e-7, float(np.sqrt(tol))) if tol else 1e-7)
        self.index = NlpIndex(self.n_intervals, len(control_names), len(model.state_names),
                              self.soft_bounds)
        self.model_evaluations = 0
        self._deadline: float | None = None
        #: Whether the model's batch methods take interval start times.
        self._takes_times = accepts_start_times(model)
        if not self._takes_times:
            logger.debug('%s takes no interval start times: treated as time-invariant',
                         type(model).__name__)
        self._t_start_s: np.ndarray | None = None
        self._structures: dict[NlpIndex, ContinuityStructure] = {}
        self._last_scaling: tuple[tuple, Scaling] | None = None
        self._batch: tuple[tuple, Any] | None = None  # (_solve_nlp's interval batch)
        #: Whether the model is monotone in every control (``Model.monotone_inputs``): the
        #: band's feasibility is then tested along its tube (:meth:`infeasible_band`).
        self.monotone = bool(self.control_names) and set(self.control_names) <= set(
            getattr(model, 'monotone_inputs', ()))

    # -- model evaluation ------------------------------------------------------------------
    def _full_inputs(self, controls: np.ndarray, disturbances: np.ndarray) -> np.ndarray:
        u = np.empty((controls.shape[0], len(self.model.input_names)))
        u[:, self._control_index] = controls
        u[:, self._disturbance_index] = disturbances
        return u

    def _times(self, t_start_s: np.ndarray | None) -> dict:
        """Keyword arguments passing interval start times to the model, if it takes them."""
        return {'t_start_s': t_start_s} if t_start_s is not None and self._takes_times else {}

    def evaluate_intervals(self, x_start: np.ndarray, controls: np.ndarray,
                           disturbances: np.ndarray, sensitivities: bool = True,
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians:
        """
        End states, outputs and sensitivities of all intervals in one batch.

        Uses the model's analytic ``interval_jacobians`` where it has them,
        otherwise forward finite differences on normalised variables, all
        perturbations in one ``simulate_intervals`` call, columns grouped by the
        model's declared sparsity (:mod:`mshoot_core.sensitivities`).
        ``t_start_s`` (B,): the intervals' start times [s] (None: time 0).
        """
        u = self._full_inputs(controls, disturbances)
        if sensitivities:
            return self._interval_jacobians(x_start, u, t_start_s)
        times = self._times(t_start_s)
        x_end, y_end = self.model.simulate_intervals(x_start, u, self.step_s, **times)
        self.model_evaluations += x_start.shape[0]
        empty = np.zeros((x_start.shape[0], 0, 0))
        return IntervalJacobians(x_end, y_end, empty, empty, empty, empty)

    def _interval_jacobians(self, x_start: np.ndarray, u: np.ndarray,
                            t_start_s: np.ndarray | None) -> IntervalJacobians:
        """:meth:`evaluate_intervals` with sensitivities, from the full inputs ``u`` (B, nu)."""
        times = self._times(t_start_s)
        jac = self.model.interval_jacobians(x_start, u, self.step_s, self.control_cols, **times)
        if jac is not None:
            self.model_evaluations += x_start.shape[0]
            return jac
        jac, spent = finite_difference_jacobians(
            self.model, x_start, u, self.step_s, self.control_cols,
            self.fd_step * self._x_scaling.scale, self.fd_step * self.control_scaling.scale,
            self.control_bounds[:, 1], self.model.jacobian_sparsity(self.control_cols),
            times.get('t_start_s'))
        self.model_evaluations += spent
        return jac

    # -- the NLP ---------------------------------------------------------------------------
    def _state_scaling_for(self, lower: np.ndarray, upper: np.ndarray) -> Scaling:
        if self.state_scaling is not None:
            return self.state_scaling
        lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        key = (lower.tobytes(), upper.tobytes(), lower.shape, upper.shape)
        last = self._last_scaling
        if last is not None and last[0] == key:  # (a solve asks twice: its bounds, relaxing)
            return last[1]
        scaling = self._scaling_of_bounds(lower, upper)
        self._last_scaling = (key, scaling)
        return scaling

    @staticmethod
    def _scaling_of_bounds(lower: np.ndarray, upper: np.ndarray) -> Scaling:
        """Return the state scaling of bounds (N, nx): their finite range per state, else 1."""
        # per state: the lowest finite lower bound and the highest finite upper bound
        lo = np.where(np.isfinite(lower), lower, np.inf).min(axis=0)
        hi = np.where(np.isfinite(upper), upper, -np.inf).max(axis=0)
        bounded = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
        return Scaling(np.where(bounded, lo, 0.0), np.where(bounded, hi - lo, 1.0))

    def reachable_envelope(self, x0: np.ndarray, disturbances: np.ndarray) -> tuple[np.ndarray,
                                                                                    np.ndarray]:
        """
        Element-wise min and max of the state trajectories under the extreme controls.

        Simulates the horizon with every control at its lower bound and at its
        upper bound (both trajectories side by side: one batch of two intervals
        per step, interval k at the solve's start time + k steps); returns (low,
        high), each (N, nx), the interval end states.
        """
        n = self.n_intervals
        # (N, 2, nu): interval k of the lower and upper sides, every control at its bound
        u = np.empty((n, 2, len(self.model.input_names)))
        for side in (0, 1):
            u[:, side, self._control_index] = self.control_bounds[:, side]
            u[:, side, self._disturbance_index] = disturbances
        times = self._t_start_s
        ends, _ = self.model.simulate_chains(
            np.repeat(np.asarray(x0)[None, :], 2, axis=0), u, self.step_s,
            **self._times(None if times is None else np.repeat(times[:, None], 2, axis=1)))
        self.model_evaluations += 2 * n
        return np.minimum(ends[:, 0], ends[:, 1]), np.maximum(ends[:, 0], ends[:, 1])

    def infeasible_band(self, x0: np.ndarray, disturbances: np.ndarray, lower: np.ndarray,
                        upper: np.ndarray, margin: float = TUBE_MARGIN) -> bool:
        """
        Whether no controls within their bounds keep the states within ``lower``/``upper``.

        Only for a model monotone in its start states and in every control
        (:attr:`monotone`); False for others (nothing is claimed). The states that
        controls within their bounds can reach at the end of interval k, the bounds kept at
        every interval end before, lie between two trajectories simulated interval by
        interval: the lowest, from the lowest such state with every control at its lower
        bound, and the highest, from the highest with every control at its upper bound, each
        clipped to the bounds after every interval (the tube). Where the highest falls below
        a lower bound, or the lowest rises above an upper bound, by more than ``margin``
        (scaled state units), the bounds cannot be kept together, even where
        :meth:`relax_bounds`' envelope (the extreme trajectories, unclipped) reaches each of
        them on its own: a hard NLP would fail, and :meth:`solve` goes to the
        least-violation phase at once. (It does not replace the envelope's test, which also
        relaxes bounds reached by less than its margin.)

        Parameters
        ----------
        x0 : ndarray, shape (nx,)
            Initial state (physical units).
        disturbances : ndarray, shape (N, nd)
            Non-control inputs of each interval.
        lower, upper : ndarray, shape (N, nx)
            State bounds at the end of each interval (physical units; +-inf for unbounded).
        margin : float
            How far a bound must be missed [scaled state units].

        """
        if not self.monotone:
            return False
        pad = margin * self._state_scaling_for(lower, upper).scale
        tube = np.repeat(np.asarray(x0, dtype=float)[None, :], 2, axis=0)  # lowest, highest
        u = np.empty((2, len(self.model.input_names)))
        u[:, self._control_index] = self.control_bounds.T  # lower bounds, upper bounds
        times = self._t_start_s
        for k in range(self.n_intervals):
            u[:, self._disturbance_index] = disturbances[k]
            ends, _ = self.model.simulate_intervals(
                tube, u, self.step_s,
                **self._times(None if times is None else np.full(2, times[k])))
            self.model_evaluations += 2
            if (ends[1] < lower[k] - pad).any() or (ends[0] > upper[k] + pad).any():
                return True
            tube = np.minimum(np.maximum(ends, lower[k]), upper[k])  # (np.clip, faster)
        return False

    def relax_bounds(self, x0: np.ndarray, disturbances: np.ndarray, lower: np.ndarray,
                     upper: np.ndarray, margin: float = 1e-4) -> tuple[np.ndarray, np.ndarray,
                                                                       bool]:
        """
        Relax state bounds that no control can reach from ``x0``.

        Where even the extreme controls cannot bring a state inside its bounds
        (too little capacity, or an initial state outside the band), the bound
        is moved to the reachable envelope (minus ``margin``, in scaled state
        units) so the hard-bounded problem stays feasible and its optimum rides
        along the band's closest reachable edge.

        Returns
        -------
        lower, upper : ndarray, shape (N, nx)
        relaxed : bool
            Whether any bound moved.

        """
        env_low, env_high = self.reachable_envelope(x0, disturbances)
        pad = margin * self._state_scaling_for(lower, upper).scale
        new_lower = np.where(env_high - pad < lower, env_high - pad, lower)
        new_upper = np.where(env_low + pad > upper, env_low + pad, upper)
        relaxed = bool((new_lower != lower).any() or (new_upper != upper).any())
        return new_lower, new_upper, relaxed

    def solve(self, x0: Sequence[float], disturbances: np.ndarray, lower: np.ndarray,
              upper: np.ndarray, solver: Solver, z0: np.ndarray | None = None,
              relax: bool = True, deadline: float | None = None,
              t0_s: float | None = None) -> ShootingResult:
        """
        Optimise the horizon from ``x0``.

        With hard bounds, where the band cannot be reached from ``x0`` (the
        extreme controls cannot bring the state inside, a monotone model's tube
        misses it (:meth:`infeasible_band`), or the hard problem fails), a first
        phase minimises the violation (soft bounds, a large
        linear penalty); the bounds are then relaxed to that least-violating
        trajectory and the hard problem is solved from it: the plan keeps the
        state as close to the band as physics allows, at the least cost.

        Parameters
        ----------
        x0 : sequence of float, length nx
            Initial state (physical units).
        disturbances : ndarray, shape (N, nd)
            Non-control inputs of each interval, in ``self.disturbance_names`` order.
        lower, upper : ndarray, shape (N, nx)
            State bounds at the end of each interval (physical units; +-inf
            for unbounded).
        solver : Solver
            The NLP solver.
        z0 : ndarray, optional
            Warm start (normalised NLP vector in :attr:`index` layout); default:
            controls 0 and states x0.
        relax : bool
            Relax unreachable hard bounds (ignored with soft bounds).
        deadline : float, optional
            :func:`time.perf_counter` time [s] at which the solver stops (the
            result then has ``success=False`` and ``budget_exceeded=True``).
        t0_s : float, optional
            Start time of the horizon [s] (the caller's time base): interval k
            is simulated from ``t0_s + k * step_s``. None: every interval
            starts at t = 0 (time-invariant models).

        Returns
        -------
        ShootingResult

        Raises
        ------
        ModelValueError
            If the model produces non-finite values (e.g. an FMU's NaN): the
            solve is over, the caller falls back.

        """
        started = time.perf_counter()
        self.model_evaluations = 0
        self._deadline = deadline
        self._batch = None  # (a batch per solve: its NLPs share it)
        n, nx = self.n_intervals, len(self.model.state_names)
        x0 = np.asarray(x0, dtype=float).reshape(-1)
        disturbances = np.asarray(disturbances, dtype=float).reshape(n, len(self.disturbance_cols))
        lower = np.asarray(lower, dtype=float).reshape(n, nx)
        upper = np.asarray(upper, dtype=float).reshape(n, nx)
        if x0.size != nx or not np.isfinite(x0).all():
            raise ValueError(f'x0 must be {nx} finite values, got {x0}')
        if not np.isfinite(disturbances).all():
            raise ValueError('disturbances must be finite')
        if (lower > upper).any():
            raise ValueError('state bounds must have lower <= upper')
        if t0_s is not None and not np.isfinite(float(t0_s)):
            raise ValueError(f't0_s must be a finite time [s], got {t0_s}')
        self._t_start_s = (None if t0_s is None
                           else float(t0_s) + np.arange(n) * self.step_s)
        self._x_scaling = self._state_scaling_for(lower, upper)
        if z0 is None or np.asarray(z0).size != self.index.size:
            z0 = self.index.pack(np.zeros((n, self.index.n_controls)),
                                 np.tile(self._x_scaling.to_hat(x0), (n, 1)))
        z0 = np.asarray(z0, dtype=float)
        if self.soft_bounds:
            result = self._solve_nlp(x0, disturbances, lower, upper, solver, z0, self.index,
                                     self.soft_penalty, self.soft_penalty_linear)
            result.relaxed = False
        else:
            unreachable = relax and (self.relaxation == 'exact-penalty' or self.relax_bounds(
                x0, disturbances, lower, upper)[2] or self.infeasible_band(
                x0, disturbances, lower, upper))
            result = None
            if not unreachable:
                result = self._solve_nlp(x0, disturbances, lower, upper, solver, z0,
                                         self.index, 0.0, 0.0)
                result.relaxed = False
            if relax and (unreachable or not result.success) and not (
                    result is not None and result.budget_exceeded):
                result = self._solve_least_violation(x0, disturbances, lower, upper, solver, z0)
        result.solve_time_s = time.perf_counter() - started
        result.model_evaluations = self.model_evaluations
        return result

    def _solve_least_violation(self, x0: np.ndarray, disturbances: np.ndarray,
                               lower: np.ndarray, upper: np.ndarray, solver: Solver,
                               z0: np.ndarray) -> ShootingResult:
        """
        Solve for the least violation of the bounds: one soft solve, a second only if it fails.

        Phase 1: the least violation (soft bounds, an exact linear penalty) at the least cost.
        Its plan is kept with the 'exact-penalty' relaxation, and with 'two-phase' where it
        converged with a solver that certifies the KKT conditions (``solver.certifies_kkt``,
        IPOPT): with the bounds relaxed to its trajectory, the hard problem of least cost
        (phase 2) has it as a KKT point, with phase 1's multipliers of the band (w1 + 2 w2 s
        >= 0 where it is missed by s, the same where it is kept), and the second-order
        conditions of phase 1 hold on phase 2's smaller critical cone: phase 2 returns the
        same plan to the solver's tolerance (but for its margin: it lets the states miss the
        band by 1e-6 more, scaled), for as many iterations again (issue 26). Phase 2 runs
        otherwise: the hard problem within the bounds relaxed to phase 1's trajectory, from it
        (SLSQP's convergence test is on the objective's change: phase 2 moves its plans).
        """
        soft = NlpIndex(self.n_intervals, self.index.n_controls, self.index.n_states, True)
        phase1 = self._solve_nlp(x0, disturbances, lower, upper, solver,
                                 soft.pack(self.index.u(z0), self.index.x(z0)), soft,
                                 LEAST_VIOLATION_QUADRATIC, LEAST_VIOLATION_LINEAR)
        if (self.relaxation == 'exact-penalty' or phase1.budget_exceeded
                or (phase1.success and solver.certifies_kkt)):
            # the large linear penalty made phase 1 lexicographic: keep its plan
            phase1.x = self.index.pack(soft.u(phase1.x), soft.x(phase1.x))
            phase1.fun = float(self._cost_functions(lambda z: None, self.index)[0](phase1.x))
            phase1.relaxed = bool(np.any(phase1.slacks > 1e-6 * self._x_scaling.scale))
            return phase1
        margin = 1e-6 * self._x_scaling.scale
        reached = phase1.simulated_states[1:]
        relaxed_lower = np.minimum(lower, reached - margin)
        relaxed_upper = np.maximum(upper, reached + margin)
        z_hard = self.index.pack(soft.u(phase1.x), self._x_scaling.to_hat(reached))
        result = self._solve_nlp(x0, disturbances, relaxed_lower, relaxed_upper, solver, z_hard,
                                 self.index, 0.0, 0.0)
        result.relaxed = True
        result.nit += phase1.nit
        result.nfev += phase1.nfev
        if not phase1.success:
            result.message = f'{result.message} (least-violation phase: {phase1.message})'
        with np.errstate(invalid='ignore'):  # unbounded states: inf - inf
            relaxed_by = np.fmax(lower - relaxed_lower, relaxed_upper - upper)
        logger.debug('bounds relaxed by up to %.3g (state units): least-violation phase %s, '
                     'least-cost phase %s', float(np.nanmax(relaxed_by, initial=0.0)),
                     phase1.message, result.message)
        return result

    def _solve_nlp(self, x0: np.ndarray, disturbances: np.ndarray, lower: np.ndarray,
                   upper: np.ndarray, solver: Solver, z0: np.ndarray, idx: NlpIndex,
                   penalty_quadratic: float, penalty_linear: float) -> ShootingResult:
        """Build and solve one NLP (hard bounds unless ``idx.soft``)."""
        n, nx = self.n_intervals, len(self.model.state_names)
        xs, us = self._x_scaling, self.control_scaling
        lower_hat, upper_hat = xs.to_hat(lower), xs.to_hat(upper)
        u_lo = us.to_hat(self.control_bounds[:, 0])
        u_hi = us.to_hat(self.control_bounds[:, 1])

        cache: dict[bytes, IntervalJacobians] = {}
        # the intervals of every evaluation: one batch of the model, its buffers written in
        # place (the start state of interval 0 and the disturbances once, here)
        u_slice, x_slice = idx.u_slice, idx.x_slice
        t_start_s = self._t_start_s
        # one batch for the NLPs of a solve (a least-violation phase, then the least cost):
        # the same intervals and times; bound to the model's driver by the first
        times = t_start_s if self._takes_times else None
        key = (id(self.model), n, self.step_s, tuple(self.control_cols),
               None if times is None else np.asarray(times, dtype=float).tobytes())
        if self._batch is not None and self._batch[0] == key:
            batch = self._batch[1]
        else:
            batch = self.model.interval_batch(n, self.step_s, self.control_cols, times)
            self._batch = (key, batch)
        batch.x_start[0] = x0
        batch.u[:] = self._full_inputs(np.zeros((n, idx.n_controls)), disturbances)
        analytic = True  # (until the model returns no analytic derivatives)
        # from_hat written into the batch's buffers (v_hat * scale, then + offset: the same
        # numbers): the starts of intervals 1..N-1, and the controls' columns of the inputs
        # where they are adjacent (a view), else assigned
        x_later, x_scale, x_offset = batch.x_start[1:], xs.scale, xs.offset
        columns = self._control_index
        u_controls = (batch.u[:, columns[0]:columns[-1] + 1] if columns.size and bool(
            (np.diff(columns) == 1).all()) else None)
        u_scale, u_offset = us.scale, us.offset

        def evaluate(z: np.ndarray) -> IntervalJacobians:
            nonlocal analytic
            key = z.tobytes()
            jac = cache.get(key)
            if jac is None:
                np.multiply(z[x_slice].reshape(n, nx)[:-1], x_scale, out=x_later)
                np.add(x_later, x_offset, out=x_later)
                u_hat = z[u_slice].reshape(n, idx.n_controls)
                if u_controls is None:
                    batch.u[:, columns] = us.from_hat(u_hat)
                else:
                    np.multiply(u_hat, u_scale, out=u_controls)
                    np.add(u_controls, u_offset, out=u_controls)
                jac = batch.jacobians() if analytic else None
                if jac is None:  # finite differences (_interval_jacobians asks again)
                    analytic = False
                    jac = self._interval_jacobians(batch.x_start.copy(), batch.u.copy(),
                                                   t_start_s)
                else:
                    self.model_evaluations += n
                cache.clear()
                cache[key] = jac
            return jac

        def eq_fun(z: np.ndarray) -> np.ndarray:
            jac = evaluate(z)
            return (xs.to_hat(jac.x_end) - z[x_slice].reshape(n, nx)).reshape(-1)

        structure = self._continuity_structure(idx)
        factors = structure.factors(xs.scale, us.scale)

        def eq_jac_values(z: np.ndarray) -> np.ndarray:
            jac = evaluate(z)
            return structure.scaled_values(jac.dx_du, jac.dx_dx0, factors)

        eq_jac = SparseJacobian(structure.rows, structure.cols, structure.shape, eq_jac_values)

        cost_fun, cost_grad = self._cost_functions(evaluate, idx)
        cost_hess = self._cost_hessian_diag(idx)

        def hess_diag(z: np.ndarray) -> np.ndarray | None:
            h = cost_hess(z)
            if idx.soft:
                h[idx.s_slice] += 2.0 * penalty_quadratic
            return h

        def fun(z: np.ndarray) -> float:
            value = cost_fun(z)
            if idx.soft:
                slack = idx.s(z)  # (np.add.reduce: np.sum without its wrapper)
                value += (penalty_quadratic * float(np.add.reduce(slack ** 2, None))
                          + penalty_linear * float(np.add.reduce(slack, None)))
            return value

        def grad(z: np.ndarray) -> np.ndarray:
            g = cost_grad(z)
            if idx.soft:
                g[idx.s_slice] += 2.0 * penalty_quadratic * z[idx.s_slice] + penalty_linear
            return g

        lb = np.full(idx.size, -np.inf)
        ub = np.full(idx.size, np.inf)
        idx.u(lb)[:] = u_lo  # (every interval's row: np.tile's values)
        idx.u(ub)[:] = u_hi
        if idx.soft:
            lb[idx.s_slice] = 0.0
            finite_lo = np.isfinite(lower_hat).reshape(-1)
            finite_hi = np.isfinite(upper_hat).reshape(-1)
            lower_flat, upper_flat, s_slice = lower_hat.reshape(-1), upper_hat.reshape(-1), \
                idx.s_slice
            everywhere = bool(finite_lo.all() and finite_hi.all())

            def ineq_fun(z: np.ndarray) -> np.ndarray:
                x_hat = z[x_slice]
                s_hat = z[s_slice]
                if everywhere:  # (a band bounded at every interval end: nothing to select)
                    return np.concatenate([x_hat - lower_flat + s_hat,
                                           upper_flat - x_hat + s_hat])
                return np.concatenate([(x_hat - lower_flat + s_hat)[finite_lo],
                                       (upper_flat - x_hat + s_hat)[finite_hi]])

            ineq_jac = _band_jacobian(idx, finite_lo, finite_hi)
        else:
            ineq_fun = ineq_jac = None
            lb[idx.x_slice] = lower_hat.reshape(-1)
            ub[idx.x_slice] = upper_hat.reshape(-1)

        nlp = Nlp(fun=fun, grad=grad, eq_fun=eq_fun, eq_jac=eq_jac, lb=lb, ub=ub,
                  ineq_fun=ineq_fun, ineq_jac=ineq_jac,
                  objective_hessian_diag=hess_diag if cost_hess is not None else None)
        if self.mode == 'naive':
            nlp = self._naive_nlp(nlp, idx, x0, disturbances, fun)
        try:
            raw = solver.solve(nlp, np.asarray(z0, dtype=float),
                               deadline=self._deadline)
            z = np.asarray(raw.x, dtype=float)
            success, status, message = bool(raw.success), int(raw.status), str(raw.message)
            nit, nfev = int(getattr(raw, 'nit', 0)), int(getattr(raw, 'nfev', 0))
            budget_exceeded = bool(getattr(raw, 'budget_exceeded', False))
        except ModelValueError:
            raise  # the model failed (non-finite values): no plan from this solve
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            logger.warning('solver %s raised %s: %s', solver.name, type(exc).__name__, exc)
            z = np.clip(np.asarray(z0, dtype=float), lb, ub)
            success, status, message, nit, nfev = False, -1, f'solver error: {exc}', 0, 0
            budget_exceeded = False
        if not np.isfinite(z).all():
            z = np.clip(np.asarray(z0, dtype=float), lb, ub)
            success, status, message = False, -2, 'solver returned non-finite values'
        z[idx.u_slice] = np.clip(z[idx.u_slice], lb[idx.u_slice], ub[idx.u_slice])
        controls = us.from_hat(idx.u(z))
        jac = evaluate(z)
        x_end = xs.from_hat(idx.x(z))
        defect = np.abs(jac.x_end - x_end)
        states = np.vstack([x0[None, :], x_end])
        result = ShootingResult(
            x=z, fun=float(fun(z)), success=success, status=status, message=message, nit=nit,
            nfev=nfev, controls=controls, states=states, outputs=jac.y_end.copy(),
            slacks=(idx.s(z) * xs.scale if idx.soft else np.zeros((n, nx))),
            max_defect=float(defect.max()), lower=lower, upper=upper,
            simulated_states=np.vstack([x0[None, :], jac.x_end]),
            solve_time_s=0.0, model_evaluations=0, budget_exceeded=budget_exceeded)
        return result

    def _continuity_structure(self, idx: NlpIndex) -> 'ContinuityStructure':
        """
        Return the continuity-constraint structure of the layout ``idx``.

        Built once per layout: the model's pattern is fixed.
        """
        if idx not in self._structures:
            self._structures[idx] = ContinuityStructure(
                idx, self.model.jacobian_sparsity(self.control_cols))
        return self._structures[idx]

    def simulate_serially(self, x_start: np.ndarray, controls: np.ndarray,
                          disturbances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Interval end states and outputs, one ``simulate`` call (DataFrames) per interval.

        Models that can simulate the way the ancestor did (an FMU loaded from its
        file for every simulation: ``simulate_fresh``) do so here.
        """
        simulate = getattr(self.model, 'simulate_fresh', self.model.simulate)
        u = self._full_inputs(controls, disturbances)
        x_end = np.empty_like(x_start)
        y_end = np.empty((x_start.shape[0], len(self.model.output_names)))
        times = self._t_start_s if self._takes_times else None
        for k in range(x_start.shape[0]):
            t0 = 0.0 if times is None else float(times[k])
            udf = pd.DataFrame(np.vstack([u[k], u[k]]), index=[t0, t0 + self.step_s],
                               columns=list(self.model.input_names))
            ydf, xdf = simulate(udf, x_start[k])
            x_end[k] = xdf.to_numpy()[-1]
            y_end[k] = ydf.to_numpy()[-1]
        self.model_evaluations += x_start.shape[0]
        return x_end, y_end

    def _naive_nlp(self, nlp: Nlp, idx: NlpIndex, x0: np.ndarray, disturbances: np.ndarray,
                   fast_fun: Callable[[np.ndarray], float]) -> Nlp:
        """Return the ancestor's evaluation: serial simulations, no cache, no derivatives."""
        xs, us = self._x_scaling, self.control_scaling

        def simulate(z: np.ndarray) -> np.ndarray:
            x_start = np.vstack([x0[None, :], xs.from_hat(idx.x(z)[:-1])])
            return self.simulate_serially(x_start, us.from_hat(idx.u(z)), disturbances)[0]

        def fun(z: np.ndarray) -> float:
            simulate(z)  # the original simulated the horizon for the cost as well
            return fast_fun(z)

        def eq_fun(z: np.ndarray) -> np.ndarray:
            return (xs.to_hat(simulate(z)) - idx.x(z)).reshape(-1)

        return dataclasses.replace(nlp, fun=fun, grad=None, eq_fun=eq_fun, eq_jac=None,
                                   ineq_jac=None)

    def _cost_hessian_diag(self, idx: NlpIndex) -> Callable[[np.ndarray], np.ndarray] | None:
        """Diagonal Hessian of a built-in cost in the NLP variables (None for user costs)."""
        if self.cost == 'quadratic':
            def hess(z: np.ndarray) -> np.ndarray:
                h = np.zeros(idx.size)
                h[idx.u_slice] = 2.0
                return h
            return hess
        if self.cost == 'output':
            def hess(z: np.ndarray) -> np.ndarray:
                return np.zeros(idx.size)  # exact for outputs affine in states and controls
            return hess
        if self.cost == 'energy':
            eps = self.energy_epsilon

            def hess(z: np.ndarray) -> np.ndarray:
                h = np.zeros(idx.size)
                h[idx.u_slice] = eps ** 2 / (z[idx.u_slice] ** 2 + eps ** 2) ** 1.5
                return h
            return hess
        return None

    def _cost_functions(self, evaluate: Callable[[np.ndarray], IntervalJacobians],
                        idx: NlpIndex) -> tuple[Callable[[np.ndarray], float],
                                                Callable[[np.ndarray], np.ndarray]]:
        if self.cost == 'quadratic':
            def cost(z: np.ndarray) -> float:
                return float(np.add.reduce(idx.u(z) ** 2, None))  # np.sum, without its wrapper

            def grad(z: np.ndarray) -> np.ndarray:
                g = np.zeros(idx.size)
                g[idx.u_slice] = 2.0 * z[idx.u_slice]
                return g
            return cost, grad
        if self.cost == 'energy':
            eps = self.energy_epsilon

            def cost(z: np.ndarray) -> float:
                return float(np.add.reduce(np.sqrt(idx.u(z) ** 2 + eps ** 2) - eps, None))

            def grad(z: np.ndarray) -> np.ndarray:
                g = np.zeros(idx.size)
                u = z[idx.u_slice]
                g[idx.u_slice] = u / np.sqrt(u ** 2 + eps ** 2)
                return g
            return cost, grad

        if self.cost == 'output':
            j = self.cost_output_index
            nx = idx.n_states

            def cost(z: np.ndarray) -> float:
                return float(np.sum(evaluate(z).y_end[:, j]))

            def grad(z: np.ndarray) -> np.ndarray:
                # interval k's output depends on its control and (k > 0) on x[k-1]
                jac = evaluate(z)
                g = np.zeros(idx.size)
                g[idx.u_slice] = (jac.dy_du[:, j, :] * self.control_scaling.scale).reshape(-1)
                start = idx.x_slice.start
                g[start:start + (idx.n_intervals - 1) * nx] = (
                    jac.dy_dx0[1:, j, :] * self._x_scaling.scale).reshape(-1)
                return g
            return cost, grad

        user_cost = self.cost
        xs = None

        def hats(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            jac = evaluate(z)
            return idx.x(z), jac.y_end / self.output_nominal, idx.u(z)

        def cost(z: np.ndarray) -> float:
            return float(user_cost(*hats(z)))

        def grad(z: np.ndarray) -> np.ndarray:
            # chain rule: x_hat and u_hat are variables; y_hat depends on (x_start, u) per
            # interval, differentiated by finite differences of the user cost
            x_hat, y_hat, u_hat = hats(z)
            jac = evaluate(z)
            base = float(user_cost(x_hat, y_hat, u_hat))
            h = 1e-7
            g = np.zeros(idx.size)
            dc_dy = np.zeros_like(y_hat)
            for arr, target in ((x_hat, idx.x_slice), (u_hat, idx.u_slice)):
                flat = arr.reshape(-1)
                for i in range(flat.size):
                    pert = arr.copy().reshape(-1)
                    pert[i] += h
                    args = [x_hat, y_hat, u_hat]
                    args[0 if target == idx.x_slice else 2] = pert.reshape(arr.shape)
                    g[target.start + i] += (float(user_cost(*args)) - base) / h
            for k in range(y_hat.shape[0]):
                for i in range(y_hat.shape[1]):
                    pert = y_hat.copy()
                    pert[k, i] += h
                    dc_dy[k, i] = (float(user_cost(x_hat, pert, u_hat)) - base) / h
            scale_x = self._x_scaling.scale
            scale_u = self.control_scaling.scale
            for k in range(self.n_intervals):
                dy = dc_dy[k] / self.output_nominal
                g[_block(idx.u_slice, k, idx.n_controls)] += (dy @ jac.dy_du[k]) * scale_u
                if k > 0:
                    g[_block(idx.x_slice, k - 1, idx.n_states)] += (dy @ jac.dy_dx0[k]) * scale_x
            return g
        del xs
        return cost, grad


class ContinuityStructure:
    """
    Sparse structure and values of the continuity-constraint Jacobian.

    Row block k (the nx continuity equations of interval k) has the entries
    d x_hat_end_k / d u_hat_k (the model's declared pattern), -I on x_hat_k,
    and, for k > 0, d x_hat_end_k / d x_hat_{k-1}: block-bidiagonal. The
    row/column arrays are fixed, so sparse solvers get one structure and
    fresh values at each call.

    Parameters
    ----------
    idx : NlpIndex
    pattern : ndarray of bool, shape (nx + ny, nx + nc), or None
        The model's interval Jacobian structure (None: dense blocks).

    """

    def __init__(self, idx: NlpIndex, pattern: np.ndarray | None) -> None:
        n, nx, nc = idx.n_intervals, idx.n_states, idx.n_controls
        if pattern is None:
            pattern = np.ones((nx, nx + nc), bool)
        self.x_rows, self.x_cols = np.nonzero(np.asarray(pattern)[:nx, :nx])
        self.u_rows, self.u_cols = np.nonzero(np.asarray(pattern)[:nx, nx:nx + nc])
        k = np.arange(n)[:, None]
        rows = [(k * nx + self.u_rows).ravel(),
                (k * nx + np.arange(nx)).ravel(),
                (k[1:] * nx + self.x_rows).ravel()]
        cols = [(idx.u_slice.start + k * nc + self.u_cols).ravel(),
                (idx.x_slice.start + k * nx + np.arange(nx)).ravel(),
                (idx.x_slice.start + (k[1:] - 1) * nx + self.x_cols).ravel()]
        self.rows = np.concatenate(rows)
        self.cols = np.concatenate(cols)
        self.shape = (n * nx, idx.size)
        self.minus_ones = -np.ones(n * nx)
        # dense blocks (every entry, in the row-major order of np.nonzero): the entries of an
        # interval are its block as laid out, taken by a reshape instead of fancy indexing
        self._u_block = (nx, nc) if self.u_rows.size == nx * nc else None
        self._x_block = (nx, nx) if self.x_rows.size == nx * nx else None

    def values(self, dx_du: np.ndarray, dx_dx0: np.ndarray, x_scale: np.ndarray,
               u_scale: np.ndarray) -> np.ndarray:
        """Return the entries at (:attr:`rows`, :attr:`cols`) from the interval sensitivities."""
        return self.scaled_values(dx_du, dx_dx0, self.factors(x_scale, u_scale))

    def factors(self, x_scale: np.ndarray,
                u_scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the normalisation of the d x/d u and d x/d x0 entries (fixed for a solve)."""
        return (u_scale[self.u_cols] / x_scale[self.u_rows],
                x_scale[self.x_cols] / x_scale[self.x_rows])

    def scaled_values(self, dx_du: np.ndarray, dx_dx0: np.ndarray,
                      factors: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Return :meth:`values` with the :meth:`factors` of the solve's scalings."""
        if dx_du.shape[1:] == self._u_block:
            du = dx_du.reshape(dx_du.shape[0], factors[0].size) * factors[0]
        else:
            du = dx_du[:, self.u_rows, self.u_cols] * factors[0]
        if dx_dx0.shape[1:] == self._x_block:
            dx = dx_dx0[1:].reshape(dx_dx0.shape[0] - 1, factors[1].size) * factors[1]
        else:
            dx = dx_dx0[1:, self.x_rows, self.x_cols] * factors[1]
        return np.concatenate([du.ravel(), self.minus_ones, dx.ravel()])

    def matrix(self, dx_du: np.ndarray, dx_dx0: np.ndarray, x_scale: np.ndarray,
               u_scale: np.ndarray) -> sparse.coo_array:
        """Return the Jacobian (normalised variables) from the interval sensitivities."""
        from scipy import sparse
        return sparse.coo_array((self.values(dx_du, dx_dx0, x_scale, u_scale),
                                 (self.rows, self.cols)), shape=self.shape)


def _band_jacobian(idx: NlpIndex, finite_lo: np.ndarray,
                   finite_hi: np.ndarray) -> SparseJacobian:
    """
    Return the constant Jacobian of the soft comfort band.

    The band is x_hat - lower + s_hat >= 0 (rows of the finite lower bounds), upper - x_hat + s_hat
    >= 0 (finite upper bounds): per row the entry of x, then that of s.
    """
    x_cols = idx.x_slice.start + np.arange(idx.n_intervals * idx.n_states)
    s_cols = idx.s_slice.start + np.arange(idx.n_intervals * idx.n_states)
    parts = [(x_cols[finite_lo], s_cols[finite_lo], 1.0),
             (x_cols[finite_hi], s_cols[finite_hi], -1.0)]
    m = int(np.count_nonzero(finite_lo) + np.count_nonzero(finite_hi))
    rows = np.repeat(np.arange(m), 2)
    cols = np.concatenate([np.column_stack([x, s]).ravel() for x, s, _ in parts])
    data = np.concatenate([np.column_stack([np.full(x.size, sign), np.ones(x.size)]).ravel()
                           for x, _, sign in parts])
    return SparseJacobian(rows, cols, (m, idx.size), lambda z: data, constant=True)


def _block(part: slice, k: int, width: int) -> slice:
    """Columns of block k (of ``width`` entries) inside the NLP slice ``part``."""
    return slice(part.start + k * width, part.start + (k + 1) * width)
