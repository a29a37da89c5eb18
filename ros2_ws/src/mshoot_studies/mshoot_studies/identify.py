r"""
Identify a control model from a plant: an excitation experiment, then a calibration.

    mshoot identify --plant PLANT.yaml --model MODEL.yaml --out out/identify
    mshoot identify --plant setpoint_zone_plant.yaml --model setpoint_zone_model.yaml \
        --days 21 --seed 1 --out out/identify
    mshoot identify --testcase DIR --card CARD.yaml --model MODEL.yaml --out out/identify

The plant is a model card of the building (``--plant``: e.g. an FMU with its overwrites), run
for ``--days`` through a scenario (``--data CSV``: a data CSV with a column per series, see
``mshoot case --help``; default the built-in synthetic weather and occupancy), or a BOPTEST
test case folder (``--testcase``) with its card (``--card``, the one ``mshoot boptest`` takes),
run under its own weather from the card's ``boptest.excitation`` section: from ``first_day``
for ``days`` (``--days`` shortens it), after ``lead_days`` under the building's own control,
outside every test period and its warm-up (refused otherwise). Its controls are held at random
levels within their card limits (``--level NAME=LO,HI`` or the section's ``levels`` narrow
them, in the control's canonical unit) for 1 to 8 control steps each (``--hold`` or
``hold_steps``). The model card (``--model``: a thermal network card, ``network`` section,
its parameters marked ``free: true`` with ``min`` and ``max``) is then fitted to the zone
temperatures of the first part of the records by least squares (analytic Jacobian;
mshoot_core.calibration) and scored on the held-out rest (``--validation-share``): per zone
the RMSE of a free run and of one control step ahead. The model's inputs must be disturbances
of the scenario or controls of the plant (by name) -- for a test case: outputs or controls of
its card (step means), or series of the model card's ``testcase_forecast`` section (the test
case's data as the controller's forecast reads it, at the plant's samples; step means) --
its zones (``T``, ``T_<zone>``) states of the plant too. ``--reference CARD`` scores the
parameter values of another card of the same network (e.g. a packaged one) on the same
held-out steps, side by side.

Writes to ``--out``: ``<model>_identified.yaml`` (the model card with the fitted values, for
``mshoot case --control`` or the MPC node's ``model``), ``identification.json`` (the fitted
parameters with 95 % intervals, warnings, the validation RMSEs), ``excitation.csv`` (the
records: inputs per step, the plant's states at the steps' starts) and ``identification.png``
(the held-out zone temperature: the plant, the free run, one step ahead); with
``--testcase``, ``card_<card>.yaml`` (the card pointed at the folder, as ``mshoot boptest``
writes it).

Exit codes: 0 done; 2 bad options or cards (one line saying what and why); 1 the plant
failed during the excitation.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import pathlib
from typing import Callable, Sequence

from mshoot_core import identification as ident
from mshoot_core.models.base import ModelValueError
from mshoot_core.units import json_ready
import pandas as pd

from mshoot_studies.cli import verb_parser

logger = logging.getLogger(__name__)

#: Files written to ``--out`` (the card's name depends on the model card).
REPORT, RECORDS, FIGURE = 'identification.json', 'excitation.csv', 'identification.png'


def _pair(text: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected LO,HI (two numbers), got {text!r}') from None
    return low, high


def _level(text: str) -> tuple[str, tuple[float, float]]:
    name, _, values = text.partition('=')
    if not name or not values:
        raise argparse.ArgumentTypeError(f'expected NAME=LO,HI, got {text!r}')
    return name, _pair(values)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """
    Build the command line of the identification.

    Fills ``parser`` (the ``identify`` verb of ``mshoot``), or a new parser when None.
    Its errors are one line (``<prog>: error: ...``) and exit 2
    (:func:`~mshoot_studies.cli.verb_parser`).
    """
    parser = verb_parser(parser, 'mshoot_studies.identify', __doc__)
    plant = parser.add_mutually_exclusive_group(required=True)
    plant.add_argument('--plant', type=pathlib.Path, metavar='CARD',
                       help='model card of the plant excited (e.g. an FMU with overwrites)')
    plant.add_argument('--testcase', type=pathlib.Path, metavar='DIR',
                       help='BOPTEST test case folder excited (with --card)')
    parser.add_argument('--card', type=pathlib.Path, metavar='CARD',
                        help="the test case's card (controls, outputs, boptest.excitation)")
    parser.add_argument('--model', type=pathlib.Path, required=True, metavar='CARD',
                        help='thermal network card calibrated (its free parameters)')
    parser.add_argument('--out', type=pathlib.Path, required=True, help='output folder')
    parser.add_argument('--data', type=pathlib.Path, default=None, metavar='CSV',
                        help='scenario data CSV (a column per series; default the built-in '
                             'synthetic scenario)')
    parser.add_argument('--days', type=float, default=None,
                        help='length of the excitation [days] (default 21; a test case: its '
                             "card's)")
    parser.add_argument('--step', type=float, default=None,
                        help='control step of the excitation and the model [s] (default 3600; '
                             "a test case: its card's, else its control step)")
    parser.add_argument('--seed', type=int, default=None,
                        help='seed of the random levels (and of the synthetic weather; '
                             "default 0, a test case: its card's)")
    parser.add_argument('--hold', type=_pair, default=None, metavar='MIN,MAX',
                        help='control steps each level is held, fewest and most (default 1,8; a '
                             "test case: its card's)")
    parser.add_argument('--level', type=_level, action='append', default=[],
                        metavar='NAME=LO,HI',
                        help="range of the levels of a control, in the control's canonical unit "
                             '(default its card limits); repeatable')
    parser.add_argument('--validation-share', type=float, default=0.3,
                        help='share of the records held out at the end, in (0, 1) (default 0.3)')
    parser.add_argument('--settle', type=int, default=12,
                        help='control steps at the start of each period not fitted nor scored, '
                             'while the unmeasured states settle (default 12)')
    parser.add_argument('--reference', type=pathlib.Path, default=None, metavar='CARD',
                        help="a network card whose values of the model's parameters are "
                             'scored on the same held-out steps (e.g. a packaged card)')
    parser.add_argument('--starts', type=int, default=1,
                        help='starts of the fit (the first the card values; default 1)')
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process arguments) and run; the exit code."""
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Run the identification parsed by :func:`build_parser`: 0, 2 on bad input, 1 on failure."""
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format='%(asctime)s %(levelname)s %(name)s: %(message)s')
    from mshoot_core.models import card as cards
    try:
        if args.hold is not None and tuple(int(v) for v in args.hold) != tuple(args.hold):
            raise ValueError(f'--hold takes whole steps, got {args.hold}')
        model_card = cards.load_card(args.model)
        if model_card.network is None:
            raise ValueError(f'--model {args.model}: not a thermal network card (no network '
                             'section): mshoot identify calibrates network parameters')
        reference = None
        if args.reference is not None:
            reference_card = cards.load_card(args.reference)
            if reference_card.network is None:
                raise ValueError(f'--reference {args.reference}: not a thermal network card')
            reference = {name: reference_card.network.parameters[name].value
                         for name in model_card.network.parameters
                         if name in reference_card.network.parameters}
        if args.testcase is not None:
            excite, source = _test_case_experiment(args, model_card)
        else:
            if args.card is not None:
                raise ValueError('--card goes with --testcase (--plant is a card itself)')
            excite, source = _plant_experiment(args)
    except (FileNotFoundError, ValueError) as exc:
        logger.error('%s', ' '.join(str(exc).split()))
        return 2
    try:
        table = excite()
    except ValueError as exc:
        logger.error('%s', ' '.join(str(exc).split()))
        return 1 if isinstance(exc, ModelValueError) else 2
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / RECORDS, index_label='time_s')
    try:
        result = ident.identify(model_card, table, args.validation_share, args.settle,
                                args.starts)
        reference_scores = None if reference is None else ident.score(
            model_card, table, reference, args.validation_share, args.settle)
    except ValueError as exc:
        logger.error('%s', ' '.join(str(exc).split()))
        return 2
    card_path = args.out / f'{args.model.stem}_identified.yaml'
    ident.write_card(model_card, result, card_path, source)
    report = {**source_report(args), 'card': str(card_path), **result.to_dict()}
    if reference_scores is not None:
        report['reference'] = {'card': str(args.reference), 'parameters': reference,
                               'validation': reference_scores}
    (args.out / REPORT).write_text(json.dumps(json_ready(report), indent=2) + '\n')
    _figure(args.out / FIGURE, result, table)
    for zone, score in result.validation.items():
        versus = '' if reference_scores is None else (
            f'; {args.reference.name}: {reference_scores[zone]["free_run_rmse_k"]:.3f} K, '
            f'{reference_scores[zone]["one_step_rmse_k"]:.3f} K')
        logger.info('zone %s: validation RMSE free run %.3f K, one step ahead %.3f K (%d steps)'
                    '%s', zone, score['free_run_rmse_k'], score['one_step_rmse_k'],
                    score['rows'], versus)
    for warning in result.result.warnings:
        logger.warning('fit: %s', warning)
    logger.info('wrote %s, %s, %s, %s', card_path, args.out / REPORT, args.out / RECORDS,
                args.out / FIGURE)
    return 0


def source_report(args: argparse.Namespace) -> dict:
    """Return what the report says of the plant and the experiment."""
    return {'plant': str(args.plant or args.testcase), 'testcase_card': str(args.card),
            'model': str(args.model), **args.experiment}


def _plant_experiment(args: argparse.Namespace) -> tuple[Callable[[], pd.DataFrame], str]:
    """Check a plant card's experiment; return the excitation (a call) and its source."""
    from mshoot_core.models import card as cards
    days = 21.0 if args.days is None else args.days
    step_s = 3600.0 if args.step is None else args.step
    seed = 0 if args.seed is None else args.seed
    if not days * 86400.0 >= 4 * step_s:
        raise ValueError(f'--days {days:g} is too short for steps of {step_s:g} s')
    hold = tuple(int(v) for v in (args.hold or (1, 8)))
    excitation = ident.Excitation(seed=seed, hold_steps=hold, levels=dict(args.level) or None)
    plant_card = cards.load_card(args.plant)
    steps = int(round(days * 86400.0 / step_s))
    scenario = _scenario(args.data, steps, step_s, seed)
    bounds = ident.control_limits(plant_card)
    plant = cards.build_model(plant_card, role='emulator')
    args.experiment = {'days': days, 'step_s': step_s, 'seed': seed}

    def excite() -> pd.DataFrame:
        try:
            logger.info('exciting %s for %g days (%d steps of %g s), seed %d', args.plant.name,
                        days, steps, step_s, seed)
            return ident.excite(plant, scenario, excitation,
                                control_names=plant_card.control_names,
                                control_bounds=bounds, step_s=step_s)
        finally:
            if hasattr(plant, 'close'):
                plant.close()
    return excite, f' from {args.plant.name} ({days:g} days, seed {seed})'


