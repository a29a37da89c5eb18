"""
BOPTEST's forecast uncertainty: its five reference forecasts, the statistics of the draws.

The references are BOPTEST's own (``forecast_uncertainty/`` of the test case folder beside the
repository, ``../shared/boptest/bestest_hydronic_heat_pump``), requested in this order on one
test case under temperature ``medium``, solar ``low``, seed 1.
"""
import io
import os
import shutil
import subprocess

from mshoot_core.boptest.testcase import TestCase
from mshoot_core.forecast import (ForecastSource, hourly_grid, MAX_HORIZON_S, moving_average,
                                  SOLAR_ERRORS, solar_on_grid, TEMPERATURE_ERRORS,
                                  temperature_on_grid)
from mshoot_core.scenario import forecast_window, synthetic_scenario
from mshoot_core.scenario_forecasts import ScenarioForecasts
from mshoot_core.settings import ForecastErrorSettings, SettingsError
import numpy as np
import pandas as pd
import pytest

from conftest import ROOT

#: BOPTEST's reference requests, in order: file, now [s], horizon [s], interval [s], whether
#: the request draws anew.
REFERENCES = (('put_forecast_uncertain.csv', 0, 86400, 3600, True),
              ('put_forecast_uncertain_5min.csv', 300, 86400, 3600, False),
              ('put_forecast_uncertain_next_hour.csv', 3900, 86400, 3600, True),
              ('put_forecast_uncertain_interval.csv', 3900, 86400, 1800, False),
              ('put_forecast_uncertain_horizon.csv', 3900, 172800, 3600, True))
REFERENCE_ERRORS = ForecastErrorSettings(temperature_uncertainty='medium',
                                         solar_uncertainty='low', seed=1)
#: Sampling error allowed in the statistics tests [standard errors].
Z = 4.0


def reference(case: TestCase, name: str) -> pd.DataFrame:
    """Return one of BOPTEST's reference forecasts of the test case."""
    path = case.directory / 'forecast_uncertainty' / name
    if not path.is_file():
        if os.environ.get('CI') == 'true':
            pytest.fail(f'BOPTEST reference forecast missing at {path} (required under CI)')
        pytest.skip(f'BOPTEST reference forecast not found at {path}')
    return pd.read_csv(path)


def test_the_five_reference_forecasts_are_reproduced(boptest_case: TestCase) -> None:
    """Reproduce TDryBul to the last bit, HGloHor to 1e-4 W/m2, the others as data."""
    source = ForecastSource.from_test_case(boptest_case, REFERENCE_ERRORS)
    for draws, (name, now, horizon, interval, redraw) in enumerate(REFERENCES):
        ref = reference(boptest_case, name)
        points = list(ref.columns[1:])
        before = source.draws
        ours = source.forecast(now, horizon, interval, points)
        assert source.draws == before + redraw, name
        np.testing.assert_array_equal(ours['time'].to_numpy(), ref['time'].to_numpy())
        np.testing.assert_array_equal(ours['TDryBul'].to_numpy(), ref['TDryBul'].to_numpy())
        np.testing.assert_allclose(ours['HGloHor'], ref['HGloHor'], rtol=0, atol=1e-4)
        assert not np.allclose(ours['TDryBul'], boptest_case.forecast_values('TDryBul',
                                                                             ref['time']))
        # every other point: the test case's data (BOPTEST's own copy has more digits)
        others = [p for p in points if p not in ('TDryBul', 'HGloHor')]
        np.testing.assert_allclose(ours[others].to_numpy(), ref[others].to_numpy(),
                                   rtol=1e-6, atol=1e-6, err_msg=name)


