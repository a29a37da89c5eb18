"""
The R1C1 FMU (C source, builder) and the FMI model interface (FmiModel via fmpy).

References are analytic: the R1C1 closed-form response written out here from
the equations of SPEC section 3, and the exact discretisation (matrix
exponential) of the linear two-node R2C2 test FMU.
"""
import copy
import math
import zipfile

import fmpy
from fmpy.fmi2 import FMU2Model, FMU2Slave
from fmpy.validation import validate_fmu
from mshoot_core import fmu_build, fmu_cache
from mshoot_core.models import fmi_me
from mshoot_core.models.base import Model
from mshoot_core.models.fmi import FmiModel, r1c1_fmi_model, R1C1_VARIABLES
from mshoot_core.models.r1c1 import R1C1Model, R1C1Parameters
import numpy as np
import pandas as pd
import pytest
import scipy.linalg

# fmpy's schema validation imports lark, which warns about deprecated stdlib modules.
pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.utils')

HOUR = 3600.0
R1C1_INPUTS = ['solrad', 'Tout', 'occ', 'dpos', 'q']
R2C2_PARAMETERS = {'Cair': 5.0e6, 'Cwall': 5.0e7, 'Raw': 0.002, 'Rwa': 0.01, 'Rwin': 0.04,
                   'fsun': 0.6}


@pytest.fixture(scope='module')
def r1c1_cs(r1c1_fmu):
    with r1c1_fmi_model(fmi_type='CoSimulation', fmu_path=r1c1_fmu) as model:
        yield model


@pytest.fixture(scope='module')
def r1c1_me(r1c1_fmu):
    with r1c1_fmi_model(fmi_type='ModelExchange', tolerance=1e-10, fmu_path=r1c1_fmu) as model:
        yield model


@pytest.fixture(scope='module')
def r2c2(r2c2_fmu):
    with FmiModel(r2c2_fmu, inputs=['Tamb', 'Qhvac', 'Qsun'],
                  states={'Ta': 'air.T', 'Tw': 'wall.T'}, outputs=['Tair', 'Pwin'],
                  parameters=R2C2_PARAMETERS, tolerance=1e-10) as model:
        yield model


def r1c1_closed_form(udf, t0_k, p=None):
    """T [K] at the index of ``udf`` from the SPEC equations, exact per interval."""
    p = p or R1C1Parameters()
    cap = p.tmass * 1.2 * 1005.0 * p.Vi
    res = p.RExt / (3.0 * p.Vi ** (2.0 / 3.0))
    temps = [t0_k]
    times = udf.index.to_numpy(dtype=float)
    for k in range(len(udf) - 1):
        solrad, tout, occ, dpos, q = udf.iloc[k][R1C1_INPUTS]
        occ_w_per_k = p.occheff * occ * 84.0 / 32.0        # occheff*occ*M(T) = a*(325.15 - T)
        vent = 1206.0 / 3600.0 * p.maxVent * dpos / 100.0  # W/K
        g = 1.0 / res + occ_w_per_k + vent
        f = ((tout + 273.15) / res + p.shgc * solrad + occ_w_per_k * 325.15
             + vent * (max(tout, p.Tve) + 273.15) + q)
        t_inf = f / g
        dt = times[k + 1] - times[k]
        temps.append(t_inf + (temps[-1] - t_inf) * math.exp(-g * dt / cap))
    return np.array(temps)


def hourly_inputs(hours, seed, dpos=True):
    rng = np.random.default_rng(seed)
    n = hours + 1
    return pd.DataFrame({'solrad': rng.uniform(0, 400, n), 'Tout': rng.uniform(-5, 30, n),
                         'occ': rng.uniform(0, 30, n),
                         'dpos': rng.uniform(0, 60, n) if dpos else np.zeros(n),
                         'q': rng.uniform(-2000, 2000, n)}, index=np.arange(n) * HOUR)


def r2c2_exact(x0, u, dt, p=R2C2_PARAMETERS):
    """Exact end states and outputs of the linear R2C2 model over one interval."""
    a = np.array([[-(1 / p['Raw'] + 1 / p['Rwin']) / p['Cair'], 1 / (p['Raw'] * p['Cair'])],
                  [1 / (p['Raw'] * p['Cwall']), -(1 / p['Raw'] + 1 / p['Rwa']) / p['Cwall']]])
    b = np.array([[1 / (p['Rwin'] * p['Cair']), 1 / p['Cair'], (1 - p['fsun']) / p['Cair']],
                  [1 / (p['Rwa'] * p['Cwall']), 0.0, p['fsun'] / p['Cwall']]])
    m = np.zeros((5, 5))
    m[:2, :2], m[:2, 2:] = a, b
    e = scipy.linalg.expm(m * dt)
    ad, bd = e[:2, :2], e[:2, 2:]
    x1 = ad @ x0 + bd @ u
    c = np.array([[1.0, 0.0], [1 / p['Rwin'], 0.0]])
    d = np.array([[0.0, 0.0, 0.0], [-1 / p['Rwin'], 0.0, 0.0]])
    return x1, c @ x1 + d @ u, ad, bd, c, d


