"""
Model cards: a model described once (YAML) for the Python API, the registry and the case.

The FMUs are built by the tests (tests/card_fmus.py from tests/fmus/, the R2C2 through
fmu_build): an R1C1 zone with names of its own (state ``cair.T``, no ``dpos``), the same zone
with a second control in kW behind an overwrite switch, and the two-state R2C2 (states in
degC). References: the built-in R1C1 FMU and the Python R1C1 run through today's names.
"""
import dataclasses
import json
import pathlib
import shutil
import subprocess
import sys
import zipfile

from mshoot_core import fmu_build
from mshoot_core.models import card as cards, registry
from mshoot_core.models.card import CardError, CardFmiModel, load_card
from mshoot_core.models.fmi import FmiModel
from mshoot_core.models.network import NetworkModel
from mshoot_core.models.r1c1 import R1C1Model, R1C1Parameters
from mshoot_core.mpc import MPC
from mshoot_core.scenario import reference_scenario
from mshoot_core.units import KELVIN
from mshoot_studies import card as card_cli, case
import numpy as np
import pandas as pd
import pytest
import yaml

from card_fmus import build_test_fmu

HOUR = 3600.0
ZONE_CARD = {
    'description': 'an R1C1 zone with names of its own',
    'fmu': 'zone.fmu',
    'controls': {'q': {'variable': 'q', 'unit': 'W', 'min': -2000, 'max': 2000}},
    'disturbances': {'solrad': {'variable': 'solrad', 'unit': 'W/m2'},
                     'Tout': {'variable': 'Tout', 'unit': 'degC'}, 'occ': {'variable': 'occ'}},
    'states': {'T': {'variable': 'cair.T', 'unit': 'K'}},
    'outputs': {'T': {'variable': 'T', 'unit': 'degC'}, 'Qr': {'variable': 'Qr', 'unit': 'J'}},
}


def write_card(folder: pathlib.Path, name: str, content: dict, fmu: pathlib.Path | None = None,
               fmu_name: str = 'zone.fmu') -> pathlib.Path:
    """Write ``content`` as ``folder/name`` with the FMU copied beside it (a relative path)."""
    folder.mkdir(parents=True, exist_ok=True)
    if fmu is not None and not (folder / fmu_name).exists():
        shutil.copyfile(fmu, folder / fmu_name)
    path = folder / name
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


def with_changes(base: dict, **changes) -> dict:
    out = json.loads(json.dumps(base))
    out.update(changes)
    return out


@pytest.fixture(scope='module')
def zone_fmu():
    return build_test_fmu('zone')


@pytest.fixture(scope='module')
def zone2_fmu():
    return build_test_fmu('zone2')


@pytest.fixture(scope='module')
def zone_cards(tmp_path_factory, zone_fmu):
    """Return the zone as Model Exchange and as Co-Simulation, FMU beside the cards."""
    folder = tmp_path_factory.mktemp('zone')
    me = write_card(folder, 'zone.yaml', ZONE_CARD, zone_fmu)
    cs = write_card(folder, 'zone_cs.yaml', with_changes(ZONE_CARD, fmi_type='co-simulation'))
    return me, cs


# -- the built-in models as cards -------------------------------------------------------------
@pytest.mark.parametrize('card_name, registry_name', [
    ('r1c1', 'python'), ('r1c1_fmu', 'fmu'), ('r1c1_fmu_cs', 'fmu-cs')])
def test_builtin_cards_are_the_registry_models(card_name, registry_name):
    card = load_card(cards.builtin_card(card_name))
    from_card = cards.build_model(card, 'control')
    reference = registry.build_model(registry_name)
    assert isinstance(reference, type(from_card))  # (R1C1Model: the network of its card)
    assert set(from_card.input_names) == set(reference.input_names)
    assert from_card.state_names == reference.state_names == ('T',)
    assert from_card.output_names == reference.output_names == ('T', 'Qr')
    assert getattr(from_card, 'fmi_type', None) == getattr(reference, 'fmi_type', None)
    assert from_card.monotone_inputs == reference.monotone_inputs == ('q',)  # an RC network
    rng = np.random.default_rng(1)
    columns = {'solrad': rng.uniform(0, 400, 6), 'Tout': rng.uniform(-5, 15, 6),
               'occ': rng.integers(0, 30, 6).astype(float), 'dpos': rng.uniform(0, 50, 6),
               'q': rng.uniform(-2000, 2000, 6)}
    x0 = rng.uniform(290, 296, (6, 1))

    def run(model):
        u = np.column_stack([columns[n] for n in model.input_names])
        return model.simulate_intervals(x0, u, HOUR)

    for got, want in zip(run(from_card), run(reference)):
        np.testing.assert_array_equal(got, want)
    # against another implementation: the Python R1C1 against the FMU (at the emulator's
    # tolerance), the FMU cards against the Python R1C1
    other = registry.build_model('fmu' if registry_name == 'python' else 'python', 1e-10)
    for got, want in zip(run(from_card), run(other)):
        np.testing.assert_allclose(got, want, rtol=1e-6)


