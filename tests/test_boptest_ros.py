"""BOPTEST over ROS: shortened baseline, rule and mshoot runs equal the core runs; cards."""
import pathlib

from mshoot_core.boptest.kpi_calculator import compute_kpis
from mshoot_core.boptest.period_scenario import period_scenario
from mshoot_core.boptest.plant import run_period
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.models.card import build_model, builtin_card, CardError, load_card
from mshoot_studies.boptest_rule import PreheatRule, rule_targets
import numpy as np
import pytest
import yaml

from conftest import private_context

pytestmark = pytest.mark.ros

LEAD_H, MARGIN_K = 3.0, 0.5
#: The heat pump house's card (its boptest.control: the control card and settings boptest_house).
CARD = pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'boptest_cards' / \
    'bestest_hydronic_heat_pump.yaml'
CONTROL = ('boptest_house', 'boptest_house')


@pytest.fixture(scope='module')
def ros_runs(boptest_case: TestCase, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Run the three controllers over ROS: peak_heat_day, 1 day of warm-up, 2 days of test."""
    import rclpy
    from mshoot_nodes.boptest_run import run_ros
    out = tmp_path_factory.mktemp('boptest_ros')
    context = private_context()
    try:
        runs = {controller: run_ros(context, controller, 'peak_heat_day', boptest_case, CARD,
                                    price='dynamic', warmup_days=1, length_days=2,
                                    lead_h=LEAD_H, margin_k=MARGIN_K, out=out / controller,
                                    timeout_s=900.0)
                for controller in ('baseline', 'rule')}
        runs['mshoot'] = run_ros(context, 'mshoot', 'peak_heat_day', boptest_case, CARD,
                                 control=CONTROL, price='dynamic', warmup_days=1, length_days=1,
                                 out=out / 'mshoot', timeout_s=900.0)
    finally:
        rclpy.try_shutdown(context=context)
    return {'runs': runs, 'out': out}


@pytest.mark.parametrize('controller', ['baseline', 'rule'])
def test_ros_run_equals_the_core_run(boptest_case: TestCase, ros_runs: dict,
                                     controller: str) -> None:
    """The emulator node steps the FMU exactly as the core loop does: same outputs, same KPIs."""
    run = ros_runs['runs'][controller]
    assert not run.failed and run.steps == 48
    card = load_card(ros_runs['out'] / controller / f'card_{CARD.stem}.yaml')
    rule = (PreheatRule(boptest_case, rule_targets(card, boptest_case), LEAD_H, MARGIN_K)
            if controller == 'rule' else None)
    core = run_period(boptest_case, 'peak_heat_day', rule, warmup_days=1, length_days=2)
    assert (run.start_s, run.end_s) == (core.start_s, core.end_s)
    columns = ['time', 'reaTZon_y', 'reaPHeaPum_y', 'reaPFan_y', 'reaPPumEmi_y', 'reaTSet_y',
               'oveTSet_u']
    ros, ref = run.records[columns], core.records[columns]
    assert len(ros) == len(ref)
    np.testing.assert_allclose(ros.to_numpy(), ref.to_numpy(), rtol=1e-9, atol=1e-9)
    ours = compute_kpis(run.records, boptest_case, run.start_s, run.end_s, 'dynamic')
    theirs = compute_kpis(core.records, boptest_case, core.start_s, core.end_s, 'dynamic')
    for key in ('tdis_tot', 'ener_tot', 'cost_tot', 'pele_tot'):
        assert ours[key] == pytest.approx(theirs[key], rel=1e-9)
    # the controller answered every step (the lockstep waits time_rat is made of)
    assert len(run.setpoint_waits_s) == 48 and min(run.setpoint_waits_s) >= 0
    written = ros_runs['out'] / controller / 'boptest_records.csv'
    assert written.is_file()


def test_mshoot_over_ros_equals_the_core_run(boptest_case: TestCase, ros_runs: dict) -> None:
    """
    The MPC node plans from /forecast and converts only: the core supervised run, to 1e-9.

    The general Controller (the card's control card and settings ``boptest_house``) over ROS,
    the emulator's card the building's with the heat pump's modulation only: the warm-up
    observed from the first zone state's history with the inputs of the first forecast's
    history, the model's duty ``d`` sent as the plant's ``Y`` (``plant_controls``); the same
    heat pump overwrites minute by minute and the same KPIs as
    :func:`~mshoot_core.boptest.supervision.supervised_plant` in the core loop.
    """
    from mshoot_core.boptest.supervision import supervised_plant
    from mshoot_core.settings import MpcSettings
    run = ros_runs['runs']['mshoot']
    assert not run.failed and run.steps == 24
    plant = ros_runs['out'] / 'mshoot' / f'card_{CARD.stem}.yaml'
    assert list(load_card(ros_runs['out'] / 'mshoot' / 'emulator_mshoot_warmup1d.yaml')
                .controls) == ['Y']
    policy = supervised_plant(boptest_case, plant, builtin_card(CONTROL[0]),
                              MpcSettings.from_file(CONTROL[1]), 'dynamic')
    core = run_period(boptest_case, 'peak_heat_day', policy, warmup_days=1, length_days=1,
                      record=policy.recorded(boptest_case))
    assert all(not o.decision.fallback for o in policy.outcomes)
    assert (run.start_s, run.end_s) == (core.start_s, core.end_s)
    columns = ['time', 'reaTZon_y', 'reaPHeaPum_y', 'reaQHeaPumCon_y', 'oveHeaPumY_u']
    ros, ref = run.records[columns], core.records[columns]
    assert len(ros) == len(ref)
    test = ros['time'].to_numpy() > run.start_s
    # the bursts within the hour reached the building: on and off inside one step
    applied = ros.loc[test, 'oveHeaPumY_u']
    assert set(applied.unique()) == {0.0, 1.0}
    np.testing.assert_allclose(ros.to_numpy(), ref.to_numpy(), rtol=1e-9, atol=1e-9,
                               equal_nan=True)
    ours = compute_kpis(run.records, boptest_case, run.start_s, run.end_s, 'dynamic')
    theirs = compute_kpis(core.records, boptest_case, core.start_s, core.end_s, 'dynamic')
    for key in ('tdis_tot', 'ener_tot', 'cost_tot', 'pele_tot'):
        assert ours[key] == pytest.approx(theirs[key], rel=1e-9, abs=1e-12)
    assert len(run.setpoint_waits_s) == 24


def test_mshoot_fault_over_ros_plan_tail_release_and_back(boptest_case: TestCase,
                                                          tmp_path: pathlib.Path) -> None:
    """
    The solver fails for 3 steps on the heat pump house over ROS: plan tail, release, back.

    The MPC node (settings ``boptest_house``, the fallback after one step of the plan's tail)
    on the emulator's card with the heat pump's modulation: the plan's tail, then the overwrite
    released (``oveHeaPumY_u`` not applied: the building's own controller runs the heat pump),
    then control again; a defined input at every minute.
    """
    import rclpy
    from mshoot_nodes.boptest_run import run_ros
    from mshoot_testing.faults import SolverOutage
    hours, failing = 8, (3, 4, 5)
    outage = SolverOutage(failing)
    context = private_context()
    try:
        run = run_ros(context, 'mshoot', 'peak_heat_day', boptest_case, CARD, control=CONTROL,
                      price='dynamic', warmup_days=1, length_days=hours / 24, out=tmp_path,
                      timeout_s=900.0,
                      mpc_settings={'on_failure': 'fallback', 'max_plan_age_steps': 1},
                      on_step=outage)
    finally:
        rclpy.try_shutdown(context=context)
    assert not run.failed and run.steps == hours
    history = list(outage.mpc.history)
    expected = (['optimum'] * failing[0] + ['plan'] + ['released'] * (len(failing) - 1)
                + ['optimum'] * (hours - failing[-1] - 1))
    assert [status.source for _, status in history] == expected
    assert [list(setpoint.released) for setpoint, _ in history] == [
        [True] if s == 'released' else [] for s in expected]
    records = run.records
    for k, source in enumerate(expected):
        t0 = run.start_s + k * 3600.0
        minutes = records[(records['time'] > t0) & (records['time'] < t0 + 3600.0)]
        assert len(minutes) == 59
        overwritten = minutes['oveHeaPumY_u'].notna()
        assert (~overwritten).all() if source == 'released' else overwritten.all()
        assert minutes['reaHeaPumY_y'].notna().all()  # the heat pump runs, by whoever
    released = records[(records['time'] > run.start_s + failing[1] * 3600.0)
                       & (records['time'] < run.start_s + (failing[-1] + 1) * 3600.0)]
    assert released['reaHeaPumY_y'].max() > 0.1  # the building's own controller heats


def test_baseline_leaves_the_building_alone_and_the_rule_preheats(ros_runs: dict) -> None:
    baseline, rule = ros_runs['runs']['baseline'], ros_runs['runs']['rule']
    test = baseline.records['time'] > baseline.start_s
    assert baseline.records.loc[test, 'oveTSet_u'].isna().all()
    applied = rule.records.loc[rule.records['time'] > rule.start_s, 'oveTSet_u']
    assert applied.notna().all()
    # 21 degC + 0.5 K while the band's lower bound is 21 degC within the next 4 h, else 15.5
    assert set(np.round(applied.unique(), 6)) == {294.65, 288.65}


def test_forecaster_serves_the_test_case_data(boptest_case: TestCase, context) -> None:
    from mshoot_nodes.conversions import forecast_series
    from mshoot_nodes.forecaster_node import ForecasterNode
    from rclpy.parameter import Parameter
    node = ForecasterNode(context=context, parameter_overrides=[
        Parameter('scenario', value='boptest:typical_heat_day:highly_dynamic'),
        Parameter('hours', value=48), Parameter('horizon_steps', value=6)])
    try:
        msg = node.publish_forecast(5)
    finally:
        node.destroy_node()
    _, start, _ = boptest_case.test_period('typical_heat_day')
    times = start + (5 + np.arange(7)) * 3600.0
    series, rejection = forecast_series(msg)
    assert rejection is None
    np.testing.assert_allclose(series['Tout'], boptest_case.lookup('TDryBul', times) - 273.15)
    np.testing.assert_allclose(series['solrad'], boptest_case.lookup('HGloHor', times))
    np.testing.assert_allclose(series['occ'], boptest_case.lookup('Occupancy[1]', times))
    np.testing.assert_allclose(msg.comfort_min_c,
                               boptest_case.lookup('LowerSetp[1]', times) - 273.15)
    np.testing.assert_allclose(msg.comfort_max_c,
                               boptest_case.lookup('UpperSetp[1]', times) - 273.15)
    np.testing.assert_allclose(msg.price_per_kwh,
                               boptest_case.lookup('PriceElectricPowerHighlyDynamic', times))


def test_scenario_rows_and_clock(boptest_case: TestCase) -> None:
    scenario = period_scenario(boptest_case, 'typical_heat_day', hours=3, price='dynamic')
    assert scenario.index.tolist() == [0.0, 3600.0, 7200.0, 10800.0]
    assert scenario.attrs['start'] == '2023-04-19T00:00:00'  # 108 d after 1 January
    assert scenario['fmu_time_s'].iloc[0] == 108 * 86400.0
    assert len(period_scenario(boptest_case, 'peak_heat_day')) == 14 * 24 + 1


def test_boptest_cards(tmp_path: pathlib.Path, boptest_case: TestCase) -> None:
    card = load_card(builtin_card('boptest_tset'))
    assert card.source == 'boptest' and card.controls['TSet'].activate == 'oveTSet_activate'
    assert card.boptest == {'test_case_dir': str(boptest_case.directory), 'warmup_days': 7.0,
                            'history_step_s': 0.0, 'setpoint_zones': {},
                            'cooling_zones': {}, 'supply_reset': None, 'power_signs': {},
                            'excitation': None, 'control': None}
    assert load_card(builtin_card('boptest_baseline')).controls['TSet'].activate is None
    with pytest.raises(ValueError, match='emulator'):
        build_model(card, role='control')
    document = yaml.safe_load(builtin_card('boptest_tset').read_text())
    both = tmp_path / 'both.yaml'
    both.write_text(yaml.safe_dump({**document, 'fmu': 'x.fmu'}))
    with pytest.raises(CardError, match="one of 'fmu'"):
        load_card(both)
    nowhere = tmp_path / 'nowhere.yaml'
    nowhere.write_text(yaml.safe_dump({**document, 'boptest': {'test_case': 'no/such'}}))
    with pytest.raises(CardError, match='no BOPTEST test case'):
        load_card(nowhere)
    wrong = tmp_path / 'wrong.yaml'
    wrong.write_text(yaml.safe_dump({**document, 'outputs': {'T': {'variable': 'TZon'}}}))
    with pytest.raises(CardError, match="'TZon' is not"):
        load_card(wrong)


def test_runner_refuses_bad_arguments(capsys, tmp_path: pathlib.Path) -> None:
    from mshoot_nodes.boptest_run import main
    assert main(['--card', str(CARD), '--out', str(tmp_path), '--periods', 'peak_cool_day',
                 '--controllers', 'baseline']) == 2
    assert 'unknown test period' in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(['--card', str(CARD), '--prices', 'cheap'])
    assert exit_info.value.code == 2