# -- the FMUs themselves --------------------------------------------------------------------
def test_build_writes_a_valid_fmu_archive(tmp_path):
    path = fmu_build.build_fmu('r1c1', tmp_path)
    assert path == tmp_path / 'R1C1.fmu'
    with zipfile.ZipFile(path) as archive:
        names = set(archive.namelist())
    assert {'modelDescription.xml', 'binaries/linux64/R1C1.so', 'sources/r1c1.c',
            'sources/fmi2Functions.h'} <= names
    assert validate_fmu(str(path)) == []
    md = fmpy.read_model_description(str(path))
    assert md.modelExchange.providesDirectionalDerivative
    assert md.modelExchange.canGetAndSetFMUstate and md.coSimulation.canGetAndSetFMUstate
    start = {v.name: float(v.start) for v in md.modelVariables if v.causality == 'parameter'}
    assert start == pytest.approx(vars(R1C1Parameters()), rel=0, abs=0)


def test_second_fmu_validates(r2c2_fmu):
    assert validate_fmu(str(r2c2_fmu)) == []
    md = fmpy.read_model_description(str(r2c2_fmu))
    assert md.coSimulation is None and not md.modelExchange.canGetAndSetFMUstate


@pytest.mark.parametrize('fmi_type', ['ModelExchange', 'CoSimulation'])
def test_fmpy_simulate_fmu_matches_closed_form(r1c1_fmu, fmi_type):
    inputs = {'solrad': 150.0, 'Tout': 25.0, 'occ': 12.0, 'dpos': 30.0, 'q': -1500.0}
    result = fmpy.simulate_fmu(str(r1c1_fmu), fmi_type=fmi_type, stop_time=6 * HOUR,
                               output_interval=HOUR, relative_tolerance=1e-10,
                               start_values={**inputs, 'heatCapacitor.T': 295.0, 'RExt': 3.0},
                               output=['T', 'Qr'])
    udf = pd.DataFrame([inputs] * 2, index=[0.0, 6 * HOUR])
    expected = r1c1_closed_form(udf, 295.0, R1C1Parameters(RExt=3.0))[-1] - 273.15
    tol = 1e-9 if fmi_type == 'CoSimulation' else 1e-5
    assert result['time'][-1] == pytest.approx(6 * HOUR)
    assert result['T'][-1] == pytest.approx(expected, abs=tol)
    assert result['Qr'][-1] == pytest.approx(-1500.0 * 6 * HOUR, rel=1e-9)


def test_fmu_state_snapshot_and_serialization(r1c1_fmu):
    with r1c1_fmi_model(fmi_type='CoSimulation', fmu_path=r1c1_fmu) as model:
        model.simulate(hourly_inputs(2, seed=5), [296.0])
        fmu = model.fmu
        snapshot = fmu.getFMUstate()
        before = fmu.getReal([20, 22])
        restored = fmu.deSerializeFMUstate(fmu.serializeFMUstate(snapshot))
        fmu.doStep(2 * HOUR, HOUR)
        assert fmu.getReal([20, 22]) != before
        fmu.setFMUstate(restored)
        assert fmu.getReal([20, 22]) == before
        fmu.freeFMUstate(snapshot)
        fmu.freeFMUstate(restored)


def test_cache_dir_from_env_builds_once(tmp_path, monkeypatch):
    monkeypatch.setenv('MSHOOT_FMU_DIR', str(tmp_path))
    calls = []
    real_build = fmu_build.build_fmu
    monkeypatch.setattr(fmu_build, 'build_fmu',
                        lambda name, out: calls.append(name) or real_build(name, out))
    first = fmu_build.ensure_fmu('r1c1')
    second = fmu_build.ensure_fmu('r1c1')
    assert first == second == tmp_path / fmu_cache.source_hash('r1c1') / 'R1C1.fmu'
    assert first.is_file() and calls == ['r1c1']
    assert fmu_cache.find_fmu('r1c1') == first


def test_missing_compiler_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv('CC', 'no-such-compiler-mshoot')
    with pytest.raises(RuntimeError, match='no-such-compiler-mshoot.*not found.*gcc'):
        fmu_build.build_fmu('r1c1', tmp_path)
    with pytest.raises(ValueError, match=r"unknown FMU 'r3c3'.*'r1c1'"):
        fmu_build.build_fmu('r3c3', tmp_path)


def test_command_line_builds_into_a_directory(tmp_path, capsys):
    assert fmu_build.main(['--out', str(tmp_path), 'r2c2']) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / 'R2C2.fmu')
    assert validate_fmu(str(tmp_path / 'R2C2.fmu')) == []


