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
import ctypes
import dataclasses
import functools
import importlib.util
import logging
import os
import pathlib
import sys
import time
from types import ModuleType
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
    #: Whether ``success`` certifies the KKT conditions to ``tol`` (primal and dual
    #: infeasibility, complementarity): then a converged least-violation solve is the plan
    #: (:meth:`mshoot_core.shooting.ShootingProblem.solve` skips its least-cost phase).
    #: SLSQP's test is on the change of the objective: its least-violation plans move by
    #: watts in the least-cost phase.
    certifies_kkt: bool = False

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


#: IPOPT options every :class:`IpoptSolver` sets beyond the solve's own (output, iterations,
#: tolerance, Hessian): the adaptive barrier update (``bench/versus.py`` gives CasADi's IPOPT
#: the same, with a solver's ``options``, for its same-options comparisons).
IPOPT_DEFAULT_OPTIONS: dict[str, Any] = {'mu_strategy': 'adaptive'}
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


#: CasADi's IPOPT build, in its wheel's package folder, in load order (dependencies first).
CASADI_IPOPT_LIBRARIES = ('libcoinmetis.so.2', 'libcoinmumps.so.3', 'libipopt.so.3')
#: Environment variable choosing the IPOPT build cyipopt calls: ``bundled`` (default) or
#: ``casadi`` (see :func:`import_cyipopt`).
IPOPT_BUILD_VARIABLE = 'MSHOOT_IPOPT_BUILD'
IPOPT_BUILDS = ('bundled', 'casadi')
#: The IPOPT library cyipopt calls: CasADi's when :func:`import_cyipopt` bound it, else None
#: (the one ``cyipopt-wheels`` bundles).
ipopt_library: pathlib.Path | None = None


def ipopt_build() -> str:
    """
    Return the IPOPT build chosen by ``$MSHOOT_IPOPT_BUILD`` (``bundled`` when unset).

    Raises
    ------
    ValueError
        The variable names no build of :data:`IPOPT_BUILDS`.

    """
    build = os.environ.get(IPOPT_BUILD_VARIABLE, '').strip() or 'bundled'
    if build not in IPOPT_BUILDS:
        raise ValueError(f'{IPOPT_BUILD_VARIABLE} must be one of {list(IPOPT_BUILDS)}, '
                         f'got {build!r}')
    return build


@functools.cache
def import_cyipopt() -> ModuleType:
    """
    Import cyipopt, its IPOPT calls bound to CasADi's IPOPT build if ``MSHOOT_IPOPT_BUILD=casadi``.

    cyipopt calls IPOPT through its C interface (``CreateIpoptProblem``, ``IpoptSolve``, ...),
    the same across IPOPT 3.14. The ``cyipopt-wheels`` package bundles IPOPT 3.14.11 with
    MUMPS 5.5.1 built without METIS (the default, ``bundled``); CasADi's wheel (``pip install
    casadi``, or ``make bench-setup``) IPOPT 3.14.19 with MUMPS 5.8.2 and METIS, which
    factorises the KKT systems of multiple shooting in a third of the time (docs/speed.md).
    With ``casadi``, its libraries are loaded into the global symbol scope before cyipopt's
    extension module, so that module's IPOPT symbols resolve to them; no Python module of
    CasADi is imported. The global scope then also holds CasADi's OpenBLAS; FMU binaries are
    loaded with ``RTLD_DEEPBIND`` (:func:`mshoot_core.fmu_binary.isolated`), so an FMU that
    carries its own BLAS/LAPACK (the BOPTEST heat pump house) still calls its own and its
    results do not depend on whether IPOPT ran in the process before. Opt-in: CasADi is a
    benchmark requirement, not a product one. Done once per process.

    Raises
    ------
    ValueError
        cyipopt is not installed; ``casadi`` is asked for but its wheel is not installed, or
        cyipopt was already imported (the binding is made when its extension loads).

    """
    global ipopt_library
    if ipopt_build() == 'casadi' and ipopt_library is None:
        if 'cyipopt' in sys.modules:
            raise ValueError(f'{IPOPT_BUILD_VARIABLE}=casadi: cyipopt was imported before '
                             'mshoot_core.solvers could bind it to the IPOPT build of CasADi')
        spec = importlib.util.find_spec('casadi')
        folder = (pathlib.Path(spec.origin).parent if spec is not None and spec.origin
                  else None)
        paths = [folder / name for name in CASADI_IPOPT_LIBRARIES] if folder else []
        if not paths or not all(path.is_file() for path in paths):
            raise ValueError(f'{IPOPT_BUILD_VARIABLE}=casadi needs the casadi wheel with '
                             f'{list(CASADI_IPOPT_LIBRARIES)}: pip install casadi (or make '
                             'bench-setup), or unset the variable')
        for path in paths:
            ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        ipopt_library = paths[-1]
        logger.info('IPOPT: the build of CasADi (%s)', ipopt_library)
    try:
        return _cyipopt_without_scipy()
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ValueError('solver "ipopt" needs cyipopt: pip install cyipopt-wheels') from exc


