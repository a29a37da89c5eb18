"""
Capped setpoints (settings ``setpoint_caps``): a zone's heating setpoint between band and plan.

A capped setpoint is sent no higher than the plan's temperature of its zone.

Fast core tests on the built-in setpoint zone (``setpoint_zone_identified``: the zone's own loop
modelled as a gain to its setpoint, no FMU). A zone at 18 degC an hour before a 21 degC band
makes the plan ask for its highest setpoint over the first hour; what is sent is the plan's
temperature at the hour's end (or the band's lower edge there, raised by band_margin_k, where
the plan falls short of it), and never below the raised lower edge of the band the step starts
in; every planned interval likewise; a safe step is not capped; bad settings are refused with clear
errors.

Supply floors (settings ``supply_floors``): the same zone with a supply temperature ``TSup``
added as a control the plan prices and that does nothing else: the plan holds it at its lower
limit; it is sent at its floor where the capped setpoint heats, and as planned where the zone
floats above it. Cooling mode (settings ``cooling_mode_margin_k``): the band setpoints moved
inward by that margin where the plan heats nowhere.
"""
import dataclasses
import pathlib

from mshoot_core.controller import controller_for
from mshoot_core.models.card import build_model, builtin_card, load_card
from mshoot_core.settings import MpcSettings, SettingsError
from mshoot_core.units import KELVIN
import numpy as np
import pytest
import yaml


NS = 1_000_000_000
STEP_NS = 3600 * NS
HORIZON = 4
CAPS = 'TSet=T'


def _controller(card=None, **settings):
    values = {'horizon_steps': HORIZON, 'cost': 'output', 'cost_output': 'Qh',
              'estimation': 'off', 'measured_states': 'T, Tw', 'setpoint_caps': CAPS}
    model = build_model(load_card(card or builtin_card('setpoint_zone_identified')))
    return controller_for(model, MpcSettings.from_flat({**values, **settings}))


def _supply_card(directory: pathlib.Path) -> pathlib.Path:
    """Write the setpoint zone with a supply temperature TSup [degC, 20-60] it prices alone."""
    card = yaml.safe_load(builtin_card('setpoint_zone_identified').read_text())
    card['network']['inputs']['TSup'] = 'degC'
    card['network']['outputs']['Qh']['terms'].append({'times': 'TSup', 'value': '0.01'})
    card['controls']['TSup'] = {'unit': 'degC', 'min': 20, 'max': 60, 'safe': 40}
    path = directory / 'supply_zone.yaml'
    path.write_text(yaml.safe_dump(card, sort_keys=False))
    return path


def _forecast(first_s, outdoor_c=0.0, occupants=0.0):
    """Hourly rows from ``first_s`` [s]: 0 degC outdoors, nobody in, the band 21-24 from 1 h."""
    times = first_s + 3600.0 * np.arange(HORIZON + 1)
    occupied = times >= 3600.0
    return {'solrad': np.zeros(times.size), 'Tout': np.full(times.size, outdoor_c),
            'occ': np.full(times.size, occupants),
            'comfort_min': np.where(occupied, 21.0, 16.0),
            'comfort_max': np.where(occupied, 24.0, 30.0)}


def _step(controller, zone_c=18.0, wall_c=15.0, outdoor_c=0.0, occupants=0.0):
    stamp = 0
    assert controller.offer_named_state(stamp, ['T', 'Tw'], [zone_c + KELVIN, wall_c + KELVIN],
                                        stamp) is None
    forecast = _forecast(0.0, outdoor_c, occupants)
    assert controller.offer_forecast(stamp, 3600.0, forecast, stamp) is None
    [outcome] = controller.poll(stamp)
    return outcome


def test_a_capped_setpoint_is_the_plans_zone_temperature():
    """
    Capped, the plan's temperature at the hour's end is sent, not the plan's setpoint.

    Uncapped, the plan's first setpoint is above the temperature it plans for the hour's end
    (the loop's gain makes up the difference); capped, that temperature is sent, and every
    planned interval is at most its own planned temperature. The MPC's result is unchanged.
    """
    free = _step(_controller(setpoint_caps=''))
    assert free.decision.source == 'optimum'
    planned_c = free.decision.predicted_state[0] - KELVIN
    assert free.decision.controls[0] > planned_c + 0.5  # asks for more than it plans to reach
    capped = _step(_controller())
    assert capped.decision.source == 'optimum'
    planned_c = capped.decision.predicted_state[0] - KELVIN
    asked = capped.result.plan['TSet'].to_numpy()
    np.testing.assert_allclose(asked[0], free.decision.controls[0], atol=1e-6)
    np.testing.assert_allclose(capped.decision.controls, [planned_c])
    plan_c = capped.decision.plan_states[:, 0] - KELVIN
    start, end = _lower_edges(plan_c.size)
    np.testing.assert_allclose(capped.decision.plan_controls[:, 0], np.maximum(
        start, np.minimum(asked[:plan_c.size], np.maximum(plan_c, end))))
    decision, schedule = capped.sent()
    np.testing.assert_allclose(schedule.values, [[planned_c]])
    np.testing.assert_allclose(decision.controls, [planned_c])