def test_write_parameters_copies_a_card_with_new_values(tmp_path, zone_cards):
    """A network card's entries take the values, bounds kept; an FMU card's its parameters."""
    source = cards.builtin_card('boptest_house')
    before = load_card(source).network.parameters
    copy = cards.write_parameters(source, {'Cz': 2.5e4, 'gi': 0.5}, tmp_path / 'out' / 'c.yaml',
                                  ['fitted by a test', 'second line'], 'the house, fitted')
    text = copy.read_text()
    assert text.startswith('# fitted by a test\n# second line\n')
    after = load_card(copy)
    assert after.description == 'the house, fitted'
    assert after.network.parameters['Cz'] == dataclasses.replace(before['Cz'], value=2.5e4)
    assert after.network.parameters['gi'].value == 0.5
    assert {n: p for n, p in after.network.parameters.items() if n not in ('Cz', 'gi')} == {
        n: p for n, p in before.items() if n not in ('Cz', 'gi')}
    assert source.read_text() != text and load_card(source).network.parameters == before
    with pytest.raises(ValueError, match=r"unknown network parameters \['nope'\]"):
        cards.write_parameters(source, {'nope': 1.0}, tmp_path / 'bad.yaml')
    # an FMU card (its FMU beside it): the copy elsewhere names the FMU by its absolute path
    fmu_copy = cards.write_parameters(zone_cards[0], {'shgc': 1.5}, tmp_path / 'fmu' / 'z.yaml')
    loaded = load_card(fmu_copy)
    assert loaded.parameters == {'shgc': 1.5}
    assert loaded.fmu == load_card(zone_cards[0]).fmu


def test_a_cards_parameters_reach_its_model(tmp_path):
    """The built-in Python card with a parameter of its own is that R1C1, not the default."""
    document = yaml.safe_load(cards.builtin_card('r1c1').read_text())
    changed = write_card(tmp_path, 'r1c1.yaml', {**document, 'parameters': {'shgc': 1.5}})
    x0, u = np.array([[293.15]]), np.array([[400.0, 5.0, 0.0, 0.0, 0.0]])  # solrad first

    def end_state(model):
        order = ['solrad', 'Tout', 'occ', 'dpos', 'q']
        return model.simulate_intervals(x0, u[:, [order.index(n) for n in model.input_names]],
                                        HOUR)[0]

    got = end_state(cards.build_model(changed))
    np.testing.assert_array_equal(got, end_state(R1C1Model(R1C1Parameters(shgc=1.5))))
    assert not np.allclose(got, end_state(R1C1Model()))


def test_registry_takes_card_paths(zone_cards, tmp_path):
    me, cs = zone_cards
    assert registry.check_model(str(me)) is None
    model = registry.build_model(str(cs), 1e-7, role='emulator')
    assert isinstance(model, FmiModel) and model.fmi_type == 'CoSimulation'
    assert model.input_names == ('q', 'solrad', 'Tout', 'occ') and model.tolerance == 1e-7
    tolerant = write_card(me.parent, 'tol.yaml', with_changes(ZONE_CARD, tolerance=1e-9))
    assert registry.build_model(str(tolerant), 1e-4).tolerance == 1e-9  # the card's wins
    bad = write_card(tmp_path, 'bad.yml', with_changes(ZONE_CARD, fmu='nowhere.fmu'))
    problem = registry.check_model(str(bad))
    assert str(bad) in problem and 'nowhere.fmu' in problem and '\n' not in problem
    with pytest.raises(ValueError, match='nowhere.fmu'):
        registry.build_model(str(bad))
    with pytest.raises(ValueError, match='cannot register'):
        registry.register('mine.yaml', lambda tolerance: R1C1Model(), 'no')


# -- an FMU with other names, through the case command ----------------------------------------
def _kpis(out: pathlib.Path) -> dict:
    kpis = json.loads((out / 'kpis.json').read_text())
    return {k: v for k, v in kpis.items() if isinstance(v, (int, float)) and not isinstance(
        v, bool) and not (k.endswith('_s') or k.startswith('solve_s') or k == 'tolerance'
                          or k == 'solve_per_control_step')}


def _assert_same_kpis(got: dict, want: dict, rel: float) -> None:
    assert got.keys() == want.keys()
    for key in want:
        assert got[key] == pytest.approx(want[key], rel=rel, abs=1e-9), key


@pytest.mark.parametrize('pair, hours, rel, atol_k', [
    (('me', 'cs'), 24, 1e-6, 1e-6), (('cs', 'me'), 12, 1e-5, 1e-3)])
def test_fmu_with_other_names_runs_the_case_like_the_builtin_fmu(zone_cards, tmp_path, pair,
                                                                 hours, rel, atol_k):
    """
    Control model and emulator from cards alone; the same KPIs as the built-in FMU.

    With Model Exchange control models (forward sensitivities) the runs agree to rounding;
    with Co-Simulation control models the optimiser works on finite differences of two FMUs
    that round differently, and stops within its tolerance: 1e-5 there.
    """
    paths = dict(zip(('me', 'cs'), zone_cards))
    builtin = {'me': 'fmu', 'cs': 'fmu-cs'}
    common = ['synthetic', '--hours', str(hours), '--horizon', '6']
    assert case.main([*common, '--control', str(paths[pair[0]]), '--emulator',
                      str(paths[pair[1]]), '--out', str(tmp_path / 'card')]) == 0
    assert case.main([*common, '--control', builtin[pair[0]], '--emulator', builtin[pair[1]],
                      '--out', str(tmp_path / 'builtin')]) == 0
    got, want = _kpis(tmp_path / 'card'), _kpis(tmp_path / 'builtin')
    assert want['steps'] == hours and want['energy_kwh'] > 1.0
    _assert_same_kpis(got, want, rel=rel)
    trajectories = [pd.read_csv(tmp_path / d / 'trajectories.csv') for d in ('card', 'builtin')]
    np.testing.assert_allclose(trajectories[0]['y_T'], trajectories[1]['y_T'], rtol=0,
                               atol=atol_k)


