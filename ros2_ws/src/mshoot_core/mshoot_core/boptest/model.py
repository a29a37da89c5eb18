"""
A grey-box control model of BOPTEST's ``bestest_hydronic_heat_pump`` house (3R... RC, 3 states).

States [K]: ``Tz`` zone (air and furniture; the comfort band bounds it), ``Tf`` floor slab
with its water, ``Te`` building envelope::

    Cz dTz/dt = (Tf - Tz)/Rzf + (Te - Tz)/Rze + (Tout - Tz)/Rzo + gz*solar + gi*gains
    Cf dTf/dt = (Tz - Tf)/Rzf + Q
    Ce dTe/dt = (Tz - Te)/Rze + (Tout - Te)/Reo + ge*solar

The heat pump is run at full load for a fraction ``d`` of each interval (the control, the
duty in [0, 1]; see :mod:`mshoot_core.boptest.economic` for its dispatch at 60 s), so its
heat and electric power are linear in ``d`` with gains that depend on the outdoor
temperature::

    Q    = d * (qa + qb*Tout)                                  heat to the floor [W]
    P_el = d * (pa + pb*Tout + paux)                           compressor, fan, pump [W]
    cost = price * P_el * dt / 3.6e6                           [EUR] per interval

Inputs held over an interval make the model linear time-invariant in its states, so every
interval has the exact solution x_end = Phi x0 + Gamma B w (matrix exponential, computed
once per interval length) and exact derivatives. Outputs at an interval's end: ``T`` the
zone temperature [degC], ``P`` the interval's mean electric power [W], ``Q`` its heat [W],
``cost`` its electricity cost [EUR].

:class:`ZoneObserver` estimates the unmeasured states ``Tf`` and ``Te`` from the measured
zone temperature (a steady-state Kalman filter of the same discretisation).
"""
from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd
import scipy.linalg

from mshoot_core.models.base import check_parameters, IntervalJacobians, Model
from mshoot_core.shooting import Scaling
from mshoot_core.units import KELVIN

#: Joules per kWh.
J_PER_KWH = 3.6e6


@dataclasses.dataclass(frozen=True)
class HouseParameters:
    """
    Parameters of the 3-state house model (defaults: a plausible start, not the fit).

    Attributes
    ----------
    Cz, Cf, Ce : float
        Heat capacities of zone, floor and envelope [J/K].
    Rzf, Rze, Rzo, Reo : float
        Resistances zone-floor, zone-envelope, zone-outdoors (windows, infiltration),
        envelope-outdoors [K/W].
    gz, ge : float
        Solar apertures to the zone and to the envelope [m2] (W per W/m2 of global
        horizontal irradiance).
    gi : float
        Fraction of the internal gains that heats the zone [-].
    qa, qb : float
        Heat pump heat at full load: qa + qb * Tout [W, W/K] (Tout in degC).
    pa, pb : float
        Compressor power at full load: pa + pb * Tout [W, W/K].
    paux : float
        Fan and emission pump power while the heat pump runs [W].

    """

    Cz: float = 5e6
    Cf: float = 3e7
    Ce: float = 5e7
    Rzf: float = 2e-3
    Rze: float = 5e-3
    Rzo: float = 2e-2
    Reo: float = 1e-2
    gz: float = 5.0
    ge: float = 5.0
    gi: float = 1.0
    qa: float = 10180.0
    qb: float = 306.0
    pa: float = 3078.0
    pb: float = 52.0
    paux: float = 530.7

    def __post_init__(self) -> None:
        check_parameters(self, 'house', positive=('Cz', 'Cf', 'Ce', 'Rzf', 'Rze', 'Rzo', 'Reo'))

    def to_dict(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_json(cls, path: str | pathlib.Path) -> HouseParameters:
        """Read the parameters from a JSON file (a mapping, or ``{'parameters': mapping}``)."""
        data = json.loads(pathlib.Path(path).read_text())
        data = data.get('parameters', data)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f'{path}: unknown house parameters {unknown}')
        return cls(**{k: float(v) for k, v in data.items()})


