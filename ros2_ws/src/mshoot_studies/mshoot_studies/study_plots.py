"""
Figures of the reference study: one PNG per part.

Headless by construction: figures are :class:`matplotlib.figure.Figure` objects
drawn by the Agg canvas, never through pyplot (no display, no global state).
"""
from __future__ import annotations

import pathlib
from typing import Mapping, Sequence

import matplotlib
from matplotlib.axes import Axes
from matplotlib.figure import Figure
import numpy as np
import pandas as pd

from mshoot_studies.sweeps import RunOutcome

DPI = 110
MODEL_COLORS = {'python': 'black', 'svr': 'tab:blue', 'linear': 'tab:orange',
                'ridge': 'tab:green', 'knn': 'tab:red', 'random_forest': 'tab:purple',
                'mlp': 'tab:brown', 'fmu': 'tab:gray'}
MODEL_NAMES = {'python': 'R1C1 (exact)', 'svr': 'SVR', 'linear': 'linear', 'ridge': 'Ridge',
               'knn': 'k-NN', 'random_forest': 'random forest', 'mlp': 'MLP', 'fmu': 'FMU'}


def _save(fig: Figure, path: pathlib.Path) -> pathlib.Path:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    return path


def _band(ax: Axes, fine: pd.DataFrame) -> None:
    hours = fine.index.to_numpy(dtype=float) / 3600.0
    ax.fill_between(hours, fine['comfort_min'], fine['comfort_max'], step='post',
                    color='tab:green', alpha=0.15, label='comfort band')


def plot_verification(outcomes: Sequence[RunOutcome], path: pathlib.Path) -> pathlib.Path:
    """
    Part 1: zone temperature [degC] with the band and heat rate [kW] for each horizon.

    Parameters
    ----------
    outcomes : sequence of RunOutcome
        One run per horizon (same period).
    path : path
        PNG to write.

    """
    fig = Figure(figsize=(11, 7))
    ax_t, ax_q = fig.subplots(2, 1, sharex=True, gridspec_kw={'height_ratios': [3, 2]})
    colors = matplotlib.colormaps['viridis'](np.linspace(0.0, 0.9, len(outcomes)))
    _band(ax_t, outcomes[0].fine)
    for color, outcome in zip(colors, outcomes):
        k = outcome.kpis
        label = (f'H = {outcome.spec.horizon} h: {k["energy_kwh"]:.1f} kWh, '
                 f'{k["discomfort_kh_hourly"]:.1f} Kh')
        hours = outcome.fine.index.to_numpy(dtype=float) / 3600.0
        ax_t.plot(hours, outcome.fine['y_T'], color=color, lw=1.2, label=label)
        step_hours = outcome.steps.index.to_numpy(dtype=float) / 3600.0
        q = outcome.steps['q'].to_numpy(dtype=float) / 1000.0
        ax_q.step(np.append(step_hours, step_hours[-1] + 1.0), np.append(q, q[-1]),
                  where='post', color=color, lw=1.2)
    ax_t.set_ylabel('zone temperature [°C]')
    ax_t.legend(loc='upper left', fontsize=8, framealpha=0.9)
    ax_t.grid(alpha=0.3)
    ax_t.set_title('Control and emulation model: R1C1 FMU; energy and discomfort '
                   '(hourly samples) per horizon')
    ax_q.axhline(0.0, color='k', lw=0.5)
    ax_q.set_ylabel('heat rate q [kW]\n(+ heating, − cooling)')
    ax_q.set_xlabel('time from 2018-04-05 00:00 [h]')
    ax_q.grid(alpha=0.3)
    return _save(fig, path)


