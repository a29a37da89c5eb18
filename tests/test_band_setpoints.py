"""
Band setpoints (settings ``band_setpoints``): plant controls sent every step at a band's edge.

Fast core tests on the two-zone card r1c1x2 with a band per zone (no FMU): the values follow
the forecast's band edge at the step's end, moved inward by the margin (at most to the band's
middle), across an unoccupied -> occupied change, clipped to the plant control's range; they
travel after the controls in what is sent (:meth:`StepOutcome.sent`, the supervised plant's
overwrites) and are released with the overwrites by the last fallback; bad settings, zones and
plant controls are refused with clear errors.
"""
import types

from mshoot_core.boptest.supervision import SupervisedPlant
from mshoot_core.controller import controller_for
from mshoot_core.models.card import build_model, CardVariable, load_card
from mshoot_core.settings import MpcSettings, SettingsError
from mshoot_core.units import KELVIN
import numpy as np
import pytest

NS = 1_000_000_000
STEP_NS = 3600 * NS
HORIZON = 4
#: The bands of the forecasts: unoccupied (16-30 degC) up to 2 h, occupied from there.
UNOCCUPIED, OCCUPIED = (16.0, 30.0), {'0': (21.0, 25.0), '1': (22.0, 26.0)}
BANDS = 'Tmax_0=max:0, Tmin_1=min:1'


def _model(folder):
    """Build the card r1c1x2 with a test case forecast naming a band per zone ('0', '1')."""
    import yaml
    from mshoot_core.models.card import builtin_card
    document = yaml.safe_load(builtin_card('r1c1x2').read_text())
    document['testcase_forecast'] = {
        'series': {'Tout': {'columns': ['TDryBul'], 'offset': -273.15}},
        'bands': {z: {'lower': f'LowerSetp[{z}]', 'upper': f'UpperSetp[{z}]'} for z in '01'}}
    path = folder / 'two_bands.yaml'
    path.write_text(yaml.safe_dump(document))
    return build_model(load_card(path))


def _controller(folder, **settings):
    values = {'horizon_steps': HORIZON, 'cost': 'energy', 'band_setpoints': BANDS,
              'band_setpoint_margin_k': 0.5}
    return controller_for(_model(folder), MpcSettings.from_flat({**values, **settings}),
                          assumed_inputs={'dpos': 0.0})


def _series(first_s):
    """Forecast rows from ``first_s`` [s], hourly: the band occupied from 2 h on."""
    times = first_s + 3600.0 * np.arange(HORIZON + 1)
    occupied = times >= 7200.0
    series = {'solrad': np.zeros(times.size), 'Tout': np.full(times.size, 5.0),
              'occ': np.zeros(times.size)}
    for zone, (low, high) in OCCUPIED.items():
        series[f'comfort_min_{zone}'] = np.where(occupied, low, UNOCCUPIED[0])
        series[f'comfort_max_{zone}'] = np.where(occupied, high, UNOCCUPIED[1])
    return series


def _step(controller, step):
    """Offer the state and the forecast of a step, return its outcome."""
    stamp = step * STEP_NS
    assert controller.offer_named_state(stamp, ['T_0', 'T_1'], [21.5 + KELVIN, 22.5 + KELVIN],
                                        stamp) is None
    assert controller.offer_forecast(stamp, 3600.0, _series(step * 3600.0), stamp) is None
    [outcome] = controller.poll(stamp)
    return outcome


def test_band_setpoints_follow_the_band_edge_and_margin(tmp_path):
    """
    Each step: the band at the step's end, the margin inward; the plan's intervals each theirs.

    Step 0 (0-1 h) ends unoccupied: 30 - 0.5 and 16 + 0.5; step 1 (1-2 h) ends at the occupied
    band (the tightest over the step): 25 - 0.5 and 22 + 0.5. A margin wider than half the band
    stops at its middle; a margin changed on the running controller applies at once.
    """
    controller = _controller(tmp_path)
    assert controller.sent_control_names == ('q_0', 'q_1', 'Tmax_0', 'Tmin_1')
    first = _step(controller, 0)
    assert first.decision.source == 'optimum'
    assert not first.band_released
    m = first.decision.plan_controls.shape[0]
    np.testing.assert_allclose(first.band_values[0], [29.5, 16.5])
    np.testing.assert_allclose(first.band_values, [[29.5, 16.5]] + [[24.5, 22.5]] * (m - 1))
    decision, schedule = first.sent()
    np.testing.assert_allclose(decision.controls,
                               [*first.decision.controls, 29.5, 16.5])
    np.testing.assert_allclose(decision.plan_controls[:, :2], first.decision.plan_controls)
    np.testing.assert_allclose(decision.plan_controls[:, 2:], first.band_values)
    assert decision.released == ()
    np.testing.assert_allclose(schedule.values, [[*first.decision.controls, 29.5, 16.5]])
    second = _step(controller, 1)
    np.testing.assert_allclose(second.band_values[0], [24.5, 22.5])
    controller.update(controller.settings.replace(band_setpoint_margin_k=3.0))
    third = _step(controller, 2)
    np.testing.assert_allclose(third.band_values[0], [23.0, 24.0])  # the bands' middles


