"""
Shared fixtures and helpers: paths, the OU44 data, private rclpy contexts, guarded spins.

Wall-clock limits here are deadlock guards (a hung test fails instead of hanging CI), set far
above what any run needs on a loaded 2-core machine; they never judge speed.

``make test TEST_WORKERS=2`` runs the suite on two pytest-xdist workers (``-n 2 --dist
loadgroup``): the tests of a file stay on one worker (a module-scoped fixture is built once),
and the tests marked ``host_discovery`` (processes finding each other over DDS on this host) all
run on one worker, one at a time, first (see :func:`pytest_collection_modifyitems`).
"""
import os
import pathlib
import time
from typing import Any, Callable

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
OU44_CSV = ROOT.parent / 'shared' / 'data' / 'ou44' / 'measurements.csv'
#: Deadlock guard of a spin [s] (wall time).
GUARD_S = 90.0
#: The xdist group of the tests marked ``host_discovery``: one worker runs them, one at a time.
HOST_DISCOVERY_GROUP = 'host_discovery'


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """
    Group the tests for pytest-xdist's ``--dist loadgroup``; a plain run is left as it is.

    A test marked ``host_discovery`` joins one group: its processes find each other over DDS on
    this host (LOCALHOST discovery, a domain drawn at random), so two of them at once on two
    workers could share a domain. These come first, as the longest unit of work. Every other
    test is grouped by its file, so a module-scoped fixture (a docs build, a run over ROS) is
    built on one worker only. Runs before xdist names the groups (``tryfirst``).
    """
    if not config.getoption('loadgroup', False):  # set on an xdist worker of --dist loadgroup
        return
    for item in items:
        marked = item.get_closest_marker('host_discovery') is not None
        item.add_marker(pytest.mark.xdist_group(HOST_DISCOVERY_GROUP if marked
                                                else item.path.name))
    items.sort(key=lambda item: item.get_closest_marker('host_discovery') is None)


@pytest.fixture(scope='session')
def ou44_csv() -> pathlib.Path:
    """Path of the OU44 measurements; skip (fail under CI=true) when absent."""
    if not OU44_CSV.is_file():
        if os.environ.get('CI') == 'true':
            pytest.fail(f'OU44 data missing at {OU44_CSV} (required under CI)')
        pytest.skip(f'OU44 data not found at {OU44_CSV}')
    return OU44_CSV


@pytest.fixture(scope='session')
def r1c1_fmu() -> pathlib.Path:
    """Return the built-in R1C1 FMU, built by ``make setup`` (as the runtime expects)."""
    from mshoot_core import fmu_cache
    return fmu_cache.find_fmu('r1c1')


@pytest.fixture(scope='session')
def r2c2_fmu() -> pathlib.Path:
    """Return the R2C2 test FMU, built by the tests (gcc) when it is not built yet."""
    from mshoot_core import fmu_build
    return fmu_build.ensure_fmu('r2c2')


def private_context() -> Any:
    """
    Return an initialised rclpy context of this test alone, with discovery off.

    In-process pub/sub still works, other processes on the machine cannot interfere; the domain
    comes from the pid, in 101..119: none of the domains (1..100, 120..209) that this suite's
    processes use to find each other on this host.
    """
    import rclpy
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'OFF'
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=101 + os.getpid() % 19)
    return ctx


@pytest.fixture
def context() -> Any:
    """Yield a private rclpy context, shut down after the test (see :func:`private_context`)."""
    import rclpy
    ctx = private_context()
    yield ctx
    rclpy.try_shutdown(context=ctx)


def spin_until(executor: Any, condition: Callable[[], bool], timeout_s: float = GUARD_S,
               what: str = 'the condition') -> None:
    """Spin ``executor`` until ``condition()`` holds; fail after ``timeout_s`` of wall time."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f'{what} not reached within {timeout_s} s')
        executor.spin_once(timeout_sec=0.02)


def spin_for(executor: Any, wall_s: float) -> None:
    """Spin ``executor`` for ``wall_s`` of wall time."""
    end = time.monotonic() + wall_s
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.02)


@pytest.fixture(scope='session')
def timed_fmus(tmp_path_factory: pytest.TempPathFactory) -> dict[str, pathlib.Path]:
    """
    Return the time-dependent test FMU (tests/fmus/timed_zone.c), built with gcc.

    ``'state'`` declares FMU-state get/set/serialise, ``'nostate'`` does not.
    """
    from timed_fmu import build_timed_fmu
    out = tmp_path_factory.mktemp('timed_fmu')
    return {'state': build_timed_fmu(out, True), 'nostate': build_timed_fmu(out, False)}


def _test_case(name: str = '') -> Any:
    """Return the BOPTEST test case (or its sibling ``name``); skip (fail under CI) if absent."""
    from mshoot_core.boptest.testcase import DIR_ENV, TestCase
    folder = pathlib.Path(os.environ.get(DIR_ENV, '/nonexistent'))
    folder = folder.parent / name if name else folder
    if not (folder / 'wrapped.fmu').is_file():
        if os.environ.get('CI') == 'true':
            pytest.fail(f'BOPTEST test case missing at {folder} (required under CI)')
        pytest.skip(f'BOPTEST test case not found at {folder}')
    return TestCase.load(folder)


@pytest.fixture(scope='session')
def boptest_case() -> Any:
    """Return the BOPTEST test case beside the repo; skip (fail under CI=true) when absent."""
    return _test_case()


@pytest.fixture(scope='session')
def office() -> Any:
    """Return BOPTEST's two-zone office beside the repo; skip (fail under CI) when absent."""
    return _test_case('multizone_office_simple_hydronic')
