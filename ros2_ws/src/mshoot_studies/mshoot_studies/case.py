r"""
The reference case (OU44 classroom, SPEC section 3) as a command.

    mshoot case ou44 --data PATH --horizon 10 --control fmu --tolerance 1e-6 \
        --cost quadratic --out out/case

runs the 72 h MPC emulation (hourly control, R1C1 emulator, perfect
forecasts) and writes ``kpis.json``, ``trajectories.csv``, ``steps.csv`` and
``plot.png`` to the output folder. ``synthetic`` instead of ``ou44`` runs the
built-in scenario, which needs no data file.

``data`` runs the data CSV of ``--data``: a time column, a column per series (named as
the models' inputs: ``Tout``, ``solrad``, ``occ``, ...) and the comfort band
``comfort_min``, ``comfort_max`` [degC], or ``--band LO,HI`` for a constant one; the rows
are averaged over each hour from the first (:func:`mshoot_core.scenario.read_data_csv`).

``--control`` and ``--emulator`` also take a model card (``CARD.yaml``, see
``mshoot card check``): any FMU with its names mapped. The MPC then optimises
the card's controls (bounded by their min/max) and the emulated building gets
its start state and actuator limits from the emulator's card.

Exit codes: 0 done; 2 bad options or inputs (one line: a bad card, an FMU
whose binary does not load, a data file with a time given twice); 1 the
emulated building failed (non-finite values): the files are still written for
the steps done, ``kpis.json`` with the reason under ``stopped``; 3 the run
ended but the MPC did not control it: more than ``--max-fallback-share`` of
its steps (default 50 %) were fallbacks (a WARNING says how many; the files
are written, ``kpis.json`` with the sentence under ``fallback_problem``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import pathlib
import time
from typing import Any, Sequence

from mshoot_core.closed_loop import ClosedLoopResult, EmulationStopped, run_closed_loop
from mshoot_core.controller import Controller
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis, FALLBACK_EXIT, fallback_problem
from mshoot_core.models.base import Model
from mshoot_core.models.registry import (build_model, BUILTIN, check_model, CONTROL_TOLERANCE,
                                         EMULATOR_TOLERANCE, is_card_path, model_names,
                                         MODEL_PARAMETERS, ModelSettings)
from mshoot_core.outputs import write_outputs
from mshoot_core.plotting import FigurePreview, PlotWorker
from mshoot_core.scenario import data_scenario, DEFAULT_DATA, PUBLISHED, reference_scenario
from mshoot_core.settings import (add_arguments, from_arguments, MpcSettings, option_wording,
                                  SettingsError)
from mshoot_core.units import KELVIN
import numpy as np
import pandas as pd

from mshoot_studies.cli import verb_parser

logger = logging.getLogger(__name__)

#: Data-driven control models (scikit-learn estimators trained as in Setup 2).
DATA_DRIVEN = ('svr', 'linear', 'ridge', 'knn', 'random_forest', 'mlp')
CONTROL_MODELS = BUILTIN + DATA_DRIVEN
#: Initial zone temperature of the case [degC].
INITIAL_C = 20.0


def control_model(kind: str, tolerance: float = CONTROL_TOLERANCE,
                  data: str | pathlib.Path | None = None, report: dict | None = None,
                  scenario_start: str | None = None) -> Model:
    """
    Build the control model of the case.

    Parameters
    ----------
    kind : str
        A model of the registry (:func:`mshoot_core.models.registry.build_model`:
        'python', 'fmu', 'fmu-cs', a path to an .fmu or a model card), or a
        scikit-learn model trained as in Setup 2 ('svr' is Setup 2 itself,
        'linear', 'ridge', 'knn', 'random_forest', 'mlp'; needs ``data``).
    tolerance : float
        Relative tolerance of an FMU control model's integrator.
    data : path-like, optional
        The OU44 measurements the data-driven models train on.
    report : dict, optional
        Filled with the training/validation report of data-driven models.
    scenario_start : str, optional
        The scenario's first row (ISO 8601), for a card's ``time_origin``.

    """
    if is_card_path(kind):
        return card_model(kind, 'control', tolerance, scenario_start)
    if kind in DATA_DRIVEN:
        if data is None:
            raise ValueError(f'--control {kind} needs --data (it trains on the OU44 '
                             'disturbances)')
        from mshoot_studies.setup2 import train_setup2
        model, training = train_setup2(data, estimator=kind)
        logger.info('%s trained: validation RMSE %.3f K free run, %.4f K one step', kind,
                    training.rmse_free_run_k, training.rmse_one_step_k)
        if report is not None:
            report.update({f.name: getattr(training, f.name)
                           for f in dataclasses.fields(training) if f.name != 'validation'})
        return model
    return build_model(kind, tolerance)


def card_model(path: str | pathlib.Path, role: str, tolerance: float,
               scenario_start: str | None = None) -> Model:
    """
    Build the model of a card for ``role`` ('control' or 'emulator').

    Its FMU time origin is taken from the scenario's start
    (:func:`mshoot_core.models.card.time_origin_seconds`).

    Raises
    ------
    ValueError
        A :class:`~mshoot_core.models.card.CardError` with every problem of the card.

    """
    from mshoot_core.models import card as cards  # (YAML, JSON Schema: cards only)
    card = cards.load_card(path)
    return cards.build_model(card, role, cards.time_origin_seconds(card, scenario_start),
                             tolerance=tolerance)


def emulator_model(kind: str, scenario_start: str | None = None) -> Model:
    """
    Build the emulated building of the case: a registry model or a card.

    At :data:`~mshoot_core.models.registry.EMULATOR_TOLERANCE` (unless the card sets one).
    """
    if is_card_path(kind):
        return card_model(kind, 'emulator', EMULATOR_TOLERANCE, scenario_start)
    return build_model(kind, EMULATOR_TOLERANCE, role='emulator')


def model_choice(value: str) -> str:
    """
    Parse ``--control``/``--emulator``: a known name or a path to a card or an FMU.

    An argparse type: a known name or a path to a card (.yaml) or an .fmu file (checked with the
    other options, every problem at once).
    """
    if value in (*CONTROL_MODELS, *model_names()) or value.endswith('.fmu') \
            or is_card_path(value):
        return value
    raise argparse.ArgumentTypeError(f'expected one of {list(CONTROL_MODELS)}, a model card '
                                     f'(.yaml) or an .fmu file, got {value!r}')


def run_case(scenario: pd.DataFrame, control: Model, emulator_model: Model,
             settings: MpcSettings | None = None, *, horizon: int | None = None,
             initial_c: float = INITIAL_C, steps: int | None = None, log_every: int = 12,
             progress: Any = None, budget_s: float | None = None,
             x0: Sequence[float] | None = None,
             actuator_bounds: Sequence[tuple[float, float]] | None = None,
             **options: Any) -> tuple[ClosedLoopResult, dict]:
    """
    Run the MPC emulation of a scenario and return the records and the KPIs.

    Parameters
    ----------
    scenario : DataFrame
        Disturbances and comfort band (:mod:`mshoot_core.scenario`).
    control, emulator_model : Model
        The control model and the emulated building.
    settings : MpcSettings, optional
        The controller's settings (default: the defaults), changed by
        ``options`` (flat names such as ``cost='energy'``, ``solver='ipopt'``,
        ``comfort='soft'``, ``mode='naive'``; ``horizon`` is short for
        ``horizon_steps``).
    horizon : int, optional
        MPC horizon in control steps (``horizon_steps``).
    initial_c : float
        Initial zone temperature [degC].
    steps, log_every, progress, budget_s :
        See :func:`mshoot_core.closed_loop.run_closed_loop`.
    x0 : sequence of float, optional
        Start state of the emulated building (default: every state at ``initial_c``).
    actuator_bounds : sequence of (float, float), optional
        The emulated building's limits of every control (default: the MPC's bounds).

    The controls are ``settings.problem.control_names``; the energy KPIs count the
    control ``q`` (or the first control when there is no ``q``).

    Raises
    ------
    EmulationStopped
        If the emulated building failed; its ``result`` holds the steps done
        and its ``kpis`` their KPIs with the reason under ``stopped`` (None
        without a step done).

    """
    if horizon is not None:
        options['horizon_steps'] = horizon
    settings = (settings or MpcSettings()).replace(options)
    p = settings.problem
    controller = Controller(control, settings)
    emulator = Emulator(emulator_model, scenario,
                        [initial_c + KELVIN] * len(emulator_model.state_names) if x0 is None
                        else list(x0),
                        control_names=p.control_names,
                        control_bounds=p.control_bounds if actuator_bounds is None
                        else actuator_bounds)
    try:
        result = run_closed_loop(controller, emulator, steps=steps, log_every=log_every,
                                 progress=progress, budget_s=budget_s)
    except EmulationStopped as stop:
        stop.kpis = None if stop.result is None else dict(
            _case_kpis(stop.result, settings), stopped=str(stop))
        raise
    return result, _case_kpis(result, settings)


def _case_kpis(result: ClosedLoopResult, settings: MpcSettings) -> dict:
    """
    Return the KPIs of a run and the settings that made it.

    The energy KPIs count the control ``q``, or the first control when there is no ``q``.
    """
    p, c = settings.problem, settings.comfort
    energy_control = 'q' if 'q' in p.control_names else p.control_names[0]
    kpis = closed_loop_kpis(result.steps, result.fine, p.step_s, result.wall_s,
                            control=energy_control)
    kpis.update(horizon_h=p.horizon_steps * p.step_s / 3600.0, cost=p.cost,
                solver=settings.solver.solver, comfort=c.comfort,
                fallbacks=int(result.steps['fallback'].sum()))
    if c.soft:
        kpis['soft_penalty'] = c.soft_penalty
    return kpis


#: Controller settings offered as options of the case command.
CASE_SETTINGS = ('horizon_steps', 'cost', 'cost_output', 'comfort', 'soft_penalty', 'solver',
                 'mode', 'relaxation', 'solver_max_iter', 'time_budget_s', 'on_failure',
                 'max_fallback_share', 'safe_value',
                 'estimation', 'measured_states', 'measurement_noise_k', 'process_noise_k',
                 'comfort_margin_std')


def option_problems(args: argparse.Namespace,
                    scenario_steps: int | None = None) -> tuple[MpcSettings | None, list[str]]:
    """
    Return the controller settings of parsed options, and every problem of the options.

    All problems at once: settings, FMU tolerance, hours, and a horizon longer than the forecasts.
    """
    problems = ModelSettings(fmu_tolerance=args.tolerance).problems()
    for option, name in (('--control', args.control), ('--emulator', args.emulator)):
        if name in DATA_DRIVEN and option == '--control':
            continue
        problem = check_model(name)
        if problem:
            problems.append(f'{option}: {problem}')
    if args.hours < 1:
        problems.append(f'--hours must be >= 1, got {args.hours}')
    settings = None
    try:
        settings = from_arguments(args, CASE_SETTINGS)
    except SettingsError as exc:
        problems += exc.problems
    horizon = getattr(args, 'horizon_steps', None)
    if scenario_steps is not None and isinstance(horizon, int) and horizon > scenario_steps:
        problems.append(f'--horizon {horizon} h reaches past the end of the forecasts: the '
                        f'scenario covers {scenario_steps} h from the first step (use at most '
                        f'{scenario_steps}, or more --hours of data)')
    return settings, [option_wording(p, MODEL_PARAMETERS) for p in problems]


def _band(text: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected LO,HI in degC, got {text!r}') from None
    if not low <= high:
        raise argparse.ArgumentTypeError(f'expected LO <= HI, got {text!r}')
    return low, high


def case_scenario(args: argparse.Namespace, data: pathlib.Path | None) -> pd.DataFrame:
    """
    Return the scenario of the case's options (``hours + 1`` rows).

    Raises
    ------
    FileNotFoundError, ValueError
        Missing or bad data, a band for another scenario than ``data``.

    """
    band = getattr(args, 'band', None)
    if args.scenario != 'data':
        if band is not None:
            raise ValueError(f'--band is for the scenario data (a data CSV), not '
                             f'{args.scenario!r}, whose band is its own')
        return reference_scenario(args.scenario, data, args.hours)
    if args.data is None:
        raise ValueError('the scenario data needs --data CSV (a column per series and a band)')
    return data_scenario(args.data, args.hours, band)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """
    Build the command line of the case.

    It fills ``parser`` (e.g. the ``case`` verb of ``mshoot``), or a new parser when None.
    Its errors are one line (``<prog>: error: ...``) and exit 2
    (:func:`~mshoot_studies.cli.verb_parser`).
    """
    parser = verb_parser(parser, 'mshoot_studies.case', __doc__)
    parser.add_argument('scenario', choices=('ou44', 'synthetic', 'data'),
                        help='ou44: the reference case (needs --data); synthetic: built-in; '
                             'data: the data CSV of --data (a column per series and a band)')
    parser.add_argument('--data', type=pathlib.Path, default=None,
                        help=f'ou44: the measurements.csv (default: {DEFAULT_DATA.resolve()} '
                             'if it exists); data: a CSV with a time column (datetime or '
                             "time_s), a column per series named as the models' inputs and "
                             'the band comfort_min, comfort_max [degC] (or --band), read as '
                             'hourly means from its first row')
    parser.add_argument('--band', type=_band, default=None, metavar='LO,HI',
                        help='data: a constant comfort band [degC] for a CSV without one '
                             "(default: the CSV's band)")
    parser.add_argument('--control', type=model_choice, default='python', metavar='MODEL',
                        help=f'control model, one of {{{",".join(CONTROL_MODELS)}}}: exact '
                             'Python R1C1, R1C1 FMU (Model Exchange or Co-Simulation), or a '
                             'scikit-learn model trained on R1C1 responses as in Setup 2 (svr '
                             'is Setup 2); or a model card CARD.yaml (default python)')
    parser.add_argument('--emulator', type=model_choice, default='python', metavar='MODEL',
                        help=f'emulation model, one of {{{",".join(BUILTIN)}}} or a model card '
                             'CARD.yaml (default python: the exact R1C1; FMUs run at tolerance '
                             f'{EMULATOR_TOLERANCE:g} unless the card sets one)')
    parser.add_argument('--tolerance', type=float, default=CONTROL_TOLERANCE,
                        help='relative tolerance of the control FMU integrator, in [1e-14, '
                             f"1e-2] (default {CONTROL_TOLERANCE:g}; a card's own tolerance "
                             'wins)')
    add_arguments(parser, CASE_SETTINGS)
    parser.add_argument('--hours', type=int, default=72,
                        help='simulated hours of control (default 72)')
    parser.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/case'),
                        help='output folder (default out/case)')
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process arguments) and run the case; the exit code."""
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """
    Run the case as parsed by :func:`build_parser`.

    Return 0, 2 on bad input, 1 if the emulated building failed (partial outputs written), 3
    (:data:`FALLBACK_EXIT`) if more than ``max_fallback_share`` of the steps fell back; the
    reason is logged.
    """
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format='%(asctime)s %(levelname)s %(name)s: %(message)s')
    settings, problems = option_problems(args)
    if problems:
        logger.error('invalid options: %s', '; '.join(problems))
        return 2
    plotter = getattr(args, 'plot_worker', None)  # started by the mshoot command
    with plotter if plotter is not None else PlotWorker() as plotter:
        return _run(args, settings, plotter)  # the worker imports matplotlib meanwhile


