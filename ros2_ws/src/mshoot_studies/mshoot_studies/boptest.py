"""
Any BOPTEST test case folder and a card: the baseline and the pre-heating rule, BOPTEST's KPIs.

    mshoot boptest --testcase DIR --card CARD.yaml --out OUT
        [--periods peak_heat_day typical_heat_day] [--prices constant dynamic]
        [--controllers baseline,rule,mshoot] [--warmup-days 7] [--days 14]
        [--lead 4 --margin 0.5 [--cooling-margin 0.5 --supply-shift -10]
         | --leads 0 2 4 --margins 0 0.5 [--cooling-margins 0 0.5 --supply-shifts 0 -10]]
        [--workers 2]
        [--control-card CARD.yaml --mpc-settings SETTINGS.yaml]
        [--uncertainty none high=1,2,3 low medium]

The folder is in BOPTEST's layout (``wrapped.fmu`` or ``models/wrapped.fmu``, Model Exchange or
Co-Simulation; ``config.json``, ``days.json``, ``kpis.json``, ``Resources/*.csv``: see
:mod:`mshoot_core.boptest.testcase` and ``docs/boptest_testcases.md``). The card (a model card of
kind ``boptest``) is data about the building: its controls (overwrite inputs with their
``activate`` switches, units, limits), the states and outputs it maps, ``boptest.warmup_days``,
``tolerance`` (Model Exchange) and, for the rule, ``boptest.setpoint_zones`` (setpoint control
-> zone) and optionally ``boptest.cooling_zones`` and ``boptest.supply_reset``. ``--testcase``
replaces the card's ``boptest.test_case``.

Each run goes through the one period loop in core (:func:`mshoot_core.boptest.plant.run_period`:
one persistent FMU instance, the warm-up under the building's own control, records every 60 s
of ``kpis.json``'s outputs and the card's variables); runs go to worker processes (one FMU
instance per process). Controllers:

- ``baseline``: the building's own control (no overwrite);
- ``rule``: each setpoint of ``boptest.setpoint_zones`` every control step = the highest lower
  bound of its zone's band over the step and the lead after it, plus a margin; each of
  ``boptest.cooling_zones`` the lowest upper bound minus a cooling margin; the supply
  temperature of ``boptest.supply_reset`` its heating curve of the measured outdoor
  temperature, shifted (:mod:`mshoot_core.boptest.rule`); ``--lead``/``--margin``
  (``--cooling-margin``, ``--supply-shift``) fixed, else tuned per period and price on the test
  period itself, on the grid ``--leads`` x ``--margins`` (x ``--cooling-margins`` x
  ``--supply-shifts`` when the card names cooling setpoints, a supply reset) (each a full run;
  :mod:`mshoot_studies.boptest_rule`), or as such a tuning chose it from the grids it wrote
  (``--rule-grids DIR``: ``DIR/rule_tuning_<period>.csv``, no grid run);
- ``mshoot``: the supervisory MPC (:class:`mshoot_core.controller.Controller`, in the loop by
  :func:`mshoot_core.boptest.supervision.supervised_plant`) of a control model card
  (``--control-card``: a file or a built-in card, with its ``testcase_forecast`` section: the
  forecast from the test case's data) and its settings (``--mpc-settings``: a YAML file of flat
  settings, or a packaged one, e.g. ``boptest_house``); without these options, those the card
  names in ``boptest.control`` (``card``, ``settings``: files relative to the card's folder or
  packaged names); the card's controls are the overwrites it sends (settings
  ``plant_controls``). One run per period, price and forecast scenario of ``--uncertainty``
  (``LEVEL`` or ``LEVEL=SEED,...``: BOPTEST's forecast errors on the outdoor temperature and
  the irradiance at that level, :func:`mshoot_core.forecast.uncertainty_runs`; default
  ``none``, perfect forecasts); the settings are told the level
  (:func:`mshoot_core.forecast_margin.allowance`: the plan's forecast margin).

The baseline and the rule never read the price nor a weather forecast: one run serves every
price scenario (only ``cost_tot`` differs); so does ``mshoot`` when its control card's forecast
has no price series (e.g. the two-zone office's, which plans gas at its one price). Writes
``OUT/kpis.json`` (one record per controller, period, price and forecast scenario: BOPTEST's
KPIs with ``tdis_zones``, the run's wall time, ``uncertainty`` and ``seed``: ``none`` and null
for perfect or no forecasts), ``OUT/kpis.md`` (the table, also printed, and with ``--report``
as a Markdown page), ``OUT/runs/<controller>_<period>[...]/records.csv``, the rule's tuning
grids ``OUT/rule_tuning_<period>.csv`` (each point's KPIs per price) and, with
``--figures``, ``OUT/<run>.png``. Bad options or a bad folder or card: one line on stderr, exit 2.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import json
import logging
import pathlib
import sys
import time
from typing import Any, Callable, Mapping, Sequence

from mshoot_core.boptest.testcase import PRICE_SCENARIOS

from mshoot_studies.worker_pool import process_pool

logger = logging.getLogger(__name__)

#: The controllers of ``--controllers``.
CONTROLLERS = ('baseline', 'rule', 'mshoot')


@dataclasses.dataclass(frozen=True)
class RunJob:
    """
    One run of a benchmark: controller, period, the price scenarios it stands for, its inputs.

    Attributes
    ----------
    controller : {'baseline', 'rule', 'mshoot'}
        The controller.
    period : str
        The test period.
    prices : tuple of str
        The price scenarios whose KPIs the run gives (the first is the one it runs with).
    lead_h, margin_k : float
        The rule's lead [h] and margin [K].
    errors : ForecastErrorSettings or None
        The forecast scenario of an mshoot run (None: perfect).
    cooling_margin_k, supply_shift_k : float
        The rule's cooling margin [K] and supply shift [K].

    """

    controller: str
    period: str
    prices: tuple[str, ...]
    lead_h: float = 0.0
    margin_k: float = 0.0
    errors: Any = None
    cooling_margin_k: float = 0.0
    supply_shift_k: float = 0.0

    @property
    def name(self) -> str:
        """
        Return the run's name: ``<controller>_<period>[_<price>[_<level>_s<seed>]]``.

        A rule's: ``rule_<period>_lead<h>_margin<K>[_cool<K>][_shift<K>]`` (the cooling margin
        and the supply shift when not 0).
        """
        from mshoot_core.forecast import scenario_suffix
        rule = (f'_lead{self.lead_h:g}_margin{self.margin_k:g}'
                + (f'_cool{self.cooling_margin_k:g}' if self.cooling_margin_k else '')
                + (f'_shift{self.supply_shift_k:g}' if self.supply_shift_k else ''))
        suffix = {'mshoot': f'_{self.prices[0]}{scenario_suffix(self.errors)}', 'baseline': '',
                  'rule': rule}[self.controller]
        return f'{self.controller}_{self.period}{suffix}'


def plan_runs(periods: Sequence[str], controllers: Sequence[str], prices: Sequence[str],
              scenarios: Sequence[Any],
              rule_parameters: Callable[[str, str], tuple[float, ...]] | None = None,
              mshoot_per_price: bool = True) -> list[RunJob]:
    """
    Return a benchmark's runs (this runner's and the ROS benchmark's, ``make boptest``).

    The baseline and the rule never read the price: one baseline run per period for every
    price scenario, one rule run per distinct parameters of the prices; mshoot one run per
    forecast scenario and price (or for every price at once, ``mshoot_per_price`` false: its
    forecast has no price series).

    Parameters
    ----------
    periods, controllers, prices : sequence of str
        The test periods, the controllers (:data:`CONTROLLERS`) and the price scenarios.
    scenarios : sequence of ForecastErrorSettings or None
        mshoot's forecast scenarios (:func:`mshoot_core.forecast.uncertainty_runs`).
    rule_parameters : callable, optional
        ``rule_parameters(period, price) -> (lead [h], margin [K][, cooling margin [K],
        supply shift [K]])``; needed for the rule.
    mshoot_per_price : bool
        One mshoot run per price scenario.

    Returns
    -------
    list of RunJob
        By period, then controller in the order given.

    """
    jobs: list[RunJob] = []
    for period in periods:
        for controller in controllers:
            if controller == 'baseline':
                jobs.append(RunJob(controller, period, tuple(prices)))
            elif controller == 'mshoot':
                groups = [(price,) for price in prices] if mshoot_per_price else [tuple(prices)]
                jobs += [RunJob(controller, period, group, errors=errors)
                         for errors in scenarios for group in groups]
            elif controller == 'rule':
                if rule_parameters is None:
                    raise ValueError('the rule runs need rule_parameters (lead and margin)')
                by_parameters: dict[tuple[float, ...], list[str]] = {}
                for price in prices:
                    values = tuple(float(v) for v in rule_parameters(period, price))
                    if len(values) not in (2, 4):
                        raise ValueError('rule_parameters must give (lead, margin[, cooling '
                                         f'margin, supply shift]), got {values}')
                    by_parameters.setdefault(values + (0.0, 0.0)[:4 - len(values)],
                                             []).append(price)
                jobs += [RunJob(controller, period, tuple(group), lead, margin,
                                cooling_margin_k=cooling, supply_shift_k=shift)
                         for (lead, margin, cooling, shift), group in by_parameters.items()]
            else:
                raise ValueError(f'unknown controller {controller!r}: expected one of '
                                 f'{list(CONTROLLERS)}')
    return jobs


def add_shared_arguments(parser: argparse.ArgumentParser) -> None:
    """
    Add the options both BOPTEST runners take alike to ``parser``.

    The building's card (``--card``), mshoot's control card and settings (``--control-card``,
    ``--mpc-settings``), the warm-up and test lengths (``--warmup-days``, ``--days``) and the
    rule's fixed lead and margin or tuning grid (``--lead``, ``--margin``, ``--leads``,
    ``--margins``): one description for ``mshoot boptest`` (:func:`build_parser`) and the ROS
    runner (``python -m mshoot_nodes.boptest_run``), whose parsed options
    :func:`mpc_configuration` and :func:`write_tables` read alike.
    """
    from mshoot_studies.boptest_rule import LEADS_H, MARGINS_K
    parser.add_argument('--card', required=True, type=pathlib.Path,
                        help='the model card of the building (kind boptest)')
    parser.add_argument('--control-card', default=None,
                        help='mshoot: the control model card (a file or a built-in card name, '
                             "e.g. boptest_house; default the card's boptest.control.card)")
    parser.add_argument('--mpc-settings', default=None,
                        help='mshoot: the MPC settings (a YAML file of flat settings or a '
                             "packaged name, e.g. boptest_house; default the card's "
                             'boptest.control.settings)')
    parser.add_argument('--warmup-days', type=float, default=None,
                        help="warm-up [days] (default the card's boptest.warmup_days)")
    parser.add_argument('--days', type=float, default=14.0,
                        help='test period length [days] (BOPTEST: 14)')
    parser.add_argument('--lead', type=float, default=None, help='rule: a fixed lead [h]')
    parser.add_argument('--margin', type=float, default=None, help='rule: a fixed margin [K]')
    parser.add_argument('--leads', type=float, nargs='+', default=list(LEADS_H),
                        help='rule tuning grid: leads [h]')
    parser.add_argument('--margins', type=float, nargs='+', default=list(MARGINS_K),
                        help='rule tuning grid: margins [K]')


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """
    Build the command line of ``mshoot boptest``.

    Fills ``parser`` (the ``boptest`` verb of ``mshoot``), or a new parser when None. Its errors
    are one line (``<prog>: error: ...``) and exit 2.
    """
    from mshoot_studies.boptest_rule import COOLING_MARGINS_K, SUPPLY_SHIFTS_K
    from mshoot_studies.cli import verb_parser
    parser = verb_parser(parser, 'mshoot_studies.boptest', __doc__)
    parser.add_argument('--testcase', required=True, type=pathlib.Path,
                        help='the BOPTEST test case folder')
    add_shared_arguments(parser)
    parser.add_argument('--out', required=True, type=pathlib.Path, help='output folder')
    parser.add_argument('--periods', nargs='+', default=None,
                        help='test periods (keys of days.json; default all of them)')
    parser.add_argument('--prices', nargs='+', default=list(PRICE_SCENARIOS),
                        choices=list(PRICE_SCENARIOS), help='price scenarios')
    parser.add_argument('--controllers', nargs='+', default=['baseline', 'rule'],
                        help='baseline, rule, mshoot; separated by spaces or commas')
    parser.add_argument('--uncertainty', nargs='+', default=['none'], metavar='LEVEL[=SEEDS]',
                        help="mshoot: forecast scenarios, e.g. none high=1,2,3 low (BOPTEST's "
                             'forecast errors of the outdoor temperature and the irradiance at '
                             'that level, one run per seed; LEVEL alone: seed 1; default none)')
    parser.add_argument('--cooling-margin', type=float, default=None,
                        help='rule: a fixed cooling margin [K] (a card with cooling_zones)')
    parser.add_argument('--supply-shift', type=float, default=None,
                        help='rule: a fixed supply shift [K] (a card with supply_reset)')
    parser.add_argument('--cooling-margins', type=float, nargs='+', default=None,
                        help='rule tuning grid: cooling margins [K] (a card with cooling_zones; '
                             f'default {" ".join(f"{v:g}" for v in COOLING_MARGINS_K)})')
    parser.add_argument('--supply-shifts', type=float, nargs='+', default=None,
                        help='rule tuning grid: supply shifts [K] (a card with supply_reset; '
                             f'default {" ".join(f"{v:g}" for v in SUPPLY_SHIFTS_K)})')
    parser.add_argument('--rule-grids', type=pathlib.Path, default=None, metavar='DIR',
                        help='rule: as an earlier tuning run chose it per period and price, '
                             'from its grids DIR/rule_tuning_<period>.csv (no grid run; '
                             'not with fixed rule parameters)')
    parser.add_argument('--workers', type=int, default=2, choices=range(1, 9), metavar='N',
                        help='runs at once, one process and FMU instance each (default 2)')
    parser.add_argument('--starts-output', default='',
                        help='an FMU output whose off -> on transitions are counted '
                             '(starts_per_day, e.g. a heat pump modulation)')
    parser.add_argument('--figures', action='store_true', help='draw OUT/<run>.png')
    parser.add_argument('--report', type=pathlib.Path, default=None,
                        help='also write the tables as a Markdown page (e.g. a docs page)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process arguments) and run; the exit code."""
    return run(build_parser().parse_args(argv))


