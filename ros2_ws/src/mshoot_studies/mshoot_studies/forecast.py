"""
The forecast a BOPTEST test case serves, with BOPTEST's forecast uncertainty, as CSV.

    mshoot forecast --testcase DIR --time 0 --horizon 86400 --interval 3600
        --temperature-uncertainty medium --solar-uncertainty low --seed 1
        --points TDryBul,HGloHor

prints what a fresh ``PUT /forecast`` at ``--time`` [s from 1 January] gets from BOPTEST
(v0.8.0) under that scenario: a ``time`` column [s] and one column per point, in BOPTEST's
names and units (``TDryBul`` [K], ``HGloHor`` [W/m2], ...). The errors touch ``TDryBul`` and
``HGloHor`` only (see :mod:`mshoot_core.forecast`); every other point is the test case's data.
Horizon and interval are in seconds, as BOPTEST takes them; a horizon over 48 h is refused for
a point with errors. Bad options: one line on stderr, exit 2.

    mshoot forecast --testcase DIR --card CARD --price dynamic --time T --horizon H
        --interval DT [--temperature-uncertainty L --solar-uncertainty L --seed S]

prints instead what a control model plans on: the forecast of the card's ``testcase_forecast``
section (:mod:`mshoot_core.boptest.forecasts`), ``H / DT + 1`` rows of interval means of length
``DT`` of the series the card names, its tightest band per zone [degC] and the price scenario's
price, with the errors before the means.
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Sequence, TextIO

from mshoot_core.boptest.forecasts import ForecastSpec, TestCaseForecasts
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.forecast import ForecastSource
from mshoot_core.settings import (add_arguments, fields_of, ForecastErrorSettings,
                                  option_wording, SettingsError)
import pandas as pd

#: The options of the error model (from the settings' descriptions).
ERROR_FIELDS = fields_of(ForecastErrorSettings)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """
    Build the command line of the forecast command.

    Fills ``parser`` (the ``forecast`` verb of ``mshoot``), or a new parser when None. Its
    errors are one line (``<prog>: error: ...``) and exit 2.
    """
    from mshoot_studies.cli import verb_parser
    parser = verb_parser(parser, 'mshoot_studies.forecast', __doc__)
    parser.add_argument('--testcase', default=None,
                        help='the BOPTEST test case folder (Resources/*.csv; default '
                             '$MSHOOT_BOPTEST_DIR)')
    parser.add_argument('--time', type=float, required=True,
                        help='time of the request [s from 1 January], as BOPTEST counts it')
    parser.add_argument('--horizon', type=float, default=86400.0,
                        help='forecast horizon [s], as BOPTEST takes it; at most 172800 (48 h) '
                             'for a point with errors (default 86400)')
    parser.add_argument('--interval', type=float, default=3600.0,
                        help='interval between the forecast times [s], as BOPTEST takes it '
                             '(default 3600)')
    add_arguments(parser, ERROR_FIELDS)
    parser.add_argument('--points', default='',
                        help="forecast points, BOPTEST's names separated by commas (default: "
                             "every series of the test case's Resources/*.csv)")
    parser.add_argument('--card', default=None,
                        help='a control model card with a testcase_forecast section: print its '
                             'interval means, band and price instead of the points (a path or '
                             'a built-in card name)')
    parser.add_argument('--price', default='constant',
                        help="with --card: the price scenario (a key of the card's price "
                             'series; default constant)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` (default: the process arguments) and run; the exit code."""
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Print the forecast (0), or one line of error on stderr (2)."""
    return print_forecast(args, sys.stdout, sys.stderr)


def print_forecast(args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    """Write the forecast of ``args`` as CSV to ``out``: 0, or 2 with one line on ``err``."""
    try:
        errors = ForecastErrorSettings(**{f.name: getattr(args, f.name) for f in ERROR_FIELDS})
    except SettingsError as exc:
        err.write('mshoot forecast: error: '
                  + '; '.join(option_wording(p, ERROR_FIELDS) for p in exc.problems) + '\n')
        return 2
    points = [p.strip() for p in args.points.split(',') if p.strip()] or None
    try:
        case = TestCase.load(args.testcase)
        if args.card is not None:
            frame = card_forecast(case, args, errors, points)
        else:
            source = ForecastSource.from_test_case(case, errors)
            frame = source.forecast(args.time, args.horizon, args.interval, points)
    except (FileNotFoundError, ValueError) as exc:
        err.write(f'mshoot forecast: error: {_one_line(exc)}\n')
        return 2
    times = frame['time'].to_numpy()
    if (times == times.round()).all():
        frame['time'] = times.astype('int64')
    return write_text(frame.to_csv(index=False), out)


def card_forecast(case: TestCase, args: argparse.Namespace, errors: ForecastErrorSettings,
                  points: Sequence[str] | None) -> pd.DataFrame:
    """
    Return the card's test case forecast of ``args`` (a ``time`` column, then its columns).

    Raises
    ------
    ValueError
        For a card without the section, a horizon that is not a whole number of intervals,
        an unknown column, or a source's refusal.

    """
    steps = args.horizon / args.interval if args.interval > 0 else float('nan')
    if not (steps >= 0 and abs(steps - round(steps)) < 1e-9):
        raise ValueError(f'with --card, expected a horizon that is a whole number >= 0 of '
                         f'intervals > 0, got {args.horizon:g} s and {args.interval:g} s')
    source = TestCaseForecasts(case, ForecastSpec.from_card(args.card), args.price, errors)
    unknown = [p for p in points or () if p not in source.columns]
    if unknown:
        raise ValueError(f'unknown columns {unknown} of the card forecast: expected among '
                         f'{list(source.columns)}')
    frame = source.frame(args.time, int(round(steps)), args.interval)
    frame = frame[list(points)] if points else frame
    return frame.reset_index().rename(columns={'time_s': 'time'})


def _one_line(exc: BaseException) -> str:
    return ' '.join(str(exc).split())


def write_text(text: str, out: TextIO) -> int:
    """
    Write ``text`` to ``out``: 0; a reader that stops early (``| head``) is not an error.

    On a broken pipe the rest is dropped and the stream pointed at ``/dev/null``, so the exit
    does not fail flushing it.
    """
    try:
        out.write(text)
        out.flush()
    except BrokenPipeError:
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, out.fileno())
        except (OSError, ValueError):  # not a file descriptor (a test's stream)
            pass
    return 0


if __name__ == '__main__':
    sys.exit(main())
