"""
The thermal network model against closed forms, matrix exponentials and differences.

References are written here from the equations, independently of the network code: the
R1C1 closed-form response, the R2C2's A and b fed to scipy's matrix exponential, central
differences of the exact solution for every derivative.
"""
import math

from mshoot_core.models import card as cards
from mshoot_core.models.multizone import multizone_network, MultiZoneModel
from mshoot_core.models.network import (_Incidence, card_network, NetworkError,
                                        NetworkModel, parse_network)
from mshoot_core.models.r1c1 import R1C1Model, R1C1Parameters
from mshoot_core.models.r2c2 import R2C2Model, R2C2Parameters
from mshoot_core.models.registry import build_model
import numpy as np
import pandas as pd
import pytest
import scipy.linalg
import scipy.sparse
import yaml

HOUR = 3600.0


def r1c1_end(t0_k, u, dt_s, p=R1C1Parameters()):
    """End temperature [K] of one interval from the R1C1 equations (closed form)."""
    solrad, tout, occ, dpos, q = u
    cap = p.tmass * 1.2 * 1005.0 * p.Vi
    ua = 3.0 * p.Vi ** (2.0 / 3.0) / p.RExt
    occupants = p.occheff * occ * 84.0 / 32.0
    vent = 1206.0 / 3600.0 * p.maxVent * dpos / 100.0
    g = ua + occupants + vent
    f = (ua * (tout + 273.15) + p.shgc * solrad + occupants * 325.15
         + vent * (max(tout, p.Tve) + 273.15) + q)
    return f / g + (t0_k - f / g) * math.exp(-g * dt_s / cap)


def r2c2_system(u, p=R2C2Parameters()):
    """Return A [1/s] and b [K/s] of the R2C2 equations for one input row."""
    solrad, tout, occ, dpos, q = u
    vent = 1206.0 / 3600.0 * p.maxVent * dpos / 100.0
    a = np.array([[-(1 / p.Raw + 1 / p.Rwin + vent) / p.Cair, 1 / (p.Raw * p.Cair)],
                  [1 / (p.Raw * p.Cwall), -(1 / p.Raw + 1 / p.Rwa) / p.Cwall]])
    b = np.array([((tout + 273.15) / p.Rwin + (1 - p.fsun) * p.shgc * solrad
                   + p.occheff * 84.0 * occ + vent * (max(tout, p.Tve) + 273.15) + q) / p.Cair,
                  ((tout + 273.15) / p.Rwa + p.fsun * p.shgc * solrad) / p.Cwall])
    return a, b


def inputs(rows, seed=0, controls=1):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 800, rows), rng.uniform(-10, 30, rows),
                            rng.integers(0, 30, rows).astype(float), rng.uniform(0, 100, rows)]
                           + [rng.uniform(-2000, 2000, rows) for _ in range(controls)])


def test_r1c1_card_is_the_closed_form_response():
    model = R1C1Model()
    u = inputs(40)
    x0 = np.random.default_rng(1).uniform(285, 300, (40, 1))
    x_end, y_end = model.simulate_intervals(x0, u, HOUR)
    expected = [r1c1_end(x0[b, 0], u[b], HOUR) for b in range(40)]
    np.testing.assert_allclose(x_end[:, 0], expected, rtol=1e-14)
    np.testing.assert_allclose(y_end[:, 0], x_end[:, 0] - 273.15, rtol=0, atol=1e-12)
    np.testing.assert_allclose(y_end[:, 1], u[:, 4] * HOUR)  # Qr per interval
    # a run: rows chained, Qr accumulated since the start
    udf = pd.DataFrame(u[:6], index=np.arange(6) * HOUR, columns=list(model.input_names))
    ydf, xdf = model.simulate(udf, [293.0])
    t = 293.0
    for k in range(5):
        t = r1c1_end(t, u[k], HOUR)
        assert xdf['T'].iloc[k + 1] == pytest.approx(t, rel=1e-14)
    assert ydf['Qr'].iloc[0] == 0.0
    np.testing.assert_allclose(ydf['Qr'].to_numpy()[1:], np.cumsum(u[:5, 4] * HOUR))