def _controllers(values: Sequence[str]) -> list[str]:
    names = [name for value in values for name in value.split(',') if name]
    unknown = [name for name in names if name not in CONTROLLERS]
    if unknown or not names:
        raise ValueError(f'--controllers: expected some of {list(CONTROLLERS)}, got {values}')
    return list(dict.fromkeys(names))


def control_card_path(value: str) -> pathlib.Path:
    """Return the control card of ``--control-card``: a file, else a built-in card's."""
    from mshoot_core.models.card import builtin_card
    path = pathlib.Path(value)
    return path if path.is_file() else builtin_card(value)


def prepare_card(card_path: pathlib.Path, testcase: pathlib.Path,
                 out: pathlib.Path) -> pathlib.Path:
    """
    Write the card with ``boptest.test_case`` = the test case folder into ``out``; its path.

    Raises
    ------
    ValueError
        For a card that is not YAML, or not a mapping with a ``boptest`` section.
    FileNotFoundError
        For a card that does not exist.

    """
    import yaml
    try:
        document = yaml.safe_load(card_path.read_text())
    except yaml.YAMLError as error:
        raise ValueError(f'{card_path}: not a YAML model card of kind boptest ('
                         f'{str(error).splitlines()[0]})') from error
    if not isinstance(document, dict) or not isinstance(document.get('boptest'), dict):
        raise ValueError(f'{card_path}: expected a model card of kind boptest (a "boptest:" '
                         'section)')
    folder = card_path.resolve().parent
    if isinstance(document.get('preload'), list):  # paths relative to the card's folder
        document['preload'] = [str((folder / e).resolve()) if isinstance(e, str) and '/' in e
                               else e for e in document['preload']]
    control = document['boptest'].get('control')
    if isinstance(control, dict):  # files relative to the card's folder; packaged names stay
        document['boptest'] = {**document['boptest'], 'control': {
            key: str((folder / value).resolve())
            if isinstance(value, str) and value and (folder / value).is_file() else value
            for key, value in control.items()}}
    document['boptest'] = {**document['boptest'], 'test_case': str(testcase.resolve())}
    out.mkdir(parents=True, exist_ok=True)
    path = out / f'card_{card_path.stem}.yaml'
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def _run_one(directory: str, card_path: str, controller: str, period: str, lead: float,
             margin: float, warmup_days: float, length_days: float, prices: list[str],
             record: list[str], records_csv: str, starts_output: str,
             mpc: tuple[str, str] | None = None, errors: Any = None,
             cooling: float = 0.0, shift: float = 0.0) -> list[dict]:
    """
    Run one controller on one period (in a worker): its KPI records, the table written.

    ``mpc`` is (control card, settings) of the controller ``mshoot`` (one price), ``errors``
    its forecast's (:class:`~mshoot_core.settings.ForecastErrorSettings`, None: perfect);
    ``lead`` [h], ``margin`` [K], ``cooling`` [K] and ``shift`` [K] the rule's parameters.
    """
    from mshoot_core.boptest.kpi_calculator import kpi_records
    from mshoot_core.forecast import scenario_fields
    from mshoot_core.boptest.plant import run_period
    from mshoot_core.boptest.testcase import TestCase
    from mshoot_core.models.card import load_card
    from mshoot_studies.boptest_rule import PreheatRule, rule_targets
    from mshoot_studies.boptest_report import count_starts
    case = TestCase.load(directory)
    card = load_card(card_path)
    policy = None
    if controller == 'rule':
        targets = rule_targets(card, case)
        policy = PreheatRule(case, targets, lead, margin, case.control_step_s, cooling, shift)
    elif controller == 'mshoot':
        from mshoot_core.boptest.supervision import supervised_plant
        from mshoot_core.settings import MpcSettings
        from mshoot_core.forecast_margin import allowance
        policy = supervised_plant(case, card_path, mpc[0],
                                  MpcSettings.from_file(mpc[1], **allowance(errors)), prices[0],
                                  errors)
    began = time.perf_counter()
    run = run_period(case, period, policy, warmup_days, length_days, record=record)
    wall = time.perf_counter() - began
    path = pathlib.Path(records_csv)
    path.parent.mkdir(parents=True, exist_ok=True)
    run.records.to_csv(path, index=False)
    walls = run.step_wall_s if controller != 'baseline' else None
    extra = ({'lead_h': lead, 'margin_k': margin, 'cooling_margin_k': cooling,
              'supply_shift_k': shift} if controller == 'rule' else {})
    records = kpi_records(run.records, case, run.start_s, run.end_s, prices, walls,
                          power_signs=card.boptest['power_signs'], controller=controller,
                          period=period)
    for entry in records:
        entry.update(extra, wall_s=wall, start_s=run.start_s, end_s=run.end_s,
                     **scenario_fields(errors))
        if starts_output:
            entry['starts_per_day'] = count_starts(run.records, starts_output, run.start_s,
                                                   run.end_s)[1]
    return records


