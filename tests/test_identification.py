"""
Identification of a control model from a plant, and the setpoint zone controlled over ROS.

The plant is the setpoint zone FMU (fmu_src/setpoint_zone.c, Model Exchange): its air state is
an energy, its zone temperature a variable computed from it, its heating a local P loop
(Kp = 3000 W/K, at most 6 kW) on a setpoint with a BOPTEST-style override. The excitation and
the fit run on shortened experiments; the closed loop over ROS on 24 h of a data CSV with a
band, against the plant's own loop on its fixed setpoint.
"""
import json

from mshoot_core import identification as ident
from mshoot_core.fmu_cache import find_fmu
from mshoot_core.models import card as cards
from mshoot_core.scenario import read_data_csv, reference_scenario, synthetic_scenario
from mshoot_studies import identify as identify_verb
from mshoot_studies.local_loop import heat_kpis, run_local_loop
import numpy as np
import pandas as pd
import pytest

CARDS = cards.CARDS_DIR
PLANT = CARDS / 'setpoint_zone_plant.yaml'
MODEL = CARDS / 'setpoint_zone_model.yaml'
IDENTIFIED = CARDS / 'setpoint_zone_identified.yaml'
#: The FMU's loop gain [W/K] and start temperature [K] (setpoint_zone.c).
KP_W_PER_K, T_START_K = 3000.0, 294.15


@pytest.fixture(scope='module')
def plant_fmu():
    """Build the setpoint zone FMU into the cache (make setup builds it too)."""
    from mshoot_core import fmu_build
    return fmu_build.ensure_fmu('setpoint_zone')


@pytest.fixture(scope='module')
def excitation(plant_fmu):
    """Six days of the plant under random setpoints (the card's limits, 18-24 degC)."""
    card = cards.load_card(PLANT)
    plant = cards.build_model(card, role='emulator')
    try:
        return ident.excite(plant, synthetic_scenario(hours=6 * 24 + 1, seed=3),
                            ident.Excitation(seed=3), control_names=card.control_names,
                            control_bounds=ident.control_limits(card))
    finally:
        plant.close()


def test_the_plants_zone_temperature_is_its_air_energy_over_capacity(plant_fmu):
    """The state T is read from the FMU's T = air.U / Cair, never written; Tw is a state."""
    card = cards.load_card(PLANT)
    plant = cards.build_model(card, role='emulator')
    try:
        assert plant.derived_states == ('T',)
        x, y = plant.plant_start([300.0, 290.0], 0.0, [21.5, 0.0, 5.0, 0.0])
        # T starts at the FMU's T_start whatever x0 says; Tw (a continuous state) is written
        assert x[0] == pytest.approx(T_START_K)
        assert x[1] == pytest.approx(290.0)
        x, y = plant.plant_step([21.5, 0.0, 5.0, 0.0], 600.0)
        heat = dict(zip(plant.output_names, y))['Qheat']
        assert 0.0 < heat <= 6000.0
        with pytest.raises(ValueError, match="states \\['T'\\] are not continuous states"):
            plant.simulate_intervals(np.array([[294.0, 294.0]]),
                                     np.array([[21.0, 0.0, 5.0, 0.0]]), 600.0)
    finally:
        plant.close()


def test_excitation_holds_random_levels_within_the_limits(excitation):
    """Levels within 18-24 degC, held for whole steps, the zone moving with them."""
    levels = excitation['TSet'].to_numpy()
    assert levels.min() >= 18.0 and levels.max() <= 24.0
    changes = np.flatnonzero(np.diff(levels[:-1]) != 0.0)
    assert 10 < changes.size < len(levels) - 1  # held 1 to 8 steps: some held longer than one
    assert excitation['T'].std() > 1.0
    with pytest.raises(ValueError, match='outside its limits'):
        ident.excite(None, excitation, ident.Excitation(levels={'TSet': (10.0, 30.0)}),
                     control_names=('TSet',), control_bounds=[(18.0, 24.0)])


def test_identified_network_recovers_the_loop_gain_and_predicts_held_out_data(excitation):
    """The fit on 70 % of six days: Kp near the plant's (its saturation aside), RMSEs < 0.3 K."""
    result = ident.identify(cards.load_card(MODEL), excitation, validation_share=0.3)
    assert result.parameters['Kp'] == pytest.approx(KP_W_PER_K, rel=0.25)  # the card: 1000
    score = result.validation['T']
    assert score['free_run_rmse_k'] < 0.3
    assert score['one_step_rmse_k'] < 0.3
    assert score['rows'] == result.validation_rows - 12  # the settling steps not scored
    start = ident.identify(cards.load_card(MODEL), excitation, max_evaluations=1)
    assert start.validation['T']['free_run_rmse_k'] > 2 * score['free_run_rmse_k']


def test_identify_command_writes_a_card_that_loads(tmp_path, plant_fmu):
    out = tmp_path / 'identify'
    code = identify_verb.main(['--plant', str(PLANT), '--model', str(MODEL), '--days', '5',
                               '--seed', '2', '--out', str(out)])
    assert code == 0
    card = cards.load_card(out / 'setpoint_zone_model_identified.yaml')
    report = json.loads((out / 'identification.json').read_text())
    assert card.network.parameters['Kp'].value == pytest.approx(report['parameters']['Kp'])
    assert report['validation']['T']['free_run_rmse_k'] < 0.5
    assert (out / 'identification.png').stat().st_size > 1000
    assert len(pd.read_csv(out / 'excitation.csv')) == 5 * 24 + 1


