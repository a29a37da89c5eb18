"""
Figures of closed-loop runs (matplotlib, headless), drawn here or in a worker process.

:func:`plot_closed_loop` draws the figure of a run in this process.
:class:`PlotWorker` draws it in a process of its own, started when a run
begins: that process imports matplotlib (the costliest import of a run's
output) while the run computes, then draws the figure it is sent at the end,
while the run writes its other files. A command that makes one figure is then
shorter by the import, on a machine with a core to spare.

This module imports only the standard library at load time (a command can
start the worker before it loads anything else; the worker runs this file as
a script, ``python -I plotting.py``, with nothing of mshoot_core on its
path); matplotlib is imported where a figure is drawn, with the Agg backend
and without pyplot.
"""
from __future__ import annotations

import logging
import os
import pathlib
import pickle
import subprocess
import sys
import tempfile
import threading
from typing import Any, TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

logger = logging.getLogger(__name__)

#: Resolution of the figure [dots per inch] (10 x 6 in).
DPI = 100
#: zlib level of the PNG: 1 writes it several times faster than the default 6, for a
#: file about a third larger.
PNG_COMPRESSION = 1
#: The PNG's Software text (as matplotlib's writer puts it).
PNG_SOFTWARE = 'Matplotlib version{version}, https://matplotlib.org/'
#: Seconds to wait for the worker's figure before drawing it here instead.
WORKER_TIMEOUT_S = 120.0


def closed_loop_series(fine: Any, steps: Any, temperature_column: str = 'y_T',
                       control: str = 'q') -> dict[str, np.ndarray]:
    """
    Return the arrays the figure of a run shows, from its records.

    Parameters
    ----------
    fine : DataFrame
        Fine-grid trajectory indexed by time [s] with the temperature [degC]
        and ``comfort_min``/``comfort_max`` [degC].
    steps : DataFrame
        Per-step records indexed by time [s] with the applied control [W].
    temperature_column : str
        Column of ``fine`` holding the zone temperature [degC].
    control : str
        Column of ``steps`` holding the heat rate [W].

    Returns
    -------
    dict of ndarray
        ``hours`` [h], ``comfort_min``, ``comfort_max``, ``temperature`` [degC]
        on the fine grid; ``step_hours`` [h] and ``q_kw`` [kW] per step.

    """
    return {'hours': fine.index.to_numpy(dtype=float) / 3600.0,
            'comfort_min': fine['comfort_min'].to_numpy(dtype=float),
            'comfort_max': fine['comfort_max'].to_numpy(dtype=float),
            'temperature': fine[temperature_column].to_numpy(dtype=float),
            'step_hours': steps.index.to_numpy(dtype=float) / 3600.0,
            'q_kw': steps[control].to_numpy(dtype=float) / 1000.0}


def _figure() -> tuple[Any, Any, Any]:
    """
    Build the figure of a run without its data.

    Two axes (temperature above, heat rate below), labels, grids, fixed margins (no layout pass at
    draw time).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(10, 6), dpi=DPI)
    FigureCanvasAgg(fig)
    ax_t, ax_q = fig.subplots(2, 1, sharex=True, gridspec_kw={'height_ratios': [3, 2]})
    fig.subplots_adjust(left=0.085, right=0.985, bottom=0.085, top=0.875, hspace=0.07)
    ax_t.set_ylabel('temperature [°C]')
    ax_t.grid(alpha=0.3)
    ax_q.axhline(0.0, color='k', lw=0.5)
    ax_q.set_ylabel('heat rate q [kW]\n(+ heating, − cooling)')
    ax_q.set_xlabel('time [h]')
    ax_q.grid(alpha=0.3)
    return fig, ax_t, ax_q


def _draw_data(figure: tuple[Any, Any, Any], series: dict[str, np.ndarray], title: str) -> None:
    """Add the run's data and title to a :func:`_figure`."""
    fig, ax_t, ax_q = figure
    hours = series['hours']
    ax_t.fill_between(hours, series['comfort_min'], series['comfort_max'], step='post',
                      color='tab:green', alpha=0.15, label='comfort band')
    ax_t.plot(hours, series['temperature'], color='tab:red', lw=1.5, label='zone T')
    ax_t.legend(loc='lower left', framealpha=0.9)
    ax_q.step(series['step_hours'], series['q_kw'], where='post', color='tab:blue', lw=1.5)
    if title:
        fig.suptitle(title)


