"""The reference case (OU44 classroom, SPEC section 3) as a command.

    mshoot case ou44 --data PATH --horizon 10 --control fmu --tolerance 1e-6 \\
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
from typing import Sequence

import pandas as pd

from mshoot_core.closed_loop import ClosedLoopResult, run_closed_loop
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models.base import Model
from mshoot_core.models.r1c1 import KELVIN, R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.outputs import write_outputs
from mshoot_core.scenario import DEFAULT_DATA, PUBLISHED, reference_scenario
from mshoot_core.solvers import SOLVERS

logger = logging.getLogger(__name__)

#: Data-driven control models (scikit-learn estimators trained as in Setup 2).
DATA_DRIVEN = ('svr', 'linear', 'ridge', 'knn', 'random_forest', 'mlp')
CONTROL_MODELS = ('python', 'fmu', 'fmu-cs') + DATA_DRIVEN


def r1c1_fmu_model(tolerance: float = 1e-6, fmi_type: str = 'ModelExchange') -> Model:
    """The built-in R1C1 FMU (built with gcc on first use) as a control or emulation model,
    with the names of :class:`R1C1Model`."""
    from mshoot_core.models.fmi import r1c1_fmi_model
    return r1c1_fmi_model(fmi_type=fmi_type, tolerance=tolerance)


def control_model(kind: str, tolerance: float = 1e-6, data: str | pathlib.Path | None = None,
                  report: dict | None = None) -> Model:
    """Build the control model of the case.

    Parameters
    ----------
    kind : {'python', 'fmu', 'fmu-cs', 'svr', 'linear', 'ridge', 'knn', 'random_forest', 'mlp'}
        The exact Python R1C1, the R1C1 FMU (Model Exchange at ``tolerance``,
        or Co-Simulation), or a scikit-learn model trained as in Setup 2 (SVR is
        Setup 2 itself; needs ``data``).
    report : dict, optional
        Filled with the training/validation report of data-driven models.
    """
    if kind == 'python':
        return R1C1Model()
    if kind == 'fmu':
        return r1c1_fmu_model(tolerance, 'ModelExchange')
    if kind == 'fmu-cs':
        return r1c1_fmu_model(tolerance, 'CoSimulation')
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
    raise ValueError(f'unknown control model {kind!r}; choose one of {list(CONTROL_MODELS)}')


def run_case(scenario: pd.DataFrame, control: Model, emulator_model: Model, *,
             horizon: int = 10, cost: str = 'quadratic', solver: str = 'slsqp',
             comfort: str = 'hard', soft_penalty: float = 1e3, initial_c: float = 20.0,
             mode: str = 'fast', steps: int | None = None, log_every: int = 12,
             **loop_options) -> tuple[ClosedLoopResult, dict]:
    """Run the MPC emulation of a scenario and return the records and the KPIs.

    ``mode`` is the MPC's evaluation mode ('fast', or 'naive': the ancestor's
    algorithm); ``loop_options`` go to :func:`run_closed_loop` (``progress``,
    ``budget_s``).
    """
    if comfort not in ('hard', 'soft'):
        raise ValueError(f"comfort must be 'hard' or 'soft', got {comfort!r}")
    mpc = MPC(control, horizon_steps=horizon, cost=cost, solver=solver, comfort=comfort,
              soft_penalty=soft_penalty, mode=mode)
    emulator = Emulator(emulator_model, scenario, [initial_c + KELVIN])
    result = run_closed_loop(mpc, emulator, steps=steps, log_every=log_every, **loop_options)
    kpis = closed_loop_kpis(result.steps, result.fine, mpc.step_s, result.wall_s)
    kpis.update(horizon_h=horizon * mpc.step_s / 3600.0, cost=cost, solver=solver,
                comfort=comfort)
    if comfort == 'soft':
        kpis['soft_penalty'] = soft_penalty
    return result, kpis


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The command line of the case: fills ``parser`` (e.g. the ``case`` verb of ``mshoot``),
    or a new parser when None."""
    if parser is None:
        parser = argparse.ArgumentParser(
            prog='python -m mshoot_studies.case', description=__doc__,
            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('scenario', choices=('ou44', 'synthetic'),
                        help='ou44: the reference case (needs --data); synthetic: built-in')
    parser.add_argument('--data', type=pathlib.Path, default=None,
                        help=f'OU44 measurements.csv (default: {DEFAULT_DATA.resolve()} '
                             'if it exists)')
    parser.add_argument('--horizon', type=int, default=10, help='MPC horizon [h] (default 10)')
    parser.add_argument('--control', choices=CONTROL_MODELS, default='python',
                        help='control model: exact Python R1C1, R1C1 FMU (Model Exchange '
                             'or Co-Simulation), or a scikit-learn model trained on R1C1 '
                             'responses as in Setup 2 (svr is Setup 2; default python)')
    parser.add_argument('--emulator', choices=('python', 'fmu', 'fmu-cs'), default='python',
                        help='emulation model (default python: the exact R1C1)')
    parser.add_argument('--tolerance', type=float, default=1e-6,
                        help='FMU integrator relative tolerance (default 1e-6)')
    parser.add_argument('--cost', choices=('quadratic', 'energy'), default='quadratic',
                        help='quadratic: sum (q/q_nom)^2 (the reference); energy: sum |q| '
                             '(smoothed; converges far faster with --solver ipopt)')
    parser.add_argument('--comfort', choices=('hard', 'soft'), default='hard',
                        help='hard: band as bounds, relaxed where unreachable; soft: slack '
                             'with quadratic penalty (default hard)')
    parser.add_argument('--soft-penalty', type=float, default=1e3,
                        help='penalty weight of soft bounds on normalised slack (default 1e3)')
    parser.add_argument('--solver', choices=sorted(SOLVERS), default='slsqp')
    parser.add_argument('--mode', choices=('fast', 'naive'), default='fast',
                        help='fast: structured, batched sensitivities (default); naive: the '
                             'original MShoot algorithm (dense finite differences, serial '
                             'simulations, no caching; slow: for side-by-side comparison)')
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
    if args.horizon < 1 or args.hours < 1:
        logger.error('--horizon and --hours must be >= 1')
        return 2
    if not args.tolerance > 0:
        logger.error('--tolerance must be > 0, got %s', args.tolerance)
        return 2
    data = args.data
    if data is None and DEFAULT_DATA.is_file():
        data = DEFAULT_DATA.resolve()
    try:
        scenario = reference_scenario(args.scenario, data, args.hours)
        started = time.perf_counter()
        report: dict = {}
        control = control_model(args.control, args.tolerance, data, report)
        emulator = control_model(args.emulator, 1e-10)
        setup_s = time.perf_counter() - started
    except (FileNotFoundError, ValueError) as exc:
        logger.error('%s', exc)
        return 2
    logger.info('running %s: %d h, horizon %d h, control %s, cost %s, comfort %s',
                args.scenario, args.hours, args.horizon, args.control, args.cost, args.comfort)
    result, kpis = run_case(scenario, control, emulator, horizon=args.horizon, cost=args.cost,
                            solver=args.solver, comfort=args.comfort,
                            soft_penalty=args.soft_penalty, mode=args.mode)
    kpis.update(scenario=args.scenario, control=args.control, emulator=args.emulator,
                tolerance=args.tolerance, mode=args.mode, setup_s=setup_s)
    if report:
        kpis['training'] = report
    if args.scenario == 'ou44' and args.hours == 72 and args.horizon in PUBLISHED:
        kpis['published'] = PUBLISHED[args.horizon]
    write_outputs(args.out, result, kpis, f'{args.scenario}: H = {args.horizon} h, control '
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
