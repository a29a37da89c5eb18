"""
SciPy's SLSQP, its compiled core driven here: the iterates of ``scipy.optimize.minimize``.

:func:`minimize_slsqp` runs the loop of SciPy's ``_minimize_slsqp`` (SciPy
1.17, the C implementation ``scipy.optimize._slsqplib``) for a problem given
with every derivative: the same calls of the core with the same values, so
the same iterates, iteration and evaluation counts, status and message as
``minimize(method='SLSQP')``, without the layers around it. Two things are
saved:

- the import of ``scipy.optimize`` (some 0.3 s of CPU, every SciPy optimiser
  and their dependencies): the core's extension module is loaded from its
  file in SciPy's folder, on its own (a few ms), when ``scipy.optimize`` is
  not already loaded;
- per iteration the SciPy wrappers (``ScalarFunction``, the constraint dicts,
  a dense Jacobian built per call): the constraint Jacobians of a
  :class:`~mshoot_core.sparse_jacobian.SparseJacobian` are written into the core's
  matrix at their fixed positions.

``tests/test_core.py`` checks it against ``scipy.optimize.minimize`` (the
same x, nit, nfev, status), so a SciPy whose core changed its interface fails
there (``requirements.txt`` pins SciPy).
"""
from __future__ import annotations

import importlib.machinery
import importlib.util
import logging
import pathlib
import re
import sys
import time
from typing import Any, Callable

import numpy as np

from mshoot_core.sparse_jacobian import SparseJacobian

logger = logging.getLogger(__name__)

#: The extension module of SciPy's SLSQP core.
CORE_MODULE = 'scipy.optimize._slsqplib'
#: Exit modes of the core, as SciPy words them.
EXIT_MODES = {-1: 'Gradient evaluation required (g & a)',
              0: 'Optimization terminated successfully',
              1: 'Function evaluation required (f & c)',
              2: 'More equality constraints than independent variables',
              3: 'More than 3*n iterations in LSQ subproblem',
              4: 'Inequality constraints incompatible',
              5: 'Singular matrix E in LSQ subproblem',
              6: 'Singular matrix C in LSQ subproblem',
              7: 'Rank-deficient equality constraint subproblem HFTI',
              8: 'Positive directional derivative for linesearch',
              9: 'Iteration limit reached'}
#: Status and message of a solve stopped at its deadline (as SciPy's for a callback's stop).
STOPPED_STATUS = 99
STOPPED_MESSAGE = '`callback` raised `StopIteration`.'