def test_applied_band_setpoints_in_a_state_are_left_out(tmp_path):
    """
    A zone state may carry every sent control as applied (the emulator's card has them all).

    The band setpoints are not model inputs: left out; the model's controls among them are
    kept; more applied controls than the controller sends are refused by their length.
    """
    controller = _controller(tmp_path)
    names = list(controller.sent_control_names)
    stamp = 0
    accepted = controller.offer_named_state(
        stamp, ['T_0', 'T_1'], [21.5 + KELVIN, 22.5 + KELVIN], stamp,
        control_names=names, control_values=[0.0, 0.0, 29.5 + KELVIN, 16.5 + KELVIN])
    assert accepted is None
    rejection = controller.offer_named_state(
        stamp, ['T_0', 'T_1'], [21.5 + KELVIN, 22.5 + KELVIN], stamp,
        control_names=[*names, 'q_0'], control_values=[0.0] * 5)
    assert rejection is not None and 'control_names has 5 elements, at most 4' in rejection.reason
    # an applied control neither the model's nor a band setpoint is still refused
    rejection = controller.offer_named_state(
        stamp, ['T_0', 'T_1'], [21.5 + KELVIN, 22.5 + KELVIN], stamp,
        control_names=['q_0', 'nonsense'], control_values=[0.0, 0.0])
    assert rejection is not None and 'nonsense' in rejection.reason


def test_band_setpoints_are_clipped_to_the_plant_controls_range(tmp_path):
    controller = _controller(tmp_path)
    with pytest.raises(ValueError, match=r"band setpoint 'Tmin_1' has no range"):
        controller.limit_band_setpoints({'Tmax_0': (15.0, 28.0)})
    with pytest.raises(ValueError, match=r"band setpoint 'Tmax_0': empty range \[28, 15\]"):
        controller.limit_band_setpoints({'Tmax_0': (28.0, 15.0), 'Tmin_1': (None, None)})
    controller.limit_band_setpoints({'Tmax_0': (15.0, 28.0), 'Tmin_1': (17.0, float('nan'))})
    outcome = _step(controller, 0)
    np.testing.assert_allclose(outcome.band_values[0], [28.0, 17.0])
    np.testing.assert_allclose(outcome.band_values[1], [24.5, 22.5])  # within the ranges


def test_band_setpoints_are_released_by_the_last_fallback(tmp_path):
    """
    The last link releases them with the overwrites; without a forecast they are released.

    A step without inputs (no plan yet) falls to the last link, which releases every overwrite
    (``release`` 'release'), the band setpoints' too; with ``release`` 'never' the safe values
    are applied, and the band setpoints are released all the same: no forecast covers the step.
    A step with its forecast on the safe values keeps its band setpoints.
    """
    controller = _controller(tmp_path, release='release')
    [outcome] = controller.poll(0, steady_ns=0) or controller.poll(0, steady_ns=60 * NS)
    assert outcome.decision.source == 'released'
    decision, _ = outcome.sent()
    assert decision.released == (True, True, True, True)
    card = types.SimpleNamespace(controls={
        name: CardVariable(f'{name}_u', unit='degC', canonical_unit='degC', min=10.0,
                           max=35.0, activate=f'{name}_activate')
        for name in controller.sent_control_names})
    plant = SupervisedPlant(controller, card, forecast=lambda t_s: None)
    [(end, overwrites)] = plant.pieces(outcome)
    assert end == 3600.0
    assert overwrites == {'q_0_u': None, 'q_1_u': None, 'Tmax_0_u': None, 'Tmin_1_u': None}
    # handed back with a forecast for the step: released with the others all the same
    assert controller.offer_forecast(STEP_NS, 3600.0, _series(3600.0), STEP_NS) is None
    handed = controller.hand_back(STEP_NS)
    assert handed.decision.source == 'released' and not handed.band_released
    np.testing.assert_allclose(handed.band_values[0], [24.5, 22.5])
    assert handed.sent()[0].released == (True,) * 4

    never = _controller(tmp_path, release='never')
    [outcome] = never.poll(0, steady_ns=0) or never.poll(0, steady_ns=60 * NS)
    assert outcome.decision.source == 'safe' and outcome.band_released
    decision, _ = outcome.sent()
    assert decision.released == (False, False, True, True)
    np.testing.assert_allclose(decision.controls[2:], 21.0)  # (safe_temperature_c, not sent)
    assert never.offer_forecast(STEP_NS, 3600.0, _series(3600.0), STEP_NS) is None
    [outcome] = (never.poll(STEP_NS, steady_ns=120 * NS)
                 or never.poll(STEP_NS, steady_ns=240 * NS))
    assert outcome.decision.source == 'safe' and not outcome.band_released
    decision, _ = outcome.sent()
    assert decision.released == ()
    np.testing.assert_allclose(decision.controls[2:], [24.5, 22.5])
    [(_, overwrites)] = SupervisedPlant(never, card, lambda t_s: None).pieces(outcome)
    assert overwrites['Tmax_0_u'] == pytest.approx(24.5)
    assert overwrites['Tmin_1_u'] == pytest.approx(22.5)


