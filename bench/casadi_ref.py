"""
CasADi/IPOPT multiple-shooting reference of mshoot's benchmark cases (a benchmark only).

    python bench/casadi_ref.py [--data PATH] [--horizon 10] [--hours 72] [--substeps 4] \
        [--ipopt-option NAME=VALUE ...] [--plot] [--out out/bench/casadi_case]

runs the OU44 reference case (SPEC section 3) as a straightforward CasADi user
would write it, in a closed loop over ``--hours`` hourly steps: the R1C1 zone
as a symbolic ODE (state T in degC), RK4 with ``--substeps`` steps per hour,
multiple shooting over the horizon (one SX graph), exact first and second
derivatives from CasADi, IPOPT with its default settings (MUMPS, tolerance
1e-8) or with the ``--ipopt-option`` given (``bench/versus.py`` passes ours:
:func:`ipopt_option`), the previous plan shifted as the initial guess of the next solve.

Same data and settings as ``mshoot_studies.case``: the scenario of
``reference_scenario`` (5-8 April 2018, hourly means, ventilation off), the
comfort band as bounds on the state at the end of every interval, the cost
sum (q/q_nom)^2 with q_nom = 2000 W, -2000 <= q <= 2000 W, initial 20 degC,
the plant mshoot's exact R1C1 emulator, the KPIs of ``mshoot_core.kpis``.
One difference, said here: the band cannot be reached on days 2-3, and
where mshoot relaxes its hard bounds to the least violation (two phases), this
script does what a CasADi user would do: slack variables s >= 0 on the band
(T + s >= lower, T - s <= upper) with a large exact penalty
1e3 * sum(s) + 10 * sum(s^2) [s in K] added to the cost, in every solve.

Writes ``kpis.json`` (the KPIs and the time of every phase) and ``steps.csv``
to ``--out``; with ``--plot`` also ``plot.png``, the figure ``mshoot case`` draws
(:func:`mshoot_core.plotting.plot_closed_loop`, in this process after the loop, as a
script would: the same output as ours, for ``bench/versus.py``'s whole commands).
:class:`CasadiMpc` is also the per-step reference of the Z-zone scale problem in
``bench/versus.py``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import pathlib
import sys
import time
from typing import Any, Sequence

import casadi as ca
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models.r1c1 import (AIR_HEAT_PER_M3H, OCC_HEAT_SPAN_K, OCC_HEAT_W,
                                     OCC_HEAT_ZERO_K, R1C1Model, R1C1Parameters)
from mshoot_core.scenario import DEFAULT_DATA, DISTURBANCE_COLUMNS, reference_scenario
from mshoot_core.units import KELVIN
import numpy as np
import pandas as pd

logger = logging.getLogger('bench.casadi')

#: Heat rate limit and nominal value of the cost [W].
Q_MAX_W = 2000.0
#: Exact penalty of the band's slack: linear [1/K] and quadratic [1/K^2] weights.
PENALTY_LINEAR = 1e3
PENALTY_QUADRATIC = 1e1
#: IPOPT as a CasADi user runs it: defaults, quiet.
IPOPT_OPTIONS = {'ipopt.print_level': 0, 'ipopt.sb': 'yes', 'print_time': False}


@dataclasses.dataclass(frozen=True)
class ZoneParameters:
    """
    Per-zone R1C1 coefficients, arrays of shape (Z,).

    Attributes
    ----------
    capacity_j_k : ndarray
        Heat capacity C [J/K].
    resistance_k_w : ndarray
        Resistance to the outdoors R [K/W].
    solar_m2 : ndarray
        Solar aperture shgc times the zone's solar share [m2].
    occupant_gain : ndarray
        occheff times the zone's occupancy share [-].
    max_vent_m3h, vent_supply_c : float
        maxVent [m3/h] and Tve [degC] (ventilation is off in the reference cases).

    """

    capacity_j_k: np.ndarray
    resistance_k_w: np.ndarray
    solar_m2: np.ndarray
    occupant_gain: np.ndarray
    max_vent_m3h: float
    vent_supply_c: float

    @property
    def n_zones(self) -> int:
        return self.capacity_j_k.size

    @classmethod
    def from_r1c1(cls, parameters: R1C1Parameters | None = None,
                  solar_share: Sequence[float] | float = 1.0,
                  occupancy_share: Sequence[float] | float = 1.0) -> 'ZoneParameters':
        """From mshoot's R1C1 parameters (per-zone arrays allowed) and zone shares."""
        p = parameters or R1C1Parameters()
        zones = np.broadcast(np.asarray(p.Vi), np.asarray(solar_share),
                             np.asarray(occupancy_share)).shape or (1,)

        def per_zone(value: Any) -> np.ndarray:
            return np.broadcast_to(np.asarray(value, dtype=float), zones).copy()

        return cls(per_zone(p.capacity_j_k), per_zone(p.resistance_k_w),
                   per_zone(p.shgc * np.asarray(solar_share)),
                   per_zone(p.occheff * np.asarray(occupancy_share)), float(p.maxVent),
                   float(p.Tve))

    @classmethod
    def from_multizone(cls, model: Any) -> 'ZoneParameters':
        """From a :class:`mshoot_core.models.multizone.MultiZoneModel` (its seeded zones)."""
        return cls.from_r1c1(model.zone_parameters, model.solar_share, model.occupancy_share)


