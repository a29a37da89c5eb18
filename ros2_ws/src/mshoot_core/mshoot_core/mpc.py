"""
The MPC controller: a configured multiple-shooting problem solved every control step.

``MPC.make_step(x0, t, forecast) -> u0`` is the loop interface; ``MPC.solve``
returns the full :class:`MpcResult`. Between steps the previous plan, shifted
by one interval, warm-starts the next solve.
"""
from __future__ import annotations

import contextlib
import functools
import logging
from typing import Any, Sequence

import numpy as np
import pandas as pd

from mshoot_core.models.base import Model
from mshoot_core.scenario import column_labels
from mshoot_core.settings import BY_NAME, MpcSettings
from mshoot_core.shooting import CostFunction, Scaling, ShootingProblem, ShootingResult
from mshoot_core.solvers import make_solver, Solver
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)

#: Default state-bound mapping of a thermal zone: state 'T' [K] bounded by the comfort
#: band columns [degC] plus an offset.
ZONE_STATE_BOUNDS = {'T': ('comfort_min', 'comfort_max', KELVIN)}


@functools.lru_cache(maxsize=1)
def _threadpools() -> Any:
    """Return the process's BLAS/OpenMP thread pools (threadpoolctl), inspected once."""
    from threadpoolctl import ThreadpoolController
    return ThreadpoolController()


def blas_threads(limit: int | None) -> contextlib.AbstractContextManager:
    """
    Limit the BLAS thread pools to ``limit`` threads inside the ``with`` block.

    MPC problems are small (tens to a few thousand variables): a multi-threaded
    BLAS only adds synchronisation, and on a loaded machine its spinning
    threads compete with the solve itself (the 72 h reference case ran 2.5x
    slower next to one other busy process). ``None`` leaves the pools alone.
    """
    if limit is None:
        return contextlib.nullcontext()
    pools = _threadpools()
    if all(pool.num_threads == int(limit) for pool in pools.lib_controllers
           if pool.user_api == 'blas'):
        return contextlib.nullcontext()  # (at the limit already, e.g. OPENBLAS_NUM_THREADS=1)
    return pools.limit(limits=int(limit), user_api='blas')


class MpcResult(ShootingResult):
    """
    One MPC step: a :class:`ShootingResult` plus the step's time, fallback and plan.

    The extra fields are ``t_s`` (start time [s]), ``fallback_used`` (bool), and ``plan``
    (DataFrame of controls and predicted states indexed by the interval start times [s]).
    """