def test_a_safe_step_is_not_capped():
    controller = _controller()
    decision = controller.supervisor.fallback(0.0, 'solve_failed', 'test')
    assert decision.source == 'safe'
    assert controller.capped(decision, 0) is decision


def _lower_edges(rows, margin_k=0.0):
    """Return the band's lower edge (+ margin) at each interval's start and end (16, 21 degC)."""
    edges = np.where(np.arange(rows + 1) >= 1, 21.0, 16.0) + margin_k
    return edges[:-1], edges[1:]


def test_a_capped_setpoint_keeps_the_band():
    """
    A capped setpoint goes for the band, and holds it.

    Where the plan expects to fall short of the band (here its predicted temperatures moved
    2 K down), the cap is the band's lower edge at the step's end raised by band_margin_k: the
    loop still goes for the band its capacity may reach. A setpoint the plan puts below the band
    the step starts in (here the plan's setpoints moved 5 K down) is sent at the band's lower
    edge, raised: the zone is held there as the building's own loop would.
    """
    controller = _controller(band_margin_k=0.3)
    outcome = _step(controller)
    decision = outcome.decision
    asked = outcome.result.plan['TSet'].to_numpy()[:decision.plan_states.shape[0]]
    start, end = _lower_edges(asked.size, 0.3)
    short = dataclasses.replace(decision, predicted_state=decision.predicted_state - 2.0,
                                plan_states=decision.plan_states - 2.0,
                                controls=asked[:1], plan_controls=asked[:, None])
    capped = controller.capped(short, 0)
    assert capped.controls[0] == pytest.approx(max(16.3, min(asked[0], 21.3)))
    np.testing.assert_allclose(capped.plan_controls[:, 0], np.maximum(start, np.minimum(
        asked, np.maximum(decision.plan_states[:, 0] - 2.0 - KELVIN, end))))
    low = dataclasses.replace(short, controls=asked[:1] - 5.0,
                              plan_controls=asked[:, None] - 5.0)
    capped = controller.capped(low, 0)
    np.testing.assert_allclose(capped.plan_controls[1:, 0], 21.3)  # in the band from 1 h
    assert capped.controls[0] == pytest.approx(max(16.3, asked[0] - 5.0))


@pytest.mark.parametrize('settings, error, match', [
    ({'setpoint_caps': 'TSet=Tw'}, ValueError, r'setpoint_caps: TSet=Tw names no zone '
                                               r"temperature with a comfort band.*\['T'\]"),
    ({'setpoint_caps': 'Tset=T'}, ValueError, r"'Tset' is not a control of the MPC \['TSet'\]"),
    ({'setpoint_caps': 'TSet T'}, SettingsError, r'setpoint_caps must be distinct '
                                                 r"'control=zone_state' items"),
    ({'actuation': 'burst'}, SettingsError, r"setpoint_caps needs actuation 'hold'"),
])
def test_bad_setpoint_caps_are_refused(settings, error, match):
    with pytest.raises(error, match=match):
        _controller(**settings)


def test_a_supply_floor_holds_where_a_capped_setpoint_heats(tmp_path):
    """
    The supply temperature is sent at its floor where the capped setpoint heats.

    A zone at 18 degC an hour before a 21 degC band, 0 degC outdoors: the plan holds TSup at its
    lower limit (it prices TSup and nothing else depends on it) and heats every interval (the
    capped setpoint at the plan's temperature of the zone, or above it); TSup is sent at 50 degC
    this step and in every planned interval. The setpoint is capped as without the floor.
    """
    card = _supply_card(tmp_path)
    plain = _step(_controller(card))
    outcome = _step(_controller(card, supply_floors='TSup=50'))
    assert outcome.decision.source == 'optimum'
    np.testing.assert_allclose(outcome.result.plan['TSup'].to_numpy(), 20.0, atol=1e-3)
    np.testing.assert_allclose(plain.decision.controls[1], 20.0, atol=1e-3)
    zones = outcome.decision.plan_states[:, 0] - KELVIN
    setpoints = outcome.decision.plan_controls[:, 0]
    assert (setpoints >= zones - 0.05).all()  # the loop heats in every interval
    np.testing.assert_allclose(outcome.decision.plan_controls[:, 1], 50.0)
    assert outcome.decision.controls[1] == pytest.approx(50.0)
    np.testing.assert_allclose(outcome.decision.controls[0], plain.decision.controls[0])
    decision, schedule = outcome.sent()
    np.testing.assert_allclose(schedule.values[0], outcome.decision.controls)


