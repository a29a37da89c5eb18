"""
FMU builds: made at setup time (``fmu_build``), only found at run time (``fmu_cache``).

The R1C1 FMU and the batch drivers are compiled by ``make setup`` into the
cache; the runtime never compiles, and a missing build is a clear error that
names the file and the command that builds it, never a slower path.
"""
import os
import re
import shutil
import subprocess

from mshoot_core import fmu_binary, fmu_build, fmu_cache
from mshoot_core.fmu_cache import NotBuiltError
from mshoot_core.models.fmi import FmiModel, r1c1_fmi_model
from mshoot_nodes.processes import executable
import numpy as np
import pytest


# -- the setup command ---------------------------------------------------------------------
def test_setup_command_builds_what_the_runtime_finds(tmp_path, monkeypatch, capsys):
    """`--cache` (what make setup runs) fills an empty cache with the FMUs and both drivers."""
    monkeypatch.setenv('MSHOOT_FMU_DIR', str(tmp_path))
    assert fmu_build.main(['--cache', 'r1c1', 'r2c2']) == 0
    printed = capsys.readouterr().out.split()
    found = [fmu_cache.find_fmu('r1c1'), fmu_cache.find_fmu('r2c2'),
             fmu_cache.find_driver('cs'), fmu_cache.find_driver('me')]
    assert printed == [str(path) for path in found]
    assert all(tmp_path in path.parents for path in found)
    assert found[2].parent.parent == found[3].parent.parent == tmp_path / 'driver'
    assert found[2].parent != found[3].parent  # each driver under the hash of its sources
    stamps = [path.stat().st_mtime_ns for path in found]
    assert fmu_build.main(['--cache', 'r1c1', 'r2c2']) == 0  # already built: kept as is
    assert [path.stat().st_mtime_ns for path in found] == stamps
    assert capsys.readouterr().out.split() == printed
    assert fmu_build.main(['--cache']) == 0  # the default: r1c1 and the drivers
    assert capsys.readouterr().out.split() == [str(found[0]), *map(str, found[2:])]


def test_setup_command_fails_when_a_driver_does_not_compile(tmp_path, monkeypatch):
    monkeypatch.setenv('MSHOOT_FMU_DIR', str(tmp_path))
    monkeypatch.setenv('CC', 'no-such-compiler-mshoot')
    assert fmu_build.main(['--cache']) == 1
    with pytest.raises(RuntimeError, match='no-such-compiler-mshoot.*not found'):
        fmu_build.ensure_driver('me')
    with pytest.raises(ValueError, match=r"unknown batch driver 'xx'.*'cs', 'me'"):
        fmu_build.ensure_driver('xx')


# -- the runtime finds builds, it never builds ------------------------------------------------
@pytest.mark.parametrize('driver, what', [
    ('cs', r'batched Co-Simulation driver \(mshoot_cs_batch, from fmu_src/cs_batch.c\)'),
    ('me', r'batched Model Exchange driver \(mshoot_me_batch, from fmu_src/me_batch.c\)')])
def test_missing_driver_is_a_clear_error(tmp_path, monkeypatch, driver, what):
    monkeypatch.setenv('MSHOOT_FMU_DIR', str(tmp_path))
    expected = fmu_cache.cached_driver_file(driver)
    with pytest.raises(NotBuiltError) as info:
        fmu_cache.find_driver(driver)
    message = str(info.value)
    assert re.search(f'the {what} is not built', message), message
    assert str(expected) in message and f'$MSHOOT_FMU_DIR={tmp_path}' in message
    assert '`make setup`' in message and '`python -m mshoot_core.fmu_build --cache`' in message
    assert not expected.exists() and not any(tmp_path.iterdir())  # nothing was built


def test_missing_driver_stops_the_model_at_construction(tmp_path, monkeypatch, r1c1_fmu,
                                                        r2c2_fmu):
    """No driver: building a model that would use it raises, with no slower path later."""
    monkeypatch.setenv('MSHOOT_FMU_DIR', str(tmp_path))
    for fmi_type, library in (('CoSimulation', 'cs'), ('ModelExchange', 'me')):
        with pytest.raises(NotBuiltError, match=f'mshoot_{library}_batch.*make setup'):
            r1c1_fmi_model(fmi_type=fmi_type, fmu_path=r1c1_fmu)
    with pytest.raises(NotBuiltError, match='mshoot_me_batch'):  # no FMU states, another FMU
        FmiModel(r2c2_fmu, inputs=['Tamb', 'Qhvac', 'Qsun'], states=['air.T', 'wall.T'],
                 outputs=['Tair'])
    # nothing was built: the cache only holds the FMUs' extractions and the records of their
    # binaries that loaded (mshoot_core.fmu_binary)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([fmu_cache.EXTRACTED,
                                                                 fmu_binary.CHECKED])


