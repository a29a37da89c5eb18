"""Any BOPTEST folder and a card: several zones and energy vectors by hand, the real office."""
import json
import pathlib

from mshoot_core import fmu_cache
from mshoot_core.boptest import weather
from mshoot_core.boptest.kpi_calculator import compute_kpis
from mshoot_core.boptest.plant import BoptestPlant
from mshoot_core.boptest.testcase import TestCase
import numpy as np
import pandas as pd
import pytest

DAY = 86400.0
#: The example cards of docs/boptest_testcases.md.
CARDS = pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'boptest_cards'


def _write(folder: pathlib.Path, name: str, rows: dict) -> None:
    pd.DataFrame(rows).to_csv(folder / 'Resources' / name, index=False)


@pytest.fixture
def two_zone_case(tmp_path: pathlib.Path) -> TestCase:
    """
    Return a 10 m2 test case of two zones and three energy vectors.

    Zones a and b, electricity, gas and district heat, its FMU in models/, the band in
    setpoints.csv, one file with a 'Time' column; the data change at 1 d + 1 h.
    """
    (tmp_path / 'Resources').mkdir()
    (tmp_path / 'models').mkdir()
    (tmp_path / 'models' / 'wrapped.fmu').write_bytes(b'')  # never loaded here
    (tmp_path / 'config.json').write_text(json.dumps({'name': 'two', 'area': 10.0}))
    (tmp_path / 'days.json').write_text(json.dumps({'p': 8}))
    (tmp_path / 'kpis.json').write_text(json.dumps({
        'OperativeZoneTemperature[a]': ['Ta'], 'OperativeZoneTemperature[b]': ['Tb'],
        'ElectricPower': ['Pfan', 'Ppump'], 'GasPower': ['Pboiler'],
        'DistrictHeatingPower': ['Pdh'], 'CO2Concentration[a]': ['CO2a'],
        'None': ['weather']}))
    times = [0.0, DAY + 3600.0, 3 * DAY]
    _write(tmp_path, 'setpoints.csv', {
        'time': times, 'LowerSetp[a]': [294.15] * 3, 'UpperSetp[a]': [297.15] * 3,
        'LowerSetp[b]': [293.15, 295.15, 295.15], 'UpperSetp[b]': [299.15] * 3,
        'UpperCO2[a]': [800.0] * 3})
    _write(tmp_path, 'internalGains.csv', {'Time': times, 'Gain[a]': [1.0] * 3})
    _write(tmp_path, 'prices.csv', {
        'time': times, 'PriceElectricPowerConstant': [0.2] * 3,
        'PriceElectricPowerDynamic': [0.1, 0.3, 0.3],
        'PriceElectricPowerHighlyDynamic': [0.1, 0.5, 0.5],
        'PriceGasPower': [0.05] * 3, 'PriceDistrictHeatingPower': [0.07, 0.09, 0.09]})
    _write(tmp_path, 'emissions.csv', {
        'time': times, 'EmissionsElectricPower': [0.5] * 3, 'EmissionsGasPower': [0.2] * 3,
        'EmissionsDistrictHeatingPower': [0.1] * 3})
    return TestCase.load(tmp_path)


def test_folder_layout(two_zone_case: TestCase) -> None:
    case = two_zone_case
    assert case.fmu_path == case.directory / 'models' / 'wrapped.fmu'
    assert case.zones == ['a', 'b']
    assert case.energy_outputs == {'ElectricPower': ['Pfan', 'Ppump'],
                                   'DistrictHeatingPower': ['Pdh'], 'GasPower': ['Pboiler']}
    assert case.resource_files == ['emissions.csv', 'internalGains.csv', 'prices.csv',
                                   'setpoints.csv']
    assert case.lookup('LowerSetp[b]', [DAY, DAY + 3600.0]).tolist() == [293.15, 295.15]
    assert case.lookup('Gain[a]', [10.0]).tolist() == [1.0]  # the 'Time' column
    assert case.band_columns('b') == ('LowerSetp[b]', 'UpperSetp[b]')
    with pytest.raises(ValueError, match='unknown energy vector'):
        case.price_column('constant', 'Coal')


