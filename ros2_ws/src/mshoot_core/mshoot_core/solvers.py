"""
NLP solvers behind one interface: SciPy SLSQP, SciPy trust-constr, IPOPT (cyipopt).

A :class:`Nlp` is the smooth problem

    min f(z)  s.t.  c_eq(z) = 0,  c_ineq(z) >= 0,  lb <= z <= ub

with callables for values and (dense) Jacobians plus an optional sparsity
pattern of the constraint Jacobian. A solver takes an :class:`Nlp` and a start
point and returns a :class:`~mshoot_core.slsqp.SolverResult` (the fields of
``scipy.optimize.OptimizeResult``); non-convergence is a status
(``success=False``), never an exception. ``scipy.optimize`` and ``scipy.sparse``
are imported where a solver needs them (SLSQP with every derivative given needs
neither: :mod:`mshoot_core.slsqp`).

A solve can be given a wall-clock deadline (:func:`time.perf_counter` seconds):
the solver itself stops at its first iteration past it (SciPy's methods
through their ``callback``, IPOPT through its ``intermediate`` callback) and
returns its last iterate with ``success=False`` and ``budget_exceeded=True``.
"""
from __future__ import annotations

import abc
import dataclasses
import logging
import time
from typing import Any, Callable

import numpy as np

from mshoot_core.slsqp import ConstraintBlock, core, minimize_slsqp, SolverResult
from mshoot_core.sparse_jacobian import SparseJacobian

logger = logging.getLogger(__name__)

Vector = np.ndarray
Matrix = np.ndarray


@dataclasses.dataclass
class Nlp:
    """
    A smooth nonlinear program in the variables z (length n).

    Attributes
    ----------
    fun, grad : callables
        Objective f(z) -> float and its gradient -> (n,) (None: the solver
        estimates it by finite differences, where it can).
    eq_fun, eq_jac : callables
        Equality constraints c_eq(z) -> (m_eq,) and Jacobian -> sparse
        (m_eq, n) ``scipy.sparse.coo_array`` whose row/column arrays are the
        same at every call (None: estimated by the solver).
    ineq_fun, ineq_jac : callables or None
        Inequality constraints c_ineq(z) >= 0 -> (m_in,) and Jacobian (as eq_jac).
    lb, ub : ndarray, shape (n,)
        Variable bounds (may be +-inf).
    objective_hessian_diag : callable or None
        Diagonal of the objective's Hessian -> (n,), when the objective is
        separable. Solvers that take a Hessian use it as the Hessian of the
        Lagrangian, which is exact when the constraints are affine (e.g. the
        R1C1 zones: interval end states are affine in start state and heat
        rate) and a Gauss-Newton-like approximation otherwise.

    """

    fun: Callable[[Vector], float]
    grad: Callable[[Vector], Vector] | None
    eq_fun: Callable[[Vector], Vector]
    eq_jac: Callable[[Vector], Matrix] | None
    lb: Vector
    ub: Vector
    ineq_fun: Callable[[Vector], Vector] | None = None
    ineq_jac: Callable[[Vector], Matrix] | None = None
    objective_hessian_diag: Callable[[Vector], Vector] | None = None


class Solver(abc.ABC):
    """Solves an :class:`Nlp` from a start point."""

    #: Short name used in configuration ('slsqp', 'ipopt', ...).
    name: str = ''

    def __init__(self, max_iter: int = 200, tol: float = 1e-10) -> None:
        if max_iter < 1:
            raise ValueError(f'max_iter must be >= 1, got {max_iter}')
        if not tol > 0:
            raise ValueError(f'tol must be > 0, got {tol}')
        self.max_iter = int(max_iter)
        self.tol = float(tol)

    @abc.abstractmethod
    def solve(self, nlp: Nlp, z0: Vector, deadline: float | None = None) -> SolverResult:
        """
        Solve ``nlp`` from ``z0``.

        Return a SolverResult (x, fun, success, status, message, nit, nfev, budget_exceeded).

        ``deadline`` is a :func:`time.perf_counter` time [s]: the solver stops at
        its first iteration past it (``success=False``, ``budget_exceeded=True``).
        """