def test_ou44_case_with_the_builtin_card_gives_todays_kpis(ou44_csv, tmp_path):
    common = ['ou44', '--data', str(ou44_csv)]
    card = cards.builtin_card('r1c1_fmu')
    assert case.main([*common, '--control', str(card), '--out', str(tmp_path / 'card')]) == 0
    assert case.main([*common, '--control', 'fmu', '--out', str(tmp_path / 'today')]) == 0
    got, want = _kpis(tmp_path / 'card'), _kpis(tmp_path / 'today')
    assert want['steps'] == 72
    _assert_same_kpis(got, want, rel=1e-6)


def test_case_rejects_a_bad_card_in_one_line(zone_cards, tmp_path, caplog):
    bad = write_card(tmp_path, 'bad.yaml', with_changes(
        ZONE_CARD, fmu=str(zone_cards[0].parent / 'zone.fmu'),
        states={'T': {'variable': 'heatCapacitor.T'}}))
    assert case.main(['synthetic', '--hours', '3', '--control', str(bad), '--out',
                      str(tmp_path / 'out')]) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == 'ERROR']
    assert len(errors) == 1 and '\n' not in errors[0]
    assert f'--control: model card {bad}' in errors[0]
    assert "'heatCapacitor.T' is not one of the continuous states" in errors[0]
    assert 'cair.T (local, state, K)' in errors[0]
    assert not (tmp_path / 'out').exists()


def test_case_rejects_cards_that_do_not_fit_the_scenario(tmp_path, caplog):
    """The R2C2 card needs a series Qsun the scenario lacks; its states are not the emulator's."""
    r2c2 = write_card(tmp_path, 'r2c2.yaml', R2C2_CARD, fmu_build.ensure_fmu('r2c2'),
                      fmu_name='r2c2.fmu')
    assert case.main(['synthetic', '--hours', '3', '--horizon', '2', '--control', str(r2c2),
                      '--out', str(tmp_path / 'out')]) == 2
    text = caplog.text
    assert "inputs ['Qsun'] are neither controls nor series of the scenario" in text
    assert "the control model has the states ['T', 'Tw'], the emulator ['T']" in text


# -- two controls, two states, unit conversion ------------------------------------------------
ZONE2_CARD = with_changes(
    ZONE_CARD, fmu='zone2.fmu', parameters={'tmass': 5.0},
    controls={'q': {'variable': 'q', 'unit': 'W', 'min': 0, 'max': 2000},
              'qc': {'variable': 'Pcool', 'unit': 'kW', 'min': 0, 'max': 2,
                     'activate': 'Pcool_activate'}})
R2C2_CARD = {
    'fmu': 'r2c2.fmu',
    'parameters': {'Rwin': 0.04},
    'controls': {'q': {'variable': 'Qhvac', 'unit': 'W'}},
    'disturbances': {'Tout': {'variable': 'Tamb'}, 'Qsun': {'variable': 'Qsun'}},
    'states': {'T': {'variable': 'air.T'}, 'Tw': {'variable': 'wall.T'}},
    'outputs': {'T': {'variable': 'Tair'}},
}


@pytest.fixture(scope='module')
def zone2_card(tmp_path_factory, zone2_fmu):
    folder = tmp_path_factory.mktemp('zone2')
    return load_card(write_card(folder, 'zone2.yaml', ZONE2_CARD, zone2_fmu, 'zone2.fmu'))


def test_two_control_card_solves_an_mpc_step(zone2_card):
    """
    Heating q [W] and a cooler qc [W]: from 26 degC on a warm day the MPC cools into the band.

    The FMU takes qc in kW behind its overwrite switch; the MPC cools without heating.
    """
    model = cards.build_model(zone2_card, 'control')
    assert isinstance(model, CardFmiModel)
    assert model.input_names == ('q', 'qc', 'solrad', 'Tout', 'occ')
    assert model.fixed_inputs == {'Pcool_activate': 1}
    mpc = MPC(model, horizon_steps=6, control_names=zone2_card.control_names)
    assert mpc.problem.control_bounds.tolist() == [[0.0, 2000.0], [0.0, 2000.0]]  # the card's
    rows = 7
    forecast = pd.DataFrame({'solrad': np.full(rows, 100.0), 'Tout': np.full(rows, 24.0),
                             'occ': np.full(rows, 5.0), 'comfort_min': np.full(rows, 21.0),
                             'comfort_max': np.full(rows, 22.0)},
                            index=np.arange(rows) * HOUR)
    result = mpc.solve([26.0 + KELVIN], 0.0, forecast)
    assert result.success, result.message
    plan = result.plan
    assert list(plan.columns[:2]) == ['q', 'qc']
    assert plan['qc'].iloc[0] > 1900.0 and np.all(plan['q'] <= 1.0)
    assert np.all(np.diff(plan['T_end'].to_numpy()[:3]) < 0)  # cooling down ...
    assert np.all(plan['T_end'].iloc[-2:] <= 22.0 + KELVIN + 1e-4)  # ... into the band
    # without the switch the FMU ignores the cooler: the same plan would not cool at all
    switchless = with_changes(ZONE2_CARD)
    del switchless['controls']['qc']['activate']
    path = write_card(zone2_card.path.parent, 'switchless.yaml', switchless)
    plain = cards.build_model(path, 'control')
    u = np.array([[0.0, 2000.0, 300.0, 24.0, 20.0], [0.0, 0.0, 300.0, 24.0, 20.0]])
    x_end, _ = plain.simulate_intervals(np.full((2, 1), 26.0 + KELVIN), u, HOUR)
    assert x_end[0, 0] == x_end[1, 0]
    x_end, _ = model.simulate_intervals(np.full((2, 1), 26.0 + KELVIN), u, HOUR)
    assert x_end[0, 0] < x_end[1, 0] - 1.0


