"""The BOPTEST benchmark under forecast uncertainty: scenarios, forecast margin, ROS == core."""
import json
import math
import pathlib

from mshoot_core.boptest.testcase import TestCase
from mshoot_core.forecast import (BENCHMARK_UNCERTAINTY, scenario_fields, scenario_suffix,
                                  TEMPERATURE_ERRORS, uncertainty_runs)
from mshoot_core.forecast_margin import (allowance, error_processes, ErrorProcess,
                                         forecast_error_std)
from mshoot_core.models.card import build_model, builtin_card, load_card
from mshoot_core.settings import ForecastErrorSettings, MpcSettings, SettingsError
import numpy as np
import pytest

#: The heat pump house's card (its boptest.control: the control card and settings boptest_house).
HOUSE_CARD = pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'boptest_cards' / \
    'bestest_hydronic_heat_pump.yaml'


def test_uncertainty_runs_parse_levels_and_seeds() -> None:
    runs = uncertainty_runs(BENCHMARK_UNCERTAINTY)
    assert [(e.temperature_uncertainty, e.solar_uncertainty, e.seed) for e in runs] == [
        ('none', 'none', 0), ('high', 'high', 1), ('high', 'high', 2), ('high', 'high', 3),
        ('low', 'low', 1), ('medium', 'medium', 1)]
    assert uncertainty_runs(['high=4', 'high=4,5', 'none=9']) == [
        ForecastErrorSettings('high', 'high', 4), ForecastErrorSettings('high', 'high', 5),
        ForecastErrorSettings()]
    for bad in (['extreme'], ['high=x'], ['high=-1'], []):
        with pytest.raises(ValueError):
            uncertainty_runs(bad)
    assert scenario_fields(None) == {'uncertainty': 'none', 'seed': None}
    assert scenario_fields(runs[0]) == {'uncertainty': 'none', 'seed': None}
    assert scenario_fields(runs[2]) == {'uncertainty': 'high', 'seed': 2}
    assert [scenario_suffix(e) for e in runs[:2]] == ['', '_high_s1']
    assert allowance(runs[0]) == allowance(None) == {}
    assert allowance(ForecastErrorSettings('low', 'medium', 3)) == {
        'forecast_uncertainty': 'medium'}


def test_forecast_margin_settings_are_validated() -> None:
    settings = MpcSettings.from_file('boptest_house')
    assert settings.comfort.error_kinds == {'Tout': 'temperature', 'solar': 'solar'}
    assert settings.comfort.forecast_uncertainty == 'none'  # perfect forecasts: no margin
    for bad in ({'forecast_error_inputs': 'Tout=wind'}, {'forecast_error_inputs': 'Tout'},
                {'forecast_uncertainty': 'extreme'},
                {'forecast_error_inputs': '', 'forecast_uncertainty': 'high'},
                {'forecast_margin_std': -1.0}):
        with pytest.raises(SettingsError):
            settings.replace(**bad)
    with pytest.raises(ValueError, match='not an input of the model'):
        error_processes({'wind': 'temperature'}, 'high', ('Tout', 'solar'))


def test_error_process_std_is_the_ar1_variance() -> None:
    """The std at lead k is the AR(1) recursion's: closed form of BOPTEST's parameters."""
    level = TEMPERATURE_ERRORS['high']
    (process,) = error_processes({'Tout': 'temperature'}, 'high', ('Tout',))
    for k in (0, 1, 5, 36):
        a2 = level.F ** 2
        var = a2 ** k * level.K0 ** 2 + level.K ** 2 * (1 - a2 ** k) / (1 - a2)
        assert process.std(k) == pytest.approx(math.sqrt(var), rel=1e-12)


def test_forecast_error_std_matches_monte_carlo() -> None:
    """
    The propagated std of the house model's states equals that of simulated AR(1) errors.

    2000 error sequences of BOPTEST's ``high`` level on the outdoor temperature and the
    irradiance, drawn as the model states them, pushed through the control model along 24 h;
    the states' spread against the propagation within the sampling error (5 %).
    """
    model = build_model(load_card(builtin_card('boptest_house')))
    names = list(model.input_names)
    hours = np.arange(24)
    u = np.zeros((24, len(names)))
    u[:, names.index('Tout')] = 2.0 + 3.0 * np.sin(hours / 24 * 2 * np.pi)
    u[:, names.index('solar')] = np.clip(500 * np.sin((hours - 7) / 10 * np.pi), 0, None)
    u[:, names.index('gains')] = 200.0
    u[:, names.index('d')] = 0.3
    x0 = np.array([294.0, 295.0, 287.0])
    processes = [ErrorProcess(names.index('Tout'), 1.5, 0.95, 0.7),
                 ErrorProcess(names.index('solar'), 60.0, 0.67, 40.0)]  # unbounded: linear
    std = forecast_error_std(model, x0, u, 3600.0, processes)
    rng = np.random.default_rng(5)
    n = 2000
    errors = np.zeros((n, 24, 2))
    errors[:, 0] = rng.normal(0, [1.5, 60.0], (n, 2))
    for k in range(1, 24):
        errors[:, k] = errors[:, k - 1] * [0.95, 0.67] + rng.normal(0, [0.7, 40.0], (n, 2))
    x = np.tile(x0, (n, 1))
    spread = [np.zeros(3)]
    for k in range(24):
        inputs = np.tile(u[k], (n, 1))
        inputs[:, names.index('Tout')] += errors[:, k, 0]
        inputs[:, names.index('solar')] += errors[:, k, 1]
        x, _ = model.simulate_intervals(x, inputs, 3600.0)
        spread.append(x.std(axis=0))
    spread = np.array(spread)
    assert std[0].tolist() == [0.0, 0.0, 0.0]
    np.testing.assert_allclose(std[1:, :2], spread[1:, :2], rtol=0.05)
    assert std[24, 0] > 0.3  # a day ahead the errors move the zone by tenths of a kelvin
    # no error at night for an irradiance bounded by its forecast: zero solar, zero spread
    night = [ErrorProcess(names.index('solar'), 60.0, 0.67, 40.0, bounded=True)]
    dark = u.copy()
    dark[:, names.index('solar')] = 0.0
    assert not forecast_error_std(model, x0, dark, 3600.0, night).any()