def _test_case_experiment(args: argparse.Namespace,
                          model_card: object) -> tuple[Callable[[], pd.DataFrame], str]:
    """Check a test case's experiment; return the excitation (a call) and its source."""
    from mshoot_core.boptest.testcase import TestCase
    from mshoot_core.models import card as cards
    if args.card is None:
        raise ValueError('--testcase needs --card (the test case card: controls, outputs, '
                         'boptest.excitation)')
    if args.data is not None:
        raise ValueError('--data goes with --plant (a test case brings its own weather)')
    from mshoot_studies.boptest import prepare_card
    case = TestCase.load(args.testcase)
    card = cards.load_card(prepare_card(args.card, args.testcase, args.out))  # the folder's
    if card.boptest is None:
        raise ValueError(f'--card {args.card}: not a BOPTEST card (no boptest section)')
    changes = {k: v for k, v in (('days', args.days), ('step_s', args.step),
                                 ('seed', args.seed)) if v is not None}
    experiment = ident.TestCaseExperiment.from_card(card, case.control_step_s, **changes)
    if args.hold is not None or args.level:
        experiment = dataclasses.replace(experiment, excitation=dataclasses.replace(
            experiment.excitation,
            hold_steps=tuple(int(v) for v in (args.hold or experiment.excitation.hold_steps)),
            levels=dict(args.level) or experiment.excitation.levels))
    ident.check_outside_test_periods(case, card, experiment)
    args.experiment = {'first_day': experiment.first_day, 'days': experiment.days,
                       'lead_days': experiment.lead_days, 'step_s': experiment.step_s,
                       'seed': experiment.excitation.seed,
                       'hold_steps': list(experiment.excitation.hold_steps),
                       'levels': experiment.excitation.levels}

    def excite() -> pd.DataFrame:
        logger.info('exciting %s from day %g for %g days (%d steps of %g s), seed %d',
                    case.name, experiment.first_day, experiment.days, experiment.steps,
                    experiment.step_s, experiment.excitation.seed)
        records = ident.excite_test_case(case, card, experiment)
        return ident.step_table(records, case, card, model_card, experiment)
    return excite, (f' from {case.name} (days {experiment.first_day:g} to '
                    f'{experiment.end_s / 86400.0:g}, seed {experiment.excitation.seed})')


