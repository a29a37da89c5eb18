"""
Controls of any quantity from the card, and the fallback that hands the building back.

The card is the source of truth of every control's unit, limits and safe value (written in the
card's unit, converted at the boundary, checked against the FMU's declared min/max); settings
only narrow them. The last link of the fallback chain releases the overwrites of a plant with
overwrite switches (the card's ``activate``): the test FMU ``zone2`` (a cooler ``Pcool`` [kW]
behind ``Pcool_activate``, which its local loop keeps off) and the BOPTEST heat pump house
(``oveHeaPumY_u`` behind ``oveHeaPumY_activate``, its own controller behind it) show it in the
records. Over ROS: the solver made to fail for three steps gives the plan's tail, then the
release, then control again, with a defined input at every minute.
"""
import json
import logging
import math
import pathlib

from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.controller import controller_for
from mshoot_core.controls import model_controls
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models import card as cards
from mshoot_core.models.card import builtin_card, CardError, load_card
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.safety import SetpointSupervisor
from mshoot_core.scenario import reference_scenario
from mshoot_core.settings import MpcSettings, SettingsError
from mshoot_core.solvers import make_solver
from mshoot_core.units import KELVIN
from mshoot_testing.faults import FaultySolver
import numpy as np
import pytest
import yaml

from card_fmus import build_test_fmu

HOUR = 3600.0
#: The zone2 test FMU's card: heating q [W], a cooler qc (Pcool [kW]) behind its switch.
ZONE2 = {
    'fmu': 'zone2.fmu', 'parameters': {'tmass': 5.0},
    'controls': {'q': {'variable': 'q', 'unit': 'W', 'min': 0, 'max': 2000, 'safe': 0},
                 'qc': {'variable': 'Pcool', 'unit': 'kW', 'min': 0, 'max': 2, 'safe': 1.5,
                        'activate': 'Pcool_activate'}},
    'disturbances': {'solrad': {'variable': 'solrad', 'unit': 'W/m2'},
                     'Tout': {'variable': 'Tout', 'unit': 'degC'}, 'occ': {'variable': 'occ'}},
    'states': {'T': {'variable': 'cair.T', 'unit': 'K'}},
    'outputs': {'T': {'variable': 'T', 'unit': 'degC'}},
}
#: Steps of the fault runs, and the steps whose solve fails.
FAULT_HOURS = 8
FAILING = (3, 4, 5)
FAULT_MPC = {'horizon_steps': 3, 'on_failure': 'fallback', 'max_plan_age_steps': 1}


def write(folder: pathlib.Path, name: str, content: dict) -> pathlib.Path:
    path = folder / name
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


@pytest.fixture(scope='module')
def zone2_folder(tmp_path_factory) -> pathlib.Path:
    folder = tmp_path_factory.mktemp('controls')
    (folder / 'zone2.fmu').write_bytes(build_test_fmu('zone2').read_bytes())
    write(folder, 'zone2.yaml', ZONE2)
    return folder


def changed(**controls) -> dict:
    out = json.loads(json.dumps(ZONE2))
    for name, entry in controls.items():
        out['controls'][name].update(entry)
    return out


# -- the card ---------------------------------------------------------------------------------
def test_limits_and_safe_values_are_written_in_the_card_unit(zone2_folder):
    card = load_card(zone2_folder / 'zone2.yaml')
    q, qc = card.control_specs()
    assert (q.unit, q.min, q.max, q.safe, q.switch) == ('W', 0.0, 2000.0, 0.0, '')
    # the cooler's card unit is kW, what the controller sees W: converted at the boundary
    assert (qc.unit, qc.min, qc.max, qc.safe) == ('W', 0.0, 2000.0, 1500.0)
    assert qc.switch == 'Pcool_activate' and qc.releasable
    assert cards.describe(card)[1]['notes'].startswith('[0, 2000]; safe 1500')
    # the model built from the card carries them to every controller
    model = cards.build_model(card, 'control')
    assert model_controls(model, ('q', 'qc')) == card.control_specs()


