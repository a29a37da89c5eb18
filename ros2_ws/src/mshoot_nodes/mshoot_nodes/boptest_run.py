"""
BOPTEST over ROS 2: any test case's baseline, tuned rule and mshoot from its card and settings.

    boptest --testcase DIR --card CARD.yaml --out OUT [--report PAGE.md]     # as mshoot boptest
        [--periods P ...] [--prices constant dynamic] [--controllers baseline rule mshoot]
        [--control-card CARD.yaml --mpc-settings SETTINGS.yaml] [--uncertainty none high=1,2,3]
        [--warmup-days 1 --days 2] [--starts-output OUTPUT] [--workers 2]
    boptest ... --docs docs     # make boptest: the heat pump benchmark's page docs/boptest.md

The same configuration as ``mshoot boptest`` (:mod:`mshoot_studies.boptest`: the test case
folder, its card of kind ``boptest``, for mshoot the control card and settings of
``--control-card``/``--mpc-settings`` or the card's ``boptest.control``; the same run planning,
:func:`mshoot_studies.boptest.plan_runs`), but every run goes over the ROS nodes in one process
(one executor, a private context, discovery off; ``--workers`` runs at once, each in a worker
process of its own): the emulator runs the test case from a card derived from the building's
(:func:`emulator_card`: one persistent FMU instance, FMU time = seconds of the year, the warm-up
under the building's own control, outputs recorded every 60 s), the forecaster serves the test
case's data and the controller answers each step:

- ``baseline``: the emulator's card maps the rule's setpoint without its overwrite switch, so
  the building's own controller is in charge; the rule node (mode ``baseline``) only clocks
  the lockstep emulator;
- ``rule``: the rule node on the card's setpoint (``boptest.setpoint_zones``: the control and
  the zone whose band it follows) with the lead and margin tuned offline, in core, beforehand
  (:func:`mshoot_studies.boptest_rule.tune_rule` over the full period; cached in
  ``<out>/rule_tuning.json``), or ``--lead``/``--margin``;
- ``mshoot``: the MPC node (:mod:`mshoot_nodes.mpc_node`: the core
  :class:`~mshoot_core.controller.Controller`) with the control card and the settings
  (:func:`mshoot_params`); the emulator's card has the overwrites the settings send
  (``plant_controls``), the warm-up and the step means of the outputs published every control
  step for the state estimator; the MPC plans from ``/forecast``: the forecaster with
  ``model`` = the control card serves its test case source (the weather derived from the FMU
  first for a folder without its own: :func:`mshoot_studies.boptest.ensure_forecast_weather`),
  the first forecast reaching back over the warm-up (``history_steps``). A schedule within the
  step (e.g. bursts) travels as the setpoint's schedule. A ROS run equals the core run of
  :func:`mshoot_core.boptest.supervision.supervised_plant` (``tests/test_boptest_ros.py``).

mshoot runs once per forecast scenario of ``--uncertainty`` (``LEVEL`` or ``LEVEL=SEED,...``,
:func:`mshoot_core.forecast.uncertainty_runs`; default
:data:`~mshoot_core.forecast.BENCHMARK_UNCERTAINTY`: perfect, ``high`` with seeds 1, 2, 3, ``low``
and ``medium`` with seed 1): the forecaster's ``temperature_uncertainty``,
``solar_uncertainty`` and ``seed`` (BOPTEST's forecast errors on the outdoor temperature and
the irradiance), the controller told the level (:func:`mshoot_core.forecast_margin.allowance`).
The baseline and the rule read no weather forecast (the rule's lead is a forecast of the band,
which stays exact): their records are ``uncertainty`` ``none``, ``seed`` null.

The baseline's and the rule's trajectories do not depend on the price scenario (they never
read it): each is simulated once per period (the rule once per distinct tuned lead/margin) and
its KPIs are computed for every price scenario it stands for; only ``cost_tot`` differs; so
does mshoot when its control card's forecast has no price series.

Writes ``<out>/kpis.json`` (records: controller, period, price, uncertainty, seed, BOPTEST's
KPIs with ``tdis_zones``, ``starts_per_day`` with ``--starts-output``, wall_s),
``<out>/kpis.md`` (the tables of ``mshoot boptest``; with ``--report`` also as a Markdown page),
``<out>/runs/<controller>_<period>[_<price>[_<level>_s<seed>]]/`` (the emulator's card and
files with ``boptest_records.csv``) and, with ``--docs``, the heat pump benchmark's page
``<docs>/boptest.md`` with ``<docs>/boptest/*.png``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import pathlib
import sys
import time
from typing import Any, Callable, Sequence

from mshoot_core.boptest.kpi_calculator import kpi_records
from mshoot_core.boptest.testcase import PRICE_SCENARIOS, TestCase
from mshoot_core.forecast import BENCHMARK_UNCERTAINTY, scenario_fields, uncertainty_runs
from mshoot_core.forecast_margin import allowance
from mshoot_core.models.card import load_card
from mshoot_core.settings import ForecastErrorSettings, MpcSettings
from mshoot_core.units import json_ready
from mshoot_studies.boptest import (add_shared_arguments, control_card_path,
                                    ensure_forecast_weather, mpc_configuration, plan_runs,
                                    prepare_card, reads_price, RunJob, runs_window,
                                    write_tables)
from mshoot_studies.boptest_page import write_docs
from mshoot_studies.boptest_report import count_starts
from mshoot_studies.boptest_rule import rule_targets, RuleTuning, tune_rule
import pandas as pd
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
import yaml

from mshoot_nodes import contract
from mshoot_nodes.emulator_node import EmulatorNode
from mshoot_nodes.forecaster_node import ForecasterNode
from mshoot_nodes.mpc_node import MpcNode
from mshoot_nodes.rule_node import RuleNode
from mshoot_nodes.startup import EXIT_CONFIG, startup_reason, StartupError

logger = logging.getLogger(__name__)

CONTROLLERS = ('baseline', 'rule', 'mshoot')
#: What ran the runs, on the ``--report`` page.
WRITER = ('`python -m mshoot_nodes.boptest_run` (every run over the ROS 2 nodes, in '
          'lockstep)')


def mshoot_params(warmup_days: float, card: str, settings: str,
                  overrides: dict[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """
    Return the node parameters of an mshoot run that differ from the rule's.

    Parameters
    ----------
    warmup_days : float
        The warm-up [days] (the first forecast's history).
    card : str
        The control card (a file or a built-in card's name).
    settings : str
        The MPC settings (a file of flat settings or a packaged name).
    overrides : dict, optional
        Flat settings over those of ``settings``.

    Returns
    -------
    dict
        ``{'controller': {...}, 'forecaster': {...}}``: the MPC node's (the control card as
        ``model``, the settings that differ from the defaults) and the forecaster's (the
        control card's test case source, its first forecast reaching back over the warm-up,
        the horizon of the settings).

    """
    path = control_card_path(card)
    chosen = MpcSettings.from_file(settings, **(overrides or {}))
    defaults = MpcSettings().flat()
    changed = {k: v for k, v in chosen.flat().items() if not _same(v, defaults[k])}
    step = float(chosen.problem.step_s)
    history = int(round(warmup_days * 86400.0 / step))
    return {'controller': {'model': str(path), 'use_sim_time': True, **changed},
            'forecaster': {'model': str(path), 'history_steps': history, 'step_s': step,
                           'horizon_steps': int(chosen.problem.horizon_steps)}}


def _same(a: Any, b: Any) -> bool:
    """Return True for equal setting values (NaN equals NaN)."""
    return a == b or (isinstance(a, float) and isinstance(b, float) and a != a and b != b)


def sent_controls(card: str, settings: MpcSettings) -> tuple[tuple[str, ...], float]:
    """
    Return the plant's controls the MPC of a control card and settings sends, and its step.

    The controller's :attr:`~mshoot_core.controller.Controller.sent_control_names` (its
    model's controls as the settings' ``plant_controls`` name them, then its band setpoints)
    and control step [s].
    """
    from mshoot_core.controller import controller_for
    from mshoot_core.models.card import build_model
    controller = controller_for(build_model(load_card(control_card_path(card))), settings)
    return controller.sent_control_names, float(controller.settings.problem.step_s)


def emulator_card(card: pathlib.Path, controls: Sequence[str], path: pathlib.Path, *,
                  warmup_days: float, switches: bool = True,
                  history_step_s: float = 0.0) -> pathlib.Path:
    """
    Write the emulator's card of a run: the building's card with the controls the run sends.

    Parameters
    ----------
    card : pathlib.Path
        The building's card (kind ``boptest``, its ``boptest.test_case`` the test case folder:
        :func:`mshoot_studies.boptest.prepare_card`).
    controls : sequence of str
        The card's controls the run's controller sends (the emulator expects exactly these).
    path : pathlib.Path
        Where the card is written.
    warmup_days : float
        The warm-up [days].
    switches : bool
        Keep the controls' overwrite switches (false: the building's own controller stays in
        charge, whatever is sent: the baseline).
    history_step_s : float
        Step of the warm-up's history and of the published step means of the outputs [s] (0:
        none; an MPC observes every control step).

    Raises
    ------
    ValueError
        For a control the card does not have.

    """
    document = yaml.safe_load(pathlib.Path(card).read_text())
    known = document.get('controls') or {}
    unknown = [name for name in controls if name not in known]
    if unknown:
        raise ValueError(f'{card}: no control {unknown} (the card has {sorted(known)})')
    chosen = {name: dict(known[name]) for name in controls}
    if not switches:
        for spec in chosen.values():
            spec.pop('activate', None)
    section = dict(document['boptest'])
    section['warmup_days'] = float(warmup_days)
    section['setpoint_zones'] = {k: v for k, v in (section.get('setpoint_zones') or {}).items()
                                 if k in chosen}
    if history_step_s:
        section['history_step_s'] = float(history_step_s)
    document.update(controls=chosen, boptest=section)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def rule_setpoint(card: Any, controller: str) -> tuple[str, str]:
    """
    Return the setpoint control the rule node sends and the zone of its band.

    The card's ``boptest.setpoint_zones`` (for the baseline, whose rule node only clocks the
    emulator: its first entry, else the card's first control and the first zone).

    Raises
    ------
    ValueError
        For the rule on a card without one setpoint zone (the rule node sends one setpoint).

    """
    zones = dict((card.boptest or {}).get('setpoint_zones') or {})
    if controller == 'rule' and len(zones) != 1:
        raise ValueError(f'model card {card.path}: the rule over ROS sends one setpoint: '
                         f'expected one boptest.setpoint_zones entry, got {zones}')
    if zones:
        control, zone = next(iter(zones.items()))
        return str(control), str(zone)
    return next(iter(card.controls)), ''


@dataclasses.dataclass
class BoptestRun:
    """One ROS run: what the emulator recorded and how long it took."""

    controller: str
    period: str
    records: pd.DataFrame
    start_s: float
    end_s: float
    setpoint_waits_s: list[float]
    wall_s: float
    steps: int
    failed: str


def _overrides(values: dict[str, Any]) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items() if value is not None]


def run_ros(context: Context, controller: str, period: str, case: TestCase,
            card: pathlib.Path, *, control: tuple[str, str] | None = None,
            price: str = 'constant', warmup_days: float = 7.0, length_days: float = 14.0,
            lead_h: float = 0.0, margin_k: float = 0.0, out: pathlib.Path | None = None,
            cards: pathlib.Path | None = None, timeout_s: float = 3600.0,
            progress: Callable[[str], None] | None = None,
            mpc_settings: dict[str, Any] | None = None,
            on_step: Callable[[int, dict[str, Any]], None] | None = None,
            errors: ForecastErrorSettings | None = None) -> BoptestRun:
    """
    Run one controller on one test period over ROS, in this process (module docstring).

    Parameters
    ----------
    context : Context
        An initialised rclpy context.
    controller : {'baseline', 'rule', 'mshoot'}
        The controller.
    period : str
        The test period.
    case : TestCase
        The test case.
    card : pathlib.Path
        The building's card (kind ``boptest``; its test case is ``case``).
    control : (str, str), optional
        For ``controller='mshoot'``: the control card and the MPC settings (files or packaged
        names; :func:`mshoot_studies.boptest.mpc_configuration`).
    price : str
        The price scenario the forecaster serves.
    warmup_days, length_days : float
        Warm-up and test period [days].
    lead_h, margin_k : float
        The rule's parameters.
    out : pathlib.Path, optional
        The emulator's output folder.
    cards : pathlib.Path, optional
        Folder for the cards written (default ``out`` or ``out/boptest/cards``).
    timeout_s : float
        Wall-clock guard [s].
    progress : callable, optional
        Called with a line every simulated day.
    mpc_settings : dict, optional
        For ``controller='mshoot'``: flat MPC settings over those of ``control``.
    on_step : callable, optional
        ``on_step(steps_done, nodes)`` after each step the emulator ran (and once before the
        first), nodes by name ('emulator', 'forecaster', 'controller'): e.g. to inject faults.
    errors : ForecastErrorSettings, optional
        For ``controller='mshoot'``: the forecaster's errors (default none: perfect); the
        controller's settings told their level (:func:`~mshoot_core.forecast_margin.allowance`,
        under ``mpc_settings``).

    Raises
    ------
    ValueError
        For a bad controller or length, or mshoot without ``control``.
    StartupError
        A node could not start.
    TimeoutError
        The run took longer than ``timeout_s``.

    """
    if controller not in CONTROLLERS:
        raise ValueError(f'controller must be one of {CONTROLLERS}, got {controller!r}')
    hours = int(round(length_days * 24))
    if abs(hours - length_days * 24) > 1e-9 or hours < 1:
        raise ValueError(f'length_days must be a positive whole number of hours, got '
                         f'{length_days!r}')
    if controller == 'mshoot' and control is None:
        raise ValueError('an mshoot run needs control: (control card, MPC settings)')
    cards = cards or out or pathlib.Path('out/boptest/cards')
    building = load_card(prepare_card(pathlib.Path(card), case.directory, cards))
    common = {'scenario': f'boptest:{period}:{price}', 'data': str(case.directory),
              'hours': hours}
    setpoint, zone = rule_setpoint(building, controller)
    params: dict[str, dict[str, Any]] = {
        'emulator': {**common, 'output_dir': str(out) if out is not None else '',
                     'ready_endpoints': [f'{contract.ZONE_STATE} subscribers>=1',
                                         f'{contract.SETPOINT} publishers>=1',
                                         f'{contract.FORECAST} publishers>=1'],
                     'initial_temperature_c': 21.0, 'lockstep_timeout_s': 600.0},
        'forecaster': {**common, 'use_sim_time': True, 'horizon_steps': 24},
        'controller': {**common, 'mode': 'baseline' if controller == 'baseline' else 'rule',
                       'lead_h': float(lead_h), 'margin_k': float(margin_k),
                       'control': setpoint, 'band_zone': zone},
    }
    controller_cls: type = RuleNode
    sent, history_step = [setpoint], 0.0
    if controller == 'mshoot':
        told = {**allowance(errors), **(mpc_settings or {})}
        mshoot = mshoot_params(warmup_days, *control, told)
        params['controller'] = {**mshoot['controller']}
        params['forecaster'].update(mshoot['forecaster'])
        params['emulator']['step_s'] = mshoot['forecaster']['step_s']
        if errors is not None:
            params['forecaster'].update(dataclasses.asdict(errors))
        controller_cls = MpcNode
        sent, history_step = sent_controls(control[0], MpcSettings.from_file(control[1], **told))
    params['emulator']['model'] = str(emulator_card(
        building.path, sent, cards / f'emulator_{controller}_warmup{warmup_days:g}d.yaml',
        warmup_days=warmup_days, switches=controller != 'baseline',
        history_step_s=history_step))
    # The one writer of /mpc/setpoint the emulator expects (another one is an intruder).
    params['emulator']['setpoint_writer'] = 'mpc' if controller == 'mshoot' else 'rule'
    nodes: list[Any] = []
    by_name: dict[str, Any] = {}
    executor = SingleThreadedExecutor(context=context)

    def make(cls: type, name: str) -> Any:
        try:
            node = cls(context=context, parameter_overrides=_overrides(params[name]))
        except Exception as exc:  # noqa: BLE001 - whatever fails at start-up: one clear line
            raise StartupError(f'{name}: cannot start: {startup_reason(exc)}') from exc
        nodes.append(node)
        by_name[name] = node
        executor.add_node(node)
        return node

    emulator = None
    began = time.perf_counter()
    try:
        make(ForecasterNode, 'forecaster')
        make(controller_cls, 'controller')
        emulator = make(EmulatorNode, 'emulator')
        day, seen = 0, -1
        while not emulator.done:
            if on_step is not None and emulator.steps_done != seen:
                seen = emulator.steps_done
                on_step(seen, by_name)
            executor.spin_once(timeout_sec=0.1)
            if progress is not None and emulator.steps_done // 24 > day:
                day = emulator.steps_done // 24
                progress(f'{controller} {period}: day {day}/{hours // 24} '
                         f'({time.perf_counter() - began:.0f} s)')
            if time.perf_counter() - began > timeout_s:
                raise TimeoutError(f'the ROS run did not finish within {timeout_s:.0f} s '
                                   f'({emulator.steps_done} steps done)')
        wall = time.perf_counter() - began
        model = emulator.emulator.model
        records = model.boptest_records()
        _, start, end = case.test_period(period, warmup_days, length_days)
        return BoptestRun(controller, period, records, start, end,
                          list(emulator.setpoint_waits_s), wall, emulator.steps_done,
                          emulator.failed)
    finally:
        if emulator is not None and emulator.emulator is not None:
            emulator.emulator.model.close()  # one FMU instance per process: free it now
        executor.shutdown()
        for node in nodes:
            node.destroy_node()


# -- the benchmark ----------------------------------------------------------------------------
def load_or_tune(case: TestCase, targets: dict, periods: Sequence[str],
                 path: pathlib.Path, *,
                 warmup_days: float, length_days: float, leads_h: Sequence[float],
                 margins_k: Sequence[float], retune: bool,
                 progress: Callable[[str], None], workers: int = 1,
                 power_signs: dict | None = None) -> dict[str, dict]:
    """
    Return the rule's tuning per period: cached in ``path`` when made with the same grid.

    ``targets``: the rule's (:func:`mshoot_studies.boptest_rule.rule_targets` of the card);
    ``power_signs``: the card's (its KPIs' sign corrections).

    Returns
    -------
    dict
        Period -> ``{'best': {price: {'lead_h', 'margin_k', ...}}, 'grid': [...], ...}``.

    """
    key = {'warmup_days': warmup_days, 'length_days': length_days,
           'leads_h': [float(v) for v in leads_h], 'margins_k': [float(v) for v in margins_k]}
    cached = json.loads(path.read_text()) if path.is_file() and not retune else {}
    out = {}
    for period in periods:
        entry = cached.get(period)
        if entry is not None and entry.get('settings') == key:
            progress(f'rule tuning {period}: from {path}')
            out[period] = entry
            continue
        began = time.perf_counter()
        tuning: RuleTuning = tune_rule(case, targets, period, leads_h, margins_k,
                                       warmup_days=warmup_days, length_days=length_days,
                                       progress=progress, workers=workers,
                                       power_signs=power_signs)
        out[period] = {'settings': key, 'weight': tuning.weight,
                       'wall_s': time.perf_counter() - began,
                       'best': {price: {k: json_ready(v) for k, v in row.items()}
                                for price, row in tuning.best.items()},
                       'grid': [{k: json_ready(v) for k, v in row.items()}
                                for row in tuning.grid.to_dict('records')]}
        cached[period] = out[period]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(cached, indent=1) + '\n')
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog='boptest', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--testcase', '--test-case', dest='test_case', default='',
                        help='the BOPTEST test case folder (default $MSHOOT_BOPTEST_DIR or '
                             '../shared/boptest/...)')
    add_shared_arguments(parser)
    parser.add_argument('--periods', nargs='+', default=None,
                        help='test periods (keys of days.json; default all of them)')
    parser.add_argument('--prices', nargs='+', default=list(PRICE_SCENARIOS),
                        choices=list(PRICE_SCENARIOS))
    parser.add_argument('--controllers', nargs='+', default=list(CONTROLLERS),
                        choices=list(CONTROLLERS))
    parser.add_argument('--uncertainty', nargs='+', default=list(BENCHMARK_UNCERTAINTY),
                        metavar='LEVEL[=SEEDS]',
                        help="mshoot's forecast scenarios (BOPTEST's forecast errors of the "
                             'outdoor temperature and the irradiance at that level, one run per '
                             'seed; LEVEL alone: seed 1; default: '
                             + ' '.join(BENCHMARK_UNCERTAINTY) + ')')
    parser.add_argument('--retune', action='store_true', help='tune the rule again')
    parser.add_argument('--workers', type=int, default=2, choices=range(1, 9),
                        metavar='N', help="runs and the rule tuning's grid points at once, "
                        'one process and FMU instance each (default 2; 1: the runs in this '
                        'process)')
    parser.add_argument('--starts-output', default='',
                        help='an FMU output whose off -> on transitions are counted '
                             '(starts_per_day, e.g. a heat pump modulation)')
    parser.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/boptest'))
    parser.add_argument('--report', type=pathlib.Path, default=None,
                        help="also write the KPI tables as a Markdown page (mshoot boptest's)")
    parser.add_argument('--docs', type=pathlib.Path, default=None,
                        help="write the heat pump benchmark's page <docs>/boptest.md and "
                             '<docs>/boptest/*.png')
    parser.add_argument('--timeout', type=float, default=3600.0,
                        help='wall-clock limit of one ROS run [s]')
    parser.add_argument('--docs-only', action='store_true',
                        help='only write the docs again from <out>/kpis.json and runs.json')
    return parser


def configure(args: argparse.Namespace) -> tuple[TestCase, Any, tuple[str, str] | None]:
    """
    Check the configuration before any run: the test case, its card, mshoot's control.

    Sets ``args.warmup_days`` (the card's by default) and ``args.periods`` (all by default).

    Returns
    -------
    (TestCase, ModelCard, (control card, settings) or None)
        The card with ``boptest.test_case`` the test case (written into ``<out>/cards``).

    Raises
    ------
    ValueError, FileNotFoundError
        For a bad folder, card, period, scenario or control.

    """
    case = TestCase.load(args.test_case or None)
    card = load_card(prepare_card(args.card, case.directory, args.out / 'cards'))
    args.warmup_days, args.periods = runs_window(case, card, args)
    control = None
    if 'mshoot' in args.controllers:
        control = mpc_configuration(args, case, card, card.path)
    for controller in ('rule', 'baseline'):
        if controller in args.controllers:
            rule_setpoint(card, controller)
    return case, card, control


def run_benchmark(args: argparse.Namespace, context: Context,
                  say: Callable[[str], None]) -> tuple[list[dict], list[dict]]:
    """Run every requested run; return the KPI records and the run descriptions."""
    case, card, control = configure(args)
    scenarios = uncertainty_runs(args.uncertainty)  # bad levels and seeds fail here
    tunings: dict[str, Any] = {}
    fixed = args.lead is not None or args.margin is not None
    if 'rule' in args.controllers and not fixed:
        tunings = load_or_tune(case, rule_targets(card, case), args.periods,
                               args.out / 'rule_tuning.json', warmup_days=args.warmup_days,
                               length_days=args.days, leads_h=args.leads,
                               margins_k=args.margins, retune=args.retune, progress=say,
                               workers=args.workers, power_signs=card.boptest['power_signs'])

    def rule_parameters(period: str, price: str) -> tuple[float, float]:
        if fixed:
            return args.lead or 0.0, args.margin or 0.0
        best = tunings[period]['best'][price]
        return best['lead_h'], best['margin_k']

    if control is not None:
        ensure_forecast_weather(case, args.periods, args.warmup_days, args.days, control[1],
                                say)
    jobs = plan_runs(args.periods, args.controllers, args.prices, scenarios, rule_parameters,
                     mshoot_per_price=control is not None and reads_price(control[0]))
    settings = {'test_case': str(case.directory), 'card': str(card.path), 'control': control,
                'warmup_days': args.warmup_days, 'length_days': args.days,
                'out': str(args.out), 'timeout_s': args.timeout,
                'starts_output': args.starts_output,
                'power_signs': card.boptest['power_signs']}
    results: list[tuple[list[dict], dict]] = []
    if args.workers == 1 or len(jobs) == 1:
        results = [run_job(job, settings, context, say) for job in jobs]
    else:  # one process per run at once: its own rclpy context and FMU instance
        import concurrent.futures
        from mshoot_studies.worker_pool import process_pool
        with process_pool(min(args.workers, len(jobs))) as pool:
            futures = [pool.submit(run_job, job, settings) for job in jobs]
            for future in concurrent.futures.as_completed(futures):
                new, run = future.result()
                say(_done_line(run, new))
            results = [future.result() for future in futures]  # the jobs' order
    records = [record for new, _ in results for record in new]
    print(write_tables(args, case, args.warmup_days, [run['name'] for _, run in results],
                       [new for new, _ in results], writer=WRITER), end='')
    return records, [run for _, run in results]


def _say(line: str) -> None:
    print(f'[boptest worker] {line}', flush=True)


def _done_line(run: dict, new: list[dict]) -> str:
    first = new[0]
    return (f'{run["name"]}: {run["steps"]} steps in {run["wall_s"]:.1f} s: tdis '
            f'{first["tdis_tot"]:.2f} K h, ener {first["ener_tot"]:.3f} kWh/m2, cost '
            + ', '.join(f'{r["price"]} {r["cost_tot"]:.4f}' for r in new) + ' EUR/m2')


def run_job(job: RunJob, settings: dict[str, Any], context: Context | None = None,
            say: Callable[[str], None] | None = None) -> tuple[list[dict], dict]:
    """
    Run one job over ROS and return its KPI records and its description.

    Without ``context`` (a worker process): in a context of its own, discovery off (the
    process's nodes find only each other).

    Raises
    ------
    RuntimeError
        If the run failed.

    """
    own = context is None
    if own:
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'OFF'
        context = Context()
        rclpy.init(args=['--ros-args', '--log-level', 'warn'], context=context,
                   domain_id=1 + os.getpid() % 100)
    say = say or _say
    case = TestCase.load(settings['test_case'])
    out = pathlib.Path(settings['out'])
    name, controller = job.name, job.controller
    control = settings['control']
    try:
        say(f'{name}: starting ({", ".join(job.prices)})')
        run = run_ros(context, controller, job.period, case, pathlib.Path(settings['card']),
                      control=tuple(control) if control else None, price=job.prices[0],
                      warmup_days=settings['warmup_days'], length_days=settings['length_days'],
                      lead_h=job.lead_h, margin_k=job.margin_k, out=out / 'runs' / name,
                      timeout_s=settings['timeout_s'], progress=say, errors=job.errors)
    finally:
        if own:
            context.try_shutdown()
    if run.failed:
        raise RuntimeError(f'{name}: the run failed: {run.failed}')
    # time_rat: the controller's wall time between two advances over the step;
    # the baseline has no controller (its node only clocks the lockstep)
    waits = run.setpoint_waits_s if controller != 'baseline' else None
    new = kpi_records(run.records, case, run.start_s, run.end_s, list(job.prices), waits,
                      power_signs=settings.get('power_signs'), controller=controller,
                      period=job.period)
    starts = settings['starts_output']
    for record in new:
        record.update(scenario_fields(job.errors))
        record['wall_s'] = run.wall_s
        if starts:
            record['starts_per_day'] = count_starts(run.records, starts, run.start_s,
                                                    run.end_s)[1]
        if controller == 'rule':
            record.update(lead_h=job.lead_h, margin_k=job.margin_k)
    described = {'name': name, 'controller': controller, 'period': job.period,
                 'prices': list(job.prices), **scenario_fields(job.errors),
                 'start_s': run.start_s, 'end_s': run.end_s, 'wall_s': run.wall_s,
                 'steps': run.steps}
    if not own:
        say(_done_line(described, new))
    return new, described


def main(argv: Sequence[str] | None = None) -> int:
    """``boptest``: run the benchmark (module docstring); exit 2 on bad arguments."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'OFF'
    began = time.perf_counter()

    def say(line: str) -> None:
        print(f'[boptest {time.perf_counter() - began:6.0f} s] {line}', flush=True)

    if args.docs_only:
        if args.docs is None:
            print('boptest: error: --docs-only needs --docs', file=sys.stderr)
            return 2
        if args.warmup_days is None:
            args.warmup_days = float(yaml.safe_load(args.card.read_text())['boptest']
                                     .get('warmup_days', 7.0))
        records = json.loads((args.out / 'kpis.json').read_text())
        runs = json.loads((args.out / 'runs.json').read_text())
        timing = args.out / 'run_time.json'
        wall = json.loads(timing.read_text())['wall_s'] if timing.is_file() else None
        say(f'wrote {write_docs(args, records, runs, wall)}')
        return 0
    context = Context()
    rclpy.init(args=['--ros-args', '--log-level', 'warn'], context=context)
    try:
        records, runs = run_benchmark(args, context, say)
    except (ValueError, FileNotFoundError) as exc:
        print(f'boptest: error: {exc}', file=sys.stderr)
        return 2
    except StartupError as exc:
        print(f'boptest: error: {exc}', file=sys.stderr)
        return EXIT_CONFIG
    finally:
        context.try_shutdown()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'kpis.json').write_text(json.dumps(records, indent=1) + '\n')
    (args.out / 'runs.json').write_text(json.dumps(runs, indent=1) + '\n')
    (args.out / 'run_time.json').write_text(json.dumps(
        {'wall_s': time.perf_counter() - began}) + '\n')
    say(f'wrote {args.out / "kpis.json"} ({len(records)} records)')
    if args.docs is not None:
        path = write_docs(args, records, runs, time.perf_counter() - began)
        say(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