def runs_window(case: Any, card: Any, args: argparse.Namespace) -> tuple[float, list[str]]:
    """
    Return the runs' warm-up [days] and test periods; check them and the card's KPI signs.

    ``--warmup-days`` (default the card's ``boptest.warmup_days``) and ``--periods`` (default
    every period of the test case), checked with ``--days`` against the test case, and the
    card's ``boptest.power_signs`` against its ``kpis.json``: before any run, for both BOPTEST
    runners.

    Raises
    ------
    ValueError
        For an unknown period, a bad length, or a bad sign correction.

    """
    from mshoot_core.boptest.kpi_calculator import check_power_signs
    warmup = float(card.boptest['warmup_days'] if args.warmup_days is None
                   else args.warmup_days)
    periods = list(case.days) if args.periods is None else list(args.periods)
    for period in periods:
        case.test_period(period, warmup, args.days)  # bad names and lengths fail here
    check_power_signs(case, card.boptest['power_signs'])
    return warmup, periods


def mpc_configuration(args: argparse.Namespace, case: Any, card: Any,
                      card_path: pathlib.Path) -> tuple[str, str]:
    """
    Return (control card, settings) of ``mshoot``, checked before any run.

    Each from its option, else from the card's ``boptest.control`` (``card``, ``settings``).

    Raises
    ------
    ValueError
        When neither names one, for bad settings, or a control card the test case cannot
        forecast or the plant's card cannot actuate.

    """
    from mshoot_core.boptest.supervision import supervised_plant
    from mshoot_core.settings import MpcSettings
    named = card.boptest.get('control') or {}
    chosen = {'card': args.control_card or named.get('card'),
              'settings': args.mpc_settings or named.get('settings')}
    missing = [key for key, value in chosen.items() if value is None]
    if missing:
        raise ValueError(f'--controllers mshoot needs the control model card and its settings: '
                         f'{card.path} names no boptest.control {missing[0]} (or give '
                         f'--{"control-card" if missing[0] == "card" else "mpc-settings"})')
    control = control_card_path(chosen['card'])
    settings = chosen['settings']
    supervised_plant(case, card_path, control, MpcSettings.from_file(settings), args.prices[0])
    return str(control), str(settings)