def zone_derivative(params: ZoneParameters, temperature_c: ca.SX, heat_w: ca.SX,
                    disturbances: ca.SX) -> ca.SX:
    """
    dT/dt [K/s] of every zone (SPEC section 3), states in degC.

    ``disturbances`` = (solrad [W/m2], Tout [degC], occ [persons], dpos [%]).
    """
    solrad, tout, occ, dpos = (disturbances[i] for i in range(4))
    capacity, resistance, solar, occupant_gain = (ca.DM(v) for v in (
        params.capacity_j_k, params.resistance_k_w, params.solar_m2, params.occupant_gain))
    occupants = occupant_gain * occ * OCC_HEAT_W * (
        OCC_HEAT_ZERO_K - KELVIN - temperature_c) / OCC_HEAT_SPAN_K
    vent = (AIR_HEAT_PER_M3H * params.max_vent_m3h * dpos / 100.0
            * (ca.fmax(tout, params.vent_supply_c) - temperature_c))
    return ((tout - temperature_c) / resistance + solar * solrad + occupants + vent
            + heat_w) / capacity


def rk4_interval(params: ZoneParameters, step_s: float, substeps: int) -> ca.Function:
    """F(T_start [degC] (Z,), q [W] (Z,), d (4,)) -> T_end [degC]: RK4, ``substeps`` steps."""
    z = params.n_zones
    temperature = ca.SX.sym('T', z)
    heat = ca.SX.sym('q', z)
    disturbances = ca.SX.sym('d', 4)
    h = step_s / substeps
    x = temperature
    for _ in range(substeps):
        k1 = zone_derivative(params, x, heat, disturbances)
        k2 = zone_derivative(params, x + h / 2 * k1, heat, disturbances)
        k3 = zone_derivative(params, x + h / 2 * k2, heat, disturbances)
        k4 = zone_derivative(params, x + h * k3, heat, disturbances)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function('F', [temperature, heat, disturbances], [x])