def test_two_control_card_runs_the_case(zone2_card, tmp_path, caplog):
    """
    The case takes the controls from the cards.

    The MPC plans q and qc each within its own limits (the card writes qc's in kW), the emulator
    clips to its card's limits.
    """
    narrow = with_changes(ZONE2_CARD)
    narrow['controls']['qc']['max'] = 1.5
    control = write_card(zone2_card.path.parent, 'narrow.yaml', narrow)
    out = tmp_path / 'case'
    assert case.main(['synthetic', '--hours', '6', '--horizon', '3', '--control', str(control),
                      '--emulator', str(zone2_card.path), '--out', str(out)]) == 0
    steps = pd.read_csv(out / 'steps.csv')
    assert {'q', 'qc'} <= set(steps.columns) and len(steps) == 6
    assert steps['q'].between(0.0, 2000.0 + 1e-6).all()
    assert steps['qc'].between(0.0, 1500.0 + 1e-6).all()
    kpis = json.loads((out / 'kpis.json').read_text())
    assert kpis['energy_kwh'] == pytest.approx(steps['q'].abs().sum() / 1000.0)


def test_fixed_inputs_of_fmimodel_are_free_inputs(zone2_fmu):
    with pytest.raises(ValueError, match=r"invalid fixed_inputs \['q'\]; expected inputs not "
                                         r'mapped as model inputs'):
        FmiModel(zone2_fmu, inputs=['q'], states={'T': 'cair.T'}, outputs=['T'],
                 fixed_inputs={'q': 1.0})


@pytest.mark.parametrize('fmi_type', ['ModelExchange', 'CoSimulation'])
def test_unit_conversion_at_the_boundary(zone2_card, zone2_fmu, fmi_type):
    """Control qc [W] reaches the FMU as Pcool [kW]; parameters reach it too; derivatives scale."""
    card = dataclasses.replace(zone2_card, interface=fmi_type)
    model = cards.build_model(card, 'control', tolerance=1e-10)
    raw = FmiModel(zone2_fmu, inputs=['q', 'Pcool', 'solrad', 'Tout', 'occ'],
                   states={'T': 'cair.T'}, outputs=['T', 'Qr'], parameters={'tmass': 5.0},
                   fixed_inputs={'Pcool_activate': True}, fmi_type=fmi_type, tolerance=1e-10)
    rng = np.random.default_rng(3)
    u = np.column_stack([rng.uniform(0, 2000, 5), rng.uniform(0, 2000, 5),
                         rng.uniform(0, 400, 5), rng.uniform(0, 25, 5), rng.uniform(0, 30, 5)])
    x0 = rng.uniform(292, 300, (5, 1))
    u_raw = u.copy()
    u_raw[:, 1] /= 1000.0
    for got, want in zip(model.simulate_intervals(x0, u, HOUR),
                         raw.simulate_intervals(x0, u_raw, HOUR)):
        np.testing.assert_allclose(got, want, rtol=1e-12)
    jac = model.interval_jacobians(x0, u, HOUR, [0, 1])
    if fmi_type == 'CoSimulation':
        assert jac is None  # finite differences on the canonical model
        return
    step = 1e-2
    up = u.copy()
    up[:, 1] += step
    x_up, y_up = model.simulate_intervals(x0, up, HOUR)
    x_end, y_end = model.simulate_intervals(x0, u, HOUR)
    np.testing.assert_allclose(jac.dx_du[:, 0, 1], (x_up[:, 0] - x_end[:, 0]) / step,
                               rtol=1e-5)
    np.testing.assert_allclose(jac.dy_du[:, 0, 1], (y_up[:, 0] - y_end[:, 0]) / step,
                               rtol=1e-5)
    assert np.all(jac.dx_du[:, 0, 1] < 0)  # cooling


