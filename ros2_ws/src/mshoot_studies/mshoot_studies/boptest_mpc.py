"""
The economic MPC on BOPTEST's heat pump house, in core (no ROS): evaluate.

    python -m mshoot_studies.boptest_mpc evaluate [--periods ...] [--prices ...]
        run the MPC (the supervisory Controller of the settings boptest_house on the card
        boptest_modulation: mshoot_core.boptest.supervision; and the baseline and the
        pre-heating rule of mshoot_studies.boptest_rule, tuned on its default grid, for
        comparison) on the test periods and write kpis.json and a markdown table (kpis.md)
        to --out

It prints its progress; bad options exit with code 2 and one line. The control model is
identified by ``mshoot identify --testcase`` (docs/identify.md).
"""
from __future__ import annotations

import argparse
import json
import logging
import pathlib
import re
import sys
import time
from typing import Sequence

logger = logging.getLogger('mshoot_studies.boptest_mpc')

#: The packaged control card of the heat pump house.
CARD = 'boptest_house'

PERIODS = ('peak_heat_day', 'typical_heat_day')
PRICES = ('constant', 'dynamic', 'highly_dynamic')


def _say(text: str) -> None:
    print(text, flush=True)


#: The heat pump's modulation: its off -> on transitions are the runs' starts per day.
STARTS_OUTPUT = 'reaHeaPumY_y'


def install(parameters: dict[str, float], target: pathlib.Path) -> pathlib.Path:
    """
    Write a copy of the packaged card with parameter values in its ``NAME: {value: ...`` lines.

    Returns ``target``, the copy (the packaged card itself is never written).
    """
    from mshoot_core.models.card import builtin_card
    text = builtin_card(CARD).read_text()
    for name, value in parameters.items():
        text, found = re.subn(rf'^(\s+{re.escape(name)}: {{value: )[^,}}]+', rf'\g<1>{value!r}',
                              text, count=1, flags=re.M)
        if not found:
            raise ValueError(f'{target}: no parameter line of {name!r}')
    target.write_text(text)
    return target


def evaluate_command(args: argparse.Namespace) -> int:
    import numpy as np
    from mshoot_core.boptest.kpi_calculator import compute_kpis, kpi_records
    from mshoot_core.boptest.plant import BoptestPlant, run_period
    from mshoot_core.boptest.supervision import supervised_plant
    from mshoot_core.boptest.testcase import TestCase
    from mshoot_core.models.card import builtin_card
    from mshoot_core.settings import MpcSettings
    from mshoot_studies.boptest_report import count_starts
    case = TestCase.load(args.case)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []

    def keep(records: list[dict], wall_s: float) -> None:
        for r in records:
            r['wall_s'] = wall_s
            r.setdefault('starts_per_day', float('nan'))
            rows.append(r)
            _say(f'  {r["controller"]:>22} {r["period"]:>16} {r["price"]:>14}: tdis '
                 f'{r["tdis_tot"]:7.3f} K h, cost {r["cost_tot"]:.4f} EUR/m2, ener '
                 f'{r["ener_tot"]:.3f} kWh/m2, starts/day {r["starts_per_day"]:.1f}')
        (out / 'kpis.json').write_text(json.dumps(rows, indent=1))

    for period in args.periods:
        if args.baseline:
            began = time.perf_counter()
            warmup_start, start, end = case.test_period(period, args.warmup_days, args.days)
            with BoptestPlant(case) as plant:
                plant.start(warmup_start)
                plant.advance(end)
                table = plant.records(start, end)
            starts = count_starts(table, STARTS_OUTPUT, start, end)[1]
            keep([dict(r, starts_per_day=starts)
                  for r in kpi_records(table, case, start, end, args.prices,
                                       controller='baseline', period=period)],
                 time.perf_counter() - began)
        if args.rule:  # the pre-heating rule of mshoot_studies.boptest_rule, tuned per price
            from mshoot_studies.boptest_rule import LEADS_H, MARGINS_K, setpoint_targets, \
                tune_rule
            targets = setpoint_targets(case, {'oveTSet_u': case.zones[0]})
            tuning = tune_rule(case, targets, period, LEADS_H, MARGINS_K, prices=args.prices,
                               warmup_days=args.warmup_days, length_days=args.days,
                               progress=_say if args.verbose else None, workers=args.workers)
            for price in args.prices:
                row = dict(tuning.best[price])
                row['period'] = period
                row['controller'] = (f'rule (lead {row["lead_h"]:g} h, '
                                     f'+{row["margin_k"]:g} K)')
                keep([row], float(row['wall_s']))
        for price in args.prices:
            card = builtin_card(CARD)
            if args.parameters:
                values = json.loads(pathlib.Path(args.parameters).read_text())
                card = install(values.get('parameters', values), out / 'boptest_house.yaml')
            settings = MpcSettings.from_file(CARD, band_margin_k=args.margin,
                                             min_run_s=args.min_run_h * 3600.0,
                                             horizon_steps=args.horizon)
            policy = supervised_plant(case, builtin_card('boptest_modulation'), card, settings,
                                      price)
            began = time.perf_counter()
            run = run_period(case, period, policy, args.warmup_days, args.days,
                             record=[*policy.recorded(case), STARTS_OUTPUT])
            wall = time.perf_counter() - began
            kpis = compute_kpis(run.records, case, run.start_s, run.end_s, price,
                                step_wall_s=np.asarray(run.step_wall_s),
                                control_step_s=settings.problem.step_s)
            name = 'mshoot' + (f' (min run {args.min_run_h:g} h)' if args.min_run_h else '')
            kpis['starts_per_day'] = count_starts(run.records, STARTS_OUTPUT, run.start_s,
                                                  run.end_s)[1]
            solves = [o.result for o in policy.outcomes if o.result is not None]
            keep([{'controller': name, 'period': period, 'price': price, **kpis,
                   'mean_solve_s': float(np.mean([r.solve_time_s for r in solves])),
                   'max_solve_s': float(np.max([r.solve_time_s for r in solves])),
                   'solver_success': float(np.mean([r.success for r in solves]))}], wall)
    (out / 'kpis.md').write_text(markdown_table(rows))
    _say(f'wrote {out / "kpis.json"} and {out / "kpis.md"}')
    return 0