class HouseModel(Model):
    """
    The 3-state house with its heat pump run by duty ``d``; exact per-interval solution.

    Inputs: ``Tout`` [degC], ``solar`` global horizontal irradiance [W/m2], ``gains``
    internal gains [W], ``price`` [EUR/kWh], ``d`` heat pump duty [-] (the control).
    States: ``Tz``, ``Tf``, ``Te`` [K]. Outputs: ``T`` zone [degC], ``P`` electric power [W],
    ``Q`` heat [W], ``cost`` [EUR] of the interval just ended.
    """

    input_names = ('Tout', 'solar', 'gains', 'price', 'd')
    state_names = ('Tz', 'Tf', 'Te')
    output_names = ('T', 'P', 'Q', 'cost')
    #: The MPC optimises the duty; the comfort band bounds the zone.
    control_names = ('d',)
    comfort_states = ('Tz',)
    #: Normalisation of the states for the optimiser (offset, scale) [K].
    state_scaling = Scaling(np.full(3, 288.15), np.full(3, 10.0))

    def __init__(self, parameters: HouseParameters | Mapping[str, float] | None = None) -> None:
        if parameters is None:
            parameters = HouseParameters()
        elif not isinstance(parameters, HouseParameters):
            parameters = HouseParameters(**dict(parameters))
        self.parameters = parameters
        p = parameters
        a = np.array([
            [-(1 / p.Rzf + 1 / p.Rze + 1 / p.Rzo) / p.Cz, 1 / (p.Rzf * p.Cz), 1 / (p.Rze * p.Cz)],
            [1 / (p.Rzf * p.Cf), -1 / (p.Rzf * p.Cf), 0.0],
            [1 / (p.Rze * p.Ce), 0.0, -(1 / p.Rze + 1 / p.Reo) / p.Ce]])
        # columns: Tout [K], solar [W/m2], gains [W], heat Q [W]
        b = np.array([[1 / (p.Rzo * p.Cz), p.gz / p.Cz, p.gi / p.Cz, 0.0],
                      [0.0, 0.0, 0.0, 1 / p.Cf],
                      [1 / (p.Reo * p.Ce), p.ge / p.Ce, 0.0, 0.0]])
        self.a, self.b = a, b
        self._discrete: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    # -- the discretisation ----------------------------------------------------------------
    def discrete(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Return (Phi (3, 3), Gamma B (3, 4)) of an interval of ``dt_s`` seconds."""
        key = float(dt_s)
        hit = self._discrete.get(key)
        if hit is None:
            m = np.zeros((7, 7))
            m[:3, :3] = self.a * key
            m[:3, 3:] = self.b * key
            e = scipy.linalg.expm(m)
            hit = (e[:3, :3].copy(), e[:3, 3:].copy())
            self._discrete[key] = hit
        return hit

    def heat_full_w(self, tout_c: np.ndarray) -> np.ndarray:
        """Heat of the heat pump at full load [W] at outdoor temperature ``tout_c`` [degC]."""
        p = self.parameters
        return p.qa + p.qb * np.asarray(tout_c, dtype=float)

    def power_full_w(self, tout_c: np.ndarray) -> np.ndarray:
        """Electric power at full load, fan and pump included [W]."""
        p = self.parameters
        return p.pa + p.pb * np.asarray(tout_c, dtype=float) + p.paux

    def _forcing(self, u: np.ndarray) -> np.ndarray:
        """Return w (B, 4) = [Tout K, solar, gains, Q] from inputs ``u`` (B, 5)."""
        q = u[:, 4] * self.heat_full_w(u[:, 0])
        return np.column_stack([u[:, 0] + KELVIN, u[:, 1], u[:, 2], q])

    def _outputs(self, x_end: np.ndarray, u: np.ndarray, dt_s: float) -> np.ndarray:
        power = u[:, 4] * self.power_full_w(u[:, 0])
        return np.column_stack([x_end[:, 0] - KELVIN, power, u[:, 4] * self.heat_full_w(u[:, 0]),
                                u[:, 3] * power * dt_s / J_PER_KWH])

    # -- the Model interface ---------------------------------------------------------------
    def simulate(self, udf: pd.DataFrame,
                 x0: Sequence[float]) -> tuple[pd.DataFrame, pd.DataFrame]:
        t, u, x0_arr = self.check_inputs(udf, x0)
        x = np.empty((t.size, 3))
        y = np.empty((t.size, 4))
        x[0] = x0_arr
        w = self._forcing(u[:-1])
        dts = np.diff(t)
        for k in range(dts.size):
            phi, gam = self.discrete(dts[k])
            x[k + 1] = phi @ x[k] + gam @ w[k]
            y[k + 1] = self._outputs(x[k + 1][None, :], u[k][None, :], dts[k])[0]
        y[0] = self._outputs(x[:1], np.zeros((1, 5)), 1.0)[0]
        return (pd.DataFrame(y, index=udf.index, columns=list(self.output_names)),
                pd.DataFrame(x, index=udf.index, columns=list(self.state_names)))

    def simulate_intervals(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           t_start_s: np.ndarray | None = None) -> tuple[np.ndarray,
                                                                         np.ndarray]:
        """Exact end states and outputs of B intervals (time-invariant: no start times)."""
        x_start, u = self._check_batch(x_start, u)
        phi, gam = self.discrete(dt_s)
        x_end = x_start @ phi.T + self._forcing(u) @ gam.T
        return x_end, self._outputs(x_end, u, dt_s)

    def interval_jacobians(self, x_start: np.ndarray, u: np.ndarray, dt_s: float,
                           wrt_inputs: Sequence[int],
                           t_start_s: np.ndarray | None = None) -> IntervalJacobians:
        """Exact end values and derivatives of B intervals."""
        x_start, u = self._check_batch(x_start, u)
        x_end, y_end = self.simulate_intervals(x_start, u, dt_s)
        phi, gam = self.discrete(dt_s)
        batch = x_start.shape[0]
        p = self.parameters
        wrt = list(wrt_inputs)
        dx_du = np.zeros((batch, 3, len(wrt)))
        dy_du = np.zeros((batch, 4, len(wrt)))
        heat = self.heat_full_w(u[:, 0])
        power = self.power_full_w(u[:, 0])
        for j, col in enumerate(wrt):
            if col == 0:    # Tout: conduction and the heat pump's gains
                dx_du[:, :, j] = gam[:, 0][None, :] + (u[:, 4] * p.qb)[:, None] * gam[:, 3]
                dy_du[:, 1, j] = u[:, 4] * p.pb
                dy_du[:, 2, j] = u[:, 4] * p.qb
                dy_du[:, 3, j] = u[:, 3] * u[:, 4] * p.pb * dt_s / J_PER_KWH
            elif col in (1, 2):
                dx_du[:, :, j] = gam[:, col][None, :]
            elif col == 3:  # price: the cost only
                dy_du[:, 3, j] = u[:, 4] * power * dt_s / J_PER_KWH
            else:           # duty
                dx_du[:, :, j] = heat[:, None] * gam[:, 3][None, :]
                dy_du[:, 1, j] = power
                dy_du[:, 2, j] = heat
                dy_du[:, 3, j] = u[:, 3] * power * dt_s / J_PER_KWH
            dy_du[:, 0, j] = dx_du[:, 0, j]
        dx_dx0 = np.broadcast_to(phi, (batch, 3, 3)).copy()
        dy_dx0 = np.zeros((batch, 4, 3))
        dy_dx0[:, 0, :] = phi[0]
        return IntervalJacobians(x_end, y_end, dx_dx0, dx_du, dy_dx0, dy_du)


class ZoneObserver:
    """
    Steady-state Kalman filter of :class:`HouseModel` from the measured zone temperature.

    The floor and envelope temperatures are not measured: the filter predicts all three
    states one interval ahead with the inputs applied, then corrects them with the
    measured zone temperature (gain from the discrete algebraic Riccati equation).

    Parameters
    ----------
    model : HouseModel
    dt_s : float
        Interval between two measurements [s].
    process_sd_k : sequence of 3 float
        Standard deviation of the process noise per interval, per state [K].
    measurement_sd_k : float
        Standard deviation of the zone temperature measurement [K].

    """

    def __init__(self, model: HouseModel, dt_s: float = 3600.0,
                 process_sd_k: Sequence[float] = (0.1, 0.05, 0.05),
                 measurement_sd_k: float = 0.05) -> None:
        self.model = model
        self.dt_s = float(dt_s)
        phi, _ = model.discrete(self.dt_s)
        c = np.array([[1.0, 0.0, 0.0]])
        q = np.diag(np.asarray(process_sd_k, dtype=float) ** 2)
        r = np.array([[float(measurement_sd_k) ** 2]])
        p = scipy.linalg.solve_discrete_are(phi.T, c.T, q, r)
        self.gain = (p @ c.T @ np.linalg.inv(c @ p @ c.T + r)).reshape(3)
        self.x: np.ndarray | None = None

    def reset(self, tz_k: float, tf_k: float | None = None, te_k: float | None = None) -> None:
        """Start from a measured zone temperature (the others equal to it unless given)."""
        self.x = np.array([tz_k, tz_k if tf_k is None else tf_k, tz_k if te_k is None else te_k],
                          dtype=float)

    def update(self, u: Sequence[float], tz_measured_k: float) -> np.ndarray:
        """
        Predict over one interval with inputs ``u`` (model input order), then correct.

        Returns
        -------
        ndarray, shape (3,)
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


def load_parameters(path: str | pathlib.Path | None = None) -> HouseParameters:
    """
    Return the identified parameters (the packaged fit unless ``path`` is given).

    The packaged fit is ``mshoot_core/boptest/house_fit.json``, written by
    ``mshoot_studies.boptest_mpc identify``.
    """
    target = pathlib.Path(path) if path is not None else (
        pathlib.Path(__file__).with_name('house_fit.json'))
    if not target.is_file():
        raise FileNotFoundError(f'{target}: no identified house parameters (run the '
                                'identification: python -m mshoot_studies.boptest_mpc identify)')
    return HouseParameters.from_json(target)


def house_model(parameters: Any = None) -> HouseModel:
    """
    Return the house model with ``parameters``.

    ``parameters``: a HouseParameters, a mapping, a JSON path, or None for the packaged fit.
    """
    if parameters is None or isinstance(parameters, (str, pathlib.Path)):
        parameters = load_parameters(parameters)
    return HouseModel(parameters)
