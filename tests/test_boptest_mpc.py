"""The BOPTEST control model, its identification, the economic MPC and its dispatch."""
from __future__ import annotations

from mshoot_core.boptest.forecasts import ForecastSpec, TestCaseForecasts
from mshoot_core.calibration import NetworkBuilder
from mshoot_core.estimation import StateEstimator
from mshoot_core.models.card import builtin_card, load_card
from mshoot_core.models.r1c1 import KELVIN
from mshoot_core.mpc import MPC
from mshoot_core.settings import MpcSettings
import numpy as np
import pandas as pd
import pytest
from scipy.integrate import solve_ivp


U = np.array([[2.0, 150.0, 300.0, 0.25, 0.4],
              [-3.0, 0.0, 0.0, 0.40, 1.0],
              [8.0, 400.0, 365.0, 0.10, 0.0]])
X = np.array([[294.0, 297.0, 290.0], [291.0, 293.0, 285.0], [296.0, 300.0, 295.0]])
#: The packaged control model of the heat pump house.
CARD = 'boptest_house'


def control_model(parameters: dict | None = None):
    """Return the card's thermal network with parameter values over the card's."""
    return NetworkBuilder(load_card(builtin_card(CARD)))(dict(parameters or {}))


def _house_rates(p: dict, u: np.ndarray):
    """Return the house's equations written out (the card's comment): dx/dt(x), power, heat."""
    tout, solar, gains, _, d = u
    heat = d * (p['qa'] + p['qb'] * tout)
    power = d * (p['pa'] + p['pb'] * tout + p['paux'])
    to = tout + KELVIN

    def rates(_t: float, x: np.ndarray) -> np.ndarray:
        tz, tf, te = x
        return np.array([((tf - tz) / p['Rzf'] + (te - tz) / p['Rze'] + (to - tz) / p['Rzo']
                          + p['gz'] * solar + p['gi'] * gains) / p['Cz'],
                         ((tz - tf) / p['Rzf'] + heat) / p['Cf'],
                         ((tz - te) / p['Rze'] + (to - te) / p['Reo'] + p['ge'] * solar)
                         / p['Ce']])
    return rates, power, heat


def test_card_model_is_the_houses_exact_solution() -> None:
    """The card boptest_house's network: the house's equations integrated, outputs and cost."""
    model = control_model()
    assert model.state_names == ('T', 'Tf', 'Te') and model.control_names == ('d',)
    assert model.comfort_states == ('T',) and model.measured_states == ('T',)
    p = model.parameters
    x_end, y_end = model.simulate_intervals(X, U, 3600.0)
    for k in range(3):
        rates, power, heat = _house_rates(p, U[k])
        sol = solve_ivp(rates, (0.0, 3600.0), X[k], rtol=1e-11, atol=1e-9, method='Radau')
        np.testing.assert_allclose(x_end[k], sol.y[:, -1], atol=1e-6)
        np.testing.assert_allclose(y_end[k], [x_end[k, 0] - KELVIN, power, heat,
                                              U[k, 3] * power / 1000.0], rtol=1e-12)
    # simulate over a frame agrees with the batch path (the cost summed from the start)
    udf = pd.DataFrame(np.vstack([U, U[-1]]), index=[0.0, 3600.0, 7200.0, 10800.0],
                       columns=list(model.input_names))
    ydf, xdf = model.simulate(udf, X[0])
    x, cost = X[0], 0.0
    for k in range(3):
        x, y = model.simulate_intervals(x[None, :], U[k:k + 1], 3600.0)
        x, cost = x[0], cost + y[0, 3]
        np.testing.assert_allclose(xdf.to_numpy()[k + 1], x)
        np.testing.assert_allclose(ydf.to_numpy()[k + 1], [*y[0, :3], cost])
    assert control_model({'Cz': 2e4}).parameters['Cz'] == 2e4
    with pytest.raises(ValueError, match='unknown network parameters'):
        control_model({'Cx': 1.0})


def test_estimator_recovers_unmeasured_states() -> None:
    model = control_model()
    settings = MpcSettings.from_file('boptest_house')
    rng = np.random.default_rng(3)
    x = np.array([293.0, 298.0, 288.0])
    estimator = StateEstimator.from_settings(model, settings.estimation, 3600.0)
    assert estimator.measured == ('T',)
    estimator.update(0.0, {'T': x[0]})  # floor and envelope wrong by 5 K
    for k in range(24 * 20):
        u = np.array([rng.uniform(-5, 10), rng.uniform(0, 300), 300.0, 0.2,
                      rng.uniform(0, 0.6)])
        x = model.simulate_intervals(x[None, :], u[None, :], 3600.0)[0][0]
        estimate = estimator.update((k + 1) * 3600.0, {'T': x[0]}, u)
    np.testing.assert_allclose(estimate.x, x, atol=0.05)