def test_r2c2_card_builds_with_two_states_in_kelvin(tmp_path):
    """The R2C2's states are in degC: the card's states are in K, its output in degC."""
    path = write_card(tmp_path, 'r2c2.yaml', R2C2_CARD, fmu_build.ensure_fmu('r2c2'),
                      fmu_name='r2c2.fmu')
    card = load_card(path)
    assert card.interface == 'ModelExchange' and card.state_names == ('T', 'Tw')
    assert [card.states[n].canonical_unit for n in card.state_names] == ['K', 'K']
    assert card.states['Tw'].model_start == pytest.approx(18.0 + KELVIN)
    np.testing.assert_allclose(card.initial_state(294.0), [294.0, 18.0 + KELVIN])
    model = cards.build_model(card, 'emulator')
    assert isinstance(model, CardFmiModel) and model.tolerance == registry.EMULATOR_TOLERANCE
    assert model.state_names == ('T', 'Tw') and model.input_names == ('q', 'Tout', 'Qsun')
    raw = FmiModel(path.parent / 'r2c2.fmu', inputs=['Qhvac', 'Tamb', 'Qsun'],
                   states=['air.T', 'wall.T'], outputs=['Tair'], parameters={'Rwin': 0.04},
                   tolerance=registry.EMULATOR_TOLERANCE)
    x0_c = np.array([[21.0, 18.0], [19.0, 17.0]])
    u = np.array([[1500.0, 2.0, 300.0], [0.0, 10.0, 0.0]])
    x_end, y_end = model.simulate_intervals(x0_c + KELVIN, u, HOUR)
    x_raw, y_raw = raw.simulate_intervals(x0_c, u, HOUR)
    np.testing.assert_allclose(x_end, x_raw + KELVIN, rtol=0, atol=1e-9)
    np.testing.assert_allclose(y_end, y_raw, rtol=0, atol=1e-9)
    jac, jac_raw = (m.interval_jacobians(x, u, HOUR, [0])
                    for m, x in ((model, x0_c + KELVIN), (raw, x0_c)))
    np.testing.assert_allclose(jac.dx_dx0, jac_raw.dx_dx0, rtol=1e-12)  # offsets only
    udf = pd.DataFrame(np.repeat(u[:1], 3, axis=0), index=[0.0, HOUR, 2 * HOUR],
                       columns=list(model.input_names))
    ydf, xdf = model.simulate(udf, x0_c[0] + KELVIN)
    ydf_raw, xdf_raw = raw.simulate(udf.set_axis(list(raw.input_names), axis=1), x0_c[0])
    np.testing.assert_allclose(xdf.to_numpy(), xdf_raw.to_numpy() + KELVIN, atol=1e-9)
    np.testing.assert_allclose(ydf.to_numpy(), ydf_raw.to_numpy(), atol=1e-9)


def test_unit_conversions():
    assert cards.conversion('degC', 'K') == (1.0, KELVIN)
    assert cards.conversion('K', 'degC') == (1.0, -KELVIN)
    assert cards.conversion('W', 'kW') == (1e-3, 0.0)
    assert cards.conversion('J', 'kWh') == pytest.approx((1 / 3.6e6, 0.0))
    assert cards.conversion('%', '1') == (0.01, 0.0)  # 50 % is 0.5 for the model
    assert cards.conversion('1', '') == (1.0, 0.0)
    with pytest.raises(ValueError, match="'W' does not convert to 'degC'"):
        cards.conversion('degC', 'W')
    assert cards.canonical_unit('states', 'T', 'degC') == ('K', None)
    assert cards.canonical_unit('outputs', 'T', 'K') == ('degC', None)
    assert cards.canonical_unit('controls', 'fan', 'kW') == ('W', None)
    assert cards.canonical_unit('outputs', 'co2', 'ppm') == ('ppm', None)  # passed through
    unit, problem = cards.canonical_unit('disturbances', 'Tout', 'ppm')
    assert unit == 'degC' and "unit 'ppm' does not convert to the canonical 'degC'" in problem


# -- bad cards: every problem at once ---------------------------------------------------------
def test_bad_card_lists_every_problem_at_once(zone_cards, tmp_path):
    content = with_changes(
        ZONE_CARD, fmu=str(zone_cards[0].parent / 'zone.fmu'), colour='blue',
        parameters={'shgc': 4.0, 'nope': 1.0},
        controls={'q': {'variable': 'heat', 'unit': 'W', 'mni': 0},
                  'fan': {'variable': 'q', 'unit': 'furlong'}},
        disturbances={'Tout': {'variable': 'Tout', 'unit': 'W'},
                      'solrad': {'variable': 'solrad', 'unit': 'kW'}},
        states={'T': {'variable': 'cair.t', 'unit': 'K'}})
    del content['outputs']
    path = write_card(tmp_path, 'bad.yaml', content)
    with pytest.raises(CardError) as caught:
        load_card(path)
    error = caught.value
    assert error.path == path and str(error).startswith(f'model card {path}: ')
    problems = error.problems
    expected = [
        "card: unknown key 'colour'",
        "missing required key 'outputs'",
        "controls.q: unknown key 'mni'; allowed: activate, max, min, safe, unit, variable",
        "controls.q: 'heat' is not a Real input of zone.fmu (Model Exchange); valid: solrad "
        '(input, W/m2), Tout (input, degC), occ (input, 1), q (input, W)',
        "controls.fan: unit 'furlong' differs from the unit 'W' zone.fmu (Model Exchange) "
        "declares for 'q'",
        "disturbances.Tout: unit 'W' differs from the unit 'degC' zone.fmu (Model Exchange) "
        "declares for 'Tout'",
        "disturbances.solrad: unit 'kW' differs from the unit 'W/m2'",
        "states.T: 'cair.t' is not one of the continuous states of zone.fmu (Model Exchange); "
        'valid: cair.T (local, state, K), Qr (output, state, J)',
        'parameters.nope: not a settable parameter of zone.fmu (Model Exchange); valid: ',
    ]
    for text in expected:
        assert sum(text in p for p in problems) == 1, (text, problems)
    assert len(problems) == len(expected)