class CasadiMpc:
    """
    Multiple-shooting MPC of Z R1C1 zones in CasADi, solved with IPOPT.

    Decision variables, each (Z, N): u = q/q_max, the interval end
    temperatures X [degC] and the band's slack S [K] >= 0. Parameters: the
    start temperatures and the disturbances of the N intervals.

    Parameters
    ----------
    params : ZoneParameters
    horizon : int
        N intervals of ``step_s`` [s].
    substeps : int
        RK4 steps per interval.
    ipopt_options : dict, optional
        IPOPT options beyond :data:`IPOPT_OPTIONS` (CasADi's spelling, ``'ipopt.NAME'``).

    """

    def __init__(self, params: ZoneParameters, horizon: int, step_s: float = 3600.0,
                 substeps: int = 4, ipopt_options: dict | None = None) -> None:
        z, n = params.n_zones, int(horizon)
        self.n_zones, self.horizon = z, n
        interval = rk4_interval(params, step_s, substeps)
        controls = ca.SX.sym('u', z, n)
        ends = ca.SX.sym('X', z, n)
        slack = ca.SX.sym('S', z, n)
        start = ca.SX.sym('x0', z)
        disturbances = ca.SX.sym('D', 4, n)
        continuity, x = [], start
        for k in range(n):
            continuity.append(interval(x, Q_MAX_W * controls[:, k], disturbances[:, k])
                              - ends[:, k])
            x = ends[:, k]
        constraints = ca.vertcat(*continuity, ca.vec(ends + slack), ca.vec(ends - slack))
        cost = (ca.sumsqr(controls) + PENALTY_LINEAR * ca.sum1(ca.vec(slack))
                + PENALTY_QUADRATIC * ca.sumsqr(slack))
        nlp = {'x': ca.vertcat(ca.vec(controls), ca.vec(ends), ca.vec(slack)),
               'p': ca.vertcat(start, ca.vec(disturbances)), 'f': cost, 'g': constraints}
        self.solver = ca.nlpsol('mpc', 'ipopt', nlp, {**IPOPT_OPTIONS, **(ipopt_options or {})})
        size = z * n
        self.lbx = np.concatenate([-np.ones(size), np.full(size, -np.inf), np.zeros(size)])
        self.ubx = np.concatenate([np.ones(size), np.full(size, np.inf), np.full(size, np.inf)])
        self._guess: np.ndarray | None = None

    def _blocks(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, X, S), each (N, Z), from the NLP vector (column-major (Z, N) blocks)."""
        size = self.n_zones * self.horizon
        return tuple(w[i * size:(i + 1) * size].reshape(self.horizon, self.n_zones)
                     for i in range(3))

    def solve(self, start_c: np.ndarray, disturbances: np.ndarray, lower_c: np.ndarray,
              upper_c: np.ndarray) -> dict:
        """
        One MPC step.

        Parameters
        ----------
        start_c : ndarray (Z,)
            Start temperatures [degC].
        disturbances : ndarray (N, 4)
            solrad, Tout, occ, dpos of every interval.
        lower_c, upper_c : ndarray (N, Z)
            Band at the end of every interval [degC].

        Returns
        -------
        dict with ``q`` (N, Z) [W], ``T`` (N, Z) [degC], ``slack`` (N, Z) [K],
        ``objective``, ``success``, ``iterations`` and IPOPT's ``stats``.

        """
        size = self.n_zones * self.horizon
        start_c = np.asarray(start_c, dtype=float).reshape(-1)
        if self._guess is None:
            guess = np.concatenate([np.zeros(size), np.tile(start_c, self.horizon),
                                    np.zeros(size)])
        else:
            guess = self._guess
        lbg = np.concatenate([np.zeros(size), np.asarray(lower_c, float).reshape(-1),
                              np.full(size, -np.inf)])
        ubg = np.concatenate([np.zeros(size), np.full(size, np.inf),
                              np.asarray(upper_c, float).reshape(-1)])
        params = np.concatenate([start_c, np.asarray(disturbances, float).reshape(-1)])
        sol = self.solver(x0=guess, p=params, lbx=self.lbx, ubx=self.ubx, lbg=lbg, ubg=ubg)
        stats = self.solver.stats()
        w = np.asarray(sol['x']).reshape(-1)
        blocks = self._blocks(w)
        shifted = []
        for block in blocks:  # the plan shifted by one interval, the last one repeated
            moved = np.vstack([block[1:], block[-1:]])
            shifted.append(moved.reshape(-1))
        self._guess = np.concatenate(shifted)
        u, ends, slack = blocks
        # IPOPT may overstep a bound by its bound_relax_factor (1e-8): clip as the plant would
        return {'q': np.clip(u, -1.0, 1.0) * Q_MAX_W, 'T': ends, 'slack': slack,
                'objective': float(sol['f']), 'success': bool(stats['success']),
                'iterations': int(stats['iter_count']), 'stats': stats}


def function_time_s(stats: dict, clock: str = 'wall') -> float:
    """Time [s] IPOPT spent in CasADi's function and derivative evaluations (clock: wall, proc)."""
    return float(sum(stats.get(f't_{clock}_{name}', 0.0) for name in (
        'nlp_f', 'nlp_g', 'nlp_grad', 'nlp_grad_f', 'nlp_jac_g', 'nlp_hess_l')))


