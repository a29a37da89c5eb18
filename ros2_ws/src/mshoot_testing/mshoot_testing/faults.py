"""
Fault injection at the real seams of the controller: the solver and the model.

Test support (package mshoot_testing, not a production package), for tests
and the soak benchmark. :class:`FaultySolver` wraps any
:class:`~mshoot_core.solvers.Solver` and :class:`FaultyModel` any
:class:`~mshoot_core.models.base.Model`; both behave exactly like the wrapped
object until a fault is armed with :meth:`Faults.arm`, then inject it on the
next calls:

- ``'fail'`` (solver): the solve reports non-convergence (``success=False``);
- ``'nan'`` (solver): the solve returns non-finite variables;
- ``'overrun'`` (solver): the solve sleeps ``delay_s`` of wall time first (a
  solve that exceeds its time budget);
- ``'raise'`` (model): every simulation raises :class:`InjectedModelError`
  (an FMU that errors) until the fault is used up.

A fault armed for ``times`` solves is consumed one per solve (a model fault
by the first simulation of each solve).

:class:`SolverOutage` is an ``on_step`` hook of the BOPTEST runner's ROS run
(:func:`mshoot_nodes.boptest_run.run_ros`): the MPC node's solver fails over a
run of control steps, then works again.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Any, Sequence

from mshoot_core.models.base import accepts_start_times, IntervalJacobians, Model
from mshoot_core.solvers import Nlp, Solver
import numpy as np
import pandas as pd
from scipy import optimize

#: Faults a :class:`FaultySolver` can inject.
SOLVER_FAULTS = ('fail', 'nan', 'overrun')
#: Faults a :class:`FaultyModel` can inject.
MODEL_FAULTS = ('raise',)


class InjectedModelError(RuntimeError):
    """Raised by a :class:`FaultyModel` with an armed fault (as an FMU error would be)."""


class Faults:
    """
    Armed faults, consumed in order (thread-safe: solves run in worker threads).

    Attributes
    ----------
    injected : Counter
        Fault kind -> times injected so far.

    """

    def __init__(self, kinds: Sequence[str]) -> None:
        self.kinds = tuple(kinds)
        self._armed: collections.deque[tuple[str, float]] = collections.deque()
        self._lock = threading.Lock()
        self.injected: collections.Counter[str] = collections.Counter()

    def arm(self, kind: str, times: int = 1, delay_s: float = 0.0) -> None:
        """Inject ``kind`` into the next ``times`` solves (``delay_s``: for 'overrun')."""
        if kind not in self.kinds:
            raise ValueError(f'fault must be one of {list(self.kinds)}, got {kind!r}')
        if times < 1 or delay_s < 0:
            raise ValueError(f'times must be >= 1 and delay_s >= 0, got {times}, {delay_s}')
        with self._lock:
            self._armed.extend([(kind, float(delay_s))] * int(times))

    def clear(self) -> None:
        """Disarm everything."""
        with self._lock:
            self._armed.clear()

    @property
    def pending(self) -> int:
        """Faults armed and not injected yet."""
        return len(self._armed)

    def take(self) -> tuple[str, float] | None:
        """Take the next armed fault (consumed), or None."""
        with self._lock:
            if not self._armed:
                return None
            fault = self._armed.popleft()
            self.injected[fault[0]] += 1
            return fault


class FaultySolver(Solver):
    """A solver that delegates to ``inner`` unless a fault is armed (see the module)."""

    name = 'faulty'

    def __init__(self, inner: Solver) -> None:
        super().__init__(inner.max_iter, inner.tol)
        self.inner = inner
        self.name = f'faulty-{inner.name}'
        self.faults = Faults(SOLVER_FAULTS)

    def solve(self, nlp: Nlp, z0: np.ndarray, deadline: float | None = None
              ) -> optimize.OptimizeResult:
        fault = self.faults.take()
        if fault is None:
            return self.inner.solve(nlp, z0, deadline)
        kind, delay_s = fault
        if kind == 'overrun':  # a solver stuck where it cannot see its deadline
            time.sleep(delay_s)
            return self.inner.solve(nlp, z0, deadline)
        if kind == 'fail':
            return optimize.OptimizeResult(x=np.asarray(z0, dtype=float).copy(),
                                           fun=float(nlp.fun(z0)), success=False, status=-1,
                                           message='injected solver failure', nit=0, nfev=1)
        return optimize.OptimizeResult(x=np.full(np.shape(z0), np.nan), fun=np.nan,
                                       success=True, status=0,
                                       message='injected non-finite solution', nit=1, nfev=1)


class FaultyModel(Model):
    """
    A model that delegates to ``inner`` unless a 'raise' fault is armed.

    Each armed fault is taken by one model call (a simulation or a Jacobian
    evaluation), which raises; the solve that made the call fails with it.
    """

    def __init__(self, inner: Model) -> None:
        self.inner = inner
        self.input_names = inner.input_names
        self.state_names = inner.state_names
        self.output_names = inner.output_names
        self.faults = Faults(MODEL_FAULTS)

    def __getattr__(self, name: str) -> Any:  # anything else the wrapped model offers
        if name == 'inner':
            raise AttributeError(name)
        return getattr(self.inner, name)

    def _maybe_raise(self) -> None:
        fault = self.faults.take()
        if fault is not None:
            raise InjectedModelError('injected model error (as an FMU that fails to '
                                     'integrate)')

    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        self._maybe_raise()
        return self.inner.simulate(udf, x0)

    def _times(self, t_start_s: np.ndarray | None) -> dict:
        """Pass interval start times on to a wrapped model that takes them."""
        if t_start_s is None or not accepts_start_times(self.inner):
            return {}
        return {'t_start_s': t_start_s}

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        self._maybe_raise()
        times = self._times(t_start_s)
        return self.inner.simulate_intervals(x_start, u, dt_s, **times)

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int],
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians | None:
        self._maybe_raise()
        times = self._times(t_start_s)
        return self.inner.interval_jacobians(x_start, u, dt_s, wrt_inputs, **times)

    def jacobian_sparsity(self, wrt_inputs: Sequence[int]) -> np.ndarray | None:
        return self.inner.jacobian_sparsity(wrt_inputs)


class SolverOutage:
    """
    An ``on_step(steps, nodes)`` hook: the MPC node's solver fails over some steps.

    At step 0 the node's solver is wrapped in a :class:`FaultySolver` (``solver``, default
    IPOPT) and the node kept (:attr:`mpc`, e.g. for its ``history``); from the first of
    ``failing`` every solve fails, from the step after the last of them the solver works again.

    Parameters
    ----------
    failing : sequence of int
        The control steps whose solves fail, consecutive, counted from 0.
    solver : str
        The wrapped solver's name (:func:`mshoot_core.solvers.make_solver`).

    """

    def __init__(self, failing: Sequence[int], solver: str = 'ipopt') -> None:
        from mshoot_core.solvers import make_solver
        self.failing = tuple(failing)
        self.solver = FaultySolver(make_solver(solver))
        self.mpc: Any = None

    def __call__(self, steps: int, nodes: dict) -> None:
        """Wrap the solver at step 0, arm the failure, clear it after the last failing step."""
        if steps == 0:
            self.mpc = nodes['controller']
            self.mpc.mpc.set_solver(self.solver)
        elif steps == self.failing[0]:
            self.solver.faults.arm('fail', times=100_000)
        elif steps == self.failing[-1] + 1:
            self.solver.faults.clear()
