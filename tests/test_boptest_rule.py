"""The BOPTEST pre-heating rule: its setpoints from the band, the choice, a short real tuning."""
import math
import pathlib
import types

from mshoot_core.boptest.testcase import TestCase
from mshoot_studies.boptest_rule import (choose, grid_tuning, PreheatRule, rule_axes,
                                         rule_targets, RuleTarget, SupplyReset, tune_rule)
import numpy as np
import pandas as pd
import pytest

HOUR = 3600.0
OFFICE_CARD = (pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'boptest_cards'
               / 'multizone_office_simple_hydronic.yaml')
#: The heat pump house's zone setpoint, zone 1's band, its declared range [K].
TARGETS = {'oveTSet_u': RuleTarget('1', 278.15, 308.15)}


def test_setpoint_is_the_band_ahead(boptest_case: TestCase) -> None:
    _, start, _ = boptest_case.test_period('peak_heat_day')
    # the band's lower bound over that day, on a 60 s grid: 21 degC until 7:15, 15 degC until
    # 20:00, 21 degC after (the occupied evening and night of the house)
    fine = np.arange(start, start + 2 * 24 * HOUR, 60.0)
    lower = boptest_case.lookup('LowerSetp[1]', fine)
    rule = PreheatRule(boptest_case, TARGETS, lead_h=2.0, margin_k=0.5)
    for hour in range(24):
        t = start + hour * HOUR
        window = (fine >= t) & (fine < t + 3 * HOUR)
        assert rule.setpoint(t, '1') == pytest.approx(lower[window].max() + 0.5), hour
    # around the morning drop at 7:15 and the evening rise at 20:00, 2 h ahead
    assert rule(start + 7 * HOUR) == {'oveTSet_u': pytest.approx(294.65)}
    assert rule.setpoint(start + 8 * HOUR, '1') == pytest.approx(288.65)
    assert rule.setpoint(start + 17 * HOUR, '1') == pytest.approx(288.65)
    assert rule.setpoint(start + 18 * HOUR, '1') == pytest.approx(294.65)
    no_lead = PreheatRule(boptest_case, TARGETS)
    assert no_lead.setpoint(start + 19 * HOUR, '1') == pytest.approx(288.15)
    with pytest.raises(ValueError, match='lead_h >= 0'):
        PreheatRule(boptest_case, TARGETS, lead_h=-1.0)
    with pytest.raises(ValueError, match='margin_k'):
        PreheatRule(boptest_case, TARGETS, margin_k=float('nan'))
    with pytest.raises(ValueError, match='unknown zones'):
        PreheatRule(boptest_case, {'oveTSet_u': RuleTarget('nZ')})
    # clipped to the input's range
    assert PreheatRule(boptest_case, TARGETS, margin_k=30.0)(start) == {'oveTSet_u': 308.15}


def test_precool_is_the_mirror_across_the_occupied_hours(office: TestCase) -> None:
    """A cooling setpoint: the lowest upper edge over the step and the lead, minus its margin."""
    _, start, _ = office.test_period('typical_heat_day', 1, 2)
    fine = np.arange(start, start + 2 * 24 * HOUR, 60.0)
    upper, lower = office.lookup('UpperSetp[sZ]', fine), office.lookup('LowerSetp[nZ]', fine)
    targets = {'max_s': RuleTarget('sZ', 288.15, 303.15, 'upper'),
               'min_n': RuleTarget('nZ', 288.15, 303.15)}
    rule = PreheatRule(office, targets, lead_h=2.0, margin_k=0.25, cooling_margin_k=0.5)
    for hour in range(24):
        t = start + hour * HOUR
        window = (fine >= t) & (fine < t + 3 * HOUR)
        assert rule(t) == {'max_s': pytest.approx(upper[window].min() - 0.5),
                           'min_n': pytest.approx(lower[window].max() + 0.25)}, hour
    # the office's band: 25 degC (21) from 7 h to 19 h, 30 degC (16) otherwise; 2 h ahead
    assert rule.setpoint(start + 4 * HOUR, 'sZ', edge='upper') == pytest.approx(302.65)
    assert rule.setpoint(start + 5 * HOUR, 'sZ', edge='upper') == pytest.approx(297.65)
    assert rule.setpoint(start + 18 * HOUR, 'sZ', edge='upper') == pytest.approx(297.65)
    assert rule.setpoint(start + 19 * HOUR, 'sZ', edge='upper') == pytest.approx(302.65)
    # the margins are the rule's own: no cooling margin, the upper edge itself; clipped
    assert PreheatRule(office, targets, margin_k=1.0)(start + 12 * HOUR)['max_s'] == \
        pytest.approx(298.15)
    assert PreheatRule(office, targets, cooling_margin_k=20.0)(start)['max_s'] == 288.15
    with pytest.raises(ValueError, match='cooling_margin_k >= 0'):
        PreheatRule(office, targets, cooling_margin_k=-0.5)
    with pytest.raises(ValueError, match='band edge'):
        RuleTarget('sZ', edge='middle')


