"""
Figures of closed-loop runs (matplotlib, headless), drawn here or in a worker process.

:func:`plot_closed_loop` draws the figure of a run in this process.
:class:`PlotWorker` draws it in a process of its own, started when a run
begins: that process imports matplotlib (the costliest import of a run's
output) while the run computes, then draws the figure it is sent at the end,
while the run writes its other files. A command that makes one figure is then
shorter by the import, on a machine with a core to spare. During the run's
last steps :class:`FigurePreview` tells the worker the extremes of the data:
it draws the figure's axes ahead, and after the run only the data on them
(the same figure; see :data:`LIMITS_TOLERANCE`).

This module imports only the standard library at load time (a command can
start the worker before it loads anything else; the worker runs this file as
a script, ``python -I -S -OO plotting.py FOLDER...`` (:func:`worker_command`),
with nothing of mshoot_core on its path and matplotlib's folders given);
matplotlib is imported where a figure is drawn, with the Agg backend and
without pyplot. The PNG is written by :func:`_png` (the pixels and metadata of
matplotlib's writer, faster).
"""
from __future__ import annotations

import logging
import os
import pathlib
import pickle
import queue
import select
import struct
import subprocess
import sys
import tempfile
import threading
from typing import Any, Sequence, TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

logger = logging.getLogger(__name__)

#: Resolution of the figure [dots per inch] (10 x 6 in).
DPI = 100
#: zlib level of the PNG: 1 writes it several times faster than the default 6, for a
#: file about a third larger.
PNG_COMPRESSION = 1
#: How close (a fraction of each axis's span) the limits of a background drawn ahead must be
#: to those of the data for the data to be drawn on it, with its limits: a millionth, a
#: thousandth of a pixel (a heat rate at its bound, say, that moves by 1e-8 kW late in a run).
LIMITS_TOLERANCE = 1e-6
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
    for axes in (ax_t, ax_q):  # ticks and grid under the data: the data can be drawn last
        axes.set_axisbelow(True)
    return fig, ax_t, ax_q


def _draw_data(figure: tuple[Any, Any, Any], series: dict[str, np.ndarray],
               title: str) -> list[tuple[Any, Any]]:
    """
    Add the run's data and title to a :func:`_figure`.

    Return them as (artist, its axes or figure), in the order a draw of the figure draws them
    (after the axes' ticks, grid and zero line: :func:`_figure` puts those below).
    """
    fig, ax_t, ax_q = figure
    hours = series['hours']
    band = ax_t.fill_between(hours, series['comfort_min'], series['comfort_max'], step='post',
                             color='tab:green', alpha=0.15, label='comfort band')
    line, = ax_t.plot(hours, series['temperature'], color='tab:red', lw=1.5, label='zone T')
    legend = ax_t.legend(loc='lower left', framealpha=0.9)
    step, = ax_q.step(series['step_hours'], series['q_kw'], where='post', color='tab:blue',
                      lw=1.5)
    artists = [(band, ax_t), (line, ax_t), (legend, ax_t), (step, ax_q)]
    if title:
        artists.append((fig.suptitle(title), fig))
    return artists


def _clear_data(figure: tuple[Any, Any, Any]) -> None:
    """Take the data of :func:`_draw_data` away again: the figure as :func:`_figure` made it."""
    fig, ax_t, ax_q = figure
    for axes in (ax_t, ax_q):
        for artist in [*axes.collections, *axes.lines[1 if axes is ax_q else 0:]]:
            artist.remove()  # (ax_q keeps its zero line)
        if axes.get_legend() is not None:
            axes.get_legend().remove()
        axes.relim()
        axes.set_autoscale_on(True)
    fig.suptitle('')


def _limits(figure: tuple[Any, Any, Any]) -> tuple:
    """Return the axes' limits (autoscaled to the data where they are automatic)."""
    _, ax_t, ax_q = figure
    return ax_t.get_xlim(), ax_t.get_ylim(), ax_q.get_xlim(), ax_q.get_ylim()


def _close(limits: tuple, other: tuple) -> bool:
    """Whether two :func:`_limits` agree to :data:`LIMITS_TOLERANCE` of every axis's span."""
    return all(abs(a - b) <= LIMITS_TOLERANCE * (hi - lo)
               for (lo, hi), pair in zip(other, limits) for a, b in zip(pair, (lo, hi)))