def test_card_problems_without_a_model(tmp_path):
    path = write_card(tmp_path, 'card.yaml', {
        'fmu': 'missing.fmu', 'builtin': 'r1c1', 'fmi_type': 'model exchange',
        'tolerance': 2.0, 'time_origin': 'soon',
        'controls': {}, 'states': {'1T': {'variable': 'x'}}, 'outputs': {'T': 'T'}})
    with pytest.raises(CardError) as caught:
        load_card(path)
    problems = caught.value.problems
    for text in ("give only one of 'fmu' (path of an FMU, relative to the card), 'builtin'",
                 "fmi_type must be one of ['auto', 'model-exchange', 'co-simulation'], got "
                 "'model exchange'", 'tolerance: 2.0 is greater than or equal to the maximum',
                 'controls: needs at least one entry', "states: name '1T' must be an identifier",
                 "outputs.T: expected object, got 'T'",
                 "time_origin must be 'scenario' or an ISO 8601 date-time"):
        assert sum(text in p for p in problems) == 1, (text, problems)
    missing = write_card(tmp_path, 'missing.yaml', with_changes(ZONE_CARD, fmu='../x/zone.fmu'))
    with pytest.raises(CardError, match=r'fmu: file not found: .*/x/zone\.fmu \(the path is '
                                        r'relative to the card'):
        load_card(missing)
    with pytest.raises(CardError, match='file not found'):
        load_card(tmp_path / 'nothing.yaml')
    (tmp_path / 'junk.fmu').write_text('not a zip')
    with pytest.raises(CardError, match=r'fmu: .*junk.fmu is not an FMU: not a ZIP archive'):
        load_card(write_card(tmp_path, 'junk.yaml', with_changes(ZONE_CARD, fmu='junk.fmu')))
    with zipfile.ZipFile(tmp_path / 'fmi3.fmu', 'w') as archive:
        archive.writestr('modelDescription.xml', FMI3_DESCRIPTION)
    with pytest.raises(CardError, match=r'fmu: fmi3.fmu: FMI 3.0 FMUs are not supported yet '
                                        r"\(fmiVersion '3.0'\); export the model as an FMI 2.0"):
        load_card(write_card(tmp_path, 'fmi3.yaml', with_changes(ZONE_CARD, fmu='fmi3.fmu')))
    twice = tmp_path / 'twice.yaml'
    twice.write_text('fmu: a.fmu\nfmu: b.fmu\n')
    with pytest.raises(CardError, match="key 'fmu' is given twice"):
        load_card(twice)
    (tmp_path / 'list.yaml').write_text('- 1\n')
    with pytest.raises(CardError, match='card: expected object'):
        load_card(tmp_path / 'list.yaml')


FMI3_DESCRIPTION = """<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="3.0" modelName="Zone3"
  instantiationToken="{8c4e810f-3df3-4a00-8276-176fa3c9f000}">
  <ModelExchange modelIdentifier="Zone3"/>
  <ModelVariables>
    <Float64 name="time" valueReference="0" causality="independent" variability="continuous"/>
  </ModelVariables>
  <ModelStructure/>
</fmiModelDescription>
"""


def test_python_r1c1_card_keeps_its_names_and_units(tmp_path):
    content = yaml.safe_load(cards.builtin_card('r1c1').read_text())
    content['controls'] = {'heat': {'variable': 'q'}}
    content['disturbances']['Tout'] = {'unit': 'K'}
    content['states']['T']['unit'] = 'degC'
    content['parameters'] = {'shgc': 3.0, 'Rext': 1.0}
    with pytest.raises(CardError) as caught:
        load_card(write_card(tmp_path, 'python.yaml', content))
    problems = caught.value.problems
    for text in ("controls.heat: the network of python.yaml keeps its own names: use 'q'",
                 "disturbances.Tout: unit 'K' differs from the unit 'degC' the network of "
                 'python.yaml',
                 "states.T: unit 'degC' differs from the unit 'K'",
                 'parameters.Rext: not a settable parameter of the network of python.yaml; '
                 'valid: RExt'):
        assert sum(text in p for p in problems) == 1, (text, problems)
    good = yaml.safe_load(cards.builtin_card('r1c1').read_text())
    good['parameters'] = {'shgc': 3.0}
    model = cards.build_model(write_card(tmp_path, 'good.yaml', good))
    assert isinstance(model, NetworkModel) and model.parameters['shgc'] == 3.0