def _deadline_callback(deadline: float | None) -> Callable | None:
    """Return a SciPy ``callback(intermediate_result)`` that stops the solve past ``deadline``."""
    if deadline is None:
        return None

    def callback(intermediate_result: SolverResult) -> None:
        if time.perf_counter() > deadline:
            raise StopIteration
    return callback


def _mark_budget(res: SolverResult, deadline: float | None) -> None:
    """Flag a result stopped by its deadline (SciPy reports it as status 99)."""
    stopped = deadline is not None and time.perf_counter() > deadline and not res.success
    res.budget_exceeded = bool(stopped)
    if stopped:
        res.success = False
        res.message = f'time budget exceeded after {int(getattr(res, "nit", 0))} iterations'


class SlsqpSolver(Solver):
    """
    SciPy's SLSQP (dense; fine for short horizons and few zones).

    With every derivative given, its compiled core is driven by
    :func:`mshoot_core.slsqp.minimize_slsqp` (the iterates of
    ``scipy.optimize.minimize``, without importing ``scipy.optimize``); a problem
    whose derivatives SciPy estimates, or a SciPy whose core this does not drive
    (:func:`mshoot_core.slsqp.core`), goes through ``scipy.optimize.minimize``.
    """

    name = 'slsqp'

    def __init__(self, max_iter: int = 200, tol: float = 1e-10) -> None:
        super().__init__(max_iter, tol)
        # Load the core (and the OpenBLAS it links) now, before any solve: the MPC limits
        # the BLAS thread pools loaded when it first solves (mpc.blas_threads), and a pool
        # loaded later would run the core's BLAS calls with its default threads, whose
        # rounding differs.
        core()

    def solve(self, nlp: Nlp, z0: Vector, deadline: float | None = None) -> SolverResult:
        derivatives = nlp.grad is not None and nlp.eq_jac is not None and (
            nlp.ineq_fun is None or nlp.ineq_jac is not None)
        fixed = (np.asarray(nlp.lb) == np.asarray(nlp.ub)).all()  # (SciPy's own case)
        if derivatives and core() is not None and not fixed:
            res = minimize_slsqp(
                nlp.fun, nlp.grad, z0, nlp.lb, nlp.ub, ConstraintBlock(nlp.eq_fun, nlp.eq_jac),
                None if nlp.ineq_fun is None else ConstraintBlock(nlp.ineq_fun, nlp.ineq_jac),
                self.max_iter, self.tol, deadline)
        else:
            from scipy import optimize
            constraints = [_scipy_constraint('eq', nlp.eq_fun, nlp.eq_jac)]
            if nlp.ineq_fun is not None:
                constraints.append(_scipy_constraint('ineq', nlp.ineq_fun, nlp.ineq_jac))
            res = optimize.minimize(nlp.fun, np.clip(z0, nlp.lb, nlp.ub), jac=nlp.grad,
                                    bounds=optimize.Bounds(nlp.lb, nlp.ub),
                                    constraints=constraints, method='SLSQP',
                                    options={'maxiter': self.max_iter, 'ftol': self.tol},
                                    callback=_deadline_callback(deadline))
        res.nit = int(getattr(res, 'nit', 0))
        _mark_budget(res, deadline)
        return res


def _scipy_constraint(kind: str, fun: Callable, jac: Callable | None) -> dict:
    """
    Return a SciPy (SLSQP) constraint dict with a dense Jacobian.

    Without ``jac`` SciPy estimates it by finite differences.
    """
    constraint = {'type': kind, 'fun': fun}
    if isinstance(jac, SparseJacobian):
        constraint['jac'] = jac.dense
    elif jac is not None:
        constraint['jac'] = lambda z: jac(z).toarray()
    return constraint


