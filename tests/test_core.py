"""mshoot_core: R1C1 analytics, multiple shooting, MPC loop, KPIs, scenarios and outputs."""
import json
import os
import pathlib
import sys

from mshoot_core import plotting
from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis, discomfort_kh, energy_kwh
from mshoot_core.models import Model, R1C1Model, R1C1Parameters
from mshoot_core.mpc import MPC
from mshoot_core.outputs import write_outputs
from mshoot_core.plotting import PlotWorker
from mshoot_core.scenario import forecast_window, synthetic_scenario
from mshoot_core.settings import ComfortSettings, MpcSettings, ProblemSettings, SettingsError
from mshoot_core.shooting import NlpIndex, ShootingProblem
from mshoot_core.solvers import make_solver, SlsqpSolver
from mshoot_core.units import KELVIN
import numpy as np
import pandas as pd
import pytest
from scipy import optimize


def r1c1_closed_form(t, T0, solrad, tout, occ, q, p=R1C1Parameters()):
    """Closed-form R1C1 response [K] to constant inputs (dpos = 0), from SPEC's equation."""
    C = p.tmass * 1.2 * 1005 * p.Vi
    R = p.RExt / (3 * p.Vi ** (2 / 3))
    g = 1 / R + p.occheff * occ * 84 / 32
    f = (tout + KELVIN) / R + p.shgc * solrad + p.occheff * occ * 84 * 325.15 / 32 + q
    return f / g + (T0 - f / g) * np.exp(-g * t / C)


def test_r1c1_parameters_match_spec():
    p = R1C1Parameters()
    assert p.capacity_j_k == pytest.approx(2.934e7, rel=1e-3)
    assert p.resistance_k_w == pytest.approx(0.021555, rel=1e-4)
    assert p.capacity_j_k * p.resistance_k_w / 3600 == pytest.approx(176, rel=0.01)


def test_r1c1_python_model_equals_closed_form():
    model = R1C1Model()
    t = np.arange(0, 6 * 3600 + 1, 600.0)
    udf = pd.DataFrame({'solrad': 300.0, 'Tout': 4.0, 'occ': 12.0, 'dpos': 0.0, 'q': -800.0},
                       index=t)
    ydf, xdf = model.simulate(udf, [294.0])
    expected = r1c1_closed_form(t, 294.0, 300.0, 4.0, 12.0, -800.0)
    np.testing.assert_allclose(xdf['T'].to_numpy(), expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ydf['T'].to_numpy(), expected - KELVIN, atol=1e-9)
    np.testing.assert_allclose(ydf['Qr'].to_numpy(), -800.0 * t, rtol=1e-12)


def test_r1c1_ventilation_term_matches_ode():
    """With dpos > 0 the exact solution still satisfies C dT/dt = RHS (checked by RK4)."""
    model = R1C1Model()
    u = np.array([[100.0, 2.0, 5.0, 40.0, 1500.0]])
    T, h = 295.0, 1.0
    for _ in range(3600):
        k1 = model.derivative(np.array([T]), u)[0]
        k2 = model.derivative(np.array([T + h / 2 * k1]), u)[0]
        k3 = model.derivative(np.array([T + h / 2 * k2]), u)[0]
        k4 = model.derivative(np.array([T + h * k3]), u)[0]
        T += h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    x_end, _ = model.simulate_intervals(np.array([[295.0]]), u, 3600.0)
    assert x_end[0, 0] == pytest.approx(T, abs=1e-9)


def test_batch_path_equals_simulate():
    model = R1C1Model()
    rng = np.random.default_rng(1)
    u = np.column_stack([rng.uniform(0, 500, 6), rng.uniform(-5, 15, 6), rng.uniform(0, 30, 6),
                         rng.uniform(0, 100, 6), rng.uniform(-2000, 2000, 6)])
    x = rng.uniform(290, 300, (6, 1))
    x_end, y_end = model.simulate_intervals(x, u, 3600.0)
    generic_x, generic_y = Model.simulate_intervals(model, x, u, 3600.0)
    np.testing.assert_array_equal(x_end, generic_x)
    np.testing.assert_allclose(y_end, generic_y, rtol=1e-15, atol=1e-9)


def test_analytic_jacobians_match_finite_differences():
    model = R1C1Model()
    problem = ShootingProblem(model, ProblemSettings(horizon_steps=3))
    problem._x_scaling = problem._state_scaling_for(np.full((3, 1), 292.0),
                                                    np.full((3, 1), 297.0))
    problem.model_evaluations = 0
    x = np.array([[293.0], [295.0], [297.0]])
    controls = np.array([[500.0], [-1500.0], [0.0]])
    dist = np.array([[100.0, 5.0, 10.0, 0.0], [0.0, 2.0, 0.0, 0.0], [400.0, 9.0, 30.0, 0.0]])
    analytic = problem.evaluate_intervals(x, controls, dist)

    class Opaque(R1C1Model):

        def interval_jacobians(self, *args, **kwargs):
            return None
    problem.model = Opaque()
    fd = problem.evaluate_intervals(x, controls, dist)
    np.testing.assert_allclose(fd.x_end, analytic.x_end)
    np.testing.assert_allclose(fd.dx_dx0, analytic.dx_dx0, rtol=1e-5)
    np.testing.assert_allclose(fd.dx_du, analytic.dx_du, rtol=1e-5)