def test_bad_folders_are_named(tmp_path: pathlib.Path, two_zone_case: TestCase) -> None:
    with pytest.raises(FileNotFoundError, match='models/wrapped.fmu'):
        TestCase.load(tmp_path / 'Resources')
    folder = two_zone_case.directory
    (folder / 'Resources' / 'notes.csv').write_text('a,b\n1,2\n')
    with pytest.raises(ValueError, match='notes.csv: no "time" column'):
        TestCase.load(folder).lookup('LowerSetp[a]', [0.0])


def _records() -> pd.DataFrame:
    """Return records every 600 s over [1 d, 1 d + 2 h]; k >= 6 (from 1 h on) later values."""
    k = np.arange(13)
    late = k >= 6
    return pd.DataFrame({
        'time': DAY + 600.0 * k,
        'Ta': np.where(late, 298.15, 293.65),      # 0.5 K below, then 1 K above [294.15, 297.15]
        'Tb': np.full(k.size, 294.15),             # 1 K above 293.15, then 1 K below 295.15
        'Pfan': np.full(k.size, 100.0), 'Ppump': np.full(k.size, 20.0),
        'Pboiler': np.where(late, 5000.0, 1000.0), 'Pdh': np.full(k.size, 400.0),
        'CO2a': np.where(late, 1000.0, 700.0), 'weather': np.zeros(k.size)})


def test_zones_and_energy_vectors_by_hand(two_zone_case: TestCase) -> None:
    """Discomfort averaged over zones (and per zone); each vector priced by its own column."""
    kpis = compute_kpis(_records(), two_zone_case, DAY, DAY + 7200.0, 'dynamic')
    zone_a = (5 * 600 * 0.5 + 600 * 0.75 + 6 * 600 * 1.0) / 3600
    # zone b: 0 K inside [293.15, 299.15] until 1 h, then 1 K below 295.15 (interval 5-6: 0.5)
    zone_b = (600 * 0.5 + 6 * 600 * 1.0) / 3600
    assert kpis['tdis_zones'] == {'a': pytest.approx(zone_a), 'b': pytest.approx(zone_b)}
    assert kpis['tdis_tot'] == pytest.approx((zone_a + zone_b) / 2)
    gas_j = 5 * 600 * 1000 + 600 * 3000 + 6 * 600 * 5000
    electric_j, heat_j = 120.0 * 7200, 400.0 * 7200
    assert kpis['ener_tot'] == pytest.approx((gas_j + electric_j + heat_j) / 3.6e6 / 10.0)
    electric_cost = (5 * 600 * 120 * 0.1 + 600 * 120 * 0.2 + 6 * 600 * 120 * 0.3)
    heat_cost = (5 * 600 * 400 * 0.07 + 600 * 400 * 0.08 + 6 * 600 * 400 * 0.09)
    assert kpis['cost_tot'] == pytest.approx(
        (electric_cost + 0.05 * gas_j + heat_cost) / 3.6e6 / 10.0)
    assert kpis['emis_tot'] == pytest.approx(
        (0.5 * electric_j + 0.2 * gas_j + 0.1 * heat_j) / 3.6e6 / 10.0)
    assert kpis['pele_tot'] == pytest.approx(120 / 10.0 / 1000)
    assert kpis['pgas_tot'] == pytest.approx(5000 / 10.0 / 1000)
    assert kpis['pdih_tot'] == pytest.approx(400 / 10.0 / 1000)
    # one zone with CO2: its excess, not halved
    assert kpis['idis_tot'] == pytest.approx((600 * 100 + 6 * 600 * 200) / 3600)


def test_a_missing_price_column_is_named(two_zone_case: TestCase) -> None:
    folder = two_zone_case.directory
    frame = pd.read_csv(folder / 'Resources' / 'prices.csv').drop(columns='PriceGasPower')
    frame.to_csv(folder / 'Resources' / 'prices.csv', index=False)
    with pytest.raises(ValueError, match="'PriceGasPower'"):
        compute_kpis(_records(), TestCase.load(folder), DAY, DAY + 7200.0)