def test_the_cli_prints_a_reference_forecast(boptest_case: TestCase, capsys) -> None:
    """A fresh request at 3900 s draws with seed 1 + 3900: BOPTEST's next-hour forecast."""
    from mshoot_studies.cli import main
    ref = reference(boptest_case, 'put_forecast_uncertain_next_hour.csv')
    code = main(['forecast', '--testcase', str(boptest_case.directory), '--time', '3900',
                 '--horizon', '86400', '--interval', '3600', '--temperature-uncertainty',
                 'medium', '--solar-uncertainty', 'low', '--seed', '1', '--points',
                 'TDryBul,HGloHor,LowerSetp[1]'])
    out = capsys.readouterr().out
    assert code == 0
    printed = pd.read_csv(io.StringIO(out))
    assert list(printed.columns) == ['time', 'TDryBul', 'HGloHor', 'LowerSetp[1]']
    assert out.splitlines()[1].startswith('3900,')
    np.testing.assert_array_equal(printed['time'], ref['time'])
    np.testing.assert_array_equal(printed['TDryBul'], ref['TDryBul'])
    np.testing.assert_allclose(printed['HGloHor'], ref['HGloHor'], rtol=0, atol=1e-4)
    np.testing.assert_array_equal(printed['LowerSetp[1]'], ref['LowerSetp[1]'])


def _command() -> str:
    """Return the ``mshoot`` command, as a shell that sourced env.sh finds it."""
    path = shutil.which('mshoot')
    assert path is not None, 'mshoot not on PATH: source env.sh'
    return path


