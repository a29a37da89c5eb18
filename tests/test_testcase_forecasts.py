"""The test case forecast source: a control card's series, bands and prices from the data."""
import pathlib

from mshoot_core import fmu_cache
from mshoot_core.boptest.forecasts import ForecastSpec, rises_after_rest, TestCaseForecasts
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.forecast import ForecastSource
from mshoot_core.settings import ForecastErrorSettings
import numpy as np
import pandas as pd
import pytest

KELVIN = 273.15
OFFICE = (pathlib.Path(__file__).resolve().parents[1].parent / 'shared' / 'boptest'
          / 'multizone_office_simple_hydronic')
#: The packaged control model of the heat pump house (its testcase_forecast section).
CARD = 'boptest_house'


def old_interval_means(case, column, t_s, step_s):
    """Return interval means as the house's forecast took them before the source (900 s)."""
    n_sub = max(1, int(round(step_s / 900.0)))
    offsets = (np.arange(n_sub) + 0.5) * step_s / n_sub
    values = case.lookup(column, (t_s[:, None] + offsets[None, :]).reshape(-1))
    return values.reshape(t_s.size, n_sub).mean(axis=1)


def old_forecast_frame(case, t_s, steps, step_s, price, margin_k=0.0, upper_margin_k=0.0):
    """Return the house's forecast frame as it was built before the source."""
    times = float(t_s) + np.arange(steps + 1) * float(step_s)
    frame = pd.DataFrame(index=pd.Index(times, name='time_s'))
    frame['Tout'] = old_interval_means(case, 'TDryBul', times, step_s) - KELVIN
    frame['solar'] = old_interval_means(case, 'HGloHor', times, step_s)
    frame['gains'] = (old_interval_means(case, 'InternalGainsCon[1]', times, step_s)
                      + old_interval_means(case, 'InternalGainsRad[1]', times, step_s))
    frame['price'] = old_interval_means(case, case.price_column(price), times, step_s)
    n_sub = max(1, int(round(step_s / 900.0)))
    ends = (times[:, None] - np.arange(n_sub)[None, :] * step_s / n_sub).reshape(-1)
    ends = np.maximum(ends, times[0])
    lower = case.lookup('LowerSetp[1]', ends).reshape(-1, n_sub)
    upper = case.lookup('UpperSetp[1]', ends).reshape(-1, n_sub)
    lo = lower.max(axis=1) - KELVIN + margin_k
    hi = upper.min(axis=1) - KELVIN - upper_margin_k
    frame['comfort_min'] = lo
    frame['comfort_max'] = np.maximum(hi, lo)
    return frame


@pytest.mark.parametrize('price', ['constant', 'dynamic', 'highly_dynamic'])
def test_the_house_forecast_equals_the_old_frame(boptest_case, price) -> None:
    source = TestCaseForecasts(boptest_case, ForecastSpec.from_card(CARD), price)
    for t0, steps, step, margins in ((16 * 86400.0, 36, 3600.0, (0.0, 0.0)),
                                     (23 * 86400.0 + 900.0, 24, 3600.0, (0.3, 0.0)),
                                     (100 * 86400.0 + 1800.0, 12, 1800.0, (0.5, 0.2)),
                                     (300 * 86400.0, 4, 900.0, (0.0, 0.4))):
        old = old_forecast_frame(boptest_case, t0, steps, step, price, *margins)
        new = source.frame(t0, steps, step)  # the raw band: margins are the controller's
        if margins != (0.0, 0.0):
            new['comfort_min'] = new['comfort_min'] + margins[0]
            new['comfort_max'] = np.maximum(new['comfort_max'] - margins[1], new['comfort_min'])
        assert list(new.columns) == list(old.columns)
        np.testing.assert_array_equal(new.index, old.index)
        np.testing.assert_allclose(new.to_numpy(), old.to_numpy(), rtol=0, atol=1e-12)


