"""
The economic MPC on BOPTEST's heat pump house, in core (no ROS): identify, then evaluate.

    python -m mshoot_studies.boptest_mpc identify [--cache DIR] [--out out/boptest/mpc]
        excite the emulator outside the test periods (cached), fit the control model, write
        identification.json (parameters, RMSE per period, power model) and, with --install,
        the values into the packaged card mshoot_core/cards/boptest_house.yaml
    python -m mshoot_studies.boptest_mpc evaluate [--periods ...] [--prices ...]
        run the MPC (the supervisory Controller of the settings boptest_house on the card
        boptest_modulation: mshoot_core.boptest.supervision; and the baseline and the
        pre-heating rule of mshoot_studies.boptest_rule, tuned on its default grid, for
        comparison) on the test periods and write kpis.json and a markdown table (kpis.md)
        to --out

Both print their progress; bad options exit with code 2 and one line.
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

PERIODS = ('peak_heat_day', 'typical_heat_day')
PRICES = ('constant', 'dynamic', 'highly_dynamic')


def _say(text: str) -> None:
    print(text, flush=True)


def _cache_default() -> pathlib.Path:
    from mshoot_core.fmu_cache import cache_dir
    return cache_dir().parent / 'boptest'


def identify_command(args: argparse.Namespace) -> int:
    from mshoot_core.boptest import identification as ident
    from mshoot_core.boptest.testcase import TestCase
    case = TestCase.load(args.case)
    started = time.perf_counter()
    records = ident.excitation_records(case, args.cache)
    _say(f'excitation records ready ({time.perf_counter() - started:.1f} s): '
         + ', '.join(f'days {r["time"].iloc[0] / 86400:.0f}-{r["time"].iloc[-1] / 86400:.0f}'
                     for r in records))
    tables = [ident.hourly_table(r, case) for r in records]
    fit = ident.identify(tables, records, starts=args.starts)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {'train_days': ident.TRAIN, 'validation_days': ident.VALIDATION,
               'runs': ident.RUNS, **fit.to_dict()}
    (out / 'identification.json').write_text(json.dumps(summary, indent=1))
    for name, m in fit.result.metrics.items():
        _say(f'{name}: RMSE {m["rmse_k"]:.3f} K, MAE {m["mae_k"]:.3f} K over {m["rows"]} h')
    p = fit.power
    _say(f'power at full load: RMSE {p["power_rmse_w"]:.0f} W of {p["power_mean_w"]:.0f} W '
         f'(mean error {p["power_mean_error_w"]:+.0f} W); COP = {p["cop_a"]:.3f} + '
         f'{p["cop_b"]:.4f} Tout (RMSE {p["cop_rmse"]:.3f})')
    for warning in fit.result.warnings:
        _say(f'warning: {warning}')
    if args.install:
        _say(f'wrote {install(fit.parameters)}')
    _say(f'wrote {out / "identification.json"}')
    return 0


#: The heat pump's modulation: its off -> on transitions are the runs' starts per day.
STARTS_OUTPUT = 'reaHeaPumY_y'


def install(parameters: dict[str, float], target: pathlib.Path | None = None) -> pathlib.Path:
    """
    Write parameter values into the card's ``NAME: {value: ...`` lines; return its path.

    ``target``: a copy of the packaged card ``boptest_house`` written there (default: the
    packaged card itself).
    """
    from mshoot_core.boptest.economic import CARD
    from mshoot_core.models.card import builtin_card
    text = builtin_card(CARD).read_text()
    target = target if target is not None else builtin_card(CARD)
    for name, value in parameters.items():
        text, found = re.subn(rf'^(\s+{re.escape(name)}: {{value: )[^,}}]+', rf'\g<1>{value!r}',
                              text, count=1, flags=re.M)
        if not found:
            raise ValueError(f'{target}: no parameter line of {name!r}')
    target.write_text(text)
    return target


def evaluate_command(args: argparse.Namespace) -> int:
    import numpy as np
    from mshoot_core.boptest.economic import CARD
    from mshoot_core.boptest.kpis import compute_kpis, kpi_records
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
    i = sub.add_parser('identify', help='excite the emulator and fit the control model')
    i.add_argument('--cache', default=None, type=pathlib.Path,
                   help='folder of the cached excitation records (default ~/.cache/mshoot/'
                   'boptest)')
    i.add_argument('--starts', type=int, default=1, help='starts of the fit')
    i.add_argument('--install', action='store_true',
                   help='write the fit into the packaged card mshoot_core/cards/'
                   'boptest_house.yaml')
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
        if args.command == 'identify':
            if args.cache is None:
                args.cache = _cache_default()
            if args.starts < 1:
                raise ValueError(f'--starts must be >= 1, got {args.starts}')
            return identify_command(args)
        if args.days <= 0 or args.warmup_days < 0 or args.horizon < 1:
            raise ValueError('--days must be > 0, --warmup-days >= 0 and --horizon >= 1')
        return evaluate_command(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f'boptest_mpc: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
