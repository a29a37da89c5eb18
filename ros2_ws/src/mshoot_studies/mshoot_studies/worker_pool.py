"""
Worker processes that end with the process that started them.

Every application that runs work on worker processes (the BOPTEST runners, the rule's tuning,
the sweeps) takes its pool from :func:`process_pool`: a
:class:`concurrent.futures.ProcessPoolExecutor` whose workers are bound to their parent. A
pool's workers otherwise outlive a parent that is killed (``kill``, a CI timeout, a closed
terminal): they go on running their FMUs and solvers for the rest of a benchmark, unseen, on a
shared 2-core machine. A bound worker is sent ``SIGTERM`` by the kernel when its parent ends
(Linux ``prctl(PR_SET_PDEATHSIG)``), and ends at once if its parent is already gone when it
starts. Elsewhere the binding is skipped with a debug line.

Stable API::

    from mshoot_studies.worker_pool import process_pool
    with process_pool(2) as pool:                      # spawn: a fresh interpreter each
        futures = [pool.submit(work, job) for job in jobs]
"""
from __future__ import annotations

import concurrent.futures
import logging
import multiprocessing
import os
import signal
import threading
import time
from typing import Any, Callable, Sequence

logger = logging.getLogger(__name__)

#: How often a worker looks whether its owner still runs [s].
WATCH_PERIOD_S = 1.0


def process_pool(workers: int, method: str = 'spawn',
                 initializer: Callable[..., Any] | None = None, initargs: Sequence[Any] = (),
                 preload: Sequence[str] = (),
                 max_tasks_per_child: int | None = None
                 ) -> concurrent.futures.ProcessPoolExecutor:
    """
    Return a process pool whose workers end with this process.

    Parameters
    ----------
    workers : int
        Worker processes, >= 1.
    method : str
        The start method (``'spawn'``: a fresh interpreter, no inherited FMU instance or
        rclpy context; ``'forkserver'``).
    initializer, initargs
        Called in every worker after the binding, as for the executor.
    preload : sequence of str
        Modules the fork server imports once (``method='forkserver'`` only).
    max_tasks_per_child : int, optional
        As for the executor (1: a fresh process per task).

    Returns
    -------
    concurrent.futures.ProcessPoolExecutor

    Raises
    ------
    ValueError
        For fewer than one worker, or preloads without a fork server.

    """
    if int(workers) < 1:
        raise ValueError(f'expected at least one worker process, got {workers!r}')
    if preload and method != 'forkserver':
        raise ValueError(f'preloaded modules need the forkserver start method, not {method!r}')
    context = multiprocessing.get_context(method)
    if preload:
        context.set_forkserver_preload(list(preload))
    return concurrent.futures.ProcessPoolExecutor(
        int(workers), mp_context=context, max_tasks_per_child=max_tasks_per_child,
        initializer=_start_worker, initargs=(os.getpid(), initializer, tuple(initargs)))


def _start_worker(parent_pid: int, initializer: Callable[..., Any] | None,
                  initargs: tuple[Any, ...]) -> None:
    """Bind this worker to the pool's owner (see the module), then run the initializer."""
    watch_owner(parent_pid)
    if initializer is not None:
        initializer(*initargs)


def watch_owner(owner_pid: int, period_s: float = WATCH_PERIOD_S) -> threading.Thread:
    """
    End this process with ``SIGTERM`` once process ``owner_pid`` is gone.

    A daemon thread looks every ``period_s``. The owner is not always this process's parent
    (under ``forkserver`` the parent is the fork server, which outlives a killed owner while
    its workers hold the owner's end of its pipe), so it is watched by its id.

    Parameters
    ----------
    owner_pid : int
        The pool owner's process id.
    period_s : float
        Time between two looks [s].

    Returns
    -------
    threading.Thread
        The watching thread (started).

    """
    def watch() -> None:
        while _alive(owner_pid):
            time.sleep(period_s)
        logger.warning('worker %d: its owner %d is gone; ending', os.getpid(), owner_pid)
        os.kill(os.getpid(), signal.SIGTERM)

    thread = threading.Thread(target=watch, name=f'owner-{owner_pid}', daemon=True)
    thread.start()
    return thread


def _alive(pid: int) -> bool:
    """Return whether process ``pid`` exists (a zombie counts as gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f'/proc/{pid}/stat', 'rb') as stat:
            return stat.read().rsplit(b')', 1)[1].split()[0] != b'Z'
    except (OSError, IndexError):
        return True  # no /proc (not Linux): the signal test is the answer