def test_the_band_is_the_tightest_over_the_interval(boptest_case) -> None:
    source = TestCaseForecasts(boptest_case, ForecastSpec.from_card(CARD))
    frame = source.frame(16 * 86400.0, 24, 3600.0)
    assert set(np.round(frame['comfort_min'], 2)) == {15.0, 21.0}
    assert set(np.round(frame['comfort_max'], 2)) == {24.0, 30.0}
    # an occupied interval anywhere in (t_k-1, t_k] makes the row's band the occupied one
    rises = np.flatnonzero(np.diff(frame['comfort_min'].to_numpy()) > 0) + 1
    for k in rises:
        inside = frame.index[k - 1] + np.arange(1, 5) * 900.0
        assert boptest_case.lookup('LowerSetp[1]', inside).max() - KELVIN == frame[
            'comfort_min'].iloc[k]


def test_a_series_with_a_lead_runs_ahead_of_its_column(boptest_case) -> None:
    """lead_s: row k holds the column's means an interval later (a schedule ahead of a band)."""
    spec = ForecastSpec.from_section({'series': {
        'now': {'columns': ['LowerSetp[1]'], 'offset': -KELVIN},
        'ahead': {'columns': ['LowerSetp[1]'], 'offset': -KELVIN, 'lead_s': 3600.0}}})
    frame = TestCaseForecasts(boptest_case, spec).frame(16 * 86400.0, 24, 3600.0)
    np.testing.assert_array_equal(frame['ahead'].to_numpy()[:-1], frame['now'].to_numpy()[1:])
    assert frame['ahead'].to_numpy()[:-1].tolist() != frame['now'].to_numpy()[:-1].tolist()


def test_rises_after_rest_need_the_whole_rest() -> None:
    values = np.array([0, 0, 0, 5, 5, 0, 5, 0, 0, 0, 5, 5, 0, 0])
    np.testing.assert_array_equal(np.flatnonzero(rises_after_rest(values, 3)), [3, 10])
    np.testing.assert_array_equal(np.flatnonzero(rises_after_rest(values, 1)), [3, 6, 10])
    np.testing.assert_array_equal(np.flatnonzero(rises_after_rest(values, 4)), [])


def test_a_series_leads_further_after_a_long_rest(boptest_case) -> None:
    """
    rest_s, rest_lead_s: the rows before a rise after a long rest run rest_lead_s ahead.

    The others run lead_s ahead. The house's band rests 10 h or more every night and never a
    whole day: with 8 h of rest every morning leads 3 h, with 24 h none.
    """
    series = {'now': {'columns': ['LowerSetp[1]'], 'offset': -KELVIN - 15.0},
              'ahead': {'columns': ['LowerSetp[1]'], 'offset': -KELVIN - 15.0, 'lead_s': 3600.0}}

    def frame(rest_s):
        spec = ForecastSpec.from_section({'series': {**series, 'lead': {
            **series['ahead'], 'rest_s': rest_s, 'rest_lead_s': 10800.0}}})
        return TestCaseForecasts(boptest_case, spec).frame(16 * 86400.0, 47, 3600.0)
    never = frame(86400.0)
    np.testing.assert_array_equal(never['lead'], never['ahead'])
    nights = frame(8 * 3600.0)
    now = nights['now'].to_numpy()
    starts = np.flatnonzero((now[1:] > 0) & (now[:-1] <= 0)) + 1  # the band's rises
    assert starts.size == 2
    lead = nights['lead'].to_numpy()
    for k in starts:  # 3 h ahead before each rise: the band's value from 3 h earlier on
        np.testing.assert_array_equal(lead[k - 3:k], now[k:k + 3])
        np.testing.assert_array_equal(lead[k - 4], nights['ahead'].to_numpy()[k - 4])
    ends = np.flatnonzero((now[1:] <= 0) & (now[:-1] > 0)) + 1
    np.testing.assert_array_equal(lead[ends - 1], nights['ahead'].to_numpy()[ends - 1])