def test_identify_command_refuses_a_model_that_is_not_a_network(tmp_path, plant_fmu, caplog):
    code = identify_verb.main(['--plant', str(PLANT), '--model', str(PLANT), '--days', '2',
                               '--out', str(tmp_path)])
    assert code == 2
    assert 'not a thermal network card' in caplog.text


def test_data_csv_is_read_as_interval_means_with_a_band(tmp_path):
    path = tmp_path / 'data.csv'
    times = pd.date_range('2024-01-01', periods=8, freq='30min')
    pd.DataFrame({'datetime': times, 'Tout': [0, 2, 4, 6, 8, 10, 12, 14],
                  'solrad': 0.0}).to_csv(path, index=False)
    scenario = read_data_csv(path, band=(20.0, 23.0))
    assert list(scenario.index) == [0.0, 3600.0, 7200.0, 10800.0]
    assert list(scenario['Tout']) == [1.0, 5.0, 9.0, 13.0]
    assert set(scenario['comfort_min']) == {20.0} and set(scenario['comfort_max']) == {23.0}
    assert scenario.attrs['start'] == '2024-01-01T00:00:00'
    with pytest.raises(ValueError, match='no comfort band'):
        read_data_csv(path)
    banded = tmp_path / 'banded.csv'
    pd.read_csv(path).assign(comfort_min=21.0, comfort_max=24.0).to_csv(banded, index=False)
    assert reference_scenario(str(banded), hours=3)['comfort_min'].eq(21.0).all()
    with pytest.raises(ValueError, match='give no band besides it'):
        read_data_csv(banded, band=(20.0, 23.0))
    twice = tmp_path / 'twice.csv'
    pd.read_csv(banded).iloc[[0, 0, 1]].to_csv(twice, index=False)
    with pytest.raises(ValueError, match='given twice'):
        read_data_csv(twice)


@pytest.mark.ros
def test_setpoint_zone_over_ros_beats_its_local_loop(context, tmp_path, plant_fmu):
    """24 h over ROS from the plant card and its identified model: less discomfort, like heat."""
    from mshoot_nodes.bringup import run_in_process
    hours = 24
    scenario = synthetic_scenario(hours=hours + 1, seed=0)
    scenario['comfort_min'], scenario['comfort_max'] = 21.0, 24.0
    data = tmp_path / 'day.csv'
    scenario.assign(time_s=scenario.index)[['time_s', 'Tout', 'solrad', 'occ', 'comfort_min',
                                            'comfort_max']].to_csv(data, index=False)
    limits: dict = {}  # the setpoint's limits and safe value: the cards'
    run = run_in_process(context, {
        'emulator': {'scenario': str(data), 'hours': hours, 'model': str(PLANT),
                     'initial_temperature_c': 21.0, **limits},
        'forecaster': {'scenario': str(data), 'hours': hours, 'horizon_steps': 12,
                       'use_sim_time': True},
        'mpc': {'model': str(IDENTIFIED), 'horizon_steps': 12, 'use_sim_time': True,
                'cost': 'output', 'cost_output': 'Qh', 'comfort_margin_std': 2.0, **limits},
    }, record=False, timeout_s=120.0)
    assert len(run.emulator.records) == hours
    mpc = heat_kpis(run.emulator.fine_frame(), 'y_Qheat_total')
    local = heat_kpis(run_local_loop(cards.load_card(PLANT), read_data_csv(data), hours),
                      'y_Qheat_total')
    assert find_fmu('setpoint_zone').is_file()
    assert local['discomfort_kh'] > 1.0          # its fixed setpoint droops below the band
    assert mpc['discomfort_kh'] < 0.25 * local['discomfort_kh']
    assert mpc['heat_kwh'] == pytest.approx(local['heat_kwh'], rel=0.1)


def test_case_takes_a_data_csv_with_a_band(tmp_path):
    from mshoot_studies import case
    path = tmp_path / 'data.csv'
    pd.DataFrame({'time_s': np.arange(5) * 3600.0, 'Tout': 5.0, 'solrad': 0.0, 'occ': 0.0,
                  'dpos': 0.0}).to_csv(path, index=False)
    args = case.build_parser().parse_args(['data', '--data', str(path), '--band', '20,23',
                                           '--hours', '3'])
    scenario = case.case_scenario(args, None)
    assert len(scenario) == 4 and set(scenario['comfort_max']) == {23.0}
    args.hours = 5
    with pytest.raises(ValueError, match='covers 4 control steps'):
        case.case_scenario(args, None)
    args = case.build_parser().parse_args(['synthetic', '--band', '20,23'])
    with pytest.raises(ValueError, match='--band is for the scenario data'):
        case.case_scenario(args, None)
    assert case.main(['data', '--data', str(path), '--hours', '3', '--out',
                      str(tmp_path / 'out')]) == 2  # no band


def test_bringup_forecasts_the_series_the_control_card_names():
    from mshoot_nodes.bringup import build_parser, node_params_from_args
    args = build_parser().parse_args(['--control-model', str(IDENTIFIED)])
    assert node_params_from_args(args)['forecaster']['series'] == ['solrad', 'Tout', 'occ']
    args = build_parser().parse_args(['--control-model', 'python'])
    assert node_params_from_args(args)['forecaster']['series'] is None  # the node's own