class MPC:
    """
    Model predictive control with multiple shooting.

    Parameters
    ----------
    model : Model
        The control model.
    settings : MpcSettings, optional
        The problem, comfort and solver settings (default: the defaults,
        changed by ``options``).
    state_bounds : dict, optional
        ``{state: (lower_column, upper_column, offset)}``: the bound of the
        state at time t is ``forecast[column] + offset`` at t (default: zone
        temperature in K from a comfort band in degC). States not listed are
        unbounded.
    solver : str or Solver, optional
        A solver name (a setting) or a configured :class:`Solver` instance,
        which then replaces the one of the settings.
    cost_function : callable, optional
        A user cost on normalised quantities (see :class:`ShootingProblem`).
    state_scaling : Scaling, optional
        Fixed normalisation of the states (default: from the bounds).
    **options
        Flat settings (:data:`mshoot_core.settings.PARAMETERS`, e.g.
        ``horizon_steps=6, cost='energy'``; ``control_names``,
        ``solver_extra``) applied over ``settings``; validated with every
        problem at once (:class:`~mshoot_core.settings.SettingsError`).

    """

    def __init__(self, model: Model, settings: MpcSettings | None = None, *,
                 state_bounds: dict | None = None, solver: str | Solver | None = None,
                 cost_function: CostFunction | None = None,
                 state_scaling: Scaling | None = None, **options: Any) -> None:
        solver_instance = solver if isinstance(solver, Solver) else None
        if solver is not None and solver_instance is None:
            options['solver'] = solver
        base = settings or MpcSettings()
        declared = getattr(model, 'control_specs', None)
        if declared and not base.problem.controls and 'controls' not in options:
            options = {'controls': tuple(declared), **options}  # the card's limits, safe values
        self.settings = base.replace(options)
        bounds = ZONE_STATE_BOUNDS if state_bounds is None else dict(state_bounds)
        unknown = [s for s in bounds if s not in model.state_names]
        if unknown:
            raise ValueError(f'state_bounds names {unknown} are not states of the model '
                             f'{list(model.state_names)}')
        for name, spec in bounds.items():
            if len(spec) != 3:
                raise ValueError(f'state_bounds[{name!r}] must be (lower_column, upper_column, '
                                 f'offset), got {spec!r}')
        self.state_bounds = bounds
        self._cost_function = cost_function
        self._state_scaling = state_scaling
        self._model = model
        self.problem = self._build_problem()
        self._solver_instance = solver_instance
        self.solver = solver_instance or make_solver(self.settings.solver.solver,
                                                     **self.settings.solver.options())
        self._warm_start: np.ndarray | None = None
        self.last_result: MpcResult | None = None

    def _build_problem(self) -> ShootingProblem:
        return ShootingProblem(self._model, self.settings.problem, self.settings.comfort,
                               cost_function=self._cost_function,
                               state_scaling=self._state_scaling)

    @property
    def blas_threads(self) -> int | None:
        """BLAS threads during a solve (None: the library's default)."""
        return self.settings.problem.blas_threads or None

    # -- configuration --------------------------------------------------------------------
    @property
    def model(self) -> Model:
        return self.problem.model

    @property
    def horizon_steps(self) -> int:
        return self.problem.n_intervals

    @property
    def step_s(self) -> float:
        return self.problem.step_s

    @property
    def forecast_columns(self) -> list[str]:
        """Columns a forecast must hold: the disturbances and the bound columns."""
        cols = list(self.problem.disturbance_names)
        for lo, hi, _ in self.state_bounds.values():
            cols += [c for c in (lo, hi) if c not in cols]
        return cols

    def set_solver(self, solver: Solver) -> None:
        """
        Use a configured solver instance from now on (e.g. a custom or instrumented one).

        A later :meth:`update` of the solver settings does not replace it.
        """
        if not isinstance(solver, Solver):
            raise TypeError(f'solver must be a Solver, got {type(solver).__name__}')
        self.solver = self._solver_instance = solver

    def update(self, settings: MpcSettings) -> str:
        """
        Apply new settings; say what it took.

        Returns
        -------
        str
            'unchanged'; 'updated' (solver or comfort switched, warm start kept
            unless the NLP layout changed); or 'rebuilt' (the problem was built
            again: horizon, cost, bounds, ...; warm start lost).

        Raises
        ------
        ValueError
            If a setting that is fixed once running (``step_s``, ``mode``,
            ``blas_threads``) or the controls change.

        """
        fixed = self.settings.fixed_changes(settings)
        if fixed:
            raise ValueError(f'{fixed} cannot change once the MPC runs: build a new one')
        changed = self.settings.changed(settings)
        if not changed:
            return 'unchanged'
        old, self.settings = self.settings, settings
        applies = set().union(*(BY_NAME[n].applies if n in BY_NAME else {'solver'}
                                for n in changed))
        if 'solver' in applies and self._solver_instance is None:
            self.solver = make_solver(settings.solver.solver, **settings.solver.options())
        if 'rebuild' in applies:
            self.problem = self._build_problem()
            self._warm_start = None
            return 'rebuilt'
        if 'comfort' in applies:
            p = self.problem
            p.soft_penalty = settings.comfort.soft_penalty
            if settings.comfort.soft != old.comfort.soft:
                p.soft_bounds = settings.comfort.soft
                p.index = type(p.index)(p.n_intervals, p.index.n_controls, p.index.n_states,
                                        p.soft_bounds)
                self._warm_start = None
        return 'updated'

    def reset(self) -> None:
        """Forget the warm start (e.g. after a jump in the state)."""
        self._warm_start = None

    # -- the loop interface ---------------------------------------------------------------
    def bounds_from_forecast(self, forecast: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
        """State bounds (N, nx) at the end of each interval from forecast rows 1..N."""
        n, names = self.horizon_steps, self.model.state_names
        lower = np.full((n, len(names)), -np.inf)
        upper = np.full((n, len(names)), np.inf)
        for name, (lo, hi, offset) in self.state_bounds.items():
            i = names.index(name)
            lower[:, i] = forecast[lo].to_numpy(dtype=float)[1:n + 1] + offset
            upper[:, i] = forecast[hi].to_numpy(dtype=float)[1:n + 1] + offset
        return lower, upper

    def check_forecast(self, forecast: pd.DataFrame) -> None:
        """Raise ValueError unless ``forecast`` has N+1 rows of finite needed columns."""
        self._forecast_values(forecast)

    def _forecast_values(self, forecast: pd.DataFrame) -> np.ndarray:
        """
        Return the first N+1 rows of :attr:`forecast_columns` as floats, shape (N+1, columns).

        Checked as :meth:`check_forecast` says (one conversion of the frame per solve).
        """
        if not isinstance(forecast, pd.DataFrame):
            raise TypeError(f'forecast must be a DataFrame, got {type(forecast).__name__}')
        columns = self.forecast_columns
        positions = {name: i for i, name in enumerate(forecast.columns)}
        missing = [c for c in columns if c not in positions]
        if missing:
            raise ValueError(f'forecast lacks columns {missing}; needs {columns}')
        rows = self.horizon_steps + 1
        if len(forecast) < rows:
            raise ValueError(f'forecast must have horizon_steps + 1 = {rows} '
                             f'rows (bounds at every interval end), got {len(forecast)}')
        try:  # all columns at once (a numeric frame): far cheaper than selecting columns
            values = forecast.to_numpy(dtype=float)[:rows, [positions[c] for c in columns]]
        except (TypeError, ValueError):  # a column that is not numeric: take ours one by one
            values = np.column_stack([forecast[c].to_numpy(dtype=float)[:rows]
                                      for c in columns])
        if not np.isfinite(values).all():
            raise ValueError('forecast holds non-finite values')
        for lo, hi, _ in self.state_bounds.values():
            if (values[:, columns.index(lo)] > values[:, columns.index(hi)]).any():
                raise ValueError(f'forecast bound {lo} exceeds {hi}')
        return values

    def solve(self, x0: Sequence[float], t_s: float, forecast: pd.DataFrame,
              deadline: float | None = None) -> MpcResult:
        """
        Optimise the horizon starting at ``t_s`` from state ``x0``.

        Parameters
        ----------
        x0 : sequence of float
            Current state (physical units, e.g. T in K).
        t_s : float
            Current time [s]: labels the plan, and interval k is simulated from
            ``t_s + k * step_s`` (time-dependent models see their own time).
        forecast : DataFrame, N+1 rows
            Row k: disturbances of interval k and the bound columns at its
            start (see :meth:`check_forecast`).
        deadline : float, optional
            :func:`time.perf_counter` time [s] at which the solver stops
            (``budget_exceeded`` in the result).

        """
        values = self._forecast_values(forecast)
        n = self.horizon_steps
        columns = self.forecast_columns
        disturbances = values[:n, :len(self.problem.disturbance_names)]  # columns come first
        names = self.model.state_names
        lower = np.full((n, len(names)), -np.inf)
        upper = np.full((n, len(names)), np.inf)
        for name, (lo, hi, offset) in self.state_bounds.items():
            i = names.index(name)
            lower[:, i] = values[1:n + 1, columns.index(lo)] + offset
            upper[:, i] = values[1:n + 1, columns.index(hi)] + offset
        with blas_threads(self.blas_threads):
            result = self.problem.solve(x0, disturbances, lower, upper, self.solver,
                                        z0=self._warm_start, deadline=deadline, t0_s=t_s)
        out = MpcResult(result)
        out.t_s = float(t_s)
        times = float(t_s) + np.arange(n) * self.step_s
        out.plan = pd.DataFrame(  # one block: a column per state would fragment the frame
            np.hstack([result.controls, result.states[1:]]),
            columns=column_labels((*self.problem.control_names,
                                   *(f'{name}_end' for name in names))),
            index=pd.Index(times, name='time_s'))
        if not result.success:
            logger.warning('MPC step at t=%.0f s: solver %s did not converge (%s); returning '
                           'its best plan (max defect %.2e)', t_s, self.solver.name,
                           result.message, result.max_defect)
        self._warm_start = self._shifted(result.x)
        self.last_result = out
        return out

    def make_step(self, x0: Sequence[float], t_s: float, forecast: pd.DataFrame) -> np.ndarray:
        """Solve and return the controls of the first interval (physical units)."""
        return self.solve(x0, t_s, forecast).controls[0].copy()

    def _shifted(self, z: np.ndarray) -> np.ndarray:
        """Return the plan shifted by one interval, the last interval repeated."""
        idx = self.problem.index
        shifted = z.copy()
        for view in (idx.u, idx.x, idx.s):
            block = view(shifted)
            if block.size:
                block[:-1] = view(z)[1:]
                block[-1] = view(z)[-1]
        return shifted
