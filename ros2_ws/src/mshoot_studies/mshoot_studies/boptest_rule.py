"""
The tuning of the pre-heating rule for BOPTEST test cases: a grid of leads and margins.

The rule itself (:class:`~mshoot_core.boptest.rule.PreheatRule`, its targets) is a decision in
core; this module tunes it. :func:`tune_rule` runs a grid of leads, margins and, for a rule
with cooling setpoints and a supply reset, cooling margins and supply shifts on a test period
(each a full run of the FMU: :func:`~mshoot_core.boptest.plant.run_period`) and picks, for
each price scenario, the point
with the smallest score ``cost_tot + weight * tdis_tot`` [EUR/m2], with ``weight`` the price
given to one Kelvin-hour of discomfort [EUR/m2 per K h] (default :data:`DISCOMFORT_WEIGHT`
= 0.1). Only the cost depends on the price scenario, so one run per grid point serves every
scenario.
"""
from __future__ import annotations

import dataclasses
import logging
import pathlib
from typing import Callable, Mapping, Sequence

from mshoot_core.boptest.kpi_calculator import kpi_records
from mshoot_core.boptest.plant import run_period
from mshoot_core.boptest.rule import (  # noqa: F401 (the rule, a decision in core)
    PreheatRule, rule_targets, RuleTarget, setpoint_targets, SupplyReset)
from mshoot_core.boptest.testcase import PRICE_SCENARIOS, TestCase
import pandas as pd

logger = logging.getLogger(__name__)

#: Default grid of :func:`tune_rule`: leads [h] and margins [K].
LEADS_H = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
MARGINS_K = (0.0, 0.25, 0.5, 0.75, 1.0)
#: Default grid axes of a rule with cooling setpoints [K], with a supply reset [K].
COOLING_MARGINS_K = (0.0, 1.0, 2.0)
SUPPLY_SHIFTS_K = (0.0, -10.0, -20.0)
#: The grid's one value of the axes a rule without cooling setpoints (supply reset) has:
#: cooling margins [K] (supply shifts [K]).
NO_AXIS = (0.0,)
#: The tuned parameters, in the order of :meth:`RuleTuning.parameters` and the grid's columns.
PARAMETERS = ('lead_h', 'margin_k', 'cooling_margin_k', 'supply_shift_k')
#: Price of one Kelvin-hour of discomfort in the tuning score [EUR/m2 per K h].
DISCOMFORT_WEIGHT = 0.1


@dataclasses.dataclass
class RuleTuning:
    """
    The result of :func:`tune_rule` on one period.

    Attributes
    ----------
    period : str
        The test period.
    grid : pd.DataFrame
        One row per grid point and price scenario: ``lead_h``, ``margin_k``,
        ``cooling_margin_k``, ``supply_shift_k``, ``price``, the KPIs
        (:func:`~mshoot_core.boptest.kpi_calculator.compute_kpis`), ``score`` and ``wall_s``.
    best : dict of str to dict
        Price scenario -> the chosen row (as a dict).
    weight : float
        The discomfort weight of the score [EUR/m2 per K h].

    """

    period: str
    grid: pd.DataFrame
    best: dict[str, dict]
    weight: float

    def parameters(self, price: str) -> tuple[float, float, float, float]:
        """Return the tuned ``(lead_h, margin_k, cooling_margin_k, supply_shift_k)`` of a price."""
        if price not in self.best:
            raise ValueError(f'no tuning for the price scenario {price!r}: have '
                             f'{sorted(self.best)}')
        row = self.best[price]
        return tuple(float(row.get(name, 0.0)) for name in PARAMETERS)  # type: ignore


def choose(grid: pd.DataFrame, weight: float = DISCOMFORT_WEIGHT) -> dict[str, dict]:
    """
    Pick the best grid point per price scenario: smallest ``cost_tot + weight * tdis_tot``.

    Ties go to the smaller lead, then the smaller margin, the smaller cooling margin, the
    smaller shift in size.

    Parameters
    ----------
    grid : pd.DataFrame
        Columns ``price``, ``lead_h``, ``margin_k``, ``cost_tot``, ``tdis_tot`` (and
        ``cooling_margin_k``, ``supply_shift_k``: 0 when missing).
    weight : float
        Discomfort weight [EUR/m2 per K h], >= 0.

    Returns
    -------
    dict of str to dict
        Price -> the chosen row (with its ``score``).

    """
    if not weight >= 0:
        raise ValueError(f'expected a weight >= 0, got {weight!r}')
    scored = grid.assign(score=grid['cost_tot'] + weight * grid['tdis_tot'])
    for name in PARAMETERS[2:]:
        if name not in scored:
            scored[name] = 0.0
    scored['_shift_size'] = scored['supply_shift_k'].abs()
    best = {}
    for price, rows in scored.groupby('price', sort=False):
        ordered = rows.sort_values(['score', 'lead_h', 'margin_k', 'cooling_margin_k',
                                    '_shift_size'], kind='stable')
        best[str(price)] = ordered.iloc[0].drop('_shift_size').to_dict()
    return best


