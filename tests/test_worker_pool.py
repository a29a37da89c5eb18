"""
Worker processes end with their pool's owner (:mod:`mshoot_studies.worker_pool`).

A killed benchmark runner once left its two busy workers running a 14-day BOPTEST period each
for half an hour. Here the owner is a real child process that starts a pool, gives a worker a
long task, and is killed with SIGKILL (no cleanup of its own runs): the busy worker must end.
"""
import pathlib
import signal
import subprocess
import sys
import time

from mshoot_studies.worker_pool import process_pool
import pytest

#: Deadlock guard [s] (wall time): far above the milliseconds the kernel's signal takes.
GUARD_S = 60.0

#: The owner: a pool of one spawned worker, busy for 10 minutes; prints the worker's pid.
OWNER = """
import os, sys, time
from mshoot_studies.worker_pool import process_pool
pool = process_pool(1, {method!r})
pid = pool.submit(os.getpid).result()
pool.submit(time.sleep, 600)
print(pid, flush=True)
time.sleep(600)
"""


def _running(pid: int) -> bool:
    """Return whether process ``pid`` exists and is not a zombie."""
    status = pathlib.Path(f'/proc/{pid}/status')
    try:
        return not any(line.split()[1] == 'Z' for line in status.read_text().splitlines()
                       if line.startswith('State:'))
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='reads /proc (Linux)')
@pytest.mark.parametrize('method', ['spawn', 'forkserver'])
def test_a_busy_worker_ends_with_its_killed_owner(method):
    """A worker busy for 10 min ends once its owner is killed (SIGKILL: no cleanup)."""
    owner = subprocess.Popen([sys.executable, '-c', OWNER.format(method=method)],
                             stdout=subprocess.PIPE, text=True)
    try:
        worker = int(owner.stdout.readline())
        assert _running(worker), 'the worker should run its task while the owner lives'
        owner.send_signal(signal.SIGKILL)
        owner.wait(timeout=GUARD_S)
        deadline = time.monotonic() + GUARD_S
        while _running(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _running(worker), f'worker {worker} outlived its killed owner'
    finally:
        owner.kill()
        owner.wait(timeout=GUARD_S)


def test_a_worker_of_an_owner_already_gone_ends():
    """A process watching an owner that does not exist ends with SIGTERM."""
    code = ('import time; from mshoot_studies.worker_pool import watch_owner; '
            'watch_owner(2 ** 22 + 12345); time.sleep(600)')  # a pid above pid_max: no owner
    done = subprocess.run([sys.executable, '-c', code], timeout=GUARD_S)
    assert done.returncode == -signal.SIGTERM


def test_bad_pools_are_refused():
    """No workers, or preloads without a fork server, are refused."""
    with pytest.raises(ValueError, match='at least one worker'):
        process_pool(0)
    with pytest.raises(ValueError, match='forkserver'):
        process_pool(1, 'spawn', preload=['json'])
