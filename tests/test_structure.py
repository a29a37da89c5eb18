"""Speed paths: naive vs fast agreement, grouped finite differences, sparse solvers, zones."""
import dataclasses
import os

from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models import R1C1Model
from mshoot_core.models.base import Model
from mshoot_core.models.fmi import r1c1_fmi_model
from mshoot_core.models.multizone import multizone_mpc_options, MultiZoneModel
from mshoot_core.models.network import NetworkModel
from mshoot_core.mpc import MPC
from mshoot_core.scenario import forecast_window, reference_scenario, synthetic_scenario
from mshoot_core.sensitivities import column_groups, finite_difference_jacobians
from mshoot_core.shooting import _band_jacobian, ContinuityStructure, NlpIndex
from mshoot_core.solvers import SlsqpSolver, SparseJacobian
import numpy as np
import pytest


@pytest.mark.parametrize('horizon', [2, 4, 10])
def test_fast_and_naive_reach_the_same_optimum(ou44_csv, horizon):
    scenario = reference_scenario('ou44', ou44_csv, hours=12)
    objectives = {}
    for mode in ('fast', 'naive'):
        mpc = MPC(R1C1Model(), horizon_steps=horizon, mode=mode)
        x = np.array([293.15])
        values = []
        for k in (0, 8, 9):  # night, then the morning with the band rising to 21 degC
            result = mpc.solve(x if k == 0 else [294.0], scenario.index[k],
                               forecast_window(scenario, k, horizon))
            values.append(result.fun)
        objectives[mode] = np.array(values)
    scale = np.maximum(np.abs(objectives['fast']), 1.0)  # objective of one full-power hour
    np.testing.assert_array_less(np.abs(objectives['naive'] - objectives['fast']) / scale,
                                 1e-6)


def test_naive_mode_spends_far_more_model_evaluations():
    s = synthetic_scenario(hours=12)
    evaluations = {}
    for mode in ('fast', 'naive'):
        mpc = MPC(R1C1Model(), horizon_steps=4, mode=mode)
        evaluations[mode] = mpc.solve([294.0], 0.0, forecast_window(s, 0, 4)).model_evaluations
    assert evaluations['naive'] > 5 * evaluations['fast']


def test_column_groups_cover_each_column_once_without_row_clashes():
    rng = np.random.default_rng(0)
    pattern = rng.random((12, 9)) < 0.25
    groups = column_groups(pattern)
    assert sorted(c for g in groups for c in g) == list(range(9))
    for group in groups:
        assert np.all(pattern[:, group].sum(axis=1) <= 1)
    assert len(column_groups(np.eye(50, dtype=bool))) == 1
    assert len(column_groups(np.ones((3, 4), bool))) == 4


def test_grouped_finite_differences_match_analytic_multizone():
    model = MultiZoneModel(20, seed=1)
    rng = np.random.default_rng(2)
    batch = 3
    x = rng.uniform(291, 297, (batch, 20))
    u = np.column_stack([rng.uniform(0, 400, (batch, 1)), rng.uniform(0, 10, (batch, 1)),
                         rng.uniform(0, 20, (batch, 1)), np.zeros((batch, 1)),
                         rng.uniform(-2000, 2000, (batch, 20))])
    wrt = list(range(4, 24))
    analytic = model.interval_jacobians(x, u, 3600.0, wrt)
    grouped, spent = finite_difference_jacobians(
        model, x, u, 3600.0, wrt, np.full(20, 1e-4), np.full(20, 1e-2), np.full(20, 2000.0),
        model.jacobian_sparsity(wrt))
    dense, spent_dense = finite_difference_jacobians(
        model, x, u, 3600.0, wrt, np.full(20, 1e-4), np.full(20, 1e-2), np.full(20, 2000.0))
    for fd in (grouped, dense):
        np.testing.assert_allclose(fd.dx_dx0, analytic.dx_dx0, atol=1e-6)
        np.testing.assert_allclose(fd.dx_du, analytic.dx_du, rtol=1e-5, atol=1e-12)
    assert spent == batch * 3  # base + one state group + one control group
    assert spent_dense == batch * 41  # base + 20 states + 20 controls