class LinearScalar(Model):
    """x_{k+1} = a x_k + b u_k per interval: a generic plug-in model with only simulate()."""

    input_names = ('u',)
    state_names = ('x',)
    output_names = ('x',)

    def __init__(self, a=0.9, b=0.5):
        self.a, self.b = a, b

    def simulate(self, udf, x0):
        t, u, x0 = self.check_inputs(udf, x0)
        x = np.empty(t.size)
        x[0] = x0[0]
        for k in range(t.size - 1):
            x[k + 1] = self.a * x[k] + self.b * u[k, 0]
        df = pd.DataFrame({'x': x}, index=udf.index)
        return df, df.copy()


def test_unconstrained_quadratic_matches_least_squares():
    """The problem min sum (x_k - r)^2 + rho sum u_k^2 for linear dynamics has a closed form."""
    a, b, r, rho, x0, n = 0.9, 0.5, 1.0, 0.1, 0.0, 6
    model = LinearScalar(a, b)

    def cost(x_hat, y_hat, u_hat):
        return float(np.sum((y_hat[:, 0] - r) ** 2) + rho * np.sum(u_hat ** 2))

    problem = ShootingProblem(model, ProblemSettings(
        control_names=('u',), control_min=-100.0, control_max=100.0, horizon_steps=n,
        step_s=1.0), cost_function=cost, control_nominal=[1.0])
    res = problem.solve([x0], np.zeros((n, 0)), np.full((n, 1), -np.inf),
                        np.full((n, 1), np.inf), SlsqpSolver(tol=1e-12))
    # x = F x0 + G u  ->  u* = argmin |F x0 + G u - r|^2 + rho |u|^2
    F = np.array([a ** (k + 1) for k in range(n)])
    G = np.array([[a ** (k - j) * b if j <= k else 0.0 for j in range(n)] for k in range(n)])
    u_star = np.linalg.solve(G.T @ G + rho * np.eye(n), G.T @ (r - F * x0))
    assert res.success
    np.testing.assert_allclose(res.controls[:, 0], u_star, atol=1e-5)
    assert res.max_defect < 1e-6


def _ou_like_problem(n=8, soft=False, cost='quadratic'):
    scenario = synthetic_scenario(hours=n + 1, seed=3)
    model = R1C1Model()
    problem = ShootingProblem(model, ProblemSettings(horizon_steps=n, cost=cost),
                              ComfortSettings(comfort='soft' if soft else 'hard'))
    dist = scenario[list(problem.disturbance_names)].to_numpy()[:n].copy()
    lower = scenario['comfort_min'].to_numpy()[1:n + 1, None] + KELVIN
    upper = scenario['comfort_max'].to_numpy()[1:n + 1, None] + KELVIN
    return problem, dist, lower, upper


def test_multiple_shooting_agrees_with_single_shooting():
    problem, dist, lower, upper = _ou_like_problem(n=8)
    x0 = np.array([293.6])  # the band rises to 21 degC at 08:00: preheating needed
    ms = problem.solve(x0, dist, lower, upper, SlsqpSolver())
    assert ms.success and ms.max_defect <= 1e-6
    model = problem.model

    def trajectory(q):
        x, out = x0.copy(), []
        for k in range(problem.n_intervals):
            u = np.concatenate([dist[k], [q[k]]])[None, :]
            x = model.simulate_intervals(x[None, :], u, 3600.0)[0][0]
            out.append(x[0])
        return np.array(out)

    # single shooting on the normalised control q/2000 [-], the states simulated through
    cons = [{'type': 'ineq', 'fun': lambda v: trajectory(2000 * v) - lower[:, 0]},
            {'type': 'ineq', 'fun': lambda v: upper[:, 0] - trajectory(2000 * v)}]
    single = optimize.minimize(lambda v: np.sum(v ** 2), np.zeros(8), method='SLSQP',
                               bounds=[(-1, 1)] * 8, constraints=cons,
                               options={'ftol': 1e-12, 'maxiter': 500})
    assert single.success, single.message
    np.testing.assert_allclose(ms.controls[:, 0], 2000 * single.x, atol=1.0)  # [W]
    assert ms.fun == pytest.approx(single.fun, rel=1e-5)


