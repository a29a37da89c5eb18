"""
A constraint Jacobian with a fixed sparsity pattern: what the solvers and the SLSQP core share.

Its own module so that :mod:`mshoot_core.solvers` (the solver interface, which re-exports it)
and :mod:`mshoot_core.slsqp` (which writes its entries into the core's dense matrix) both
import it without importing each other.
"""
from __future__ import annotations

from typing import Callable, TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy import sparse

Vector = np.ndarray
Matrix = np.ndarray


class SparseJacobian:
    """
    A constraint Jacobian with a fixed sparsity pattern, usable as ``Nlp.eq_jac``.

    Calling it returns the ``scipy.sparse.coo_array`` as any Jacobian callable
    of an :class:`Nlp` does; solvers that know it take the pattern once and only
    the entries at each call (IPOPT), or fill a dense matrix without a sparse
    object in between (SLSQP).

    Parameters
    ----------
    rows, cols : ndarray of int
        Positions of the entries (no position twice), in the order of ``values``.
    shape : (int, int)
        (m, n).
    values : callable
        ``values(z) -> (nnz,)`` the entries at z.
    constant : bool
        Whether the entries are the same at every z (``values`` is then called with None too).

    """

    def __init__(self, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int],
                 values: Callable[[Vector], Vector], constant: bool = False) -> None:
        self.rows = np.asarray(rows, dtype=np.intp)
        self.cols = np.asarray(cols, dtype=np.intp)
        if self.rows.shape != self.cols.shape or self.rows.ndim != 1:
            raise ValueError(f'rows and cols must be two 1-d arrays of one length, got '
                             f'{self.rows.shape} and {self.cols.shape}')
        self.shape = (int(shape[0]), int(shape[1]))
        self.values = values
        self.constant = bool(constant)
        self._flat = self.rows * self.shape[1] + self.cols

    def __call__(self, z: Vector) -> sparse.coo_array:
        from scipy import sparse
        return sparse.coo_array((self.values(z), (self.rows, self.cols)), shape=self.shape)

    def dense(self, z: Vector) -> Matrix:
        """Return the Jacobian at ``z`` as a full array of shape (m, n)."""
        out = np.zeros(self.shape)
        out.reshape(-1)[self._flat] = self.values(z)
        return out