def test_uncertainty_table_means_ranges_and_verdict() -> None:
    from mshoot_studies.boptest_report import uncertainty_table
    base = {'period': 'p', 'price': 'c'}
    records = [dict(base, controller='baseline', uncertainty='none', tdis_tot=5.0, cost_tot=1.0),
               dict(base, controller='rule', uncertainty='none', tdis_tot=1.0, cost_tot=0.9),
               dict(base, controller='mshoot', uncertainty='none', tdis_tot=0.5, cost_tot=0.6)]
    records += [dict(base, controller='mshoot', uncertainty='high', seed=s, tdis_tot=t,
                     cost_tot=c) for s, t, c in ((1, 0.6, 0.62), (2, 0.9, 0.63), (3, 1.2, 0.61))]
    lines = uncertainty_table(records)
    row = next(line for line in lines if line.startswith('| p |'))
    assert '0.90 [0.60-1.20] / 0.6200 [0.6100-0.6300]' in row  # mean [range] of 3 seeds
    assert '| yes |' in row and '+3.3 / +0.40' in row
    records[-1]['tdis_tot'] = 1.5  # the mean 1.0: not below the rule's 1.0
    assert '**no**' in next(line for line in uncertainty_table(records)
                            if line.startswith('| p |'))


@pytest.mark.ros
def test_benchmark_under_uncertainty_over_ros_equals_the_core_run(
        boptest_case: TestCase, tmp_path: pathlib.Path) -> None:
    """
    The benchmark's mshoot run under ``high`` over ROS equals the core run with its errors.

    Seed 3: its records carry the scenario, and it equals the core run with the same errors to
    1e-9, which differs from the core run on perfect forecasts (the errors reached the plan).

    Shortened: peak_heat_day, 1 day of warm-up, 1 day of test, the dynamic price.
    """
    from mshoot_core.boptest.kpi_calculator import compute_kpis
    from mshoot_core.boptest.plant import run_period
    from mshoot_core.boptest.supervision import supervised_plant
    from mshoot_nodes.boptest_run import main
    from mshoot_studies.boptest import prepare_card
    out = tmp_path / 'boptest'
    assert main(['--controllers', 'mshoot', '--uncertainty', 'high=3', '--periods',
                 'peak_heat_day', '--prices', 'dynamic', '--warmup-days', '1', '--days', '1',
                 '--out', str(out), '--testcase', str(boptest_case.directory),
                 '--card', str(HOUSE_CARD)]) == 0
    (record,) = json.loads((out / 'kpis.json').read_text())
    assert (record['controller'], record['uncertainty'], record['seed']) == ('mshoot', 'high', 3)
    (run,) = json.loads((out / 'runs.json').read_text())
    assert run['name'] == 'mshoot_peak_heat_day_dynamic_high_s3' and run['seed'] == 3
    import pandas as pd
    ros = pd.read_csv(out / 'runs' / run['name'] / 'boptest_records.csv')

    def core(errors: ForecastErrorSettings | None) -> pd.DataFrame:
        # the house's card names its MPC: control card and settings boptest_house
        settings = MpcSettings.from_file('boptest_house', **allowance(errors))
        plant = prepare_card(HOUSE_CARD, boptest_case.directory, tmp_path / 'plant')
        policy = supervised_plant(boptest_case, plant, builtin_card('boptest_house'), settings,
                                  'dynamic', errors)
        result = run_period(boptest_case, 'peak_heat_day', policy, warmup_days=1, length_days=1,
                            record=policy.recorded(boptest_case))
        assert all(not o.decision.fallback for o in policy.outcomes)
        return result.records

    high = core(ForecastErrorSettings('high', 'high', 3))
    columns = ['time', 'reaTZon_y', 'reaPHeaPum_y', 'reaQHeaPumCon_y', 'oveHeaPumY_u']
    assert len(ros) == len(high)
    np.testing.assert_allclose(ros[columns].to_numpy(), high[columns].to_numpy(), rtol=1e-9,
                               atol=1e-9, equal_nan=True)
    kpis = compute_kpis(high, boptest_case, run['start_s'], run['end_s'], 'dynamic')
    assert record['cost_tot'] == pytest.approx(kpis['cost_tot'], rel=1e-9, abs=1e-12)
    perfect = core(None)
    test = high['time'].to_numpy() > run['start_s']
    moved = np.abs(high.loc[test, 'oveHeaPumY_u'].to_numpy()
                   - perfect.loc[test, 'oveHeaPumY_u'].to_numpy())
    assert np.nanmax(moved) == 1.0  # some minute the heat pump ran in one and not the other