def test_bad_band_setpoints_are_refused(tmp_path):
    """Bad syntax, unknown zones, model controls and plant controls without a switch."""
    for bad in ('Tmax_0=top:0', 'Tmax_0', 'Tmax_0=max:', 'A=max:0, A=min:1', '1x=max:0',
                'Tmax_0=max:0-1'):
        with pytest.raises(SettingsError, match='band_setpoints must be distinct'):
            MpcSettings.from_flat(band_setpoints=bad)
    with pytest.raises(SettingsError, match=r"band_setpoints: \['Y'\] are also sent as model "
                       'controls'):
        MpcSettings.from_flat(plant_controls='q=Y', band_setpoints='Y=max')
    with pytest.raises(ValueError, match=r"names the band of zone '7' \(comfort_min_7, "
                       r"comfort_max_7\), which the controller's forecast does not carry: its "
                       r"bands are those of the zones \['0', '1'\]"):
        _controller(tmp_path, band_setpoints='Tmax_0=max:7')
    with pytest.raises(ValueError, match="zone ''"):
        _controller(tmp_path, band_setpoints='Tmax_0=max')  # (this card: a band per zone)
    with pytest.raises(ValueError, match=r"band_setpoints: 'q_1' is also sent as a model "
                       'control'):
        _controller(tmp_path, band_setpoints='q_1=max:1')
    controller = _controller(tmp_path)
    spec = CardVariable('x_u', unit='degC', canonical_unit='degC', min=10.0, max=35.0,
                        activate='x_activate')
    controls = {'q_0': spec, 'q_1': spec, 'Tmax_0': spec}
    with pytest.raises(ValueError, match=r"band setpoint 'Tmin_1' .*expected a control of the "
                       'card with an overwrite switch'):
        SupervisedPlant(controller, types.SimpleNamespace(controls=controls), lambda t: None)
    controls['Tmin_1'] = CardVariable('y_u', unit='degC', canonical_unit='degC')
    with pytest.raises(ValueError, match=r"band setpoint 'Tmin_1' .*overwrite switch"):
        SupervisedPlant(controller, types.SimpleNamespace(controls=controls), lambda t: None)


def test_the_mpc_nodes_setpoint_carries_the_band_setpoints(tmp_path):
    """
    The MPC node's setpoint message carries them after the controls.

    As ``MpcNode._publish`` builds it: named after the controls, with the plan's intervals and
    the release flags; it passes the node's final check.
    """
    from mshoot_core.safety import check_setpoint
    from mshoot_nodes import conversions as cv
    controller = _controller(tmp_path, release='release')
    outcome = _step(controller, 0)
    names = controller.sent_control_names
    decision, schedule = outcome.sent()
    msg = cv.decision_setpoint_msg(0, decision, 3600.0, controller.interface, 21.0, 'zone',
                                   schedule, names)
    assert list(msg.control_names) == ['q_0', 'q_1', 'Tmax_0', 'Tmin_1']
    np.testing.assert_allclose(msg.control_values[2:], [29.5, 16.5])
    m = outcome.decision.plan_controls.shape[0]
    plan = np.asarray(msg.plan_controls).reshape(len(names), m)  # name-major
    np.testing.assert_allclose(plan[2:].T, outcome.band_values)
    assert list(msg.released) == []
    assert check_setpoint(msg.step_s, msg.control_names, msg.control_values,
                          msg.temperature_names, msg.temperature_setpoints_c, msg.plan_controls,
                          msg.plan_temperatures_c, expected_controls=names) is None
    released, _ = controller.hand_back(STEP_NS).sent()
    msg = cv.decision_setpoint_msg(STEP_NS, released, 3600.0, controller.interface, 21.0,
                                   control_names=names)
    assert list(msg.released) == [True] * 4 and list(msg.plan_controls) == []
