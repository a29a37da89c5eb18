"""
Calibrate the R1C1 zone model on measured data: the OU44 reference calibration.

    mshoot calibrate ou44 --data ../shared/data/ou44/measurements.csv --out out/calibration

The defaults reproduce the reference study's setup: the R1C1 with the measured
inputs solrad, Tout, occ, dpos and the radiator valve vpos (q = 2689 W *
vpos / 100); free tmass, shgc, occheff and RExt within the study's own
estimation bounds (tmass 1-50, shgc 0-10, occheff 0.5-3, RExt 0.5-4: prior
knowledge, ``--bounds wide`` for 1-250, 0-20, 0-10, 0.1-40); Tve = 21 degC,
Vi = 486.5 m3 and maxVent = 4800 m3/h fixed; training 2018-04-04 08:00 to
2018-04-09 08:00, validation 2018-04-09 08:00 to 2018-04-13 08:00; inputs
held over each 30-minute row; each period simulated freely from the measured
temperature at its first row. Least squares within the bounds with the
analytic Jacobian of the R1C1 (:mod:`mshoot_core.calibration`); with the
study's bounds the least-squares optimum within the wide bounds is fitted
too and reported next to it (``comparison``).

Writes to ``--out``: ``calibration.json`` (the fitted parameters with
approximate 95 % confidence intervals, RMSE and MAE per period next to those
of the published parameters computed the same way, warnings, wall time),
``r1c1_calibrated.yaml`` (a model card of the Python R1C1 with the fitted
parameters, for ``mshoot case --control``) and ``calibration.png`` (measured
vs simulated over both periods). ``--cv-folds N`` adds a blocked
cross-validation inside the training period (no validation data).

``--model r2c2`` calibrates the Python R2C2 instead (air and envelope nodes,
analytic Jacobian; free by default Cair, Cwall, Raw, Rwa, Rwin, shgc, fsun,
occheff within :data:`R2C2_BOUNDS`, Tve and maxVent fixed as above): only the
air temperature is compared, the envelope starts at the measured air
temperature of each period's first row; writes ``r2c2_calibrated.yaml``.

``--learned NAME`` fits a learned (scikit-learn) zone model instead, one of
the built-in estimators (:data:`~mshoot_core.models.sklearn_model.ESTIMATOR_FACTORIES`),
on the same periods and scored the same way
(:func:`mshoot_core.calibration.fit_learned`): the regressor learns the
temperature increment over one 30-minute row on the training rows, then each
period is simulated freely from its first measured temperature. The report
describes the regressor in place of parameters (no confidence intervals) and
adds the R1C1 calibrated with the default setup under ``comparison``; the
figure shows the learned model, the published and the calibrated R1C1. No
card is written: model cards describe physical models (an FMU or a built-in
R1C1/R2C2), not fitted regressors. The options of the least-squares fit
(``--model``, ``--free``, ``--bounds``, ``--bound``, ``--prior``,
``--starts``, ``--loss``, ``--f-scale``, ``--jac``, ``--cv-folds``,
``--no-compare``) do not apply and are refused.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import pathlib
import time
from typing import Any, Sequence

from mshoot_core import calibration
from mshoot_core.models import card as cards
from mshoot_core.models.r1c1 import OCC_HEAT_W, R1C1Parameters
from mshoot_core.models.r2c2 import R2C2Parameters
from mshoot_core.models.sklearn_model import ESTIMATOR_FACTORIES
from mshoot_core.scenario import DEFAULT_DATA
import numpy as np
import yaml

from mshoot_studies.cli import verb_parser

logger = logging.getLogger(__name__)

#: Wide bounds of every R1C1 parameter that may be freed (``--bounds wide``).
BOUNDS = {'tmass': (1.0, 250.0), 'shgc': (0.0, 20.0), 'occheff': (0.0, 10.0),
          'RExt': (0.1, 40.0), 'Tve': (10.0, 30.0), 'Vi': (50.0, 5000.0),
          'maxVent': (0.0, 20000.0)}
#: Bounds of every R2C2 parameter that may be freed (``--model r2c2``; no study bounds).
R2C2_BOUNDS = {'Cair': (1.0e5, 1.0e8), 'Cwall': (1.0e6, 1.0e9), 'Raw': (1.0e-4, 0.1),
               'Rwa': (1.0e-3, 1.0), 'Rwin': (1.0e-3, 1.0), 'shgc': (0.0, 20.0),
               'fsun': (0.0, 1.0), 'occheff': (0.0, 10.0), 'Tve': (10.0, 30.0),
               'maxVent': (0.0, 20000.0)}
#: R2C2 parameters freed by default.
R2C2_FREE = ('Cair', 'Cwall', 'Raw', 'Rwa', 'Rwin', 'shgc', 'fsun', 'occheff')
#: Bounds by ``--bounds`` choice: the study's own (the default) or the wide ones.
BOUND_SETS = {'study': {**BOUNDS, **calibration.OU44_STUDY_BOUNDS}, 'wide': BOUNDS}
#: What calibration.json says of each choice of bounds.
BOUND_SOURCES = {
    'study': "the reference study's own estimation bounds (original MShoot "
             'examples/bs2019/case1/case1_est.py: tmass 1-50, shgc 0-10, occheff 0.5-3, '
             'RExt 0.5-4), used as prior knowledge: they were set before, and not fitted to, '
             'these data; the published parameters are the bounded least-squares optimum of the '
             "study's own setup within them",
    'wide': 'wide bounds (tmass 1-250, shgc 0-20, occheff 0-10, RExt 0.1-40): no prior '
            'knowledge beyond physical signs'}
#: Parameters freed by default (the study's).
FREE = ('tmass', 'shgc', 'occheff', 'RExt')
#: The published (calibrated) parameters of the reference case.
PUBLISHED = dataclasses.asdict(R1C1Parameters())
#: Default parameters of the Python R2C2 (its start values), Tve and maxVent the OU44's.
R2C2_DEFAULTS = {**dataclasses.asdict(R2C2Parameters()), 'Tve': calibration.OU44_FIXED['Tve'],
                 'maxVent': calibration.OU44_FIXED['maxVent']}
#: Floor area of the OU44 classroom [m2] (the data's README; the study's Vi = 139 m2 * 3.5 m).
FLOOR_AREA_M2 = 139.0
#: Files written to ``--out``.
JSON_NAME = 'calibration.json'
CARD_NAME = 'r1c1_calibrated.yaml'
R2C2_CARD_NAME = 'r2c2_calibrated.yaml'
FIGURE_NAME = 'calibration.png'
#: Why ``--learned`` writes no card.
NO_CARD = ('no model card: cards describe physical models (an FMU or the built-in R1C1, R1C1 '
           'FMU or R2C2), and this project has no card format for a fitted regressor')
#: Options of the least-squares fit, refused with ``--learned`` (destination -> option).
FIT_OPTIONS = {'model': '--model', 'free': '--free', 'bounds': '--bounds', 'bound': '--bound',
               'prior': '--prior', 'starts': '--starts', 'loss': '--loss',
               'f_scale': '--f-scale', 'jac': '--jac', 'cv_folds': '--cv-folds',
               'no_compare': '--no-compare'}


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """
    Build the command line of the calibration.

    Fills ``parser`` (the ``calibrate`` verb of ``mshoot``), or a new parser when None.
    Its errors are one line (``<prog>: error: ...``) and exit 2
    (:func:`~mshoot_studies.cli.verb_parser`).
    """
    parser = verb_parser(parser, 'mshoot_studies.calibrate', __doc__)
    parser.add_argument('case', choices=['ou44'], help='the measured building (ou44)')
    parser.add_argument('--data', type=pathlib.Path, default=None,
                        help=f'the OU44 measurements.csv (default: {DEFAULT_DATA})')
    parser.add_argument('--out', type=pathlib.Path, default=pathlib.Path('out/calibration'),
                        help='output folder (default: out/calibration)')
    parser.add_argument('--train', nargs=2, metavar=('START', 'END'),
                        default=list(calibration.OU44_TRAIN),
                        help='training period, inclusive: local times of the data, '
                             'YYYY-MM-DD HH:MM (default: %(default)s)')
    parser.add_argument('--validation', nargs=2, metavar=('START', 'END'),
                        default=list(calibration.OU44_VALIDATION),
                        help='validation period, inclusive, as --train (default: %(default)s)')
    parser.add_argument('--model', type=pathlib.Path, default=None, metavar='CARD',
                        help='model card of the model to calibrate (e.g. the built-in R1C1 FMU '
                             "card), or 'r2c2' (the Python R2C2); default: the Python R1C1")
    parser.add_argument('--free', default=None,
                        help='comma-separated parameters to fit, from '
                             f'{list(BOUNDS)} (default: {",".join(FREE)}; R2C2: from '
                             f'{list(R2C2_BOUNDS)}, default {",".join(R2C2_FREE)}); the '
                             'others are fixed at their published (R2C2: default) values')
    parser.add_argument('--bounds', choices=sorted(BOUND_SETS), default='study',
                        help="default bounds: the reference study's (prior knowledge; tmass "
                             '1:50, shgc 0:10, occheff 0.5:3, RExt 0.5:4) or wide ones (tmass '
                             '1:250, shgc 0:20, occheff 0:10, RExt 0.1:40) (default: '
                             '%(default)s)')
    parser.add_argument('--bound', action='append', default=[], metavar='NAME=LO:HI',
                        help='bounds of a free parameter over --bounds, in its unit (repeatable; '
                             'others: '
                             + ', '.join(f'{k} {lo:g}:{hi:g}' for k, (lo, hi) in BOUNDS.items()
                                         if k not in calibration.OU44_STUDY_BOUNDS)
                             + ')')
    parser.add_argument('--prior', action='append', default=[], metavar='NAME=MEAN:SD',
                        help='Gaussian prior on a free parameter, in its unit (repeatable; '
                             'default: none)')
    parser.add_argument('--starts', type=int, default=1,
                        help='number of starts: the published values, then random points '
                             'within the bounds (default: 1)')
    parser.add_argument('--seed', type=int, default=0,
                        help='seed of the random starts (default: %(default)s)')
    parser.add_argument('--loss', choices=calibration.LOSSES, default='linear',
                        help='fit criterion: least squares or a robust loss of '
                             'scipy.optimize.least_squares (default: %(default)s)')
    parser.add_argument('--f-scale', type=float, default=1.0,
                        help='residual [K] beyond which a robust loss weighs less '
                             '(default: %(default)s)')
    parser.add_argument('--jac', choices=calibration.JACOBIANS, default='auto',
                        help='Jacobian of the residuals: analytic where the model has '
                             "parameter sensitivities, else finite differences ('auto'), or "
                             'forced (default: %(default)s)')
    parser.add_argument('--cv-folds', type=int, default=0,
                        help='blocked cross-validation inside the training period with this '
                             'many folds (0: none; default: %(default)s)')
    parser.add_argument('--no-compare', action='store_true',
                        help='with the study bounds, skip the comparison fit within the wide '
                             'bounds')
    parser.add_argument('--learned', default=None, metavar='NAME',
                        help='fit a learned (scikit-learn) zone model instead, one of '
                             f'{", ".join(ESTIMATOR_FACTORIES)}: it learns the temperature '
                             'increment over one row on the training rows and is scored by the '
                             'same free simulation; the least-squares options do not apply '
                             '(--seed seeds random_forest and mlp)')
    parser.add_argument('--max-heat', type=float, default=calibration.OU44_MAX_HEAT_W,
                        help='radiator power at a fully open valve [W] (default: %(default)s)')
    parser.add_argument('--no-figure', action='store_true', help='skip the figure')
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    return parser


def _pair(text: str, option: str) -> tuple[str, float, float]:
    """Parse ``NAME=A:B``."""
    name, sep, rest = text.partition('=')
    first, sep2, second = rest.partition(':')
    try:
        if not (sep and sep2):
            raise ValueError
        return name.strip(), float(first), float(second)
    except ValueError:
        raise ValueError(f'{option} {text!r}: expected NAME=A:B with numbers A and B') from None


def free_parameters(args: argparse.Namespace,
                    structure: str = 'r1c1') -> list[calibration.FreeParameter]:
    """
    Return the free parameters of the command line (names, bounds, priors).

    ``structure`` is 'r1c1' (the R1C1's parameters, :data:`BOUND_SETS`) or
    'r2c2' (the R2C2's, :data:`R2C2_BOUNDS`, started at their defaults).

    Raises
    ------
    ValueError
        For an unknown or repeated name, bad bounds or priors.

    """
    r2c2 = structure == 'r2c2'
    table = R2C2_BOUNDS if r2c2 else BOUND_SETS[getattr(args, 'bounds', 'wide')]
    text = args.free if args.free is not None else ','.join(R2C2_FREE if r2c2 else FREE)
    names = [n.strip() for n in text.split(',') if n.strip()]
    unknown = [n for n in names if n not in table]
    if not names or unknown:
        raise ValueError(f'--free {text!r}: expected names from {list(table)}')
    if len(set(names)) != len(names):
        raise ValueError(f'--free {text!r}: a parameter is named twice')
    starts = R2C2_DEFAULTS if r2c2 else PUBLISHED
    bounds = {n: table[n] for n in names}
    for text in args.bound:
        name, lo, hi = _pair(text, '--bound')
        if name not in bounds:
            raise ValueError(f'--bound {text!r}: {name!r} is not a free parameter ({names})')
        bounds[name] = (lo, hi)
    priors: dict[str, tuple[float, float]] = {}
    for text in args.prior:
        name, mean, sd = _pair(text, '--prior')
        if name not in bounds:
            raise ValueError(f'--prior {text!r}: {name!r} is not a free parameter ({names})')
        priors[name] = (mean, sd)
    free = []
    for name, (lo, hi) in bounds.items():
        start = min(max(starts[name], lo), hi) if lo < hi else starts[name]
        mean, sd = priors.get(name, (None, None))
        free.append(calibration.FreeParameter(name, start, lo, hi, mean, sd))
    return free


def physical(parameters: dict[str, float]) -> dict[str, float]:
    """
    Return the physical quantities of R1C1 parameters, to judge their plausibility.

    ``capacity_kj_m2k``: heat capacity per floor area [kJ/(m2 K)] (EN ISO
    13790 classes: 80 very light, 110 light, 165 medium, 260 heavy, 370 very
    heavy); ``envelope_ua_w_k``: conductance to the outdoors 1/R [W/K];
    ``occupant_heat_w``: heat per occupant at 20 degC [W]; ``shgc_m2``: the
    solar aperture [m2]; ``envelope_time_constant_h``: C R [h].
    """
    values = R1C1Parameters(**{k: v for k, v in {**PUBLISHED, **parameters}.items()
                               if k in PUBLISHED})
    capacity = values.capacity_j_k
    return {'capacity_mj_k': capacity / 1e6,
            'capacity_kj_m2k': capacity / FLOOR_AREA_M2 / 1e3,
            'envelope_ua_w_k': 1.0 / values.resistance_k_w,
            'occupant_heat_w': values.occheff * OCC_HEAT_W,
            'shgc_m2': values.shgc,
            'envelope_time_constant_h': capacity * values.resistance_k_w / 3600.0}


def physical_r2c2(parameters: dict[str, float]) -> dict[str, float]:
    """
    Return the physical quantities of R2C2 parameters, to judge their plausibility.

    ``capacity_kj_m2k``: both capacities per floor area [kJ/(m2 K)];
    ``air_capacity_mj_k``, ``envelope_capacity_mj_k`` [MJ/K];
    ``envelope_ua_w_k``: steady conductance to the outdoors 1/Rwin +
    1/(Raw + Rwa) [W/K]; ``occupant_heat_w`` [W]; ``shgc_m2`` [m2].
    """
    p = R2C2Parameters(**{**R2C2_DEFAULTS, **parameters})
    return {'air_capacity_mj_k': p.Cair / 1e6, 'envelope_capacity_mj_k': p.Cwall / 1e6,
            'capacity_kj_m2k': (p.Cair + p.Cwall) / FLOOR_AREA_M2 / 1e3,
            'envelope_ua_w_k': 1.0 / p.Rwin + 1.0 / (p.Raw + p.Rwa),
            'occupant_heat_w': p.occheff * OCC_HEAT_W, 'shgc_m2': p.shgc}


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process arguments) and run; the exit code."""
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Run the calibration parsed by :func:`build_parser`: 0, or 2 on bad input."""
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format='%(asctime)s %(levelname)s %(name)s: %(message)s')
    started = time.perf_counter()
    data = args.data if args.data is not None else DEFAULT_DATA.resolve()
    try:
        if isinstance(args.starts, bool) or args.starts < 1:
            raise ValueError(f'--starts must be >= 1, got {args.starts}')
        if not (np.isfinite(args.max_heat) and args.max_heat > 0):
            raise ValueError(f'--max-heat must be a positive power [W], got {args.max_heat}')
        if not (np.isfinite(args.f_scale) and args.f_scale > 0):
            raise ValueError(f'--f-scale must be a positive residual [K], got {args.f_scale}')
        if args.cv_folds < 0 or args.cv_folds == 1:
            raise ValueError(f'--cv-folds must be 0 (none) or >= 2, got {args.cv_folds}')
        if args.learned is not None:  # then the setup below is the default R1C1's
            check_learned(args)
        model_arg = args.model
        if model_arg is not None and str(model_arg) == 'r2c2':
            model_arg = cards.builtin_card('r2c2')
        card = None if model_arg is None else cards.load_card(model_arg)
        r2c2 = card is not None and builtin_network(card) == 'r2c2'
        free = free_parameters(args, 'r2c2' if r2c2 else 'r1c1')
        train, validation = calibration.ou44_periods(data, tuple(args.train),
                                                     tuple(args.validation), args.max_heat)
        if r2c2:  # the envelope starts at the measured air temperature
            fixed = {k: v for k, v in {**R2C2_DEFAULTS, **card.parameters}.items()
                     if k not in {p.name for p in free}}
            build = calibration.r2c2_builder(fixed)
            train, validation = (dataclasses.replace(p, x0=np.array([p.x0[0], p.x0[0]]))
                                 for p in (train, validation))
        elif card is None or builtin_network(card) == 'r1c1':
            fixed = {k: v for k, v in PUBLISHED.items() if k not in {p.name for p in free}}
            build = calibration.r1c1_builder(fixed)
        else:
            fixed = {k: v for k, v in card.parameters.items()
                     if k not in {p.name for p in free}}
            build = calibration.card_builder(card)
            build({p.name: p.initial for p in free})  # unknown parameter names fail here
            train, validation = (dataclasses.replace(p, x0=card.initial_state(p.x0[0]))
                                 for p in (train, validation))
        if args.jac == 'analytic' and not hasattr(build({}), 'parameter_sensitivities'):
            raise ValueError('--jac analytic: this model has no parameter sensitivities; use '
                             '--jac auto or fd')
        if args.cv_folds > (len(train.measured) - 1) // 2:
            raise ValueError(f'--cv-folds {args.cv_folds}: the training period has only '
                             f'{len(train.measured) - 1} rows to fold')
    except (ValueError, FileNotFoundError) as error:
        logger.error('%s', ' '.join(str(error).split()))
        return 2
    if args.learned is not None:
        return run_learned(args, data, build, free, [train, validation], started)
    options = {'starts': args.starts, 'seed': args.seed, 'jac': args.jac, 'loss': args.loss,
               'f_scale': args.f_scale}
    result = calibration.calibrate(build, free, [train], [validation], **options)
    published, published_sim = score_published([train, validation])
    comparison, compared_sim = {}, None
    if args.bounds == 'study' and not args.no_compare and not r2c2:
        wide = [dataclasses.replace(p, lower=BOUNDS[p.name][0], upper=BOUNDS[p.name][1])
                for p in free]
        logger.info('comparison: the same fit within the wide bounds')
        other = calibration.calibrate(build, wide, [train], [validation], **options)
        compared_sim = other.simulated
        comparison['wide_bounds'] = {
            'bounds': {p.name: [p.lower, p.upper] for p in wide},
            'parameters': other.parameters, 'physical': physical({**fixed, **other.parameters}),
            'ci95': {k: list(v) for k, v in other.ci95.items()},
            'rmse_train_k': other.metrics['train']['rmse_k'],
            'rmse_validation_k': other.metrics['validation']['rmse_k'],
            'warnings': other.warnings, 'wall_s': other.wall_s}
    cross_validation = None
    if args.cv_folds:
        logger.info('cross-validation inside the training period: %d folds', args.cv_folds)
        cross_validation = {'folds_n': args.cv_folds, **calibration.cross_validate(
            build, free, train, args.cv_folds, **options)}
        if 'wide_bounds' in comparison:
            comparison['wide_bounds']['cross_validation'] = calibration.cross_validate(
                build, wide, train, args.cv_folds, **options)['rmse_k']
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    card_path = write_card(out / (R2C2_CARD_NAME if r2c2 else CARD_NAME),
                           {**fixed, **result.parameters}, result, card)
    figure = None
    if not args.no_figure:
        figure = draw(out / FIGURE_NAME, [train, validation], result.simulated, published_sim,
                      compared_sim, 'calibrated R2C2' if r2c2 else
                      f'calibrated ({args.bounds} bounds)',
                      'R2C2' if r2c2 else 'R1C1')
    overridden = {p.name for p in free} & {_pair(t, '--bound')[0] for t in args.bound}
    report = {
        'case': args.case, 'data': str(data),
        'model': 'python r1c1' if card is None else str(card.path),
        'parameters': result.parameters,
        'physical': (physical_r2c2 if r2c2 else physical)({**fixed, **result.parameters}),
        'fixed': fixed,
        'rmse_train_k': result.metrics['train']['rmse_k'],
        'rmse_validation_k': result.metrics['validation']['rmse_k'],
        'mae_train_k': result.metrics['train']['mae_k'],
        'mae_validation_k': result.metrics['validation']['mae_k'],
        'published': published, 'wall_s': result.wall_s,
        'total_wall_s': None,
        'bounds_source': ('R2C2 bounds of mshoot_studies.calibrate.R2C2_BOUNDS (no study '
                          'bounds for this structure)' if r2c2 else BOUND_SOURCES[args.bounds]) + (
            f'; overridden by --bound for {sorted(overridden)}' if overridden else ''),
        'setup': {'train': list(args.train), 'validation': list(args.validation),
                  'rows': {p.name: len(p.measured) for p in (train, validation)},
                  'max_heat_w': args.max_heat, 'inputs': list(train.inputs.columns),
                  'bounds_choice': args.bounds,
                  'bounds': {p.name: [p.lower, p.upper] for p in free},
                  'priors': {p.name: [p.prior_mean, p.prior_sd] for p in free
                             if p.prior_sd is not None},
                  'starts': args.starts, 'seed': args.seed, 'loss': args.loss,
                  'f_scale_k': args.f_scale,
                  'metric': 'rows 1..N of each period (row 0 is the measured start state)'},
        'comparison': comparison, 'cross_validation': cross_validation,
        'card': str(card_path), 'figure': None if figure is None else str(figure),
        **{k: v for k, v in result.to_dict().items() if k not in ('parameters', 'wall_s')},
    }
    report['total_wall_s'] = time.perf_counter() - started
    (out / JSON_NAME).write_text(json.dumps(report, indent=2, default=_json_default) + '\n')
    logger.info('RMSE train %.4f K (published %.4f K), validation %.4f K (published %.4f K); '
                'fit %.2f s (%s Jacobian), total %.2f s; wrote %s', report['rmse_train_k'],
                published['rmse_train_k'], report['rmse_validation_k'],
                published['rmse_validation_k'], result.wall_s, result.jac,
                report['total_wall_s'], out / JSON_NAME)
    return 0


def score_published(periods: Sequence[calibration.Period]
                    ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """
    Score the published R1C1 parameters on ``periods``, simulated as a calibration simulates.

    Each period is simulated freely from its measured first-row temperature.

    Returns
    -------
    (dict, dict)
        The report's ``published`` entry (parameters, physical quantities,
        ``rmse_<period>_k`` and ``mae_<period>_k`` [K]) and the simulated
        temperature per period [degC].

    """
    model = calibration.r1c1_builder()({})
    published = {'parameters': PUBLISHED, 'physical': physical(PUBLISHED)}
    simulated = {}
    for period in periods:  # the R1C1 from the measured temperature
        simulated[period.name] = calibration.simulate_period(
            model, dataclasses.replace(period, x0=period.x0[:1]))
        scores = calibration.metrics(simulated[period.name], period.measured)
        published[f'rmse_{period.name}_k'] = scores['rmse_k']
        published[f'mae_{period.name}_k'] = scores['mae_k']
    return published, simulated


def check_learned(args: argparse.Namespace) -> None:
    """
    Check ``--learned``: a built-in estimator, none of the least-squares options.

    Raises
    ------
    ValueError
        For an unknown estimator name or an option of :data:`FIT_OPTIONS`
        set to other than its default.

    """
    if args.learned not in ESTIMATOR_FACTORIES:
        raise ValueError(f'--learned {args.learned!r}: expected one of '
                         f'{", ".join(ESTIMATOR_FACTORIES)}')
    defaults = build_parser().parse_args([args.case])
    given = [option for dest, option in FIT_OPTIONS.items()
             if getattr(args, dest) != getattr(defaults, dest)]
    if given:
        raise ValueError(f'--learned {args.learned}: {", ".join(given)} set(s) the least-squares '
                         'fit of a physical model and does not apply to a learned model')


def run_learned(args: argparse.Namespace, data: pathlib.Path, build: calibration.Builder,
                free: Sequence[calibration.FreeParameter],
                periods: Sequence[calibration.Period], started: float) -> int:
    """
    Fit and score the learned model of ``--learned``; write the report and the figure.

    Parameters
    ----------
    args : Namespace
        The command line, checked by :func:`check_learned`.
    data : path
        The measurements read.
    build, free
        The default R1C1 calibration, fitted for the comparison.
    periods : sequence of Period
        ``[train, validation]`` of the R1C1.
    started : float
        ``time.perf_counter()`` at the command's start [s].

    Returns
    -------
    int
        0.

    """
    train, validation = periods
    result = calibration.fit_learned(args.learned, [train], [validation], seed=args.seed)
    published, published_sim = score_published(periods)
    logger.info('comparison: the R1C1 calibrated with the default setup')
    r1c1 = calibration.calibrate(build, free, [train], [validation])
    comparison = {'r1c1_calibrated': {
        'parameters': r1c1.parameters, 'bounds_source': BOUND_SOURCES['study'],
        **{f'{m}_{p}_k': r1c1.metrics[p][f'{m}_k'] for p in ('train', 'validation')
           for m in ('rmse', 'mae')}, 'wall_s': r1c1.wall_s}}
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    figure = None
    if not args.no_figure:
        figure = draw(out / FIGURE_NAME, periods, result.simulated, published_sim,
                      r1c1.simulated, f'learned {args.learned}',
                      f'Learned {args.learned} model', 'calibrated R1C1 (study bounds)')
    report = {
        'case': args.case, 'data': str(data), 'kind': 'learned',
        'model': f'learned {args.learned} (scikit-learn {result.regressor})',
        'parameters': result.parameters,
        **{f'{m}_{p}_k': result.metrics[p][f'{m}_k'] for m in ('rmse', 'mae')
           for p in ('train', 'validation')},
        'published': published, 'comparison': comparison, 'wall_s': result.wall_s,
        'total_wall_s': None, 'fit_s': result.fit_s,
        'uncertainty': calibration.LEARNED_UNCERTAINTY,
        'setup': {'train': list(args.train), 'validation': list(args.validation),
                  'rows': {p.name: len(p.measured) for p in periods},
                  'max_heat_w': args.max_heat, 'inputs': list(train.inputs.columns),
                  'seed': args.seed,
                  'training': 'one-step temperature increments over the rows of the training '
                              'period only, from the measured temperature [K] and the inputs '
                              'held over each row',
                  'metric': 'rows 1..N of each period (row 0 is the measured start state), '
                            'each period simulated freely from it'},
        'metrics': result.metrics, 'warnings': result.warnings,
        'card': None, 'card_note': NO_CARD, 'figure': None if figure is None else str(figure)}
    report['total_wall_s'] = time.perf_counter() - started
    (out / JSON_NAME).write_text(json.dumps(report, indent=2, default=_json_default) + '\n')
    logger.info('learned %s: RMSE train %.4f K (published %.4f K, calibrated R1C1 %.4f K), '
                'validation %.4f K (published %.4f K, calibrated R1C1 %.4f K); fit %.2f s, '
                'total %.2f s; wrote %s', args.learned, report['rmse_train_k'],
                published['rmse_train_k'], comparison['r1c1_calibrated']['rmse_train_k'],
                report['rmse_validation_k'], published['rmse_validation_k'],
                comparison['r1c1_calibrated']['rmse_validation_k'], result.wall_s,
                report['total_wall_s'], out / JSON_NAME)
    return 0


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f'not JSON serialisable: {type(value).__name__}')


def builtin_network(card: cards.ModelCard) -> str | None:
    """Return 'r1c1' or 'r2c2' for a card of a built-in network (by name or the card itself)."""
    if card.builtin in cards.PYTHON_SOURCES:
        return card.builtin
    for name in cards.PYTHON_SOURCES:
        if card.path.resolve() == cards.builtin_card(name).resolve():
            return name
    return None


def write_card(path: pathlib.Path, parameters: dict[str, float],
               result: calibration.CalibrationResult,
               card: cards.ModelCard | None = None) -> pathlib.Path:
    """
    Write the model card of the calibrated model with ``parameters``; check that it loads.

    The card is ``card`` (default: the built-in ``r1c1`` card) with a
    description and the parameters; an FMU it names is referred to by its
    absolute path.
    """
    source = cards.builtin_card('r1c1') if card is None else card.path
    document = yaml.safe_load(source.read_text())
    builtin = 'r1c1' if card is None else builtin_network(card)
    if builtin is not None:  # the built-in network by name, its parameters here
        document = {'builtin': builtin, **{k: v for k, v in document.items()
                                           if k not in ('network', 'builtin')}}
    elif card.builtin is None and card.fmu is not None:
        document['fmu'] = str(card.fmu)
    rmse = result.metrics
    what = 'R1C1 zone' if card is None else document.get('description', 'zone model')
    text = (f'{what}, calibrated by mshoot calibrate (RMSE train '
            f'{rmse["train"]["rmse_k"]:.3f} K, validation {rmse["validation"]["rmse_k"]:.3f} K)'
            if 'validation' in rmse else f'{what}, calibrated by mshoot calibrate')
    ordered = {'description': text}
    ordered.update({k: document[k] for k in ('builtin', 'fmu') if k in document})
    ordered['parameters'] = {k: float(v) for k, v in parameters.items()}
    ordered.update({k: v for k, v in document.items() if k not in ordered})
    path.write_text('# Written by mshoot calibrate.\n'
                    + yaml.safe_dump(ordered, sort_keys=False, default_flow_style=None))
    cards.load_card(path)  # raises CardError if the card does not load
    return path


def draw(path: pathlib.Path, periods: Sequence[calibration.Period],
         simulated: dict[str, np.ndarray], published: dict[str, np.ndarray],
         wide: dict[str, np.ndarray] | None = None,
         label: str = 'calibrated', structure: str = 'R1C1',
         wide_label: str = 'least squares, wide bounds') -> pathlib.Path:
    """Draw measured vs simulated (fitted, published, ``wide``: a third fit) over the periods."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mshoot_core.plotting import DPI, PNG_COMPRESSION
    fig = Figure(figsize=(10, 6))
    FigureCanvasAgg(fig)
    ax_t, ax_e = fig.subplots(2, 1, sharex=True, gridspec_kw={'height_ratios': [3, 2]})
    fig.subplots_adjust(left=0.085, right=0.985, bottom=0.1, top=0.9, hspace=0.07)
    for k, period in enumerate(periods):
        when = period.timestamps if period.timestamps is not None else period.inputs.index
        first = k == 0
        ax_t.plot(when, period.measured, color='k', lw=1.2, label='measured' if first else None)
        ax_t.plot(when, simulated[period.name], color='tab:red', lw=1.4,
                  label=label if first else None)
        ax_t.plot(when, published[period.name], color='tab:blue', lw=1.0, ls='--',
                  label='published R1C1 parameters' if first else None)
        ax_e.plot(when, simulated[period.name] - period.measured, color='tab:red', lw=1.2)
        ax_e.plot(when, published[period.name] - period.measured, color='tab:blue', lw=1.0,
                  ls='--')
        if wide is not None:
            ax_t.plot(when, wide[period.name], color='tab:green', lw=1.0, ls=':',
                      label=wide_label if first else None)
            ax_e.plot(when, wide[period.name] - period.measured, color='tab:green', lw=1.0,
                      ls=':')
        if k > 0:
            for ax in (ax_t, ax_e):
                ax.axvline(when[0], color='grey', lw=1.0, ls=':')
        ax_t.text(when[len(when) // 2], 1.01, period.name, transform=ax_t.get_xaxis_transform(),
                  ha='center', va='bottom')
    ax_t.set_ylabel('zone temperature [°C]')
    ax_t.grid(alpha=0.3)
    ax_t.legend(loc='upper left', framealpha=0.9)
    ax_e.axhline(0.0, color='k', lw=0.5)
    ax_e.set_ylabel('simulated − measured [K]')
    ax_e.grid(alpha=0.3)
    fig.suptitle(f'{structure} calibration: free simulation of each period from its first '
                 'measurement')
    fig.autofmt_xdate()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, pil_kwargs={'compress_level': PNG_COMPRESSION})
    return path


if __name__ == '__main__':
    raise SystemExit(main())
