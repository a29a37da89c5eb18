"""Shared pieces of the benchmarks: timed MPC runs on the reference case, tables, JSON."""
from __future__ import annotations

import json
import logging
import pathlib
import platform
import time

from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.scenario import DEFAULT_DATA, reference_scenario
from mshoot_core.units import KELVIN
from mshoot_studies.case import control_model
import numpy as np

logger = logging.getLogger('bench')
OUT = pathlib.Path(__file__).resolve().parents[1] / 'out' / 'bench'


def data_path() -> pathlib.Path:
    """Return the OU44 measurements beside the project (the benchmarks need them)."""
    path = DEFAULT_DATA.resolve()
    if not path.is_file():
        raise SystemExit(f'benchmark data missing: {path}')
    return path


def timed_run(control: str, horizon: int, *, mode: str = 'fast', steps: int | None = None,
              tolerance: float = 1e-6, models: dict | None = None, **mpc_options) -> dict:
    """
    Run the reference case with a control model; return timing and KPI figures.

    ``models`` caches built control models by (control, tolerance), so the
    training of data-driven models and the FMU load are not timed as MPC work.
    """
    scenario = reference_scenario('ou44', data_path())
    key = (control, tolerance)
    if models is not None and key in models:
        model = models[key]
    else:
        model = control_model(control, tolerance, data_path())
        if models is not None:
            models[key] = model
    mpc = MPC(model, horizon_steps=horizon, mode=mode, **mpc_options)
    emulator = Emulator(R1C1Model(), scenario, [20.0 + KELVIN])
    result = run_closed_loop(mpc, emulator, steps=steps, log_every=0)
    kpis = closed_loop_kpis(result.steps, result.fine, mpc.step_s, result.wall_s)
    per_step = result.steps['solve_time_s'].to_numpy()
    return {'control': control, 'horizon_h': horizon, 'mode': mode, 'steps': len(per_step),
            'wall_s': result.wall_s, 'step_median_s': float(np.median(per_step)),
            'iterations': int(result.steps['iterations'].sum()),
            'model_evaluations': int(result.steps['model_evaluations'].sum()),
            'energy_kwh': kpis['energy_kwh'], 'discomfort_kh': kpis['discomfort_kh'],
            'discomfort_kh_hourly': kpis['discomfort_kh_hourly'],
            'solver_failures': kpis['solver_failures'],
            'objectives': result.steps['objective'].to_list()}


def print_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> None:
    """Print rows as a fixed-width table; columns are (key, header, format)."""
    widths = [max(len(h), 10) for _, h, _ in columns]
    logger.info('  '.join(h.rjust(w) for (_, h, _), w in zip(columns, widths)))
    for row in rows:
        cells = []
        for (key, _, fmt), w in zip(columns, widths):
            value = row.get(key, '')
            cells.append((format(value, fmt) if value != '' else '-').rjust(w))
        logger.info('  '.join(cells))


def write_json(name: str, payload: dict) -> pathlib.Path:
    """Write a benchmark's figures to out/bench/NAME.json with the machine's description."""
    OUT.mkdir(parents=True, exist_ok=True)
    payload = {'machine': {'python': platform.python_version(), 'cpu': platform.processor()
                           or platform.machine(), 'time': time.strftime('%Y-%m-%dT%H:%M:%S')},
               **payload}
    path = OUT / f'{name}.json'
    path.write_text(json.dumps(payload, indent=2, default=float) + '\n')
    logger.info('wrote %s', path)
    return path


def setup_logging() -> None:
    logging.basicConfig(level=logging.INFO, format='%(message)s')
    logging.getLogger('mshoot_core').setLevel(logging.ERROR)