@pytest.mark.parametrize('entry, match', [
    ({'rest_s': 3600.0}, 'rest_s and rest_lead_s go together'),
    ({'rest_s': 3600.0, 'rest_lead_s': 1800.0}, r'rest_lead_s >= lead_s \(3600\)'),
    ({'rest_s': 0.0, 'rest_lead_s': 7200.0}, 'rest_s > 0'),
])
def test_a_bad_rest_lead_is_refused(entry, match) -> None:
    with pytest.raises(ValueError, match=match):
        ForecastSpec.from_section({'series': {'x': {'columns': ['LowerSetp[1]'],
                                                    'lead_s': 3600.0, **entry}}})


@pytest.mark.skipif(not OFFICE.is_dir(), reason=f'needs the office test case at {OFFICE}')
def test_the_offices_pumps_start_at_4_h_after_a_weekend() -> None:
    """The office's control card: the BMS's pumps from 6 h, from 4 h after 36 h unoccupied."""
    card = (pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'boptest_cards'
            / 'multizone_office_simple_hydronic_control.yaml')
    source = TestCaseForecasts(TestCase.load(OFFICE), ForecastSpec.from_card(card))
    for day, first in ((67, None), (68, 4), (69, 6), (107, None), (110, 4)):  # Sun, Mon, Tue
        occupied = source.frame(day * 86400.0, 23, 3600.0)['occupied'].to_numpy()
        hours = np.flatnonzero(occupied > 0)
        assert (hours[0] if hours.size else None) == first
        assert hours.size == 0 or hours[-1] == 17  # pumps off from 19 h: the band's hour ahead


def test_a_missing_column_names_the_folder_and_the_files(boptest_case, tmp_path,
                                                         monkeypatch) -> None:
    # an empty cache (the derived weather lives beside the cache's folder, so a folder of its
    # own): a weather of the office derived by another run would supply TDryBul
    monkeypatch.setenv(fmu_cache.CACHE_ENV, str(tmp_path / 'empty' / 'fmu'))
    spec = ForecastSpec.from_section({'series': {'Tout': {'columns': ['TDryBul'],
                                                          'offset': -KELVIN},
                                                 'x': {'columns': ['Nope[1]']}}}, 'card.yaml')
    with pytest.raises(ValueError, match=r"card.yaml.*lacks the column \['Nope\[1\]'\].*"
                                         r'searched .*weather\.csv'):
        TestCaseForecasts(boptest_case, spec)
    if OFFICE.is_dir():  # no weather.csv there: the temperature is missing, said so
        with pytest.raises(ValueError, match=r"lacks the columns \['TDryBul', 'Nope\[1\]'\]"):
            TestCaseForecasts(TestCase.load(OFFICE), spec)


def test_a_price_scenario_without_a_column_is_refused(boptest_case) -> None:
    spec = ForecastSpec.from_section({'series': {'price': {'price': {
        'constant': 'PriceElectricPowerConstant'}}}})
    with pytest.raises(ValueError, match=r"no price column for the price scenario 'dynamic'"):
        TestCaseForecasts(boptest_case, spec, 'dynamic')
    with pytest.raises(ValueError, match='series'):
        ForecastSpec.from_section({'series': {'Tout': {'offset': 1.0}}})


def test_several_zones_get_a_band_each() -> None:
    if not OFFICE.is_dir():
        pytest.skip(f'no office test case at {OFFICE}')
    case = TestCase.load(OFFICE)
    spec = ForecastSpec.from_section({
        'series': {'gas': {'price': {'constant': 'PriceGasPower'}},
                   'gains_nZ': {'columns': ['InternalGainsCon[nZ]', 'InternalGainsRad[nZ]']}},
        'bands': {z: {'lower': f'LowerSetp[{z}]', 'upper': f'UpperSetp[{z}]'}
                  for z in ('nZ', 'sZ')}})
    frame = TestCaseForecasts(case, spec).frame(20 * 86400.0, 24, 3600.0)
    assert list(frame.columns) == ['gas', 'gains_nZ', 'comfort_min', 'comfort_max',
                                   'comfort_min_nZ', 'comfort_max_nZ', 'comfort_min_sZ',
                                   'comfort_max_sZ']
    np.testing.assert_array_equal(frame['comfort_min'], frame['comfort_min_nZ'])
    assert frame['comfort_min_sZ'].max() > frame['comfort_min_sZ'].min()


