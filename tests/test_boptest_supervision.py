"""The general controller on the BOPTEST heat pump house: measured inputs, settings, core loop."""
from __future__ import annotations

import pathlib

from mshoot_core.boptest.plant import run_period
from mshoot_core.boptest.supervision import supervised_plant
from mshoot_core.calibration import NetworkBuilder
from mshoot_core.controller import controller_for
from mshoot_core.models.card import builtin_card, load_card
from mshoot_core.settings import MpcSettings, SettingsError
from mshoot_core.units import NS_PER_S
import numpy as np
import pandas as pd
import pytest

HOUR_NS = int(3600 * NS_PER_S)


def _house():
    return NetworkBuilder(load_card(builtin_card('boptest_house')))({})


def _forecast(tout_c: float, solar: float, rows: int = 37) -> dict[str, np.ndarray]:
    return {'Tout': np.full(rows, tout_c), 'solar': np.full(rows, solar),
            'gains': np.full(rows, 300.0), 'price': np.full(rows, 0.25),
            'comfort_min': np.full(rows, 21.0), 'comfort_max': np.full(rows, 24.0)}


def _heat(model, duty: float, tout_c: float, solar: float) -> float:
    """Return the model's heat Q [W] at a duty (the condenser heat the plant measures)."""
    u = np.array([[tout_c, solar, 300.0, 0.25, duty]])
    _, y = model.simulate_intervals(np.full((1, 3), 293.15), u, 3600.0)
    return float(y[0, model.output_names.index('Q')])


def test_inputs_measured_by_outputs_enter_the_estimate() -> None:
    """
    The step's measured weather and the duty of the measured heat enter the estimate.

    A controller with ``measured_inputs`` and a wrong forecast of the weather, told only the
    heat pump's mean heat, estimates what a controller without them estimates when told the
    weather by its forecast and the duty as applied; without the heat, the applied duty holds;
    a wrong heat moves the estimate.
    """
    model = _house()
    settings = MpcSettings.from_file('boptest_house')
    assert settings.estimation.input_measurements == {
        'Tout': ('mean_Tout', ''), 'solar': ('mean_solrad', ''), 'd': ('mean_Q_hp', 'Q')}
    tout, solar, duty = 3.0, 120.0, 0.4
    weather = {'output_names': ['mean_Tout', 'mean_solrad'], 'output_values': [tout, solar]}
    applied = {'control_names': ['d'], 'control_values': [duty]}
    estimates = []
    for measured, forecast, outputs in (
            (True, _forecast(tout + 5.0, 0.0), {
                'output_names': ['mean_Tout', 'mean_solrad', 'mean_Q_hp'],
                'output_values': [tout, solar, _heat(model, duty, tout, solar)]}),
            (False, _forecast(tout, solar), applied),
            (True, _forecast(tout - 4.0, 10.0), {**weather, **applied}),
            (True, _forecast(tout, solar), {
                'output_names': ['mean_Tout', 'mean_solrad', 'mean_Q_hp'],
                'output_values': [tout, solar, _heat(model, 0.6, tout, solar)]})):
        c = controller_for(model, settings if measured else settings.replace(measured_inputs=''))
        assert c.offer_forecast(0, 3600.0, forecast, 0) is None
        assert c.offer_named_state(0, ['T'], [293.15], 0) is None
        assert c.offer_named_state(HOUR_NS, ['T'], [293.4], HOUR_NS, **outputs) is None
        assert c.estimator.resets == 0 and c.estimator.updates == 2
        estimates.append(c.estimate.x)
    np.testing.assert_allclose(estimates[0], estimates[1], rtol=0, atol=1e-9)
    np.testing.assert_allclose(estimates[2], estimates[1], rtol=0, atol=1e-9)
    assert estimates[3][1] - estimates[1][1] > 1e-4  # more heat: a warmer floor


