"""
An R2C2 zone in plain Python: an air node and an envelope node, exact per interval.

    Cair  dT/dt  = (Tw - T)/Raw + (Tout + 273.15 - T)/Rwin + (1 - fsun)*shgc*solrad
                   + occheff*84*occ + qv + q
    Cwall dTw/dt = (T - Tw)/Raw + (Tout + 273.15 - Tw)/Rwa + fsun*shgc*solrad
    qv = (1206/3600)*(maxVent*dpos/100)*(max(Tout, Tve) + 273.15 - T)

The air node ``T`` [K] is what a room sensor measures; the envelope node
``Tw`` [K] (walls, slab, furniture) is not measured in a real building, so the
model declares ``measured_states = ('T',)`` and a controller estimates ``Tw``
(:mod:`mshoot_core.estimation`). It takes the inputs of the R1C1 zone
(``solrad``, ``Tout``, ``occ``, ``dpos``, ``q``), so it runs on the same
scenarios and forecasts.

With inputs held constant over an interval the dynamics are linear,
dx/dt = A(u) x + b(u), and each interval has the exact solution
x(t) = Phi x0 + Gamma b with Phi = expm(A t) and Gamma = A^-1 (Phi - I) (A is
Hurwitz, hence invertible): no integrator and exact derivatives (the Frechet
derivative of the matrix exponential for ``dpos``, which changes A).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
import pandas as pd
import scipy.linalg

from mshoot_core.models.base import IntervalJacobians, Model
from mshoot_core.models.r1c1 import AIR_HEAT_PER_M3H, KELVIN, OCC_HEAT_W

#: Input columns (the R1C1 zone's).
SOLRAD, TOUT, OCC, DPOS, Q = range(5)


@dataclasses.dataclass(frozen=True)
class R2C2Parameters:
    """
    Parameters of the R2C2 zone (defaults: a classroom of the OU44 building's size).

    Attributes
    ----------
    Cair : float
        Heat capacity of the air node (air, furniture, surface layers) [J/K].
    Cwall : float
        Heat capacity of the envelope node (walls, slab) [J/K].
    Raw : float
        Resistance between the air and the envelope node [K/W].
    Rwa : float
        Resistance between the envelope node and the outdoors [K/W].
    Rwin : float
        Resistance between the air and the outdoors (windows, infiltration) [K/W].
    shgc : float
        Solar heat gain coefficient [m2] (W per W/m2).
    fsun : float
        Share of the solar gains absorbed by the envelope node [-], in [0, 1].
    occheff : float
        Occupant heat multiplier [-] (84 W per person times this).
    Tve : float
        Ventilation supply temperature [degC].
    maxVent : float
        Maximum ventilation flow [m3/h].

    """

    Cair: float = 5.0e6
    Cwall: float = 5.0e7
    Raw: float = 0.002
    Rwa: float = 0.03
    Rwin: float = 0.05
    shgc: float = 4.6
    fsun: float = 0.6
    occheff: float = 1.0
    Tve: float = 21.0
    maxVent: float = 4800.0

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) \
                    or not np.isfinite(value):
                raise ValueError(f'R2C2 parameter {field.name} must be a finite number, got '
                                 f'{value!r}')
        for name in ('Cair', 'Cwall', 'Raw', 'Rwa', 'Rwin'):
            if getattr(self, name) <= 0:
                raise ValueError(f'R2C2 parameter {name} must be > 0, got {getattr(self, name)}')
        for name in ('shgc', 'occheff', 'maxVent'):
            if getattr(self, name) < 0:
                raise ValueError(f'R2C2 parameter {name} must be >= 0, got {getattr(self, name)}')
        if not 0.0 <= self.fsun <= 1.0:
            raise ValueError(f'R2C2 parameter fsun must be in [0, 1], got {self.fsun}')


class R2C2Model(Model):
    """
    The R2C2 zone with its exact per-interval solution (see the module).

    Inputs: ``solrad`` [W/m2], ``Tout`` [degC], ``occ`` [persons], ``dpos`` [%], ``q`` [W].
    States: ``T`` (air) and ``Tw`` (envelope) [K]. Outputs: ``T`` [degC] and ``Qr`` [J]
    (integral of q since the start of the simulation; per interval in
    :meth:`simulate_intervals`).

    Parameters
    ----------
    parameters : R2C2Parameters, optional
        Default: the defaults of :class:`R2C2Parameters`.
    measured_states : sequence of str
        The states a sensor measures (default: the air node only); a
        controller estimates the others.

    """

    input_names = ('solrad', 'Tout', 'occ', 'dpos', 'q')
    state_names = ('T', 'Tw')
    output_names = ('T', 'Qr')
    control_names = ('q',)
    comfort_states = ('T',)

    def __init__(self, parameters: R2C2Parameters | None = None,
                 measured_states: Sequence[str] = ('T',)) -> None:
        self.parameters = parameters or R2C2Parameters()
        measured = tuple(measured_states)
        unknown = [s for s in measured if s not in self.state_names]
        if not measured or unknown or len(set(measured)) != len(measured):
            raise ValueError(f'measured_states must be distinct states of the R2C2 '
                             f'{list(self.state_names)}, got {list(measured)}')
        self.measured_states = measured

    # -- the linear system of an interval ---------------------------------------------------
    def _vent(self, u: np.ndarray) -> np.ndarray:
        """Ventilation conductance [W/K] of inputs ``u`` (B, 5)."""
        return AIR_HEAT_PER_M3H * self.parameters.maxVent * u[:, DPOS] / 100.0

    def system(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return ``A`` (B, 2, 2) [1/s] and ``b`` (B, 2) [K/s] with dx/dt = A x + b for inputs u.

        ``u`` has shape (B, 5), columns in :attr:`input_names` order.
        """
        p = self.parameters
        vent = self._vent(u)
        a = np.empty((u.shape[0], 2, 2))
        a[:, 0, 0] = -(1.0 / p.Raw + 1.0 / p.Rwin + vent) / p.Cair
        a[:, 0, 1] = 1.0 / (p.Raw * p.Cair)
        a[:, 1, 0] = 1.0 / (p.Raw * p.Cwall)
        a[:, 1, 1] = -(1.0 / p.Raw + 1.0 / p.Rwa) / p.Cwall
        tout_k = u[:, TOUT] + KELVIN
        sun = p.shgc * u[:, SOLRAD]
        b = np.empty((u.shape[0], 2))
        b[:, 0] = (tout_k / p.Rwin + (1.0 - p.fsun) * sun + p.occheff * OCC_HEAT_W * u[:, OCC]
                   + vent * (np.maximum(u[:, TOUT], p.Tve) + KELVIN) + u[:, Q]) / p.Cair
        b[:, 1] = (tout_k / p.Rwa + p.fsun * sun) / p.Cwall
        return a, b

    def _input_derivatives(self, u: np.ndarray, col: int) -> tuple[np.ndarray, np.ndarray]:
        """Return dA/du_col (B, 2, 2) and db/du_col (B, 2)."""
        p = self.parameters
        batch = u.shape[0]
        da, db = np.zeros((batch, 2, 2)), np.zeros((batch, 2))
        dvent = AIR_HEAT_PER_M3H * p.maxVent / 100.0
        if col == SOLRAD:
            db[:, 0], db[:, 1] = (1.0 - p.fsun) * p.shgc / p.Cair, p.fsun * p.shgc / p.Cwall
        elif col == TOUT:
            above = (u[:, TOUT] >= p.Tve).astype(float)
            db[:, 0] = (1.0 / p.Rwin + self._vent(u) * above) / p.Cair
            db[:, 1] = 1.0 / (p.Rwa * p.Cwall)
        elif col == OCC:
            db[:, 0] = p.occheff * OCC_HEAT_W / p.Cair
        elif col == DPOS:
            da[:, 0, 0] = -dvent / p.Cair
            db[:, 0] = dvent * (np.maximum(u[:, TOUT], p.Tve) + KELVIN) / p.Cair
        elif col == Q:
            db[:, 0] = 1.0 / p.Cair
        else:
            raise ValueError(f'input column {col} out of range [0, {len(self.input_names)})')
        return da, db

    def transition(self, u: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """
        Return ``Phi`` (B, 2, 2) [-] and ``Gamma @ b`` (B, 2) [K] of B intervals of ``dt_s`` [s].

        The end state of an interval is ``Phi @ x0 + Gamma @ b``.
        """
        a, b = self.system(u)
        phi = scipy.linalg.expm(a * float(dt_s))
        forced = np.linalg.solve(a, np.einsum('bij,bj->bi', phi - np.eye(2), b)[..., None])
        return phi, forced[..., 0]

    # -- the Model interface ----------------------------------------------------------------
    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        t, u, x0_arr = self.check_inputs(udf, x0)
        dt = np.diff(t)
        states = np.empty((t.size, 2))
        states[0] = x0_arr
        if np.allclose(dt, dt[0], rtol=1e-12, atol=0.0):
            phi, forced = self.transition(u[:-1], float(dt[0]))
        else:
            pairs = [self.transition(u[k:k + 1], float(dt[k])) for k in range(dt.size)]
            phi = np.concatenate([p[0] for p in pairs])
            forced = np.concatenate([p[1] for p in pairs])
        for k in range(dt.size):
            states[k + 1] = phi[k] @ states[k] + forced[k]
        heat = np.zeros(t.size)
        heat[1:] = np.cumsum(u[:-1, Q] * dt)
        xdf = pd.DataFrame(states, index=udf.index, columns=list(self.state_names))
        ydf = pd.DataFrame({'T': states[:, 0] - KELVIN, 'Qr': heat}, index=udf.index)
        return ydf, xdf

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """Exact end values of B intervals (``t_start_s`` ignored: time-invariant)."""
        x_start, u = self._check_batch(x_start, u)
        phi, forced = self.transition(u, dt_s)
        x_end = np.einsum('bij,bj->bi', phi, x_start) + forced
        return x_end, np.column_stack([x_end[:, 0] - KELVIN, u[:, Q] * dt_s])

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int],
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians:
        """Exact end values and derivatives (``t_start_s`` ignored: time-invariant)."""
        x_start, u = self._check_batch(x_start, u)
        dt_s = float(dt_s)
        a, b = self.system(u)
        phi = scipy.linalg.expm(a * dt_s)
        x_end = np.einsum('bij,bj->bi', phi, x_start) + np.linalg.solve(
            a, np.einsum('bij,bj->bi', phi - np.eye(2), b)[..., None])[..., 0]
        y_end = np.column_stack([x_end[:, 0] - KELVIN, u[:, Q] * dt_s])
        batch, wrt = x_start.shape[0], list(wrt_inputs)
        dx_du = np.zeros((batch, 2, len(wrt)))
        dy_du = np.zeros((batch, 2, len(wrt)))
        for j, col in enumerate(wrt):
            da, db = self._input_derivatives(u, col)
            if np.any(da):  # A changes: the Frechet derivative of the augmented exponential
                for k in range(batch):
                    m = np.zeros((3, 3))
                    m[:2, :2], m[:2, 2] = a[k], b[k]
                    dm = np.zeros((3, 3))
                    dm[:2, :2], dm[:2, 2] = da[k], db[k]
                    _, de = scipy.linalg.expm_frechet(m * dt_s, dm * dt_s)
                    dx_du[k, :, j] = de[:2, :2] @ x_start[k] + de[:2, 2]
            else:  # only b changes: Gamma @ db
                dx_du[:, :, j] = np.linalg.solve(
                    a, np.einsum('bij,bj->bi', phi - np.eye(2), db)[..., None])[..., 0]
            dy_du[:, 0, j] = dx_du[:, 0, j]
            if col == Q:
                dy_du[:, 1, j] = dt_s
        dy_dx0 = np.zeros((batch, 2, 2))
        dy_dx0[:, 0, :] = phi[:, 0, :]
        return IntervalJacobians(x_end, y_end, phi, dx_du, dy_dx0, dy_du)