def test_r2c2_card_is_the_matrix_exponential():
    model = R2C2Model(R2C2Parameters(Tve=19.0))
    u = inputs(20, seed=2)
    x0 = np.random.default_rng(3).uniform(285, 300, (20, 2))
    x_end, _ = model.simulate_intervals(x0, u, 900.0)
    for b in range(20):
        a, f = r2c2_system(u[b], R2C2Parameters(Tve=19.0))
        m = np.zeros((3, 3))
        m[:2, :2], m[:2, 2] = a * 900.0, f * 900.0
        expected = scipy.linalg.expm(m) @ np.append(x0[b], 1.0)
        np.testing.assert_allclose(x_end[b], expected[:2], rtol=1e-13)


@pytest.mark.parametrize('build', [R1C1Model, lambda: R2C2Model(R2C2Parameters(Tve=15.0)),
                                   lambda: MultiZoneModel(3)])
def test_interval_jacobians_are_central_differences(build):
    """Every input: heat rates (b only), the damper (A), Tout (through max(Tout, Tve))."""
    model = build()
    nu, nx = len(model.input_names), len(model.state_names)
    u = inputs(12, seed=4, controls=nu - 4)
    x0 = np.random.default_rng(5).uniform(285, 300, (12, nx))
    wrt = list(range(nu))
    jac = model.interval_jacobians(x0, u, HOUR, wrt)
    for j in wrt:
        h = 1e-4 * max(1.0, np.abs(u[:, j]).max())
        up, down = u.copy(), u.copy()
        up[:, j] += h
        down[:, j] -= h
        (xu, yu), (xd, yd) = (model.simulate_intervals(x0, v, HOUR) for v in (up, down))
        np.testing.assert_allclose(jac.dx_du[:, :, j], (xu - xd) / (2 * h), rtol=1e-6,
                                   atol=1e-9 * np.abs(jac.dx_du).max())
        np.testing.assert_allclose(jac.dy_du[:, :, j], (yu - yd) / (2 * h), rtol=1e-6,
                                   atol=1e-9 * np.abs(jac.dy_du).max())
    for i in range(nx):
        h = 1e-3
        up, down = x0.copy(), x0.copy()
        up[:, i] += h
        down[:, i] -= h
        (xu, _), (xd, _) = (model.simulate_intervals(x, u, HOUR) for x in (up, down))
        np.testing.assert_allclose(jac.dx_dx0[:, :, i], (xu - xd) / (2 * h), rtol=1e-7,
                                   atol=1e-12)


THREE_NODES = """
inputs: {Tout: degC, sun: W/m2, d: '1', m: '1'}
parameters:
  Cz: {value: 5.0e+6, min: 1.0e+5, max: 1.0e+8, free: true}
  Cf: 3.0e+7
  Ce: 5.0e+7
  Rzf: 0.002
  Rze: 0.005
  Reo: 0.01
  ua: {value: 60.0, min: 0, max: 500, free: true}
  qa: 8000.0
  qb: {value: 250.0, min: 0, max: 1000, free: true}
  g: 4.0
  k: 20.0
nodes:
  Tz: {capacity: Cz}
  Tf: {capacity: Cf, measured: false}
  Te: {capacity: Ce, measured: false}
boundaries:
  outdoor: Tout + 273.15
conductances:
  - {between: [Tz, Tf], value: 1 / Rzf}
  - {between: [Tz, Te], value: 1 / Rze}
  - {between: [Te, outdoor], value: 1 / Reo}
  - {between: [Tz, outdoor], value: ua}
  - {between: [Tz, outdoor], value: k, times: m}     # a window opening m in [0, 1]
gains:
  - {node: Tf, value: qa, times: d}
  - {node: Tf, value: qb, times: [d, Tout]}          # heat pump: linear in duty and Tout
  - {node: Te, value: g, times: sun}
outputs:
  T: {terms: [{state: Tz}], offset: -273.15}
  mean: {terms: [{state: Tz, value: 0.5}, {state: Te, value: 0.5}]}
  Q: {terms: [{value: qa, times: d}, {value: qb, times: [d, Tout]}]}
  E: {integral: true, terms: [{value: qa, times: d}, {value: qb, times: [d, Tout]}]}
"""