def test_monotone_is_the_card_authors_claim(zone_cards, tmp_path, r1c1_fmu):
    """
    A model is monotone as its card says; an FMU claims nothing unless its card does.

    ``false`` withdraws a built-in model's claim; anything but a boolean is a problem of the
    card.
    """
    zone = load_card(zone_cards[0])
    assert zone.monotone is None and cards.build_model(zone).monotone_inputs == ()
    claimed = write_card(zone_cards[0].parent, 'monotone.yaml', with_changes(
        yaml.safe_load(zone_cards[0].read_text()), monotone=True))
    model = cards.build_model(claimed)
    assert model.monotone_inputs == ('q',)
    assert MPC(model, horizon_steps=2).problem.monotone
    withdrawn = with_changes(yaml.safe_load(cards.builtin_card('r1c1').read_text()),
                             monotone=False)
    python = cards.build_model(write_card(tmp_path, 'r1c1.yaml', withdrawn))
    assert isinstance(python, NetworkModel) and python.monotone_inputs == ()
    assert not MPC(python, horizon_steps=2).problem.monotone
    assert R1C1Model().monotone_inputs == ('q',)  # (derived from the network's structure)
    with pytest.raises(CardError, match='monotone'):
        load_card(write_card(tmp_path, 'bad.yaml', with_changes(withdrawn, monotone='yes')))
    # the built-in FMU claims it, another file of the same names does not
    from mshoot_core.models.fmi import r1c1_fmi_model
    assert r1c1_fmi_model(fmi_type='ModelExchange').monotone_inputs == ('q',)
    assert r1c1_fmi_model(fmi_type='ModelExchange', fmu_path=r1c1_fmu).monotone_inputs == ()


def test_overwrite_switch_must_be_a_free_input(zone2_card):
    content = with_changes(ZONE2_CARD)
    content['controls']['q']['activate'] = 'Pcool'  # mapped as a control already
    content['disturbances']['solrad']['activate'] = 'x'  # not a key of disturbances
    content['controls']['qc']['activate'] = 'Pcool_on'
    with pytest.raises(CardError) as caught:
        load_card(write_card(zone2_card.path.parent, 'switches.yaml', content))
    problems = caught.value.problems
    for text in ("controls.q.activate: 'Pcool' is mapped as a control or disturbance",
                 "controls.qc.activate: 'Pcool_on' is not an input of zone2.fmu (Model "
                 'Exchange); valid: Pcool (input, kW), Pcool_activate (input), solrad',
                 "disturbances.solrad: unknown key 'activate'"):
        assert sum(text in p for p in problems) == 1, (text, problems)


def test_time_origin(zone_cards):
    card = load_card(zone_cards[0])
    assert card.time_origin == 'scenario'
    assert cards.time_origin_seconds(card, '2018-04-05T00:00:00') == 0.0
    dated = dataclasses.replace(card, time_origin='2018-01-01T00:00:00')
    assert cards.time_origin_seconds(dated, '2018-01-02T06:00:00') == -30 * HOUR
    with pytest.raises(ValueError, match='time zone'):
        cards.time_origin_seconds(dated, '2018-01-02T06:00:00+01:00')
    # an unquoted YAML date-time is read as a date-time, and taken as one
    text = zone_cards[0].read_text() + 'time_origin: 2018-01-01T00:00:00\n'
    unquoted = zone_cards[0].parent / 'dated.yaml'
    unquoted.write_text(text)
    assert load_card(unquoted).time_origin == '2018-01-01T00:00:00'


def test_schema_and_builtin_cards_ship_with_the_package(tmp_path):
    """The package's build (setuptools build_py, as a wheel is made) holds the cards and schema."""
    schema = cards.schema()
    assert schema['title'] == 'mshoot model card'
    assert {'fmu', 'builtin', 'controls', 'states', 'outputs'} <= set(schema['properties'])
    package = pathlib.Path(cards.__file__).resolve().parents[2]
    subprocess.run([sys.executable, 'setup.py', '-q', 'build_py', '--build-lib',
                    str(tmp_path / 'lib')], cwd=package, check=True, capture_output=True,
                   timeout=300)
    built = tmp_path / 'lib' / 'mshoot_core'
    for source in (*cards.CARDS_DIR.glob('*.yaml'), cards.SCHEMA_PATH):
        shipped = built / source.relative_to(package / 'mshoot_core')
        assert shipped.read_bytes() == source.read_bytes(), shipped
    assert sorted(p.name for p in (built / 'cards').glob('*.yaml')) == [
        'boptest_baseline.yaml', 'boptest_house.yaml', 'boptest_modulation.yaml',
        'boptest_setpoint.yaml', 'boptest_tset.yaml', 'r1c1.yaml',
        'r1c1_fmu.yaml', 'r1c1_fmu_cs.yaml', 'r1c1x2.yaml', 'r2c2.yaml',
        'setpoint_zone_identified.yaml', 'setpoint_zone_model.yaml', 'setpoint_zone_plant.yaml']


def test_documented_cards_follow_the_schema():
    """The worked cards of the models page (docs/concepts/models.md) stay valid cards."""
    page = (pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'concepts' / 'models.md')
    blocks = [b.split('```', 1)[0] for b in page.read_text().split('```yaml\n')[1:]]
    assert len(blocks) == 2
    for block in blocks:
        document = yaml.safe_load(block)
        assert cards.schema_problems(document) == [], block
        assert {'fmu', 'fmi_type', 'controls', 'states', 'outputs'} <= set(document)