def plot_tolerance(ours: Sequence[Mapping], window: Sequence[Mapping],
                   gradients: Sequence[Mapping], path: pathlib.Path, *,
                   published_loose: tuple[float, float] | None, published: Mapping | None,
                   horizon: int, window_spec: tuple[int, int] | None = None) -> pathlib.Path:
    """
    Part 2: energy vs discomfort per tolerance; naive vs ours; gradient error vs tolerance.

    Parameters
    ----------
    ours : rows with tolerance, energy_kwh [kWh], discomfort_kh [K h]
        Our runs over the period at ``horizon``.
    window : rows with tolerance, method ('ours' / 'naive'), energy_kwh, steps
        The short-window comparison.
    gradients : rows of :func:`mshoot_studies.study.gradient_accuracy`
        Gradient errors against the exact derivative, per tolerance.
    path : path
        PNG to write.
    published_loose : (float, float) or None
        The ancestor's energy range at loose tolerances [kWh].
    published : mapping or None
        The ancestor's result at 1e-11 (``energy_kwh``, ``discomfort_kh_hourly``).
    horizon : int
        Horizon of ``ours`` [h].
    window_spec : (int, int), optional
        Horizon [h] and length [h] of the short window.

    """
    fig = Figure(figsize=(16, 5))
    axes = fig.subplots(1, 3)
    ax = axes[0]
    tols = [r['tolerance'] for r in ours]
    ax.semilogx(tols, [r['energy_kwh'] for r in ours], 'o-', color='tab:blue',
                label=f'ours: energy, H = {horizon} h')
    if published_loose is not None:
        ax.fill_between([1e-7, 1e-4], [published_loose[0]] * 2, [published_loose[1]] * 2,
                        color='tab:red', alpha=0.2, label='original: energy at 1e-4...1e-7')
    if published is not None:
        ax.semilogx([1e-11], [published['energy_kwh']], '*', ms=15, color='tab:red',
                    markeredgecolor='k', ls='none', label='original: energy at 1e-11')
    ax.set_ylim(0.0, max([r['energy_kwh'] for r in ours]
                         + ([published_loose[1]] if published_loose else []) + [0.01]) * 1.1)
    ax.invert_xaxis()
    ax.set_xlabel('FMU tolerance')
    ax.set_ylabel('energy [kWh]')
    ax_d = ax.twinx()
    ax_d.semilogx(tols, [r['discomfort_kh_hourly'] for r in ours], 's:', color='tab:green',
                  label='ours: discomfort (hourly samples)')
    if published is not None:
        ax_d.semilogx([1e-11], [published['discomfort_kh_hourly']], 'P', ms=11,
                      color='tab:green', markeredgecolor='k', ls='none',
                      label='original: discomfort at 1e-11')
    ax_d.set_ylim(0.0, max([r['discomfort_kh_hourly'] for r in ours]
                           + ([published['discomfort_kh_hourly']] if published else [])
                           + [0.01]) * 1.6)
    ax_d.set_ylabel('discomfort, hourly samples [Kh] (dotted)')
    handles, labels = ax.get_legend_handles_labels()
    handles_d, labels_d = ax_d.get_legend_handles_labels()
    ax.legend(handles + handles_d, labels + labels_d, fontsize=7, loc='lower left')
    ax.set_title('Whole period: energy and discomfort per tolerance')
    ax.grid(alpha=0.3)

    ax = axes[1]
    # energy over the steps the naive run finished (all of them unless its budget ran out)
    naive_rows = [r for r in window if r['method'] == 'naive']
    same_steps = {r['tolerance']: r.get('ours_energy_same_steps_kwh') for r in naive_rows}
    plotted = []
    for method, color, marker in (('ours', 'tab:blue', 'o'), ('naive', 'tab:red', 's')):
        rows = [r for r in window if r['method'] == method]
        x = [r['tolerance'] for r in rows]
        y = [(same_steps.get(r['tolerance']) or r['energy_kwh']) if method == 'ours'
             else r['energy_kwh'] for r in rows]
        plotted += y
        ax.plot(x, y, marker=marker, color=color, label=f'{method}: energy [kWh]')
        if method == 'naive':
            for r in rows:
                if r['steps'] < r['steps_requested']:
                    ax.annotate(f'{r["steps"]}/{r["steps_requested"]} steps\n(budget)',
                                (r['tolerance'], r['energy_kwh']), textcoords='offset points',
                                xytext=(0, 8), ha='center', fontsize=7, color=color)
    ax.set_xscale('log')
    ax.invert_xaxis()
    energies = [e for e in plotted if np.isfinite(e)]
    if energies:
        # at least +-10 % around the mean, so that tiny differences do not look large
        middle = 0.5 * (max(energies) + min(energies))
        half = max(0.55 * (max(energies) - min(energies)), 0.1 * abs(middle), 1e-3)
        ax.set_ylim(middle - half, middle + half)
    ax.set_xlabel('FMU tolerance')
    ax.set_ylabel('energy over the steps the naive run finished [kWh]')
    ax2 = ax.twinx()
    for method, color in (('ours', 'tab:blue'), ('naive', 'tab:red')):
        rows = [r for r in window if r['method'] == method]
        ax2.plot([r['tolerance'] for r in rows], [r['wall_per_step_s'] for r in rows], ls=':',
                 marker='.', color=color, label=f'{method}: wall per step [s]')
    ax2.set_yscale('log')
    ax2.set_ylabel('wall time per MPC step [s] (dotted)')
    handles = ax.get_legend_handles_labels()
    handles2 = ax2.get_legend_handles_labels()
    ax.legend(handles[0] + handles2[0], handles[1] + handles2[1], fontsize=8, loc='best')
    if window_spec is not None:
        ax.set_title(f'Naive vs ours: H = {window_spec[0]} h, {window_spec[1]} h')
    ax.grid(alpha=0.3)

    ax = axes[2]
    g_tols = [r['tolerance'] for r in gradients]
    ax.loglog(g_tols, [r['fd_median_rel_error'] for r in gradients], 's-', color='tab:red',
              label='naive finite difference, median')
    ax.loglog(g_tols, [r['fd_max_rel_error'] for r in gradients], 's:', color='tab:red',
              alpha=0.6, label='naive finite difference, max')
    if all('sens_median_rel_error' in r for r in gradients):
        floor = 1e-16
        ax.loglog(g_tols, [max(r['sens_median_rel_error'], floor) for r in gradients], 'o-',
                  color='tab:blue', label='our sensitivities, median')
        ax.loglog(g_tols, [max(r['sens_max_rel_error'], floor) for r in gradients], 'o:',
                  color='tab:blue', alpha=0.6, label='our sensitivities, max')
    ax.axhline(1.0, color='k', lw=0.5)
    ax.invert_xaxis()
    ax.set_xlabel('FMU tolerance')
    ax.set_ylabel('relative error of dT_end/dq [-]')
    ax.set_title('Gradient accuracy (1 h interval)')
    ax.grid(alpha=0.3, which='both')
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_data_driven(validations: Mapping[str, pd.DataFrame],
                     responses: Mapping[str, tuple[np.ndarray, np.ndarray]],
                     outcomes: Mapping[str, RunOutcome], path: pathlib.Path) -> pathlib.Path:
    """
    Part 3: validation free runs, one-step response to q, closed-loop temperatures.

    Parameters
    ----------
    validations : {model: DataFrame with T_true, T_free_run [degC], index time [s]}
        Free runs of each model over the validation data.
    responses : {model: (q [W], end temperature [degC])}
        One-step response of each model to the heat rate.
    outcomes : {model: RunOutcome}
        Closed-loop run of each model over the period.
    path : path
        PNG to write.

    """
    fig = Figure(figsize=(16, 9))
    grid = fig.add_gridspec(2, 2, height_ratios=[1, 1])
    ax_v = fig.add_subplot(grid[0, 0])
    ax_r = fig.add_subplot(grid[0, 1])
    ax_c = fig.add_subplot(grid[1, :])
    first = True
    for m, table in validations.items():
        days = (table.index.to_numpy(dtype=float) - float(table.index[0])) / 86400.0
        if first:
            ax_v.plot(days, table['T_true'], color='black', lw=2.0, label='R1C1 (truth)')
            first = False
        ax_v.plot(days, table['T_free_run'], color=MODEL_COLORS.get(m), lw=1.0,
                  label=MODEL_NAMES.get(m, m))
    ax_v.set_xlabel('validation time from 9 April [days]')
    ax_v.set_ylabel('zone temperature [°C]')
    ax_v.set_title('Validation: free run from the true initial state')
    ax_v.grid(alpha=0.3)
    ax_v.legend(fontsize=8, ncol=2)
    for m, (q, t_end) in responses.items():
        ax_r.plot(q / 1000.0, t_end, color=MODEL_COLORS.get(m), lw=2.0 if m == 'python' else 1.2,
                  label=MODEL_NAMES.get(m, m))
    ax_r.set_xlabel('heat rate q over the hour [kW]')
    ax_r.set_ylabel('temperature after 1 h [°C]')
    ax_r.set_title('One step from 21 °C against q (what the solver differentiates)')
    ax_r.grid(alpha=0.3)
    ax_r.legend(fontsize=8, ncol=2)
    some = max(outcomes.values(), key=lambda o: o.spec.hours)
    _band(ax_c, some.fine)
    for m, outcome in outcomes.items():
        if outcome.completed_steps == 0:
            continue
        k = outcome.kpis
        hours = outcome.fine.index.to_numpy(dtype=float) / 3600.0
        cut = '' if outcome.finished else f', {outcome.completed_steps} steps (budget)'
        if outcome.spec.hours < some.spec.hours:
            cut += f', first {outcome.spec.hours} h'
        ax_c.plot(hours, outcome.fine['y_T'], color=MODEL_COLORS.get(m),
                  lw=2.0 if m == 'python' else 1.1,
                  label=f'{MODEL_NAMES.get(m, m)}: {k["energy_kwh"]:.1f} kWh, '
                        f'{k["discomfort_kh"]:.1f} Kh{cut}')
    ax_c.set_xlabel('time from 2018-04-05 00:00 [h]')
    ax_c.set_ylabel('zone temperature [°C]')
    ax_c.set_title('Closed loop, each model as the control model, R1C1 emulator '
                   f'(H = {some.spec.horizon} h, SLSQP)')
    ax_c.grid(alpha=0.3)
    ax_c.legend(fontsize=8, ncol=2, loc='upper left')
    return _save(fig, path)


