"""
Calibration variants: the OU44 R1C1 fit under each choice of bounds, priors and criterion.

    python bench/calibration_variants.py [--folds 5] [--starts 20]

Every variant is scored the issue's way (free simulation of each period from
its first measured row, RMSE over rows 1..N) on training and validation, and
by a blocked cross-validation inside the training period (``--folds`` blocks,
each fitted on the other rows): the only score a choice may be made on
without the validation data. The prior strength of the 'physical priors'
variant is chosen by that cross-validation. Also reproduces the study's own
setup (hourly means, a 20 degC start, the study's bounds), whose bounded
least-squares optimum is the published parameters. Writes
out/bench/calibration_variants.json.
"""
from __future__ import annotations

import argparse
import sys
import time

from mshoot_core import calibration
from mshoot_studies.calibrate import BOUNDS, FLOOR_AREA_M2, physical, PUBLISHED
import numpy as np
import pandas as pd

from common import data_path, logger, print_table, setup_logging, write_json

#: tmass of an EN ISO 13790 'medium' zone (165 kJ/(m2 K) of floor) and of its lightest and
#: heaviest classes (80 and 370 kJ/(m2 K)), for the OU44 classroom's air volume.
TMASS_PER_KJ_M2K = FLOOR_AREA_M2 * 1e3 / (1.2 * 1005.0 * PUBLISHED['Vi'])
TMASS_MEDIUM = 165.0 * TMASS_PER_KJ_M2K
TMASS_CLASSES = (80.0 * TMASS_PER_KJ_M2K, 370.0 * TMASS_PER_KJ_M2K)
#: Prior strengths tried (prior sd = strength x prior mean).
STRENGTHS = (0.1, 0.25, 0.5, 1.0, 2.0)


def free_within(bounds: dict, priors: dict | None = None) -> list[calibration.FreeParameter]:
    """Return the OU44 free parameters with ``bounds`` and optional ``priors`` (mean, sd)."""
    out = []
    for p in calibration.OU44_FREE:
        lo, hi = bounds.get(p.name, (p.lower, p.upper))
        mean, sd = (priors or {}).get(p.name, (None, None))
        out.append(calibration.FreeParameter(p.name, min(max(p.initial, lo), hi), lo, hi, mean,
                                             sd))
    return out


def score(name: str, free: list, train: calibration.Period, validation: calibration.Period,
          folds: int, **options) -> dict:
    """Fit, score train/validation and cross-validate one variant."""
    build = calibration.r1c1_builder(calibration.OU44_FIXED)
    result = calibration.calibrate(build, free, [train], [validation], **options)
    cv = calibration.cross_validate(build, free, train, folds, **options)
    fixed = {k: v for k, v in PUBLISHED.items() if k not in result.parameters}
    return {'variant': name, **result.parameters,
            'rmse_train_k': result.metrics['train']['rmse_k'],
            'rmse_validation_k': result.metrics['validation']['rmse_k'],
            'cv_rmse_k': cv['rmse_k'], 'fit_s': result.wall_s,
            'at_bound': [w.split(' ')[0] for w in result.warnings if 'bound' in w],
            'physical': physical({**fixed, **result.parameters}),
            'starts_distinct_costs': len({round(s['cost'], 6) for s in result.starts})}