def _background(figure: tuple[Any, Any, Any], extremes: dict[str, Sequence[float]],
                current: tuple | None = None) -> tuple:
    """
    Draw the figure without its data for a run whose data span ``extremes``.

    ``extremes``: the (lowest, highest) values of every array of :func:`closed_loop_series`
    (the comfort band's two arrays as one ``band``). The axes are scaled to them as to data of
    those extremes (two points per series, whose bounding boxes are the data's); the data and
    the title are left out. Return the canvas's pixels and the limits they were drawn with,
    for :func:`_finish`; or ``current``, such a background, when its limits are those of
    ``extremes`` (:func:`_close`): nothing is drawn then.
    """
    import numpy as np  # (this module loads with the standard library only)
    band = extremes['band']
    stand_in = {'hours': np.asarray(extremes['hours'], dtype=float),
                'comfort_min': np.full(2, float(band[0])),
                'comfort_max': np.full(2, float(band[1])),
                'temperature': np.asarray(extremes['temperature'], dtype=float),
                'step_hours': np.asarray(extremes['step_hours'], dtype=float),
                'q_kw': np.asarray(extremes['q_kw'], dtype=float)}
    artists = _draw_data(figure, stand_in, '')
    limits = _limits(figure)
    if current is None or not _close(limits, current[1]):
        for artist, _ in artists:
            artist.set_visible(False)
        fig = figure[0]
        fig.canvas.draw()
        current = (fig.canvas.copy_from_bbox(fig.bbox), limits)
    _clear_data(figure)
    return current


def _finish(figure: tuple[Any, Any, Any], series: dict[str, np.ndarray],
            path: str | pathlib.Path, title: str,
            background: tuple | None = None) -> pathlib.Path:
    """
    Add the run's data and title to a :func:`_figure` and write the PNG.

    With a :func:`_background` whose limits are those the data give (to
    :data:`LIMITS_TOLERANCE`), the axes take its limits and only the data and the title are
    drawn, on it: the pixels of the whole figure drawn with those limits (the data are drawn
    last anyway, and do not reach the axes' frame). Else the whole figure is drawn.
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    artists = _draw_data(figure, series, title)
    fig, ax_t, ax_q = figure
    if background is not None and _close(_limits(figure), background[1]):
        x_t, y_t, _, y_q = background[1]
        ax_t.set_xlim(x_t)  # (shared with ax_q)
        ax_t.set_ylim(y_t)
        ax_q.set_ylim(y_q)
        fig.canvas.restore_region(background[0])
        for artist, owner in artists:
            owner.draw_artist(artist)
    else:
        fig.canvas.draw()
    path.write_bytes(_png(fig.canvas.buffer_rgba(), fig.dpi))
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
    hours = np.arange(73.0)
    band = np.where((hours % 24 >= 8) & (hours % 24 < 17), 1.0, 0.0)
    _draw_data(figure, {'hours': hours, 'comfort_min': 21.0 - 2.0 * band,
                        'comfort_max': 22.0 + 2.0 * band,
                        'temperature': 21.0 + 2.5 * np.sin(hours / 6.0),
                        'step_hours': hours[:-1], 'q_kw': 2.0 * np.cos(hours[:-1] / 5.0)},
               '49.9 kWh, 8.5 Kh (8.1 Kh hourly), wall 1.0 s\nou44: H = 10 h, control fmu')
    figure[0].draw_without_rendering()
    _clear_data(figure)


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
    While the run goes, :meth:`preview` may tell it the extremes the data will
    span (:class:`FigurePreview`): it then draws the figure without its data
    ahead, and only the data once they come, when they span the same axes'
    limits (to :data:`LIMITS_TOLERANCE`: the same figure). Whatever goes wrong
    with the worker (it cannot start, fails or times out), :meth:`wait` draws
    the figure in this process instead, with a logged warning: the figure is
    never lost. Use as a context manager, or call :meth:`close`, so an unused
    worker does not outlive the run.

    The worker reads messages from its stdin, each a length (8 bytes) and a pickle: previews,
    then the figure.
    """

    def __init__(self) -> None:
        self._process: subprocess.Popen | None = None
        self._errors = tempfile.TemporaryFile()
        self._sender: threading.Thread | None = None
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._request: tuple[dict, pathlib.Path, str] | None = None
        try:
            self._process = subprocess.Popen(worker_command(), stdin=subprocess.PIPE,
                                             stdout=subprocess.DEVNULL, stderr=self._errors)
        except OSError as exc:
            logger.warning('plot worker not started (%s): the figure is drawn in this process',
                           exc)
        else:  # messages go through a thread: a write the pipe cannot take yet waits there
            self._sender = threading.Thread(target=self._write,
                                            args=(self._process, self._outbox), daemon=True)
            self._sender.start()

    def _post(self, message: dict | None) -> None:
        """Queue a message for the worker (None: the last one, stdin is closed after it)."""
        self._outbox.put(None if message is None else
                         _frame(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)))

    def preview(self, extremes: dict[str, Sequence[float]]) -> None:
        """
        Tell the worker the extremes the figure's data will span; do not wait.

        ``extremes``: (lowest, highest) of every array of :func:`closed_loop_series`, the
        comfort band's two as ``band``. A guess that turns out wrong costs the worker a
        draw, not a different figure. Ignored once the figure is sent.
        """
        if self._process is not None and self._request is None:
            self._post({'kind': 'preview', 'extremes': {
                name: (float(low), float(high)) for name, (low, high) in extremes.items()}})

    def send(self, fine: Any, steps: Any, path: str | pathlib.Path, title: str = '',
             temperature_column: str = 'y_T', control: str = 'q') -> None:
        """Give the worker the figure of :func:`plot_closed_loop` to draw; do not wait."""
        if self._request is not None:
            raise RuntimeError('a PlotWorker draws one figure')
        series = closed_loop_series(fine, steps, temperature_column, control)
        path = pathlib.Path(path).resolve()
        self._request = (series, path, title)
        if self._process is not None:
            self._post({'kind': 'figure', 'series': series, 'path': str(path), 'title': title})
            self._post(None)

    @staticmethod
    def _write(process: subprocess.Popen, outbox: queue.SimpleQueue) -> None:
        try:
            while (payload := outbox.get()) is not None:
                process.stdin.write(payload)
                process.stdin.flush()
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
        if self._request is None:
            self._outbox.put(None)  # the sender thread ends
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


