"""
Scale: Z zones in one MPC problem, time per MPC step against zones and horizon.

    python bench/scale.py [--zones 1 10 50 100] [--horizons 6 10 12 24] [--steps 3]

Each case solves ``--steps`` consecutive MPC steps of a building of Z
independent R1C1 zones (:class:`MultiZoneModel`) on the built-in scenario with
IPOPT (sparse) and reports the median time per step; SLSQP (dense) is shown
next to it where it finishes in reasonable time (Z <= 10). The growth
exponent is fitted on log(time) against log(Z).
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings

from mshoot_core.models.multizone import multizone_mpc_options, MultiZoneModel
from mshoot_core.mpc import MPC
from mshoot_core.scenario import forecast_window, synthetic_scenario
import numpy as np
import pandas as pd

from common import logger, print_table, setup_logging, write_json


#: Initial temperature of every zone [degC].
INITIAL_C = 20.5


def zone_case(n_zones: int, horizon: int, solver: str, steps: int) -> tuple[
        MultiZoneModel, MPC, pd.DataFrame, np.ndarray]:
    """
    Return the scale problem: Z independent R1C1 zones on the built-in scenario.

    Returns the model, the configured MPC, a scenario long enough for
    ``steps`` steps at ``horizon`` and the initial state [K] (``bench/versus.py``
    builds its CasADi counterpart from the same pieces).
    """
    model = MultiZoneModel(n_zones)
    mpc = MPC(model, horizon_steps=horizon, **multizone_mpc_options(model, solver))
    scenario = synthetic_scenario(hours=steps + horizon + 1)
    return model, mpc, scenario, np.full(n_zones, INITIAL_C + 273.15)


def time_steps(n_zones: int, horizon: int, solver: str, steps: int) -> dict:
    """Median wall time [s] of ``steps`` consecutive MPC steps, and solver figures."""
    _, mpc, scenario, x = zone_case(n_zones, horizon, solver, steps)
    times, iterations, failures, relaxed = [], 0, 0, 0
    for k in range(steps):
        started = time.perf_counter()
        result = mpc.solve(x, scenario.index[k], forecast_window(scenario, k, horizon))
        times.append(time.perf_counter() - started)
        iterations += result.nit
        failures += not result.success
        relaxed += bool(result.relaxed)
        x = result.simulated_states[1]
    return {'zones': n_zones, 'horizon_h': horizon, 'solver': solver,
            'variables': mpc.problem.index.size, 'step_median_s': float(np.median(times)),
            'iterations_per_step': iterations / steps, 'failures': failures,
            'relaxed_steps': relaxed}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--zones', nargs='+', type=int, default=[1, 10, 50, 100])
    parser.add_argument('--horizons', nargs='+', type=int, default=[6, 10, 12, 24])
    parser.add_argument('--steps', type=int, default=3, help='MPC steps per case (default 3)')
    args = parser.parse_args(argv)
    setup_logging()
    warnings.simplefilter('ignore', category=Warning)
    rows = []
    for horizon in args.horizons:
        for zones in args.zones:
            for solver in ('ipopt', 'slsqp'):
                if solver == 'slsqp' and zones > 10:
                    continue
                row = time_steps(zones, horizon, solver, args.steps)
                rows.append(row)
                logger.info('Z=%d H=%d %s: %.3f s/step (%d variables)', zones, horizon, solver,
                            row['step_median_s'], row['variables'])
    growth = {}
    for horizon in args.horizons:
        sel = [r for r in rows if r['horizon_h'] == horizon and r['solver'] == 'ipopt'
               and r['zones'] > 1]
        if len(sel) >= 2:
            slope = np.polyfit(np.log([r['zones'] for r in sel]),
                               np.log([r['step_median_s'] for r in sel]), 1)[0]
            growth[horizon] = float(slope)
            logger.info('H=%d: time per step grows as Z^%.2f (IPOPT, Z > 1)', horizon, slope)
    print_table(rows, [('zones', 'Z', 'd'), ('horizon_h', 'H [h]', 'd'), ('solver', 'solver', 's'),
                       ('variables', 'variables', 'd'), ('step_median_s', 's/step', '.3f'),
                       ('iterations_per_step', 'iters/step', '.1f'),
                       ('relaxed_steps', 'relaxed', 'd'), ('failures', 'failures', 'd')])
    target = [r for r in rows if r['zones'] == 100 and r['horizon_h'] == 10
              and r['solver'] == 'ipopt']
    if target:
        logger.info('target Z=100, H=10: %.3f s per step (goal <= 0.5 s)',
                    target[0]['step_median_s'])
    write_json('scale', {'steps': args.steps, 'rows': rows, 'growth_exponent': growth})
    return 0


if __name__ == '__main__':
    sys.exit(main())
