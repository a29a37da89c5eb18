"""
The weather of a test case folder without ``weather.csv``, derived once from its FMU's outputs.

Stable API::

    from mshoot_core.boptest import weather
    frame = weather.derive_weather(case, start_s, end_s)     # BOPTEST columns, rows 900 s apart
    path = weather.ensure_weather(case)                      # the year, once, into the cache
    path = weather.ensure_weather(case, days=16, first_day=57)   # or a window (merged in)
    weather.ensure_window(case, start_s, end_s)              # the days around a run, if needed
    case.derived_weather_path                                # where TestCase.lookup reads it

    python -m mshoot_core.boptest.weather DIR [57 73]       # derive the year (or days) once

BOPTEST's forecasts read a test case's ``Resources/weather.csv`` (``TDryBul`` [K], ``HGloHor``
[W/m2], ... the points of :data:`~mshoot_core.boptest.testcase.WEATHER_POINTS`, rows every
900 s from 1 January). A folder that lacks it but whose FMU reports its weather station (outputs
``<prefix>reaWea<Point>_y``, the point's first letter capitalised, e.g.
``weaSta_reaWeaTDryBul_y``, ``weaSta_reaWeaRelHum_y``) gets the same table from those
outputs: the FMU is run under its own control over the year (one instance, in pieces of
:data:`PIECE_DAYS`), each output sampled at the row times, and the table is written to the
cache, ``<cache base>/boptest/weather/<sha256 of the FMU file, 16 hex>/weather.csv`` (the base
of :func:`mshoot_core.fmu_cache.cache_dir`'s folder: ``~/.cache/mshoot``), never into the test
case folder. The weather is the building's own input, the same under any control, so the year
is derived once per FMU file. :class:`~mshoot_core.boptest.testcase.TestCase` then finds its
columns as it finds those of ``weather.csv``.
"""
from __future__ import annotations

import logging
import pathlib
import re
import sys
import time
from typing import Any, Sequence

import numpy as np
import pandas as pd

from mshoot_core.boptest.testcase import SECONDS_PER_DAY, WEATHER_POINTS
from mshoot_core.period_loop import run_steps

logger = logging.getLogger(__name__)

#: Rows of the derived table [s] (BOPTEST's weather.csv).
ROW_S = 900.0
#: Days run between two writes of the records (the memory of a long run) [days].
PIECE_DAYS = 5.0
#: An FMU output of the weather station: ``<prefix>reaWea<point>_y``.
_OUTPUT = re.compile(r'^(?:.*_)?reaWea(?P<point>[A-Za-z]+)_y$')


def weather_outputs(outputs: Sequence[str]) -> dict[str, str]:
    """
    Return BOPTEST weather point -> the FMU output that reports it, among ``outputs``.

    Raises
    ------
    ValueError
        When no output reports a weather point.

    """
    points = {point.lower(): point for point in WEATHER_POINTS}
    found: dict[str, str] = {}
    for name in outputs:
        match = _OUTPUT.match(name)
        point = points.get(match['point'].lower()) if match else None
        if point is not None:
            found.setdefault(point, name)
    if not found:
        raise ValueError('the FMU has no weather station outputs (<prefix>reaWea<point>_y, '
                         f'point one of {sorted(WEATHER_POINTS)})')
    return found


def derive_weather(case: Any, start_s: float, end_s: float, row_s: float = ROW_S,
                   lead_s: float = 0.0) -> pd.DataFrame:
    """
    Run the test case's FMU from ``start_s`` to ``end_s``; return its weather outputs.

    Parameters
    ----------
    case : TestCase
        The test case.
    start_s, end_s : float
        First and last row [s from 1 January].
    row_s : float
        Row spacing [s].
    lead_s : float
        Run before the first row [s] (the FMU starts at ``start_s - lead_s``).

    Returns
    -------
    DataFrame
        Index: time [s from 1 January], every ``row_s`` from ``start_s`` to ``end_s``; columns:
        the weather points the FMU reports, in its units (K, W/m2, -, ...), each its value at
        the row time.

    """
    from mshoot_core.boptest.plant import BoptestPlant
    if not (0.0 <= start_s - lead_s and start_s < end_s and row_s > 0):
        raise ValueError(f'expected 0 <= start_s - lead_s, start_s < end_s and row_s > 0, got '
                         f'{start_s:g}, {end_s:g}, {lead_s:g}, {row_s:g}')
    rows = start_s + row_s * np.arange(int(np.floor((end_s - start_s) / row_s + 1e-9)) + 1)
    plant = BoptestPlant(case, record=[])  # reads the FMU's variables, holds no instance
    outputs = weather_outputs(plant.outputs_available)
    plant = BoptestPlant(case, record=list(outputs.values()))
    pieces = []

    def piece(t_s: float, to_s: float, decided: None) -> None:
        plant.advance(to_s)
        pieces.append(_at(plant.records(), rows[(rows > t_s + 1e-6) & (rows <= to_s + 1e-6)],
                          outputs))
        plant.drop_records()

    with plant:
        plant.start(start_s - lead_s)
        if lead_s > 0:
            plant.advance(start_s)
        pieces.append(_at(plant.records(start_s - 1e-3), rows[:1], outputs))
        plant.drop_records()
        run_steps(start_s, rows[-1], PIECE_DAYS * SECONDS_PER_DAY, piece,
                  label=f'weather of {case.name}')
    frame = pd.concat(pieces)
    frame.index.name = 'time'
    return frame