#: The BMS heating curve of the office's fan coils: 70 degC at -10 degC, 40 degC at 20 degC [K].
CURVE = SupplyReset('Tout_y', (263.15, 293.15), (343.15, 313.15), floor_k=313.15,
                    lower_k=293.15, upper_k=353.15)


def test_supply_reset_curve_floor_and_range() -> None:
    assert CURVE.value(263.15) == pytest.approx(343.15)
    assert CURVE.value(278.15) == pytest.approx(328.15)  # 5 degC: 55 degC
    assert CURVE.value(253.15) == pytest.approx(343.15)  # constant beyond the points
    assert CURVE.value(303.15) == pytest.approx(313.15)
    assert CURVE.value(278.15, -10.0) == pytest.approx(318.15)  # shifted
    assert CURVE.value(278.15, -20.0) == pytest.approx(313.15)  # 35 degC: the floor
    free = SupplyReset('Tout_y', CURVE.outdoor_k, CURVE.supply_k, lower_k=293.15,
                       upper_k=353.15)
    assert free.value(293.15, -30.0) == pytest.approx(293.15)  # 10 degC: the input's minimum
    assert free.value(263.15, 20.0) == pytest.approx(353.15)  # 90 degC: its maximum
    with pytest.raises(ValueError, match='finite outdoor'):
        CURVE.value(math.nan)
    for outdoor, supply in (((263.15,), (343.15,)), ((293.15, 263.15), (343.15, 313.15)),
                            ((263.15, 293.15), (343.15,))):
        with pytest.raises(ValueError, match='strictly increasing'):
            SupplyReset('Tout_y', outdoor, supply)


def test_rule_sends_the_reset_of_the_measured_outdoor_temperature(office: TestCase) -> None:
    _, start, _ = office.test_period('typical_heat_day', 1, 2)
    rule = PreheatRule(office, {'sup': CURVE, 'min_n': RuleTarget('nZ')}, supply_shift_k=-10.0)
    assert rule(start, {'Tout_y': 273.15}) == {'sup': pytest.approx(333.15 - 10.0),
                                               'min_n': pytest.approx(289.15)}
    with pytest.raises(ValueError, match='outdoor temperature Tout_y'):
        rule(start)
    with pytest.raises(ValueError, match='outdoor temperature Tout_y'):
        rule(start, {'T_y': 293.15})
    with pytest.raises(ValueError, match='supply_shift_k finite'):
        PreheatRule(office, {'sup': CURVE}, supply_shift_k=math.inf)


def _card(boptest: dict) -> types.SimpleNamespace:
    """Return a card as rule_targets reads it: the heat pump's setpoint, supply, outdoor."""
    def variable(name: str, unit: str = 'K', activate: str | None = None) -> types.SimpleNamespace:
        return types.SimpleNamespace(variable=name, unit=unit, activate=activate)
    return types.SimpleNamespace(
        path='card.yaml', boptest=boptest,
        controls={'TSet': variable('oveTSet_u', activate='oveTSet_activate'),
                  'Pump': variable('ovePum_u', '1', 'ovePum_activate'),
                  'Free': variable('oveTSet_u')},
        outputs={'Tout': variable('weaSta_reaWeaTDryBul_y'), 'P': variable('reaPHeaPum_y', 'W')})