# -- the real office: Model Exchange, two zones, gas ---------------------------------------------
def test_office_folder(office: TestCase) -> None:
    assert office.zones == ['sZ', 'nZ'] and office.area_m2 == 5000.0
    assert list(office.energy_outputs) == ['ElectricPower', 'GasPower']
    assert 'setpoints.csv' in office.resource_files and 'weather.csv' not in office.resource_files
    assert office.lookup('LowerSetp[nZ]', [0.0]).tolist() == [289.15]
    plant = BoptestPlant(office, record=[])
    assert plant.interface == 'ModelExchange'
    assert plant.inputs['bms_oveTZonSetMinNz_u'].lower == 288.15


def test_office_overwrite_is_an_event_that_acts(office: TestCase) -> None:
    """Model Exchange: a setpoint overwrite and its switch take effect (events), then release."""
    t0 = (office.days['peak_heat_day'] - 7) * DAY + 21 * 3600.0
    applied = 'bms_oveTZonSetMinNz_y'  # the FMU's reading of the signal its BMS follows
    with BoptestPlant(office, record=['structure_reaTZonNz_y', applied]) as plant:
        plant.start(t0)
        plant.advance(t0 + 3600.0)
        own = plant.records(t0 + 60.0, t0 + 3600.0)
        plant.advance(t0 + 3 * 3600.0, {'bms_oveTZonSetMinNz_u': 303.15})
        forced = plant.records(t0 + 3660.0, t0 + 3 * 3600.0)
        plant.advance(t0 + 4 * 3600.0)
        released = plant.records(t0 + 3 * 3600.0 + 60.0, t0 + 4 * 3600.0)
        assert plant.read([applied])[applied] == released[applied].iloc[-1]
        with pytest.raises(ValueError, match='not Real variables'):
            plant.read(['no_such_variable'])
    assert (own[applied] == 289.15).all()  # the night set-back of the BMS
    assert (forced['bms_oveTZonSetMinNz_u'] == 303.15).all()
    assert (forced[applied] == 303.15).all()
    assert released['bms_oveTZonSetMinNz_u'].isna().all() and (released[applied] == 289.15).all()