# independent nodes beyond the zones: a gain into two nodes, a heat rate with two gains, a
# node without conductance, an output mixing states and one with an input term
INDEPENDENT_NODES = {
    'inputs': {'solrad': 'W/m2', 'Tout': 'degC', 'occ': '1', 'dpos': '%', 'q_0': 'W',
               'q_1': 'W', 'q_2': 'W'},
    'parameters': {'C': 2e6},
    'nodes': {'T_0': {'capacity': 'C'}, 'T_1': {'capacity': '2 * C'},
              'T_2': {'capacity': 'C'}},
    'boundaries': {'outdoor': 'Tout + 273.15', 'supply': 'max(Tout, 16) + 273.15'},
    'conductances': [{'between': ['T_0', 'outdoor'], 'value': 80},
                     {'between': ['T_1', 'outdoor'], 'value': 40},
                     {'between': ['T_0', 'supply'], 'value': 3, 'times': ['dpos']}],
    'gains': [{'node': 'T_0', 'value': 1, 'times': ['q_0']},
              {'node': 'T_1', 'value': 0.5, 'times': ['q_0']},
              {'node': 'T_1', 'value': 2, 'times': ['solrad']},
              {'node': 'T_2', 'value': 1, 'times': ['q_2']},
              {'node': 'T_2', 'value': 1, 'times': ['q_2']},
              {'node': 'T_1', 'value': 1, 'times': ['q_1']}],
    'outputs': {'mean': {'terms': [{'state': 'T_0', 'value': 0.5},
                                   {'state': 'T_2', 'value': 0.5}]},
                'T_1': {'terms': [{'state': 'T_1'}], 'offset': -273.15},
                'E': {'integral': True, 'terms': [{'value': 1, 'times': ['q_1']}]}}}


@pytest.mark.parametrize('build', [lambda: MultiZoneModel(6, seed=4),
                                   lambda: NetworkModel(INDEPENDENT_NODES)])
def test_closed_form_batch_rewrites_its_entries_and_matches_a_fresh_evaluation(build):
    # the optimiser's batch of a network of independent nodes keeps its derivative arrays
    # across calls: every call must give what a fresh interval_jacobians gives (no stale
    # entry from the call before), on a subset of the heat rates in another order and with
    # a shared input too, and its arrays must not be writable
    model = build()
    nx, nu = len(model.state_names), len(model.input_names)
    heat_rates = list(range(4, nu))
    rng = np.random.default_rng(5)
    for wrt in (heat_rates, heat_rates[::-2], [1, 3] + heat_rates[:2]):
        batch = model.interval_batch(3, 3600.0, wrt)
        for _ in range(3):
            x = rng.uniform(291, 297, (3, nx))
            u = np.column_stack([rng.uniform(0, 400, (3, 1)), rng.uniform(0, 20, (3, 1)),
                                 rng.uniform(0, 20, (3, 1)), rng.uniform(0, 50, (3, 1)),
                                 rng.uniform(-2000, 2000, (3, nu - 4))])
            batch.x_start[:] = x
            batch.u[:] = u
            got = batch.jacobians()
            fresh = model.interval_jacobians(x, u, 3600.0, wrt)
            x_end, y_end = model.simulate_intervals(x, u, 3600.0)
            np.testing.assert_array_equal(got.x_end, x_end)
            np.testing.assert_array_equal(got.y_end, y_end)
            for name in ('dx_dx0', 'dx_du', 'dy_dx0', 'dy_du'):
                np.testing.assert_array_equal(getattr(got, name), getattr(fresh, name))
            decay = np.diagonal(got.dx_dx0, axis1=1, axis2=2)
            assert np.count_nonzero(got.dx_dx0) == 3 * nx and (decay > 0).all()
            heated = sum(np.count_nonzero(model._gain_only[c]) for c in wrt if c >= 4)
            shared = np.count_nonzero(got.dx_du[:, :, [j for j, c in enumerate(wrt) if c < 4]])
            assert np.count_nonzero(got.dx_du) == 3 * heated + shared
            with pytest.raises(ValueError):
                got.dx_du[0, 0, 0] = 1.0
            with pytest.raises(ValueError):
                got.dx_dx0[0, 0, 0] = 1.0


def test_a_network_subclass_with_its_own_interval_jacobians_gets_the_batch_that_calls_it():
    # the batch gives what interval_jacobians gives, also where a subclass changes it (a
    # model converting units, a test's slow model): no closed-form batch around it
    class Shifted(NetworkModel):

        def interval_jacobians(self, x_start, u, dt_s, wrt_inputs, t_start_s=None):
            jac = super().interval_jacobians(x_start, u, dt_s, wrt_inputs)
            return dataclasses.replace(jac, x_end=jac.x_end + 1.0)

    model = Shifted(INDEPENDENT_NODES)
    batch = model.interval_batch(2, 3600.0, [4, 6])
    batch.x_start[:] = 293.0
    batch.u[:] = 100.0
    x_end, _ = model.simulate_intervals(batch.x_start, batch.u, 3600.0)
    np.testing.assert_array_equal(batch.jacobians().x_end, x_end + 1.0)