def test_unreachable_band_rides_through_with_max_cooling():
    problem, dist, lower, upper = _ou_like_problem(n=6)
    dist[:, 0] = 600.0  # strong sun
    dist[:, 2] = 60.0   # a crowded room: gains far beyond 2 kW of cooling
    res = problem.solve([297.0], dist, lower, upper, SlsqpSolver())
    assert res.relaxed, 'the band is unreachable: bounds must be reported relaxed'
    assert np.all(np.isfinite(res.controls))
    np.testing.assert_allclose(res.controls[:, 0], -2000.0, atol=0.1)  # [W]
    assert res.max_defect <= 1e-6
    # the plan cannot be beaten on violation: max cooling is the least-violating plan
    assert np.all(res.states[1:, 0] >= upper[:, 0] - 1e-9)


def test_unreachable_band_success_is_honest_when_solver_stops_early():
    problem, dist, lower, upper = _ou_like_problem(n=6)
    dist[:, 2] = 60.0
    res = problem.solve([297.0], dist, lower, upper, SlsqpSolver(max_iter=1))
    assert not res.success
    assert np.all(np.isfinite(res.controls))
    assert np.all(np.abs(res.controls) <= 2000.0)


def test_converged_least_violation_plan_is_the_least_cost_plan_within_its_violation():
    """
    A converged least-violation plan of IPOPT is kept: the second phase would return it again.

    The band is out of reach at hour 3 only (below the full-cooling envelope), free after: the
    plan cools fully until then and spends nothing after. A cold hard solve of least cost
    within the bounds relaxed to that plan's trajectory (the skipped second phase, from
    nothing of the first) gives the same heat rates to 1e-6 of the nominal and the same cost;
    SLSQP, which certifies no KKT point, still runs the second phase.
    """
    pytest.importorskip('cyipopt', reason='needs cyipopt-wheels')
    problem, dist, lower, upper = _ou_like_problem(n=8)
    x0 = np.array([296.0])
    low, _ = problem.reachable_envelope(x0, dist)
    upper[2] = low[2] - 0.3  # [K] below what full cooling reaches at the end of hour 3
    ipopt = make_solver('ipopt')
    assert ipopt.certifies_kkt and not SlsqpSolver().certifies_kkt
    kept = problem.solve(x0, dist, lower, upper, ipopt)
    assert kept.success and kept.relaxed
    assert kept.slacks[2, 0] == pytest.approx(0.3, abs=1e-6)  # the least violation [K]
    assert np.all(np.delete(kept.slacks[:, 0], 2) <= 1e-6)
    reached = kept.simulated_states[1:]
    cold = problem.solve(x0, dist, np.minimum(lower, reached), np.maximum(upper, reached),
                         ipopt, relax=False)
    assert cold.success
    np.testing.assert_allclose(kept.controls, cold.controls, rtol=0.0, atol=2e-3)  # [W]
    assert kept.fun == pytest.approx(cold.fun, rel=1e-6)
    np.testing.assert_allclose(kept.controls[:3, 0], -2000.0, atol=2e-3)
    assert np.abs(kept.controls[3:, 0]).max() < 10.0  # nothing to cool once it is out of reach


def test_soft_bounds_trade_energy_for_comfort():
    problem, dist, lower, upper = _ou_like_problem(n=8, soft=True)
    results = {}
    for penalty in (1.0, 1e4):
        problem.soft_penalty = penalty
        res = problem.solve([290.0], dist, lower, upper, SlsqpSolver())
        assert res.success and res.max_defect <= 1e-6
        results[penalty] = (np.sum(np.abs(res.controls)), np.sum(res.slacks))
    assert results[1e4][0] > results[1.0][0]  # more energy ...
    assert results[1e4][1] < results[1.0][1]  # ... for less violation


def test_energy_cost_spends_less_energy_than_quadratic():
    energies = {}
    for cost in ('quadratic', 'energy'):
        problem, dist, lower, upper = _ou_like_problem(n=8, cost=cost)
        res = problem.solve([293.6], dist, lower, upper, SlsqpSolver())
        assert res.success
        assert np.all(res.states[1:, 0] >= lower[:, 0] - 1e-6)
        energies[cost] = np.sum(np.abs(res.controls))
    assert energies['energy'] < energies['quadratic'] * 0.999


class _RecordingSlsqp(SlsqpSolver):
    """SLSQP that keeps every NLP it solves, with its start point, and its results."""

    def __init__(self, **options):
        super().__init__(**options)
        self.solved = []

    def solve(self, nlp, z0, deadline=None):
        res = super().solve(nlp, z0, deadline)
        self.solved.append((nlp, np.array(z0, dtype=float), res))
        return res


