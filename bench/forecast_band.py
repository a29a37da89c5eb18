"""
The forecast band of BOPTEST's forecast uncertainty against the truth over a day.

    python bench/forecast_band.py [--testcase DIR] [--day 110] [--level high] [--seeds 20]

A fresh forecast is requested at 00:00 of day ``--day`` of the test case (horizon 24 h,
interval 15 min) under ``--level`` for temperature and solar, with ``--seeds`` seeds 1000 apart
(1000, 2000, ...: seeds 1 apart often share their solar draw, since candidate ``i`` of seed
``s`` is drawn with ``s + i * i``; the script prints how many draws are distinct); the
figure shows the truth, the mean of the forecasts and their range (min to max), for the outdoor
temperature and the global horizontal irradiance. Writes ``docs/forecasts/forecast_band.png``
and prints the mean absolute error of the forecasts by lead time.
"""
from __future__ import annotations

import argparse
import pathlib

from mshoot_core.boptest.testcase import default_directory, TestCase
from mshoot_core.forecast import ForecastSource
from mshoot_core.settings import ForecastErrorSettings, UNCERTAINTY_LEVELS
from mshoot_core.units import KELVIN
import numpy as np

OUT = pathlib.Path(__file__).resolve().parents[1] / 'docs' / 'forecasts' / 'forecast_band.png'
#: Spacing of the seeds drawn.
SEED_SPACING = 1000


def draw(case: TestCase, day: int, level: str, seeds: int) -> tuple[np.ndarray, ...]:
    """Return times [h], truth and the forecasts (seeds x times) of both points."""
    now = day * 86400.0
    temperature, solar = [], []
    for seed in SEED_SPACING * np.arange(1, seeds + 1):
        errors = ForecastErrorSettings(temperature_uncertainty=level, solar_uncertainty=level,
                                       seed=int(seed))
        frame = ForecastSource.from_test_case(case, errors).forecast(
            now, 86400.0, 900.0, ['TDryBul', 'HGloHor'])
        temperature.append(frame['TDryBul'].to_numpy() - KELVIN)
        solar.append(frame['HGloHor'].to_numpy())
    times = frame['time'].to_numpy()
    truth_t = case.forecast_values('TDryBul', times) - KELVIN
    truth_g = case.forecast_values('HGloHor', times)
    return ((times - now) / 3600.0, truth_t, np.array(temperature), truth_g, np.array(solar))


def plot(hours: np.ndarray, truth_t: np.ndarray, temperature: np.ndarray,
         truth_g: np.ndarray, solar: np.ndarray, title: str, out: pathlib.Path) -> None:
    """Draw the two bands and save the figure at ``out``."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    figure, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for ax, truth, draws, label in ((axes[0], truth_t, temperature, 'outdoor temperature [degC]'),
                                    (axes[1], truth_g, solar, 'global horizontal [W/m2]')):
        ax.fill_between(hours, draws.min(axis=0), draws.max(axis=0), color='tab:orange',
                        alpha=0.3, linewidth=0, label=f'forecast range ({len(draws)} seeds)')
        ax.plot(hours, draws.mean(axis=0), color='tab:orange', label='forecast mean')
        ax.plot(hours, truth, color='black', linewidth=1.5, label='truth')
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc='upper left', fontsize=8)
    axes[1].set_xlabel('lead time [h]')
    axes[1].set_xticks(range(0, 25, 3))
    axes[0].set_title(title, fontsize=10)
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=110)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    """Draw the band; print the mean absolute errors by lead time."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--testcase', default=str(default_directory()))
    parser.add_argument('--day', type=int, default=110,
                        help='day of the year [d from 1 January] (default 110: 21 April, in '
                             'the typical heat period)')
    parser.add_argument('--level', default='high', choices=UNCERTAINTY_LEVELS[1:])
    parser.add_argument('--seeds', type=int, default=20)
    parser.add_argument('--out', type=pathlib.Path, default=OUT)
    args = parser.parse_args(argv)
    case = TestCase.load(args.testcase)
    hours, truth_t, temperature, truth_g, solar = draw(case, args.day, args.level, args.seeds)
    title = (f'{case.name}, day {args.day}: forecasts requested at 00:00\n'
             f"BOPTEST's forecast uncertainty {args.level!r} (temperature and solar), "
             f'seeds {SEED_SPACING}, {2 * SEED_SPACING}, ..., {args.seeds * SEED_SPACING}')
    plot(hours, truth_t, temperature, truth_g, solar, title, args.out)
    print(f'{"lead [h]":>8} {"|e_T| mean [K]":>15} {"|e_G| mean [W/m2]":>18}')
    for lead in (0, 1, 3, 6, 12, 18, 24):
        i = int(np.argmin(np.abs(hours - lead)))
        print(f'{lead:8d} {np.abs(temperature[:, i] - truth_t[i]).mean():15.2f} '
              f'{np.abs(solar[:, i] - truth_g[i]).mean():18.1f}')
    distinct = [len({tuple(row) for row in draws}) for draws in (temperature, solar)]
    print(f'distinct draws of {args.seeds}: temperature {distinct[0]}, solar {distinct[1]}')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