def report_page(case: Any, args: argparse.Namespace, warmup: float, tables: str,
                writer: str = '`mshoot boptest`', figures: Sequence[str] = ()) -> str:
    """
    Return the Markdown page of ``--report``: what ran, the KPI tables, the zone figures.

    Parameters
    ----------
    case : TestCase
        The test case.
    args : argparse.Namespace
        The command's options.
    warmup : float
        The warm-up [days].
    tables : str
        The KPI tables (``OUT/kpis.md``).
    writer : str
        What ran the runs (Markdown), e.g. this command.
    figures : sequence of str
        The per-period zone figures (:func:`report_figures`), relative to the page.

    """
    cards = [f'`{pathlib.Path(p).name}`' for p in (args.card, args.control_card, args.mpc_settings)
             if p is not None]
    return '\n'.join([
        f'# BOPTEST `{case.name}`: {", ".join(_controllers(args.controllers))}', '',
        f'Written by {writer} with `--report` from the runs in `{args.out}`: the test '
        f'periods {", ".join(f"`{p}`" for p in (args.periods or case.days))} ({args.days:g} '
        f"days each after {warmup:g} days of warm-up under the building's own control), the "
        f'prices {", ".join(f"`{p}`" for p in args.prices)}; cards and settings '
        f'{", ".join(cards)} (`docs/boptest_cards/`). KPIs as BOPTEST defines them '
        '([bringing a BOPTEST test case](boptest_testcases.md)); the second table is each '
        "zone's own discomfort.", '', tables,
        *[line for path in figures
          for line in ('', f'![{pathlib.Path(path).stem}: each zone under every controller]'
                           f'({path})')]])