def _run(args: argparse.Namespace, settings: MpcSettings, plotter: PlotWorker) -> int:
    data = args.data
    if data is None and DEFAULT_DATA.is_file():
        data = DEFAULT_DATA.resolve()
    models: list[Model] = []
    try:
        try:
            scenario = case_scenario(args, data)
            settings, problems = option_problems(args, len(scenario) - 1)
            if problems:
                raise ValueError(f"invalid options: {'; '.join(problems)}")
            started = time.perf_counter()
            report: dict = {}
            start = scenario.attrs.get('start')
            models.append(control_model(args.control, args.tolerance, data, report, start))
            models.append(emulator_model(args.emulator, start))
            control, emulator = models
            settings, x0, actuators, problems = card_setup(args, settings, control, emulator,
                                                           scenario)
            if problems:
                raise ValueError(f"invalid options: {'; '.join(problems)}")
            setup_s = time.perf_counter() - started
        except (FileNotFoundError, ValueError) as exc:
            logger.error('%s', exc)
            return 2
        horizon = settings.problem.horizon_steps
        logger.info('running %s: %d h, horizon %d h, control %s, cost %s, comfort %s',
                    args.scenario, args.hours, horizon, args.control, args.cost, args.comfort)
        stopped = None
        try:  # (the plot worker gets the figure's extremes during the last steps)
            result, kpis = run_case(scenario, control, emulator, settings, x0=x0,
                                    actuator_bounds=actuators,
                                    progress=FigurePreview(
                                        plotter, scenario, len(scenario) - 1,
                                        settings.problem.step_s,
                                        control=settings.problem.control_names[0]))
        except EmulationStopped as stop:
            stopped, result, kpis = stop, stop.result, stop.kpis or {'stopped': str(stop)}
    finally:
        for model in models:  # FMUs: free the instances
            close = getattr(model, 'close', None)
            if close is not None:
                close()
    kpis.update(scenario=args.scenario, control=args.control, emulator=args.emulator,
                tolerance=args.tolerance, mode=args.mode, setup_s=setup_s)
    if report:
        kpis['training'] = report
    if args.scenario == 'ou44' and args.hours == 72 and horizon in PUBLISHED:
        kpis['published'] = PUBLISHED[horizon]
    too_few = None if stopped is not None or result is None else fallback_problem(
        int(result.steps['fallback'].sum()), len(result.steps),
        settings.supervisor.max_fallback_share)
    if too_few:
        kpis['fallback_problem'] = too_few
    if stopped is not None:
        _write_stopped(args.out, result, kpis, f'{args.scenario}: H = {horizon} h, control '
                                               f'{args.control}, stopped',
                       settings.problem.control_names[0])
        logger.error('%s; wrote the %d steps done to %s', stopped,
                     0 if result is None else len(result.steps), args.out)
        return 1
    write_outputs(args.out, result, kpis, f'{args.scenario}: H = {horizon} h, control '
                                          f'{args.control}, {args.cost} cost', plotter,
                  control=settings.problem.control_names[0])
    logger.info('energy %.2f kWh (heating %.2f, cooling %.2f), discomfort %.2f Kh (hourly '
                'samples %.2f Kh), wall %.2f s, median solve %.4f s, %d solver failures',
                kpis['energy_kwh'], kpis['heating_kwh'], kpis['cooling_kwh'],
                kpis['discomfort_kh'], kpis['discomfort_kh_hourly'], kpis['wall_s'],
                kpis['solve_s_median'], kpis['solver_failures'])
    logger.info('wrote %s', args.out / 'kpis.json')
    if too_few:
        logger.warning('%s (%s); exit code %d', too_few,
                       _fallback_reasons(result.steps), FALLBACK_EXIT)
        return FALLBACK_EXIT
    return 0


