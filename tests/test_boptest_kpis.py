"""BOPTEST KPIs: hand-computed trajectories on a tiny test case, and a real baseline by hand."""
import json
import pathlib

from mshoot_core.boptest.kpi_calculator import compute_kpis, KPI_NAMES, kpi_records, peak_power
from mshoot_core.boptest.plant import BoptestPlant
from mshoot_core.boptest.testcase import TestCase
import numpy as np
import pandas as pd
import pytest

DAY = 86400.0


def _write(folder: pathlib.Path, name: str, rows: dict) -> None:
    pd.DataFrame(rows).to_csv(folder / 'Resources' / name, index=False)


@pytest.fixture
def tiny_case(tmp_path: pathlib.Path) -> TestCase:
    """Return a test case of 2 m2 whose data change once, at 1 d + 1 h (rows at the changes)."""
    (tmp_path / 'Resources').mkdir()
    (tmp_path / 'wrapped.fmu').write_bytes(b'')  # never loaded here
    (tmp_path / 'config.json').write_text(json.dumps({'name': 'tiny', 'area': 2.0}))
    (tmp_path / 'days.json').write_text(json.dumps({'p': 8}))  # test period from 1 day
    (tmp_path / 'kpis.json').write_text(json.dumps({
        'OperativeZoneTemperature[1]': ['reaTZon_y'],
        'ElectricPower': ['reaPFan_y', 'reaPHeaPum_y', 'reaPPumEmi_y'],
        'CO2Concentration[1]': ['reaCO2RooAir_y']}))
    times = [0.0, DAY + 3600.0, 3 * DAY]
    _write(tmp_path, 'dataFromModel.csv', {
        'time': times, 'LowerSetp[1]': [294.15, 295.15, 295.15],
        'UpperSetp[1]': [297.15, 297.15, 297.15], 'UpperCO2[1]': [800.0] * 3})
    _write(tmp_path, 'prices.csv', {
        'time': times, 'PriceElectricPowerConstant': [0.2] * 3,
        'PriceElectricPowerDynamic': [0.1, 0.3, 0.3],
        'PriceElectricPowerHighlyDynamic': [0.1, 0.5, 0.5]})
    _write(tmp_path, 'emissions.csv', {'time': times, 'EmissionsElectricPower': [0.5] * 3})
    _write(tmp_path, 'weather.csv', {'time': times, 'TDryBul': [273.15] * 3})
    return TestCase.load(tmp_path)


def _tiny_records() -> pd.DataFrame:
    """
    Return records every 600 s over [1 d, 1 d + 2 h] (k = 0..12), plus one row on either side.

    k <= 5: T 293.65 K, heat pump 1000 W, CO2 700 ppm; k >= 6 (from 1 h on): T 298.15 K,
    3000 W, 1000 ppm. Fan 100 W and pump 20 W throughout. The rows outside the period carry
    values that would show if they were counted.
    """
    k = np.arange(-1, 14)
    late = k >= 6
    return pd.DataFrame({
        'time': DAY + 600.0 * k,
        'reaTZon_y': np.where(late, 298.15, 293.65),
        'reaPHeaPum_y': np.where(late, 3000.0, 1000.0),
        'reaPFan_y': np.full(k.size, 100.0),
        'reaPPumEmi_y': np.full(k.size, 20.0),
        'reaCO2RooAir_y': np.where(late, 1000.0, 700.0),
        'reaHeaPumY_y': np.where((k == 3) | (k == 4) | (k >= 9), 0.5, 0.0),
    }).assign(**{'reaTZon_y': lambda f: f['reaTZon_y'].where(k.clip(0, 12) == k, 250.0),
                 'reaPHeaPum_y': lambda f: f['reaPHeaPum_y'].where(k.clip(0, 12) == k, 1e6)})