#: The record table of a run in its folder ``OUT/runs/<name>/``: ``mshoot boptest``'s, the
#: ROS benchmark's (its emulator node's).
RECORD_FILES = ('records.csv', 'boptest_records.csv')


def report_figures(case: Any, names: Sequence[str], results: Sequence[Sequence[dict]],
                   out: pathlib.Path, report: pathlib.Path, warmup: float,
                   days: float) -> list[str]:
    """
    Draw a figure per period beside the report page: each zone under every run of the period.

    One run per controller and period is drawn (the first of its price and forecast
    scenarios: the baseline and the rule serve every price; the figure shows the
    temperatures, not the cost), from the run's records in ``OUT/runs/<name>/``
    (:data:`RECORD_FILES`: this command's or the ROS benchmark's emulator's).

    Parameters
    ----------
    case : TestCase
        The test case.
    names : sequence of str
        The runs' names (their folders under ``OUT/runs``).
    results : sequence of list of dict
        Each run's KPI records (``controller``, ``period``).
    out, report : pathlib.Path
        The output folder and the report page.
    warmup, days : float
        The warm-up and the test period's length [days].

    Returns
    -------
    list of str
        The figures' paths relative to the report's folder
        (``<report stem>/<period>.png``).

    """
    import pandas as pd
    from mshoot_studies.boptest_report import plot_zones
    folder = report.parent / report.stem
    periods: dict[str, dict[str, pd.DataFrame]] = {}
    for name, result in zip(names, results):
        runs = periods.setdefault(result[0]['period'], {})
        if result[0]['controller'] not in runs:
            folder_of_run = out / 'runs' / name
            tables = [folder_of_run / file for file in RECORD_FILES
                      if (folder_of_run / file).is_file()]
            if not tables:
                raise FileNotFoundError(f'no records of run {name} in {folder_of_run} '
                                        f'(expected one of {list(RECORD_FILES)})')
            runs[result[0]['controller']] = pd.read_csv(tables[0])
    paths = []
    for period, runs in periods.items():
        _, start, end = case.test_period(period, warmup, days)
        path = plot_zones(case, runs, start, end, f'{case.name}: {period}',
                          folder / f'{period}.png')
        paths.append(str(path.relative_to(report.parent)))
    return paths