def _finish(figure: tuple[Any, Any, Any], series: dict[str, np.ndarray],
            path: str | pathlib.Path, title: str) -> pathlib.Path:
    """Add the run's data and title to a :func:`_figure` and write the PNG."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _draw_data(figure, series, title)
    figure[0].canvas.draw()
    path.write_bytes(_png(figure[0].canvas.buffer_rgba(), figure[0].dpi))
    return path


def _png(rgba: Any, dpi: float) -> bytes:
    """
    Return the PNG of an RGBA image (rows top down), as ``savefig`` writes it, faster.

    The pixels, resolution and Software text of matplotlib's PNG (through Pillow) for the
    pixels of its Agg canvas, written here: every row with PNG's 'up' filter (the difference
    to the row above, one numpy subtraction), then zlib at :data:`PNG_COMPRESSION`. About a
    third of the time of Pillow's encoder, whose filter is chosen per row, for a file of
    about the same size.
    """
    import struct
    import zlib

    import matplotlib
    import numpy as np
    pixels = np.asarray(rgba, dtype=np.uint8)
    height, width, channels = pixels.shape
    rows = pixels.reshape(height, width * channels)
    raw = np.empty((height, 1 + width * channels), dtype=np.uint8)
    raw[0, 0], raw[1:, 0] = 0, 2  # the first row as it is (filter 0), the others 'up' (2)
    raw[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=raw[1:, 1:])  # modulo 256, as PNG's filter
    per_metre = int(round(dpi / 0.0254))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack('>I', len(data)) + kind + data
                + struct.pack('>I', zlib.crc32(kind + data)))

    software = PNG_SOFTWARE.format(version=matplotlib.__version__).encode('latin-1')
    return b''.join([
        b'\x89PNG\r\n\x1a\n',
        chunk(b'IHDR', struct.pack('>IIBBBBB', width, height, 8, 6, 0, 0, 0)),  # 8-bit RGBA
        chunk(b'tEXt', b'Software\x00' + software),
        chunk(b'pHYs', struct.pack('>IIB', per_metre, per_metre, 1)),
        chunk(b'IDAT', zlib.compress(raw.tobytes(), PNG_COMPRESSION)),
        chunk(b'IEND', b'')])


def _rehearse(figure: tuple[Any, Any, Any]) -> None:
    """
    Lay out a :func:`_figure` once with made-up data of a typical run, then take the data away.

    What that first layout makes stays for the real draw: the tick marks and labels of a
    72 h run's axes, the text layouts of their labels, of the legend and of a two-line
    title, the fonts. It is a draw without rendering (``Figure.draw_without_rendering``):
    rendering it too made the real draw no faster, for a third more CPU. The figure is
    left as :func:`_figure` made it (no data, limits automatic again), so the real data
    draws the same figure as without the rehearsal.
    """
    import numpy as np  # (this module loads with the standard library only)
    fig, ax_t, ax_q = figure
    hours = np.arange(73.0)
    band = np.where((hours % 24 >= 8) & (hours % 24 < 17), 1.0, 0.0)
    _draw_data(figure, {'hours': hours, 'comfort_min': 21.0 - 2.0 * band,
                        'comfort_max': 22.0 + 2.0 * band,
                        'temperature': 21.0 + 2.5 * np.sin(hours / 6.0),
                        'step_hours': hours[:-1], 'q_kw': 2.0 * np.cos(hours[:-1] / 5.0)},
               '49.9 kWh, 8.5 Kh (8.1 Kh hourly), wall 1.0 s\nou44: H = 10 h, control fmu')
    fig.draw_without_rendering()
    for axes in (ax_t, ax_q):
        for artist in [*axes.collections, *axes.lines[1 if axes is ax_q else 0:]]:
            artist.remove()  # (ax_q keeps its zero line)
        if axes.get_legend() is not None:
            axes.get_legend().remove()
        axes.relim()
        axes.set_autoscale_on(True)
    fig.suptitle('')


def draw_closed_loop(series: dict[str, np.ndarray], path: str | pathlib.Path,
                     title: str = '') -> pathlib.Path:
    """
    Draw the zone temperature with its comfort band and the heat rate to a PNG.

    Parameters
    ----------
    series : dict of ndarray
        As :func:`closed_loop_series` returns.
    path : path-like
        PNG file to write (its folder is created).
    title : str
        Figure title (e.g. the KPIs).

    """
    return _finish(_figure(), series, path, title)


def plot_closed_loop(fine: Any, steps: Any, path: str | pathlib.Path, title: str = '',
                     temperature_column: str = 'y_T', control: str = 'q') -> pathlib.Path:
    """
    Plot the zone temperature with its comfort band and the heat rate (in this process).

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
        Column of ``fine`` holding the zone temperature [degC].
    control : str
        Column of ``steps`` holding the heat rate [W].

    """
    return draw_closed_loop(closed_loop_series(fine, steps, temperature_column, control), path,
                            title)


class PlotWorker:
    """
    A process that imports matplotlib now and draws one closed-loop figure later.

    Start it when a run begins; :meth:`send` gives it the figure's data (and
    returns at once), :meth:`wait` waits for the PNG; :meth:`plot` does both.
    Whatever goes wrong with the worker (it cannot start, fails or times out),
    :meth:`wait` draws the figure in this process instead, with a logged
    warning: the figure is never lost. Use as a context manager, or call
    :meth:`close`, so an unused worker does not outlive the run.
    """

    def __init__(self) -> None:
        self._process: subprocess.Popen | None = None
        self._errors = tempfile.TemporaryFile()
        self._sender: threading.Thread | None = None
        self._request: tuple[dict, pathlib.Path, str] | None = None
        try:
            # -I: the worker sees neither the environment's paths nor this module's folder
            self._process = subprocess.Popen(
                [sys.executable, '-I', str(pathlib.Path(__file__).resolve())],
                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._errors)
        except OSError as exc:
            logger.warning('plot worker not started (%s): the figure is drawn in this process',
                           exc)

    def send(self, fine: Any, steps: Any, path: str | pathlib.Path, title: str = '',
             temperature_column: str = 'y_T', control: str = 'q') -> None:
        """Give the worker the figure of :func:`plot_closed_loop` to draw; do not wait."""
        if self._request is not None:
            raise RuntimeError('a PlotWorker draws one figure')
        series = closed_loop_series(fine, steps, temperature_column, control)
        path = pathlib.Path(path).resolve()
        self._request = (series, path, title)
        if self._process is not None:
            payload = pickle.dumps({'series': series, 'path': str(path), 'title': title},
                                   protocol=pickle.HIGHEST_PROTOCOL)
            # a payload larger than the pipe's buffer waits for the worker to read it
            self._sender = threading.Thread(target=self._write, args=(self._process, payload),
                                            daemon=True)
            self._sender.start()

    @staticmethod
    def _write(process: subprocess.Popen, payload: bytes) -> None:
        try:
            process.stdin.write(payload)
            process.stdin.close()
        except (OSError, ValueError):  # the worker is gone: wait() draws the figure here
            pass

    def wait(self) -> pathlib.Path:
        """Return the PNG of the figure sent, once written (drawn here if the worker failed)."""
        if self._request is None:
            raise RuntimeError('no figure sent to the PlotWorker')
        series, path, title = self._request
        process, self._process = self._process, None
        if process is not None:
            # a blocking wait, returning the moment the worker ends (Popen.wait with a timeout
            # polls, sleeping up to 50 ms between looks); a timer kills a worker that hangs
            watchdog = threading.Timer(WORKER_TIMEOUT_S, process.kill)
            watchdog.daemon = True
            watchdog.start()
            try:
                self._sender.join(WORKER_TIMEOUT_S)
                code = process.wait()
                timed_out = not watchdog.is_alive()
                watchdog.cancel()
                if code == 0 and path.is_file() and not timed_out:
                    return path
                self._errors.seek(0)
                reason = (f'no figure after {WORKER_TIMEOUT_S:g} s' if timed_out else
                          f'exit code {code}: {self._errors.read().decode(errors="replace")}')
            finally:
                watchdog.cancel()
                self._errors.close()
            logger.warning('plot worker failed (%s): the figure is drawn in this process',
                           reason.strip())
        return draw_closed_loop(series, path, title)

    def plot(self, fine: Any, steps: Any, path: str | pathlib.Path, title: str = '',
             temperature_column: str = 'y_T', control: str = 'q') -> pathlib.Path:
        """:meth:`send` and :meth:`wait`: the PNG of :func:`plot_closed_loop`."""
        self.send(fine, steps, path, title, temperature_column, control)
        return self.wait()

    def close(self) -> None:
        """Stop the worker if it has not drawn its figure (idempotent)."""
        process, self._process = self._process, None
        if process is not None:
            process.kill()
            process.wait()
            if process.stdin is not None:
                try:
                    process.stdin.close()
                except OSError:
                    pass
        self._errors.close()

    def __enter__(self) -> 'PlotWorker':
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()


def _serve() -> None:
    """
    Run the plot worker: lay out the figure, rehearse it, add the data, write the PNG.

    Import matplotlib, lay out the figure once with made-up data (:func:`_rehearse`: the
    ticks, text layouts and fonts of that layout are kept), then add the data read from
    stdin (a pickle) and write the PNG.

    Without the cyclic garbage collector: this process lives for one figure and leaves with
    ``os._exit``, so nothing is gained by collecting, while its collections, which traverse
    every object of matplotlib's import, cost some 30 ms of CPU during the import (taken
    from the run on a busy machine) and could pause the final draw by 10-30 ms.
    """
    import gc
    gc.disable()
    import matplotlib
    matplotlib.use('Agg')
    figure = _figure()
    _rehearse(figure)
    data = sys.stdin.buffer.read()
    if not data:  # the run ended without a figure
        return
    request = pickle.loads(data)
    _finish(figure, request['series'], request['path'], request['title'])


if __name__ == '__main__':
    _serve()
    sys.stderr.flush()
    os._exit(0)  # the PNG is written and closed: skip the interpreter's teardown, which the
    # run would wait for (a tenth of a second with matplotlib loaded)