def _cyipopt_without_scipy() -> ModuleType:
    """
    Import the ``cyipopt`` package with its IPOPT interface but not yet its SciPy interface.

    cyipopt's ``__init__`` imports ``cyipopt.scipy_interface`` (``minimize_ipopt``), which
    imports ``scipy.optimize``: a third of a second of CPU, a tenth of the whole OU44 command
    with ``--solver ipopt``, for an interface mshoot does not use. Where the package lays its
    extension out as ``cyipopt-wheels`` does (the top-level module ``ipopt_wrapper``), the
    package module is made from its spec without running ``__init__``, given what
    ``__init__`` takes from the extension and ``cyipopt.exceptions`` (``Problem``,
    ``set_logging_level``, ``CyIpoptEvaluationError``, ...) and ``__version__``, and runs
    ``__init__`` at the first use of any other name (``cyipopt.minimize_ipopt`` works as
    before, a module ``__getattr__``). Another layout: ``import cyipopt`` as it is.
    """
    if 'cyipopt' in sys.modules:
        return sys.modules['cyipopt']
    spec = importlib.util.find_spec('cyipopt')
    if (spec is None or spec.loader is None or not spec.submodule_search_locations
            or importlib.util.find_spec('ipopt_wrapper') is None):
        import cyipopt
        return cyipopt
    package = importlib.util.module_from_spec(spec)
    sys.modules['cyipopt'] = package
    try:
        # the extension imports cyipopt.exceptions: a submodule of the package made above
        parts = [importlib.import_module('ipopt_wrapper'),
                 importlib.import_module('cyipopt.exceptions')]
        version = importlib.import_module('cyipopt.version')
    except BaseException:
        for name in [name for name in sys.modules if name.split('.')[0] == 'cyipopt']:
            del sys.modules[name]
        raise
    for part in parts:  # as ``from part import *``
        names = getattr(part, '__all__', None) or [
            name for name in vars(part) if not name.startswith('_')]
        for name in names:
            setattr(package, name, getattr(part, name))
    package.__version__ = version.__version__

    def rest_of_package(name: str) -> Any:
        del package.__getattr__  # (once: __init__ then defines every name it has)
        spec.loader.exec_module(package)
        return getattr(package, name)
    package.__getattr__ = rest_of_package
    return package


class IpoptSolver(Solver):
    """
    IPOPT through cyipopt (the ``cyipopt-wheels`` package), with sparse Jacobians.

    The IPOPT build is cyipopt's own, or CasADi's by choice (:func:`import_cyipopt`).

    The pattern is taken once from a :class:`SparseJacobian`; the exact diagonal objective Hessian
    where the problem gives it, else a limited-memory approximation; ``options`` are IPOPT's (e.g.
    :data:`IPOPT_LARGE_PROBLEM_OPTIONS`).
    """

    name = 'ipopt'
    certifies_kkt = True

    def __init__(self, max_iter: int = 200, tol: float = 1e-8,
                 options: dict | None = None) -> None:
        super().__init__(max_iter, tol)
        cyipopt = import_cyipopt()
        self.options = dict(options or {})
        # cyipopt logs every callback at INFO level: keep it to warnings
        cyipopt_logger = logging.getLogger('cyipopt')
        if cyipopt_logger.getEffectiveLevel() < logging.WARNING:
            cyipopt_logger.setLevel(logging.WARNING)
        # ... and tell cyipopt: it took its threshold from the level its logger had when it was
        # first imported, and below it looks the logger up at every callback
        cyipopt.set_logging_level(cyipopt_logger.getEffectiveLevel())

    def solve(self, nlp: Nlp, z0: Vector, deadline: float | None = None) -> SolverResult:
        if nlp.grad is None or nlp.eq_jac is None:
            raise ValueError('IPOPT needs derivatives: use mode "fast" or the slsqp solver')
        import cyipopt
        z_start = np.clip(z0, nlp.lb, nlp.ub)
        use_hessian = (nlp.objective_hessian_diag is not None
                       and 'hessian_approximation' not in self.options)
        callbacks = _IpoptCallbacks(nlp, z_start, deadline)
        m = callbacks.constraint_values.size
        cu = np.zeros(m)
        cu[callbacks.n_eq:] = 2e19
        lb = np.where(np.isfinite(nlp.lb), nlp.lb, -2e19)
        ub = np.where(np.isfinite(nlp.ub), nlp.ub, 2e19)
        problem = cyipopt.Problem(n=z0.size, m=m, problem_obj=callbacks, lb=lb, ub=ub,
                                  cl=np.zeros(m), cu=cu)
        problem.add_option('print_level', 0)
        problem.add_option('sb', 'yes')
        problem.add_option('max_iter', self.max_iter)
        problem.add_option('tol', self.tol)
        problem.add_option('hessian_approximation', 'exact' if use_hessian else 'limited-memory')
        for key, value in {**IPOPT_DEFAULT_OPTIONS, **self.options}.items():
            problem.add_option(key, value)
        start = time.perf_counter()
        z, info = problem.solve(z_start)
        status = int(info['status'])
        res = SolverResult(
            x=z, fun=float(info['obj_val']), success=status in (0, 1), status=status,
            message=info['status_msg'].decode() if isinstance(info['status_msg'], bytes)
            else str(info['status_msg']),
            nit=callbacks.nit, nfev=callbacks.nfev,
            wall_s=time.perf_counter() - start)
        _mark_budget(res, deadline)
        return res