def test_card_check_names_limits_outside_the_fmu_and_safe_values_outside_the_limits(
        zone2_folder):
    # the FMU declares Pcool >= 0 kW; a card writing W values as if in kW is caught elsewhere
    with pytest.raises(CardError) as info:
        load_card(write(zone2_folder, 'below.yaml', changed(qc={'min': -1})))
    assert ('controls.qc: min -1 kW is outside the min 0 kW zone2.fmu (Model Exchange) '
            "declares for 'Pcool'") in str(info.value)
    with pytest.raises(CardError, match=r'controls.q: safe 3000 W must be within \[min, max\] '
                       r'= \[0, 2000\] W'):
        load_card(write(zone2_folder, 'safe.yaml', changed(q={'safe': 3000})))


def test_setpoint_limits_in_kelvin_against_the_boptest_fmu(boptest_case, tmp_path):
    """The heat pump house's setpoint in K: its limits in K work, limits in degC are named."""
    document = yaml.safe_load(builtin_card('boptest_tset').read_text())
    document['boptest']['test_case'] = str(boptest_case.directory)
    spec = load_card(write(tmp_path, 'kelvin.yaml', document)).control_specs()[0]
    assert spec.unit == 'degC' and spec.switch == 'oveTSet_activate'
    assert (spec.min, spec.max, spec.safe) == pytest.approx((5.0, 35.0, 21.0))
    # limits written in degC under unit K: the FMU's declared min says what went wrong
    document['controls']['TSet'].update(min=5, max=35, safe=21)
    with pytest.raises(CardError) as info:
        load_card(write(tmp_path, 'celsius.yaml', document))
    assert 'controls.TSet: min 5 K is outside the min 278.15 K' in str(info.value)
    # the card may speak degC of a variable the FMU declares in K (converted at the boundary)
    document['controls']['TSet']['unit'] = 'degC'
    card = load_card(write(tmp_path, 'degc.yaml', document))
    assert card.controls['TSet'].unit == 'K'  # what the FMU speaks
    assert (card.control_specs()[0].min, card.control_specs()[0].max) == (5.0, 35.0)


# -- settings narrow the card -----------------------------------------------------------------
def test_settings_narrow_the_card_limits_and_override_its_safe_values(zone2_folder, caplog):
    model = cards.build_model(zone2_folder / 'zone2.yaml', 'control')
    base = controller_for(model, MpcSettings.from_flat(horizon_steps=2)).settings
    assert base.problem.control_bounds == ((0.0, 2000.0), (0.0, 2000.0))
    assert base.safe_values == (0.0, 1500.0) and base.released == (False, True)
    narrow = base.replace(control_max=1000.0)
    assert narrow.problem.control_bounds == ((0.0, 1000.0), (0.0, 1000.0))
    with pytest.raises(SettingsError, match='safe of qc'):
        narrow.replace(release='never')  # the card's safe 1500 W is outside the narrowed range
    assert narrow.replace(safe_value=500.0).safe_values == (500.0, 500.0)
    with pytest.raises(SettingsError, match="leave no range within the card's limits"):
        base.replace(control_min=2500.0)
    assert base.replace(release='never').released == (False, False)
    assert base.replace(release='release').released == (True, True)
    with caplog.at_level(logging.WARNING):
        old = base.replace(heat_rate_max_w=800.0)
    assert old.problem.control_max == 800.0
    assert 'heat_rate_max_w is deprecated: use control_max' in caplog.text
    # a model that declares no controls: the R1C1 convention (the built-in card's q)
    assert MPC(R1C1Model(), horizon_steps=2).problem.control_bounds.tolist() == [[-2000, 2000]]


