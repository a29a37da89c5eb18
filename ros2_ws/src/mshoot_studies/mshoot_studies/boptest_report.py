"""
The report of BOPTEST runs: KPI table (markdown) and figures (matplotlib, Agg).

- :func:`kpi_table`: KPI records (``<out>/kpis.json``) as a markdown table;
- :func:`count_starts`: off -> on transitions of a signal (e.g. a heat pump's modulation);
- :func:`plot_run`: one run: every zone's temperature with its band (and setpoints named by the
  caller), the power of every energy vector with the electricity price;
- :func:`plot_kpi_bars`: thermal discomfort, energy and cost of the controllers side by side;
- :func:`plot_zones`: one period, a panel per zone: its band and its temperature under every
  controller, so that whose discomfort is where shows at a glance.
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
                 ('price', 'price', '{}'), ('uncertainty', 'forecast', '{}'),
                 ('seed', 'seed', '{}'), ('tdis_tot', 'tdis [K h]', '{:.2f}'),
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


def plot_zones(case: TestCase, runs: Mapping[str, pd.DataFrame], start_s: float, end_s: float,
               title: str, path: pathlib.Path) -> pathlib.Path:
    """
    Draw one period, a panel per zone: the band and the zone's temperature under each run.

    Parameters
    ----------
    case : TestCase
        The test case (zones, bands, the zone temperature outputs).
    runs : dict of str to pd.DataFrame
        Legend label (e.g. the controller) -> the run's record table (``time`` [s from
        1 January] and the zone temperature outputs [K]).
    start_s, end_s : float
        The test period [s].
    title : str
        Figure title.
    path : pathlib.Path
        The PNG file.

    Raises
    ------
    ValueError
        For no run, or a run without a zone's temperature output.

    """
    if not runs:
        raise ValueError('plot_zones: no run to draw')
    outputs = case.zone_temperature_outputs
    for label, records in runs.items():
        missing = [name for names in outputs.values() for name in names
                   if name not in records]
        if missing:
            raise ValueError(f'plot_zones: run {label!r} has no {missing}')
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(len(outputs), 1, figsize=(10, 2.4 * len(outputs) + 0.6),
                             sharex=True, squeeze=False)
    grid = np.arange(start_s, end_s + 1.0, 900.0)
    days = (grid - start_s) / 86400.0
    for ax, (zone, names) in zip(axes[:, 0], outputs.items()):
        lower, upper = case.band_columns(zone)
        ax.fill_between(days, case.lookup(lower, grid) - KELVIN,
                        case.lookup(upper, grid) - KELVIN, step='post', color='0.85',
                        label='comfort band')
        for label, records in runs.items():
            period = records[(records['time'] >= start_s) & (records['time'] <= end_s)]
            t = (period['time'].to_numpy() - start_s) / 86400.0
            for name in names:
                ax.plot(t, period[name].to_numpy() - KELVIN, lw=0.8, label=label)
        ax.set_ylabel(f'{zone} [degC]')
        ax.legend(loc='upper right', fontsize=7, ncol=len(runs) + 1)
    axes[0, 0].set_title(title, fontsize=10)
    axes[-1, 0].set_xlabel(f'days from the start of the test period ({start_s / 86400:.0f} d)')
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _level_stats(records: Sequence[Mapping[str, object]], key: str) -> dict[tuple, dict]:
    """Return per (period, price, level) the mean, min, max and count of ``key``."""
    frame = pd.DataFrame(list(records))
    out = {}
    for group, rows in frame.groupby(['period', 'price', 'uncertainty'], sort=False):
        values = rows[key].to_numpy(dtype=float)
        out[group] = {'mean': float(values.mean()), 'min': float(values.min()),
                      'max': float(values.max()), 'n': int(values.size)}
    return out


def uncertainty_table(records: Sequence[Mapping[str, object]],
                      levels: Sequence[str] = ('none', 'low', 'medium', 'high'),
                      against: Sequence[str] = ('baseline', 'rule')) -> list[str]:
    """
    Return mshoot's KPIs per forecast uncertainty level beside the forecast-free controllers.

    One row per period and price: the ``against`` controllers' ``tdis_tot`` / ``cost_tot``,
    mshoot's at each level present (the mean over the level's seeds, with the range when there
    are several), whether mshoot's mean at the highest level is lower on both than every
    ``against`` controller, and its loss against its own perfect-forecast run (cost [%],
    discomfort [K h]).

    Parameters
    ----------
    records : sequence of dict
        KPI records with ``controller``, ``period``, ``price``, ``uncertainty``, ``tdis_tot``,
        ``cost_tot``.
    levels : sequence of str
        The levels, in column order (those without a record are left out).
    against : sequence of str
        The controllers mshoot is compared with.

    """
    mshoot = [r for r in records if r['controller'] == 'mshoot']
    present = [lv for lv in levels if any(r.get('uncertainty') == lv for r in mshoot)]
    if not mshoot or not present:
        return []
    tdis, cost = _level_stats(mshoot, 'tdis_tot'), _level_stats(mshoot, 'cost_tot')
    others = {(r['controller'], r['period'], r['price']): r for r in records
              if r['controller'] in against}
    top = present[-1]

    def cell(key: tuple) -> str:
        if key not in tdis:
            return '-'
        t, c = tdis[key], cost[key]
        if t['n'] == 1:
            return f'{t["mean"]:.2f} / {c["mean"]:.4f}'
        return (f'{t["mean"]:.2f} [{t["min"]:.2f}-{t["max"]:.2f}] / {c["mean"]:.4f} '
                f'[{c["min"]:.4f}-{c["max"]:.4f}]')

    seeds = {lv: max(v['n'] for k, v in tdis.items() if k[2] == lv) for lv in present}
    lines = ['| period | price | ' + ' | '.join(f'{c} tdis / cost' for c in against) + ' | '
             + ' | '.join(f'mshoot {lv}' + (f' (mean [range] of {seeds[lv]} seeds)'
                                            if seeds[lv] > 1 else '') for lv in present)
             + f' | {top}: better on both | {top} - none: cost [%] / tdis [K h] |',
             '|---|---|' + '---|' * (len(against) + len(present) + 2)]
    wins = total = 0
    for period, price in dict.fromkeys((r['period'], r['price']) for r in mshoot):
        row = [others.get((c, period, price)) for c in against]
        cells = [f'{o["tdis_tot"]:.2f} / {o["cost_tot"]:.4f}' if o else '-' for o in row]
        cells += [cell((period, price, lv)) for lv in present]
        key = (period, price, top)
        better = key in tdis and all(o is not None and tdis[key]['mean'] < o['tdis_tot']
                                     and cost[key]['mean'] < o['cost_tot'] for o in row)
        wins += better
        total += key in tdis
        base = (period, price, 'none')
        loss = (f'{100 * (cost[key]["mean"] / cost[base]["mean"] - 1):+.1f} / '
                f'{tdis[key]["mean"] - tdis[base]["mean"]:+.2f}'
                if key in tdis and base in tdis and top != 'none' else '-')
        cells += ['yes' if better else '**no**', loss]
        lines.append(f'| {period} | {price} | ' + ' | '.join(cells) + ' |')
    return [*lines, '', f'mshoot under `{top}` (mean over its seeds) is lower on both '
            f'`tdis_tot` and `cost_tot` than {" and ".join(against)} in {wins} of {total} '
            'runs.', '']


def plot_uncertainty(case: TestCase, records: Sequence[Mapping[str, object]], now_s: float,
                     path: pathlib.Path, horizon_s: float = 36 * 3600.0, draws: int = 30,
                     levels: Sequence[str] = ('low', 'medium', 'high')) -> pathlib.Path:
    """
    Draw the forecast bands against the truth, and mshoot's KPIs per uncertainty level.

    Top: the outdoor temperature and the irradiance a forecast request at ``now_s`` gets
    (:class:`mshoot_core.forecast.ForecastSource`, horizon ``horizon_s``), the 5-95 % band of
    ``draws`` seeds per level, against the test case's data. Bottom: mshoot's ``tdis_tot`` and
    ``cost_tot`` relative to its perfect-forecast run per level (mean over seeds; one line
    per period and price), the baseline's and the rule's as horizontal marks per run.

    Parameters
    ----------
    case : TestCase
        The test case.
    records : sequence of dict
        KPI records (``controller``, ``period``, ``price``, ``uncertainty``, KPIs).
    now_s : float
        Time of the forecast request [s from 1 January].
    path : pathlib.Path
        The PNG file.
    horizon_s : float
        The forecast's horizon [s].
    draws : int
        Seeds drawn per level (1..draws).
    levels : sequence of str
        The levels whose bands are drawn.

    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from mshoot_core.forecast import ForecastSource, SOLAR_POINT, TEMPERATURE_POINT
    from mshoot_core.settings import ForecastErrorSettings
    fig, axes = plt.subplots(2, 2, figsize=(12, 7))
    times = np.arange(now_s, now_s + horizon_s + 1.0, 900.0)
    hours = (times - now_s) / 3600.0
    for ax, point, offset, unit in ((axes[0, 0], TEMPERATURE_POINT, -KELVIN, 'degC'),
                                    (axes[0, 1], SOLAR_POINT, 0.0, 'W/m2')):
        for level, alpha in reversed(list(zip(levels, (0.55, 0.35, 0.2)))):  # narrow on top
            values = np.array([ForecastSource.from_test_case(case, ForecastErrorSettings(
                temperature_uncertainty=level, solar_uncertainty=level, seed=seed)).forecast(
                now_s, horizon_s, 900.0, [point])[point].to_numpy() for seed in
                range(1, draws + 1)])
            ax.fill_between(hours, np.percentile(values, 5, axis=0) + offset,
                            np.percentile(values, 95, axis=0) + offset, alpha=alpha,
                            label=f'{level}: 5-95 % of {draws} seeds')
        ax.plot(hours, case.forecast_values(point, times) + offset, 'k', lw=1.2, label='truth')
        ax.set_ylabel(f'{point} [{unit}]')
        ax.set_xlabel(f'hours from the request at day {now_s / 86400:.0f} of the year')
        ax.legend(fontsize=7, loc='upper right')
    frame = pd.DataFrame([r for r in records if r['controller'] == 'mshoot'])
    order = ['none', *levels]
    if not frame.empty:
        for ax, key, label in ((axes[1, 0], 'tdis_tot', 'mshoot tdis [K h]'),
                               (axes[1, 1], 'cost_tot', 'mshoot cost / perfect-forecast cost')):
            for (period, price), rows in frame.groupby(['period', 'price'], sort=False):
                means = rows.groupby('uncertainty')[key].mean()
                present = [lv for lv in order if lv in means.index]
                y = means[present].to_numpy()
                if key == 'cost_tot' and 'none' in means.index:
                    y = y / float(means['none'])
                ax.plot([order.index(lv) for lv in present], y, 'o-', ms=3, lw=0.8,
                        label=f'{period.replace("_heat_day", "")} {price.replace("_", " ")}')
            ax.set_xticks(range(len(order)), order)
            ax.set_xlabel('forecast uncertainty (temperature and solar)')
            ax.set_ylabel(label)
        axes[1, 0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