def test_card_entries_of_the_rule(boptest_case: TestCase) -> None:
    """The card's cooling zones and supply reset as targets; every bad entry named."""
    reset = {'control': 'TSet', 'outdoor': 'Tout', 'points': [[-10, 30], [15, 20]], 'floor': 21}
    targets = rule_targets(_card({'setpoint_zones': {'TSet': '1'}}), boptest_case)
    assert targets == {'oveTSet_u': RuleTarget('1', 278.15, 308.15)}  # the heat pump's, as was
    assert rule_axes(targets, None, None) == ((0.0,), (0.0,))
    with pytest.raises(ValueError, match='cooling margins .0.5. given, but the rule has no '
                                         'cooling setpoint'):
        rule_axes(targets, [0.5], None)
    with pytest.raises(ValueError, match='supply shifts .-10.0. given, but the rule has no '
                                         'supply reset'):
        rule_axes(targets, None, [-10])
    cooled = rule_targets(_card({'setpoint_zones': {'TSet': '1'}, 'cooling_zones': {}}),
                          boptest_case)
    assert cooled == targets
    with pytest.raises(ValueError, match='supply_reset names a zone setpoint'):
        rule_targets(_card({'setpoint_zones': {'TSet': '1'}, 'supply_reset': reset}),
                     boptest_case)
    good = _card({'setpoint_zones': {}, 'cooling_zones': {'TSet': '1'}})
    with pytest.raises(ValueError, match='needs boptest.setpoint_zones'):
        rule_targets(good, boptest_case)
    bad = [
        ({'cooling_zones': {'TSet': '1'}}, 'in both boptest.setpoint_zones and'),
        ({'cooling_zones': {'Free': '1'}}, "cooling_zones names 'Free': expected a control "
                                           'with an overwrite switch'),
        ({'cooling_zones': ['TSet']}, 'cooling_zones: expected a mapping'),
        ({'supply_reset': {**reset, 'control': 'Nope'}}, "supply_reset names 'Nope'"),
        ({'supply_reset': {**reset, 'control': 'Pump'}}, 'the control must be in K'),
        ({'supply_reset': {**reset, 'outdoor': 'P'}}, 'the outdoor must be in K'),
        ({'supply_reset': {**reset, 'outdoor': 'TDryBul'}}, "outdoor 'TDryBul': expected an "
                                                            'output of the card'),
        ({'supply_reset': {**reset, 'points': [[15, 20], [-10, 30]]}}, 'strictly increasing'),
        ({'supply_reset': {**reset, 'points': [[15, 20, 1]]}}, 'pairs [outdoor, supply]'),
        ({'supply_reset': {**reset, 'slope': 1}}, 'expected a mapping with control'),
        ({'supply_reset': 'TSet'}, 'expected a mapping with control'),
    ]
    for extra, message in bad:
        with pytest.raises(ValueError) as error:
            rule_targets(_card({'setpoint_zones': {'TSet': '1'}, **extra}), boptest_case)
        assert message in str(error.value), (extra, str(error.value))


def test_office_card_names_its_rule(office: TestCase, tmp_path: pathlib.Path) -> None:
    """The office's card: pre-heat and pre-cool of both zones, the boiler's heating curve."""
    from mshoot_core.models.card import load_card
    from mshoot_studies.boptest import prepare_card
    card = load_card(prepare_card(OFFICE_CARD, office.directory, tmp_path))
    targets = rule_targets(card, office)
    edges = {name: (t.zone, t.edge) for name, t in targets.items() if isinstance(t, RuleTarget)}
    assert edges == {'bms_oveTZonSetMinNz_u': ('nZ', 'lower'),
                     'bms_oveTZonSetMinSz_u': ('sZ', 'lower'),
                     'bms_oveTZonSetMaxNz_u': ('nZ', 'upper'),
                     'bms_oveTZonSetMaxSz_u': ('sZ', 'upper')}
    reset = targets['bms_oveTProHea_u']
    assert reset == SupplyReset('weaSta_reaWeaTDryBul_y', (263.15, 293.15), (343.15, 313.15),
                                293.15, 293.15, 353.15)
    assert rule_axes(targets, [0, 0.5], [0, -10]) == ((0.0, 0.5), (0.0, -10.0))


