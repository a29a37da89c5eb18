r"""
The reference case (OU44 classroom, SPEC section 3) as a command.

    mshoot case ou44 --data PATH --horizon 10 --control fmu --tolerance 1e-6 \
        --cost quadratic --out out/case

runs the 72 h MPC emulation (hourly control, R1C1 emulator, perfect
forecasts) and writes ``kpis.json``, ``trajectories.csv``, ``steps.csv`` and
``plot.png`` to the output folder. ``synthetic`` instead of ``ou44`` runs the
built-in scenario, which needs no data file.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import pathlib
import sys
import time
from typing import Any, Sequence

from mshoot_core.closed_loop import ClosedLoopResult, run_closed_loop
from mshoot_core.controller import Controller
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import KELVIN
from mshoot_core.models.registry import (build_model, BUILTIN, CONTROL_TOLERANCE,
                                         EMULATOR_TOLERANCE, MODEL_PARAMETERS, ModelSettings)
from mshoot_core.outputs import write_outputs
from mshoot_core.scenario import DEFAULT_DATA, PUBLISHED, reference_scenario
from mshoot_core.settings import (add_arguments, from_arguments, MpcSettings, option_wording,
                                  SettingsError)
import pandas as pd

logger = logging.getLogger(__name__)

#: Data-driven control models (scikit-learn estimators trained as in Setup 2).
DATA_DRIVEN = ('svr', 'linear', 'ridge', 'knn', 'random_forest', 'mlp')
CONTROL_MODELS = BUILTIN + DATA_DRIVEN


def control_model(kind: str, tolerance: float = CONTROL_TOLERANCE,
                  data: str | pathlib.Path | None = None, report: dict | None = None) -> Model:
    """
    Build the control model of the case.

    Parameters
    ----------
    kind : str
        A model of the registry (:func:`mshoot_core.models.registry.build_model`:
        'python', 'fmu', 'fmu-cs' or a path to an .fmu), or a scikit-learn
        model trained as in Setup 2 ('svr' is Setup 2 itself, 'linear', 'ridge',
        'knn', 'random_forest', 'mlp'; needs ``data``).
    tolerance : float
        Relative tolerance of an FMU control model's integrator.
    data : path-like, optional
        The OU44 measurements the data-driven models train on.
    report : dict, optional
        Filled with the training/validation report of data-driven models.

    """
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


def run_case(scenario: pd.DataFrame, control: Model, emulator_model: Model,
             settings: MpcSettings | None = None, *, horizon: int | None = None,
             initial_c: float = 20.0, steps: int | None = None, log_every: int = 12,
             progress: Any = None, budget_s: float | None = None,
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

    """
    if horizon is not None:
        options['horizon_steps'] = horizon
    settings = (settings or MpcSettings()).replace(options)
    controller = Controller(control, settings)
    emulator = Emulator(emulator_model, scenario, [initial_c + KELVIN])
    result = run_closed_loop(controller, emulator, steps=steps, log_every=log_every,
                             progress=progress, budget_s=budget_s)
    p, c = settings.problem, settings.comfort
    kpis = closed_loop_kpis(result.steps, result.fine, p.step_s, result.wall_s)
    kpis.update(horizon_h=p.horizon_steps * p.step_s / 3600.0, cost=p.cost,
                solver=settings.solver.solver, comfort=c.comfort,
                fallbacks=int(result.steps['fallback'].sum()))
    if c.soft:
        kpis['soft_penalty'] = c.soft_penalty
    return result, kpis


#: Controller settings offered as options of the case command.
CASE_SETTINGS = ('horizon_steps', 'cost', 'comfort', 'soft_penalty', 'solver', 'mode',
                 'relaxation', 'solver_max_iter', 'time_budget_s', 'on_failure')


