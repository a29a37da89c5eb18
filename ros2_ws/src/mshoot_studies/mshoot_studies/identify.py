"""
Identify a control model from a plant: an excitation experiment, then a calibration.

    mshoot identify --plant PLANT.yaml --model MODEL.yaml --out out/identify
    mshoot identify --plant setpoint_zone_plant.yaml --model setpoint_zone_model.yaml \
        --days 21 --seed 1 --out out/identify

The plant (``--plant``: a model card of the building, e.g. an FMU with its overwrites) is run
for ``--days`` through a scenario (``--data CSV``: a data CSV with a column per series, see
``mshoot case --help``; default the built-in synthetic weather and occupancy) with its
controls held at random levels within their card limits (``--level NAME=LO,HI`` narrows them,
in the control's canonical unit) for 1 to 8 control steps each (``--hold``). The model card
(``--model``: a thermal network card, ``network`` section, its parameters marked
``free: true`` with ``min`` and ``max``) is then fitted to the zone temperatures of the first
part of the records by least squares (analytic Jacobian; mshoot_core.calibration) and scored
on the held-out rest (``--validation-share``): per zone the RMSE of a free run and of one
control step ahead. The model's inputs must be disturbances of the scenario or controls of
the plant (by name), its zones (``T``, ``T_<zone>``) states of the plant too.

Writes to ``--out``: ``<model>_identified.yaml`` (the model card with the fitted values, for
``mshoot case --control`` or the MPC node's ``model``), ``identification.json`` (the fitted
parameters with 95 % intervals, warnings, the validation RMSEs), ``excitation.csv`` (the
records: inputs per step, the plant's states at the steps' starts) and ``identification.png``
(the held-out zone temperature: the plant, the free run, one step ahead).

Exit codes: 0 done; 2 bad options or cards (one line saying what and why); 1 the plant
failed during the excitation.
"""
from __future__ import annotations

import argparse
import json
import logging
import pathlib
from typing import Sequence

from mshoot_core import identification as ident
from mshoot_core.models.base import ModelValueError
import pandas as pd

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
    """
    if parser is None:
        parser = argparse.ArgumentParser(prog='python -m mshoot_studies.identify',
                                         description=__doc__,
                                         formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--plant', type=pathlib.Path, required=True, metavar='CARD',
                        help='model card of the plant excited (e.g. an FMU with overwrites)')
    parser.add_argument('--model', type=pathlib.Path, required=True, metavar='CARD',
                        help='thermal network card calibrated (its free parameters)')
    parser.add_argument('--out', type=pathlib.Path, required=True, help='output folder')
    parser.add_argument('--data', type=pathlib.Path, default=None, metavar='CSV',
                        help='scenario data CSV (a column per series; default the built-in '
                             'synthetic scenario)')
    parser.add_argument('--days', type=float, default=21.0,
                        help='length of the excitation [days] (default 21)')
    parser.add_argument('--step', type=float, default=3600.0,
                        help='control step of the excitation and the model [s] (default 3600)')
    parser.add_argument('--seed', type=int, default=0,
                        help='seed of the random levels (and of the synthetic weather)')
    parser.add_argument('--hold', type=_pair, default=(1, 8), metavar='MIN,MAX',
                        help='steps each level is held, fewest and most (default 1,8)')
    parser.add_argument('--level', type=_level, action='append', default=[],
                        metavar='NAME=LO,HI',
                        help='range of the levels of a control (default its card limits); '
                             'repeatable')
    parser.add_argument('--validation-share', type=float, default=0.3,
                        help='share of the records held out at the end (default 0.3)')
    parser.add_argument('--settle', type=int, default=12,
                        help='steps at the start of each period not fitted nor scored, while '
                             'the unmeasured states settle (default 12)')
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
    plant = None
    try:
        hold = tuple(int(v) for v in args.hold)
        if hold != tuple(args.hold):
            raise ValueError(f'--hold takes whole steps, got {args.hold}')
        if not args.days * 86400.0 >= 4 * args.step:
            raise ValueError(f'--days {args.days:g} is too short for steps of {args.step:g} s')
        excitation = ident.Excitation(seed=args.seed, hold_steps=hold,
                                      levels=dict(args.level) or None)
        model_card = cards.load_card(args.model)
        if model_card.network is None:
            raise ValueError(f'--model {args.model}: not a thermal network card (no network '
                             'section): mshoot identify calibrates network parameters')
        plant_card = cards.load_card(args.plant)
        steps = int(round(args.days * 86400.0 / args.step))
        scenario = _scenario(args.data, steps, args.step, args.seed)
        plant = cards.build_model(plant_card, role='emulator')
        bounds = ident.control_limits(plant_card)
    except (FileNotFoundError, ValueError) as exc:
        logger.error('%s', ' '.join(str(exc).split()))
        if plant is not None and hasattr(plant, 'close'):
            plant.close()
        return 2
    try:
        logger.info('exciting %s for %g days (%d steps of %g s), seed %d', args.plant.name,
                    args.days, steps, args.step, args.seed)
        table = ident.excite(plant, scenario, excitation, control_names=plant_card.control_names,
                             control_bounds=bounds, step_s=args.step)
    except ValueError as exc:
        logger.error('%s', ' '.join(str(exc).split()))
        return 1 if isinstance(exc, ModelValueError) else 2
    finally:
        if hasattr(plant, 'close'):
            plant.close()
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / RECORDS, index_label='time_s')
    try:
        result = ident.identify(model_card, table, args.validation_share, args.settle,
                                args.starts)
    except ValueError as exc:
        logger.error('%s', ' '.join(str(exc).split()))
        return 2
    card_path = args.out / f'{args.model.stem}_identified.yaml'
    ident.write_card(model_card, result, card_path,
                     f' from {args.plant.name} ({args.days:g} days, seed {args.seed})')
    report = {'plant': str(args.plant), 'model': str(args.model), 'days': args.days,
              'step_s': args.step, 'seed': args.seed, 'card': str(card_path),
              **result.to_dict()}
    (args.out / REPORT).write_text(json.dumps(report, indent=2, default=float) + '\n')
    _figure(args.out / FIGURE, result, table)
    for zone, score in result.validation.items():
        logger.info('zone %s: validation RMSE free run %.3f K, one step ahead %.3f K (%d steps)',
                    zone, score['free_run_rmse_k'], score['one_step_rmse_k'], score['rows'])
    for warning in result.result.warnings:
        logger.warning('fit: %s', warning)
    logger.info('wrote %s, %s, %s, %s', card_path, args.out / REPORT, args.out / RECORDS,
                args.out / FIGURE)
    return 0


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
        name = 'validation' if len(zones) == 1 else f'validation_{zone}'
        simulated = result.result.simulated[name]
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