def _grid_point(directory: str, targets: dict[str, RuleTarget | SupplyReset], period: str,
                point: tuple[float, float, float, float], prices: Sequence[str],
                warmup_days: float, length_days: float,
                record: Sequence[str] | None,
                power_signs: Mapping[str, float] | None = None) -> tuple[list[dict], float]:
    """Run one grid point (in this process or a worker): its KPI rows and wall time [s]."""
    case = TestCase.load(directory)
    lead, margin, cooling, shift = point
    rule = PreheatRule(case, targets, lead, margin, case.control_step_s, cooling, shift)
    run = run_period(case, period, rule, warmup_days, length_days, record=record)
    rows = [{**record, 'wall_s': run.wall_s}
            for record in kpi_records(run.records, case, run.start_s, run.end_s, prices,
                                      run.step_wall_s, power_signs=power_signs,
                                      **dict(zip(PARAMETERS, point)))]
    return rows, run.wall_s


def rule_kinds(targets: Mapping[str, RuleTarget | SupplyReset]) -> tuple[bool, bool]:
    """Return whether a rule's targets have a cooling setpoint, and a supply reset."""
    return (any(isinstance(t, RuleTarget) and t.edge == 'upper' for t in targets.values()),
            any(isinstance(t, SupplyReset) for t in targets.values()))