def test_multizone_batch_equals_simulate_and_single_zone_equals_r1c1():
    model = MultiZoneModel(3)
    s = synthetic_scenario(hours=5)
    udf = s[['solrad', 'Tout', 'occ', 'dpos']].copy()
    for i in range(3):
        udf[f'q_{i}'] = [500.0 * (i - 1)] * 5
    ydf, xdf = model.simulate(udf, [293.0, 294.0, 295.0])
    x_end, _ = model.simulate_intervals(xdf.to_numpy()[:-1], udf.to_numpy()[:-1], 3600.0)
    np.testing.assert_array_equal(x_end, xdf.to_numpy()[1:])
    zone = R1C1Model(dataclasses.replace(model.zone_parameters,
                                         Vi=float(model.zone_parameters.Vi[1])))
    zu = udf.to_numpy()[:-1, :5].copy()
    zu[:, 0] *= model.solar_share[1]
    zu[:, 2] *= model.occupancy_share[1]
    zu[:, 4] = udf['q_1'].to_numpy()[:-1]
    x1, _ = zone.simulate_intervals(xdf.to_numpy()[:-1, [1]], zu, 3600.0)
    np.testing.assert_allclose(x1[:, 0], xdf['T_1'].to_numpy()[1:], rtol=0, atol=1e-9)


def test_continuity_structure_is_block_bidiagonal():
    idx = NlpIndex(4, 2, 2)
    pattern = np.array([[1, 0, 1, 0], [0, 1, 0, 1]], bool)
    structure = ContinuityStructure(idx, pattern)
    dx_du = np.zeros((4, 2, 2)) + np.eye(2)
    dx_dx0 = np.zeros((4, 2, 2)) + 2 * np.eye(2)
    jac = structure.matrix(dx_du, dx_dx0, np.ones(2), np.ones(2)).toarray()
    assert jac.shape == (8, 16)
    assert np.count_nonzero(jac) == 4 * 2 + 8 + 3 * 2
    np.testing.assert_array_equal(jac[2:4, 8:10], 2 * np.eye(2))   # d x_1 / d x_0
    np.testing.assert_array_equal(jac[2:4, 10:12], -np.eye(2))
    assert not np.any(jac[4:6, 8:10])                             # nothing two blocks back


def test_sparse_jacobian_gives_the_same_matrix_dense_and_sparse():
    rows, cols = np.array([0, 2, 1, 2]), np.array([3, 0, 1, 2])
    jac = SparseJacobian(rows, cols, (3, 4), lambda z: z[:4] * 10.0)
    z = np.array([1.0, 2.0, 3.0, 4.0])
    expected = np.zeros((3, 4))
    expected[rows, cols] = [10.0, 20.0, 30.0, 40.0]
    np.testing.assert_array_equal(jac.dense(z), expected)
    np.testing.assert_array_equal(jac(z).toarray(), expected)
    with pytest.raises(ValueError, match='one length'):
        SparseJacobian(rows, cols[:3], (3, 4), lambda z: z)


def test_soft_band_jacobian_is_the_derivative_of_the_band_rows():
    """
    Soft band rows: +-1 on the state, +1 on its slack, one row each, in that order.

    x - lower + s >= 0 for finite lower bounds, upper - x + s >= 0 for finite upper ones.
    """
    idx = NlpIndex(3, 1, 2, soft=True)
    finite_lo = np.array([True, False, True, True, True, False])
    finite_hi = np.array([True, True, False, True, False, True])
    jac = _band_jacobian(idx, finite_lo, finite_hi).dense(np.zeros(idx.size))
    expected = []
    for finite, sign in ((finite_lo, 1.0), (finite_hi, -1.0)):
        for i in np.flatnonzero(finite):
            row = np.zeros(idx.size)
            row[idx.x_slice.start + i] = sign
            row[idx.s_slice.start + i] = 1.0
            expected.append(row)
    np.testing.assert_array_equal(jac, np.array(expected))


