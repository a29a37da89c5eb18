"""The two-zone office under mshoot's supervisory MPC, by configuration only (cards, settings)."""
import pathlib

from mshoot_core import fmu_cache
from mshoot_core.boptest import weather
from mshoot_core.boptest.kpi_calculator import kpi_records
from mshoot_core.boptest.plant import run_period
from mshoot_core.boptest.supervision import supervised_plant
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.models.card import load_card
from mshoot_core.settings import MpcSettings
import numpy as np
import pytest

CARDS = pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'boptest_cards'
PLANT = CARDS / 'multizone_office_simple_hydronic.yaml'
CONTROL = CARDS / 'multizone_office_simple_hydronic_control.yaml'
SETTINGS = CARDS / 'multizone_office_simple_hydronic_mpc.yaml'
DAY = 86400.0
#: The shortened run: 6 h of warm-up, 12 h of test from typical_heat_day's start (midnight to
#: noon: the night, the BMS's pumps on at 6 h, the band's 21 degC from 7 h), a 6 h horizon.
WARMUP_DAYS, LENGTH_DAYS, HORIZON = 0.25, 0.5, 6


@pytest.fixture(scope='module')
def runs(office: TestCase, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Run the baseline and the MPC on the shortened period (the weather derived for it)."""
    from mshoot_studies.boptest import prepare_card
    monkeypatch = pytest.MonkeyPatch()
    monkeypatch.setenv(fmu_cache.CACHE_ENV, str(tmp_path_factory.mktemp('office_cache') / 'fmu'))
    plant = prepare_card(PLANT, office.directory, tmp_path_factory.mktemp('card'))
    try:
        warmup_start, start, end = office.test_period('typical_heat_day', WARMUP_DAYS,
                                                      LENGTH_DAYS)
        weather.ensure_window(office, warmup_start, end + (HORIZON + 1) * 3600.0)
        case = TestCase.load(office.directory)
        settings = MpcSettings.from_file(SETTINGS).replace(horizon_steps=HORIZON)
        policy = supervised_plant(case, plant, CONTROL, settings)
        record = policy.recorded(case)
        mpc = run_period(case, 'typical_heat_day', policy, WARMUP_DAYS, LENGTH_DAYS,
                         record=record)
        baseline = run_period(case, 'typical_heat_day', None, WARMUP_DAYS, LENGTH_DAYS,
                              record=record)
    finally:
        monkeypatch.undo()
    return {'case': case, 'plant': plant, 'policy': policy, 'mpc': mpc, 'baseline': baseline,
            'start': start, 'end': end}


def test_office_mpc_sends_its_decisions_as_the_bms_overwrites(runs: dict) -> None:
    """
    Every step of the period is planned and held as the card's overwrites, none before.

    The maximum setpoints too: each zone's band's upper edge over the step less the margin.
    """
    policy, table, start = runs['policy'], runs['mpc'].records, runs['start']
    card = load_card(runs['plant'])
    period = [o for o in policy.outcomes if o.t_s >= start - 1e-6]
    assert len(period) == round(LENGTH_DAYS * 24)
    assert not any(o.decision.fallback for o in period)
    names = policy.controller.settings.problem.control_names
    assert names == ('TSetMin_nZ', 'TSetMin_sZ', 'TSupHea')
    for outcome in period:
        rows = table[(table['time'] > outcome.t_s + 1e-6)
                     & (table['time'] <= outcome.t_s + 3600.0 + 1e-6)]
        for name, value in zip(names, outcome.decision.controls):
            spec = card.controls[name]
            sent = rows[spec.variable].to_numpy()
            np.testing.assert_allclose(sent, value + 273.15, atol=1e-9)  # degC -> K
            assert spec.min - 1e-9 <= sent.min() - 273.15 <= sent.max() - 273.15 <= \
                spec.max + 1e-9  # (the card's limits in its canonical unit, degC)
        bands = [card.controls[b[0]].variable for b in policy.controller.band_setpoints]
        np.testing.assert_allclose(rows[bands].to_numpy() - outcome.band_values[0], 273.15,
                                   atol=1e-9, err_msg=f'{outcome.t_s:.0f} s')
    margin = policy.controller.settings.actuation.band_setpoint_margin_k
    maxima = np.array([o.band_values[0] for o in period])
    assert margin > 0 and set(np.round(maxima.ravel(), 9)) == {25.0 - margin, 30.0 - margin}
    warmup = table[table['time'] < start - 1e-6]
    assert warmup[[card.controls[n].variable for n in policy.controller.sent_control_names]
                  ].isna().all().all()
    # the boiler's supply temperature costs gas and nothing else in the model: its lower limit
    supply = np.array([o.decision.controls[2] for o in period])
    np.testing.assert_allclose(supply, 40.0, atol=1e-3)


def test_office_mpc_burns_less_gas_than_the_bms_and_keeps_the_band(runs: dict) -> None:
    """
    Against the BMS on the same 12 h: less gas, neither zone's discomfort worse.

    (Not less cost over these 12 h: the plan's pre-heat from 6 h runs the fan coils' fans,
    whose electricity outweighs the gas saved before noon; over the 2-day run it costs less.)
    """
    case, start, end = runs['case'], runs['start'], runs['end']
    kpis = {name: kpi_records(runs[name].records, case, start, end, ['constant'], None)[0]
            for name in ('mpc', 'baseline')}
    mpc, baseline = kpis['mpc'], kpis['baseline']

    def gas_kwh(table: 'object') -> float:
        window = table[(table['time'] >= start) & (table['time'] <= end)]
        return float(window['heating_cooling_reaPProHea_y'].sum() * 60.0 / 3.6e6)

    assert gas_kwh(runs['mpc'].records) < gas_kwh(runs['baseline'].records)  # 119 vs 123 kWh
    for zone in case.zones:
        assert mpc['tdis_zones'][zone] <= baseline['tdis_zones'][zone] + 0.05


def test_office_settings_plan_on_the_card_and_release_to_the_bms() -> None:
    """The settings file fits the control card; its last fallback releases every overwrite."""
    from mshoot_core.controller import controller_for
    from mshoot_core.models.card import build_model
    controller = controller_for(build_model(load_card(CONTROL)), MpcSettings.from_file(SETTINGS))
    settings = controller.settings
    assert settings.released == (True, True, True)
    # each zone kept in its own band (the card names both zones' bands)
    assert controller.mpc.state_bounds == {
        'T_nZ': ('comfort_min_nZ', 'comfort_max_nZ', 273.15),
        'T_sZ': ('comfort_min_sZ', 'comfort_max_sZ', 273.15)}
    assert settings.actuation.plant_names == {name: name for name in
                                              settings.problem.control_names}
    import yaml
    plant = yaml.safe_load(PLANT.read_text())['controls']  # (its FMU: the test case's)
    assert all(plant[name]['activate'] for name in controller.sent_control_names)
    # the maximum (cooling) setpoints at the band's upper edge less the margin, not planned
    assert controller.sent_control_names[3:] == ('TSetMax_nZ', 'TSetMax_sZ')
    assert [b[1:] for b in controller.band_setpoints] == [
        ('max', 'comfort_min_nZ', 'comfort_max_nZ'), ('max', 'comfort_min_sZ', 'comfort_max_sZ')]
