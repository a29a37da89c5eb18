"""
The report of BOPTEST runs: KPI table (markdown) and figures (matplotlib, Agg).

- :func:`kpi_table`: KPI records (``<out>/kpis.json``) as a markdown table;
- :func:`count_starts`: off -> on transitions of a signal (e.g. a heat pump's modulation);
- :func:`plot_run`: one run: every zone's temperature with its band (and setpoints named by the
  caller), the power of every energy vector with the electricity price;
- :func:`plot_kpi_bars`: thermal discomfort, energy and cost of the controllers side by side.
"""
from __future__ import annotations

import logging
import pathlib
from typing import Iterable, Mapping, Sequence

from mshoot_core.boptest.testcase import PRICE_SCENARIOS, TestCase
from mshoot_core.units import KELVIN
import numpy as np
import pandas as pd

logger = logging.getLogger(__name__)

#: Columns of the KPI table: key, header, format.
TABLE_COLUMNS = (('controller', 'controller', '{}'), ('period', 'period', '{}'),
                 ('price', 'price', '{}'), ('tdis_tot', 'tdis [K h]', '{:.2f}'),
                 ('idis_tot', 'idis [ppm h]', '{:.1f}'), ('ener_tot', 'ener [kWh/m2]', '{:.3f}'),
                 ('cost_tot', 'cost [EUR/m2]', '{:.4f}'),
                 ('emis_tot', 'emis [kgCO2/m2]', '{:.3f}'),
                 ('pele_tot', 'pele [kW/m2]', '{:.4f}'), ('pgas_tot', 'pgas [kW/m2]', '{:.4f}'),
                 ('pdih_tot', 'pdih [kW/m2]', '{:.4f}'), ('time_rat', 'time_rat [-]', '{:.2e}'),
                 ('starts_per_day', 'starts/day', '{:.2f}'))
#: Time tolerance [s].
_EPS_S = 1e-6