@pytest.mark.parametrize('soft', [False, True])
@pytest.mark.parametrize('x0', [293.6, 297.0])
def test_slsqp_driver_takes_scipys_iterates(soft, x0):
    """
    The SLSQP driver (:mod:`mshoot_core.slsqp`) is ``scipy.optimize.minimize(method='SLSQP')``.

    Hard and soft bounds, a reachable band (x0 = 293.6 K) and one that needs the least-violation
    phase (297 K in a crowded room): the same iterates to the last bit (x, nit, nfev,
    status, message).
    """
    problem, dist, lower, upper = _ou_like_problem(n=6, soft=soft)
    dist[:, 2] = 60.0 if x0 > 295 else dist[:, 2]
    solver = _RecordingSlsqp(max_iter=100, tol=1e-10)
    problem.solve([x0], dist, lower, upper, solver)
    assert solver.solved and (soft or x0 < 295 or len(solver.solved) == 2)
    for nlp, z0, ours in solver.solved:
        constraints = [{'type': 'eq', 'fun': nlp.eq_fun, 'jac': nlp.eq_jac.dense}]
        if nlp.ineq_fun is not None:
            constraints.append({'type': 'ineq', 'fun': nlp.ineq_fun, 'jac': nlp.ineq_jac.dense})
        scipys = optimize.minimize(nlp.fun, np.clip(z0, nlp.lb, nlp.ub), jac=nlp.grad,
                                   bounds=optimize.Bounds(nlp.lb, nlp.ub),
                                   constraints=constraints, method='SLSQP',
                                   options={'maxiter': 100, 'ftol': 1e-10})
        np.testing.assert_array_equal(ours.x, scipys.x)
        assert (ours.nit, ours.nfev, ours.njev, ours.status, ours.message, ours.success) == (
            scipys.nit, scipys.nfev, scipys.njev, scipys.status, scipys.message, scipys.success)
        assert ours.fun == scipys.fun


def test_slsqp_without_a_core_it_can_drive_uses_scipys_minimize(monkeypatch):
    """With a SciPy whose SLSQP core the driver does not follow, SciPy's minimize: one plan."""
    from mshoot_core import slsqp
    problem, dist, lower, upper = _ou_like_problem(n=6)
    driven = problem.solve([293.6], dist, lower, upper, SlsqpSolver())
    monkeypatch.setattr(slsqp, '_core', False)  # as core() leaves it for another SciPy
    assert slsqp.core() is None
    fallback = problem.solve([293.6], dist, lower, upper, SlsqpSolver())
    np.testing.assert_array_equal(driven.x, fallback.x)
    assert (driven.nit, driven.nfev) == (fallback.nit, fallback.nfev)


def test_slsqp_driver_stops_at_its_deadline_as_scipy_reports_a_callback_stop():
    problem, dist, lower, upper = _ou_like_problem(n=6)
    res = problem.solve([293.6], dist, lower, upper, SlsqpSolver(), deadline=0.0)
    assert res.budget_exceeded and not res.success and res.nit <= 1


def test_slsqp_core_is_loaded_with_its_solver_before_the_blas_pools_are_limited():
    """
    Building the SLSQP solver loads its core and the OpenBLAS it links.

    The MPC limits the BLAS thread pools loaded when it first solves: a pool loaded later,
    by the first solve, would keep its default threads and round the core's BLAS sums
    differently (a ROS run and the core loop then differ by ~1e-7 K).
    """
    import subprocess
    import sys
    probe = ('import sys\n'
             'from mshoot_core.solvers import SlsqpSolver\n'
             'before = "scipy.optimize._slsqplib" in sys.modules\n'
             'SlsqpSolver()\n'
             'print(before, "scipy.optimize._slsqplib" in sys.modules)\n')
    done = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ['False', 'True']


def test_nlp_index_named_views():
    idx = NlpIndex(3, 2, 1, soft=True)
    z = np.arange(idx.size, dtype=float)
    assert idx.u(z).shape == (3, 2) and idx.x(z).shape == (3, 1) and idx.s(z).shape == (3, 1)
    z2 = idx.pack(idx.u(z), idx.x(z), idx.s(z))
    np.testing.assert_array_equal(z, z2)


def test_controls_must_be_model_inputs():
    with pytest.raises(ValueError, match='controls must be model inputs'):
        ShootingProblem(R1C1Model(), ProblemSettings(control_names=('power',)))


def test_bad_settings_are_reported_all_at_once():
    with pytest.raises(SettingsError) as info:
        MPC(R1C1Model(), control_min=10.0, control_max=-10.0, horizon_steps=0,
            cost='cubic', soft_penalty=-1.0)
    problems = ' | '.join(info.value.problems)
    for expected in ('horizon_steps must be in [1, 1000], got 0', 'cost must be one of',
                     'soft_penalty must be in'):
        assert expected in problems
    assert len(info.value.problems) == 3  # the bounds rule waits until every field is valid
    with pytest.raises(SettingsError, match='control_min must be < control_max'):
        MpcSettings.from_flat(control_min=10.0, control_max=-10.0)
    with pytest.raises(SettingsError, match=r"unknown setting\(s\) \['horizon'\]"):
        MpcSettings.from_flat(horizon=3)