def _fallback_reasons(steps: pd.DataFrame) -> str:
    """Return the fallback codes of a run's steps with their counts (``solve_failed x 24``)."""
    codes = steps.loc[steps['fallback'].astype(bool), 'fallback_code'].value_counts()
    return ', '.join(f'{code} x {count}' for code, count in codes.items())


def card_setup(args: argparse.Namespace, settings: MpcSettings, control: Model,
               emulator: Model, scenario: pd.DataFrame
               ) -> tuple[MpcSettings, np.ndarray | None, list | None, list[str]]:
    """
    Apply the cards of ``--control``/``--emulator`` to the case; list every problem.

    What the cards change in the case, and every problem of the pair with the scenario.

    The control card gives the MPC's controls (``control_names``) with each one's unit,
    limits and safe value (``controls``; the settings ``control_min``/``control_max`` only
    narrow them); the emulator card gives the start state (``T`` from the initial
    temperature, other states from the card) and the actuator limits (where it has none, the
    MPC's).

    Returns
    -------
    settings, x0 (None: the default), actuator bounds (None: the MPC's), problems

    """
    problems: list[str] = []
    control_card = emulator_card = None
    if is_card_path(args.control) or is_card_path(args.emulator):
        from mshoot_core.models import card as cards  # (YAML, JSON Schema: cards only)
        control_card = cards.load_card(args.control) if is_card_path(args.control) else None
        emulator_card = (cards.load_card(args.emulator) if is_card_path(args.emulator)
                         else None)
    names = control_card.control_names if control_card else settings.problem.control_names
    changes: dict[str, Any] = {'control_names': names}
    if control_card:  # each control's unit, limits and safe value
        changes['controls'] = control_card.control_specs()
    try:
        settings = settings.replace(changes)
    except ValueError as exc:
        problems.append(f'--control {args.control}: {exc}')
    missing = [c for c in names if c not in emulator.input_names]
    if missing:
        problems.append(f'--emulator {args.emulator} has no inputs {missing} for the controls of '
                        f'--control {args.control}')
    for option, model, label in (('--control', control, args.control),
                                 ('--emulator', emulator, args.emulator)):
        lacking = [n for n in model.input_names if n not in names and n not in scenario.columns]
        if lacking:
            problems.append(f'{option} {label}: inputs {lacking} are neither controls nor '
                            f'series of the scenario {[*scenario.columns]}')
    if tuple(control.state_names) != tuple(emulator.state_names):
        problems.append(f'the control model has the states {list(control.state_names)}, the '
                        f'emulator {list(emulator.state_names)}: the MPC starts each step from '
                        'the emulated states, so they must be the same')
    if 'T' not in control.state_names:
        problems.append(f'--control {args.control}: no state T (the zone temperature [K] the '
                        'comfort band bounds)')
    if 'T' not in emulator.output_names:
        problems.append(f'--emulator {args.emulator}: no output T (the zone temperature '
                        '[degC] of the comfort KPIs)')
    x0 = actuators = None
    if emulator_card is not None:
        try:
            x0 = emulator_card.initial_state(INITIAL_C + KELVIN)
        except ValueError as exc:
            problems.append(str(exc))
        mpc = dict(zip(names, settings.problem.control_bounds))
        own = {c.name: (c.min, c.max) for c in emulator_card.control_specs()}
        actuators = [tuple(m if math.isnan(e) else e for e, m in zip(own.get(c, mpc[c]), mpc[c]))
                     for c in names]
    return settings, x0, actuators, problems


def _write_stopped(out: pathlib.Path, result: ClosedLoopResult | None, kpis: dict,
                   title: str, control: str = 'q') -> None:
    """Return the files of a stopped run: those of its steps done, or ``kpis.json`` alone."""
    if result is not None:
        write_outputs(out, result, kpis, title, control=control)
        return
    out.mkdir(parents=True, exist_ok=True)
    for name in ('trajectories.csv', 'steps.csv', 'plot.png'):  # not from an earlier run
        (out / name).unlink(missing_ok=True)
    (out / 'kpis.json').write_text(json.dumps(kpis, indent=2, sort_keys=True) + '\n')


if __name__ == '__main__':
    from mshoot_studies.cli import exit_now
    exit_now(main())