def test_settings_of_measured_inputs_are_checked() -> None:
    """Bad measured inputs, plant controls or state scaling: every problem, said clearly."""
    model = _house()
    settings = MpcSettings.from_file('boptest_house')
    assert settings.actuation.plant_names == {'d': 'Y'}
    assert (settings.problem.state_offset, settings.problem.state_scale) == (288.15, 10.0)
    with pytest.raises(SettingsError, match='measured_inputs must be'):
        settings.replace(measured_inputs='Tout=a=b')
    with pytest.raises(SettingsError, match='plant_controls must be'):
        settings.replace(plant_controls='d')
    with pytest.raises(SettingsError, match='state_offset and state_scale go together'):
        MpcSettings.from_flat(state_offset=288.15)
    with pytest.raises(SettingsError, match='state_scale must be > 0'):
        MpcSettings.from_flat(state_offset=288.15, state_scale=0.0)
    with pytest.raises(ValueError, match="'wind' is not an input of the model"):
        controller_for(model, settings.replace(measured_inputs='wind=mean_wind'))
    with pytest.raises(ValueError, match='needs a control'):
        controller_for(model, settings.replace(measured_inputs='Tout=mean_Q_hp/Q'))
    with pytest.raises(ValueError, match='no settings file'):
        MpcSettings.from_file('no_such_settings')


def test_short_core_run_of_the_house(boptest_case) -> None:
    """
    One day of warm-up observed step by step, one test day decided by the controller.

    Every step an optimum; the estimate followed the warm-up (one update per step, never
    restarted); the heat pump ran the planned bursts (its overwrite 0 or 1, switched inside
    hours), the building's own control during the warm-up.
    """
    case = boptest_case
    settings = MpcSettings.from_file('boptest_house', horizon_steps=24)
    policy = supervised_plant(case, builtin_card('boptest_modulation'),
                              builtin_card('boptest_house'), settings, 'dynamic')
    controller = policy.controller
    run = run_period(case, 'peak_heat_day', policy, 1.0, 1.0, record=policy.recorded(case))
    assert [o.decision.source for o in policy.outcomes] == ['optimum'] * 24
    assert controller.estimator.updates == 49 and controller.estimator.resets == 0
    test = run.records[run.records['time'] > run.start_s]
    assert set(test['oveHeaPumY_u'].unique()) == {0.0, 1.0}
    assert run.records.loc[run.records['time'] <= run.start_s, 'oveHeaPumY_u'].isna().all()
    hours = np.floor((test['time'].to_numpy() - 1e-6 - run.start_s) / 3600.0)
    switched = pd.Series(test['oveHeaPumY_u'].to_numpy()).groupby(hours).nunique()
    assert (switched > 1).any()


def test_mshoot_boptest_runs_the_mpc_by_configuration(boptest_case, tmp_path,
                                                      capsys: pytest.CaptureFixture) -> None:
    """
    ``mshoot boptest --controllers baseline,rule,mshoot``: the MPC its test case card names.

    A shortened run (1 day of warm-up, 1 day); the MPC beats the building's own control on
    cost and discomfort, ran the heat pump's modulation in bursts (the rule its setpoint).
    """
    import json
    from mshoot_studies import cli
    card = pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'boptest_cards' / \
        'bestest_hydronic_heat_pump.yaml'
    out = tmp_path / 'hp'
    code = cli.main(['boptest', '--testcase', str(boptest_case.directory), '--card', str(card),
                     '--controllers', 'baseline,rule,mshoot', '--periods', 'peak_heat_day',
                     '--prices', 'dynamic', '--warmup-days', '1', '--days', '1', '--lead', '3',
                     '--margin', '0.5', '--workers', '2', '--out', str(out)])
    assert code == 0
    assert '| mshoot | peak_heat_day | dynamic |' in capsys.readouterr().out
    kpis = {r['controller']: r for r in json.loads((out / 'kpis.json').read_text())}
    assert set(kpis) == {'baseline', 'rule', 'mshoot'}
    assert kpis['mshoot']['cost_tot'] < 0.95 * kpis['baseline']['cost_tot']
    assert kpis['mshoot']['tdis_tot'] <= kpis['baseline']['tdis_tot']
    runs = out / 'runs'
    ours = pd.read_csv(runs / 'mshoot_peak_heat_day_dynamic' / 'records.csv')
    test = ours[ours['time'] > kpis['mshoot']['start_s']]
    assert set(test['oveHeaPumY_u'].unique()) == {0.0, 1.0} and test['oveTSet_u'].isna().all()
    rule = pd.read_csv(runs / 'rule_peak_heat_day_lead3_margin0.5' / 'records.csv')
    assert rule.loc[rule['time'] > kpis['rule']['start_s'], 'oveHeaPumY_u'].isna().all()