def _at(records: pd.DataFrame, times: np.ndarray, outputs: dict[str, str]) -> pd.DataFrame:
    """Return the recorded outputs at ``times`` (rows of the records, every sample)."""
    record_times = records['time'].to_numpy(dtype=float)
    where = np.searchsorted(record_times, times - 1e-6)
    where = np.clip(where, 0, record_times.size - 1)
    if np.any(np.abs(record_times[where] - times) > 1e-6):
        raise ValueError('the plant recorded no sample at a row time (rows must fall on its '
                         'samples)')
    return pd.DataFrame({point: records[name].to_numpy(dtype=float)[where]
                         for point, name in outputs.items()}, index=times)


def ensure_weather(case: Any, days: float = 365.0, first_day: float = 0.0) -> pathlib.Path:
    """
    Derive the test case's weather once over ``days`` from ``first_day``; return the file.

    The cache file holds one contiguous window of rows: a window it already covers is not run
    again; one it does not is derived from the end (or to the start) of what it holds, so the
    rows stay contiguous, and merged in. A lookup outside the rows fails
    (:meth:`~mshoot_core.boptest.testcase.TestCase.lookup`). Written to a temporary file beside
    the target and renamed into place, so an interrupted run leaves nothing half-written.

    Parameters
    ----------
    case : TestCase
        The test case.
    days : float
        Length of the window [days].
    first_day : float
        Its start [days from 1 January], >= 0.

    """
    if not (first_day >= 0.0 and days > 0.0):
        raise ValueError(f'expected first_day >= 0 and days > 0, got {first_day:g}, {days:g}')
    path = case.derived_weather_path
    start_s, end_s = first_day * SECONDS_PER_DAY, (first_day + days) * SECONDS_PER_DAY
    held = pd.read_csv(path, index_col=0) if path.is_file() else None
    pieces = []
    if held is None:
        pieces.append(derive_weather(case, start_s, end_s))
    else:
        first, last = float(held.index[0]), float(held.index[-1])
        if start_s < first - 1e-6:
            pieces.append(derive_weather(case, start_s, first))
        if end_s > last + 1e-6:
            pieces.append(derive_weather(case, last, end_s))
        if not pieces:
            return path
        pieces.append(held)
    logger.info('derived the weather of %s over days %g to %g from its FMU into %s', case.name,
                first_day, first_day + days, path)
    frame = pd.concat(pieces)
    frame.index = frame.index.to_numpy(dtype=float)
    frame = frame[~frame.index.duplicated(keep='last')].sort_index()
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.with_suffix(f'.{time.time_ns()}.tmp')
    frame.to_csv(staging, index_label='time')
    staging.replace(path)
    return path


def ensure_window(case: Any, start_s: float, end_s: float) -> pathlib.Path | None:
    """
    Make the weather of a folder without its own cover [start_s, end_s] [s from 1 January].

    Returns the derived file (:func:`ensure_weather` over the whole days around the window),
    or None for a folder with its own weather (nothing to derive).
    """
    if not case.weather_derived:
        return None
    first = float(np.floor(max(0.0, start_s) / SECONDS_PER_DAY))
    last = float(np.ceil(end_s / SECONDS_PER_DAY))
    return ensure_weather(case, days=max(1.0, last - first), first_day=first)


def main(argv: Sequence[str] | None = None) -> int:
    """Derive the weather of the folder ``argv[0]`` (days ``argv[1]`` to ``argv[2]``): 0, or 2."""
    from mshoot_core.boptest.testcase import TestCase
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(levelname)s %(message)s')
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) not in (1, 3) or args[0].startswith('-'):
        sys.stderr.write('usage: python -m mshoot_core.boptest.weather TEST_CASE_DIR '
                         '[FIRST_DAY LAST_DAY]\n')
        return 2
    try:
        first, last = (float(args[1]), float(args[2])) if len(args) == 3 else (0.0, 365.0)
        logger.info('wrote %s', ensure_weather(TestCase.load(args[0]), last - first, first))
    except (FileNotFoundError, ValueError) as exc:
        sys.stderr.write(f'{exc}\n')
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())