def test_the_supervisor_releases_after_the_plan_tail():
    supervisor = SetpointSupervisor([(0.0, 1.0)], HOUR, [0.0], max_plan_age_steps=1,
                                    released=[True])

    class Result:
        success, message = True, ''
        controls = np.array([[0.2], [0.4], [0.6]])
        states = np.array([[290.0], [291.0], [292.0], [293.0]])

    assert supervisor.review(0.0, Result()).source == 'optimum'
    tail = supervisor.fallback(HOUR, 'solve_failed', 'injected')
    assert (tail.source, tail.controls.tolist(), tail.released) == ('plan', [0.4], ())
    last = supervisor.fallback(2 * HOUR, 'solve_failed', 'injected')
    assert (last.source, last.released, last.controls.tolist()) == ('released', (True,), [0.0])
    assert "overwrites released (the building's own controller acts)" in last.reason
    assert supervisor.sources == {'optimum': 1, 'plan': 1, 'released': 1}


# -- the fallback over a real FMU with an overwrite switch ------------------------------------
def fault_run(card: pathlib.Path) -> tuple:
    """Return the core run of the zone2 card: the solver fails at the FAILING steps."""
    model = cards.build_model(card, 'control')
    solver = FaultySolver(make_solver('slsqp'))
    controller = controller_for(model, MpcSettings.from_flat(FAULT_MPC))
    controller.mpc.set_solver(solver)
    scenario = reference_scenario('synthetic', None, FAULT_HOURS)

    def progress(rows, fines):
        if len(rows) == FAILING[0]:
            solver.faults.arm('fail', times=100_000)
        if len(rows) == FAILING[-1] + 1:
            solver.faults.clear()

    emulator = Emulator(cards.build_model(card, 'emulator'), scenario, [24.0 + KELVIN],
                        control_names=('q', 'qc'))
    result = run_closed_loop(controller, emulator, progress=progress, log_every=0)
    return result, emulator


def expected_sources() -> list[str]:
    return (['optimum'] * FAILING[0] + ['plan'] + ['released'] * (len(FAILING) - 1)
            + ['optimum'] * (FAULT_HOURS - FAILING[-1] - 1))


def test_fallback_releases_the_overwrite_then_control_comes_back(zone2_folder, caplog):
    card = zone2_folder / 'zone2.yaml'
    with caplog.at_level(logging.WARNING, logger='mshoot_core.safety'):
        result, emulator = fault_run(card)
    steps, fine = result.steps, result.fine
    assert steps['source'].tolist() == expected_sources()
    released = steps['source'] == 'released'
    assert (steps.loc[released, 'released'] == 'qc').all()
    assert (steps.loc[~released, 'released'] == '').all()
    assert "overwrites released (the building's own controller acts)" in caplog.text
    # the records: the switch off over the released steps (every minute inside), on otherwise
    for t in steps.index:
        minutes = fine.loc[t + 60.0:t + HOUR - 60.0, 'Pcool_activate']
        assert len(minutes) == 59 and (minutes == (0 if released[t] else 1)).all()
    assert fine[['q', 'qc']].notna().all().all()  # a defined input at every minute
    # the plant ignored the cooler's safe value (1.5 kW) while released: as with qc = 0
    plain = cards.build_model(card, 'control')
    for t in steps.index[released]:
        x0 = steps.loc[t, 'T_start']
        weather = emulator.scenario.loc[t, ['solrad', 'Tout', 'occ']]
        u = np.array([[steps.loc[t, 'q'], 0.0, *weather]])
        assert steps.loc[t, 'qc'] == 1500.0
        x_end, _ = plain.simulate_intervals(np.array([[x0]]), u, HOUR)
        assert x_end[0, 0] == pytest.approx(steps.loc[t, 'T_end'], abs=1e-6)
    kpis = closed_loop_kpis(steps, fine, HOUR, 1.0, ['q'], 'y_T')
    assert kpis['released_steps'] == len(FAILING) - 1