def ipopt_option(text: str) -> tuple[str, Any]:
    """
    Return ('ipopt.NAME', value) from 'NAME=VALUE' (an int or float where VALUE reads as one).

    Raises ValueError for text without '='.
    """
    name, sep, value = text.partition('=')
    if not sep or not name:
        raise ValueError(f'expected an IPOPT option as NAME=VALUE, got {text!r}')
    for kind in (int, float):
        try:
            return f'ipopt.{name}', kind(value)
        except ValueError:
            pass
    return f'ipopt.{name}', value


def run_case(data: pathlib.Path | None, horizon: int, hours: int, substeps: int,
             initial_c: float = 20.0,
             ipopt_options: dict | None = None
             ) -> tuple[dict, pd.DataFrame, dict, pd.DataFrame]:
    """
    Run the closed loop of the reference case; return (kpis, steps, phase times [s], fine).

    ``fine``: the plant's trajectory on its fine grid (with the band), for the figure.

    ``ipopt_options``: IPOPT options beyond IPOPT's defaults, in CasADi's spelling.
    """
    timing = {}
    started, cpu = time.perf_counter(), time.process_time()
    scenario = reference_scenario('ou44', data, hours)
    disturbances = scenario[list(DISTURBANCE_COLUMNS)].to_numpy(dtype=float)
    band = scenario[['comfort_min', 'comfort_max']].to_numpy(dtype=float)
    timing['data_s'] = time.perf_counter() - started
    timing['data_cpu_s'] = time.process_time() - cpu

    started, cpu = time.perf_counter(), time.process_time()
    mpc = CasadiMpc(ZoneParameters.from_r1c1(), horizon, substeps=substeps,
                    ipopt_options=ipopt_options)
    emulator = Emulator(R1C1Model(), scenario, [initial_c + KELVIN])
    timing['build_s'] = time.perf_counter() - started
    timing['build_cpu_s'] = time.process_time() - cpu

    loop_started, loop_cpu = time.perf_counter(), time.process_time()
    rows, fines = [], []
    solves = plant = evaluations = solves_cpu = plant_cpu = 0.0
    for k in range(hours):
        window = np.minimum(np.arange(k, k + horizon + 1), len(scenario) - 1)
        started, cpu = time.perf_counter(), time.process_time()
        plan = mpc.solve(emulator.x - KELVIN, disturbances[window[:-1]],
                         band[window[1:], :1], band[window[1:], 1:])
        solve_s = time.perf_counter() - started
        solves += solve_s
        solves_cpu += time.process_time() - cpu
        evaluations += function_time_s(plan['stats'])
        started, cpu = time.perf_counter(), time.process_time()
        record = emulator.advance([plan['q'][0, 0]])
        plant += time.perf_counter() - started
        plant_cpu += time.process_time() - cpu
        rows.append({'time_s': record.t_start_s, 'q': float(record.controls[0]),
                     'T_end': float(record.x_end[0]), 'T_predicted': plan['T'][0, 0] + KELVIN,
                     'solve_time_s': solve_s, 'success': plan['success'],
                     'iterations': plan['iterations'], 'objective': plan['objective']})
        fines.append(record.fine if k == 0 else record.fine.iloc[1:])
    loop_s = time.perf_counter() - loop_started
    timing['loop_cpu_s'] = time.process_time() - loop_cpu
    started, cpu = time.perf_counter(), time.process_time()
    steps = pd.DataFrame(rows).set_index('time_s')
    fine = pd.concat(fines)
    kpis = closed_loop_kpis(steps, fine, 3600.0, loop_s)
    kpis.update(iterations=int(steps['iterations'].sum()))
    timing.update(loop_s=loop_s, solves_s=solves, function_evaluations_s=evaluations,
                  plant_s=plant, kpis_s=time.perf_counter() - started,
                  solves_cpu_s=solves_cpu, plant_cpu_s=plant_cpu,
                  kpis_cpu_s=time.process_time() - cpu)
    return kpis, steps, timing, fine