def test_errors_touch_temperature_and_solar_only(boptest_case) -> None:
    spec = ForecastSpec.from_card(CARD)
    t0 = 16 * 86400.0 + 1200.0
    exact = TestCaseForecasts(boptest_case, spec, 'dynamic').frame(t0, 36, 3600.0)
    errors = ForecastErrorSettings(temperature_uncertainty='high', solar_uncertainty='high',
                                   seed=3)
    source = TestCaseForecasts(boptest_case, spec, 'dynamic', errors)
    noisy = source.frame(t0, 36, 3600.0)
    for column in ('gains', 'price', 'comfort_min', 'comfort_max'):
        np.testing.assert_array_equal(noisy[column], exact[column])
    assert np.abs(noisy['Tout'] - exact['Tout']).mean() > 0.2
    assert np.abs(noisy['solar'] - exact['solar']).max() > 5.0
    # the interval means of BOPTEST's forecast of the same request, sampled at the midpoints
    direct = ForecastSource.from_test_case(boptest_case, errors)
    times = t0 + np.arange(37 * 4) * 900.0 + 450.0
    values = direct.at('TDryBul', t0, 37 * 3600.0, times).reshape(37, 4).mean(axis=1)
    np.testing.assert_allclose(noisy['Tout'], values - KELVIN, rtol=0, atol=1e-12)
    # the same draw within the hour; a new one the next hour; the seed decides
    again = source.frame(t0 + 600.0, 36, 3600.0)
    assert source.source.draws == 1 and np.isfinite(again['Tout']).all()
    same_seed = TestCaseForecasts(boptest_case, spec, 'dynamic', errors).frame(t0, 36, 3600.0)
    pd.testing.assert_frame_equal(same_seed, noisy)
    with pytest.raises(ValueError, match='48 h'):
        source.frame(t0, 48, 3600.0)


def test_scenario_forecasts_with_a_card_serve_its_source(boptest_case) -> None:
    """The forecaster's core: a BOPTEST period's step forecast is the card's frame."""
    from mshoot_core.boptest.period_scenario import period_scenario
    from mshoot_core.scenario_forecasts import ScenarioForecasts
    from mshoot_core.models.card import builtin_card
    scenario = period_scenario(boptest_case, 'typical_heat_day', hours=48, price='constant')
    errors = ForecastErrorSettings(temperature_uncertainty='low', seed=2)
    forecasts = ScenarioForecasts(scenario, errors, builtin_card(CARD))
    assert forecasts.series == ('Tout', 'solar', 'gains')
    window = forecasts.window(3, 24)
    source = TestCaseForecasts(boptest_case, ForecastSpec.from_card(CARD), 'constant',
                               errors)
    expected = source.frame(scenario['fmu_time_s'].iloc[3], 24, 3600.0)
    np.testing.assert_array_equal(window.to_numpy(), expected.to_numpy())
    assert window.index[0] == scenario.index[3] and window.index.name == scenario.index.name
    with pytest.raises(ValueError, match='48 h'):
        forecasts.window(3, 48)
    # a card without the section: the scenario's rows, as without a card
    plain = ScenarioForecasts(scenario, None, builtin_card('r1c1'))
    assert plain.testcase is None and plain.series is None
    pd.testing.assert_frame_equal(plain.window(3, 5), ScenarioForecasts(scenario).window(3, 5))