def test_unknown_solver_rejected():
    with pytest.raises(ValueError, match='choose one of'):
        make_solver('newton')


def test_forecast_window_pads_with_last_row():
    s = synthetic_scenario(hours=5)
    w = forecast_window(s, 3, 4)
    assert len(w) == 5
    np.testing.assert_array_equal(w['Tout'].to_numpy()[1:], s['Tout'].to_numpy()[[4, 4, 4, 4]])
    assert w.index[0] == s.index[3]


@pytest.mark.parametrize('labelled', [False, True])
def test_forecast_window_is_the_scenario_rows_with_their_times(labelled):
    """The rows (the last repeated), times on the step grid, the attrs; a text column kept."""
    s = synthetic_scenario(hours=7)
    if labelled:
        s['label'] = [f'row {k}' for k in range(len(s))]
    w = forecast_window(s, 5, 4)
    last = len(s) - 1
    expected = s.iloc[[min(k, last) for k in range(5, 10)]].copy()
    expected.index = pd.Index(s.index[5] + 3600.0 * np.arange(5), name=s.index.name)
    pd.testing.assert_frame_equal(w, expected)
    assert w.attrs == s.attrs and w.attrs
    w.iloc[0, 0] = -1.0  # a copy: the scenario is not changed through it
    assert s.iloc[5, 0] != -1.0


def test_mpc_rejects_bad_forecast():
    mpc = MPC(R1C1Model(), horizon_steps=3)
    s = synthetic_scenario(hours=10)
    with pytest.raises(ValueError, match='rows'):
        mpc.solve([293.0], 0.0, s.iloc[:3])
    bad = s.iloc[:4].copy()
    bad.loc[bad.index[1], 'comfort_min'] = 30.0
    with pytest.raises(ValueError, match='exceeds'):
        mpc.solve([293.0], 0.0, bad)
    bad = s.iloc[:4].copy()
    bad.loc[bad.index[2], 'Tout'] = np.nan
    with pytest.raises(ValueError, match='non-finite'):
        mpc.solve([293.0], 0.0, bad)
    with pytest.raises(ValueError, match=r"lacks columns \['occ'\]"):
        mpc.solve([293.0], 0.0, s.iloc[:4].drop(columns='occ'))
    with pytest.raises(TypeError, match='DataFrame'):
        mpc.solve([293.0], 0.0, s.iloc[:4].to_dict())


def test_mpc_reads_the_forecast_columns_it_needs_only():
    """Columns the MPC does not use may hold anything, in any order: the plan is the same."""
    s = synthetic_scenario(hours=10)
    window = forecast_window(s, 6, 3)
    other = window[window.columns[::-1]].assign(note='a label', Tout_text=window['Tout'].map(str))
    plans = [MPC(R1C1Model(), horizon_steps=3).solve([293.6], window.index[0], w).controls
             for w in (window, other)]
    np.testing.assert_array_equal(plans[0], plans[1])


def test_kpis_against_hand_computation():
    q = np.array([1000.0, -500.0, 0.0])
    e = energy_kwh(q, 3600.0)
    assert e == {'energy_kwh': 1.5, 'heating_kwh': 1.0, 'cooling_kwh': 0.5}
    t = np.arange(0, 7201, 60.0)
    temp = np.where(t < 3600, 23.0, 20.0)  # 1 K above 22 for an hour, then 1 K below 21
    fine = pd.DataFrame({'y_T': temp, 'comfort_min': 21.0, 'comfort_max': 22.0}, index=t)
    d = discomfort_kh(fine)
    assert d['discomfort_kh'] == pytest.approx(2.0, abs=1 / 60 + 1e-9)
    assert d['discomfort_kh_hourly'] == pytest.approx(3.0)  # samples at 0 h, 1 h and 2 h


def test_closed_loop_warm_start_and_records():
    s = synthetic_scenario(hours=13, seed=2)
    mpc = MPC(R1C1Model(), horizon_steps=4)
    em = Emulator(R1C1Model(), s, [293.15])
    result = run_closed_loop(mpc, em, log_every=0)
    assert len(result.steps) == 12 and len(result.plans) == 12
    assert result.steps['success'].all()
    # control model == emulation model: prediction is exact
    np.testing.assert_allclose(result.steps['T_predicted'], result.steps['T_end'], atol=1e-6)
    assert len(result.fine) == 12 * 60 + 1
    kpis = closed_loop_kpis(result.steps, result.fine, 3600.0, result.wall_s)
    assert kpis['steps'] == 12 and kpis['solver_failures'] == 0