# -- R1C1: closed form vs Python model vs FMU (CS and ME) -----------------------------------
def test_constant_inputs_follow_the_exponential_response(r1c1_cs, r1c1_me):
    row = {'solrad': 200.0, 'Tout': 5.0, 'occ': 20.0, 'dpos': 0.0, 'q': 2000.0}
    times = np.arange(9) * HOUR
    udf = pd.DataFrame([row] * times.size, index=times)
    t0 = 293.15
    # T(t) = T_inf + (T0 - T_inf) exp(-g t / C) in one piece, not chained per interval.
    p = R1C1Parameters()
    cap = p.tmass * 1.2 * 1005.0 * p.Vi
    res = p.RExt / (3.0 * p.Vi ** (2.0 / 3.0))
    occ_w_per_k = p.occheff * row['occ'] * 84.0 / 32.0
    g = 1.0 / res + occ_w_per_k
    t_inf = ((row['Tout'] + 273.15) / res + p.shgc * row['solrad'] + occ_w_per_k * 325.15
             + row['q']) / g
    expected = t_inf + (t0 - t_inf) * np.exp(-g * times / cap)
    _, x_py = R1C1Model().simulate(udf, [t0])
    y_cs, x_cs = r1c1_cs.simulate(udf, [t0])
    y_me, x_me = r1c1_me.simulate(udf, [t0])
    np.testing.assert_allclose(x_py['T'], expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(x_cs['T'], expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(y_cs['T'], expected - 273.15, rtol=0, atol=1e-9)
    np.testing.assert_allclose(x_me['T'], expected, rtol=0, atol=1e-6)
    assert expected[-1] - expected[0] > 1.0  # the response is not trivially flat


def test_hourly_switching_inputs_match_python_model(r1c1_cs, r1c1_me):
    udf = hourly_inputs(8, seed=1)
    t0 = 291.0
    expected = r1c1_closed_form(udf, t0)
    heat = np.concatenate([[0.0], np.cumsum(udf['q'].to_numpy()[:-1] * HOUR)])
    y_py, x_py = R1C1Model().simulate(udf, [t0])
    np.testing.assert_allclose(x_py['T'], expected, rtol=0, atol=1e-9)
    for model, tol in ((r1c1_cs, 1e-9), (r1c1_me, 1e-6)):
        ydf, xdf = model.simulate(udf, [t0])
        assert list(xdf.columns) == ['T'] and list(ydf.columns) == ['T', 'Qr']
        assert xdf.index.equals(udf.index) and xdf['T'].iloc[0] == t0
        np.testing.assert_allclose(xdf['T'], expected, rtol=0, atol=tol)
        np.testing.assert_allclose(ydf['T'], y_py['T'], rtol=0, atol=tol)
        np.testing.assert_allclose(ydf['Qr'], heat, rtol=1e-9, atol=1e-6)
    assert np.ptp(expected) > 1.0


def test_parameters_reach_the_fmu(r1c1_fmu):
    params = R1C1Parameters(tmass=20.0, RExt=2.5, shgc=6.0, Tve=18.0)
    udf = hourly_inputs(4, seed=2)
    expected = r1c1_closed_form(udf, 294.0, params)
    with r1c1_fmi_model(params, fmi_type='CoSimulation', fmu_path=r1c1_fmu) as model:
        _, xdf = model.simulate(udf, [294.0])
        np.testing.assert_allclose(xdf['T'], expected, rtol=0, atol=1e-9)
        # every simulation resets the FMU and re-applies the parameters
        _, again = model.simulate(udf, [294.0])
        np.testing.assert_array_equal(again.to_numpy(), xdf.to_numpy())
    default = r1c1_closed_form(udf, 294.0)
    assert abs(default[-1] - expected[-1]) > 0.1


@pytest.mark.parametrize('which', ['r1c1_cs', 'r1c1_me', 'r2c2'])
def test_simulate_intervals_equals_per_interval_simulate(which, request):
    model = request.getfixturevalue(which)
    rng = np.random.default_rng(3)
    batch = 6
    if which == 'r2c2':
        x_start = rng.uniform(15, 25, (batch, 2))
        u = np.column_stack([rng.uniform(-5, 20, batch), rng.uniform(0, 3000, batch),
                             rng.uniform(0, 2000, batch)])
    else:
        x_start = rng.uniform(288, 300, (batch, 1))
        u = hourly_inputs(batch - 1, seed=4).to_numpy()
    x_end, y_end = model.simulate_intervals(x_start, u, HOUR)
    assert x_end.shape == x_start.shape and y_end.shape == (batch, 2)
    # Co-Simulation: the same FMI calls, the same numbers; Model Exchange: the batch is
    # integrated by the compiled Runge-Kutta driver, ``simulate`` by CVode (both at 1e-10)
    atol = 0.0 if which == 'r1c1_cs' else 1e-6
    if which != 'r1c1_cs':
        assert model.me_batch_plan() is None and model._me_driver
    for b in range(batch):
        udf = pd.DataFrame([u[b], u[b]], index=[0.0, HOUR], columns=list(model.input_names))
        ydf, xdf = model.simulate(udf, x_start[b])
        np.testing.assert_allclose(x_end[b], xdf.to_numpy()[-1], rtol=0, atol=atol)
        np.testing.assert_allclose(y_end[b], ydf.to_numpy()[-1], rtol=1e-12, atol=atol)
    # and again, in another order, on the same instance
    x_again, y_again = model.simulate_intervals(x_start[::-1], u[::-1], HOUR)
    np.testing.assert_array_equal(x_again, x_end[::-1])
    np.testing.assert_array_equal(y_again, y_end[::-1])
    if which != 'r2c2':
        x_py, y_py = R1C1Model().simulate_intervals(x_start, u, HOUR)
        tol = 1e-9 if which == 'r1c1_cs' else 1e-6
        np.testing.assert_allclose(x_end, x_py, rtol=0, atol=tol)
        np.testing.assert_allclose(y_end, y_py, rtol=1e-9, atol=tol)


# -- derivatives --------------------------------------------------------------------------------
@pytest.mark.parametrize('tolerance', [1e-10, 1e-6])
def test_r1c1_interval_jacobians_match_finite_differences(r1c1_fmu, r1c1_cs, tolerance):
    rng = np.random.default_rng(6)
    batch = 4
    x_start = rng.uniform(288, 300, (batch, 1))
    u = hourly_inputs(batch - 1, seed=7).to_numpy(copy=True)
    u[:, 1] = [25.0, 10.0, 30.0, 15.0]  # Tout on both sides of Tve (21 degC), dpos > 0
    wrt = [4, 0, 1, 2, 3]
    assert r1c1_cs.interval_jacobians(x_start, u, HOUR, wrt) is None  # CS: FD fallback
    with r1c1_fmi_model(fmi_type='ModelExchange', tolerance=tolerance,
                        fmu_path=r1c1_fmu) as model:
        jac = model.interval_jacobians(x_start, u, HOUR, wrt)
    assert jac.dx_du.shape == (batch, 1, 5) and jac.dy_dx0.shape == (batch, 2, 1)
    # central differences through the exact (Co-Simulation) solution
    steps = np.array([1.0, 1e-2, 1e-3, 1e-3, 1e-3])
    fd_x = np.empty((batch, 1, 5))
    fd_y = np.empty((batch, 2, 5))
    for j, (col, h) in enumerate(zip(wrt, steps)):
        up, down = u.copy(), u.copy()
        up[:, col] += h
        down[:, col] -= h
        (xu, yu), (xd, yd) = r1c1_cs.simulate_intervals(x_start, up, HOUR), \
            r1c1_cs.simulate_intervals(x_start, down, HOUR)
        fd_x[:, :, j] = (xu - xd) / (2 * h)
        fd_y[:, :, j] = (yu - yd) / (2 * h)
    xu, yu = r1c1_cs.simulate_intervals(x_start + 1e-3, u, HOUR)
    xd, yd = r1c1_cs.simulate_intervals(x_start - 1e-3, u, HOUR)
    # forward sensitivities: the error follows the tolerance, no finite-difference noise
    # (at 1e-6 still 0.1 %, where differences of integrated states would be useless)
    rtol = 1e-6 if tolerance < 1e-8 else 1e-3
    np.testing.assert_allclose(jac.dx_du, fd_x, rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(jac.dy_du[:, 0], fd_y[:, 0], rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(jac.dy_du[:, 1, 0], HOUR, rtol=1e-9)  # dQr/dq
    np.testing.assert_allclose(jac.dy_du[:, 1, 1:], 0.0, atol=1e-9)
    np.testing.assert_allclose(jac.dx_dx0[:, 0, 0], (xu - xd)[:, 0] / 2e-3, rtol=rtol)
    np.testing.assert_allclose(jac.dy_dx0[:, :, 0], (yu - yd) / 2e-3, rtol=rtol, atol=1e-9)
    x_cs, y_cs = r1c1_cs.simulate_intervals(x_start, u, HOUR)
    np.testing.assert_allclose(jac.x_end, x_cs, rtol=0, atol=1e-4 if tolerance > 1e-8 else 1e-6)


def test_r2c2_interval_jacobians_are_exact_matrices(r2c2):
    rng = np.random.default_rng(8)
    x_start = rng.uniform(15, 25, (3, 2))
    u = np.column_stack([rng.uniform(-5, 20, 3), rng.uniform(0, 3000, 3),
                         rng.uniform(0, 2000, 3)])
    jac = r2c2.interval_jacobians(x_start, u, HOUR, [1, 0, 2])
    for b in range(3):
        x1, y1, ad, bd, c, d = r2c2_exact(x_start[b], u[b], HOUR)
        np.testing.assert_allclose(jac.x_end[b], x1, rtol=0, atol=1e-6)
        np.testing.assert_allclose(jac.y_end[b], y1, rtol=1e-7, atol=1e-5)
        np.testing.assert_allclose(jac.dx_dx0[b], ad, rtol=1e-5, atol=1e-8)  # non-symmetric
        np.testing.assert_allclose(jac.dx_du[b], bd[:, [1, 0, 2]], rtol=1e-5, atol=1e-10)
        np.testing.assert_allclose(jac.dy_dx0[b], c @ ad, rtol=1e-5, atol=1e-8)
        np.testing.assert_allclose(jac.dy_du[b], (c @ bd + d)[:, [1, 0, 2]], rtol=1e-5,
                                   atol=1e-9)
    assert abs(ad[0, 1] - ad[1, 0]) > 0.1


# -- the third-party-style FMU through the same interface ------------------------------------
def test_second_fmu_simulates_through_fmimodel(r2c2):
    assert r2c2.fmi_type == 'ModelExchange'  # auto: the FMU has no Co-Simulation
    assert r2c2.state_names == ('Ta', 'Tw') and r2c2.output_names == ('Tair', 'Pwin')
    rng = np.random.default_rng(9)
    n = 7
    udf = pd.DataFrame({'Tamb': rng.uniform(-5, 20, n), 'Qhvac': rng.uniform(0, 4000, n),
                        'Qsun': rng.uniform(0, 3000, n)}, index=np.arange(n) * HOUR)
    x = np.array([21.0, 17.0])
    ydf, xdf = r2c2.simulate(udf, x)
    u = udf.to_numpy()
    assert ydf['Pwin'].iloc[0] == pytest.approx((21.0 - u[0, 0]) / 0.04)
    for k in range(n - 1):
        x, y, *_ = r2c2_exact(x, u[k], HOUR)  # outputs at t_{k+1} use interval k's inputs
        np.testing.assert_allclose(xdf.to_numpy()[k + 1], x, rtol=0, atol=1e-6)
        np.testing.assert_allclose(ydf.to_numpy()[k + 1], y, rtol=1e-7, atol=1e-5)
    assert np.ptp(xdf['Ta']) > 1.0


def test_unsupported_fmi_type_and_closed_model(r2c2_fmu):
    with pytest.raises(ValueError, match=r"supports \['ModelExchange'\].*CoSimulation"):
        FmiModel(r2c2_fmu, inputs=['Tamb'], states=['air.T'], outputs=['Tair'],
                 fmi_type='CoSimulation')
    model = FmiModel(r2c2_fmu, inputs=['Tamb'], states=['air.T'], outputs=['Tair'])
    model.close()
    model.close()
    with pytest.raises(RuntimeError, match='closed'):
        model.simulate_intervals([[20.0]], [[0.0]], HOUR)


# -- configuration errors ---------------------------------------------------------------------
@pytest.mark.parametrize('fmi_type', ['CoSimulation', 'ModelExchange'])
@pytest.mark.parametrize('field, bad, valid', [
    ('inputs', R1C1_INPUTS[:-1] + ['qq'], 'solrad'),
    ('states', {'T': 'T'}, 'heatCapacitor.T'),
    ('outputs', ['T', 'Qr', 'nope'], 'Qr'),
])
def test_bad_variable_names_list_the_valid_choices(r1c1_fmu, fmi_type, field, bad, valid):
    config = {**R1C1_VARIABLES, field: bad}
    with pytest.raises(ValueError) as info:
        FmiModel(r1c1_fmu, fmi_type=fmi_type, **config)
    message = str(info.value)
    assert 'expected' in message and 'got' in message and repr(valid) in message
    bad_names = bad.values() if isinstance(bad, dict) else bad
    assert any(repr(name) in message for name in bad_names)


def test_bad_parameters_and_settings(r1c1_fmu):
    with pytest.raises(ValueError, match=r"\['tmas'\].*'tmass'"):
        FmiModel(r1c1_fmu, parameters={'tmas': 10.0}, **R1C1_VARIABLES)
    with pytest.raises(ValueError, match='finite'):
        FmiModel(r1c1_fmu, parameters={'tmass': float('nan')}, **R1C1_VARIABLES)
    with pytest.raises(ValueError, match='fmi_type'):
        FmiModel(r1c1_fmu, fmi_type='Scheduled', **R1C1_VARIABLES)
    with pytest.raises(ValueError, match='tolerance'):
        FmiModel(r1c1_fmu, tolerance=0.0, **R1C1_VARIABLES)
    with pytest.raises(ValueError, match=r"monotone_inputs must be inputs .*\['heat'\]"):
        FmiModel(r1c1_fmu, monotone_inputs=['q', 'heat'], **R1C1_VARIABLES)
    with pytest.raises(TypeError, match='string'):
        FmiModel(r1c1_fmu, inputs='q', states=['heatCapacitor.T'], outputs=['T'])
    with pytest.raises(FileNotFoundError):
        FmiModel(r1c1_fmu.with_name('missing.fmu'), **R1C1_VARIABLES)


def test_bad_simulation_arguments(r1c1_cs):
    with pytest.raises(ValueError, match=r'shape \(B, 1\)'):
        r1c1_cs.simulate_intervals(np.zeros((2, 2)), np.zeros((2, 5)), HOUR)
    with pytest.raises(ValueError, match=r'shape \(2, 5\)'):
        r1c1_cs.simulate_intervals(np.full((2, 1), 293.0), np.zeros((2, 4)), HOUR)
    with pytest.raises(ValueError, match='dt_s'):
        r1c1_cs.simulate_intervals(np.full((1, 1), 293.0), np.zeros((1, 5)), 0.0)
    with pytest.raises(ValueError, match='lacks input columns'):
        r1c1_cs.simulate(hourly_inputs(2, seed=0).drop(columns='q'), [293.0])


# -- one extraction, one instance -------------------------------------------------------------
@pytest.mark.parametrize('fmi_type', ['CoSimulation', 'ModelExchange'])
def test_instance_is_extracted_and_instantiated_once(r1c1_fmu, monkeypatch, tmp_path, fmi_type):
    counts = {'extract': 0, 'instantiate': 0, 'read': 0, 'reset': 0}

    def counting(name, function):
        def wrapper(*args, **kwargs):
            counts[name] += 1
            return function(*args, **kwargs)
        return wrapper

    # extractions go to a fresh cache folder (the drivers stay where make setup built them)
    where = tmp_path / 'extracted'
    monkeypatch.setattr(fmu_cache, 'extracted_dir',
                        lambda path: where / fmu_cache.file_sha256(path)[:32])
    monkeypatch.setattr(zipfile.ZipFile, 'extractall',
                        counting('extract', zipfile.ZipFile.extractall))
    monkeypatch.setattr(fmpy, 'read_model_description',
                        counting('read', fmpy.read_model_description))
    for cls in (FMU2Model, FMU2Slave):
        monkeypatch.setattr(cls, 'instantiate', counting('instantiate', cls.instantiate))
        monkeypatch.setattr(cls, 'reset', counting('reset', cls.reset))
    udf = hourly_inputs(5, seed=11)
    with r1c1_fmi_model(fmi_type=fmi_type, fmu_path=r1c1_fmu) as model:
        unzip_dir = model._unzip_dir
        assert unzip_dir.parent == where
        for _ in range(3):
            model.simulate(udf, [293.0])
        for _ in range(2):
            model.simulate_intervals(np.full((5, 1), 293.0), udf.to_numpy()[:5] * 0.5, HOUR)
        model.interval_jacobians(np.full((2, 1), 293.0), udf.to_numpy()[:2], HOUR, [4])
        assert unzip_dir.is_dir()
    assert counts['extract'] == counts['read'] == counts['instantiate'] == 1
    # reset per simulation instead of a new instance (the first simulation initialises the
    # fresh instance; Co-Simulation batches reset inside the compiled driver)
    assert counts['reset'] >= 2
    assert unzip_dir.is_dir()  # the extraction stays in the cache ...
    with r1c1_fmi_model(fmi_type=fmi_type, fmu_path=r1c1_fmu) as again:
        assert again._unzip_dir == unzip_dir  # ... for the next model of the same file
    # (the second model loaded the description the first one read: fmi.DESCRIPTION_PICKLE)
    assert counts['extract'] == counts['read'] == 1
    assert list(where.iterdir()) == [unzip_dir]


def test_batched_co_simulation_driver_equals_fmpy_calls():
    """The compiled batch driver makes the same FMI calls as the fmpy path: same numbers."""
    model = r1c1_fmi_model(fmi_type='CoSimulation')
    rng = np.random.default_rng(5)
    batch = 25
    x = rng.uniform(289.0, 299.0, (batch, 1))
    u = np.column_stack([rng.uniform(0, 600, batch), rng.uniform(-5, 15, batch),
                         rng.uniform(0, 40, batch), rng.uniform(0, 80, batch),
                         rng.uniform(-2000, 2000, batch)])
    model.simulate_intervals(x[:1], u[:1], 3600.0)  # the first initialisation goes via fmpy
    x_c, y_c = model.simulate_intervals(x, u, 3600.0)
    assert model._cs_driver, 'the batched driver was not used'
    model._cs_driver = False  # force the fmpy path
    x_py, y_py = model.simulate_intervals(x, u, 3600.0)
    np.testing.assert_array_equal(x_c, x_py)
    np.testing.assert_array_equal(y_c, y_py)
    x_ref, y_ref = R1C1Model().simulate_intervals(x, u, 3600.0)
    np.testing.assert_allclose(x_c, x_ref, rtol=0, atol=1e-9)


def _me_batch_cases(which, batch, seed):
    rng = np.random.default_rng(seed)
    if which == 'r2c2':
        x = rng.uniform(15, 25, (batch, 2))
        u = np.column_stack([rng.uniform(-5, 20, batch), rng.uniform(0, 3000, batch),
                             rng.uniform(0, 2000, batch)])
    else:
        x = rng.uniform(289.0, 299.0, (batch, 1))
        u = np.column_stack([rng.uniform(0, 600, batch), rng.uniform(-5, 30, batch),
                             rng.uniform(0, 40, batch), rng.uniform(0, 80, batch),
                             rng.uniform(-2000, 2000, batch)])
    return x, u


def _me_model(which, tolerance=1e-10):
    if which == 'r2c2':
        return FmiModel(fmu_build.ensure_fmu('r2c2'), inputs=['Tamb', 'Qhvac', 'Qsun'],
                        states={'Ta': 'air.T', 'Tw': 'wall.T'}, outputs=['Tair', 'Pwin'],
                        parameters=R2C2_PARAMETERS, tolerance=tolerance)
    return r1c1_fmi_model(fmi_type='ModelExchange', tolerance=tolerance)


@pytest.mark.parametrize('which', ['r1c1', 'r2c2'])  # with / without FMU state snapshots
def test_batched_model_exchange_driver_matches_cvode_and_exact(which):
    """The compiled Runge-Kutta batch equals CVode within the integration tolerance."""
    x, u = _me_batch_cases(which, 12, seed=21)
    with _me_model(which) as fast, _me_model(which) as slow:
        x_c, y_c = fast.simulate_intervals(x, u, HOUR)
        assert fast._me_driver, 'the batched Model Exchange driver was not used'
        slow._me_driver = False  # CVode, as before the driver
        assert slow.me_batch_plan() is not None
        x_cv, y_cv = slow.simulate_intervals(x, u, HOUR)
    if which == 'r2c2':
        exact = [r2c2_exact(x[b], u[b], HOUR) for b in range(len(x))]
        x_ref, y_ref = np.array([e[0] for e in exact]), np.array([e[1] for e in exact])
    else:
        with r1c1_fmi_model(fmi_type='CoSimulation') as cs:  # the exact solution per step
            x_ref, y_ref = cs.simulate_intervals(x, u, HOUR)
    np.testing.assert_allclose(x_c, x_cv, rtol=0, atol=1e-6)  # CVode's own error ~5e-7 K
    np.testing.assert_allclose(y_c, y_cv, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(x_c, x_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(y_c, y_ref, rtol=1e-9, atol=1e-7)


@pytest.mark.parametrize('which', ['r1c1', 'r2c2'])
def test_batched_model_exchange_sensitivities_match_cvode(which):
    """Forward sensitivities integrated in C equal those integrated by CVode."""
    x, u = _me_batch_cases(which, 8, seed=22)
    wrt = [1, 0, 2] if which == 'r2c2' else [4, 0, 1, 3]
    with _me_model(which) as fast, _me_model(which) as slow:
        jac = fast.interval_jacobians(x, u, HOUR, wrt)
        assert fast._me_driver
        slow._me_driver = False
        ref = slow.interval_jacobians(x, u, HOUR, wrt)
    for name in ('dx_dx0', 'dx_du', 'dy_dx0', 'dy_du'):
        a, b = getattr(jac, name), getattr(ref, name)
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-9 * np.abs(b).max(), err_msg=name)
    np.testing.assert_allclose(jac.x_end, ref.x_end, rtol=0, atol=1e-6)


@pytest.mark.parametrize('which', ['r1c1', 'r2c2'])  # with / without FMU state snapshots
def test_chained_model_exchange_batch_equals_consecutive_batches(which):
    """
    Trajectories of consecutive intervals in one chained batch: the numbers of one batch each.

    :meth:`FmiModel.simulate_chains` hands the end states on inside the driver; the default
    (:meth:`Model.simulate_chains`) makes N calls of ``simulate_intervals``. Bit for bit,
    with interval start times.
    """
    x, u = _me_batch_cases(which, 3 * 5, seed=24)
    x0, inputs = x[:3], u.reshape(5, 3, -1)
    times = HOUR * (np.arange(5)[:, None] + np.zeros((1, 3)))
    with _me_model(which, tolerance=1e-6) as chained, _me_model(which, tolerance=1e-6) as steps:
        x_end, y_end = chained.simulate_chains(x0, inputs, HOUR, t_start_s=times)
        assert chained._me_driver and any(key[-1] == 3 for key in chained._me_problems)
        x_ref, y_ref = Model.simulate_chains(steps, x0, inputs, HOUR, t_start_s=times)
    assert x_end.shape == (5, 3, x0.shape[1]) and y_end.shape == y_ref.shape
    np.testing.assert_array_equal(x_end, x_ref)
    np.testing.assert_array_equal(y_end, y_ref)


@pytest.mark.parametrize('which', ['r1c1', 'r2c2'])  # with / without FMU state snapshots
def test_interval_batch_gives_what_interval_jacobians_gives(which):
    """
    An FMU's interval batch (bound to the driver after its first evaluation): the call's numbers.

    Bit for bit, at new starts and inputs written into its buffers each time, with start
    times; non-finite inputs are refused as the call refuses them.
    """
    x, u = _me_batch_cases(which, 3 * 6, seed=25)
    wrt = [1, 0, 2] if which == 'r2c2' else [4, 0]
    times = HOUR * np.arange(6)
    with _me_model(which, tolerance=1e-6) as model, _me_model(which, tolerance=1e-6) as ref:
        batch = model.interval_batch(6, HOUR, wrt, times)
        for k in range(3):
            batch.x_start[:] = x[6 * k:6 * k + 6]
            batch.u[:] = u[6 * k:6 * k + 6]
            ours = batch.jacobians()
            theirs = ref.interval_jacobians(x[6 * k:6 * k + 6], u[6 * k:6 * k + 6], HOUR, wrt,
                                            t_start_s=times)
            for name in ('x_end', 'y_end', 'dx_dx0', 'dx_du', 'dy_dx0', 'dy_du'):
                np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name))
        assert batch._bound is not None, 'the batch did not bind to the driver'
        batch.u[2, 0] = np.nan
        with pytest.raises(ValueError, match='finite'):
            batch.jacobians()


def test_event_indicators_keep_model_exchange_on_cvode(monkeypatch):
    """Event indicators keep Model Exchange off the explicit driver (dispatch decision)."""
    x, u = _me_batch_cases('r1c1', 3, seed=23)
    with _me_model('r1c1') as model, r1c1_fmi_model(fmi_type='CoSimulation') as cs:
        assert model.me_batch_plan() is None
        assert cs.me_batch_plan() == 'Co-Simulation FMU'
        # create CVode before the patch (an FMU with real event indicators gives it roots)
        model.simulate(pd.DataFrame(u[:2], index=[0.0, HOUR], columns=R1C1_INPUTS), x[0])
        # (on a copy: the description is shared with every model of the FMU file)
        monkeypatch.setattr(model, 'model_description', copy.copy(model.model_description))
        model.model_description.numberOfEventIndicators = 1
        assert model.me_batch_plan() == 'the FMU has event indicators'

        def refuse(*args, **kwargs):
            raise AssertionError('the batched driver was called for an FMU with events')

        monkeypatch.setattr(model, '_me_batch_in_c', refuse)
        x_end, _ = model.simulate_intervals(x, u, HOUR)  # CVode, as before
        assert model.interval_jacobians(x, u, HOUR, [4]) is None  # finite differences
        x_ref, _ = cs.simulate_intervals(x, u, HOUR)
        np.testing.assert_allclose(x_end, x_ref, rtol=0, atol=1e-6)
        assert model._solver is not None


def test_stiff_model_exchange_batch_falls_back_to_cvode(monkeypatch, caplog):
    """Too many Runge-Kutta steps: a logged warning, then CVode for this model."""
    x, u = _me_batch_cases('r1c1', 4, seed=24)
    monkeypatch.setattr(fmi_me, 'ME_MAX_STEPS', 0)
    with _me_model('r1c1') as model, caplog.at_level('WARNING', logger=fmi_me.__name__):
        x_end, y_end = model.simulate_intervals(x, u, HOUR)
        assert 'stopped at interval 0 (more than 0 steps' in caplog.text
        assert 'integrates with CVode from now on' in caplog.text
        assert model._me_driver is False
        assert model.me_batch_plan() == 'the compiled driver was disabled'
        with r1c1_fmi_model(fmi_type='CoSimulation') as cs:
            x_ref, _ = cs.simulate_intervals(x, u, HOUR)
        np.testing.assert_allclose(x_end, x_ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize('fmi_type', ['CoSimulation', 'ModelExchange'])
def test_simulate_fresh_reproduces_the_reused_instance(fmi_type):
    """The ancestor's way (simulate_fmu from the file each time) gives the same trajectory."""
    model = r1c1_fmi_model(fmi_type=fmi_type, tolerance=1e-10)
    udf = hourly_inputs(4, seed=3)
    ydf, xdf = model.simulate(udf, [294.0])
    y_fresh, x_fresh = model.simulate_fresh(udf, [294.0])
    np.testing.assert_allclose(x_fresh.to_numpy(), xdf.to_numpy(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(y_fresh.to_numpy(), ydf.to_numpy(), rtol=1e-9, atol=1e-6)