def _mshoot(*args: str) -> subprocess.CompletedProcess:
    """Run the ``mshoot`` command (as a user does)."""
    return subprocess.run([_command(), *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=300, check=False)


def test_the_cli_refuses_bad_options_in_one_line(boptest_case: TestCase) -> None:
    base = ['forecast', '--testcase', str(boptest_case.directory), '--time', '3600']
    cases = {('--horizon', '180000', '--temperature-uncertainty', 'high'): '48 h',
             ('--temperature-uncertainty', 'extreme'): 'invalid choice',
             ('--points', 'TDryBul,Rain'): "'Rain'",
             ('--interval', '0'): 'interval > 0',
             ('--seed', '-1'): '--seed must be in',
             ('--time', 'noon'): "invalid float value: 'noon'"}
    for extra, wording in cases.items():
        done = _mshoot(*base, *extra)
        assert done.returncode == 2, (extra, done.stderr)
        assert done.stdout == ''
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and wording in lines[0], (extra, done.stderr)
    missing = _mshoot('forecast', '--testcase', str(boptest_case.directory))
    assert missing.returncode == 2 and len(missing.stderr.strip().splitlines()) == 1
    assert '--time' in missing.stderr


def test_the_cli_piped_to_head_ends_without_a_traceback(boptest_case: TestCase) -> None:
    done = subprocess.run(f'"{_command()}" forecast --testcase "{boptest_case.directory}" '
                          '--time 0 --horizon 172800 --interval 60 --temperature-uncertainty high '
                          '--solar-uncertainty high --seed 3 | head -n 2', shell=True,
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0
    assert len(done.stdout.splitlines()) == 2 and done.stdout.startswith('time,')
    assert 'Traceback' not in done.stderr and 'Error' not in done.stderr, done.stderr


@pytest.mark.parametrize('level', ['low', 'medium', 'high'])
def test_temperature_errors_follow_the_ar1_model(level: str) -> None:
    """Means, standard deviations and AR coefficient of 2000 draws, within 4 standard errors."""
    model = TEMPERATURE_ERRORS[level]
    draws, points = 2000, 20
    errors = -np.array([temperature_on_grid(np.zeros(points), level, seed)
                        for seed in range(draws)])
    first = errors[:, 0]
    assert abs(first.mean() - model.F0) < Z * model.K0 / np.sqrt(draws)
    assert abs(first.std(ddof=1) - model.K0) < Z * model.K0 / np.sqrt(2 * (draws - 1))
    # the AR(1) step: e[i+1] = F e[i] + mu + K n, pooled over every step of every draw
    x, y = errors[:, :-1].reshape(-1), errors[:, 1:].reshape(-1)
    slope, intercept = np.polyfit(x, y, 1)
    residual = y - slope * x - intercept
    n = x.size
    slope_se = residual.std(ddof=2) / (x.std() * np.sqrt(n))
    assert abs(slope - model.F) < Z * slope_se, (slope, model.F, slope_se)
    assert abs(intercept - model.mu) < Z * residual.std() * np.sqrt(1 / n + x.mean() ** 2
                                                                    / (n * x.var()))
    assert abs(residual.std(ddof=2) - model.K) < Z * model.K / np.sqrt(2 * (n - 2))
    # the last point's mean and spread, from the model's recursion
    i = points - 1
    mean = model.F ** i * model.F0 + model.mu * (1 - model.F ** i) / (1 - model.F)
    std = np.sqrt(model.F ** (2 * i) * model.K0 ** 2
                  + model.K ** 2 * (1 - model.F ** (2 * i)) / (1 - model.F ** 2))
    assert abs(errors[:, i].mean() - mean) < Z * std / np.sqrt(draws)
    assert abs(errors[:, i].std(ddof=1) - std) < Z * std / np.sqrt(2 * (draws - 1))


@pytest.mark.parametrize('level', ['low', 'medium', 'high'])
def test_solar_errors_follow_the_ar1_laplace_model(level: str) -> None:
    """Raw draws: the Laplace first error and innovation (mean, variance 2 b^2), and phi."""
    model = SOLAR_ERRORS[level]
    draws, points = 2000, 20
    errors = np.array([model.draw(np.random.RandomState(seed), points)
                       for seed in range(draws)])
    first, std0 = errors[:, 0], np.sqrt(2) * model.bg0
    assert abs(first.mean() - model.ag0) < Z * std0 / np.sqrt(draws)
    # a Laplace variable's variance 2 b^2 has a sampling std of sqrt(20) b^2 / sqrt(draws)
    assert abs(first.var(ddof=1) - std0 ** 2) < Z * np.sqrt(20) * model.bg0 ** 2 / np.sqrt(draws)
    x, y = errors[:, :-1].reshape(-1), errors[:, 1:].reshape(-1)
    slope, intercept = np.polyfit(x, y, 1)
    residual = y - slope * x - intercept
    slope_se = residual.std(ddof=2) / (x.std() * np.sqrt(x.size))
    assert abs(slope - model.phi) < Z * slope_se
    n = x.size
    assert abs(intercept - model.ag) < Z * residual.std() * np.sqrt(1 / n + x.mean() ** 2
                                                                    / (n * x.var()))
    assert abs(residual.var(ddof=2) - 2 * model.bg ** 2) < Z * np.sqrt(20) * model.bg ** 2 \
        / np.sqrt(n)


def test_solar_forecast_is_bounded_and_dark_at_night() -> None:
    truth = np.array([0, 0, 20, 120, 300, 450, 380, 200, 60, 0, 0, 0], dtype=float)
    for seed in range(200):
        forecast = solar_on_grid(truth, 'high', seed)
        assert np.all(forecast >= 0.2 * truth - 1e-12) and np.all(forecast <= 2 * truth + 1e-12)
        assert np.all(forecast[truth == 0] == 0)
    assert not np.array_equal(solar_on_grid(truth, 'high', 1), truth)
    np.testing.assert_array_equal(solar_on_grid(truth, 'none', 1), truth)
    # the moving average keeps the ends and exact zeros, averages the values given
    np.testing.assert_allclose(moving_average(np.array([3.0, 0.0, 6.0, 9.0, 1.0])),
                               [3.0, 0.0, 5.0, 16 / 3, 1.0])


def test_the_hourly_grid() -> None:
    np.testing.assert_array_equal(hourly_grid(3900.0, 7200.0), [3600.0, 7200.0, 10800.0,
                                                                14400.0])
    assert hourly_grid(0.0, 86400.0).size == 26


def _source(errors: ForecastErrorSettings) -> ForecastSource:
    """Return a source over four days of smooth weather (no files)."""
    times = np.arange(0.0, 4 * 86400.0 + 1, 900.0)
    frame = pd.DataFrame({'T': 275.0 + 5 * np.sin(2 * np.pi * times / 86400.0),
                          'G': np.clip(600 * np.sin(2 * np.pi * (times / 86400.0 - 0.25)), 0,
                                       None), 'price': 0.3}, index=times)
    return ForecastSource(lambda name, at: np.interp(at, times, frame[name].to_numpy()),
                          ('T', 'G', 'price'), errors, 'T', 'G')


def test_draws_are_reproducible_by_seed() -> None:
    errors = ForecastErrorSettings(temperature_uncertainty='high', solar_uncertainty='high',
                                   seed=5)
    # (not seed 6: its solar draw is seed 5's second candidate, s + i * i)
    first = _source(errors).forecast(7200.0, 86400.0, 3600.0)
    again = _source(errors).forecast(7200.0, 86400.0, 3600.0)
    pd.testing.assert_frame_equal(first, again)
    other = _source(ForecastErrorSettings(temperature_uncertainty='high',
                                          solar_uncertainty='high', seed=500)).forecast(
        7200.0, 86400.0, 3600.0)
    assert not np.allclose(first['T'], other['T'])
    assert not np.allclose(first['G'], other['G'])
    np.testing.assert_array_equal(first['price'], other['price'])
    exact = _source(ForecastErrorSettings()).forecast(7200.0, 86400.0, 3600.0)
    assert np.abs(first['T'] - exact['T']).max() > 0.1


def test_the_same_draw_within_one_hour() -> None:
    source = _source(ForecastErrorSettings(temperature_uncertainty='medium',
                                           solar_uncertainty='medium', seed=2))
    at_hour = source.forecast(3600.0, 36000.0, 1800.0)
    later = source.forecast(5400.0, 36000.0, 1800.0)
    assert source.draws == 1
    # the same errors: the later request's rows are the first request's, one row on
    pd.testing.assert_frame_equal(later.iloc[:-1].reset_index(drop=True),
                                  at_hour.iloc[1:].reset_index(drop=True))
    source.forecast(7199.0, 36000.0, 1800.0)
    assert source.draws == 1
    next_hour = source.forecast(7200.0, 36000.0, 1800.0)
    assert source.draws == 2
    assert not np.allclose(next_hour['T'].to_numpy()[:-2], at_hour['T'].to_numpy()[2:])
    source.forecast(7300.0, 39600.0, 1800.0)  # same hour, another horizon: redrawn
    assert source.draws == 3


def test_horizons_over_48_h_are_refused_with_errors() -> None:
    uncertain = _source(ForecastErrorSettings(temperature_uncertainty='low'))
    uncertain.forecast(0.0, MAX_HORIZON_S, 3600.0)
    with pytest.raises(ValueError, match=r"48 h\) with forecast uncertainty \['low'\], got "
                       r"176400 s \(points \['T'\]\)"):
        uncertain.forecast(0.0, MAX_HORIZON_S + 3600.0, 3600.0)
    # a point without errors has no such limit
    assert len(uncertain.forecast(0.0, 72 * 3600.0, 3600.0, ['G', 'price'])) == 73
    assert len(_source(ForecastErrorSettings()).forecast(0.0, 72 * 3600.0, 3600.0)) == 73


def test_bad_requests_and_settings_are_refused() -> None:
    source = _source(ForecastErrorSettings(solar_uncertainty='low'))
    for args, wording in (((-1.0, 3600.0, 3600.0), 'time >= 0'),
                          ((0.0, -1.0, 3600.0), 'horizon >= 0'),
                          ((0.0, 3600.0, 0.0), 'interval > 0'),
                          ((float('nan'), 3600.0, 3600.0), 'finite time')):
        with pytest.raises(ValueError, match=wording):
            source.forecast(*args)
    with pytest.raises(ValueError, match='distinct forecast points'):
        source.forecast(0.0, 3600.0, 3600.0, ['T', 'rain'])
    with pytest.raises(SettingsError, match='temperature_uncertainty must be one of'):
        ForecastErrorSettings(temperature_uncertainty='severe')
    with pytest.raises(SettingsError) as info:
        ForecastErrorSettings(solar_uncertainty='max', seed=-3)
    assert len(info.value.problems) == 2


def test_scenario_forecasts_change_the_weather_only() -> None:
    scenario = synthetic_scenario(hours=73)
    exact = ScenarioForecasts(scenario)
    pd.testing.assert_frame_equal(exact.window(5, 10), forecast_window(scenario, 5, 10))
    errors = ForecastErrorSettings(temperature_uncertainty='high', solar_uncertainty='high',
                                   seed=4)
    window = ScenarioForecasts(scenario, errors).window(5, 10)
    truth = forecast_window(scenario, 5, 10)
    others = [c for c in truth.columns if c not in ('Tout', 'solrad')]
    pd.testing.assert_frame_equal(window[others], truth[others])
    assert np.abs(window['Tout'] - truth['Tout']).max() > 0.1
    source = ForecastSource(lambda name, at: np.interp(at, scenario.index.to_numpy(float),
                                                       scenario[name].to_numpy(float)),
                            ('Tout', 'solrad'), errors, 'Tout', 'solrad')
    expected = source.forecast(5 * 3600.0, 10 * 3600.0, 3600.0)
    np.testing.assert_array_equal(window['Tout'], expected['Tout'])
    np.testing.assert_array_equal(window['solrad'], expected['solrad'])
    with pytest.raises(ValueError, match='48 h'):
        ScenarioForecasts(scenario, errors).window(0, 49)


def test_the_cli_prints_a_control_cards_forecast(boptest_case: TestCase, capsys) -> None:
    """``--card``: the card source's interval means, band and price, with the errors."""
    from mshoot_core.boptest.forecasts import ForecastSpec, TestCaseForecasts
    from mshoot_studies.cli import main
    t0 = 16 * 86400.0 + 3600.0
    code = main(['forecast', '--testcase', str(boptest_case.directory), '--card',
                 'boptest_house', '--price', 'highly_dynamic', '--time', f'{t0:g}',
                 '--horizon', '43200', '--interval', '3600', '--temperature-uncertainty',
                 'high', '--solar-uncertainty', 'high', '--seed', '11'])
    assert code == 0
    printed = pd.read_csv(io.StringIO(capsys.readouterr().out))
    errors = ForecastErrorSettings(temperature_uncertainty='high', solar_uncertainty='high',
                                   seed=11)
    expected = TestCaseForecasts(boptest_case, ForecastSpec.from_card('boptest_house'),
                                 'highly_dynamic', errors).frame(t0, 12, 3600.0)
    assert list(printed.columns) == ['time', *expected.columns]
    np.testing.assert_array_equal(printed['time'], expected.index)
    np.testing.assert_allclose(printed[list(expected.columns)], expected, rtol=1e-14, atol=0)
    bad = {('--interval', '7000'): 'whole number',
           ('--points', 'Tout,rain'): "unknown columns ['rain']",
           ('--price', 'free'): "price scenario 'free'",
           ('--card', 'r1c1'): "no 'testcase_forecast' section"}
    for extra, wording in bad.items():
        done = _mshoot('forecast', '--testcase', str(boptest_case.directory), '--card',
                       'boptest_house', '--time', f'{t0:g}', '--horizon', '43200', *extra)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and done.stdout == '', (extra, done.stderr)
        assert len(lines) == 1 and wording in lines[0], (extra, done.stderr)