def test_closed_loop_progress_and_budget():
    """Progress sees every step's records as they accrue; a spent budget ends the run early."""
    s = synthetic_scenario(hours=7, seed=3)
    seen = []

    def progress(rows, fines):
        seen.append((len(rows), len(fines), rows[-1]['time_s']))

    result = run_closed_loop(MPC(R1C1Model(), horizon_steps=3), Emulator(R1C1Model(), s, [293.15]),
                             progress=progress, log_every=0)
    assert [n for n, _, _ in seen] == list(range(1, 7)) and all(n == m for n, m, _ in seen)
    assert [t for _, _, t in seen] == list(result.steps.index)
    short = run_closed_loop(MPC(R1C1Model(), horizon_steps=3), Emulator(R1C1Model(), s, [293.15]),
                            log_every=0, budget_s=0.0)
    assert len(short.steps) == 1 and len(short.fine) == 61  # the first step always runs
    np.testing.assert_allclose(short.steps['T_end'], result.steps['T_end'].iloc[:1])


def test_solve_runs_with_one_blas_thread_and_restores_the_pools(monkeypatch):
    """During a solve the BLAS pools have the MPC's limit; afterwards their own size again."""
    from threadpoolctl import threadpool_info

    from mshoot_core import shooting
    blas = [p for p in threadpool_info() if p['user_api'] == 'blas']
    if not blas:
        pytest.skip('no BLAS thread pool loaded (numpy/scipy without OpenBLAS or MKL)')
    before = [p['num_threads'] for p in blas]
    seen = []
    original = shooting.ShootingProblem.solve

    def spy(self, *args, **kwargs):
        seen.append({p['num_threads'] for p in threadpool_info() if p['user_api'] == 'blas'})
        return original(self, *args, **kwargs)

    monkeypatch.setattr(shooting.ShootingProblem, 'solve', spy)
    s = synthetic_scenario(hours=4)
    MPC(R1C1Model(), horizon_steps=3).solve([294.0], 0.0, forecast_window(s, 0, 3))
    MPC(R1C1Model(), horizon_steps=3, blas_threads=0).solve([294.0], 0.0,
                                                            forecast_window(s, 0, 3))
    assert seen[0] == {1} and seen[1] == set(before)
    assert [p['num_threads'] for p in threadpool_info() if p['user_api'] == 'blas'] == before
    with pytest.raises(ValueError, match='blas_threads'):
        MPC(R1C1Model(), blas_threads=-1)