def main(argv: Sequence[str] | None = None) -> int:
    started_epoch = time.time()
    main_start_cpu = time.process_time()  # the interpreter's start and the imports
    started = time.perf_counter()
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--data', type=pathlib.Path, default=None,
                        help=f'OU44 measurements.csv (default {DEFAULT_DATA.resolve()})')
    parser.add_argument('--horizon', type=int, default=10, help='horizon [h] (default 10)')
    parser.add_argument('--hours', type=int, default=72, help='control steps (default 72)')
    parser.add_argument('--substeps', type=int, default=4,
                        help='RK4 steps per hour (default 4)')
    parser.add_argument('--ipopt-option', action='append', default=[], metavar='NAME=VALUE',
                        help='an IPOPT option beyond its defaults (repeatable), e.g. '
                        'mu_strategy=adaptive')
    parser.add_argument('--plot', action='store_true',
                        help='draw plot.png, the figure of mshoot case (after the loop)')
    parser.add_argument('--out', type=pathlib.Path,
                        default=pathlib.Path('out/bench/casadi_case'))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='%(message)s')
    if args.horizon < 1 or args.hours < 1 or args.substeps < 1:
        parser.error('--horizon, --hours and --substeps must be >= 1')
    try:
        options = dict(ipopt_option(text) for text in args.ipopt_option)
    except ValueError as exc:
        parser.error(str(exc))
    try:
        kpis, steps, timing, fine = run_case(args.data, args.horizon, args.hours,
                                             args.substeps, ipopt_options=options)
    except (FileNotFoundError, ValueError) as exc:
        logger.error('%s', exc)
        return 2
    output_started, output_cpu = time.perf_counter(), time.process_time()
    args.out.mkdir(parents=True, exist_ok=True)
    steps.to_csv(args.out / 'steps.csv')
    if args.plot:  # (matplotlib imported here, as mshoot's own fallback draws it)
        from mshoot_core.plotting import plot_closed_loop
        plot_closed_loop(fine, steps, args.out / 'plot.png',
                         f"CasADi/IPOPT: energy {kpis['energy_kwh']:.2f} kWh, discomfort "
                         f"{kpis['discomfort_kh']:.2f} Kh")
    timing['output_s'] = time.perf_counter() - output_started
    timing['output_cpu_s'] = time.process_time() - output_cpu
    timing['main_s'] = time.perf_counter() - started
    timing.update(main_start_epoch=started_epoch, main_end_epoch=time.time(),
                  main_start_cpu_s=main_start_cpu, main_end_cpu_s=time.process_time())
    kpis.update(horizon_h=args.horizon, substeps=args.substeps, casadi=ca.__version__,
                penalty_linear=PENALTY_LINEAR, penalty_quadratic=PENALTY_QUADRATIC,
                ipopt_options=options, timing=timing)
    (args.out / 'kpis.json').write_text(json.dumps(kpis, indent=2, sort_keys=True) + '\n')
    logger.info('casadi: energy %.2f kWh, discomfort %.2f Kh (hourly %.2f Kh), loop %.2f s, '
                'median solve %.4f s, %d failures', kpis['energy_kwh'], kpis['discomfort_kh'],
                kpis['discomfort_kh_hourly'], kpis['wall_s'], kpis['solve_s_median'],
                kpis['solver_failures'])
    return 0


if __name__ == '__main__':
    sys.exit(main())
