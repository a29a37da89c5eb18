"""Figures of closed-loop runs (matplotlib, headless)."""
from __future__ import annotations

import pathlib

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402


def plot_closed_loop(fine: pd.DataFrame, steps: pd.DataFrame, path: str | pathlib.Path,
                     title: str = '', temperature_column: str = 'y_T',
                     control: str = 'q') -> pathlib.Path:
    """
    Plot the zone temperature with its comfort band and the heat rate.

    Parameters
    ----------
    fine : DataFrame
        Fine-grid trajectory indexed by time [s] with the temperature [degC]
        and ``comfort_min``/``comfort_max`` [degC].
    steps : DataFrame
        Per-step records indexed by time [s] with the applied control [W].
    path : path-like
        PNG file to write.
    title : str
        Figure title (e.g. the KPIs).
    temperature_column : str
        Column of ``fine`` with the zone temperature [degC].
    control : str
        Column of ``steps`` with the applied heat rate [W].

    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    hours = fine.index.to_numpy(dtype=float) / 3600.0
    fig, (ax_t, ax_q) = plt.subplots(2, 1, sharex=True, figsize=(10, 6),
                                     gridspec_kw={'height_ratios': [3, 2]})
    ax_t.fill_between(hours, fine['comfort_min'], fine['comfort_max'], step='post',
                      color='tab:green', alpha=0.15, label='comfort band')
    ax_t.plot(hours, fine[temperature_column], color='tab:red', lw=1.5, label='zone T')
    ax_t.set_ylabel('temperature [°C]')
    ax_t.legend(loc='lower left', framealpha=0.9)
    ax_t.grid(alpha=0.3)
    step_hours = steps.index.to_numpy(dtype=float) / 3600.0
    q_kw = steps[control].to_numpy(dtype=float) / 1000.0
    ax_q.step(step_hours, q_kw, where='post', color='tab:blue', lw=1.5)
    ax_q.axhline(0.0, color='k', lw=0.5)
    ax_q.set_ylabel('heat rate q [kW]\n(+ heating, − cooling)')
    ax_q.set_xlabel('time [h]')
    ax_q.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
