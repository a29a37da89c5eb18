"""
Absolute time: control-model intervals simulated at their own FMU time.

The test FMU (``tests/fmus/timed_zone.c``) has internal gains on a schedule of
FMU time (8-17 h with time events, or a smooth daily profile without events),
so an interval's end state depends on when it runs. The references are one
continuous simulation of the same FMU (``simulate``, which has always run on
the index times) and the closed loop against the FMU itself as the building.
"""
from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.controller import Controller
from mshoot_core.emulation import Emulator
from mshoot_core.models.fmi import FmiModel, r1c1_fmi_model
from mshoot_core.models.fmi_drivers import MeBatchDriver
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.scenario import synthetic_scenario
from mshoot_core.solvers import make_solver
import numpy as np
import pandas as pd
import pytest

from timed_fmu import VARIABLES

HOUR = 3600.0
HOURS = 36
#: Closed-loop steps of the MPC tests (a day: the gains switch on and off).
LOOP_HOURS = 24


def timed_model(path, fmi_type, schedule, tolerance=1e-10, **kwargs):
    return FmiModel(path, **VARIABLES, fmi_type=fmi_type, tolerance=tolerance,
                    parameters={'schedule': float(schedule)}, **kwargs)


def hourly_inputs(hours=HOURS, seed=3, start_s=0.0):
    rng = np.random.default_rng(seed)
    t = start_s + np.arange(hours + 1) * HOUR
    return pd.DataFrame({'Tout': rng.uniform(-5.0, 15.0, hours + 1),
                         'q': rng.uniform(-1500.0, 1500.0, hours + 1)}, index=t)


CASES = [pytest.param(fmi, schedule, variant, id=f'{fmi}-{name}-{variant}')
         for fmi in ('ModelExchange', 'CoSimulation')
         for schedule, name in ((0, 'steps'), (1, 'smooth'))
         for variant in ('state', 'nostate')]


@pytest.mark.parametrize('fmi_type, schedule, variant', CASES)
def test_intervals_at_their_own_time_chain_into_one_simulation(timed_fmus, fmi_type, schedule,
                                                               variant):
    """
    Intervals from the continuous trajectory's states, each at its own start time, end on it.

    ME: compiled driver for the smooth profile, CVode for the time events; with FMU-state snapshots
    or re-initialisation; CS: the compiled driver. At time 0 they do not.
    """
    udf = hourly_inputs()
    with timed_model(timed_fmus[variant], fmi_type, schedule) as model:
        ydf, xdf = model.simulate(udf, [293.15])
        x_start = xdf.to_numpy()[:-1]
        u = udf.to_numpy()[:-1]
        times = udf.index.to_numpy()[:-1]
        x_end, y_end = model.simulate_intervals(x_start, u, HOUR, t_start_s=times)
        x_zero, _ = model.simulate_intervals(x_start, u, HOUR)
        if fmi_type == 'ModelExchange' and schedule == 1:  # no events: the compiled driver
            assert isinstance(model._me_driver, MeBatchDriver)
    tol = 1e-9 if fmi_type == 'CoSimulation' else 2e-6
    np.testing.assert_allclose(x_end, xdf.to_numpy()[1:], rtol=0, atol=tol)
    np.testing.assert_allclose(y_end[:, [0, 2]], ydf[['T', 'Pint']].to_numpy()[1:], rtol=0,
                               atol=max(tol, 1e-9 * 3000.0))
    assert np.max(np.abs(x_zero - xdf.to_numpy()[1:])) > 0.2  # time 0: the gains are missed