def as_defined_table(records: Sequence[Mapping[str, Any]]) -> str:
    """
    Return the Markdown table of BOPTEST's energy sums as the outputs are written.

    Only for records whose KPIs correct a power output's sign (the card's
    ``boptest.power_signs``; :func:`mshoot_core.boptest.kpi_calculator.compute_kpis`);
    empty otherwise.
    """
    rows = [r for r in records if r.get('as_defined')]
    if not rows:
        return ''
    signs = sorted({name for r in rows for name in r.get('power_signs', {})})
    lines = ['', f'With {", ".join(f"`{s}`" for s in signs)} counted as written (below zero; '
                 "the card's `boptest.power_signs`), BOPTEST's sums would be:", '',
             '| controller | period | price | ener [kWh/m2] | cost [EUR/m2] | '
             'emis [kgCO2/m2] |', '|---|---|---|---|---|---|']
    lines += [f'| {r["controller"]} | {r["period"]} | {r["price"]} | '
              f'{r["as_defined"]["ener_tot"]:.3f} | {r["as_defined"]["cost_tot"]:.4f} | '
              f'{r["as_defined"]["emis_tot"]:.3f} |' for r in rows]
    return '\n'.join(lines) + '\n'


def write_tables(args: argparse.Namespace, case: Any, warmup: float, names: Sequence[str],
                 results: Sequence[Sequence[dict]], writer: str = '`mshoot boptest`') -> str:
    """
    Write the KPI tables to ``OUT/kpis.md`` (and the ``--report`` page); return them.

    The tables of this command and of the ROS benchmark (``mshoot_nodes.boptest_run``).

    Parameters
    ----------
    args : argparse.Namespace
        The command's options (``out``, ``report`` and those :func:`report_page` reads).
    case : TestCase
        The test case.
    warmup : float
        The warm-up [days].
    names : sequence of str
        The runs' names.
    results : sequence of list of dict
        Each run's KPI records (one per price scenario it stands for).
    writer : str
        What ran the runs (:func:`report_page`).

    """
    from mshoot_studies.boptest_report import kpi_table
    records = [entry for result in results for entry in result]
    # the rule's cooling margin and supply shift where its card has them (not 0 somewhere)
    extra = (('lead_h', 'lead [h]', '{:g}'), ('margin_k', 'margin [K]', '{:g}'),
             *((key, header, '{:g}') for key, header in (
                 ('cooling_margin_k', 'cooling margin [K]'),
                 ('supply_shift_k', 'supply shift [K]'))
               if any(r.get(key) for r in records)),
             ('wall_s', 'run wall [s]', '{:.1f}'))
    table = kpi_table(records, extra)
    zones = ['', '| run | price | ' + ' | '.join(f'tdis [{z}] [K h]' for z in case.zones)
             + ' |', '|---|---|' + '---|' * len(case.zones)]
    zones += [f'| {name} | {r["price"]} | '
              + ' | '.join(f'{r["tdis_zones"][z]:.3f}' for z in case.zones) + ' |'
              for name, result in zip(names, results) for r in result[:1]]
    text = table + '\n'.join(zones) + '\n' + as_defined_table(records)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'kpis.md').write_text(text)
    if args.report is not None:
        figures = report_figures(case, names, results, args.out, args.report, warmup,
                                 args.days)
        args.report.write_text(report_page(case, args, warmup, text, writer, figures))
    return text