def test_choose_by_score() -> None:
    grid = pd.DataFrame({
        'price': ['constant'] * 3 + ['dynamic'] * 3,
        'lead_h': [0.0, 2.0, 4.0] * 2, 'margin_k': [0.0, 0.5, 0.5] * 2,
        'cost_tot': [0.50, 0.60, 0.70, 0.50, 0.90, 0.70],
        'tdis_tot': [5.0, 1.0, 0.0, 5.0, 1.0, 0.0]})
    # scores with weight 0.1: constant 1.0, 0.7, 0.7 (tie: smaller lead); dynamic 1.0, 1.0, 0.7
    best = choose(grid, weight=0.1)
    assert (best['constant']['lead_h'], best['dynamic']['lead_h']) == (2.0, 4.0)
    assert best['constant']['score'] == pytest.approx(0.7)
    assert choose(grid, weight=0.0)['dynamic']['lead_h'] == 0.0


def test_a_tuning_grid_written_is_chosen_again(tmp_path: pathlib.Path) -> None:
    """
    The rule as a tuning run chose it, from the grid it wrote: the same choice, no run.

    A grid with cooling margins and shifts per price, as ``rule_tuning_<period>.csv``: each
    price's parameters are its smallest score's; a missing grid, price or column is refused.
    """
    grid = pd.DataFrame({
        'lead_h': 0.0, 'margin_k': 0.0, 'price': ['constant'] * 3 + ['highly_dynamic'] * 3,
        'cooling_margin_k': [0.5, 1.0, 2.0] * 2, 'supply_shift_k': [-10.0, -20.0, -30.0] * 2,
        'cost_tot': [0.10, 0.11, 0.15, 0.09, 0.08, 0.14], 'tdis_tot': [0.5, 0.2, 0.1] * 2})
    grid.to_csv(tmp_path / 'rule_tuning_typical_cool_day.csv', index=False)
    # scores with weight 0.1: constant 0.15, 0.13, 0.16; highly_dynamic 0.14, 0.10, 0.15
    tuning = grid_tuning(tmp_path, 'typical_cool_day', ['constant', 'highly_dynamic'])
    assert tuning.parameters('constant') == (0.0, 0.0, 1.0, -20.0)
    assert tuning.parameters('highly_dynamic') == (0.0, 0.0, 1.0, -20.0)
    assert grid_tuning(tmp_path, 'typical_cool_day', ['constant'], weight=1.0).parameters(
        'constant') == (0.0, 0.0, 2.0, -30.0)
    with pytest.raises(ValueError, match=r"no rule tuning grid for 'peak_heat_day': .*"
                                         r'rule_tuning_peak_heat_day.csv is missing'):
        grid_tuning(tmp_path, 'peak_heat_day', ['constant'])
    with pytest.raises(ValueError, match=r"no grid point for the price scenarios \['dynamic'\]"):
        grid_tuning(tmp_path, 'typical_cool_day', ['constant', 'dynamic'])
    grid.drop(columns='tdis_tot').to_csv(tmp_path / 'rule_tuning_mix_day.csv', index=False)
    with pytest.raises(ValueError, match=r"no column \['tdis_tot'\]"):
        grid_tuning(tmp_path, 'mix_day', ['constant'])


def test_short_tuning_on_the_fmu(boptest_case: TestCase) -> None:
    """Pre-heating 3 h ahead with a margin beats no lead on a cold short period, by the KPIs."""
    tuning = tune_rule(boptest_case, TARGETS, 'peak_heat_day', leads_h=(0.0, 3.0),
                       margins_k=(0.5,), warmup_days=1, length_days=2)
    assert len(tuning.grid) == 2 * 3
    by_lead = tuning.grid[tuning.grid['price'] == 'constant'].set_index('lead_h')
    assert by_lead.loc[3.0, 'tdis_tot'] < by_lead.loc[0.0, 'tdis_tot']
    for price in ('constant', 'dynamic', 'highly_dynamic'):
        rows = tuning.grid[tuning.grid['price'] == price]
        scores = rows['cost_tot'] + tuning.weight * rows['tdis_tot']
        assert tuning.best[price]['score'] == pytest.approx(scores.min())
        # the heat pump's rule has no cooling setpoint nor supply reset: their axes are 0
        assert tuning.parameters(price) == (tuning.best[price]['lead_h'], 0.5, 0.0, 0.0)


