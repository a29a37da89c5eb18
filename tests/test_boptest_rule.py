"""The BOPTEST pre-heating rule: its setpoints from the band, the choice, a short real tuning."""
from mshoot_core.boptest.testcase import TestCase
from mshoot_studies.boptest_rule import choose, PreheatRule, RuleTarget, tune_rule
import numpy as np
import pandas as pd
import pytest

HOUR = 3600.0
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
        assert tuning.parameters(price) == (tuning.best[price]['lead_h'], 0.5)


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