@pytest.mark.parametrize('fmi_type', ['ModelExchange', 'CoSimulation'])
def test_time_origin_shifts_the_fmu_time(timed_fmus, fmi_type):
    """With ``time_origin_s = -5 h`` the caller's t = 0 is FMU time 5 h."""
    udf = hourly_inputs(12, seed=8)
    with timed_model(timed_fmus['state'], fmi_type, 0, time_origin_s=-5 * HOUR) as shifted, \
            timed_model(timed_fmus['state'], fmi_type, 0) as plain:
        ydf, xdf = plain.simulate(udf.set_axis(udf.index + 5 * HOUR), [290.0])
        ydf_s, xdf_s = shifted.simulate(udf, [290.0])
        x_end, _ = shifted.simulate_intervals(xdf.to_numpy()[:-1], udf.to_numpy()[:-1], HOUR,
                                              t_start_s=udf.index.to_numpy()[:-1])
    np.testing.assert_allclose(xdf_s.to_numpy(), xdf.to_numpy(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ydf_s['Pint'].to_numpy(), ydf['Pint'].to_numpy())
    tol = 1e-9 if fmi_type == 'CoSimulation' else 2e-6
    np.testing.assert_allclose(x_end, xdf.to_numpy()[1:], rtol=0, atol=tol)
    assert ydf['Pint'].iloc[3] == 3000.0 and ydf['Pint'].iloc[2] == 0.0  # on at 8 h FMU time


@pytest.mark.parametrize('schedule', [0, 1])
def test_forward_sensitivities_at_their_own_time(timed_fmus, schedule):
    """ME derivatives (compiled driver / CVode) integrate each interval at its own time."""
    udf = hourly_inputs(24, seed=5)
    with timed_model(timed_fmus['state'], 'ModelExchange', schedule) as model:
        _, xdf = model.simulate(udf, [293.15])
        x_start, u = xdf.to_numpy()[:-1], udf.to_numpy()[:-1]
        times = udf.index.to_numpy()[:-1]
        jac = model.interval_jacobians(x_start, u, HOUR, [1], t_start_s=times)
    np.testing.assert_allclose(jac.x_end, xdf.to_numpy()[1:], rtol=0, atol=2e-6)
    # linear in T and q: dT_end/dq = (1 - exp(-UA dt / C)) / UA, dT_end/dT0 = exp(-UA dt / C)
    decay = np.exp(-250.0 * HOUR / 1e7)
    np.testing.assert_allclose(jac.dx_du[:, 0, 0], (1.0 - decay) / 250.0, rtol=1e-5)
    np.testing.assert_allclose(jac.dx_dx0[:, 0, 0], decay, rtol=1e-6)


def test_time_invariant_fmu_gives_the_same_numbers_at_any_time():
    """The built-in R1C1 (no time dependence): start times change nothing, bit for bit."""
    rng = np.random.default_rng(2)
    x = rng.uniform(290.0, 298.0, (12, 1))
    u = np.column_stack([rng.uniform(0, 300, 12), rng.uniform(-5, 15, 12), rng.integers(0, 30, 12),
                         np.zeros(12), rng.uniform(-2000, 2000, 12)])
    times = 7 * 86400.0 + np.arange(12) * HOUR
    for fmi_type in ('ModelExchange', 'CoSimulation'):
        with r1c1_fmi_model(fmi_type=fmi_type, tolerance=1e-6) as model:
            plain = model.simulate_intervals(x, u, HOUR)
            timed = model.simulate_intervals(x, u, HOUR, t_start_s=times)
            np.testing.assert_array_equal(timed[0], plain[0])
            np.testing.assert_array_equal(timed[1], plain[1])
            if fmi_type == 'ModelExchange':
                jac = model.interval_jacobians(x, u, HOUR, [4])
                jac_t = model.interval_jacobians(x, u, HOUR, [4], t_start_s=times)
                np.testing.assert_array_equal(jac_t.dx_du, jac.dx_du)
    exact, _ = R1C1Model().simulate_intervals(x, u, HOUR, t_start_s=times)
    np.testing.assert_allclose(timed[0], exact, rtol=0, atol=1e-9)


def test_start_times_are_checked(timed_fmus):
    with timed_model(timed_fmus['state'], 'CoSimulation', 0) as model:
        with pytest.raises(ValueError, match=r'one start time \[s\] per interval \(2\)'):
            model.simulate_intervals(np.full((2, 1), 293.0), np.zeros((2, 2)), HOUR,
                                     t_start_s=[0.0])
        with pytest.raises(ValueError, match='finite'):
            model.simulate_intervals(np.full((1, 1), 293.0), np.zeros((1, 2)), HOUR,
                                     t_start_s=[np.nan])
    with pytest.raises(ValueError, match='time_origin_s must be a finite time'):
        timed_model(timed_fmus['state'], 'CoSimulation', 0, time_origin_s=float('inf'))


@pytest.mark.parametrize('fmi_type', ['CoSimulation', 'ModelExchange'])
def test_mpc_predicts_a_time_dependent_fmu(timed_fmus, fmi_type):
    """
    The MPC on the time-dependent FMU controlling that FMU predicts the emulated state.

    Every plan's first interval predicts the emulated state (a perfect model); time-0 intervals
    miss the gains.
    """
    scenario = synthetic_scenario(hours=LOOP_HOURS + 7)
    tolerance = 1e-10 if fmi_type == 'ModelExchange' else 1e-8
    with timed_model(timed_fmus['state'], fmi_type, 0, tolerance) as control, \
            timed_model(timed_fmus['state'], fmi_type, 0) as plant:
        mpc = MPC(control, horizon_steps=6)
        result = run_closed_loop(Controller(mpc=mpc), Emulator(plant, scenario, [293.15]),
                                 steps=LOOP_HOURS, log_every=0)
        steps = result.steps
        assert steps['success'].all() and not steps['fallback'].any()
        error = np.abs(steps['T_predicted'] - steps['T_end']).to_numpy()
        assert error.max() < (1e-6 if fmi_type == 'CoSimulation' else 1e-4), error.max()
        # the same solve at 7 h with the intervals at time 0 (as before absolute time)
        window = scenario.iloc[7:14]
        lower, upper = mpc.bounds_from_forecast(window)
        disturbances = window[list(mpc.problem.disturbance_names)].to_numpy()[:6]
        x0 = [steps['T_start'].iloc[7]]
        solver = make_solver('slsqp')
        timed = mpc.problem.solve(x0, disturbances, lower, upper, solver, t0_s=7 * HOUR)
        legacy = mpc.problem.solve(x0, disturbances, lower, upper, solver)
        truth = []
        for z in (timed, legacy):
            u = np.column_stack([disturbances[:, 0], z.controls[:, 0]])
            udf = pd.DataFrame(np.vstack([u, u[-1:]]), columns=['Tout', 'q'],
                               index=7 * HOUR + np.arange(7) * HOUR)
            truth.append(plant.simulate(udf, x0)[1]['T'].to_numpy()[1:])
    assert np.max(np.abs(timed.states[1:, 0] - truth[0])) < 1e-4
    assert np.max(np.abs(legacy.states[1:, 0] - truth[1])) > 0.5  # the gains from 8 h missed