def rule_axes(targets: Mapping[str, RuleTarget | SupplyReset],
              cooling_margins_k: Sequence[float] | None,
              supply_shifts_k: Sequence[float] | None
              ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """
    Return the grid's cooling margins and supply shifts for a rule's targets.

    A rule without cooling setpoints (without a supply reset) has the one value
    :data:`NO_AXIS`; with them, the values given (None: :data:`NO_AXIS`).

    Raises
    ------
    ValueError
        For values other than 0 given for targets that have no such setpoint.

    """
    has_cooling, has_reset = rule_kinds(targets)
    axes = []
    for values, present, what in ((cooling_margins_k, has_cooling, 'cooling margins'),
                                  (supply_shifts_k, has_reset, 'supply shifts')):
        chosen = NO_AXIS if values is None else tuple(float(v) for v in values)
        if not chosen:
            raise ValueError(f'the tuning grid needs at least one of its {what}')
        if not present and chosen != NO_AXIS:
            raise ValueError(f'{what} {list(chosen)} given, but the rule has no '
                             f'{"cooling setpoint" if what[0] == "c" else "supply reset"} '
                             '(the card names none)')
        axes.append(chosen)
    return axes[0], axes[1]


def grid_path(folder: pathlib.Path, period: str) -> pathlib.Path:
    """Return where a tuning writes, and reads, a period's grid: ``rule_tuning_<period>.csv``."""
    return pathlib.Path(folder) / f'rule_tuning_{period}.csv'


def grid_tuning(folder: pathlib.Path, period: str, prices: Sequence[str],
                weight: float = DISCOMFORT_WEIGHT) -> RuleTuning:
    """
    Return the rule as an earlier tuning chose it: its grid ``rule_tuning_<period>.csv``.

    The grid a tuning run wrote (``mshoot boptest`` without fixed rule parameters:
    ``OUT/rule_tuning_<period>.csv``), chosen again by :func:`choose`: no run of the grid.

    Parameters
    ----------
    folder : pathlib.Path
        The folder of the grids.
    period : str
        The test period.
    prices : sequence of str
        The price scenarios the grid must have.
    weight : float
        The discomfort weight of the score [EUR/m2 per K h].

    Raises
    ------
    ValueError
        When the grid is missing, lacks a column :func:`choose` reads or a price scenario.

    """
    path = grid_path(folder, period)
    if not path.is_file():
        raise ValueError(f'no rule tuning grid for {period!r}: {path} is missing (a tuning run '
                         'writes it: mshoot boptest --controllers rule without --lead, --margin)')
    grid = pd.read_csv(path)
    missing = sorted({'price', 'lead_h', 'margin_k', 'cost_tot', 'tdis_tot'} - set(grid))
    if missing:
        raise ValueError(f'{path}: no column {missing}')
    absent = sorted(set(prices) - set(grid['price']))
    if absent:
        raise ValueError(f'{path}: no grid point for the price scenarios {absent}')
    return RuleTuning(period, grid, choose(grid, weight), weight)


def tune_rule(case: TestCase, targets: Mapping[str, RuleTarget | SupplyReset], period: str,
              leads_h: Sequence[float] = LEADS_H,
              margins_k: Sequence[float] = MARGINS_K, weight: float = DISCOMFORT_WEIGHT,
              prices: Sequence[str] = tuple(PRICE_SCENARIOS), warmup_days: float = 7.0,
              length_days: float = 14.0, progress: Callable[[str], None] | None = None,
              workers: int = 1, record: Sequence[str] | None = None,
              cooling_margins_k: Sequence[float] | None = None,
              supply_shifts_k: Sequence[float] | None = None,
              power_signs: Mapping[str, float] | None = None) -> RuleTuning:
    """
    Tune the rule's parameters on a test period by a grid of full runs (module docstring).

    Parameters
    ----------
    case : TestCase
        The test case.
    targets : dict of str to RuleTarget
        The setpoints the rule writes (:func:`rule_targets`).
    period : str
        The test period.
    leads_h, margins_k : sequence of float
        The grid [h], [K].
    weight : float
        Discomfort weight of the score [EUR/m2 per K h].
    prices : sequence of str
        Price scenarios to choose for.
    warmup_days, length_days : float
        Run lengths [days] (BOPTEST: 7 and 14).
    progress : callable, optional
        Called with one line per run done.
    workers : int
        Grid points run at once, each in its own process (one FMU instance per process;
        ``spawn`` start): the grid and the choice do not depend on it.
    record : sequence of str, optional
        The outputs the runs record (default every output of the FMU; a supply reset's
        outdoor temperature among them).
    cooling_margins_k, supply_shifts_k : sequence of float, optional
        The grid's cooling margins [K] and supply shifts [K] (:func:`rule_axes`; None: 0 only).
    power_signs : dict of str to float, optional
        Power outputs the FMU writes with the wrong sign (the card's ``boptest.power_signs``:
        :func:`~mshoot_core.boptest.kpi_calculator.compute_kpis`), corrected in the score.

    Returns
    -------
    RuleTuning

    """
    if not leads_h or not margins_k:
        raise ValueError('the tuning grid needs at least one lead and one margin')
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f'workers must be an integer >= 1, got {workers!r}')
    coolings, shifts = rule_axes(targets, cooling_margins_k, supply_shifts_k)
    points = [(float(lead), float(margin), cooling, shift) for lead in leads_h
              for margin in margins_k for cooling in coolings for shift in shifts]
    args = [(str(case.directory), dict(targets), period, point, tuple(prices),
             warmup_days, length_days, None if record is None else list(record),
             dict(power_signs or {}))
            for point in points]
    results: list[tuple[list[dict], float] | None] = [None] * len(points)

    def report(n: int, k: int) -> None:
        rows_k, wall = results[k]
        lead, margin, cooling, shift = points[k]
        extra = (f', cooling margin {cooling:g} K' if coolings != NO_AXIS else '') + \
            (f', supply shift {shift:g} K' if shifts != NO_AXIS else '')
        message = (f'rule tuning {period} {n}/{len(points)}: lead {lead:g} h, margin '
                   f'{margin:g} K{extra}: tdis {rows_k[-1]["tdis_tot"]:.3f} K h, ener '
                   f'{rows_k[-1]["ener_tot"]:.3f} kWh/m2 ({wall:.1f} s)')
        logger.info(message)
        if progress is not None:
            progress(message)

    if workers == 1 or len(points) == 1:
        for k, point_args in enumerate(args):
            results[k] = _grid_point(*point_args)
            report(k + 1, k)
    else:
        import concurrent.futures
        from mshoot_studies.worker_pool import process_pool
        with process_pool(min(workers, len(points))) as pool:
            futures = {pool.submit(_grid_point, *point_args): k
                       for k, point_args in enumerate(args)}
            for n, future in enumerate(concurrent.futures.as_completed(futures), 1):
                results[futures[future]] = future.result()
                report(n, futures[future])
    rows = [row for result in results for row in result[0]]
    grid = pd.DataFrame(rows)
    return RuleTuning(period, grid, choose(grid, weight), weight)