def test_kpis_hand_computed(tiny_case: TestCase) -> None:
    table = _tiny_records()
    start, end = DAY, DAY + 7200.0
    kpis = compute_kpis(table, tiny_case, start, end, 'dynamic', step_wall_s=[1.0, 3.0],
                        control_step_s=3600.0)
    # discomfort: 0.5 K below 294.15 up to k = 5 (5 intervals of 600 s), then 1 K above 297.15
    # from k = 6 (6 intervals); the interval 5-6 is a trapezoid of 0.5 and 1
    assert kpis['tdis_tot'] == pytest.approx((5 * 600 * 0.5 + 600 * 0.75 + 6 * 600 * 1.0) / 3600)
    # power 1120 W then 3120 W
    energy_j = 5 * 600 * 1120 + 600 * (1120 + 3120) / 2 + 6 * 600 * 3120
    assert kpis['ener_tot'] == pytest.approx(energy_j / 3.6e6 / 2.0)
    # dynamic price 0.1 EUR/kWh before 1 d + 1 h (k <= 5), 0.3 after
    cost = 5 * 600 * 1120 * 0.1 + 600 * (1120 * 0.1 + 3120 * 0.3) / 2 + 6 * 600 * 3120 * 0.3
    assert kpis['cost_tot'] == pytest.approx(cost / 3.6e6 / 2.0)
    assert kpis['emis_tot'] == pytest.approx(0.5 * energy_j / 3.6e6 / 2.0)
    # CO2 200 ppm above 800 from k = 6; 100 on average over the interval 5-6
    assert kpis['idis_tot'] == pytest.approx((600 * 100 + 6 * 600 * 200) / 3600)
    # 15 min bins: the largest mean is 3120 W (bins made of k >= 6 samples only)
    assert kpis['pele_tot'] == pytest.approx(3120 / 2.0 / 1000)
    assert kpis['time_rat'] == pytest.approx(2.0 / 3600)
    assert kpis['tdis_zones'] == {'1': pytest.approx(kpis['tdis_tot'])}
    assert kpis['pgas_tot'] is None and kpis['pdih_tot'] is None
    constant = compute_kpis(table, tiny_case, start, end)
    assert constant['cost_tot'] == pytest.approx(0.2 * energy_j / 3.6e6 / 2.0)
    assert constant['time_rat'] is None
    assert set(KPI_NAMES) <= set(constant)


def test_kpi_records_per_price(tiny_case: TestCase) -> None:
    records = kpi_records(_tiny_records(), tiny_case, DAY, DAY + 7200.0, controller='baseline',
                          period='p')
    assert [r['price'] for r in records] == ['constant', 'dynamic', 'highly_dynamic']
    assert all(r['controller'] == 'baseline' and r['period'] == 'p' for r in records)
    costs = [r['cost_tot'] for r in records]
    assert costs[0] < costs[1] < costs[2]
    assert len({r['ener_tot'] for r in records}) == 1


def test_power_signs_correct_a_reversed_output(tiny_case: TestCase) -> None:
    """An output written with the wrong sign (the fan here) is counted positive when named."""
    table = _tiny_records().assign(reaPFan_y=-100.0)
    start, end = DAY, DAY + 7200.0
    as_written = compute_kpis(table, tiny_case, start, end, 'dynamic')
    corrected = compute_kpis(table, tiny_case, start, end, 'dynamic',
                             power_signs={'reaPFan_y': -1})
    right = compute_kpis(_tiny_records(), tiny_case, start, end, 'dynamic')
    for key in ('ener_tot', 'cost_tot', 'emis_tot', 'pele_tot'):
        assert corrected[key] == pytest.approx(right[key], rel=1e-12)
        assert corrected['as_defined'][key] == pytest.approx(as_written[key], rel=1e-12)
    # 200 W of the 1120 W / 3120 W: the fan's 100 W counted as -100 W
    assert as_written['ener_tot'] == pytest.approx(right['ener_tot'] * (1 - 200 / 2120),
                                                   rel=0.05)
    assert corrected['power_signs'] == {'reaPFan_y': -1.0}
    assert 'as_defined' not in right and corrected['tdis_tot'] == right['tdis_tot']
    with pytest.raises(ValueError,
                       match=r"\['reaTZon_y'\] are not power outputs of the kpis.json of tiny"):
        compute_kpis(table, tiny_case, start, end, power_signs={'reaTZon_y': -1})
    with pytest.raises(ValueError, match='expected -1 or 1'):
        compute_kpis(table, tiny_case, start, end, power_signs={'reaPFan_y': 2})


def test_peak_power_bins() -> None:
    # bins [0, 900), [900, 1800), [1800, 2700), [2700, 3600): means 2, 10, 5, 1
    times = np.arange(10) * 300.0
    power = np.array([1, 2, 3, 10, 20, 0, 5, 5, 5, 1], dtype=float)
    assert peak_power(times, power) == 10.0
    # shifted by 300 s: [900, 1800) holds the samples 3, 10, 20
    assert peak_power(times + 300.0, power) == pytest.approx(11.0)