def _cell(value: object, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return '-'
    return fmt.format(value)


def kpi_table(records: Iterable[Mapping[str, object]],
              extra: Sequence[tuple[str, str, str]] = ()) -> str:
    """
    Return the records as a markdown table (:data:`TABLE_COLUMNS` plus ``extra``).

    A column no record has a value in is left out (e.g. ``pgas_tot`` of an all-electric
    building).
    """
    records = list(records)
    columns = [c for c in (*TABLE_COLUMNS, *extra)
               if c[0] in ('controller', 'period', 'price')
               or any(r.get(c[0]) is not None for r in records)]
    lines = ['| ' + ' | '.join(c[1] for c in columns) + ' |',
             '|' + '|'.join('---' for _ in columns) + '|']
    for record in records:
        lines.append('| ' + ' | '.join(_cell(record.get(key), fmt) for key, _, fmt in columns)
                     + ' |')
    return '\n'.join(lines) + '\n'


def count_starts(records: pd.DataFrame, column: str, start_s: float | None = None,
                 end_s: float | None = None, threshold: float = 0.01) -> tuple[int, float]:
    """
    Count the starts of a signal: off -> on transitions (e.g. a heat pump's modulation).

    A start is a sample above ``threshold`` whose previous sample is at or below it; only
    starts at sample times in (start_s, end_s] count.

    Parameters
    ----------
    records : pd.DataFrame
        A record table with ``time`` [s] and ``column``.
    column : str
        The signal.
    start_s, end_s : float, optional
        The window [s]; default the table's span.
    threshold : float
        Value above which the signal is on.

    Returns
    -------
    tuple of (int, float)
        The number of starts and the starts per day of the window.

    Raises
    ------
    ValueError
        For missing columns or an empty window.

    """
    for name in ('time', column):
        if name not in records.columns:
            raise ValueError(f'the record table lacks the column {name!r}')
    times = records['time'].to_numpy(dtype=float)
    on = records[column].to_numpy(dtype=float) > threshold
    t0 = times[0] if start_s is None else float(start_s)
    t1 = times[-1] if end_s is None else float(end_s)
    if not t1 > t0:
        raise ValueError(f'empty window [{t0:g}, {t1:g}] s')
    rising = np.zeros_like(on)
    rising[1:] = on[1:] & ~on[:-1]
    inside = (times > t0 + _EPS_S) & (times <= t1 + _EPS_S)
    count = int(np.count_nonzero(rising & inside))
    return count, count / ((t1 - t0) / 86400.0)


def plot_run(records: pd.DataFrame, case: TestCase, start_s: float, end_s: float,
             title: str, path: pathlib.Path, prices: Sequence[str] = tuple(PRICE_SCENARIOS),
             setpoints: Mapping[str, str] | None = None) -> pathlib.Path:
    """
    Draw one run: zone temperatures and bands (and setpoints); power and price(s).

    Parameters
    ----------
    records : pd.DataFrame
        The run's record table (``time`` [s from 1 January], the test case's KPI outputs).
    case : TestCase
        The test case (zones, bands, energy vectors, prices).
    start_s, end_s : float
        The test period [s].
    title : str
        Figure title.
    path : pathlib.Path
        The PNG file.
    prices : sequence of str
        Price scenarios drawn.
    setpoints : dict of str to str, optional
        Legend label -> a recorded column [K] drawn with the temperatures.

    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    period = records[(records['time'] >= start_s) & (records['time'] <= end_s)]
    t = period['time'].to_numpy()
    days = (t - start_s) / 86400.0
    fig, (ax_t, ax_p) = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
    several = len(case.zones) > 1
    for zone, outputs in case.zone_temperature_outputs.items():
        lower, upper = case.band_columns(zone)
        suffix = f' [{zone}]' if several else ''
        ax_t.fill_between(days, case.lookup(lower, t) - KELVIN, case.lookup(upper, t) - KELVIN,
                          step='post', alpha=0.15, label=f'comfort band{suffix}')
        for name in outputs:
            ax_t.plot(days, period[name] - KELVIN, lw=1.0, label=f'zone temperature{suffix}')
    for label, column in (setpoints or {}).items():
        if column in period:
            ax_t.plot(days, period[column] - KELVIN, lw=0.8, label=label)
    ax_t.set_ylabel('[degC]')
    ax_t.legend(loc='upper right', fontsize=7, ncol=3)
    ax_t.set_title(title, fontsize=10)
    for vector, outputs in case.energy_outputs.items():
        power = sum(period[name].to_numpy() for name in outputs)
        ax_p.plot(days, power / 1000.0, lw=0.6,
                  label='electric power' if vector == 'ElectricPower' else vector)
    ax_p.set_ylabel('[kW]')
    ax_p.set_xlabel(f'days from the start of the test period ({start_s / 86400:.0f} d)')
    ax_price = ax_p.twinx()
    for name, style in zip(prices, ('-', '--', ':')):
        ax_price.step(days, case.lookup(case.price_column(name), t), where='post', color='k',
                      lw=0.8, ls=style, label=f'price {name}')
    ax_price.set_ylabel('[EUR/kWh]')
    handles = ax_p.get_legend_handles_labels()
    more = ax_price.get_legend_handles_labels()
    ax_p.legend(handles[0] + more[0], handles[1] + more[1], loc='upper right', fontsize=7,
                ncol=4)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_kpi_bars(records: Sequence[Mapping[str, object]], path: pathlib.Path,
                  controllers: Sequence[str] = ('baseline', 'rule', 'mshoot')) -> pathlib.Path:
    """Draw tdis, ener and cost per (period, price), one bar per controller present."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    frame = pd.DataFrame(list(records))
    present = [c for c in controllers if c in set(frame['controller'])]
    groups = list(dict.fromkeys(zip(frame['period'], frame['price'])))
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    width = 0.8 / max(1, len(present))
    x = np.arange(len(groups))
    for ax, (key, label) in zip(axes, (('tdis_tot', 'thermal discomfort [K h]'),
                                       ('ener_tot', 'energy [kWh/m2]'),
                                       ('cost_tot', 'cost [EUR/m2]'))):
        for k, controller in enumerate(present):
            rows = frame[frame['controller'] == controller].set_index(['period', 'price'])
            values = [float(rows.loc[g, key]) if g in rows.index else np.nan for g in groups]
            ax.bar(x + (k - (len(present) - 1) / 2) * width, values, width, label=controller)
        ax.set_xticks(x, [f'{p.replace("_heat_day", "")}\n{q.replace("_", " ")}'
                          for p, q in groups], fontsize=7)
        ax.set_title(label, fontsize=10)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