def three_nodes(**values):
    return NetworkModel(yaml.safe_load(THREE_NODES), values=values, control_names=('d',))


def test_a_coupled_network_with_products_has_exact_derivatives():
    """Three coupled nodes, a modulated conductance, a gain of a product of two inputs."""
    model = three_nodes()
    rng = np.random.default_rng(6)
    u = np.column_stack([rng.uniform(-10, 15, 8), rng.uniform(0, 600, 8),
                         rng.uniform(0, 1, 8), rng.uniform(0, 1, 8)])
    x0 = rng.uniform(285, 300, (8, 3))
    jac = model.interval_jacobians(x0, u, HOUR, [0, 1, 2, 3])
    for j in range(4):
        h = 1e-5 * max(1.0, np.abs(u[:, j]).max())
        up, down = u.copy(), u.copy()
        up[:, j] += h
        down[:, j] -= h
        (xu, yu), (xd, yd) = (model.simulate_intervals(x0, v, HOUR) for v in (up, down))
        # (the differences' round-off: 1e-16 of 300 K over 2 h)
        np.testing.assert_allclose(jac.dx_du[:, :, j], (xu - xd) / (2 * h), rtol=1e-6,
                                   atol=1e-6 * np.abs(jac.dx_du[:, :, j]).max())
        np.testing.assert_allclose(jac.dy_du[:, :, j], (yu - yd) / (2 * h), rtol=1e-6,
                                   atol=1e-6 * np.abs(jac.dy_du[:, :2, j]).max())
    # the heat pump's outputs: Q = d (qa + qb Tout), E = Q dt per interval, since the start
    np.testing.assert_allclose(jac.y_end[:, 2], u[:, 2] * (8000.0 + 250.0 * u[:, 0]))
    np.testing.assert_allclose(jac.y_end[:, 3], jac.y_end[:, 2] * HOUR)
    udf = pd.DataFrame(u, index=np.arange(8) * HOUR, columns=list(model.input_names))
    ydf, xdf = model.simulate(udf, x0[0])
    np.testing.assert_allclose(ydf['E'].to_numpy()[1:], np.cumsum(jac.y_end[:-1, 2] * HOUR))
    np.testing.assert_allclose(ydf['mean'], 0.5 * (xdf['Tz'] + xdf['Te']))


@pytest.mark.parametrize('build, names', [
    (three_nodes, ['Cz', 'Cf', 'Rzf', 'Reo', 'ua', 'qb', 'g', 'k']),
    (lambda **v: R1C1Model(R1C1Parameters(**{'Tve': 12.0, **v})),
     ['tmass', 'shgc', 'occheff', 'RExt', 'Tve', 'Vi', 'maxVent'])])
def test_parameter_sensitivities_are_central_differences(build, names):
    model = build()
    rng = np.random.default_rng(7)
    nu = len(model.input_names)
    u = (inputs(13, seed=8) if nu == 5 else np.column_stack([
        rng.uniform(-10, 15, 13), rng.uniform(0, 600, 13), rng.uniform(0, 1, 13),
        rng.uniform(0, 1, 13)]))
    udf = pd.DataFrame(u, index=np.arange(13) * HOUR, columns=list(model.input_names))
    x0 = [293.0] * len(model.state_names)
    ydf, sens = model.parameter_sensitivities(udf, x0, names)
    pd.testing.assert_frame_equal(ydf, model.simulate(udf, x0)[0])
    for j, name in enumerate(names):
        value = model.parameters[name]
        h = 1e-5 * abs(value)
        up = build(**{name: value + h}).simulate(udf, x0)[0].to_numpy()
        down = build(**{name: value - h}).simulate(udf, x0)[0].to_numpy()
        np.testing.assert_allclose(sens[:, :, j], (up - down) / (2 * h), rtol=1e-5,
                                   atol=1e-9 * max(1.0, np.abs(sens[:, :, j]).max()),
                                   err_msg=name)