def test_a_period_scenario_has_the_forecasts_band(tmp_path: pathlib.Path) -> None:
    """One band over an interval: the scenario's rows and the forecast agree, mid-hour too."""
    import json
    from mshoot_core.boptest.forecasts import BandSource, interval_band
    from mshoot_core.boptest.period_scenario import period_scenario
    day = 86400.0
    (tmp_path / 'Resources').mkdir()
    (tmp_path / 'wrapped.fmu').write_bytes(b'')  # never loaded here
    (tmp_path / 'config.json').write_text(json.dumps({'name': 'blip', 'area': 10.0}))
    (tmp_path / 'days.json').write_text(json.dumps({'p': 16}))  # test period from day 9
    (tmp_path / 'kpis.json').write_text(json.dumps({'OperativeZoneTemperature[1]': ['T'],
                                                   'ElectricPower': ['P']}))
    times = np.arange(0.0, 30 * day, 1800.0)
    blip = np.isclose(np.mod(times, day), 12.5 * 3600.0)  # raised for half an hour at 12:30
    pd.DataFrame({'time': times, 'LowerSetp[1]': np.where(blip, 295.15, 293.15),
                  'UpperSetp[1]': np.where(blip, 296.15, 297.15),
                  'PriceElectricPowerConstant': 0.2, 'TDryBul': 275.0, 'HGloHor': 100.0}
                 ).to_csv(tmp_path / 'Resources' / 'weather.csv', index=False)
    case = TestCase.load(tmp_path)
    scenario = period_scenario(case, 'p', hours=48, price='constant')
    start = 9 * day
    assert scenario['fmu_time_s'].iloc[0] == start
    # the rows at 13:00 hold the half hour before: the tightest band, not the band at 13:00
    at_one = np.isclose(np.mod(scenario['fmu_time_s'], day), 13 * 3600.0)
    assert at_one.sum() == 2
    np.testing.assert_allclose(scenario.loc[at_one, ['comfort_min', 'comfort_max']],
                               [[22.0, 23.0]] * 2, atol=1e-9)
    np.testing.assert_allclose(scenario.loc[~at_one, 'comfort_min'], 20.0, atol=1e-9)
    np.testing.assert_allclose(scenario.loc[~at_one, 'comfort_max'], 24.0, atol=1e-9)
    # the forecast of a card with the same band: the same rows
    spec = ForecastSpec.from_section({'series': {'Tout': {'columns': ['TDryBul']}},
                                      'bands': {'1': {'lower': 'LowerSetp[1]',
                                                      'upper': 'UpperSetp[1]'}}})
    frame = TestCaseForecasts(case, spec).frame(start, 48, 3600.0)
    np.testing.assert_array_equal(frame['comfort_min'].to_numpy(), scenario['comfort_min'])
    np.testing.assert_array_equal(frame['comfort_max'].to_numpy(), scenario['comfort_max'])
    lo, hi = interval_band(case, BandSource('LowerSetp[1]', 'UpperSetp[1]'),
                           scenario['fmu_time_s'].to_numpy(), 3600.0)
    np.testing.assert_array_equal(lo, scenario['comfort_min'])


def test_a_series_at_given_times_leads_as_the_frame_does(boptest_case) -> None:
    """
    series_at: the columns at each time plus the lead, exact.

    With a rest lead of 3 h after 8 h at rest, every sample (a minute apart) of the 3 h before
    a rise of the house's band reads the band 3 h later, every other one 1 h later.
    """
    spec = ForecastSpec.from_section({'series': {'lead': {
        'columns': ['LowerSetp[1]'], 'offset': -KELVIN - 15.0, 'lead_s': 3600.0,
        'rest_s': 8 * 3600.0, 'rest_lead_s': 10800.0}}})
    source = TestCaseForecasts(boptest_case, spec)
    samples = 16 * 86400.0 + 60.0 * np.arange(48 * 60)
    values = source.series_at('lead', samples, 60.0)
    band = boptest_case.lookup('LowerSetp[1]', samples) - KELVIN - 15.0
    rises = samples[1:][(band[1:] > 0) & (band[:-1] <= 0)]
    assert rises.size == 2
    before = np.zeros(samples.size, dtype=bool)
    for rise in rises:  # from 3 h to 1 h before it (the last hour leads 1 h into the band)
        before |= (samples >= rise - 10800.0) & (samples < rise - 3600.0)
    later = np.where(before, 10800.0, 3600.0)
    np.testing.assert_array_equal(
        values, boptest_case.lookup('LowerSetp[1]', samples + later) - KELVIN - 15.0)
    assert values[before].min() > 0 and before.sum() == 2 * 120