def test_write_outputs_writes_the_run_files(tmp_path):
    scenario = synthetic_scenario(hours=7)
    result = run_closed_loop(MPC(R1C1Model(), horizon_steps=3),
                             Emulator(R1C1Model(), scenario, [20.0 + KELVIN]), log_every=0)
    kpis = closed_loop_kpis(result.steps, result.fine, 3600.0, result.wall_s)
    write_outputs(tmp_path / 'run', result, dict(kpis, note='synthetic'), 'a title')
    assert json.loads((tmp_path / 'run' / 'kpis.json').read_text()) == pytest.approx(
        dict(kpis, note='synthetic'))
    traj = pd.read_csv(tmp_path / 'run' / 'trajectories.csv', index_col='time_s')
    np.testing.assert_allclose(traj['y_T'].to_numpy(), result.fine['y_T'].to_numpy())
    steps = pd.read_csv(tmp_path / 'run' / 'steps.csv', index_col='time_s')
    np.testing.assert_allclose(steps['q'].to_numpy(), result.steps['q'].to_numpy())
    assert (tmp_path / 'run' / 'plot.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def _small_run():
    scenario = synthetic_scenario(hours=7)
    result = run_closed_loop(MPC(R1C1Model(), horizon_steps=3),
                             Emulator(R1C1Model(), scenario, [20.0 + KELVIN]), log_every=0)
    return result, closed_loop_kpis(result.steps, result.fine, 3600.0, result.wall_s)


def test_write_csv_writes_pandas_bytes(tmp_path):
    """The fast writer of float frames writes what ``to_csv`` writes; other frames go to it."""
    from mshoot_core.outputs import write_csv
    rng = np.random.default_rng(3)
    values = rng.normal(size=(400, 5)) * 10.0 ** rng.integers(-20, 20, size=(400, 5))
    values[0] = [0.0, -0.0, np.inf, -np.inf, np.nan]
    values[1] = [1e16, 1e-5, 1e-4, 5e-324, 0.1]
    frame = pd.DataFrame(values, columns=['x_T', 'y_T', 'y_Qr', 'comfort_min', 'q'],
                         index=pd.Index(np.arange(400) * 60.0, name='time_s'))
    odd = frame.rename(columns={'q': 'q, heat'}).assign(ok=True)
    # repeated values (each formatted once), signed zeros and NaNs in one column, and a
    # column equal to an earlier one (its fields reused) or equal but for a zero's sign
    steps = np.repeat(rng.normal(size=40), 10)
    steps[:30] = np.tile([0.0, -0.0, np.nan], 10)
    repeats = frame.assign(q=steps, T=frame['x_T'], u=frame['x_T'].replace(0.0, -0.0))
    for table in (frame, odd, frame.astype({'q': 'float32'}), repeats, repeats.iloc[:0]):
        write_csv(table, tmp_path / 'ours.csv', index_label='time_s')
        table.to_csv(tmp_path / 'pandas.csv', index_label='time_s')
        assert (tmp_path / 'ours.csv').read_bytes() == (tmp_path / 'pandas.csv').read_bytes()


def test_plot_worker_draws_the_figure_of_this_process(tmp_path):
    """
    The worker process writes the PNG this process would, pixel for pixel.

    The worker has its own interpreter; matplotlib is imported while the run computes.
    """
    import matplotlib.image
    result, kpis = _small_run()
    with PlotWorker() as plotter:
        write_outputs(tmp_path / 'worker', result, kpis, 'a title', plotter)
    write_outputs(tmp_path / 'here', result, kpis, 'a title')
    worker, here = (matplotlib.image.imread(tmp_path / name / 'plot.png')
                    for name in ('worker', 'here'))
    assert worker.shape == here.shape == (600, 1000, 4)
    np.testing.assert_array_equal(worker, here)
    assert len(np.unique(here.reshape(-1, 4), axis=0)) > 20  # a drawn figure, not a blank


def test_figure_png_is_what_matplotlibs_writer_gives(tmp_path):
    """Our PNG writer: the pixels, mode, resolution and text of ``savefig``'s PNG."""
    from PIL import Image
    result, _ = _small_run()
    series = plotting.closed_loop_series(result.fine, result.steps)
    ours = plotting.draw_closed_loop(series, tmp_path / 'ours.png', 'a title\nline two')
    figure = plotting._figure()
    plotting._draw_data(figure, series, 'a title\nline two')
    figure[0].savefig(tmp_path / 'matplotlib.png', dpi=plotting.DPI)
    with Image.open(ours) as mine, Image.open(tmp_path / 'matplotlib.png') as theirs:
        assert mine.mode == theirs.mode == 'RGBA'
        assert mine.info == theirs.info  # Software, dpi
        np.testing.assert_array_equal(np.asarray(mine), np.asarray(theirs))
        assert len(np.unique(np.asarray(mine).reshape(-1, 4), axis=0)) > 20


def _extremes(series):
    """Return the (lowest, highest) of a figure's series, as FigurePreview sends them."""
    extremes = {name: (float(series[name].min()), float(series[name].max()))
                for name in ('hours', 'temperature', 'step_hours', 'q_kw')}
    extremes['band'] = (float(series['comfort_min'].min()), float(series['comfort_max'].max()))
    return extremes


def test_figure_drawn_on_a_background_drawn_ahead_has_the_pixels_of_a_whole_draw(tmp_path):
    """
    The data drawn on a background drawn for their extremes: the figure drawn whole.

    Also when the background was drawn for other limits (it is not used then), or for limits
    a millionth of a span off (used: its limits).
    """
    from PIL import Image
    result, _ = _small_run()
    series = plotting.closed_loop_series(result.fine, result.steps)
    whole = plotting.draw_closed_loop(series, tmp_path / 'whole.png', 'a title')
    exact = _extremes(series)
    other = dict(exact, q_kw=(exact['q_kw'][0] - 0.5, exact['q_kw'][1]))
    span = exact['q_kw'][1] - exact['q_kw'][0]
    close = dict(exact, q_kw=(exact['q_kw'][0] - 1e-9 * span, exact['q_kw'][1]))
    pixels = {}
    for name, extremes in (('exact', exact), ('other', other), ('close', close)):
        figure = plotting._figure()
        plotting._rehearse(figure)
        background = plotting._background(figure, extremes)
        assert plotting._background(figure, extremes, background) is background  # not redrawn
        draws = []
        canvas_draw = figure[0].canvas.draw
        figure[0].canvas.draw = lambda: (draws.append(1), canvas_draw())
        plotting._finish(figure, series, tmp_path / f'{name}.png', 'a title', background)
        assert len(draws) == (1 if name == 'other' else 0), name  # the data alone on it
        with Image.open(tmp_path / f'{name}.png') as image:
            pixels[name] = np.asarray(image)
    with Image.open(whole) as image:
        for name, drawn in pixels.items():
            np.testing.assert_array_equal(drawn, np.asarray(image), err_msg=name)


def test_plot_worker_with_previews_draws_the_figure_of_this_process(tmp_path):
    """A run's previews (FigurePreview) reach the worker; its PNG is the one drawn here."""
    import matplotlib.image
    scenario = synthetic_scenario(hours=7)
    sent = []
    with PlotWorker() as plotter:
        preview = plotting.FigurePreview(plotter, scenario, len(scenario) - 1, 3600.0, lead=4)
        original = plotter.preview
        plotter.preview = lambda extremes: (sent.append(extremes), original(extremes))
        result = run_closed_loop(MPC(R1C1Model(), horizon_steps=3),
                                 Emulator(R1C1Model(), scenario, [20.0 + KELVIN]),
                                 log_every=0, progress=preview)
        kpis = closed_loop_kpis(result.steps, result.fine, 3600.0, result.wall_s)
        write_outputs(tmp_path / 'worker', result, kpis, 'a title', plotter)
    write_outputs(tmp_path / 'here', result, kpis, 'a title')
    worker, here = (matplotlib.image.imread(tmp_path / name / 'plot.png')
                    for name in ('worker', 'here'))
    np.testing.assert_array_equal(worker, here)
    # from 4 steps before the end, while new; the time axes and the band known ahead
    assert 1 <= len(sent) <= 4
    final = _extremes(plotting.closed_loop_series(result.fine, result.steps))
    for name in ('hours', 'step_hours', 'band'):
        assert sent[0][name] == final[name], name
    for name in ('temperature', 'q_kw'):
        assert final[name][0] <= sent[-1][name][0] <= sent[-1][name][1] <= final[name][1]


def test_plot_worker_runs_optimised_only_where_its_bytecode_can_be(monkeypatch):
    """
    -OO where matplotlib's bytecode of that level is there or can be written; else not.

    (Without it, every worker would compile matplotlib anew.) The setup prepares it:
    after :func:`plotting.prepare_worker` it is there.
    """
    import importlib.util
    spec = importlib.util.find_spec('matplotlib')
    cached = importlib.util.cache_from_source(spec.origin, optimization=2)
    assert plotting.prepare_worker() == 0
    command = plotting.worker_command()
    assert command[:4] == [sys.executable, '-I', '-S', '-OO']
    assert command[4] == str(pathlib.Path(plotting.__file__).resolve())
    assert str(pathlib.Path(spec.origin).parent.parent) in command[5:]
    if os.access(os.path.dirname(cached), os.W_OK):
        assert os.path.exists(cached)
    real_exists = os.path.exists
    monkeypatch.setattr(plotting.os.path, 'exists',
                        lambda path: path != cached and real_exists(path))
    monkeypatch.setattr(plotting.os, 'access', lambda path, mode: False)
    assert '-OO' not in plotting.worker_command()
    monkeypatch.setattr(plotting.os, 'access', lambda path, mode: True)  # written by its first
    assert '-OO' in plotting.worker_command()


def test_plot_worker_that_cannot_run_still_gives_the_figure(tmp_path, monkeypatch, caplog):
    result, kpis = _small_run()
    monkeypatch.setattr(plotting.sys, 'executable', str(tmp_path / 'no-python'))
    with PlotWorker() as plotter:  # the interpreter does not exist: not started
        write_outputs(tmp_path / 'run', result, kpis, 'a title', plotter)
    assert (tmp_path / 'run' / 'plot.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 'drawn in this process' in caplog.text
    broken = tmp_path / 'broken-python'
    broken.write_text('#!/bin/sh\necho "no figure today" >&2\nexit 3\n')
    broken.chmod(0o755)
    monkeypatch.setattr(plotting.sys, 'executable', str(broken))
    caplog.clear()
    with PlotWorker() as plotter:  # starts, then fails: the figure is drawn here
        path = plotter.plot(result.fine, result.steps, tmp_path / 'again' / 'plot.png', 'x')
    assert path.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 'exit code 3: no figure today' in caplog.text


def test_emulator_schedule_within_the_step():
    """A plant takes pieces within the step (on the fine grid); other models refuse them."""
    from mshoot_core.models.card import build_model, builtin_card, load_card
    scenario = synthetic_scenario(hours=3, seed=4)
    with pytest.raises(ValueError, match='plant'):
        Emulator(R1C1Model(), scenario, [293.15]).advance(
            [0.0], [(0.0, [0.0]), (1800.0, [500.0])])
    card = load_card(builtin_card('r1c1_fmu_cs'))

    def emulator():
        return Emulator(build_model(card, 'emulator'), scenario, [293.15])

    split, held_on, held_off = emulator(), emulator(), emulator()
    record = split.advance([0.0], [(0.0, [0.0]), (1800.0, [1000.0])])
    assert list(record.fine['q'].iloc[[0, 29, 30, 60]]) == [0.0, 0.0, 1000.0, 1000.0]
    on, off = held_on.advance([1000.0]), held_off.advance([0.0])
    # half a step of heat: between none and a whole step of it
    assert off.x_end[0] < record.x_end[0] < on.x_end[0]
    # the first half of the split step is the unheated one, to the sample
    np.testing.assert_allclose(record.fine['x_T'].iloc[:31], off.fine['x_T'].iloc[:31],
                               rtol=1e-12)
    for bad in ([(60.0, [0.0])], [(0.0, [0.0]), (90.0, [1.0])], [(0.0, [0.0]), (3600.0, [1.0])]):
        with pytest.raises(ValueError, match='offsets'):
            emulator().advance([0.0], bad)