def reads_price(control_card: str) -> bool:
    """Return True when the control card's forecast carries a price series (one per scenario)."""
    from mshoot_core.boptest.forecasts import ForecastSpec
    return any(source.prices for source in ForecastSpec.from_card(control_card).series.values())


def ensure_forecast_weather(case: Any, periods: Sequence[str], warmup: float, days: float,
                            settings: str, say: Callable[[str], None]) -> None:
    """
    Derive, once, the weather the MPC's forecasts read over the runs (a folder without it).

    Parameters
    ----------
    case : TestCase
        The test case (nothing to do when it has weather of its own).
    periods : sequence of str
        The test periods of the runs.
    warmup, days : float
        The warm-up and the test period [days].
    settings : str
        The MPC settings (their horizon and step: how far past the period it reads).
    say : callable
        Told, once, what is derived.

    """
    from mshoot_core.boptest.weather import ensure_window
    from mshoot_core.settings import MpcSettings
    if not case.weather_derived:
        return
    problem = MpcSettings.from_file(settings).problem
    windows = [case.test_period(period, warmup, days) for period in periods]
    start = min(w[0] for w in windows)
    end = max(w[2] for w in windows) + (problem.horizon_steps + 1) * problem.step_s
    say(f'the weather of {case.name} from its FMU over days {start / 86400:g} to '
        f'{end / 86400:g} (once, into the cache)')
    ensure_window(case, start, end)


def run(args: argparse.Namespace) -> int:
    """Run the command (module docstring): 0, or 2 with one line on stderr."""
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    try:
        return _run(args)
    except (ValueError, FileNotFoundError) as exc:
        sys.stderr.write(f'mshoot boptest: error: {exc}\n')
        return 2


def _say(began: float, line: str) -> None:
    print(f'[boptest {time.perf_counter() - began:6.1f} s] {line}', flush=True)