class SolverResult(dict):
    """
    The result of a solve: a dict whose keys are also attributes.

    The fields and behaviour of ``scipy.optimize.OptimizeResult`` (``x``,
    ``fun``, ``success``, ``status``, ``message``, ``nit``, ``nfev``, ...),
    without importing ``scipy.optimize`` for it.
    """

    def __getattr__(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError as exc:
            raise AttributeError(name) from exc

    __setattr__ = dict.__setitem__
    __delattr__ = dict.__delitem__

    def __dir__(self) -> list[str]:
        return list(self.keys())

    def __repr__(self) -> str:
        fields = ', '.join(f'{key}={value!r}' for key, value in self.items())
        return f'{type(self).__name__}({fields})'


#: The SciPy release whose SLSQP loop :func:`minimize_slsqp` follows (``requirements.txt`` pins
#: it); with another SciPy, :func:`core` gives None and the solver calls SciPy's ``minimize``.
SCIPY_RELEASE = '1.17.'

_core: Any = None


def core() -> Any:
    """
    Return SciPy's SLSQP core function ``slsqp``, or None where this module cannot drive it.

    From the loaded ``scipy.optimize`` if it is, else its extension module
    loaded on its own from SciPy's folder (and registered under its name, so
    that a later ``import scipy.optimize`` uses the same module). None with a SciPy
    other than :data:`SCIPY_RELEASE` (its core's interface may differ: an apt-installed
    SciPy, say) or without the core.
    """
    global _core
    if _core is not None:
        return _core or None
    _core = False
    scipy_spec = importlib.util.find_spec('scipy')  # finds the package, runs nothing
    if scipy_spec is None or not scipy_spec.submodule_search_locations:
        return None
    folder = pathlib.Path(next(iter(scipy_spec.submodule_search_locations)))
    try:
        text = (folder / 'version.py').read_text()
        release = re.search(r'^version\s*=\s*[\'"]([^\'"]+)', text, re.MULTILINE)
    except OSError:
        release = None
    if release is None or not release.group(1).startswith(SCIPY_RELEASE):
        logger.debug('SciPy %s: SLSQP through scipy.optimize.minimize',
                     release.group(1) if release else '(version unknown)')
        return None
    module = sys.modules.get(CORE_MODULE)
    if module is None and 'scipy.optimize' in sys.modules:
        import scipy.optimize._slsqplib as module
    if module is None:
        paths = [folder / 'optimize' / f'_slsqplib{suffix}'
                 for suffix in importlib.machinery.EXTENSION_SUFFIXES]
        path = next((p for p in paths if p.is_file()), None)
        if path is None:
            return None
        spec = importlib.util.spec_from_file_location(CORE_MODULE, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        sys.modules[CORE_MODULE] = module
    _core = getattr(module, 'slsqp', None) or False
    return _core or None


class ConstraintBlock:
    """
    One block of constraint rows: values ``fun(x)`` and Jacobian ``jac``.

    ``jac`` is a :class:`~mshoot_core.sparse_jacobian.SparseJacobian` (entries written at
    their fixed positions) or a callable returning a dense array or a SciPy sparse matrix.
    """

    def __init__(self, fun: Callable[[np.ndarray], np.ndarray], jac: Any) -> None:
        self.fun = fun
        self.jac = jac


def minimize_slsqp(fun: Callable[[np.ndarray], float], grad: Callable[[np.ndarray], np.ndarray],
                   x0: np.ndarray, lb: np.ndarray, ub: np.ndarray,
                   eq: ConstraintBlock | None, ineq: ConstraintBlock | None,
                   max_iter: int, ftol: float, deadline: float | None = None) -> SolverResult:
    """
    Minimise ``fun`` subject to ``eq.fun(x) = 0``, ``ineq.fun(x) >= 0`` and ``lb <= x <= ub``.

    As ``scipy.optimize.minimize(fun, x0, jac=grad, bounds=Bounds(lb, ub),
    constraints=..., method='SLSQP', options={'maxiter': max_iter, 'ftol':
    ftol})`` with a callback stopping it past ``deadline``
    (:func:`time.perf_counter` time [s]).

    Parameters
    ----------
    fun, grad : callable
        Objective f(x) -> float and its gradient -> (n,).
    x0 : ndarray, shape (n,)
        Start point (clipped to the bounds).
    lb, ub : ndarray, shape (n,)
        Bounds (may be +-inf); some lb < ub (all fixed: use SciPy).
    eq, ineq : ConstraintBlock or None
        The equality and inequality constraints.
    max_iter : int
        Iteration limit.
    ftol : float
        SLSQP's accuracy goal (``ftol``).
    deadline : float, optional
        The solve stops at its first iteration past it (status 99).

    Returns
    -------
    SolverResult
        x, fun, jac, nit, nfev, njev, status, message, success, multipliers.

    """
    slsqp = core()
    if slsqp is None:
        raise RuntimeError("SciPy's SLSQP core cannot be driven here (see core())")
    lb = np.asarray(lb, dtype=float)
    ub = np.asarray(ub, dtype=float)
    x = np.clip(np.asarray(x0, dtype=float).reshape(-1), lb, ub)
    n = x.size
    blocks = [block for block in (eq, ineq) if block is not None]
    sizes = [np.atleast_1d(block.fun(x)).size for block in blocks]
    meq = sizes[0] if eq is not None else 0
    m = sum(sizes)
    mieq = m - meq
    # the core marks infinite bounds with NaN
    xl = np.where(np.isfinite(lb), lb, np.nan)
    xu = np.where(np.isfinite(ub), ub, np.nan)

    # SciPy's ScalarFunction: one memorised point; the objective and the gradient are
    # evaluated (on a copy of the point) when the point moved or they are not known there
    memo_x, memo_f, memo_g, nfev, ngev = x.copy(), 0.0, x, 0, 0
    f_known = g_known = False

    def move(point: np.ndarray) -> None:
        nonlocal memo_x, f_known, g_known
        if not (point == memo_x).all():  # np.array_equal, for arrays of one shape
            memo_x = point.copy()
            f_known = g_known = False

    def objective(point: np.ndarray) -> float:
        nonlocal memo_f, f_known, nfev
        move(point)
        if not f_known:
            memo_f = float(fun(memo_x.copy()))
            f_known = True
            nfev += 1
        return memo_f

    def gradient(point: np.ndarray) -> np.ndarray:
        nonlocal memo_g, g_known, ngev
        move(point)
        if not g_known:
            memo_g = np.atleast_1d(np.asarray(grad(memo_x.copy()), dtype=float))
            g_known = True
            ngev += 1
        return memo_g

    state = {'acc': ftol, 'alpha': 0.0, 'f0': 0.0, 'gs': 0.0, 'h1': 0.0, 'h2': 0.0, 'h3': 0.0,
             'h4': 0.0, 't': 0.0, 't0': 0.0, 'tol': 10.0 * ftol, 'exact': 0,
             'inconsistent': 0, 'reset': 0, 'iter': 0, 'itermax': int(max_iter), 'line': 0,
             'm': m, 'meq': meq, 'mode': 0, 'n': n}
    indices = np.zeros([max(m + 2 * n + 2, 1)], dtype=np.int32)
    buffer_size = (n * (n + 1) // 2 + 3 * m * n - (m + 5 * n + 7) * meq + 9 * m + 8 * n * n
                   + 35 * n + meq * meq + 28)
    if mieq == 0:
        buffer_size += 2 * n * (n + 1)
    buffer = np.zeros(max(buffer_size, 1), dtype=np.float64)
    mult = np.zeros([max(1, m + 2 * n + 2)], dtype=np.float64)
    C = np.zeros([max(1, m), n], dtype=np.float64, order='F')
    d = np.zeros([max(1, m)], dtype=np.float64)
    writers = _jacobian_writers(blocks, sizes, C)

    rows = np.cumsum([0, *sizes])
    values = [(block.fun, slice(start, stop))
              for block, start, stop in zip(blocks, rows[:-1], rows[1:])]

    def constraint_values(point: np.ndarray) -> None:
        for function, block_rows in values:
            d[block_rows] = np.asarray(function(point), dtype=float).reshape(-1)

    def constraint_normals(point: np.ndarray) -> None:
        for write in writers:
            write(point)

    fx = objective(x)
    g = gradient(x)
    constraint_normals(x)
    constraint_values(x)
    iter_prev = 0
    stopped = False
    while True:
        slsqp(state, fx, g, C, d, x, mult, xl, xu, buffer, indices)
        mode = state['mode']
        if mode == 1:
            fx = objective(x)
            constraint_values(x)
        elif mode == -1:
            g = gradient(x)
            constraint_normals(x)
        if state['iter'] > iter_prev and deadline is not None \
                and time.perf_counter() > deadline:
            stopped = True
            break
        if abs(mode) != 1:
            break
        iter_prev = state['iter']
    mode = state['mode']
    result = SolverResult(x=x, fun=fx, jac=g, nit=state['iter'], nfev=nfev,
                          njev=ngev, status=mode, message=EXIT_MODES[mode],
                          success=mode == 0, multipliers=mult[:m])
    if stopped:
        result.update(success=False, status=STOPPED_STATUS, message=STOPPED_MESSAGE)
    return result


def _jacobian_writers(blocks: list[ConstraintBlock], sizes: list[int],
                      C: np.ndarray) -> list[Callable[[np.ndarray], None]]:
    """
    Return a function per block that writes its Jacobian at a point into its rows of ``C``.

    A :class:`~mshoot_core.sparse_jacobian.SparseJacobian`'s entries go to their fixed
    positions of the Fortran-ordered ``C`` (the other entries of its rows stay zero; the core
    does not change ``C``), a constant one's once, here; others' dense arrays to the block's
    rows.
    """
    m = C.shape[0]
    flat = C.T.reshape(-1)  # a view: C is Fortran-ordered
    writers = []
    row = 0
    for block, size in zip(blocks, sizes):
        jac = block.jac
        if isinstance(jac, SparseJacobian):
            if jac.shape[0] != size:
                raise ValueError(f'constraint Jacobian has {jac.shape[0]} rows, the '
                                 f'constraints {size}')
            positions = jac.cols * m + (jac.rows + row)
            if jac.constant:
                flat[positions] = jac.values(None)
                row += size
                continue

            def write(point: np.ndarray, values: Callable = jac.values,
                      positions: np.ndarray = positions) -> None:
                flat[positions] = values(point)
        else:
            rows = slice(row, row + size)

            def write(point: np.ndarray, jac: Callable = jac, rows: slice = rows) -> None:
                value = jac(point)
                C[rows] = value.toarray() if hasattr(value, 'toarray') else value
        writers.append(write)
        row += size
    return writers