class _IpoptCallbacks:
    """
    The callbacks cyipopt calls for one :class:`Nlp`, on arrays allocated once per solve.

    The constraint Jacobian's pattern is the concatenation of the equality and inequality
    patterns (taken from a :class:`SparseJacobian` without an evaluation, else from one
    evaluation at ``z_start``); its constant parts (e.g. a soft band's) are written into
    the entries once, the others at each call, in place. The constraint values are written
    into one array. (cyipopt copies what a callback returns into IPOPT's own arrays.)
    """

    def __init__(self, nlp: Nlp, z_start: Vector, deadline: float | None) -> None:
        self.nlp = nlp
        self.deadline = deadline
        self.nfev = 0
        self.nit = 0
        offset, entries, row_parts, col_parts = 0, 0, [], []
        varying: list[tuple[slice, Callable[[Vector], Vector]]] = []
        constant: list[tuple[slice, Vector]] = []
        for jac in [nlp.eq_jac] + ([nlp.ineq_jac] if nlp.ineq_fun is not None else []):
            if isinstance(jac, SparseJacobian):  # the pattern without an evaluation
                rows, cols, m_part, values = jac.rows, jac.cols, jac.shape[0], jac.values
                fixed = jac.constant
            else:
                structure = jac(z_start)
                rows, cols, m_part = structure.row, structure.col, structure.shape[0]
                fixed = False

                def values(z: Vector, jac: Callable = jac) -> Vector:
                    return jac(z).data
            part = slice(entries, entries + rows.size)
            if fixed:
                constant.append((part, values(None)))
            else:
                varying.append((part, values))
            row_parts.append(rows + offset)
            col_parts.append(cols)
            offset += m_part
            entries += rows.size
            if len(row_parts) == 1:
                self.n_eq = m_part
        self.rows = np.concatenate(row_parts)
        self.cols = np.concatenate(col_parts)
        self.jacobian_values = np.empty(entries)
        for part, values in constant:
            self.jacobian_values[part] = values
        self._varying = varying
        self.constraint_values = np.empty(offset)
        self._eq = self.constraint_values[:self.n_eq]
        self._ineq = self.constraint_values[self.n_eq:]
        self._diagonal = np.arange(z_start.size)

    def objective(self, z: Vector) -> float:
        self.nfev += 1
        return self.nlp.fun(z)

    def gradient(self, z: Vector) -> Vector:
        return self.nlp.grad(z)

    def constraints(self, z: Vector) -> Vector:
        self._eq[:] = self.nlp.eq_fun(z)
        if self._ineq.size:
            self._ineq[:] = self.nlp.ineq_fun(z)
        return self.constraint_values

    def jacobian(self, z: Vector) -> Vector:
        for part, values in self._varying:
            self.jacobian_values[part] = values(z)
        return self.jacobian_values

    def jacobianstructure(self) -> tuple[np.ndarray, np.ndarray]:
        return self.rows, self.cols

    def hessianstructure(self) -> tuple[np.ndarray, np.ndarray]:
        return self._diagonal, self._diagonal

    def hessian(self, z: Vector, lagrange: Vector, obj_factor: float) -> Vector:
        return obj_factor * self.nlp.objective_hessian_diag(z)

    def intermediate(self, *args: Any) -> bool:
        self.nit = int(args[1])
        # False stops IPOPT (status 5, user requested stop) past the deadline
        return self.deadline is None or time.perf_counter() <= self.deadline


SOLVERS: dict[str, type[Solver]] = {cls.name: cls for cls in (SlsqpSolver, TrustConstrSolver,
                                                              IpoptSolver)}


def make_solver(name: str | Solver, **options) -> Solver:
    """Return a solver by name ('slsqp', 'trust-constr', 'ipopt') or pass one through."""
    if isinstance(name, Solver):
        return name
    if name not in SOLVERS:
        raise ValueError(f'unknown solver {name!r}; choose one of {sorted(SOLVERS)}')
    return SOLVERS[name](**options)
