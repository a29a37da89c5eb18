"""
SIGINT and SIGTERM as a request to stop, not an exception in the middle of a write.

Python turns SIGINT into KeyboardInterrupt wherever the main thread happens to
be (possibly inside a bag write) and dies on SIGTERM without running any
``finally``. Processes that must end cleanly (the recorder: a valid bag with
everything received) install :class:`StopSignals` and poll it between short
spins, then finish their work and close.
"""
from __future__ import annotations

import signal
import threading
from types import FrameType
from typing import Any, Callable, Sequence

Handler = Callable[[int, FrameType | None], Any] | int | None


class StopSignals:
    """
    Turn ``signals`` into a stop request while installed (a context manager).

    Attributes
    ----------
    received : str
        Name of the first signal received ('' while none).

    """

    def __init__(self, signals: Sequence[int] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.signals = tuple(signals)
        self.received = ''
        self._event = threading.Event()
        self._previous: dict[int, Handler] = {}

    @property
    def requested(self) -> bool:
        """Return True once one of the signals arrived."""
        return self._event.is_set()

    def request(self, name: str = 'request') -> None:
        """Ask to stop as a signal would (e.g. from a test or another thread)."""
        if not self._event.is_set():
            self.received = name
        self._event.set()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.request(signal.Signals(signum).name)

    def install(self) -> StopSignals:
        """Install the handlers (main thread only); returns self."""
        for signum in self.signals:
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def restore(self) -> None:
        """Put the previous handlers back."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
        self._previous.clear()

    def __enter__(self) -> StopSignals:
        return self.install()

    def __exit__(self, *exc: object) -> None:
        self.restore()
