"""
Tolerance: the 72 h case with the R1C1 FMU (Model Exchange) at integrator tolerances.

Tolerances 1e-4 ... 1e-11: energy and discomfort per tolerance and their spread.

    python bench/tolerance.py [--horizon 10] [--tolerances 1e-4 1e-6 1e-7 1e-9 1e-11]

The ancestor's finite-difference gradients made energy rise from 44 to 57-109 kWh
at loose tolerances; our sensitivities (FMI directional derivatives integrated
along each interval) keep the result independent of the tolerance.
"""
from __future__ import annotations

import argparse
import sys

from common import logger, print_table, setup_logging, timed_run, write_json


def spread(values: list[float]) -> float:
    """(max - min) / mean [-]."""
    mean = sum(values) / len(values)
    return (max(values) - min(values)) / abs(mean) if mean else 0.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--horizon', type=int, default=10)
    parser.add_argument('--tolerances', nargs='+', type=float,
                        default=[1e-4, 1e-6, 1e-7, 1e-9, 1e-11])
    parser.add_argument('--control', default='fmu', choices=['fmu', 'fmu-cs'])
    args = parser.parse_args(argv)
    setup_logging()
    rows = []
    for tol in args.tolerances:
        row = timed_run(args.control, args.horizon, tolerance=tol)
        row.pop('objectives')
        row['tolerance'] = tol
        rows.append(row)
        logger.info('tolerance %.0e: %.3f kWh, %.3f Kh (%.3f Kh hourly), %.1f s', tol,
                    row['energy_kwh'], row['discomfort_kh'], row['discomfort_kh_hourly'],
                    row['wall_s'])
    print_table(rows, [('tolerance', 'tolerance', '.0e'), ('energy_kwh', 'kWh', '.3f'),
                       ('discomfort_kh', 'Kh', '.3f'),
                       ('discomfort_kh_hourly', 'Kh hourly', '.3f'),
                       ('wall_s', 'wall [s]', '.1f'), ('solver_failures', 'failures', 'd')])
    spreads = {key: spread([r[key] for r in rows])
               for key in ('energy_kwh', 'discomfort_kh', 'discomfort_kh_hourly')}
    for key, value in spreads.items():
        logger.info('spread of %s across tolerances: %.3f %% (target <= 2 %%)', key,
                    100 * value)
    write_json('tolerance', {'horizon_h': args.horizon, 'control': args.control, 'rows': rows,
                             'spread': spreads})
    return 0


if __name__ == '__main__':
    sys.exit(main())