def option_problems(args: argparse.Namespace,
                    scenario_steps: int | None = None) -> tuple[MpcSettings | None, list[str]]:
    """
    Return the controller settings of parsed options, and every problem of the options.

    All problems at once: settings, FMU tolerance, hours, and a horizon longer than the forecasts.
    """
    problems = ModelSettings(fmu_tolerance=args.tolerance).problems()
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


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """
    Build the command line of the case.

    It fills ``parser`` (e.g. the ``case`` verb of ``mshoot``), or a new parser when None.
    """
    if parser is None:
        parser = argparse.ArgumentParser(
            prog='python -m mshoot_studies.case', description=__doc__,
            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('scenario', choices=('ou44', 'synthetic'),
                        help='ou44: the reference case (needs --data); synthetic: built-in')
    parser.add_argument('--data', type=pathlib.Path, default=None,
                        help=f'OU44 measurements.csv (default: {DEFAULT_DATA.resolve()} '
                             'if it exists)')
    parser.add_argument('--control', choices=CONTROL_MODELS, default='python',
                        help='control model: exact Python R1C1, R1C1 FMU (Model Exchange '
                             'or Co-Simulation), or a scikit-learn model trained on R1C1 '
                             'responses as in Setup 2 (svr is Setup 2; default python)')
    parser.add_argument('--emulator', choices=BUILTIN, default='python',
                        help='emulation model (default python: the exact R1C1; FMUs run at '
                             f'tolerance {EMULATOR_TOLERANCE:g})')
    parser.add_argument('--tolerance', type=float, default=CONTROL_TOLERANCE,
                        help='relative tolerance of the control FMU integrator, in [1e-14, '
                             f'1e-2] (default {CONTROL_TOLERANCE:g})')
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
    """Run the case as parsed by :func:`build_parser`; 0, or 2 on bad input (logged)."""
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format='%(asctime)s %(levelname)s %(name)s: %(message)s')
    settings, problems = option_problems(args)
    if problems:
        logger.error('invalid options: %s', '; '.join(problems))
        return 2
    data = args.data
    if data is None and DEFAULT_DATA.is_file():
        data = DEFAULT_DATA.resolve()
    try:
        scenario = reference_scenario(args.scenario, data, args.hours)
        settings, problems = option_problems(args, len(scenario) - 1)
        if problems:
            raise ValueError(f"invalid options: {'; '.join(problems)}")
        started = time.perf_counter()
        report: dict = {}
        control = control_model(args.control, args.tolerance, data, report)
        emulator = build_model(args.emulator, EMULATOR_TOLERANCE)
        setup_s = time.perf_counter() - started
    except (FileNotFoundError, ValueError) as exc:
        logger.error('%s', exc)
        return 2
    horizon = settings.problem.horizon_steps
    logger.info('running %s: %d h, horizon %d h, control %s, cost %s, comfort %s',
                args.scenario, args.hours, horizon, args.control, args.cost, args.comfort)
    result, kpis = run_case(scenario, control, emulator, settings)
    kpis.update(scenario=args.scenario, control=args.control, emulator=args.emulator,
                tolerance=args.tolerance, mode=args.mode, setup_s=setup_s)
    if report:
        kpis['training'] = report
    if args.scenario == 'ou44' and args.hours == 72 and horizon in PUBLISHED:
        kpis['published'] = PUBLISHED[horizon]
    write_outputs(args.out, result, kpis, f'{args.scenario}: H = {horizon} h, control '
                                          f'{args.control}, {args.cost} cost')
    logger.info('energy %.2f kWh (heating %.2f, cooling %.2f), discomfort %.2f Kh (hourly '
                'samples %.2f Kh), wall %.2f s, median solve %.4f s, %d solver failures',
                kpis['energy_kwh'], kpis['heating_kwh'], kpis['cooling_kwh'],
                kpis['discomfort_kh'], kpis['discomfort_kh_hourly'], kpis['wall_s'],
                kpis['solve_s_median'], kpis['solver_failures'])
    logger.info('wrote %s', args.out / 'kpis.json')
    return 0


if __name__ == '__main__':
    sys.exit(main())
