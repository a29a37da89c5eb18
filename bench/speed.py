"""
Speed: the 72 h reference case, fast path vs the ancestor's naive algorithm, side by side.

    python bench/speed.py [--naive-steps 3] [--controls fmu fmu-cs python svr] [--horizons 2 10]

For each control model and horizon: the fast path runs all 72 steps; the naive
mode runs the first ``--naive-steps`` steps (at H = 10 a naive step costs
seconds to minutes). The ratio compares per-step medians of the same steps.

The naive baseline is skipped by default for the Model Exchange FMU at
H = 10 (``--naive-skip fmu:10``): one such step took 2191 s and 312520
simulations, and SLSQP stopped without converging (objective 63 % above the
fast path's), because its finite differences meet the integrator's noise at
tolerance 1e-6. ``--naive-skip none`` runs it anyway.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from common import logger, print_table, setup_logging, timed_run, write_json

#: Control models of the reference case (``mshoot_studies.case.control_model``)
CONTROLS = ('fmu', 'fmu-cs', 'python', 'svr')


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--naive-steps', type=int, default=3,
                        help='MPC steps of the naive baseline (default 3)')
    parser.add_argument('--controls', nargs='+', default=list(CONTROLS),
                        choices=CONTROLS)
    parser.add_argument('--horizons', nargs='+', type=int, default=[2, 10])
    parser.add_argument('--naive-skip', nargs='+', default=['fmu:10'], metavar='CONTROL:H',
                        help='runs without the naive baseline (default fmu:10, which takes '
                             "~35 min a step); 'none' skips nothing")
    parser.add_argument('--json', default='speed', metavar='NAME',
                        help='write the figures to out/bench/NAME.json (default speed)')
    args = parser.parse_args(argv)
    skip = naive_skips(parser, args.naive_skip)
    setup_logging()
    rows, models = [], {}
    for control in args.controls:
        for horizon in args.horizons:
            fast = timed_run(control, horizon, models=models)
            if (control, horizon) in skip:
                logger.info('%s H=%d: fast %.2f s for 72 steps (median %.4f s/step), naive '
                            'skipped (--naive-skip)', control, horizon, fast['wall_s'],
                            fast['step_median_s'])
                fast.pop('objectives')
                rows.append(fast)
                continue
            fast_same = timed_run(control, horizon, steps=args.naive_steps, models=models)
            naive = timed_run(control, horizon, mode='naive', steps=args.naive_steps,
                              models=models)
            ratio = naive['step_median_s'] / fast_same['step_median_s']
            # objectives of near-empty plans are ~0: compare on the scale of one full-power hour
            rel = float(np.max(np.abs(np.subtract(naive['objectives'], fast_same['objectives']))
                               / np.maximum(np.abs(fast_same['objectives']), 1.0)))
            for row in (fast, naive):
                row.pop('objectives')
            rows.append({**fast, 'naive_step_median_s': naive['step_median_s'],
                         'naive_iterations_per_step': naive['iterations'] / naive['steps'],
                         'naive_evaluations_per_step': naive['model_evaluations']
                         / naive['steps'],
                         'naive_failures': naive['solver_failures'],
                         'speedup': ratio, 'objective_rel_diff': rel})
            logger.info('%s H=%d: fast %.2f s for 72 steps (median %.4f s/step), naive median '
                        '%.3f s/step: %.0fx', control, horizon, fast['wall_s'],
                        fast['step_median_s'], naive['step_median_s'], ratio)
    print_table(rows, [('control', 'control', 's'), ('horizon_h', 'H [h]', 'd'),
                       ('wall_s', 'fast 72h [s]', '.2f'),
                       ('step_median_s', 'fast/step [s]', '.4f'),
                       ('iterations', 'fast iters', 'd'),
                       ('model_evaluations', 'fast evals', 'd'),
                       ('naive_step_median_s', 'naive/step [s]', '.3f'),
                       ('naive_evaluations_per_step', 'naive evals/step', '.0f'),
                       ('naive_failures', 'naive fails', 'd'),
                       ('speedup', 'speed-up', '.0f'),
                       ('objective_rel_diff', 'obj rel diff', '.1e'),
                       ('energy_kwh', 'kWh', '.2f'), ('discomfort_kh_hourly', 'Kh hourly', '.2f')])
    write_json(args.json, {'naive_steps': args.naive_steps, 'rows': rows})
    return 0


def naive_skips(parser: argparse.ArgumentParser, items: list[str]) -> set[tuple[str, int]]:
    """Parse ``CONTROL:H`` pairs (or ``none``) into a set of (control, horizon [h])."""
    if items == ['none']:
        return set()
    pairs = set()
    for item in items:
        control, _, horizon = item.partition(':')
        if control not in CONTROLS or not horizon.isdigit():
            parser.error(f'--naive-skip: {item!r} is not CONTROL:H with CONTROL one of '
                         f"{', '.join(CONTROLS)} and H whole hours (or 'none')")
        pairs.add((control, int(horizon)))
    return pairs


if __name__ == '__main__':
    sys.exit(main())