def _scenario(data: pathlib.Path | None, steps: int, step_s: float, seed: int) -> pd.DataFrame:
    """Return the excitation's scenario: ``steps + 1`` rows ``step_s`` apart."""
    from mshoot_core import scenario as scenarios
    if data is None:
        return scenarios.synthetic_scenario(hours=steps + 1, seed=seed, step_s=step_s)
    table = scenarios.read_data_csv(data, step_s=step_s)
    if len(table) < steps + 1:
        raise ValueError(f'--data {data}: {len(table)} rows of {step_s:g} s, the excitation '
                         f'needs {steps + 1}: shorten --days')
    return table.iloc[:steps + 1]


def _figure(path: pathlib.Path, result: ident.Identification,
            table: pd.DataFrame) -> None:
    """Draw the held-out zone temperatures: plant, free run, one step ahead."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    zones = list(result.validation)
    fig, axes = plt.subplots(len(zones), 1, figsize=(9, 3.2 * len(zones)), squeeze=False)
    for ax, zone in zip(axes[:, 0], zones):
        simulated = result.free_run[zone]
        hours = (table.index[result.train_rows - 1:] - table.index[0]) / 3600.0
        measured = table[zone].to_numpy(float)[result.train_rows - 1:] - ident.KELVIN
        ax.plot(hours, measured, 'k-', lw=1.2, label='plant')
        ax.plot(hours, simulated, 'C0-', lw=1.0,
                label=f'free run (RMSE {result.validation[zone]["free_run_rmse_k"]:.2f} K)')
        ax.plot(hours[1:], result.one_step[zone], 'C1.', ms=3,
                label=f'one step ahead (RMSE {result.validation[zone]["one_step_rmse_k"]:.2f} K)')
        ax.set_ylabel(f'{zone} [degC]')
        ax.legend(loc='best', fontsize=8)
    axes[-1, 0].set_xlabel('time since the excitation started [h]')
    fig.suptitle('held-out data: the plant and the identified model')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == '__main__':
    from mshoot_studies.cli import exit_now
    exit_now(main())
