"""
The BOPTEST benchmark's report: KPI table (markdown) and figures (matplotlib, Agg).

- :func:`kpi_table`: the records of ``out/boptest/kpis.json`` as a markdown table;
- :func:`plot_run`: one run: zone temperature with the band and the setpoint the local loop
  followed, electric power with the price;
- :func:`plot_kpi_bars`: thermal discomfort, energy and cost of the controllers side by side.
"""
from __future__ import annotations

import logging
import pathlib
from typing import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from mshoot_core.boptest.testcase import LOWER_SETPOINT, PRICE_SCENARIOS, TestCase, \
    UPPER_SETPOINT
from mshoot_core.units import KELVIN

logger = logging.getLogger(__name__)

#: Columns of the KPI table: key, header, format.
TABLE_COLUMNS = (('controller', 'controller', '{}'), ('period', 'period', '{}'),
                 ('price', 'price', '{}'), ('tdis_tot', 'tdis [K h]', '{:.2f}'),
                 ('idis_tot', 'idis [ppm h]', '{:.1f}'), ('ener_tot', 'ener [kWh/m2]', '{:.3f}'),
                 ('cost_tot', 'cost [EUR/m2]', '{:.4f}'),
                 ('emis_tot', 'emis [kgCO2/m2]', '{:.3f}'),
                 ('pele_tot', 'pele [kW/m2]', '{:.4f}'), ('time_rat', 'time_rat [-]', '{:.2e}'),
                 ('starts_per_day', 'starts/day', '{:.2f}'))


def _cell(value: object, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return '-'
    return fmt.format(value)


def kpi_table(records: Iterable[Mapping[str, object]],
              extra: Sequence[tuple[str, str, str]] = ()) -> str:
    """Return the records as a markdown table (:data:`TABLE_COLUMNS` plus ``extra``)."""
    columns = [*TABLE_COLUMNS, *extra]
    lines = ['| ' + ' | '.join(c[1] for c in columns) + ' |',
             '|' + '|'.join('---' for _ in columns) + '|']
    for record in records:
        lines.append('| ' + ' | '.join(_cell(record.get(key), fmt) for key, _, fmt in columns)
                     + ' |')
    return '\n'.join(lines) + '\n'


def plot_run(records: pd.DataFrame, case: TestCase, start_s: float, end_s: float,
             title: str, path: pathlib.Path, prices: Sequence[str] = tuple(PRICE_SCENARIOS),
             ) -> pathlib.Path:
    """
    Draw one run: zone temperature, band and setpoint; electric power and price(s).

    Parameters
    ----------
    records : pd.DataFrame
        The run's record table (``time`` [s from 1 January], ``reaTZon_y``, ``reaTSet_y``, the
        power outputs).
    case : TestCase
        The test case (band, prices).
    start_s, end_s : float
        The test period [s].
    title : str
        Figure title.
    path : pathlib.Path
        The PNG file.
    prices : sequence of str
        Price scenarios drawn.

    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    period = records[(records['time'] >= start_s) & (records['time'] <= end_s)]
    t = period['time'].to_numpy()
    days = (t - start_s) / 86400.0
    fig, (ax_t, ax_p) = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
    ax_t.fill_between(days, case.lookup(LOWER_SETPOINT, t) - KELVIN,
                      case.lookup(UPPER_SETPOINT, t) - KELVIN, step='post', color='tab:green',
                      alpha=0.15, label='comfort band')
    modulated = ('oveHeaPumY_u' in period
                 and bool(period['oveHeaPumY_u'].notna().any()))
    if 'reaTSet_y' in period:
        ax_t.plot(days, period['reaTSet_y'] - KELVIN, color='tab:orange', lw=0.8,
                  label=('local setpoint (not in charge: heat pump modulation overwritten)'
                         if modulated else 'setpoint followed'))
    ax_t.plot(days, period['reaTZon_y'] - KELVIN, color='tab:red', lw=1.0,
              label='zone operative temperature')
    ax_t.set_ylabel('[degC]')
    ax_t.legend(loc='upper right', fontsize=7, ncol=3)
    ax_t.set_title(title, fontsize=10)
    power = sum(period[name].to_numpy() for name in case.power_outputs)
    ax_p.plot(days, power / 1000.0, color='tab:blue', lw=0.6, label='electric power')
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