def markdown_table(rows: Sequence[dict]) -> str:
    """Return the KPI records as a markdown table."""
    lines = ['| controller | period | price | tdis_tot [K h] | cost_tot [EUR/m2] | '
             'ener_tot [kWh/m2] | starts/day | time_rat | wall [s] |',
             '|---|---|---|---:|---:|---:|---:|---:|---:|']
    for r in rows:
        ratio = '' if r.get('time_rat') is None else f'{r["time_rat"]:.2e}'
        lines.append(f'| {r["controller"]} | {r["period"]} | {r["price"]} | '
                     f'{r["tdis_tot"]:.3f} | {r["cost_tot"]:.4f} | {r["ener_tot"]:.3f} | '
                     f'{r["starts_per_day"]:.1f} | {ratio} | {r["wall_s"]:.0f} |')
    return '\n'.join(lines) + '\n'


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='python -m mshoot_studies.boptest_mpc',
                                description=__doc__.split('\n')[1])
    p.add_argument('--case', default=None, help='test case folder (default: the shared one)')
    p.add_argument('--out', default='out/boptest/mpc', help='output folder')
    sub = p.add_subparsers(dest='command', required=True)
    e = sub.add_parser('evaluate', help='closed-loop KPIs on the test periods')
    e.add_argument('--periods', nargs='+', default=list(PERIODS), choices=PERIODS)
    e.add_argument('--prices', nargs='+', default=list(PRICES), choices=PRICES)
    e.add_argument('--no-baseline', dest='baseline', action='store_false')
    e.add_argument('--no-rule', dest='rule', action='store_false')
    e.add_argument('--parameters', default=None, help='JSON of parameters over the card '
                   'boptest_house (default: its values)')
    e.add_argument('--margin', type=float, default=0.5,
                   help='raise of the lower edge of the band in the plan [K]')
    e.add_argument('--min-run-h', type=float, default=0.0, help='minimum run time [h]')
    e.add_argument('--horizon', type=int, default=36, help='horizon [h]')
    e.add_argument('--days', type=float, default=14.0, help='test period length [days]')
    e.add_argument('--warmup-days', type=float, default=7.0, help='warm-up [days]')
    e.add_argument('--verbose', action='store_true', help='progress every simulated day')
    e.add_argument('--workers', type=int, default=1, choices=range(1, 9), metavar='N',
                   help="the rule's tuning: grid points run at once, one process each")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    try:
        if args.days <= 0 or args.warmup_days < 0 or args.horizon < 1:
            raise ValueError('--days must be > 0, --warmup-days >= 0 and --horizon >= 1')
        return evaluate_command(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f'boptest_mpc: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