# -- mshoot card ------------------------------------------------------------------------------
def test_card_check_prints_what_the_card_maps(zone2_card, capsys):
    assert card_cli.main(['check', str(zone2_card.path)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f'model card {zone2_card.path}: OK\n')
    assert 'parameters: tmass = 5.0' in out
    lines = {line.split()[1]: line.split() for line in out.splitlines()
             if line.split()[:1] in (['control'], ['disturbance'], ['state'], ['output'])}
    assert lines['qc'][:6] == ['control', 'qc', 'Pcool', 'input', 'kW', 'W']
    assert 'kW = 0.001 * W' in out and 'Pcool_activate := 1' in out
    assert lines['T'][:6] == ['output', 'T', 'T', 'output', 'degC', 'degC']


def test_card_check_exits_2_with_every_problem(tmp_path, capsys):
    path = write_card(tmp_path, 'bad.yaml', with_changes(ZONE_CARD, fmu='gone.fmu', extra=1))
    assert card_cli.main(['check', str(path)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f'model card {path}: 2 problems'
    assert err[1].startswith("  - card: unknown key 'extra'")
    assert err[2].startswith('  - fmu: file not found')


def test_mshoot_card_executable(zone_cards, zone_fmu, tmp_path):
    mshoot = shutil.which('mshoot')
    assert mshoot is not None, 'mshoot not on PATH: source env.sh'
    good = subprocess.run([mshoot, 'card', 'check', str(zone_cards[1])], capture_output=True,
                          text=True, timeout=120)
    assert good.returncode == 0, good.stderr
    assert 'as CoSimulation (fmi_type co-simulation)' in good.stdout
    bad = write_card(tmp_path, 'bad.yaml', with_changes(ZONE_CARD, fmu=str(zone_fmu),
                                                        states={'T': {'variable': 'T'}}))
    done = subprocess.run([mshoot, 'card', 'check', str(bad)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    assert "'T' is not one of the continuous states" in done.stderr
    listing = subprocess.run([mshoot, 'card', 'variables', str(zone_fmu), '--causality',
                              'input'], capture_output=True, text=True, timeout=120)
    assert listing.returncode == 0
    names = [line.split()[0] for line in listing.stdout.splitlines()[2:]]
    assert names == ['solrad', 'Tout', 'occ', 'q']


def test_case_options_accept_names_and_cards(tmp_path, caplog):
    """A card path reaches the card loader (its problem, exit 2); an unknown name is refused."""
    common = ['synthetic', '--hours', '2', '--out', str(tmp_path / 'out')]
    for option, name in (('--control', 'x.yaml'), ('--emulator', 'x.yml')):
        caplog.clear()
        assert case.main([*common, option, str(tmp_path / name)]) == 2
        assert f'{option}: model card {tmp_path / name}: file not found' in caplog.text
    with pytest.raises(SystemExit) as stop:
        case.main([*common, '--control', 'nope'])
    assert stop.value.code == 2


def test_case_scenario_has_the_series_of_the_zone_card(zone_cards, tmp_path):
    """The case feeds the zone card's disturbances from the scenario's series (no dpos)."""
    card = load_card(zone_cards[0])
    assert 'dpos' not in card.disturbance_names
    assert case.main(['synthetic', '--hours', '2', '--horizon', '2', '--control',
                      str(zone_cards[0]), '--emulator', str(zone_cards[0]), '--out',
                      str(tmp_path / 'out')]) == 0
    # the emulated zone (an R1C1 with names of its own) followed the Python R1C1 driven by the
    # scenario's series and the applied heat rates
    fine = pd.read_csv(tmp_path / 'out' / 'trajectories.csv', index_col='time_s')
    steps = pd.read_csv(tmp_path / 'out' / 'steps.csv', index_col='time_s')
    scenario = reference_scenario('synthetic', hours=2)
    reference, x = R1C1Model(), np.array([[case.INITIAL_C + KELVIN]])
    for t, q in steps['q'].items():
        row = {**scenario.loc[t].to_dict(), 'q': q}
        x, _ = reference.simulate_intervals(x, np.array([[row[n] for n in
                                                          reference.input_names]]), HOUR)
        assert fine.loc[t + HOUR, 'x_T'] == pytest.approx(x[0, 0], abs=1e-5)


def test_co_simulation_only_fmu_runs_from_its_card(tmp_path):
    """
    An FMU that offers only Co-Simulation runs from its card.

    `auto` picks Co-Simulation, `model-exchange` is a problem of the card, and as control model
    and emulator it gives the built-in CS FMU's KPIs.
    """
    fmu = build_test_fmu('zone_cs')
    auto = write_card(tmp_path, 'zone_cs.yaml', ZONE_CARD, fmu)
    model = cards.build_model(auto)
    try:
        assert model.fmi_type == 'CoSimulation'
    finally:
        model.close()
    me = write_card(tmp_path, 'zone_me.yaml', with_changes(ZONE_CARD, fmi_type='model-exchange'))
    with pytest.raises(CardError, match=r"offers \['CoSimulation'\] only, got 'model-exchange'"):
        load_card(me)
    common = ['synthetic', '--hours', '12', '--horizon', '6']
    assert case.main([*common, '--control', str(auto), '--emulator', str(auto), '--out',
                      str(tmp_path / 'card')]) == 0
    assert case.main([*common, '--control', 'fmu-cs', '--emulator', 'fmu-cs', '--out',
                      str(tmp_path / 'builtin')]) == 0
    _assert_same_kpis(_kpis(tmp_path / 'card'), _kpis(tmp_path / 'builtin'), rel=1e-5)