def plot_time(rows: Sequence[Mapping], path: pathlib.Path, hours: int) -> pathlib.Path:
    """
    Part 4: wall time [s] and median solve time [s] against the horizon [h].

    Parameters
    ----------
    rows : rows with horizon_h and ``<model>_wall_s``, ``<model>_solve_s_median``
        for model in fmu, python, svr, and ``published_wall_s``.
    path : path
        PNG to write.
    hours : int
        Simulated period [h] (for the labels).

    """
    fig = Figure(figsize=(13, 5))
    ax_w, ax_s = fig.subplots(1, 2)
    horizons = [r['horizon_h'] for r in rows]
    for m, label in (('fmu', 'R1C1 FMU'), ('python', 'R1C1 Python'), ('svr', 'SVR')):
        ax_w.semilogy(horizons, [r[f'{m}_wall_s'] for r in rows], 'o-',
                      color=MODEL_COLORS[m], label=label)
        ax_s.semilogy(horizons, [r[f'{m}_solve_s_median'] for r in rows], 'o-',
                      color=MODEL_COLORS[m], label=label)
    pub = [(r['horizon_h'], r['published_wall_s']) for r in rows
           if r.get('published_wall_s') is not None]
    if pub:
        ax_w.semilogy([p[0] for p in pub], [p[1] for p in pub], '*', ms=14,
                      color='tab:red', markeredgecolor='k', label='original (FMU), published')
    ax_w.set_xlabel('horizon H [h]')
    ax_w.set_ylabel(f'wall time of the {hours} h closed loop [s]')
    ax_w.set_title('Whole run')
    ax_w.grid(alpha=0.3, which='both')
    ax_w.legend(fontsize=9)
    ax_s.set_xlabel('horizon H [h]')
    ax_s.set_ylabel('median solve time per MPC step [s]')
    ax_s.set_title('One MPC step')
    ax_s.grid(alpha=0.3, which='both')
    ax_s.legend(fontsize=9)
    return _save(fig, path)


