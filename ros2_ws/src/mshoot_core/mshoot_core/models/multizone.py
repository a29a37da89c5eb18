"""
A building of Z R1C1 zones, vectorised: the scale test case of the optimiser.

Every zone follows the R1C1 equations of :mod:`mshoot_core.models.r1c1` with
its own size, solar aperture and occupancy share, under the shared outdoor
conditions, and has its own heater/cooler ``q_i``. The zones are thermally
independent (no heat flows between them), so the per-interval Jacobian is
diagonal: the model declares that structure, and finite differences perturb
all zones at once.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

from mshoot_core.models.base import IntervalBatch, IntervalJacobians, Model
from mshoot_core.models.r1c1 import KELVIN, R1C1Model, R1C1Parameters


class MultiZoneModel(Model):
    """
    Z independent R1C1 zones in one model.

    Inputs ``solrad``, ``Tout``, ``occ``, ``dpos`` (shared) and ``q_0`` ...
    ``q_{Z-1}`` [W]; states ``T_0`` ... [K]; outputs ``Tc_0`` ... [degC].
    The controls (:attr:`control_names`) are the heat rates ``q_i``; every state
    is a zone temperature bounded by the comfort band (:attr:`comfort_states`;
    see :func:`mshoot_core.models.registry.control_interface`).

    Parameters
    ----------
    n_zones : int
        Number of zones Z.
    seed : int
        Seed of the zone-to-zone variation: volume x U(0.7, 1.3), solar
        aperture x U(0.5, 1.5), occupancy share x U(0.5, 1.5).
    base : R1C1Parameters, optional
        Parameters of the reference zone (default: the OU44 classroom).

    """

    def __init__(self, n_zones: int, seed: int = 0,
                 base: R1C1Parameters | None = None) -> None:
        if int(n_zones) != n_zones or n_zones < 1:
            raise ValueError(f'n_zones must be a positive integer, got {n_zones}')
        self.n_zones = int(n_zones)
        rng = np.random.default_rng(seed)
        base = base or R1C1Parameters()
        volume = base.Vi * rng.uniform(0.7, 1.3, self.n_zones)
        self.solar_share = rng.uniform(0.5, 1.5, self.n_zones)
        self.occupancy_share = rng.uniform(0.5, 1.5, self.n_zones)
        # one R1C1 model with per-zone parameter arrays: all zones in one numpy expression
        self.zones = R1C1Model(R1C1Parameters(**{**base.__dict__, 'Vi': volume}))
        self.input_names = ('solrad', 'Tout', 'occ', 'dpos') + tuple(
            f'q_{i}' for i in range(self.n_zones))
        self.state_names = tuple(f'T_{i}' for i in range(self.n_zones))
        self.output_names = tuple(f'Tc_{i}' for i in range(self.n_zones))
        self.control_names = tuple(f'q_{i}' for i in range(self.n_zones))
        self.monotone_inputs = self.control_names  # (R1C1 zones, each in its own q)
        self.comfort_states = self.state_names

    def _zone_inputs(self, u: np.ndarray) -> np.ndarray:
        """Return the inputs of every zone, shape (B, Z, 5), from the model inputs (B, 4 + Z)."""
        batch = u.shape[0]
        zone_u = np.empty((batch, self.n_zones, 5))
        zone_u[:, :, 0] = u[:, [0]] * self.solar_share
        zone_u[:, :, 1] = u[:, [1]]
        zone_u[:, :, 2] = u[:, [2]] * self.occupancy_share
        zone_u[:, :, 3] = u[:, [3]]
        zone_u[:, :, 4] = u[:, 4:]
        return zone_u

    def _coefficients(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return f [W], g [W/K] and capacity C [J/K] per batch row and zone, shapes (B, Z)."""
        f, g = self.zones.affine_coefficients(self._zone_inputs(u))
        return f, g, np.broadcast_to(self.zones.parameters.capacity_j_k, f.shape)

    def simulate(self, udf: pd.DataFrame, x0: Sequence[float]) -> tuple[pd.DataFrame,
                                                                        pd.DataFrame]:
        t, u, x0_arr = self.check_inputs(udf, x0)
        states = np.empty((t.size, self.n_zones))
        states[0] = x0_arr
        for k in range(t.size - 1):
            states[k + 1] = self.simulate_intervals(states[k][None, :], u[k][None, :],
                                                    t[k + 1] - t[k])[0][0]
        xdf = pd.DataFrame(states, index=udf.index, columns=list(self.state_names))
        ydf = pd.DataFrame(states - KELVIN, index=udf.index, columns=list(self.output_names))
        return ydf, xdf

    def _exact(self, x_start: np.ndarray, u: np.ndarray,
               dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the exact end states (B, Z) [K], the decay exp(-g dt / C) and g [W/K]."""
        f, g, cap = self._coefficients(u)
        decay = np.exp(-g * dt_s / cap)
        return f / g + (x_start - f / g) * decay, decay, g

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """Exact end values of B intervals (``t_start_s`` ignored: time-invariant)."""
        x_end = self._exact(np.atleast_2d(np.asarray(x_start, dtype=float)),
                            np.atleast_2d(np.asarray(u, dtype=float)), dt_s)[0]
        return x_end, x_end - KELVIN

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int],
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians | None:
        """Exact derivatives w.r.t. the zone inputs (``t_start_s`` ignored), else None."""
        batch = _ZoneBatch(self, np.atleast_2d(x_start).shape[0], dt_s, wrt_inputs)
        if not batch.analytic:
            return None  # derivatives w.r.t. shared disturbances: use finite differences
        batch.x_start[:] = x_start
        batch.u[:] = u
        return batch.jacobians()

    def interval_batch(self, batch: int, dt_s: float, wrt_inputs: Sequence[int],
                       t_start_s: np.ndarray | None = None) -> IntervalBatch:
        """Return the zones' batch: derivative arrays allocated once, their diagonals rewritten."""
        return _ZoneBatch(self, batch, dt_s, wrt_inputs)

    def jacobian_sparsity(self, wrt_inputs: Sequence[int]) -> np.ndarray:
        z = self.n_zones
        pattern = np.zeros((2 * z, z + len(wrt_inputs)), bool)
        zones = np.arange(z)
        for rows in (zones, zones + z):
            pattern[rows, zones] = True
            for j, col in enumerate(wrt_inputs):
                if col >= 4:
                    pattern[rows[col - 4], z + j] = True
                else:
                    pattern[rows, z + j] = True
        return pattern


class _ZoneBatch(IntervalBatch):
    """
    B intervals of a :class:`MultiZoneModel`, evaluated again and again (the optimiser's loop).

    An :class:`~mshoot_core.models.base.IntervalBatch` whose derivative arrays (B, Z, Z) and
    (B, Z, len(wrt_inputs)) are allocated once, zero but for their diagonals, which each
    :meth:`jacobians` writes by index arrays (no loop over zones): the arrays it returns are
    read-only and the batch's own, valid until its next call. The outputs are the states in
    degC, so their derivatives are the same arrays.
    """

    def __init__(self, model: MultiZoneModel, batch: int, dt_s: float,
                 wrt_inputs: Sequence[int]) -> None:
        super().__init__(model, batch, dt_s, wrt_inputs)
        wrt = np.asarray(self.wrt_inputs, dtype=np.intp).reshape(-1)
        #: Whether every differentiated input is a heat rate (else no analytic derivatives).
        self.analytic = not (wrt < 4).any()
        z = model.n_zones
        self._zones = np.arange(z)
        self._controlled = wrt - 4  # the zone of each differentiated heat rate
        self._columns = np.arange(wrt.size)
        self._dx_dx0 = np.zeros((int(batch), z, z))
        self._dx_du = np.zeros((int(batch), z, wrt.size))

    def jacobians(self) -> IntervalJacobians | None:
        if not self.analytic:
            return None
        x_end, decay, g = self.model._exact(self.x_start, self.u, self.dt_s)
        dx_dx0, dx_du, zones, controlled = self._dx_dx0, self._dx_du, self._zones, self._controlled
        dx_dx0.flags.writeable = dx_du.flags.writeable = True
        dx_dx0[:, zones, zones] = decay
        dx_du[:, controlled, self._columns] = (1.0 - decay[:, controlled]) / g[:, controlled]
        dx_dx0.flags.writeable = dx_du.flags.writeable = False
        return IntervalJacobians(x_end, x_end - KELVIN, dx_dx0, dx_du, dx_dx0, dx_du)


def multizone_mpc_options(model: MultiZoneModel, solver: str = 'ipopt') -> dict:
    """
    MPC keyword arguments for a :class:`MultiZoneModel`.

    One heater per zone (-2000..2000 W), every zone bounded by the comfort
    band, and for IPOPT the large-problem configuration: a single
    exact-penalty solve where the band is out of reach, Mehrotra's
    predictor-corrector (the problem is a convex QP: the zones are affine in
    state and heat rate, the cost is quadratic), and the linear-algebra
    settings of :data:`mshoot_core.solvers.IPOPT_LARGE_PROBLEM_OPTIONS`.
    """
    options = {'control_names': model.control_names,
               'heat_rate_min_w': -2000.0, 'heat_rate_max_w': 2000.0,
               'state_bounds': {name: ('comfort_min', 'comfort_max', KELVIN)
                                for name in model.comfort_states},
               'solver': solver}
    if solver == 'ipopt':
        from mshoot_core.solvers import IPOPT_LARGE_PROBLEM_OPTIONS
        options.update(relaxation='exact-penalty',
                       solver_extra={'options': {'mehrotra_algorithm': 'yes',
                                                 **IPOPT_LARGE_PROBLEM_OPTIONS}})
    return options