def test_office_baseline_through_mshoot_boptest(office: TestCase, tmp_path: pathlib.Path,
                                                capsys: pytest.CaptureFixture) -> None:
    """
    ``mshoot boptest`` runs the office's baseline (ME, libgfortran.so.3 stand-in) from its card.

    A shortened run (1 day of warm-up, 1 day of test); its KPIs equal BOPTEST's definitions
    written out again from the stored records (gas priced by PriceGasPower).
    """
    from mshoot_studies import cli
    out = tmp_path / 'office'
    code = cli.main(['boptest', '--testcase', str(office.directory), '--card',
                     str(CARDS / 'multizone_office_simple_hydronic.yaml'), '--controllers',
                     'baseline', '--periods', 'peak_heat_day', '--warmup-days', '1', '--days',
                     '1', '--workers', '1', '--out', str(out), '--report',
                     str(tmp_path / 'page.md')])
    assert code == 0
    printed = capsys.readouterr().out
    assert '| baseline | peak_heat_day | constant |' in printed and 'tdis [nZ]' in printed
    page = (tmp_path / 'page.md').read_text()
    assert page.startswith('# BOPTEST `multizone_office_simple_hydronic`: baseline\n')
    assert (out / 'kpis.md').read_text() in page and '`peak_heat_day` (1 days each' in page
    assert "`heating_cooling_reaPProCoo_y` counted as written (below zero; the card's" in page
    # the per-zone figure of the period beside the page, linked from it
    assert page.endswith('\n![peak_heat_day: each zone under every controller]'
                         '(page/peak_heat_day.png)')
    assert (tmp_path / 'page' / 'peak_heat_day.png').stat().st_size > 10_000
    from mshoot_studies.boptest_report import plot_zones
    run = pd.read_csv(out / 'runs' / 'baseline_peak_heat_day' / 'records.csv')
    with pytest.raises(ValueError, match=r"run 'cut' has no \['structure_reaTZonSz_y'\]"):
        plot_zones(office, {'cut': run.drop(columns='structure_reaTZonSz_y')}, 0.0, 1.0, '',
                   tmp_path / 'cut.png')
    records = json.loads((out / 'kpis.json').read_text())
    assert [r['price'] for r in records] == ['constant', 'dynamic', 'highly_dynamic']
    table = pd.read_csv(out / 'runs' / 'baseline_peak_heat_day' / 'records.csv')
    _, start, end = office.test_period('peak_heat_day', 1, 1)
    period = table[(table['time'] >= start) & (table['time'] <= end)]
    t = period['time'].to_numpy()
    assert np.diff(t).max() == 60.0 and t[0] == start and t[-1] == end
    raw = {name: pd.read_csv(office.directory / 'Resources' / name)
           for name in ('setpoints.csv', 'prices.csv')}

    def held(file: str, column: str) -> np.ndarray:
        frame = raw[file]
        rows = np.searchsorted(frame['time'].to_numpy(), t, side='right') - 1
        return frame[column].to_numpy()[rows]

    tdis = {}
    for zone, output in (('nZ', 'structure_reaTZonNz_y'), ('sZ', 'structure_reaTZonSz_y')):
        temperature = period[output].to_numpy()
        excess = (np.clip(held('setpoints.csv', f'LowerSetp[{zone}]') - temperature, 0, None)
                  + np.clip(temperature - held('setpoints.csv', f'UpperSetp[{zone}]'), 0, None))
        tdis[zone] = float(np.sum((excess[1:] + excess[:-1]) / 2 * np.diff(t)) / 3600)
    written = period[office.energy_outputs['ElectricPower']].sum(axis=1).to_numpy()
    chiller = period['heating_cooling_reaPProCoo_y'].to_numpy()
    assert chiller.max() <= 0.0  # the build's chiller power is below zero (the card's signs)
    gas = period['heating_cooling_reaPProHea_y'].to_numpy()
    area_j = 3.6e6 * 5000.0
    integral = (lambda y: float(np.sum((y[1:] + y[:-1]) / 2 * np.diff(t))))
    for record in records:
        assert record['tdis_zones'] == {z: pytest.approx(v, rel=1e-9, abs=1e-12)
                                        for z, v in tdis.items()}
        assert record['tdis_tot'] == pytest.approx((tdis['nZ'] + tdis['sZ']) / 2, rel=1e-9)
        assert record['power_signs'] == {'heating_cooling_reaPProCoo_y': -1.0}
        column = {'constant': 'PriceElectricPowerConstant',
                  'dynamic': 'PriceElectricPowerDynamic',
                  'highly_dynamic': 'PriceElectricPowerHighlyDynamic'}[record['price']]
        # the KPIs count the chiller positive; BOPTEST's sums as written are kept beside them
        for kpis, electric in ((record, written - 2 * chiller), (record['as_defined'], written)):
            assert kpis['ener_tot'] == pytest.approx(integral(electric + gas) / area_j,
                                                     rel=1e-9)
            cost = (integral(electric * held('prices.csv', column))
                    + integral(gas * held('prices.csv', 'PriceGasPower')))
            assert kpis['cost_tot'] == pytest.approx(cost / area_j, rel=1e-9)
        assert record['pgas_tot'] > 0 and record['pele_tot'] > 0 and record['pdih_tot'] is None
    # a March day in Brussels: the boiler heats
    assert gas.max() > 1000.0