def plot_tradeoff(curves: Mapping[str, Sequence[Mapping]], hard: Mapping[str, RunOutcome],
                  path: pathlib.Path) -> pathlib.Path:
    """
    Part 5: energy [kWh] vs discomfort [K h] per cost; q of the hard-comfort runs.

    Parameters
    ----------
    curves : {cost: rows with comfort, soft_penalty, energy_kwh, discomfort_kh}
        Trade-off curve of each cost.
    hard : {cost: RunOutcome}
        Run of each cost with hard comfort.
    path : path
        PNG to write.

    """
    fig = Figure(figsize=(15, 5.5))
    ax_c, ax_q = fig.subplots(1, 2, gridspec_kw={'width_ratios': [1, 1.4]})
    colors = {'quadratic': 'tab:blue', 'energy': 'tab:orange'}
    names = {'quadratic': 'quadratic cost Σq²', 'energy': 'energy cost Σ|q|'}
    for cost, rows in curves.items():
        soft = sorted((r for r in rows if r['comfort'] == 'soft'),
                      key=lambda r: r['discomfort_kh'])
        ax_c.plot([r['discomfort_kh'] for r in soft], [r['energy_kwh'] for r in soft], 'o-',
                  color=colors[cost], label=f'{names[cost]}, soft comfort')
        for r in soft:
            ax_c.annotate(f'w={r["soft_penalty"]:g}', (r['discomfort_kh'], r['energy_kwh']),
                          textcoords='offset points', xytext=(5, -10), fontsize=7,
                          color=colors[cost])
        for r in rows:
            if r['comfort'] == 'hard':
                ax_c.plot([r['discomfort_kh']], [r['energy_kwh']], marker='*', ms=15,
                          color=colors[cost], markeredgecolor='k', ls='none',
                          label=f'{names[cost]}, hard comfort')
    ax_c.set_xlabel('discomfort [Kh]')
    ax_c.set_ylabel('energy [kWh]')
    ax_c.set_title('Energy-discomfort trade-off (soft penalty weight w)')
    ax_c.grid(alpha=0.3)
    ax_c.legend(fontsize=8)
    for cost, outcome in hard.items():
        steps_h = outcome.steps.index.to_numpy(dtype=float) / 3600.0
        q = outcome.steps['q'].to_numpy(dtype=float) / 1000.0
        k = outcome.kpis
        ax_q.step(np.append(steps_h, steps_h[-1] + 1.0), np.append(q, q[-1]), where='post',
                  color=colors[cost], lw=1.3,
                  label=f'{names[cost]}: {k["energy_kwh"]:.1f} kWh, '
                        f'{k["discomfort_kh"]:.2f} Kh')
    ax_q.axhline(0.0, color='k', lw=0.5)
    ax_q.set_xlabel('time from 2018-04-05 00:00 [h]')
    ax_q.set_ylabel('heat rate q [kW] (+ heating, − cooling)')
    ax_q.set_title('Applied heat rate, hard comfort')
    ax_q.grid(alpha=0.3)
    ax_q.legend(fontsize=8, loc='lower left')
    return _save(fig, path)