def test_a_node_without_conductance_integrates_its_heat():
    model = NetworkModel({'inputs': {'q': 'W'}, 'parameters': {'C': 1e6},
                          'nodes': {'T': {'capacity': 'C'}},
                          'gains': [{'node': 'T', 'value': 1, 'times': 'q'}],
                          'outputs': {'T': {'terms': [{'state': 'T'}]}}})
    jac = model.interval_jacobians([[293.0]], [[1000.0]], HOUR, [0])
    assert jac.x_end[0, 0] == pytest.approx(293.0 + 1000.0 * HOUR / 1e6)
    assert jac.dx_du[0, 0, 0] == pytest.approx(HOUR / 1e6)
    assert jac.dx_dx0[0, 0, 0] == 1.0


def test_monotone_inputs_follow_from_the_structure():
    """Metzler A and nonnegative gains of a control alone: monotone; anything else: no claim."""
    assert R1C1Model().monotone_inputs == ('q',)
    assert R2C2Model().monotone_inputs == ('q',)
    assert MultiZoneModel(3).monotone_inputs == ('q_0', 'q_1', 'q_2')
    assert three_nodes().monotone_inputs == ()  # d multiplies Tout: its sign is the weather's
    section = yaml.safe_load(THREE_NODES)
    section['gains'][1] = {'node': 'Tf', 'value': 'qb', 'times': 'd'}
    assert NetworkModel(section, control_names=('d',)).monotone_inputs == ('d',)
    assert NetworkModel(section, control_names=('d', 'm')).monotone_inputs == ('d',)  # A
    section['conductances'][0]['times'] = 'm'  # a modulated node-node conductance
    assert NetworkModel(section, control_names=('d',)).monotone_inputs == ()
    # the claim holds: every end state nondecreasing in the start states and in q
    model = R2C2Model()
    u = inputs(30, seed=9)
    jac = model.interval_jacobians(np.full((30, 2), 293.0), u, HOUR, [4])
    assert np.all(jac.dx_dx0 >= 0) and np.all(jac.dx_du >= 0)


def test_a_bad_network_reports_every_problem():
    section = yaml.safe_load(THREE_NODES)
    section['nodes']['Tz']['capacity'] = 'Cz * missing'
    section['conductances'][0]['between'] = ['Tz', 'nowhere']
    section['gains'][0]['times'] = 'dd'
    section['boundaries']['outdoor'] = 'Tout + __import__'
    section['outputs']['T']['terms'][0]['state'] = 'Tx'
    section['parameters']['ua']['max'] = 10.0  # value 60 out of its bounds
    section['extra'] = 1
    with pytest.raises(NetworkError) as caught:
        parse_network(section)
    problems = caught.value.problems
    for text in ("network: unknown keys ['extra']", "nodes.Tz.capacity: 'Cz * missing' names "
                 "['missing']", "conductances[0].between: ['Tz', 'nowhere'] must name",
                 "gains[0].times: ['dd'] are not inputs", "boundaries.outdoor: 'Tout + "
                 "__import__' names ['__import__']", "outputs.T.terms[0].state: 'Tx' is not a "
                 'node', 'parameters.ua: value 60.0 must lie within [min 0, max 10.0]'):
        assert sum(text in p for p in problems) == 1, (text, problems)
    with pytest.raises(NetworkError, match="uses 'x.y'"):
        parse_network({**yaml.safe_load(THREE_NODES), 'nodes': {'Tz': {'capacity': 'x.y'}}})
    with pytest.raises(ValueError, match='capacities must be > 0'):
        three_nodes(Cz=-1.0)
    with pytest.raises(ValueError, match=r"\['1 / Rzf'\] are not finite"):
        three_nodes(Rzf=0.0)
    with pytest.raises(ValueError, match=r"unknown network parameters \['nope'\]"):
        three_nodes(nope=1.0)