def test_kpis_refuse_bad_input(tiny_case: TestCase) -> None:
    table = _tiny_records()
    with pytest.raises(ValueError, match='do not cover'):
        compute_kpis(table, tiny_case, DAY, DAY + 3 * 3600.0)
    with pytest.raises(ValueError, match='lacks the KPI outputs'):
        compute_kpis(table.drop(columns='reaPFan_y'), tiny_case, DAY, DAY + 3600.0)
    with pytest.raises(ValueError, match='unknown price scenario'):
        compute_kpis(table, tiny_case, DAY, DAY + 3600.0, price='flat')
    with pytest.raises(ValueError, match='empty test period'):
        compute_kpis(table, tiny_case, DAY, DAY)


@pytest.fixture(scope='module')
def short_baseline(boptest_case: TestCase) -> tuple[pd.DataFrame, float, float]:
    """Run the real FMU: peak_heat_day with 1 day of warm-up and 2 days of test, baseline."""
    warmup_start, start, end = boptest_case.test_period('peak_heat_day', 1, 2)
    with BoptestPlant(boptest_case) as plant:
        plant.start(warmup_start)
        plant.advance(end)
        return plant.records(), start, end


def _by_hand(table: pd.DataFrame, folder: pathlib.Path, start: float, end: float,
             area: float) -> dict:
    """Compute the definitions of the README independently (raw CSVs, pandas, explicit sums)."""
    period = table[(table['time'] >= start) & (table['time'] <= end)]
    t = period['time'].to_numpy()

    def held(file: str, column: str) -> np.ndarray:
        raw = pd.read_csv(folder / 'Resources' / file).set_index('time')[column]
        return raw.reindex(raw.index.union(t)).ffill().loc[t].to_numpy()

    def integral(y: np.ndarray) -> float:
        return float(np.sum((y[1:] + y[:-1]) / 2 * np.diff(t)))

    temp = period['reaTZon_y'].to_numpy()
    below = np.clip(held('dataFromModel.csv', 'LowerSetp[1]') - temp, 0, None)
    above = np.clip(temp - held('dataFromModel.csv', 'UpperSetp[1]'), 0, None)
    power = (period['reaPHeaPum_y'] + period['reaPFan_y'] + period['reaPPumEmi_y']).to_numpy()
    excess = np.clip(period['reaCO2RooAir_y'].to_numpy()
                     - held('dataFromModel.csv', 'UpperCO2[1]'), 0, None)
    quarter = pd.Series(power, index=pd.to_timedelta(t, unit='s')).resample('15min').mean()
    hand = {'tdis_tot': integral(below + above) / 3600,
            'idis_tot': integral(excess) / 3600,
            'ener_tot': integral(power) / 3.6e6 / area,
            'emis_tot': integral(power * held('emissions.csv', 'EmissionsElectricPower'))
            / 3.6e6 / area,
            'pele_tot': quarter.max() / area / 1000}
    for name in ('Constant', 'Dynamic', 'HighlyDynamic'):
        hand[name] = integral(power * held('prices.csv', f'PriceElectricPower{name}')) \
            / 3.6e6 / area
    return hand


def test_short_baseline_kpis_by_hand(boptest_case: TestCase, short_baseline) -> None:
    """The baseline KPIs by mshoot equal BOPTEST's definitions computed by hand."""
    table, start, end = short_baseline
    assert np.diff(table['time']).max() == 60.0
    hand = _by_hand(table, boptest_case.directory, start, end, boptest_case.area_m2)
    records = kpi_records(table, boptest_case, start, end)
    for name in ('tdis_tot', 'idis_tot', 'ener_tot', 'emis_tot', 'pele_tot'):
        assert records[0][name] == pytest.approx(hand[name], rel=1e-9, abs=1e-12), name
    for record, name in zip(records, ('Constant', 'Dynamic', 'HighlyDynamic')):
        assert record['cost_tot'] == pytest.approx(hand[name], rel=1e-9)
    # a January baseline heats and lets the zone below the band at times (the published
    # 14-day figures are 8.4 K h and 3.48 kWh/m2, i.e. about 0.25 kWh/m2 a day)
    assert 0.1 < records[0]['ener_tot'] / 2 < 0.5
    assert records[0]['tdis_tot'] > 0
