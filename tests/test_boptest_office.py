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
#: The shortened run of the issue: 1 day of warm-up, then 2 days of test from typical_heat_day's
#: start (two working days: the nights, the BMS's pumps on at 6 h, the band's 21 degC from 7 h,
#: the evenings), a 6 h horizon. Its core run is also the reference of the run over ROS.
WARMUP_DAYS, LENGTH_DAYS, HORIZON = 1.0, 2.0, 6


@pytest.fixture(scope='module')
def runs(office: TestCase, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Run the baseline and the MPC on the shortened period (the weather derived for it)."""
    from mshoot_studies.boptest import prepare_card
    monkeypatch = pytest.MonkeyPatch()
    cache = str(tmp_path_factory.mktemp('office_cache') / 'fmu')
    monkeypatch.setenv(fmu_cache.CACHE_ENV, cache)
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
            'start': start, 'end': end, 'cache': cache}


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
    # less band_setpoint_margin_k, cooling_mode_margin_k where the plan heats nowhere
    actuation = policy.controller.settings.actuation
    margin, cooling = actuation.band_setpoint_margin_k, actuation.cooling_mode_margin_k
    modes = [policy.controller.heats_ahead(o.decision) for o in period]
    for outcome, heats in zip(period, modes):
        inward = cooling if heats is False else margin
        assert set(np.round(outcome.band_values[0], 9)) <= {25.0 - inward, 30.0 - inward}
    assert 0 < margin < cooling and True in modes and False in modes  # both modes: 6 h plans
    warmup = table[table['time'] < start - 1e-6]
    assert warmup[[card.controls[n].variable for n in policy.controller.sent_control_names]
                  ].isna().all().all()
    # the boiler's supply temperature costs gas and nothing else in the model: planned at its
    # lower limit, sent at its floor where a capped setpoint heats (settings supply_floors)
    floor = policy.controller.settings.actuation.supply_floor_items['TSupHea']
    states = list(policy.controller.model.state_names)
    heating = []
    for outcome in period:
        np.testing.assert_allclose(outcome.result.plan['TSupHea'].to_numpy()[0], 20.0, atol=1e-3)
        heating.append(any(
            outcome.decision.controls[i] >= outcome.decision.predicted_state[
                states.index(zone)] - 273.15 - 0.05 for i, zone in enumerate(('T_nZ', 'T_sZ'))))
        assert outcome.decision.controls[2] == pytest.approx(floor if heating[-1] else 20.0,
                                                             abs=1e-3)
    assert floor > 20.0 and 0 < sum(heating) < len(heating)  # both: mornings heat, nights not
    # the minimum setpoints capped (settings setpoint_caps): at most the plan's temperature of
    # the zone at the step's end (or the band's raised lower edge there), at least the raised
    # lower edge at the step's start; the lower edge is 21 degC where the maximum is 25 - margin
    # (over the step: at its start where it is so at both ends, the band's hours being whole)
    raised = policy.controller.settings.comfort.band_margin_k
    assert raised > 0 and policy.controller.settings.actuation.cap_items == {
        'TSetMin_nZ': 'T_nZ', 'TSetMin_sZ': 'T_sZ'}
    steps = [o for o in policy.outcomes if o.t_s >= start - 3600.0 - 1e-6]
    lower = [21.0 if o.band_values[0][0] < 26.0 else 16.0 for o in steps]  # 25 less the margin
    capped = 0
    for outcome, begin, end in zip(steps[1:], lower, lower[1:]):
        asked = outcome.result.plan[list(names)].to_numpy()[0]
        for i, zone in enumerate(('T_nZ', 'T_sZ')):
            planned = outcome.decision.predicted_state[states.index(zone)] - 273.15
            sent = outcome.decision.controls[i]
            at_start = min(begin, end) + raised
            assert at_start - 1e-9 <= sent <= max(planned, end + raised) + 1e-9
            assert sent <= max(asked[i], at_start) + 1e-9
            capped += sent < asked[i] - 0.5
    assert capped > 0  # the plan's pre-heating setpoints were capped


def test_office_mpc_burns_less_gas_than_the_bms_and_keeps_the_band(runs: dict) -> None:
    """
    Against the BMS on the same day: less gas, neither zone's discomfort worse.

    (The cost is not checked: the plan's pre-heat from 6 h runs the fan coils' fans, whose
    electricity can outweigh the gas saved on a short run.)
    """
    case, start, end = runs['case'], runs['start'], runs['end']
    kpis = {name: kpi_records(runs[name].records, case, start, end, ['constant'], None)[0]
            for name in ('mpc', 'baseline')}
    mpc, baseline = kpis['mpc'], kpis['baseline']

    def gas_kwh(table: 'object') -> float:
        window = table[(table['time'] >= start) & (table['time'] <= end)]
        return float(window['heating_cooling_reaPProHea_y'].sum() * 60.0 / 3.6e6)

    assert gas_kwh(runs['mpc'].records) < gas_kwh(runs['baseline'].records)
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


@pytest.mark.ros
def test_office_over_ros_equals_the_core_run(runs: dict, tmp_path: pathlib.Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """
    The office's MPC over ROS (``python -m mshoot_nodes.boptest_run``) equals its core run.

    The emulator, forecaster and MPC nodes from the same cards and settings
    (:func:`mshoot_nodes.boptest_run.run_ros`): two zones, five named overwrites (both
    minimum setpoints capped, the boiler's supply temperature planned and floored; both maximum
    setpoints at the band), the gas price, the weather derived
    from the FMU; every step's decision, the setpoints the building got minute by minute, both
    zone temperatures, the gas and the KPIs (``pgas_tot``, ``tdis_zones``) equal to 1e-9.
    """
    import rclpy
    from conftest import private_context
    from mshoot_nodes.boptest_run import run_ros
    monkeypatch.setenv(fmu_cache.CACHE_ENV, runs['cache'])  # the weather derived for the run
    case, core, policy = runs['case'], runs['mpc'], runs['policy']
    seen: dict = {}

    def keep(steps: int, nodes: dict) -> None:
        seen.setdefault('mpc', nodes['controller'])

    context = private_context()
    try:
        ros = run_ros(context, 'mshoot', 'typical_heat_day', case, PLANT,
                      control=(str(CONTROL), str(SETTINGS)), price='constant',
                      warmup_days=WARMUP_DAYS, length_days=LENGTH_DAYS, out=tmp_path,
                      timeout_s=900.0, mpc_settings={'horizon_steps': HORIZON}, on_step=keep)
    finally:
        rclpy.try_shutdown(context=context)
    steps = round(LENGTH_DAYS * 24)
    assert not ros.failed and ros.steps == steps
    assert (ros.start_s, ros.end_s) == (core.start_s, core.end_s)
    # every step's decision: the overwrites by name [degC] (the planned controls, then the
    # band setpoints), none a fallback
    names = policy.controller.sent_control_names
    period = [o for o in policy.outcomes if o.t_s >= runs['start'] - 1e-6]
    history = list(seen['mpc'].history)
    assert len(history) == len(period) == steps
    for (setpoint, status), outcome in zip(history, period):
        assert status.source == 'optimum' and not list(setpoint.released)
        sent = dict(zip(setpoint.control_names, setpoint.control_values))
        np.testing.assert_allclose([sent[n] for n in names], outcome.sent()[0].controls,
                                   rtol=1e-9, atol=1e-9)
    # what the building got and did, minute by minute (the warm-up's own control included)
    card = load_card(runs['plant'])
    columns = ['time', *(card.controls[n].variable for n in names),
               *(v.variable for v in card.states.values()), 'heating_cooling_reaPProHea_y']
    ours, theirs = ros.records[columns], core.records[columns]
    assert len(ours) == len(theirs) and ours[columns[1]].notna().sum() == steps * 60
    np.testing.assert_allclose(ours.to_numpy(), theirs.to_numpy(), rtol=1e-9, atol=1e-9,
                               equal_nan=True)
    prices = ['constant', 'highly_dynamic']
    for a, b in zip(kpi_records(ros.records, case, ros.start_s, ros.end_s, prices, None),
                    kpi_records(core.records, case, core.start_s, core.end_s, prices, None)):
        for key in ('tdis_tot', 'ener_tot', 'cost_tot', 'pele_tot', 'pgas_tot'):
            assert a[key] == pytest.approx(b[key], rel=1e-9, abs=1e-12), key
        for zone in case.zones:
            assert a['tdis_zones'][zone] == pytest.approx(b['tdis_zones'][zone], rel=1e-9,
                                                          abs=1e-12)


@pytest.mark.ros
def test_office_over_ros_releases_every_overwrite_on_its_last_fallback(
        runs: dict, tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """
    The solver fails for 2 steps of the office over ROS: the plan's tail, then all released.

    The MPC node on the office's settings (the fallback after one step of the plan's tail,
    ``release: release``): the five named overwrites held from the plan, then released
    together (the BMS's own setpoints and supply temperature: the overwrite inputs not applied)
    and sent again once the solver is back.
    """
    import rclpy
    from conftest import private_context
    from mshoot_nodes.boptest_run import run_ros
    from mshoot_testing.faults import SolverOutage
    monkeypatch.setenv(fmu_cache.CACHE_ENV, runs['cache'])  # the weather derived for the run
    hours, failing = 5, (2, 3)
    outage = SolverOutage(failing)
    context = private_context()
    try:
        run = run_ros(context, 'mshoot', 'typical_heat_day', runs['case'], PLANT,
                      control=(str(CONTROL), str(SETTINGS)), warmup_days=0.25,
                      length_days=hours / 24, out=tmp_path, timeout_s=900.0,
                      mpc_settings={'horizon_steps': HORIZON, 'on_failure': 'fallback',
                                    'max_plan_age_steps': 1}, on_step=outage)
    finally:
        rclpy.try_shutdown(context=context)
    assert not run.failed and run.steps == hours
    history = list(outage.mpc.history)
    expected = ['optimum'] * failing[0] + ['plan', 'released'] + ['optimum']
    assert [status.source for _, status in history] == expected
    card = load_card(runs['plant'])
    names = runs['policy'].controller.sent_control_names
    assert [sorted(setpoint.control_names) for setpoint, _ in history] == [sorted(names)] * hours
    assert [list(setpoint.released) for setpoint, _ in history] == [
        [True] * len(names) if s == 'released' else [] for s in expected]
    variables = [card.controls[n].variable for n in names]
    for k, source in enumerate(expected):
        t0 = run.start_s + k * 3600.0
        minutes = run.records[(run.records['time'] > t0) & (run.records['time'] < t0 + 3600.0)]
        overwritten = minutes[variables].notna().to_numpy()
        assert (~overwritten).all() if source == 'released' else overwritten.all()


def test_office_emulator_cards_over_ros(runs: dict, tmp_path: pathlib.Path) -> None:
    """The emulator's card of each run: the overwrites its controller sends, from the office's."""
    from mshoot_nodes.boptest_run import emulator_card, rule_setpoint, sent_controls
    card = load_card(runs['plant'])
    sent, step = sent_controls(str(CONTROL), MpcSettings.from_file(SETTINGS))
    assert (sent, step) == (('TSetMin_nZ', 'TSetMin_sZ', 'TSupHea', 'TSetMax_nZ',
                             'TSetMax_sZ'), 3600.0)
    mshoot = load_card(emulator_card(card.path, sent, tmp_path / 'mshoot.yaml', warmup_days=1,
                                     history_step_s=step))
    assert list(mshoot.controls) == list(sent)
    assert all(mshoot.controls[n].activate == card.controls[n].activate for n in sent)
    assert mshoot.boptest['history_step_s'] == 3600.0
    assert mshoot.boptest['setpoint_zones'] == {'TSetMin_nZ': 'nZ', 'TSetMin_sZ': 'sZ'}
    # the baseline: one setpoint, its switch removed (the BMS in charge whatever is sent)
    assert rule_setpoint(card, 'baseline') == ('TSetMin_nZ', 'nZ')
    baseline = load_card(emulator_card(card.path, ['TSetMin_nZ'], tmp_path / 'baseline.yaml',
                                       warmup_days=1, switches=False))
    assert baseline.controls['TSetMin_nZ'].activate is None
    with pytest.raises(ValueError, match='sends one setpoint'):
        rule_setpoint(card, 'rule')  # two setpoint zones: the rule node sends one
    with pytest.raises(ValueError, match=r"no control \['TSet'\]"):
        emulator_card(card.path, ['TSet'], tmp_path / 'bad.yaml', warmup_days=1)