def study_setup(path: object) -> dict:
    """Fit the study's own setup: hourly means, 5 days from the first row, start at 20 degC."""
    raw = pd.read_csv(path, parse_dates=['datetime']).set_index('datetime')
    hourly = raw.resample('1h').mean().ffill().bfill()
    seconds = (hourly.index - hourly.index[0]).total_seconds().to_numpy()
    keep = seconds <= 5 * 86400
    inputs = pd.DataFrame({'solrad': hourly['solrad'], 'Tout': hourly['Tout'],
                           'occ': hourly['occ'], 'dpos': hourly['dpos'],
                           'q': calibration.OU44_MAX_HEAT_W * hourly['vpos'] / 100.0}
                          ).to_numpy()[keep]
    period = calibration.Period('study', pd.DataFrame(
        inputs, columns=['solrad', 'Tout', 'occ', 'dpos', 'q'],
        index=pd.Index(seconds[keep], name='time_s')), np.array([293.15]),
        hourly['T'].to_numpy()[keep])
    build = calibration.r1c1_builder(calibration.OU44_FIXED)
    # (the study's tool also scored row 0, whose error no parameter changes)
    result = calibration.calibrate(build, calibration.OU44_STUDY_FREE, [period])
    return {'parameters': result.parameters, 'published': {
        k: PUBLISHED[k] for k in result.parameters}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--folds', type=int, default=5)
    parser.add_argument('--starts', type=int, default=20)
    args = parser.parse_args(argv)
    setup_logging()
    started = time.perf_counter()
    train, validation = calibration.ou44_periods(data_path())
    wide = {k: BOUNDS[k] for k in calibration.OU44_STUDY_BOUNDS}
    rows = [score('least squares, wide bounds', free_within(wide), train, validation,
                  args.folds),
            score(f'least squares, wide, {args.starts} starts', free_within(wide), train,
                  validation, args.folds, starts=args.starts)]
    for loss in ('soft_l1', 'huber', 'cauchy'):
        rows.append(score(f'{loss} (f_scale 0.3 K), wide', free_within(wide), train,
                          validation, args.folds, loss=loss, f_scale=0.3))
    priors = []
    for strength in STRENGTHS:
        prior = {'tmass': (TMASS_MEDIUM, strength * TMASS_MEDIUM), 'occheff': (1.0, strength)}
        priors.append(score(f'physical priors, sd {strength:g} x mean', free_within(
            wide, prior), train, validation, args.folds))
    best = min(priors, key=lambda row: row['cv_rmse_k'])
    best['variant'] += ' (chosen by CV)'
    rows.extend(priors)
    rows.append(score('EN ISO 13790 mass classes (tmass %.0f-%.0f)' % TMASS_CLASSES,
                      free_within({**wide, 'tmass': TMASS_CLASSES}), train, validation,
                      args.folds))
    rows.append(score("study's bounds (the default)", free_within(
        calibration.OU44_STUDY_BOUNDS), train, validation, args.folds))
    rows.append(score("study's bounds, soft_l1 (f_scale 0.3 K)", free_within(
        calibration.OU44_STUDY_BOUNDS), train, validation, args.folds, loss='soft_l1',
        f_scale=0.3))
    published = calibration.r1c1_builder()({})
    reference = {'variant': 'published parameters', **{k: PUBLISHED[k] for k in wide}}
    for period in (train, validation):
        reference[f'rmse_{period.name}_k'] = calibration.metrics(
            calibration.simulate_period(published, period), period.measured)['rmse_k']
    rows.insert(0, reference)
    print_table(rows, [('variant', 'variant', '>46'), ('tmass', 'tmass', '.1f'),
                       ('shgc', 'shgc', '.3f'), ('occheff', 'occheff', '.3f'),
                       ('RExt', 'RExt', '.3f'), ('rmse_train_k', 'train [K]', '.3f'),
                       ('rmse_validation_k', 'valid. [K]', '.3f'),
                       ('cv_rmse_k', 'CV [K]', '.3f'), ('fit_s', 'fit [s]', '.2f')])
    chosen = min(rows[1:], key=lambda row: row['cv_rmse_k'])
    logger.info('lowest cross-validation RMSE inside the training period: %s (%.3f K)',
                chosen['variant'], chosen['cv_rmse_k'])
    study = study_setup(data_path())
    logger.info("the study's setup (hourly, 20 degC start, its bounds): least squares %s; "
                'published %s', {k: round(v, 4) for k, v in study['parameters'].items()},
                {k: round(v, 4) for k, v in study['published'].items()})
    write_json('calibration_variants', {'folds': args.folds, 'variants': rows,
                                        'lowest_cv': chosen['variant'], 'study_setup': study,
                                        'wall_s': time.perf_counter() - started})
    return 0


if __name__ == '__main__':
    sys.exit(main())