def test_missing_driver_raises_at_the_first_batch_after_the_cache_changed(
        tmp_path, monkeypatch, r1c1_fmu):
    """A model that lost its driver (closed and reopened elsewhere) looks it up again."""
    x, u = np.full((3, 1), 293.0), np.tile([100.0, 5.0, 10.0, 20.0, 500.0], (3, 1))
    with r1c1_fmi_model(fmi_type='ModelExchange', fmu_path=r1c1_fmu) as model:
        x_end, _ = model.simulate_intervals(x, u, 3600.0)
        monkeypatch.setenv('MSHOOT_FMU_DIR', str(tmp_path))
        model._me_driver = None  # as after close(): bound again on the next batch
        with pytest.raises(NotBuiltError, match='mshoot_me_batch'):
            model.simulate_intervals(x, u, 3600.0)
        assert model.me_batch_plan() is None  # still the driver's job: no silent CVode
        monkeypatch.delenv('MSHOOT_FMU_DIR')
        monkeypatch.setenv('HOME', str(tmp_path / 'home'))  # nor in the default cache
        with pytest.raises(NotBuiltError, match=f'{tmp_path}/home/.cache/mshoot/fmu/driver/'):
            model.interval_jacobians(x, u, 3600.0, [4])
    assert np.ptp(x_end) == 0.0 and x_end[0, 0] != 293.0


def test_missing_builtin_fmu_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv('MSHOOT_FMU_DIR', str(tmp_path))
    stale = tmp_path / '0123456789abcdef' / 'R1C1.fmu'  # a build of other sources
    stale.parent.mkdir()
    stale.write_bytes(b'')
    with pytest.raises(NotBuiltError) as info:
        r1c1_fmi_model(fmi_type='ModelExchange')
    message = str(info.value)
    assert f'the R1C1 FMU is not built: expected {fmu_cache.cached_fmu_file("r1c1")}' in message
    assert f'only for other sources ({stale})' in message
    assert '`python -m mshoot_core.fmu_build --cache r1c1`' in message
    assert '`make setup`' in message
    assert sorted(p.name for p in tmp_path.iterdir()) == [stale.parent.name]


def test_node_with_a_missing_build_exits_with_the_command_that_builds_it(tmp_path, r1c1_fmu):
    """The MPC node on the R1C1 FMU: no FMU, then no driver; exit 2, one line, no build."""
    no_fmu = tmp_path / 'empty'
    no_driver = tmp_path / 'fmu_only'
    fmu_copy = no_driver / r1c1_fmu.parent.name / r1c1_fmu.name
    fmu_copy.parent.mkdir(parents=True)
    shutil.copyfile(r1c1_fmu, fmu_copy)
    no_fmu.mkdir()
    cases = {no_fmu: 'cannot start: the R1C1 FMU is not built: expected '
                     f'{no_fmu / r1c1_fmu.parent.name / r1c1_fmu.name}',
             no_driver: 'cannot start: the batched Model Exchange driver (mshoot_me_batch, '
                        'from fmu_src/me_batch.c) is not built'}
    procs = {}
    for cache, _ in cases.items():
        env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='OFF', MSHOOT_FMU_DIR=str(cache))
        procs[cache] = subprocess.Popen(
            executable('mpc', 'mpc_node') + ['--ros-args', '-p', 'model:=fmu'], env=env,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for cache, expected in cases.items():
        output, _ = procs[cache].communicate(timeout=60)
        assert procs[cache].returncode == 2, output
        assert expected in output and '`make setup`' in output, output
        assert 'Traceback' not in output, output
    assert list(no_fmu.iterdir()) == []
    built = [p.relative_to(no_driver) for p in no_driver.rglob('*') if p.is_file()]
    assert [p for p in built if p.parts[0] not in (fmu_cache.EXTRACTED, fmu_binary.CHECKED)
            ] == [fmu_copy.relative_to(no_driver)]  # not extractions nor binary checks