def test_tuning_on_two_worker_processes_gives_the_same_grid(boptest_case: TestCase) -> None:
    """Grid points on a pool of 2 processes (one FMU each): the same rows in the same order."""
    kwargs = {'leads_h': (0.0, 3.0), 'margins_k': (0.5,), 'warmup_days': 1, 'length_days': 1}
    serial = tune_rule(boptest_case, TARGETS, 'peak_heat_day', workers=1, **kwargs)
    pooled = tune_rule(boptest_case, TARGETS, 'peak_heat_day', workers=2, **kwargs)
    columns = ['lead_h', 'margin_k', 'price', 'tdis_tot', 'ener_tot', 'cost_tot']
    assert serial.grid[columns].equals(pooled.grid[columns])
    assert serial.best['constant']['lead_h'] == pooled.best['constant']['lead_h']
    with pytest.raises(ValueError, match='workers'):
        tune_rule(boptest_case, TARGETS, 'peak_heat_day', workers=0, **kwargs)


def test_office_rule_overwrites_act_on_the_fmu(office: TestCase, tmp_path: pathlib.Path) -> None:
    """
    The card's rule on the office FMU (6 h warm-up, 12 h): every overwrite applied as decided.

    Each step's applied maximum setpoints are the band's upper edge ahead minus the cooling
    margin, and the boiler's applied supply the heating curve at the outdoor temperature
    measured at the step's start, shifted (by -40 K: below the card's 20 degC floor in every
    step of these 12 h), at or above the card's floor.
    """
    from mshoot_core.boptest.plant import run_period
    from mshoot_core.models.card import load_card
    from mshoot_studies.boptest import prepare_card
    card = load_card(prepare_card(OFFICE_CARD, office.directory, tmp_path))
    targets = rule_targets(card, office)
    reset = targets['bms_oveTProHea_u']
    rule = PreheatRule(office, targets, lead_h=1.0, cooling_margin_k=2.0, supply_shift_k=-40.0)
    applied = {'bms_oveTProHea_u': 'bms_oveTProHea_y',
               'bms_oveTZonSetMaxSz_u': 'bms_oveTZonSetMaxSz_y',
               'bms_oveTZonSetMinNz_u': 'bms_oveTZonSetMinNz_y'}
    run = run_period(office, 'typical_heat_day', rule, 0.25, 0.5,
                     record=[reset.outdoor, *applied.values()])
    table = run.records
    times = table['time'].to_numpy()
    supplies = []
    for step in range(12):
        t = run.start_s + step * HOUR
        outdoor = table[reset.outdoor].to_numpy()[np.flatnonzero(times <= t + 1e-6)[-1]]
        decided = rule(t, {reset.outdoor: outdoor})
        inside = (times > t + 1e-6) & (times <= t + HOUR + 1e-6)
        assert inside.sum() == 60  # a record every 60 s
        for name, output in applied.items():
            assert table.loc[inside, output].to_numpy() == pytest.approx(decided[name]), \
                (step, name)
        supplies.append(decided['bms_oveTProHea_u'])
        assert decided['bms_oveTProHea_u'] == pytest.approx(
            max(float(np.interp(outdoor, reset.outdoor_k, reset.supply_k)) - 40.0,
                reset.floor_k))
    # the night at 28 degC (30 - 2), the occupied day from 6 h (an hour's lead) at 23 degC
    maxima = [rule.setpoint(run.start_s + h * HOUR, 'sZ', edge='upper') for h in (0, 6)]
    assert maxima == [pytest.approx(301.15), pytest.approx(296.15)]
    assert supplies == [pytest.approx(293.15)] * len(supplies)  # the floor, 20 degC