class TrustConstrSolver(Solver):
    """SciPy's trust-constr with sparse constraint Jacobians."""

    name = 'trust-constr'

    def solve(self, nlp: Nlp, z0: Vector, deadline: float | None = None) -> SolverResult:
        from scipy import optimize, sparse
        n_eq = nlp.eq_fun(z0).size

        def sparse_jac(jac: Callable | None) -> Callable | str:
            return '2-point' if jac is None else (lambda z: sparse.csr_array(jac(z)))
        constraints = [optimize.NonlinearConstraint(
            nlp.eq_fun, np.zeros(n_eq), np.zeros(n_eq), jac=sparse_jac(nlp.eq_jac),
            hess=optimize.BFGS())]
        if nlp.ineq_fun is not None:
            n_in = nlp.ineq_fun(z0).size
            constraints.append(optimize.NonlinearConstraint(
                nlp.ineq_fun, np.zeros(n_in), np.full(n_in, np.inf),
                jac=sparse_jac(nlp.ineq_jac), hess=optimize.BFGS()))
        z0 = np.clip(z0, nlp.lb, nlp.ub)
        res = optimize.minimize(nlp.fun, z0, jac=nlp.grad if nlp.grad is not None else '2-point',
                                hess=optimize.BFGS(),
                                bounds=optimize.Bounds(nlp.lb, nlp.ub),
                                constraints=constraints, method='trust-constr',
                                options={'maxiter': self.max_iter, 'gtol': self.tol,
                                         'xtol': self.tol, 'verbose': 0},
                                callback=_deadline_callback(deadline))
        res.success = bool(res.status in (1, 2))
        _mark_budget(res, deadline)
        return res


#: IPOPT options for large, structured problems (many zones), where the linear algebra is
#: most of a solve. The wheel's IPOPT has one linear solver, MUMPS (5.5.1 without METIS;
#: the HSL solvers are not built in), whose solve phase is slow on the many tiny fronts
#: of a multiple-shooting KKT system: each front costs BLAS calls, with a lock per call
#: in the bundled OpenBLAS 0.3.15. These two options cut that cost by a third at 100
#: zones with the same iterates there: no iterative-refinement step where the first
#: solve is already accurate (IPOPT still refines when its residual test asks), and the
#: approximate minimum degree ordering, which suits the block-banded structure. Not the
#: default: on small, badly conditioned problems (one zone with the smoothed energy
#: cost) they change the rounding enough to move the converged plans by ~1 W.
IPOPT_LARGE_PROBLEM_OPTIONS: dict[str, Any] = {'min_refinement_steps': 0,
                                               'mumps_pivot_order': 0}


