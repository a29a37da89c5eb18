"""
An R2C2 zone in plain Python: an air node and an envelope node, exact per interval.

Its heat balances [W]::

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
derivative of the matrix exponential for ``dpos``, which changes A). ``Phi``
in closed form (:func:`expm2`: A has real eigenvalues), the Frechet
derivatives by eigendecomposition (:func:`expm_frechet_batch`), all intervals
at once. :meth:`R2C2Model.parameter_sensitivities` gives the exact derivatives
of the air temperature with respect to every parameter, for calibration
(:func:`mshoot_core.calibration.model_builder` of ``R2C2Model`` and
``R2C2Parameters``: an analytic Jacobian).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
import pandas as pd

from mshoot_core.models.base import check_parameters, IntervalJacobians, Model
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
        check_parameters(self, 'R2C2', positive=('Cair', 'Cwall', 'Raw', 'Rwa', 'Rwin'),
                         nonnegative=('shgc', 'occheff', 'maxVent'))
        if not 0.0 <= self.fsun <= 1.0:
            raise ValueError(f'R2C2 parameter fsun must be in [0, 1], got {self.fsun}')


def expm2(a: np.ndarray) -> np.ndarray:
    """
    Return ``expm(a)`` of a batch of 2x2 matrices with real eigenvalues, in closed form.

    ``expm(a) = exp(l2) I + D (a - l2 I)`` with the eigenvalues ``l1 >= l2``
    and ``D = (exp(l1) - exp(l2)) / (l1 - l2)`` (``exp(l1)`` when equal),
    computed without cancellation. The A of an RC network is similar to a
    symmetric matrix: its eigenvalues are real. Equal to
    :func:`scipy.linalg.expm` to round-off, without its per-matrix cost.

    Parameters
    ----------
    a : ndarray, shape (B, 2, 2)
        The matrices [-] (``A dt``).

    Returns
    -------
    ndarray, shape (B, 2, 2)

    """
    half = 0.5 * (a[:, 0, 0] - a[:, 1, 1])
    cross = a[:, 0, 1] * a[:, 1, 0]
    q = np.sqrt(np.maximum(half ** 2 + cross, 0.0))
    mean = 0.5 * (a[:, 0, 0] + a[:, 1, 1])
    low = mean - q  # l2
    gap = 2.0 * q  # l1 - l2 >= 0
    small = gap < 1e-8
    safe = np.where(small, 1.0, gap)
    divided = np.exp(mean + q) * np.where(small, 1.0 - gap / 2.0, -np.expm1(-safe) / safe)
    # a - l2 I: the diagonal q + half and q - half, each without cancellation
    plus = np.where(half >= 0, q + half, cross / np.where(q - half > 0, q - half, 1.0))
    minus = np.where(half <= 0, q - half, cross / np.where(q + half > 0, q + half, 1.0))
    out = np.empty_like(a, dtype=float)
    e_low = np.exp(low)
    out[:, 0, 0] = e_low + divided * plus
    out[:, 1, 1] = e_low + divided * minus
    out[:, 0, 1] = divided * a[:, 0, 1]
    out[:, 1, 0] = divided * a[:, 1, 0]
    return out


def expm_frechet_batch(m: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return ``expm(m)`` and its Frechet derivatives along ``e`` for a batch of matrices.

    Through the eigendecomposition ``m = V diag(l) V^-1`` (the augmented
    matrix of an RC network is diagonalisable: real distinct eigenvalues of a
    matrix similar to a symmetric one, and 0):
    ``L(m, e) = V ((V^-1 e V) * D) V^-1`` with the divided differences
    ``D_ij = (exp(l_i) - exp(l_j)) / (l_i - l_j)`` (``exp(l_i)`` when equal).
    Equal to :func:`scipy.linalg.expm_frechet` (to about 1e-12 relative here)
    at a fraction of its cost in a batch.

    Parameters
    ----------
    m : ndarray, shape (R, n, n)
        The matrices (diagonalisable).
    e : ndarray, shape (R, P, n, n)
        P directions per matrix.

    Returns
    -------
    expm : ndarray, shape (R, n, n)
    frechet : ndarray, shape (R, P, n, n)

    """
    lam, v = np.linalg.eig(m)
    v_inv = np.linalg.inv(v)
    li, lj = lam[:, :, None], lam[:, None, :]
    top = np.where(li.real >= lj.real, li, lj)  # exp(top) * expm1(d) / d with d <= 0
    d = np.where(li.real >= lj.real, lj - li, li - lj)
    small = np.abs(d) < 1e-8
    safe = np.where(small, 1.0, d)
    divided = np.exp(top) * np.where(small, 1.0 + d / 2.0, np.expm1(safe) / safe)
    expm = np.einsum('rij,rj,rjk->rik', v, np.exp(lam), v_inv)
    inner = np.einsum('rij,rpjk,rkl->rpil', v_inv, e, v) * divided[:, None]
    frechet = np.einsum('rij,rpjk,rkl->rpil', v, inner, v_inv)
    return expm.real, frechet.real


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
    #: A's off-diagonal entries (1 / (C Raw)) are positive, so Phi = expm(A t) >= 0: both
    #: nodes' ends are nondecreasing in both starts and in q (heat into the air node)
    monotone_inputs = ('q',)
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
        phi = expm2(a * float(dt_s))
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
        phi = expm2(a * dt_s)
        x_end = np.einsum('bij,bj->bi', phi, x_start) + np.linalg.solve(
            a, np.einsum('bij,bj->bi', phi - np.eye(2), b)[..., None])[..., 0]
        y_end = np.column_stack([x_end[:, 0] - KELVIN, u[:, Q] * dt_s])
        batch, wrt = x_start.shape[0], list(wrt_inputs)
        dx_du = np.zeros((batch, 2, len(wrt)))
        dy_du = np.zeros((batch, 2, len(wrt)))
        for j, col in enumerate(wrt):
            da, db = self._input_derivatives(u, col)
            if np.any(da):  # A changes: the Frechet derivative of the augmented exponential
                m = np.zeros((batch, 3, 3))
                m[:, :2, :2], m[:, :2, 2] = a, b
                dm = np.zeros((batch, 1, 3, 3))
                dm[:, 0, :2, :2], dm[:, 0, :2, 2] = da, db
                _, de = expm_frechet_batch(m * dt_s, dm * dt_s)
                dx_du[:, :, j] = (np.einsum('bij,bj->bi', de[:, 0, :2, :2], x_start)
                                  + de[:, 0, :2, 2])
            else:  # only b changes: Gamma @ db
                dx_du[:, :, j] = np.linalg.solve(
                    a, np.einsum('bij,bj->bi', phi - np.eye(2), db)[..., None])[..., 0]
            dy_du[:, 0, j] = dx_du[:, 0, j]
            if col == Q:
                dy_du[:, 1, j] = dt_s
        dy_dx0 = np.zeros((batch, 2, 2))
        dy_dx0[:, 0, :] = phi[:, 0, :]
        return IntervalJacobians(x_end, y_end, phi, dx_du, dy_dx0, dy_du)

    # -- calibration ------------------------------------------------------------------------
    def _parameter_derivatives(self, u: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Return dA/dp (B, 2, 2) and db/dp (B, 2) of the parameter ``name`` for inputs u."""
        p = self.parameters
        a, b = self.system(u)
        da, db = np.zeros_like(a), np.zeros_like(b)
        tout_k = u[:, TOUT] + KELVIN
        solrad = u[:, SOLRAD]
        if name == 'Cair':
            da[:, 0, :], db[:, 0] = -a[:, 0, :] / p.Cair, -b[:, 0] / p.Cair
        elif name == 'Cwall':
            da[:, 1, :], db[:, 1] = -a[:, 1, :] / p.Cwall, -b[:, 1] / p.Cwall
        elif name == 'Raw':
            g = 1.0 / p.Raw ** 2  # d(1/Raw)/dRaw = -g
            da[:, 0, 0], da[:, 0, 1] = g / p.Cair, -g / p.Cair
            da[:, 1, 0], da[:, 1, 1] = -g / p.Cwall, g / p.Cwall
        elif name == 'Rwa':
            da[:, 1, 1] = 1.0 / (p.Rwa ** 2 * p.Cwall)
            db[:, 1] = -tout_k / (p.Rwa ** 2 * p.Cwall)
        elif name == 'Rwin':
            da[:, 0, 0] = 1.0 / (p.Rwin ** 2 * p.Cair)
            db[:, 0] = -tout_k / (p.Rwin ** 2 * p.Cair)
        elif name == 'shgc':
            db[:, 0] = (1.0 - p.fsun) * solrad / p.Cair
            db[:, 1] = p.fsun * solrad / p.Cwall
        elif name == 'fsun':
            db[:, 0] = -p.shgc * solrad / p.Cair
            db[:, 1] = p.shgc * solrad / p.Cwall
        elif name == 'occheff':
            db[:, 0] = OCC_HEAT_W * u[:, OCC] / p.Cair
        elif name == 'Tve':
            db[:, 0] = self._vent(u) * (u[:, TOUT] < p.Tve) / p.Cair
        elif name == 'maxVent':
            dvent = AIR_HEAT_PER_M3H * u[:, DPOS] / 100.0
            da[:, 0, 0] = -dvent / p.Cair
            db[:, 0] = dvent * (np.maximum(u[:, TOUT], p.Tve) + KELVIN) / p.Cair
        else:
            names = [f.name for f in dataclasses.fields(R2C2Parameters)]
            raise ValueError(f'unknown R2C2 parameter {name!r}; expected one of {names}')
        return da, db

    def parameter_sensitivities(self, udf: pd.DataFrame, x0: Sequence[float],
                                names: Sequence[str]) -> tuple[pd.DataFrame, np.ndarray]:
        """
        Simulate as :meth:`simulate` and return the exact output derivatives w.r.t. parameters.

        Each interval is ``[x; 1](t + dt) = expm(M dt) [x; 1](t)`` with the augmented
        ``M = [[A, b], [0, 0]]``; the derivative of ``expm(M dt)`` along
        ``dM/dp dt`` is the Frechet derivative (:func:`expm_frechet_batch`, all
        intervals and parameters at once). Forward sensitivities:
        ``dx_{k+1}/dp = dE_k [x_k; 1] + Phi_k dx_k/dp``, ``dx_0/dp = 0`` (the
        start state is given).

        Parameters
        ----------
        udf : DataFrame
            Inputs as for :meth:`simulate`.
        x0 : sequence of float, length 2
            Start state [K].
        names : sequence of str
            Fields of :class:`R2C2Parameters`.

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
            For an unknown name.

        """
        names = list(names)
        for name in names:  # reject unknown names before simulating
            self._parameter_derivatives(np.zeros((1, 5)), name)
        ydf, xdf = self.simulate(udf, x0)
        t, u, _ = self.check_inputs(udf, x0)
        states = xdf.to_numpy()
        dt = np.diff(t)
        rows, n = dt.size, len(names)
        a, b = self.system(u[:-1])
        m = np.zeros((rows, 3, 3))  # the augmented [[A, b], [0, 0]] dt of every interval
        m[:, :2, :2], m[:, :2, 2] = a, b
        m *= dt[:, None, None]
        dm = np.zeros((rows, n, 3, 3))
        for j, name in enumerate(names):
            da, db = self._parameter_derivatives(u[:-1], name)
            dm[:, j, :2, :2], dm[:, j, :2, 2] = da, db
        dm *= dt[:, None, None, None]
        exp, frechet = expm_frechet_batch(m, dm)
        phi = exp[:, :2, :2]
        augmented = np.column_stack([states[:-1], np.ones(rows)])  # [x_k; 1]
        sens = np.zeros((t.size, 2, n))
        for k in range(rows):
            sens[k + 1] = (np.einsum('jab,b->aj', frechet[k, :, :2, :], augmented[k])
                           + phi[k] @ sens[k])
        dy_dp = np.zeros((t.size, 2, n))
        dy_dp[:, 0, :] = sens[:, 0, :]
        return ydf, dy_dp