def test_a_card_with_a_network_is_checked_and_built(tmp_path):
    document = {'description': 'three nodes', 'network': yaml.safe_load(THREE_NODES),
                'parameters': {'qb': 300.0},
                'controls': {'d': {'unit': '1', 'min': 0, 'max': 1}},
                'disturbances': {'Tout': {'unit': 'degC'}, 'sun': {'unit': 'W/m2'},
                                 'm': {'unit': '1'}},
                'states': {'Tz': {'unit': 'K'}, 'Tf': {'unit': 'K', 'measured': False},
                           'Te': {'unit': 'K', 'measured': False}},
                'outputs': {'T': {'unit': 'degC'}, 'Q': {'unit': 'W'}}}
    path = tmp_path / 'house.yaml'
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    card = cards.load_card(path)
    model = cards.build_model(card)
    assert isinstance(model, NetworkModel) and card.source == 'network'
    assert model.parameters['qb'] == 300.0 and model.control_names == ('d',)
    assert model.measured_states == ('Tz',)
    assert [p.name for p in card.network.free_parameters] == ['Cz', 'ua', 'qb']
    document['network']['gains'][0]['node'] = 'Tx'
    document['builtin'] = 'r1c1'
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    with pytest.raises(cards.CardError) as caught:
        cards.load_card(path)
    assert any("one of 'fmu'" in p and 'not several' in p for p in caught.value.problems)
    del document['builtin']
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    with pytest.raises(cards.CardError, match=r"network: gains\[0\].node: 'Tx' is not a node"):
        cards.load_card(path)


def test_builtin_models_are_built_from_their_cards():
    """The registry's python, r2c2 and r1c1x2 are the networks of the built-in cards."""
    for name, card_name in (('python', 'r1c1'), ('r2c2', 'r2c2'), ('r1c1x2', 'r1c1x2')):
        model = build_model(name)
        spec = card_network(cards.builtin_card(card_name))
        assert isinstance(model, NetworkModel) and model.state_names == tuple(spec.nodes)
        assert model.parameters == {k: p.value for k, p in spec.parameters.items()}
    # the two-zone card is the seeded multi-zone network written out, to the last digit
    written = yaml.safe_load(cards.builtin_card('r1c1x2').read_text())['network']
    assert written == multizone_network(2, seed=0)
    u = inputs(5, controls=2)
    x0 = np.full((5, 2), 294.0)
    np.testing.assert_array_equal(build_model('r1c1x2').simulate_intervals(x0, u, HOUR)[0],
                                  MultiZoneModel(2, seed=0).simulate_intervals(x0, u, HOUR)[0])


def test_large_incidences_sum_by_gathers_as_the_sparse_product_does():
    # a large network's sums into nodes: gathers where every node receives few terms, with
    # the sparse product's values to the last bit (the same additions in the same order)
    rng = np.random.default_rng(3)
    terms, size = 700, 200
    bins = rng.permutation(np.concatenate([np.arange(size)] * 3
                                          + [rng.integers(0, size, terms - 3 * size)]))
    weights = rng.uniform(-2.0, 2.0, terms)
    incidence = _Incidence((np.arange(terms), bins), weights, terms, size)
    assert 1 < len(incidence.gathers) <= _Incidence.GATHERS
    values = rng.uniform(-1e3, 1e3, (6, terms))
    product = values @ scipy.sparse.csr_matrix((weights, (np.arange(terms), bins)),
                                               shape=(terms, size))
    np.testing.assert_array_equal(incidence(values), product)
    crowded = _Incidence((np.arange(terms), np.zeros(terms, int)), weights, terms, size)
    assert not crowded.gathers  # one node of 700 terms: the sparse product
    np.testing.assert_allclose(crowded(values)[:, 0], values @ weights, rtol=1e-12)