def test_reachable_envelope_is_the_extreme_trajectories():
    """Both extreme trajectories, simulated side by side, equal each simulated alone."""
    model = MultiZoneModel(3, seed=2)
    mpc = MPC(model, horizon_steps=5, **multizone_mpc_options(model, 'slsqp'))
    problem = mpc.problem
    disturbances = synthetic_scenario(hours=6)[list(problem.disturbance_names)].to_numpy()[:5]
    x0 = np.array([290.0, 295.0, 300.0])
    low, high = problem.reachable_envelope(x0, disturbances)
    sides = []
    for side in (0, 1):
        x, ends = x0, []
        for k in range(5):
            u = np.concatenate([disturbances[k], problem.control_bounds[:, side]])[None, :]
            x = model.simulate_intervals(x[None, :], u, 3600.0)[0][0]
            ends.append(x)
        sides.append(np.array(ends))
    np.testing.assert_array_equal(low, np.minimum(*sides))
    np.testing.assert_array_equal(high, np.maximum(*sides))
    assert np.all(sides[1] > sides[0])  # full heating ends warmer than full cooling


@pytest.mark.parametrize('solver', ['ipopt', 'trust-constr'])
def test_sparse_solvers_agree_with_slsqp(solver):
    s = synthetic_scenario(hours=10, seed=4)
    forecast = forecast_window(s, 6, 4)  # morning: preheating for the 08:00 band
    ref = MPC(R1C1Model(), horizon_steps=4).solve([293.6], s.index[6], forecast)
    res = MPC(R1C1Model(), horizon_steps=4, solver=solver).solve([293.6], s.index[6], forecast)
    assert ref.success and res.success, res.message
    np.testing.assert_allclose(res.controls, ref.controls, atol=2.0)  # [W]
    assert res.fun == pytest.approx(ref.fun, rel=1e-4)


def test_multizone_mpc_ipopt_matches_slsqp_and_relaxes_honestly():
    model = MultiZoneModel(4, seed=3)
    s = synthetic_scenario(hours=12)
    forecast = forecast_window(s, 5, 6)
    x0 = np.full(4, 292.9)
    results = {solver: MPC(model, horizon_steps=6, **multizone_mpc_options(model, solver))
               .solve(x0, s.index[5], forecast) for solver in ('slsqp', 'ipopt')}
    for r in results.values():
        assert r.max_defect < 1e-6
        assert np.all(np.abs(r.controls) <= 2000 + 1e-6)
    np.testing.assert_allclose(results['ipopt'].controls, results['slsqp'].controls, atol=5.0)


IPOPT_BANNER_SCRIPT = """
import re, sys
import numpy as np, scipy.sparse
from mshoot_core import solvers
log = sys.argv[1]
solver = solvers.IpoptSolver(options={'output_file': log, 'file_print_level': 5, 'sb': 'no'})
jac = scipy.sparse.coo_array(np.array([[1.0, 1.0, 0.0]]))
nlp = solvers.Nlp(fun=lambda z: float(np.sum((z - 1.0) ** 2)), grad=lambda z: 2 * (z - 1.0),
                  eq_fun=lambda z: np.array([z[0] + z[1] - 1.0]), eq_jac=lambda z: jac,
                  lb=np.full(3, -5.0), ub=np.full(3, 5.0),
                  objective_hessian_diag=lambda z: np.full(3, 2.0))
result = solver.solve(nlp, np.zeros(3))
assert result.success and np.allclose(result.x, [0.5, 0.5, 1.0], atol=1e-7), result
print(solvers.ipopt_library)
"""