def _run(args: argparse.Namespace) -> int:
    from mshoot_core.boptest.plant import BoptestPlant, recorded_outputs
    from mshoot_core.boptest.testcase import TestCase
    from mshoot_core.forecast import uncertainty_runs
    from mshoot_core.models.card import load_card
    from mshoot_studies.boptest_report import plot_run
    from mshoot_studies.boptest_rule import COOLING_MARGINS_K, PreheatRule, rule_axes, \
        grid_path, grid_tuning, rule_kinds, rule_targets, SUPPLY_SHIFTS_K, tune_rule
    began = time.perf_counter()
    controllers = _controllers(args.controllers)
    scenarios = uncertainty_runs(args.uncertainty)
    case = TestCase.load(args.testcase)
    card_path = prepare_card(args.card, args.testcase, args.out)
    card = load_card(card_path)
    warmup, periods = runs_window(case, card, args)
    variables = [v.variable for v in (*card.states.values(), *card.outputs.values())]
    record = recorded_outputs(case, [*variables, *([args.starts_output]
                                                   if args.starts_output else [])])
    plant = BoptestPlant(case, record=record)  # checks the names; no instance
    targets = rule_targets(card, case) if 'rule' in controllers else {}
    cooled, reset = rule_kinds(targets)
    fixed = (args.cooling_margin or 0.0, args.supply_shift or 0.0)
    grid = (args.cooling_margins if args.cooling_margins is not None or not cooled
            else COOLING_MARGINS_K,
            args.supply_shifts if args.supply_shifts is not None or not reset
            else SUPPLY_SHIFTS_K)
    if targets:  # the rule's parameters against its card, before any run
        rule_axes(targets, None if fixed[0] == 0 else [fixed[0]],
                  None if fixed[1] == 0 else [fixed[1]])
        rule_axes(targets, *grid)
        PreheatRule(case, targets, args.lead or 0.0, args.margin or 0.0, case.control_step_s,
                    *fixed)  # fixed values out of range are refused here
    mpc = mpc_configuration(args, case, card, card_path) if 'mshoot' in controllers else None
    if mpc is not None:
        ensure_forecast_weather(case, periods, warmup, args.days, mpc[1],
                                lambda line: _say(began, line))
    _say(began, f'{case.name} ({plant.interface}, zones {case.zones}, energy '
                f'{list(case.energy_outputs)}): {controllers} on {periods}')
    tunings: dict[str, Any] = {}

    fixed_rule = any(v is not None for v in (args.lead, args.margin, args.cooling_margin,
                                             args.supply_shift))
    if fixed_rule and args.rule_grids is not None:
        raise ValueError('--rule-grids takes the rule from a tuning: not with --lead, --margin, '
                         '--cooling-margin or --supply-shift')

    def rule_parameters(period: str, price: str) -> tuple[float, ...]:
        if fixed_rule:
            return args.lead or 0.0, args.margin or 0.0, *fixed
        if period not in tunings and args.rule_grids is not None:
            tunings[period] = grid_tuning(args.rule_grids, period, args.prices)
        if period not in tunings:
            tunings[period] = tune_rule(case, targets, period, args.leads, args.margins,
                                        prices=args.prices, warmup_days=warmup,
                                        length_days=args.days, workers=args.workers,
                                        record=record,
                                        progress=lambda line: _say(began, line),
                                        cooling_margins_k=grid[0], supply_shifts_k=grid[1],
                                        power_signs=card.boptest['power_signs'])
        return tunings[period].parameters(price)

    # mshoot: one run per price when its forecast has a price series, else one for all
    jobs = plan_runs(periods, controllers, args.prices, scenarios, rule_parameters,
                     mshoot_per_price=mpc is not None and reads_price(mpc[0]))
    names = [job.name for job in jobs]
    arguments = [(str(case.directory), str(card_path), job.controller, job.period, job.lead_h,
                  job.margin_k, warmup, args.days, list(job.prices), record,
                  str(args.out / 'runs' / name / 'records.csv'), args.starts_output,
                  mpc if job.controller == 'mshoot' else None, job.errors,
                  job.cooling_margin_k, job.supply_shift_k)
                 for job, name in zip(jobs, names)]
    results: list[list[dict]] = [[] for _ in jobs]
    with process_pool(min(args.workers, len(jobs))) as pool:
        futures = {pool.submit(_run_one, *a): k for k, a in enumerate(arguments)}
        for future in concurrent.futures.as_completed(futures):
            k = futures[future]
            results[k] = future.result()
            first = results[k][0]
            _say(began, f'{names[k]}: {first["wall_s"]:.1f} s wall: tdis '
                        f'{first["tdis_tot"]:.3f} K h, ener {first["ener_tot"]:.4f} kWh/m2')
    records = [entry for result in results for entry in result]
    args.out.mkdir(parents=True, exist_ok=True)
    for period, tuning in tunings.items():  # the rule's grid, every point and price
        tuning.grid.to_csv(grid_path(args.out, period), index=False)
    (args.out / 'kpis.json').write_text(json.dumps(records, indent=1) + '\n')
    print(write_tables(args, case, warmup, names, results), end='')
    if args.figures:
        import pandas as pd
        for name, result in zip(names, results):
            first = result[0]
            plot_run(pd.read_csv(args.out / 'runs' / name / 'records.csv'), case,
                     first['start_s'], first['end_s'], name, args.out / f'{name}.png',
                     prices=args.prices)
    _say(began, f'wrote {args.out / "kpis.json"} ({len(records)} records)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
