"""
A steady-state Kalman observer of a linear time-invariant control model from one measured state.

:class:`ZoneObserver` estimates the unmeasured states of the heat pump house's control model
(the network of the card ``boptest_house``: the floor ``Tf`` and the envelope ``Te``) from the
measured zone temperature, the model's first state.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.linalg

from mshoot_core.models.base import Model


class ZoneObserver:
    """
    Steady-state Kalman filter of a linear time-invariant model from its measured first state.

    The other states are not measured: the filter predicts all states one interval ahead with
    the inputs applied, then corrects them with the measured first state (gain from the
    discrete algebraic Riccati equation).

    Parameters
    ----------
    model : Model
        A model linear in its states with a transition that does not depend on the inputs
        (its ``interval_jacobians``' ``dx_dx0``), the measured state first.
    dt_s : float
        Interval between two measurements [s].
    process_sd_k : sequence of float
        Standard deviation of the process noise per interval, per state [K].
    measurement_sd_k : float
        Standard deviation of the measurement [K].

    """

    def __init__(self, model: Model, dt_s: float = 3600.0,
                 process_sd_k: Sequence[float] = (0.1, 0.05, 0.05),
                 measurement_sd_k: float = 0.05) -> None:
        self.model = model
        self.dt_s = float(dt_s)
        n = len(model.state_names)
        jac = model.interval_jacobians(np.full((1, n), 293.15),
                                       np.zeros((1, len(model.input_names))), self.dt_s, [])
        phi = jac.dx_dx0[0]
        c = np.zeros((1, n))
        c[0, 0] = 1.0
        q = np.diag(np.asarray(process_sd_k, dtype=float) ** 2)
        r = np.array([[float(measurement_sd_k) ** 2]])
        p = scipy.linalg.solve_discrete_are(phi.T, c.T, q, r)
        self.gain = (p @ c.T @ np.linalg.inv(c @ p @ c.T + r)).reshape(n)
        self.x: np.ndarray | None = None

    def reset(self, tz_k: float) -> None:
        """Start from a measured zone temperature [K] (the other states equal to it)."""
        self.x = np.full(len(self.model.state_names), float(tz_k))

    def update(self, u: Sequence[float], tz_measured_k: float) -> np.ndarray:
        """
        Predict over one interval with inputs ``u`` (model input order), then correct.

        Returns
        -------
        ndarray, shape (states,)
            The estimated states [K] at the end of the interval.

        """
        if self.x is None:
            self.reset(tz_measured_k)
            return self.x.copy()
        x_pred, _ = self.model.simulate_intervals(self.x[None, :],
                                                  np.asarray(u, dtype=float)[None, :], self.dt_s)
        x_pred = x_pred[0]
        self.x = x_pred + self.gain * (float(tz_measured_k) - x_pred[0])
        return self.x.copy()