class FigurePreview:
    """
    Tells a :class:`PlotWorker` the extremes of a run's figure during the run's last steps.

    A ``progress`` callback of :func:`mshoot_core.closed_loop.run_closed_loop`
    (``progress(rows, fines)`` after every step). It keeps the lowest and highest zone
    temperature and heat rate so far; the time axes and the comfort band's extremes are
    the scenario's. From ``lead`` steps before the end, whenever those extremes are new,
    it sends them (:meth:`PlotWorker.preview`), so that the worker draws the figure's
    background while the last steps run and only the data after them.

    Parameters
    ----------
    plotter : PlotWorker
        The worker that will draw the run's figure.
    scenario : DataFrame
        The run's scenario (index time [s], ``comfort_min``/``comfort_max`` [degC]), from the
        run's first row.
    steps : int
        The run's control steps.
    step_s : float
        The control step [s].
    lead : int
        Steps before the end from which previews are sent (enough for the worker to draw
        one before the run ends).
    temperature_column, control : str
        As :func:`closed_loop_series`.

    """

    def __init__(self, plotter: PlotWorker, scenario: Any, steps: int, step_s: float,
                 lead: int = 12, temperature_column: str = 'y_T', control: str = 'q') -> None:
        times = scenario.index.to_numpy(dtype=float)
        self.plotter, self.steps, self.lead = plotter, int(steps), int(lead)
        self.temperature_column, self.control = temperature_column, control
        self._known = {
            'hours': (times[0] / 3600.0, (times[steps - 1] + float(step_s)) / 3600.0),
            'step_hours': (times[0] / 3600.0, times[steps - 1] / 3600.0),
            'band': (float(scenario['comfort_min'].to_numpy(dtype=float)[:steps].min()),
                     float(scenario['comfort_max'].to_numpy(dtype=float)[:steps].max()))}
        self._temperature = (float('inf'), float('-inf'))
        self._q_kw = (float('inf'), float('-inf'))
        self._sent: dict | None = None

    def __call__(self, rows: list[dict], fines: list[Any]) -> None:
        """Take the step just done; send the extremes when they are due and new."""
        values = fines[-1][self.temperature_column].to_numpy(dtype=float)
        q_kw = float(rows[-1][self.control]) / 1000.0
        self._temperature = (min(self._temperature[0], float(values.min())),
                             max(self._temperature[1], float(values.max())))
        self._q_kw = (min(self._q_kw[0], q_kw), max(self._q_kw[1], q_kw))
        left = self.steps - len(rows)
        if 0 < left <= self.lead:
            extremes = dict(self._known, temperature=self._temperature, q_kw=self._q_kw)
            if extremes != self._sent:
                self.plotter.preview(extremes)
                self._sent = extremes


