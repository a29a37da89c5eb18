"""
Finite-difference interval sensitivities, batched and column-grouped.

Interval k depends only on its own start state and inputs, so its Jacobian
is a small (nx + ny) x (nx + nc) block. All intervals and all perturbations go
to the model in ONE ``simulate_intervals`` call. Where the model declares the
structure of that block (``Model.jacobian_sparsity``), columns that share no
row are perturbed together (Curtis-Powell-Reid grouping), so a model of Z
independent zones costs a handful of perturbations, not 2Z.
"""
from __future__ import annotations

import numpy as np

from mshoot_core.models.base import IntervalJacobians, Model


def column_groups(pattern: np.ndarray) -> list[list[int]]:
    """
    Greedy grouping of columns that share no non-zero row.

    Parameters
    ----------
    pattern : ndarray of bool, shape (rows, cols)
        Structural non-zeros.

    Returns
    -------
    list of lists of column indices; every column appears in exactly one group.

    """
    pattern = np.asarray(pattern, dtype=bool)
    groups: list[list[int]] = []
    used_rows: list[np.ndarray] = []
    for col in range(pattern.shape[1]):
        rows = pattern[:, col]
        for g, taken in enumerate(used_rows):
            if not np.any(taken & rows):
                groups[g].append(col)
                used_rows[g] = taken | rows
                break
        else:
            groups.append([col])
            used_rows.append(rows.copy())
    return groups


def finite_difference_jacobians(model: Model, x_start: np.ndarray, u: np.ndarray,
                                dt_s: float, wrt_inputs: list[int], x_step: np.ndarray,
                                u_step: np.ndarray, u_upper: np.ndarray,
                                pattern: np.ndarray | None = None,
                                t_start_s: np.ndarray | None = None
                                ) -> tuple[IntervalJacobians, int]:
    """
    Forward-difference end values and sensitivities of B intervals in one batch.

    Parameters
    ----------
    model : Model
        The model whose intervals are perturbed.
    x_start : ndarray, shape (B, nx)
        Start state of each interval.
    u : ndarray, shape (B, nu)
        Inputs of each interval (all columns).
    dt_s : float
        Interval length [s].
    wrt_inputs : list of int
        Columns of ``u`` to differentiate with respect to (the controls).
    x_step, u_step : ndarray, shapes (nx,), (nc,)
        Perturbation per state and per control (physical units).
    u_upper : ndarray, shape (nc,)
        Upper bounds of the controls: a perturbation that would cross one is
        taken backwards, so the model is never driven past its limits.
    pattern : ndarray of bool, shape (nx + ny, nx + nc), optional
        Structural non-zeros of [d(x_end, y_end) / d(x_start, controls)];
        None means dense.
    t_start_s : ndarray, shape (B,), optional
        Start time of each interval [s]; a perturbed interval is simulated at
        the time of its base interval. None: not passed to the model.

    Returns
    -------
    (IntervalJacobians, number of interval simulations spent)

    """
    batch, nx = x_start.shape
    nc = len(wrt_inputs)
    ny = len(model.output_names)
    if pattern is None:
        pattern = np.ones((nx + ny, nx + nc), bool)
    groups = column_groups(pattern)
    steps = np.concatenate([x_step, u_step])
    # a backward step where a forward one would cross the control's upper bound
    signs = np.ones((batch, nx + nc))
    for j, col in enumerate(wrt_inputs):
        signs[:, nx + j] = np.where(u[:, col] + u_step[j] <= u_upper[j], 1.0, -1.0)
    batch_x, batch_u = [x_start], [u]
    for group in groups:
        xp, up = x_start.copy(), u.copy()
        for c in group:
            if c < nx:
                xp[:, c] += steps[c]
            else:
                up[:, wrt_inputs[c - nx]] += signs[:, c] * steps[c]
        batch_x.append(xp)
        batch_u.append(up)
    times = {} if t_start_s is None else {
        't_start_s': np.concatenate([t_start_s] * len(batch_x))}  # each at its base's time
    x_all, y_all = model.simulate_intervals(np.vstack(batch_x), np.vstack(batch_u), dt_s,
                                            **times)
    x_all = x_all.reshape(1 + len(groups), batch, nx)
    y_all = y_all.reshape(1 + len(groups), batch, ny)
    base = np.concatenate([x_all[0], y_all[0]], axis=1)
    jac = np.zeros((batch, nx + ny, nx + nc))
    for g, group in enumerate(groups):
        diff = np.concatenate([x_all[1 + g], y_all[1 + g]], axis=1) - base
        for c in group:
            rows = pattern[:, c]
            jac[:, rows, c] = diff[:, rows] / (signs[:, c:c + 1] * steps[c])
    result = IntervalJacobians(x_all[0], y_all[0], jac[:, :nx, :nx], jac[:, :nx, nx:],
                               jac[:, nx:, :nx], jac[:, nx:, nx:])
    return result, x_all.shape[0] * batch