def test_output_cost_moves_heat_to_cheap_hours() -> None:
    """The cost 'output' (price x power) shifts the heat pump's runs to the cheap hours."""
    model = control_model({'Cz': 5e6, 'Cf': 3e7, 'Ce': 5e7, 'Rzf': 2e-3, 'Rze': 5e-3,
                           'Rzo': 2e-2, 'Reo': 1e-2, 'gz': 5.0, 'ge': 5.0, 'gi': 1.0})
    n = 12
    settings = MpcSettings.from_file('boptest_house', horizon_steps=n, control_names=('d',),
                                     band_margin_k=0.0)
    forecast = pd.DataFrame({'Tout': 0.0, 'solar': 0.0, 'gains': 300.0,
                             'price': np.where(np.arange(n + 1) < 6, 0.10, 0.40),
                             'comfort_min': np.where(np.arange(n + 1) >= 6, 21.0, 15.0),
                             'comfort_max': 30.0}, index=np.arange(n + 1) * 3600.0)
    bounds = {'T': ('comfort_min', 'comfort_max', KELVIN)}
    x0 = [293.0, 294.0, 288.0]
    result = MPC(model, settings, state_bounds=bounds).solve(x0, 0.0, forecast)
    assert result.success
    duty = result.controls[:, 0]
    assert duty[:6].sum() > max(0.1, 3 * duty[6:].sum())  # pre-heats while cheap
    assert np.all(result.states[7:, 0] >= 21.0 + KELVIN - 0.02)
    flat = forecast.assign(price=0.25)
    flat_duty = MPC(model, settings, state_bounds=bounds).solve(x0, 0.0, flat).controls[:, 0]
    assert flat_duty[:6].sum() < duty[:6].sum()
    with pytest.raises(ValueError, match='cost_output'):
        MPC(model, settings.replace(cost_output='nope'), state_bounds=bounds)


def test_forecast_frame_from_the_data(boptest_case) -> None:
    case = boptest_case
    t0 = 16 * 86400.0
    source = TestCaseForecasts(case, ForecastSpec.from_card(CARD), 'dynamic')
    frame = source.frame(t0, 24, 3600.0)  # the raw band: the margin is the controller's
    assert list(frame.columns) == ['Tout', 'solar', 'gains', 'price', 'comfort_min',
                                   'comfort_max']
    assert len(frame) == 25
    sub = t0 + 3 * 3600.0 + np.arange(4) * 900.0 + 450.0
    assert frame['price'].iloc[3] == pytest.approx(
        case.lookup('PriceElectricPowerDynamic', sub).mean())
    assert frame['Tout'].iloc[3] == pytest.approx(case.lookup('TDryBul', sub).mean() - KELVIN)
    for k in range(1, 25):  # bound of interval k-1: the tightest band over it
        inside = t0 + (k - 1) * 3600.0 + np.arange(1, 5) * 900.0  # (t_k-1, t_k]
        assert frame['comfort_min'].iloc[k] == pytest.approx(
            case.lookup('LowerSetp[1]', inside).max() - KELVIN)
        assert frame['comfort_max'].iloc[k] == pytest.approx(
            case.lookup('UpperSetp[1]', inside).min() - KELVIN)
    assert set(np.round(frame['comfort_min'], 2)) == {15.0, 21.0}


def test_short_closed_loop_beats_the_baseline(boptest_case) -> None:
    """
    Two test days after one day of warm-up: less discomfort and cost than the baseline.

    The economic MPC: the Controller of the settings ``boptest_house`` on the card
    ``boptest_modulation`` (:func:`~mshoot_core.boptest.supervision.supervised_plant`).
    """
    from mshoot_core.boptest.kpi_calculator import compute_kpis
    from mshoot_core.boptest.plant import BoptestPlant, run_period
    from mshoot_core.boptest.supervision import supervised_plant
    from mshoot_core.models.card import builtin_card
    case = boptest_case
    policy = supervised_plant(case, builtin_card('boptest_modulation'),
                              builtin_card(CARD),
                              MpcSettings.from_file('boptest_house', horizon_steps=24),
                              'dynamic')
    result = run_period(case, 'peak_heat_day', policy, 1.0, 2.0,
                        record=[*policy.recorded(case), 'reaHeaPumY_y'])
    mpc = compute_kpis(result.records, case, result.start_s, result.end_s, 'dynamic')
    outcomes = policy.outcomes
    assert len(outcomes) == 48 and all(o.result.success for o in outcomes)
    warmup_start, start, end = case.test_period('peak_heat_day', 1.0, 2.0)
    with BoptestPlant(case) as plant:
        plant.start(warmup_start)
        plant.advance(end)
        baseline = compute_kpis(plant.records(start, end), case, start, end, 'dynamic')
    assert mpc['tdis_tot'] <= baseline['tdis_tot']
    assert mpc['cost_tot'] < 0.95 * baseline['cost_tot']
    # the plant ran the planned duty: measured full-load fraction per hour ~ the plan
    records = result.records
    hours = np.floor((records['time'].to_numpy() - 1e-6 - start) / 3600.0)
    ran = records.assign(h=hours)[(hours >= 0) & (hours < 48)].groupby('h')[
        'reaHeaPumY_y'].apply(lambda y: float(np.mean(y > 0.5)))
    assert abs(ran.sum() - sum(float(o.decision.controls[0]) for o in outcomes)) < 2.0


def test_study_exits_2_on_bad_options(capsys) -> None:
    from mshoot_studies import boptest_mpc
    assert boptest_mpc.main(['evaluate', '--days', '-1']) == 2
    assert '--days' in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        boptest_mpc.main(['evaluate', '--prices', 'free'])
    assert exc.value.code == 2
