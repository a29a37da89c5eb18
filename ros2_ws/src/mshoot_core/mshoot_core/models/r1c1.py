"""
The R1C1 zone model of the OU44 reference case, in plain Python (exact solution).

    C dT/dt = (Tout + 273.15 - T)/R + shgc*solrad + occheff*occ*M(T) + qv + q
    C = tmass*1.2*1005*Vi,  R = RExt/(3*Vi^(2/3)),  M(T) = 84*(325.15 - T)/32
    qv = (1206/3600)*(maxVent*dpos/100)*(max(Tout, Tve) + 273.15 - T)

With inputs held constant over an interval the right-hand side is affine in
T, dT/dt = (f - g*T)/C, so each interval has the closed-form solution
T(t) = T_inf + (T0 - T_inf)*exp(-g*t/C), T_inf = f/g: no integrator, no
tolerance, and exact derivatives, also with respect to the parameters
(:meth:`R1C1Model.parameter_sensitivities`, the forward sensitivities of the
exact discretisation, for calibration).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
import pandas as pd

from mshoot_core.models.base import check_parameters, IntervalJacobians, Model

KELVIN = 273.15
#: Metabolic heat per occupant [W] at 293.15 K, falling linearly to 0 W at 325.15 K.
OCC_HEAT_W = 84.0
OCC_HEAT_ZERO_K = 325.15
OCC_HEAT_SPAN_K = 32.0
#: Volumetric heat capacity of air [J/(m3 K)] over 3600 s/h, as in the original model.
AIR_HEAT_PER_M3H = 1206.0 / 3600.0
#: Heat capacity of the zone air per m3 and per unit of tmass [J/(m3 K)].
AIR_CAPACITY_J_M3K = 1.2 * 1005.0


@dataclasses.dataclass(frozen=True)
class R1C1Parameters:
    """
    Parameters of the R1C1 zone (defaults: the calibrated OU44 classroom).

    Each field may also be an array of per-zone values (see
    :class:`mshoot_core.models.multizone.MultiZoneModel`).

    Attributes
    ----------
    tmass : float
        Thermal mass multiplier of the zone air [-].
    shgc : float
        Solar heat gain coefficient [m2] (W per W/m2).
    occheff : float
        Occupant heat multiplier [-].
    RExt : float
        External wall resistance parameter [K m2/W].
    Tve : float
        Ventilation supply temperature [degC].
    Vi : float
        Zone volume [m3].
    maxVent : float
        Maximum ventilation flow [m3/h].

    """

    tmass: float = 50.0
    shgc: float = 4.608961327935981
    occheff: float = 2.0836995296486704
    RExt: float = 4.0
    Tve: float = 21.0
    Vi: float = 486.5
    maxVent: float = 4800.0

    def __post_init__(self) -> None:
        check_parameters(self, 'R1C1', positive=('tmass', 'RExt', 'Vi'), arrays=True)

    @property
    def capacity_j_k(self) -> float:
        """Heat capacity C [J/K]."""
        return self.tmass * AIR_CAPACITY_J_M3K * self.Vi

    @property
    def resistance_k_w(self) -> float:
        """Thermal resistance R to the outdoors [K/W]."""
        return self.RExt / (3.0 * self.Vi ** (2.0 / 3.0))


class R1C1Model(Model):
    """
    The R1C1 zone with its exact per-interval solution.

    Inputs: ``solrad`` [W/m2], ``Tout`` [degC], ``occ`` [persons], ``dpos``
    [%], ``q`` [W]. State: ``T`` [K]. Outputs: ``T`` [degC], ``Qr`` = integral
    of q [J] since the start of the simulation.
    """

    input_names = ('solrad', 'Tout', 'occ', 'dpos', 'q')
    state_names = ('T',)
    output_names = ('T', 'Qr')
    #: T(t) = T_inf + (T0 - T_inf) exp(-g t / C), T_inf = f / g with g, C > 0: increasing in T0
    #: and in q (f grows with q)
    monotone_inputs = ('q',)

    def __init__(self, parameters: R1C1Parameters | None = None) -> None:
        self.parameters = parameters or R1C1Parameters()

    def affine_coefficients(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (f [W], g [W/K]) with C dT/dt = f - g*T for inputs ``u`` (..., 5)."""
        p = self.parameters
        solrad, tout, occ, dpos, q = (u[..., i] for i in range(5))
        occ_slope = p.occheff * occ * OCC_HEAT_W / OCC_HEAT_SPAN_K
        vent = AIR_HEAT_PER_M3H * p.maxVent * dpos / 100.0
        g = 1.0 / p.resistance_k_w + occ_slope + vent
        f = ((tout + KELVIN) / p.resistance_k_w + p.shgc * solrad
             + occ_slope * OCC_HEAT_ZERO_K + vent * (np.maximum(tout, p.Tve) + KELVIN) + q)
        return f, g

    def derivative(self, T: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dT/dt [K/s] for states ``T`` (B,) and inputs ``u`` (B, 5)."""
        f, g = self.affine_coefficients(np.atleast_2d(u))
        return (f - g * T) / self.parameters.capacity_j_k

    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        t, u, x0_arr = self.check_inputs(udf, x0)
        temps = np.empty(t.size)
        heat = np.zeros(t.size)
        temps[0] = x0_arr[0]
        dt = np.diff(t)
        f, g = self.affine_coefficients(u[:-1])
        decay = np.exp(-g * dt / self.parameters.capacity_j_k)
        t_inf = f / g
        for k in range(dt.size):
            temps[k + 1] = t_inf[k] + (temps[k] - t_inf[k]) * decay[k]
        heat[1:] = np.cumsum(u[:-1, 4] * dt)
        index = udf.index
        xdf = pd.DataFrame({'T': temps}, index=index)
        ydf = pd.DataFrame({'T': temps - KELVIN, 'Qr': heat}, index=index)
        return ydf, xdf

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """Exact end values of B intervals (``t_start_s`` ignored: time-invariant)."""
        x_start = np.atleast_2d(np.asarray(x_start, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        f, g = self.affine_coefficients(u)
        decay = np.exp(-g * dt_s / self.parameters.capacity_j_k)
        t_end = f / g + (x_start[:, 0] - f / g) * decay
        return t_end[:, None], np.column_stack([t_end - KELVIN, u[:, 4] * dt_s])

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int],
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians:
        """Exact end values and derivatives (``t_start_s`` ignored: time-invariant)."""
        x_start = np.atleast_2d(np.asarray(x_start, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        x_end, y_end = self.simulate_intervals(x_start, u, dt_s)
        f, g = self.affine_coefficients(u)
        cap = self.parameters.capacity_j_k
        decay = np.exp(-g * dt_s / cap)
        batch = x_start.shape[0]
        wrt = list(wrt_inputs)
        dx_du = np.zeros((batch, 1, len(wrt)))
        dy_du = np.zeros((batch, 2, len(wrt)))
        for j, col in enumerate(wrt):
            if col == 4:  # q enters f only: dT_end/dq = (1 - decay)/g
                dx_du[:, 0, j] = (1.0 - decay) / g
                dy_du[:, 1, j] = dt_s
            else:  # disturbances: differentiate numerically through the exact solution
                step = 1e-6 * np.maximum(1.0, np.abs(u[:, col]))
                up = u.copy()
                up[:, col] += step
                x_up, _ = self.simulate_intervals(x_start, up, dt_s)
                dx_du[:, 0, j] = (x_up[:, 0] - x_end[:, 0]) / step
            dy_du[:, 0, j] = dx_du[:, 0, j]
        dx_dx0 = decay[:, None, None]
        dy_dx0 = np.zeros((batch, 2, 1))
        dy_dx0[:, 0, 0] = decay
        return IntervalJacobians(x_end, y_end, dx_dx0, dx_du, dy_dx0, dy_du)

    def simulate_parameter_batch(self, udf: pd.DataFrame, x0: Sequence[float]) -> np.ndarray:
        """
        Simulate B parameter vectors at once: the parameters are arrays of B values.

        Each field of :attr:`parameters` is a scalar (shared) or an array of
        shape (B,); the B zones see the same inputs and start state. One
        numpy expression per row serves all B (batched finite differences of
        a calibration).

        Parameters
        ----------
        udf : DataFrame
            Inputs as for :meth:`simulate`.
        x0 : sequence of float, length 1
            Start temperature [K], shared.

        Returns
        -------
        ndarray, shape (T, 2, B)
            The outputs (:attr:`output_names`: T [degC], Qr [J]) of every
            parameter vector at every row.

        """
        t, u, x0_arr = self.check_inputs(udf, x0)
        dt = np.diff(t)[:, None]
        f, g = self.affine_coefficients(u[:-1, None, :])
        cap = np.asarray(self.parameters.capacity_j_k, dtype=float)
        f, g = np.broadcast_arrays(f, g)
        decay = np.exp(-g * dt / cap)
        t_inf = f / g
        out = np.zeros((t.size, 2, f.shape[1]))
        out[0, 0] = x0_arr[0]
        for k in range(dt.shape[0]):
            out[k + 1, 0] = t_inf[k] + (out[k, 0] - t_inf[k]) * decay[k]
        out[:, 0] -= KELVIN
        out[1:, 1] = np.cumsum(u[:-1, 4] * dt[:, 0])[:, None]
        return out

    def _coefficient_derivatives(self, u: np.ndarray, names: Sequence[str]
                                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the derivatives of f [W], g [W/K] (rows of ``u``) and C [J/K] by ``names``."""
        p = self.parameters
        solrad, tout, occ, dpos = (u[:, i] for i in range(4))
        vi23 = p.Vi ** (2.0 / 3.0)
        conductance = 3.0 * vi23 / p.RExt  # 1/R [W/K]
        per_occupant = occ * OCC_HEAT_W / OCC_HEAT_SPAN_K
        per_vent = AIR_HEAT_PER_M3H * dpos / 100.0
        supply = np.maximum(tout, p.Tve) + KELVIN
        rows = u.shape[0]
        df = np.zeros((rows, len(names)))
        dg = np.zeros((rows, len(names)))
        dcap = np.zeros(len(names))
        for j, name in enumerate(names):
            if name == 'tmass':
                dcap[j] = AIR_CAPACITY_J_M3K * p.Vi
            elif name == 'shgc':
                df[:, j] = solrad
            elif name == 'occheff':
                dg[:, j] = per_occupant
                df[:, j] = per_occupant * OCC_HEAT_ZERO_K
            elif name == 'RExt':
                dg[:, j] = -conductance / p.RExt
                df[:, j] = dg[:, j] * (tout + KELVIN)
            elif name == 'Tve':  # through max(Tout, Tve): 0 where the outdoor air is warmer
                df[:, j] = per_vent * p.maxVent * (p.Tve > tout)
            elif name == 'maxVent':
                dg[:, j] = per_vent
                df[:, j] = per_vent * supply
            elif name == 'Vi':
                dg[:, j] = conductance * (2.0 / 3.0) / p.Vi
                df[:, j] = dg[:, j] * (tout + KELVIN)
                dcap[j] = p.tmass * AIR_CAPACITY_J_M3K
            else:
                raise ValueError(f'unknown R1C1 parameter {name!r}; expected names from '
                                 f'{[f.name for f in dataclasses.fields(R1C1Parameters)]}')
        return df, dg, dcap

    def parameter_sensitivities(self, udf: pd.DataFrame, x0: Sequence[float],
                                names: Sequence[str]) -> tuple[pd.DataFrame, np.ndarray]:
        """
        Simulate as :meth:`simulate` and return the exact output derivatives w.r.t. parameters.

        Forward sensitivities of the exact per-interval solution: with
        a = exp(-g dt/C) and T_inf = f/g,
        dT_{k+1}/dp = dT_inf/dp (1 - a) + (T_k - T_inf) da/dp + a dT_k/dp,
        dT_0/dp = 0 (the start state is given).

        Parameters
        ----------
        udf : DataFrame
            Inputs as for :meth:`simulate`.
        x0 : sequence of float, length 1
            Start temperature [K].
        names : sequence of str
            Fields of :class:`R1C1Parameters` (scalar-valued).

        Returns
        -------
        ydf : DataFrame
            The outputs of :meth:`simulate`.
        dy_dp : ndarray, shape (T, 2, len(names))
            d output / d parameter at every row [output unit per parameter
            unit]; ``Qr`` does not depend on the parameters (zeros).

        Raises
        ------
        ValueError
            For an unknown name or array-valued parameters.

        """
        names = list(names)
        if any(np.ndim(getattr(self.parameters, f.name)) for f in
               dataclasses.fields(self.parameters)):
            raise ValueError('parameter_sensitivities needs scalar R1C1 parameters')
        ydf, xdf = self.simulate(udf, x0)
        t, u, _ = self.check_inputs(udf, x0)
        temps = xdf['T'].to_numpy()
        dt = np.diff(t)
        f, g = self.affine_coefficients(u[:-1])
        df, dg, dcap = self._coefficient_derivatives(u[:-1], names)
        cap = self.parameters.capacity_j_k
        decay = np.exp(-g * dt / cap)
        t_inf = f / g
        dt_inf = (df * g[:, None] - f[:, None] * dg) / (g ** 2)[:, None]
        ddecay = -(decay * dt)[:, None] * (dg * cap - g[:, None] * dcap[None, :]) / cap ** 2
        sens = np.zeros((t.size, len(names)))
        for k in range(dt.size):
            sens[k + 1] = (dt_inf[k] * (1.0 - decay[k]) + (temps[k] - t_inf[k]) * ddecay[k]
                           + decay[k] * sens[k])
        dy_dp = np.zeros((t.size, 2, len(names)))
        dy_dp[:, 0, :] = sens
        return ydf, dy_dp