class IpoptSolver(Solver):
    """
    IPOPT through cyipopt (the ``cyipopt-wheels`` package), with sparse Jacobians.

    The pattern is taken once from a :class:`SparseJacobian`; the exact diagonal objective Hessian
    where the problem gives it, else a limited-memory approximation; ``options`` are IPOPT's (e.g.
    :data:`IPOPT_LARGE_PROBLEM_OPTIONS`).
    """

    name = 'ipopt'

    def __init__(self, max_iter: int = 200, tol: float = 1e-8,
                 options: dict | None = None) -> None:
        super().__init__(max_iter, tol)
        try:
            import cyipopt  # noqa: F401
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise ValueError('solver "ipopt" needs cyipopt: pip install cyipopt-wheels') from exc
        self.options = dict(options or {})
        # cyipopt logs every callback at INFO level: keep it to warnings
        cyipopt_logger = logging.getLogger('cyipopt')
        if cyipopt_logger.getEffectiveLevel() < logging.WARNING:
            cyipopt_logger.setLevel(logging.WARNING)

    def solve(self, nlp: Nlp, z0: Vector, deadline: float | None = None) -> SolverResult:
        if nlp.grad is None or nlp.eq_jac is None:
            raise ValueError('IPOPT needs derivatives: use mode "fast" or the slsqp solver')
        import cyipopt
        n = z0.size
        z_start = np.clip(z0, nlp.lb, nlp.ub)
        jacobians = [nlp.eq_jac] + ([nlp.ineq_jac] if nlp.ineq_fun is not None else [])
        offsets, row_parts, col_parts, entries = [0], [], [], []
        for jac in jacobians:
            if isinstance(jac, SparseJacobian):  # the pattern without an evaluation
                rows, cols, m_part, values = jac.rows, jac.cols, jac.shape[0], jac.values
            else:
                structure = jac(z_start)
                rows, cols, m_part = structure.row, structure.col, structure.shape[0]

                def values(z: Vector, jac: Callable = jac) -> Vector:
                    return jac(z).data
            row_parts.append(rows + offsets[-1])
            col_parts.append(cols)
            offsets.append(offsets[-1] + m_part)
            entries.append(values)
        rows, cols = np.concatenate(row_parts), np.concatenate(col_parts)
        m, n_eq = offsets[-1], offsets[1]
        counter = {'nfev': 0, 'nit': 0}
        use_hessian = (nlp.objective_hessian_diag is not None
                       and 'hessian_approximation' not in self.options)
        diag = np.arange(n)

        class _Problem:

            def objective(self, z):
                counter['nfev'] += 1
                return nlp.fun(z)

            def gradient(self, z):
                return nlp.grad(z)

            def constraints(self, z):
                parts = [nlp.eq_fun(z)]
                if nlp.ineq_fun is not None:
                    parts.append(nlp.ineq_fun(z))
                return np.concatenate(parts)

            def jacobian(self, z):
                return np.concatenate([values(z) for values in entries])

            def jacobianstructure(self):
                return rows, cols

            def hessianstructure(self):
                return diag, diag

            def hessian(self, z, lagrange, obj_factor):
                return obj_factor * nlp.objective_hessian_diag(z)

            def intermediate(self, *args):
                counter['nit'] = int(args[1])
                # False stops IPOPT (status 5, user requested stop) past the deadline
                return deadline is None or time.perf_counter() <= deadline

        cu = np.zeros(m)
        cu[n_eq:] = 2e19
        lb = np.where(np.isfinite(nlp.lb), nlp.lb, -2e19)
        ub = np.where(np.isfinite(nlp.ub), nlp.ub, 2e19)
        problem = cyipopt.Problem(n=n, m=m, problem_obj=_Problem(), lb=lb, ub=ub,
                                  cl=np.zeros(m), cu=cu)
        problem.add_option('print_level', 0)
        problem.add_option('sb', 'yes')
        problem.add_option('max_iter', self.max_iter)
        problem.add_option('tol', self.tol)
        problem.add_option('hessian_approximation', 'exact' if use_hessian else 'limited-memory')
        problem.add_option('mu_strategy', 'adaptive')
        for key, value in self.options.items():
            problem.add_option(key, value)
        start = time.perf_counter()
        z, info = problem.solve(z_start)
        status = int(info['status'])
        res = SolverResult(
            x=z, fun=float(info['obj_val']), success=status in (0, 1), status=status,
            message=info['status_msg'].decode() if isinstance(info['status_msg'], bytes)
            else str(info['status_msg']),
            nit=counter['nit'], nfev=counter['nfev'],
            wall_s=time.perf_counter() - start)
        _mark_budget(res, deadline)
        return res


SOLVERS: dict[str, type[Solver]] = {cls.name: cls for cls in (SlsqpSolver, TrustConstrSolver,
                                                              IpoptSolver)}


def make_solver(name: str | Solver, **options) -> Solver:
    """Return a solver by name ('slsqp', 'trust-constr', 'ipopt') or pass one through."""
    if isinstance(name, Solver):
        return name
    if name not in SOLVERS:
        raise ValueError(f'unknown solver {name!r}; choose one of {sorted(SOLVERS)}')
    return SOLVERS[name](**options)
