"""
The files of a closed-loop run: KPIs, per-step records, trajectories and a plot.

One writer for every way a run is made (the core loop, the ROS nodes, the
applications), so their output folders read alike.
"""
from __future__ import annotations

import json
import pathlib
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from mshoot_core.closed_loop import ClosedLoopResult

if TYPE_CHECKING:  # matplotlib only where plots are made
    from mshoot_core.plotting import PlotWorker


def write_outputs(out: pathlib.Path, result: ClosedLoopResult, kpis: dict,
                  title: str, plotter: PlotWorker | None = None, *, control: str = 'q',
                  temperature_column: str = 'y_T') -> None:
    """
    Write ``kpis.json``, ``trajectories.csv``, ``steps.csv`` and ``plot.png`` to ``out``.

    Parameters
    ----------
    out : path
        Output folder (created if missing).
    result : ClosedLoopResult
        The run's records: ``steps`` (one row per control step, index time [s])
        and ``fine`` (the emulated trajectory, index time [s]).
    kpis : dict
        :func:`mshoot_core.kpis.closed_loop_kpis` figures (energy [kWh],
        discomfort [K h], wall time [s], ...) plus anything JSON-ready.
    title : str
        First line of the plot's title (the KPIs make the second).
    plotter : PlotWorker, optional
        A worker process started with the run (:class:`mshoot_core.plotting.PlotWorker`):
        it draws the figure while the other files are written. Default: the
        figure is drawn in this process. Either way the PNG is written when
        this function returns.
    control, temperature_column : str
        The heat rate column of ``steps`` [W] and the zone temperature column of
        ``fine`` [degC] plotted (a multi-zone run: those of its first zone).

    """
    out.mkdir(parents=True, exist_ok=True)
    subtitle = (f"{kpis['energy_kwh']:.1f} kWh, {kpis['discomfort_kh']:.1f} Kh "
                f"({kpis['discomfort_kh_hourly']:.1f} Kh hourly), wall {kpis['wall_s']:.1f} s")
    if plotter is not None:
        plotter.send(result.fine, result.steps, out / 'plot.png', f'{title}\n{subtitle}',
                     temperature_column, control)
    (out / 'kpis.json').write_text(json.dumps(kpis, indent=2, sort_keys=True) + '\n')
    write_csv(result.fine, out / 'trajectories.csv', index_label='time_s')
    result.steps.to_csv(out / 'steps.csv', index_label='time_s')
    if plotter is not None:
        plotter.wait()
    else:
        from mshoot_core.plotting import plot_closed_loop
        plot_closed_loop(result.fine, result.steps, out / 'plot.png', f'{title}\n{subtitle}',
                         temperature_column=temperature_column, control=control)


#: Characters that make the csv module quote a field (QUOTE_MINIMAL), or that a label must not
#: start or end with for the fast writer.
_QUOTED = frozenset(',"\r\n')


def write_csv(frame: pd.DataFrame, path: pathlib.Path, index_label: str) -> None:
    """
    Write ``frame`` as ``frame.to_csv(path, index_label=index_label)`` does, faster when it can.

    A frame of floats (index and columns) with plain labels is written by formatting
    each value as pandas does (``repr`` of the float, NaN as an empty field): the same
    bytes, several times faster than pandas' writer for the fine grid of a run. Any other
    frame goes to ``to_csv``.
    """
    labels = [index_label, *frame.columns]
    plain = all(isinstance(label, str) and label and not (_QUOTED & set(label))
                and label == label.strip() for label in labels)
    floats = frame.index.dtype == np.float64 and all(
        dtype == np.float64 for dtype in frame.dtypes)
    if not (plain and floats) or frame.columns.nlevels > 1 or frame.index.nlevels > 1:
        frame.to_csv(path, index_label=index_label)
        return

    columns = [frame.index.to_numpy(dtype=np.float64)]
    columns += [frame.iloc[:, j].to_numpy(dtype=np.float64) for j in range(frame.shape[1])]
    bits = [np.ascontiguousarray(column).view(np.int64) for column in columns]
    texts: list[list[str]] = []
    for j, column in enumerate(bits):  # a column equal to an earlier one, bit for bit: its fields
        same = next((i for i in range(j) if np.array_equal(column, bits[i])), None)
        texts.append(texts[same] if same is not None else _float_fields(column))
    lines = [','.join(labels), *map(','.join, zip(*texts)), '']
    pathlib.Path(path).write_text('\n'.join(lines), encoding='utf-8')


def _float_fields(bits: np.ndarray) -> list[str]:
    """
    Return the CSV fields of a float64 column given as its bits (int64): each ``repr``.

    NaN gives an empty field, as pandas' ``na_rep``. Each distinct value (bit for bit, so
    -0.0 and 0.0 apart) is formatted once: a run's controls and comfort band repeat over the
    fine grid.
    """
    distinct, inverse = np.unique(bits, return_inverse=True)
    fields = np.array([repr(value) if value == value else ''
                       for value in distinct.view(np.float64).tolist()], dtype=object)
    return fields[inverse.reshape(-1)].tolist()