def test_a_warm_up_in_the_first_state_is_observed_like_steps() -> None:
    """
    A first state carrying the warm-up (ZoneState history) estimates what steps would.

    Step by step: a forecast and a state every hour (as the core loop offers them). At once:
    one forecast reaching back over the warm-up (``history_steps``), the warm-up as the first
    state's history, in either order (the history waits for the forecast that covers it).
    """
    model = _house()
    settings = MpcSettings.from_file('boptest_house')
    hours = 4
    tout = 2.0 + np.arange(hours + 1.0)
    solar = 50.0 * np.arange(hours + 1.0)
    duty = np.array([0.0, 0.3, 1.0, 0.5, 0.0])
    zone = 293.15 + 0.1 * np.arange(hours + 1.0)
    heat = [_heat(model, d, t, s) for d, t, s in zip(duty, tout, solar)]
    t0 = 10 * HOUR_NS
    names = ['mean_Tout', 'mean_solrad', 'mean_Q_hp']
    # step by step
    steps = controller_for(model, settings)
    for k in range(hours + 1):
        stamp = t0 + k * HOUR_NS
        outputs = {} if k == 0 else {'output_names': names, 'output_values': [
            tout[k - 1], solar[k - 1], heat[k - 1]]}
        assert steps.offer_named_state(stamp, ['T'], [zone[k]], stamp, **outputs) is None
        forecast = _forecast(tout[k], solar[k])
        assert steps.offer_forecast(stamp, 3600.0, forecast, stamp) is None
    # at once: the means over the interval ending at each time (NaN at the first), by output
    means = np.array([[np.nan, *tout[:-1]], [np.nan, *solar[:-1]], [np.nan, *heat[:-1]]])
    history = (list(3600.0 * np.arange(-hours, 1.0)), list(zone), ['Tout', 'solrad', 'Q_hp'],
               list(means.reshape(-1)))
    now = t0 + hours * HOUR_NS
    long = {k: np.concatenate([np.full(hours, v[0]), v]) for k, v in _forecast(0, 0).items()}
    long['Tout'][:hours], long['solar'][:hours] = tout[:-1], solar[:-1]
    long['Tout'][hours:], long['solar'][hours:] = tout[-1], solar[-1]
    for forecast_first in (True, False):
        c = controller_for(model, settings)

        def forecast() -> None:
            assert c.offer_forecast(now, 3600.0, long, now, history_steps=hours) is None

        if forecast_first:
            forecast()
        assert c.offer_named_state(now, ['T'], [zone[-1]], now, output_names=names,
                                   output_values=[tout[-2], solar[-2], heat[-2]],
                                   history=history) is None
        if not forecast_first:
            assert c.estimate is None  # waiting for the forecast that covers the warm-up
            forecast()
        assert c.estimator.resets == 0 and c.estimator.updates == hours + 1
        np.testing.assert_allclose(c.estimate.x, steps.estimate.x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(c.estimate.std, steps.estimate.std, rtol=0, atol=1e-9)
        assert c.estimate.t_s == now / NS_PER_S
    # a forecast whose history is as long as itself is refused
    c = controller_for(model, settings)
    rejection = c.offer_forecast(now, 3600.0, _forecast(0, 0, rows=3), now, history_steps=3)
    assert rejection is not None and 'history_steps' in rejection.reason


def test_controls_by_plant_name() -> None:
    """Settings ``plant_controls``: setpoints name the plant's control, states may too."""
    model = _house()
    c = controller_for(model, MpcSettings.from_file('boptest_house', measured_inputs=''))
    assert c.plant_control_names == ('Y',)
    assert c.offer_forecast(0, 3600.0, _forecast(3.0, 0.0), 0) is None
    assert c.offer_named_state(0, ['T'], [293.15], 0) is None
    applied = c.offer_named_state(HOUR_NS, ['T'], [293.3], HOUR_NS, control_names=['Y'],
                                  control_values=[0.5])
    assert applied is None and c.estimator.resets == 0 and c.estimator.updates == 2
    wrong = c.offer_named_state(2 * HOUR_NS, ['T'], [293.3], 2 * HOUR_NS,
                                control_names=['TSet'], control_values=[0.5])
    assert wrong is not None and 'TSet' in wrong.reason