def test_a_supply_floor_leaves_a_floating_zone_as_planned(tmp_path):
    """
    Where the zone floats above its capped setpoint, the supply temperature is as planned.

    A zone and its envelope at 23.5 degC, 20 degC outdoors and 300 occupants' gains: the plan
    sets the loop's lowest setpoint and the zone stays above the 21 degC band over the 4 h on
    its gains; every capped setpoint is below the zone (the loop idle) and TSup is sent as
    planned, at its lower limit.
    """
    controller = _controller(_supply_card(tmp_path), supply_floors='TSup=50')
    outcome = _step(controller, zone_c=23.5, wall_c=23.5, outdoor_c=20.0, occupants=300.0)
    assert outcome.decision.source == 'optimum'
    zones = outcome.decision.plan_states[:, 0] - KELVIN
    assert (outcome.decision.plan_controls[:, 0] < zones - 0.05).all()  # the loop idle
    np.testing.assert_allclose(outcome.decision.plan_controls[:, 1], 20.0, atol=1e-3)
    assert outcome.decision.controls[1] == pytest.approx(20.0, abs=1e-3)


@pytest.mark.parametrize('settings, error, match', [
    ({'supply_floors': 'TSup=warm'}, SettingsError, r'supply_floors must be distinct '
                                                    r"'control=floor' items"),
    ({'supply_floors': 'TSup=50', 'setpoint_caps': ''}, SettingsError,
     r'supply_floors needs setpoint_caps'),
    ({'supply_floors': 'TSet=22'}, SettingsError, r"supply_floors: \['TSet'\] are also capped"),
    ({'supply_floors': 'Tsup=50'}, ValueError, r"supply_floors: 'Tsup' is not a control of the "
                                               r"MPC \['TSet', 'TSup'\]"),
    ({'supply_floors': 'TSup=70'}, ValueError, r'supply_floors: TSup=70 is outside the '
                                               r"control's limits \[20, 60\]"),
])
def test_bad_supply_floors_are_refused(tmp_path, settings, error, match):
    with pytest.raises(error, match=match):
        _controller(_supply_card(tmp_path), **settings)


def test_cooling_mode_moves_the_band_setpoints_where_the_plan_heats_nowhere():
    """
    Band setpoints at ``cooling_mode_margin_k`` where the plan heats nowhere, else as before.

    A maximum setpoint at the band's upper edge (24 degC from 1 h) less 0.5 K, 1.5 K in cooling
    mode: the cold zone's plan heats (23.5 degC sent); the warm zone's plan heats in no interval
    (22.5 degC sent, every interval likewise); without the setting, 23.5 degC either way.
    """
    bands = {'band_setpoints': 'TMax=max', 'band_setpoint_margin_k': 0.5}
    warm = {'zone_c': 23.5, 'wall_c': 23.5, 'outdoor_c': 20.0, 'occupants': 300.0}
    controller = _controller(cooling_mode_margin_k=1.5, **bands)
    cold = _step(controller)
    assert controller.heats_ahead(cold.decision) is True
    np.testing.assert_allclose(cold.band_values[0], [23.5])
    controller = _controller(cooling_mode_margin_k=1.5, **bands)
    floating = _step(controller, **warm)
    assert controller.heats_ahead(floating.decision) is False
    np.testing.assert_allclose(floating.band_values, 22.5)
    np.testing.assert_allclose(_step(_controller(**bands), **warm).band_values, 23.5)
    safe = controller.supervisor.fallback(0.0, 'solve_failed', 'test')
    assert controller.heats_ahead(safe) is None  # not known: as heating
    with pytest.raises(SettingsError, match=r'cooling_mode_margin_k must be NaN or within '
                                            r'\[0, 20\] K, got -1'):
        _controller(cooling_mode_margin_k=-1.0, **bands)