def worker_command() -> list[str]:
    """
    Return the command line of the plot worker: this file, run by this interpreter.

    ``-I``: the worker sees neither the environment's paths nor this module's folder; ``-S``:
    nor runs the site module (its .pth files: ~25 ms), given matplotlib's folders instead
    (those of this interpreter's site packages and the one that holds matplotlib here, found
    without importing it). ``-OO`` where matplotlib's bytecode of that level is there or can
    be written beside it (:func:`prepare_worker` writes it): without docstrings, which
    matplotlib builds and interpolates as it imports, the worker's import of matplotlib takes
    a third less CPU (0.21 instead of 0.31 s here), and the figure is the same. Where that
    bytecode can be neither found nor written, every start would compile matplotlib anew
    (seconds): the worker runs unoptimised then.
    """
    import importlib.util
    import site
    folders = list(site.getsitepackages()) if hasattr(site, 'getsitepackages') else []
    spec = importlib.util.find_spec('matplotlib')
    optimise = False
    if spec is not None and spec.submodule_search_locations:
        folders.insert(0, str(pathlib.Path(next(iter(spec.submodule_search_locations))).parent))
        if spec.origin is not None:
            cached = importlib.util.cache_from_source(spec.origin, optimization=2)
            optimise = os.path.exists(cached) or os.access(os.path.dirname(cached), os.W_OK)
    optimise = optimise and not os.environ.get('MSHOOT_NO_OO')  # AB-TEMP
    return [sys.executable, '-I', '-S', *(['-OO'] if optimise else []),
            str(pathlib.Path(__file__).resolve()), *dict.fromkeys(folders)]


def prepare_worker() -> int:
    """
    Start the plot worker once without a figure, and wait for it: its imports compiled.

    The worker imports matplotlib and lays out its figure, then ends, having written the
    bytecode of its imports at its optimisation level (``-OO``, :func:`worker_command`),
    which installs do not compile; the first run's worker would otherwise compile them, for
    a second or more of CPU. For setup scripts.

    Returns
    -------
    int
        The worker's exit code (0: prepared).

    """
    return subprocess.call(worker_command(), stdin=subprocess.DEVNULL,
                           stdout=subprocess.DEVNULL)


def _frame(payload: bytes) -> bytes:
    """Return a message to the worker: its length (8 bytes, big-endian) and ``payload``."""
    return struct.pack('>Q', len(payload)) + payload


def _read_exactly(fd: int, size: int) -> bytes | None:
    """Read ``size`` bytes from ``fd`` (None: the end of the input before the first byte)."""
    chunks, left = [], size
    while left:
        chunk = os.read(fd, left)
        if not chunk:
            if left == size:
                return None
            raise EOFError(f'the input ended {left} bytes before the end of a message')
        chunks.append(chunk)
        left -= len(chunk)
    return b''.join(chunks)


def _read_message(fd: int) -> dict | None:
    """Read the next message of :meth:`PlotWorker._post` from ``fd`` (None: no more)."""
    header = _read_exactly(fd, 8)
    if header is None:
        return None
    payload = _read_exactly(fd, struct.unpack('>Q', header)[0])
    if payload is None:
        raise EOFError('the input ended after a message header')
    return pickle.loads(payload)


def _serve(fd: int = 0) -> None:
    """
    Run the plot worker: lay out the figure, rehearse it, draw previews, write the PNG.

    Import matplotlib, lay out the figure once with made-up data (:func:`_rehearse`: the
    ticks, text layouts and fonts of that layout are kept), then read the messages of
    :class:`PlotWorker` from ``fd`` (stdin): a preview draws the figure's background for
    the extremes it gives (unless a newer message already waits), the figure adds its data
    and writes the PNG.

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
    background = None
    while True:
        message = _read_message(fd)
        if message is None:  # the run ended without a figure
            return
        if message['kind'] == 'preview':
            if not select.select([fd], [], [], 0)[0]:  # (a newer message makes it stale)
                background = _background(figure, message['extremes'], background)
            continue
        _finish(figure, message['series'], message['path'], message['title'], background)
        return


if __name__ == '__main__':
    sys.path.extend(sys.argv[1:])  # (started with -S: matplotlib's folders)
    _serve()
    sys.stderr.flush()
    os._exit(0)  # the PNG is written and closed: skip the interpreter's teardown, which the
    # run would wait for (a tenth of a second with matplotlib loaded)