def test_boptest_plant_hands_the_heat_pump_back(boptest_case, tmp_path):
    """Released, the heat pump house's own controller runs the heat pump (records: activate 0)."""
    document = yaml.safe_load(builtin_card('boptest_modulation').read_text())
    document['boptest'] = {'test_case': str(boptest_case.directory), 'warmup_days': 0}
    card = write(tmp_path, 'modulation.yaml', document)
    model = cards.build_model(card, 'emulator')
    scenario = reference_scenario('synthetic', None, 3)
    emulator = Emulator(model, scenario, [21.0 + KELVIN], control_names=('Y',))
    try:
        on = emulator.advance([1.0])  # the heat pump overwritten to full load
        back = emulator.advance([0.0], released=[True])  # handed back: its own controller
        again = emulator.advance([0.0])  # overwritten again, off
        records = model.boptest_records()
    finally:
        model.close()
    assert (on.released, back.released, again.released) == ((), ('Y',), ())
    assert (on.fine['oveHeaPumY_activate'] == 1).all()
    assert (back.fine['oveHeaPumY_activate'] == 0).all()
    hour = records[(records['time'] > back.t_start_s - model.time_origin_s + 1)
                   & (records['time'] <= back.t_start_s - model.time_origin_s + HOUR)]
    assert hour['oveHeaPumY_u'].isna().all()  # no overwrite applied over the hour
    last = records[records['time'] > again.t_start_s - model.time_origin_s + 1]
    assert (last['oveHeaPumY_u'] == 0.0).all() and (last['reaHeaPumY_y'] < 1e-3).all()
    assert not math.isnan(float(hour['reaHeaPumY_y'].iloc[-1]))


# -- over ROS ---------------------------------------------------------------------------------
def test_fallback_over_ros_plan_tail_release_and_back(zone2_folder, context):
    """
    The solver fails for three steps over ROS: the plan's tail, then released, then control back.

    Real nodes (emulator, forecaster, MPC) in one process, lockstep; the emulator's records show
    ``Pcool_activate`` = 0 over the released steps and a defined input at every minute; the
    decisions are those of the core run. The plant is any card with an overwrite switch: the
    heat pump house (``boptest_modulation.yaml``) plugs in as the emulator's model once the MPC
    node runs its control model.
    """
    from mshoot_testing.harness import ClosedLoop
    card = str(zone2_folder / 'zone2.yaml')
    core, _ = fault_run(zone2_folder / 'zone2.yaml')
    model = cards.build_model(card, 'control')
    solver = FaultySolver(make_solver('slsqp'))
    loop = ClosedLoop(context, {'emulator': {'hours': FAULT_HOURS, 'model': card,
                                             'initial_temperature_c': 24.0},
                                'forecaster': {'hours': FAULT_HOURS},
                                'mpc': {'model': card, **FAULT_MPC}}, mpc_model=model)
    try:
        loop.mpc.mpc.set_solver(solver)
        loop.run_steps(FAILING[0])
        solver.faults.arm('fail', times=100_000)
        loop.run_steps(len(FAILING))
        solver.faults.clear()
        loop.run_to_end(120.0)
        history = list(loop.mpc_history())[:FAULT_HOURS]
        applied = loop.emulator.applied_frame()
        fine = loop.emulator.fine_frame()
        health = loop.mpc.health()
    finally:
        loop.close()
    assert [status.source for _, status in history] == expected_sources()
    released = [list(setpoint.released) for setpoint, _ in history]
    assert released == [[False, True] if s == 'released' else [] for s in expected_sources()]
    assert applied['released'].tolist() == core.steps['released'].tolist()
    np.testing.assert_allclose(applied['T_end'], core.steps['T_end'], rtol=0, atol=1e-9)
    assert fine['Pcool_activate'].tolist() == core.fine['Pcool_activate'].tolist()
    assert fine[['q', 'qc']].notna().all().all()
    assert health.values['released'] == len(FAILING) - 1  # (on /diagnostics)