@pytest.mark.parametrize('build', ['bundled', 'casadi'])
def test_ipopt_build_is_the_one_chosen(tmp_path, build):
    """MSHOOT_IPOPT_BUILD=casadi runs CasADi's IPOPT (MUMPS >= 5.6, METIS); else cyipopt's own."""
    import re
    import subprocess
    import sys

    if build == 'casadi':
        pytest.importorskip('casadi', reason='MSHOOT_IPOPT_BUILD=casadi needs the casadi wheel '
                            '(make bench-setup)')
    log = tmp_path / 'ipopt.out'
    done = subprocess.run([sys.executable, '-c', IPOPT_BANNER_SCRIPT, str(log)],
                          env=dict(os.environ, MSHOOT_IPOPT_BUILD=build),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    banner = re.search(r'Ipopt version (\d+)\.(\d+)\.(\d+), running with linear solver '
                       r'MUMPS (\d+)\.(\d+)', log.read_text())
    assert banner is not None, log.read_text()[:400]
    mumps = tuple(map(int, banner.groups()[3:]))
    bound = done.stdout.strip().splitlines()[-1]
    if build == 'casadi':
        assert bound.endswith('libipopt.so.3') and mumps >= (5, 6), (bound, banner.group(0))
    else:
        assert bound == 'None' and mumps < (5, 6), (bound, banner.group(0))


CYIPOPT_SCIPY_INTERFACE_SCRIPT = """
import json, sys
import numpy as np
from mshoot_core import solvers
cyipopt = solvers.import_cyipopt()
before = 'scipy.optimize' in sys.modules
problem = cyipopt.Problem  # (a name of the extension: no import)
after_problem = 'scipy.optimize' in sys.modules
result = cyipopt.minimize_ipopt(lambda x: float(np.sum((x - 2.0) ** 2)), np.zeros(2),
                                options={'print_level': 0, 'sb': 'yes'})
import cyipopt as again
print(json.dumps([before, after_problem, 'scipy.optimize' in sys.modules, again is cyipopt,
                  result.x.tolist(), cyipopt.__version__]))
"""


def test_cyipopt_scipy_interface_is_imported_when_used():
    """import_cyipopt leaves out cyipopt's SciPy interface until one of its names is used."""
    import json
    import subprocess
    import sys

    pytest.importorskip('cyipopt', reason='needs cyipopt-wheels')
    done = subprocess.run([sys.executable, '-c', CYIPOPT_SCIPY_INTERFACE_SCRIPT],
                          capture_output=True, text=True, timeout=120, env=dict(os.environ))
    assert done.returncode == 0, done.stderr[-2000:]
    before, after_problem, after, same, x, version = json.loads(done.stdout.splitlines()[-1])
    assert (before, after_problem, after, same) == (False, False, True, True)
    np.testing.assert_allclose(x, [2.0, 2.0], atol=1e-6)
    assert version


def test_ipopt_build_refuses_an_unknown_name(monkeypatch):
    from mshoot_core import solvers
    monkeypatch.setenv('MSHOOT_IPOPT_BUILD', 'fastest')
    with pytest.raises(ValueError, match="MSHOOT_IPOPT_BUILD must be one of.*'fastest'"):
        solvers.ipopt_build()


def test_model_without_sparsity_is_dense():
    assert Model.jacobian_sparsity(R1C1Model(), [4]) is None


def test_model_exchange_and_co_simulation_closed_loops_agree(ou44_csv):
    """
    The R1C1 FMU as Model Exchange and as Co-Simulation: the same KPIs.

    Model Exchange: compiled Runge-Kutta batches with forward sensitivities; Co-Simulation: exact
    steps, finite differences.
    """
    scenario = reference_scenario('ou44', ou44_csv, hours=24)
    kpis = {}
    for fmi_type in ('ModelExchange', 'CoSimulation'):
        with r1c1_fmi_model(fmi_type=fmi_type, tolerance=1e-6) as model:
            mpc = MPC(model, horizon_steps=6)
            result = run_closed_loop(mpc, Emulator(R1C1Model(), scenario, [293.15]),
                                     log_every=0)
            if fmi_type == 'ModelExchange':
                assert model.me_batch_plan() is None and model._me_driver
        kpis[fmi_type] = closed_loop_kpis(result.steps, result.fine, mpc.step_s, result.wall_s)
    me, cs = kpis['ModelExchange'], kpis['CoSimulation']
    assert me['solver_failures'] == cs['solver_failures'] == 0
    assert me['energy_kwh'] > 1.0
    assert me['energy_kwh'] == pytest.approx(cs['energy_kwh'], rel=1e-4)
    assert me['discomfort_kh'] == pytest.approx(cs['discomfort_kh'], rel=1e-3, abs=1e-3)


# -- the band's feasible tube (monotone models) ------------------------------------------------
def test_band_the_envelope_reaches_but_no_plan_keeps_is_infeasible_along_the_tube():
    """
    A band each of whose bounds the envelope reaches but no plan keeps: infeasible.

    Warm by hour 1, then cooler by hour 2 than full cooling gets from there: the hard NLP
    fails on it. The solve goes to the least-violation phase at once, and its plan is the one
    the hard NLP's failure led to, to the last bit, for fewer model evaluations.
    """
    model = R1C1Model()
    problem = MPC(model, horizon_steps=3).problem
    disturbances = synthetic_scenario(hours=4)[list(problem.disturbance_names)].to_numpy()[:3]
    x0 = np.array([293.15])
    low, high = problem.reachable_envelope(x0, disturbances)
    lower, upper = np.full((3, 1), -np.inf), np.full((3, 1), np.inf)
    lower[0] = high[0] - 0.1
    full_cooling = problem._full_inputs(problem.control_bounds[None, :, 0], disturbances[1:2])
    from_warm = model.simulate_intervals(lower[0][None, :], full_cooling, 3600.0)[0][0]
    upper[1] = from_warm - 0.05
    assert low[1] < upper[1] and high[0] > lower[0]  # each bound reachable on its own
    assert not problem.relax_bounds(x0, disturbances, lower, upper)[2]
    assert problem.monotone and problem.infeasible_band(x0, disturbances, lower, upper)
    assert not problem.solve(x0, disturbances, lower, upper, SlsqpSolver(), relax=False).success
    upper[1] = from_warm + 0.05  # now reachable from the warm end: feasible
    assert not problem.infeasible_band(x0, disturbances, lower, upper)
    assert problem.solve(x0, disturbances, lower, upper, SlsqpSolver(), relax=False).success
    upper[1] = from_warm - 0.05
    tube = problem.solve(x0, disturbances, lower, upper, SlsqpSolver())
    problem.monotone = False  # the claim withdrawn: the hard NLP first, its failure, then the same
    hard_first = problem.solve(x0, disturbances, lower, upper, SlsqpSolver())
    assert tube.relaxed and hard_first.relaxed
    for name in ('x', 'controls', 'states', 'slacks', 'outputs'):
        np.testing.assert_array_equal(getattr(tube, name), getattr(hard_first, name), name)
    assert (tube.fun, tube.nit, tube.success) == (hard_first.fun, hard_first.nit,
                                                  hard_first.success)
    assert tube.model_evaluations < hard_first.model_evaluations


@pytest.mark.parametrize('name', ['r1c1', 'r2c2', 'zones'])
def test_tube_calls_infeasible_only_bands_the_hard_nlp_fails_on(name):
    """
    Where the tube calls a band infeasible, the hard NLP fails on it; the plans are unchanged.

    Random bands, narrow and jumping, within the envelope; every solve's plan is the one
    without the model's claim, to the last bit.
    """
    from mshoot_core.models.r2c2 import R2C2Model
    model = {'r1c1': R1C1Model(), 'r2c2': R2C2Model(), 'zones': MultiZoneModel(2, seed=1)}[name]
    n = 4
    options = multizone_mpc_options(model, 'slsqp') if name == 'zones' else {}
    problem = MPC(model, horizon_steps=n, **options).problem
    bounded = [i for i, s in enumerate(model.state_names) if s == 'T' or s.startswith('T_')]
    scenario = synthetic_scenario(hours=24, seed=5)
    rng = np.random.default_rng(7)
    counts = {'infeasible': 0, 'feasible': 0}
    for trial in range(24):
        start = int(rng.integers(0, 24 - n))
        disturbances = scenario[list(problem.disturbance_names)].to_numpy()[start:start + n]
        x0 = rng.uniform(291.0, 296.0, len(model.state_names))
        low, high = problem.reachable_envelope(x0, disturbances)
        # bands within the envelope (each bound reachable on its own), narrow, jumping
        centre = low + rng.uniform(0.0, 1.0, low.shape) * (high - low)
        width = rng.uniform(0.05, 0.8, low.shape)
        lower, upper = (np.full((n, len(model.state_names)), value) for value in (-np.inf, np.inf))
        lower[:, bounded] = (centre - width / 2)[:, bounded]
        upper[:, bounded] = (centre + width / 2)[:, bounded]
        infeasible = problem.infeasible_band(x0, disturbances, lower, upper)
        hard = problem.solve(x0, disturbances, lower, upper, SlsqpSolver(), relax=False)
        if infeasible:
            assert not hard.success, (trial, hard.message)
            counts['infeasible'] += 1
        elif hard.success:
            counts['feasible'] += 1
        problem.monotone = True
        tube = problem.solve(x0, disturbances, lower, upper, SlsqpSolver())
        problem.monotone = False
        hard_first = problem.solve(x0, disturbances, lower, upper, SlsqpSolver())
        problem.monotone = True
        np.testing.assert_array_equal(tube.x, hard_first.x, str(trial))
        assert tube.relaxed == hard_first.relaxed
    assert counts['infeasible'] >= 2 and counts['feasible'] >= 2, counts