def test_mshoot_boptest_refuses_bad_input_in_one_line(boptest_case: TestCase,
                                                      tmp_path: pathlib.Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    from mshoot_studies import cli
    card = CARDS / 'bestest_hydronic_heat_pump.yaml'
    base = ['boptest', '--testcase', str(boptest_case.directory), '--out', str(tmp_path)]
    named = '  control: {card: boptest_house, settings: boptest_house}\n'
    assert named in card.read_text()
    unnamed, misnamed, missing = (tmp_path / f'{n}.yaml' for n in ('unnamed', 'misnamed',
                                                                   'missing'))
    unnamed.write_text(card.read_text().replace(named, ''))
    misnamed.write_text(card.read_text().replace(named, named.replace('card:', 'cards:')))
    missing.write_text(card.read_text().replace(named, named.replace('card: boptest_house',
                                                                     'card: absent.yaml')))
    cases = [
        (['--card', str(unnamed), '--controllers', 'mshoot'], 'names no boptest.control card'),
        (['--card', str(unnamed), '--controllers', 'mshoot', '--control-card', 'boptest_house'],
         'names no boptest.control settings (or give --mpc-settings)'),
        (['--card', str(card), '--controllers', 'mshoot', '--mpc-settings', 'no_such'],
         "no settings file 'no_such'"),
        (['--card', str(misnamed), '--controllers', 'mshoot'],
         "boptest.control: unknown key 'cards'; allowed: card, settings"),
        (['--card', str(missing), '--controllers', 'mshoot'],
         "boptest.control.card: 'absent.yaml' is neither a file"),
        (['--card', str(card), '--controllers', 'mshoot', '--control-card', 'r1c1',
          '--mpc-settings', 'boptest_house'], 'cost_output must be one of'),
        (['--card', str(card), '--controllers', 'baseline,fancy'], 'expected some of'),
        (['--card', str(card), '--periods', 'peak_cool_day'], 'unknown test period'),
        (['--card', str(CARDS.parent / 'index.md')], 'kind boptest'),
    ]
    no_zones = tmp_path / 'no_zones.yaml'
    no_zones.write_text(card.read_text().replace("setpoint_zones: {TSet: '1'}", ''))
    cases.append((['--card', str(no_zones), '--controllers', 'rule'], 'setpoint_zones'))
    # the heat pump's card names no cooling setpoint nor supply reset: no axis of them
    cases.append((['--card', str(card), '--controllers', 'rule', '--cooling-margin', '0.5'],
                  'cooling margins [0.5] given, but the rule has no cooling setpoint'))
    cases.append((['--card', str(card), '--controllers', 'rule', '--supply-shifts', '0', '-10'],
                  'supply shifts [0.0, -10.0] given, but the rule has no supply reset'))
    cases.append((['--card', str(card), '--controllers', 'rule', '--margin', '-1'],
                  'expected margin_k >= 0'))
    cases.append((['--card', str(card), '--controllers', 'rule', '--lead', '1', '--rule-grids',
                   str(tmp_path)], '--rule-grids takes the rule from a tuning: not with --lead'))
    cases.append((['--card', str(card), '--controllers', 'rule', '--rule-grids', str(tmp_path)],
                  'no rule tuning grid for '))
    for extra, message in cases:
        assert cli.main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert message in err and err.count('\n') == 1, (extra, err)


# -- the office's weather: derived once from its FMU's weather station outputs -------------------
def _mos(case: TestCase) -> np.ndarray:
    """Return the rows of the test case's .mos weather table (its 30 columns)."""
    path = next((case.directory / 'Resources').glob('*.mos'))
    lines = [line for line in path.read_text().splitlines() if line[:1].isdigit()]
    return np.array([[float(v) for v in line.split()] for line in lines])


def test_weather_outputs_map_to_boptest_names():
    outputs = weather.weather_outputs(['weaSta_reaWeaTDryBul_y', 'weaSta_reaWeaRelHum_y',
                                       'reaWeaHGloHor_y', 'reaTZon_y', 'weaSta_reaWeaFoo_y'])
    assert outputs == {'TDryBul': 'weaSta_reaWeaTDryBul_y', 'relHum': 'weaSta_reaWeaRelHum_y',
                       'HGloHor': 'reaWeaHGloHor_y'}
    with pytest.raises(ValueError, match='no weather station outputs'):
        weather.weather_outputs(['reaTZon_y'])


def test_office_weather_derived_once_and_found_by_lookup(office, tmp_path, monkeypatch):
    monkeypatch.setenv(fmu_cache.CACHE_ENV, str(tmp_path / 'fmu'))  # this test's cache
    case = TestCase.load(office.directory)
    with pytest.raises(ValueError, match='python -m mshoot_core.boptest.weather'):
        case.lookup('TDryBul', [0.0])
    path = weather.ensure_weather(case, days=1.0)
    assert path == case.derived_weather_path and tmp_path in path.parents
    stamp = path.stat().st_mtime_ns
    assert weather.ensure_weather(case, days=1.0) == path and path.stat().st_mtime_ns == stamp
    case = TestCase.load(office.directory)
    assert {'TDryBul', 'HGloHor', 'HDirNor', 'HDifHor', 'relHum', 'winSpe', 'solZen'} <= set(
        case.columns)
    assert np.diff(case.row_times('TDryBul')).tolist() == [900.0] * 96
    mos = _mos(case)
    hours = np.arange(25) * 3600.0
    np.testing.assert_allclose(case.lookup('TDryBul', hours), mos[:25, 1] + 273.15, atol=1e-6)
    np.testing.assert_allclose(case.lookup('relHum', hours), mos[:25, 3] / 100.0, atol=1e-6)
    # the radiation of an hour [Wh/m2] against the mean of the derived irradiance [W/m2] over
    # the day (the FMU interpolates the hourly sums; 97 rows 900 s apart, trapezoids)
    rows = case.row_times('HGloHor')
    irradiance = case.lookup('HGloHor', rows)
    day_wh = float(np.sum((irradiance[1:] + irradiance[:-1]) / 2.0) * 900.0 / 3600.0)
    assert day_wh == pytest.approx(mos[1:25, 8].sum(), rel=0.05)
    assert day_wh > 100.0  # a winter day in Brussels, not a dark one
    # a later window is derived from where the rows end (contiguous) and merged in; a window
    # the rows cover is not run again
    held = case.lookup('TDryBul', rows)
    weather.ensure_weather(case, days=0.25, first_day=1.0)
    assert path.stat().st_mtime_ns != stamp
    stamp = path.stat().st_mtime_ns
    assert weather.ensure_weather(case, days=0.5, first_day=0.5) == path
    assert path.stat().st_mtime_ns == stamp
    case = TestCase.load(office.directory)
    assert np.diff(case.row_times('TDryBul')).tolist() == [900.0] * 120
    np.testing.assert_array_equal(case.lookup('TDryBul', rows), held)
    hours = np.arange(25, 31) * 3600.0
    np.testing.assert_allclose(case.lookup('TDryBul', hours), mos[25:31, 1] + 273.15, atol=1e-6)
    with pytest.raises(ValueError, match='times outside the data'):
        case.lookup('TDryBul', [1.5 * 86400.0])
    with pytest.raises(ValueError, match='first_day >= 0 and days > 0'):
        weather.ensure_weather(case, days=0.0)


def test_a_test_case_card_names_its_mpc(boptest_case: TestCase, tmp_path: pathlib.Path) -> None:
    """``boptest.control``: files relative to the card's folder, else packaged names."""
    from mshoot_core.models.card import builtin_card, CardError, load_card
    from mshoot_core.settings import SETTINGS_DIR
    from mshoot_studies.boptest import prepare_card
    card = CARDS / 'bestest_hydronic_heat_pump.yaml'
    text = card.read_text()
    folder = tmp_path / 'mine'
    folder.mkdir()
    (folder / 'model.yaml').write_text(builtin_card('boptest_house').read_text())
    (folder / 'mpc.yaml').write_text((SETTINGS_DIR / 'boptest_house.yaml').read_text())
    named = '  control: {card: boptest_house, settings: boptest_house}\n'
    mine = folder / 'house.yaml'
    mine.write_text(text.replace(named, '  control: {card: model.yaml, settings: mpc.yaml}\n'))
    loaded = load_card(mine)
    assert loaded.boptest['control'] == {'card': str(folder / 'model.yaml'),
                                         'settings': str(folder / 'mpc.yaml')}
    assert load_card(card).boptest['control'] == {
        'card': str(builtin_card('boptest_house')),
        'settings': str(SETTINGS_DIR / 'boptest_house.yaml')}
    # the copy mshoot boptest runs from (another folder) keeps naming the same files
    copy = load_card(prepare_card(mine, boptest_case.directory, tmp_path / 'out'))
    assert copy.boptest['control'] == loaded.boptest['control']
    # a packaged name is not taken for a path, nor a path for a packaged name
    for entry, message in (('{card: model}', "'model' is neither a file"),
                           ('{settings: ../mpc.yaml}', "'../mpc.yaml' is neither a file"),
                           ('{}', 'control'), ('{card: 3}', 'control')):
        mine.write_text(text.replace(named, f'  control: {entry}\n'))
        with pytest.raises(CardError, match=message):
            load_card(mine)


def test_benchmark_runs_planned_once_for_both_runners():
    """
    ``plan_runs`` (``mshoot boptest`` and ``make boptest``): the runs and their names.

    The baseline once for every price, the rule once per distinct parameters, mshoot per
    forecast scenario and price (or once for every price when its forecast reads none).
    """
    from mshoot_core.forecast import uncertainty_runs
    from mshoot_studies.boptest import plan_runs
    prices = ['constant', 'dynamic', 'highly_dynamic']
    scenarios = uncertainty_runs(['none', 'high=2'])
    parameters = {'constant': (3.0, 0.5), 'dynamic': (2.0, 0.5), 'highly_dynamic': (2.0, 0.5)}
    jobs = plan_runs(['peak_heat_day'], ['baseline', 'rule', 'mshoot'], prices, scenarios,
                     lambda period, price: parameters[price])
    assert [(job.name, job.prices) for job in jobs] == [
        ('baseline_peak_heat_day', tuple(prices)),
        ('rule_peak_heat_day_lead3_margin0.5', ('constant',)),
        ('rule_peak_heat_day_lead2_margin0.5', ('dynamic', 'highly_dynamic')),
        ('mshoot_peak_heat_day_constant', ('constant',)),
        ('mshoot_peak_heat_day_dynamic', ('dynamic',)),
        ('mshoot_peak_heat_day_highly_dynamic', ('highly_dynamic',)),
        ('mshoot_peak_heat_day_constant_high_s2', ('constant',)),
        ('mshoot_peak_heat_day_dynamic_high_s2', ('dynamic',)),
        ('mshoot_peak_heat_day_highly_dynamic_high_s2', ('highly_dynamic',))]
    together = plan_runs(['a', 'b'], ['mshoot'], prices, scenarios[:1], mshoot_per_price=False)
    assert [(job.period, job.prices) for job in together] == [('a', tuple(prices)),
                                                              ('b', tuple(prices))]
    with pytest.raises(ValueError, match='rule_parameters'):
        plan_runs(['a'], ['rule'], prices, scenarios)
    # a rule with cooling setpoints and a supply reset: its cooling margin and shift, when not 0
    office = {'constant': (1.0, 0.0, 0.5, -20.0), 'dynamic': (1.0, 0.0, 0.0, 0.0),
              'highly_dynamic': (1.0, 0.0)}
    jobs = plan_runs(['p'], ['rule'], prices, scenarios, lambda period, price: office[price])
    assert [(job.name, job.prices, job.cooling_margin_k, job.supply_shift_k) for job in jobs] == [
        ('rule_p_lead1_margin0_cool0.5_shift-20', ('constant',), 0.5, -20.0),
        ('rule_p_lead1_margin0', ('dynamic', 'highly_dynamic'), 0.0, 0.0)]
    with pytest.raises(ValueError, match='rule_parameters must give'):
        plan_runs(['a'], ['rule'], prices, scenarios, lambda period, price: (1.0,))
