"""
FMUs and data files as users have them: broken binaries, missing libraries, strict schemas.

Each case runs the real ``mshoot`` command (or the model it builds) on a real FMU made broken:
the built-in R1C1 FMU with its binary truncated, its modelDescription made to break the FMI
schema, its directional derivatives withdrawn; the zone test FMU linked against a library
the host lacks; the OU44 data with a time given twice or rows out of order.
"""
import json
import logging
import os
import pathlib
import shutil
import subprocess
import sys
import uuid
import zipfile

from mshoot_core import fmu_binary, fmu_cache
from mshoot_core.fmu_build import CFLAGS, find_compiler
from mshoot_core.fmu_cache import FMI2_HEADERS, SOURCE_DIR
from mshoot_core.kpis import fallback_problem
from mshoot_core.models import card as cards
from mshoot_core.models.defaults import FINITE_DIFFERENCE_TOLERANCE
from mshoot_core.models.fmi import summarise
import numpy as np
import pandas as pd
import pytest
import yaml

from card_fmus import FMU_SOURCES

#: The built-in R1C1 FMU's card (Model Exchange), naming an FMU file instead of the built-in.
R1C1_CARD = {
    'fmu': 'r1c1.fmu',
    'fmi_type': 'model-exchange',
    'controls': {'q': {'variable': 'q', 'unit': 'W', 'min': -2000, 'max': 2000}},
    'disturbances': {'solrad': {'variable': 'solrad', 'unit': 'W/m2'},
                     'Tout': {'variable': 'Tout', 'unit': 'degC'},
                     'occ': {'variable': 'occ', 'unit': '1'},
                     'dpos': {'variable': 'dpos', 'unit': '%'}},
    'states': {'T': {'variable': 'heatCapacitor.T', 'unit': 'K'}},
    'outputs': {'T': {'variable': 'T', 'unit': 'degC'}, 'Qr': {'variable': 'Qr', 'unit': 'J'}},
}
#: The multizone office test case beside the repository (its binary needs libgfortran.so.3).
MULTIZONE = (pathlib.Path(__file__).resolve().parents[2] / 'shared' / 'boptest'
             / 'multizone_office_simple_hydronic')


def mshoot(*args: str, timeout: float = 300.0, **options) -> subprocess.CompletedProcess:
    """Run the real ``mshoot`` command."""
    command = shutil.which('mshoot')
    assert command is not None, 'mshoot not on PATH: source env.sh'
    streams = {} if 'stdout' in options else {'capture_output': True}
    return subprocess.run([command, *args], text=True, timeout=timeout, **streams, **options)


def copy_fmu(source: pathlib.Path, target: pathlib.Path, description=None,
             binary=None) -> pathlib.Path:
    """Copy an FMU, its modelDescription and binary passed through the given edits."""
    with zipfile.ZipFile(source) as old, zipfile.ZipFile(target, 'w') as new:
        for item in old.infolist():
            data = old.read(item)
            if item.filename == 'modelDescription.xml' and description is not None:
                data = description(data.decode()).encode()
            elif item.filename.startswith('binaries/') and binary is not None:
                data = binary(data)
            new.writestr(item, data)
    return target


def write_card(folder: pathlib.Path, content: dict, name: str = 'card.yaml') -> pathlib.Path:
    path = folder / name
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


def error_lines(stderr: str) -> list[str]:
    """Return the lines of a command's stderr that report an error (no traceback allowed)."""
    assert 'Traceback' not in stderr, stderr
    return [line for line in stderr.splitlines() if line.strip()]


# -- broken binaries ----------------------------------------------------------------------------
@pytest.fixture(params=[2000, 100], ids=['bus-error', 'unreadable'])
def truncated_card(request, tmp_path, r1c1_fmu):
    """Return a card of the R1C1 FMU whose binary is cut after ``param`` bytes (a valid zip)."""
    copy_fmu(r1c1_fmu, tmp_path / 'r1c1.fmu', binary=lambda data: data[:request.param])
    return write_card(tmp_path, R1C1_CARD), request.param


def test_a_truncated_binary_is_an_error_not_a_signal(truncated_card, tmp_path):
    card, size = truncated_card
    check = mshoot('card', 'check', str(card))
    assert check.returncode == 2, check.stdout
    lines = error_lines(check.stderr)
    assert lines[0] == f'model card {card}: 1 problem'
    assert 'R1C1.so' in lines[1]
    # 2000 bytes: the headers load and mapping the rest raises SIGBUS; 100: the loader refuses
    assert ('is damaged' in lines[1] and 'SIGBUS' in lines[1]) if size == 2000 else \
        'does not load' in lines[1]
    run = mshoot('case', 'synthetic', '--hours', '2', '--horizon', '2', '--control', str(card),
                 '--out', str(tmp_path / 'out'))
    assert run.returncode == 2
    errors = [line for line in error_lines(run.stderr) if ' ERROR ' in line]
    assert len(errors) == 1 and 'R1C1.so' in errors[0], run.stderr
    # in this process too: a ValueError, and the process lives on
    with pytest.raises(fmu_binary.FmuBinaryError, match='R1C1.so'):
        cards.build_model(card)


def test_a_good_binary_is_checked_once(tmp_path, r1c1_fmu):
    """The check's result is kept per binary: a second check starts no process."""
    fmu = copy_fmu(r1c1_fmu, tmp_path / 'r1c1.fmu',
                   binary=lambda data: data + uuid.uuid4().bytes)  # a binary of its own
    folder = fmu_cache.extract_fmu(fmu)
    binary = fmu_binary.binary_file(folder, 'R1C1')
    key = fmu_binary._check_key(binary, (), fmu_binary.preloaded())
    record = fmu_cache.cache_dir() / fmu_binary.CHECKED / key
    assert not record.exists()
    fmu_binary.check_binary(folder, 'R1C1')
    assert record.is_file()
    # the record is what the second check reads: a record saying "preload X" is obeyed
    record.write_text('["libm.so.6"]')
    assert fmu_binary.check_binary(folder, 'R1C1') == ('libm.so.6',)


# -- a library the host lacks -------------------------------------------------------------------
def zone_needing(tmp_path: pathlib.Path, soname: str) -> pathlib.Path:
    """Build the zone test FMU linked against ``soname``, which is then deleted (a missing lib)."""
    build = tmp_path / 'build'
    build.mkdir()
    stub = build / soname
    (build / 'stub.c').write_text('int mshoot_stub_answer(void) { return 42; }\n')
    compiler = find_compiler()
    subprocess.run([compiler, '-shared', '-fPIC', f'-Wl,-soname,{soname}', '-o', str(stub),
                    str(build / 'stub.c')], check=True)
    library = build / 'Zone.so'
    subprocess.run([compiler, *CFLAGS, '-DMODEL_GUID="{8c4e810f-3df3-4a00-8276-176fa3c9f000}"',
                    '-I', str(SOURCE_DIR), '-o', str(library), str(FMU_SOURCES / 'zone.c'),
                    '-Wl,--no-as-needed', str(stub), '-lm'], check=True)
    description = (FMU_SOURCES / 'zone.xml').read_text()
    description = description.replace('@GUID@', '{8c4e810f-3df3-4a00-8276-176fa3c9f000}')
    description = description.replace('@DATETIME@', '2026-01-01T00:00:00Z')
    fmu = tmp_path / 'zone.fmu'
    with zipfile.ZipFile(fmu, 'w') as archive:
        archive.writestr('modelDescription.xml', description)
        archive.write(library, 'binaries/linux64/Zone.so')
    shutil.rmtree(build)
    assert all((SOURCE_DIR / h).is_file() for h in FMI2_HEADERS)
    return fmu


def test_a_missing_library_is_named_and_a_stand_in_provides_it(tmp_path):
    soname = f'libmshoot_gone_{os.getpid()}.so.3'
    zone_needing(tmp_path, soname)
    content = {'fmu': 'zone.fmu',
               'controls': {'q': {'variable': 'q', 'unit': 'W', 'min': -2000, 'max': 2000}},
               'disturbances': {n: {'variable': n} for n in ('solrad', 'Tout', 'occ')},
               'states': {'T': {'variable': 'cair.T', 'unit': 'K'}},
               'outputs': {'T': {'variable': 'T', 'unit': 'degC'}}}
    bare = write_card(tmp_path, content, 'bare.yaml')
    check = mshoot('card', 'check', str(bare))
    assert check.returncode == 2
    problem = error_lines(check.stderr)[1]
    assert f'needs the library {soname}, which this host does not have' in problem
    assert 'preload' in problem and 'soname' in problem  # how to provide it
    # a stand-in's source, built into the cache for the soname the binary lacks
    shim = tmp_path / 'shim'
    shim.mkdir()
    (shim / 'stand_in.c').write_text('int mshoot_stub_answer(void) { return 7; }\n')
    (shim / 'v.map').write_text('{ global: mshoot_stub_answer; local: *; };\n')
    with_shim = write_card(tmp_path, {**content, 'preload': [{'source': 'shim'}]}, 'shim.yaml')
    check = mshoot('card', 'check', str(with_shim))
    assert check.returncode == 0, check.stderr
    assert f'preloading {fmu_cache.cache_dir() / fmu_binary.STAND_IN}' in check.stdout
    assert f'/{soname})' in check.stdout
    # and the model runs from that card in this process, with the stand-in preloaded
    model = cards.build_model(with_shim, 'emulator')
    try:
        x, _ = model.simulate_intervals(np.array([[293.15]]),
                                        np.array([[0.0, 0.0, 5.0, 0.0]]), 3600.0)
        assert 280.0 < x[0, 0] < 293.15  # cools towards 5 degC outside
    finally:
        model.close()
    assert any(p.endswith(f'/{soname}') for p in fmu_binary.preloaded())


def test_a_boptest_card_takes_its_stand_ins_from_the_test_case(tmp_path):
    """The test case folder's shim/ is what its FMU gets: a card's preload would be ignored."""
    document = yaml.safe_load(cards.builtin_card('boptest_tset').read_text())
    (tmp_path / 'shim').mkdir()
    card = write_card(tmp_path, {**document, 'preload': [{'source': 'shim'}]})
    with pytest.raises(cards.CardError, match="preload: a BOPTEST test case's FMU takes its "
                                              'stand-ins from the test case folder'):
        cards.load_card(card)


@pytest.mark.skipif(not (MULTIZONE / 'wrapped.fmu').is_file(), reason='no multizone office')
def test_multizone_office_binary_gets_its_libgfortran3_stand_in():
    folder = fmu_cache.extract_fmu(MULTIZONE / 'wrapped.fmu')
    (identifier,) = fmu_binary.model_identifiers(folder)
    with pytest.raises(fmu_binary.FmuBinaryError, match='needs the library libgfortran.so.3'):
        fmu_binary._load_in_child(fmu_binary.binary_file(folder, identifier), [])
    before = [pathlib.Path(p).name for p in fmu_binary.preloaded()]
    preloaded = fmu_binary.check_binary(folder, identifier,
                                        [fmu_binary.Library(source=MULTIZONE / 'shim')])
    # the stand-in is preloaded now: by this check, or by an earlier one in this process (a
    # BOPTEST run of the office), whose preloads every later check starts from
    assert [pathlib.Path(p).name for p in preloaded] == (
        [] if 'libgfortran.so.3' in before else ['libgfortran.so.3'])
    assert 'libgfortran.so.3' in [pathlib.Path(p).name for p in fmu_binary.preloaded()]


# -- one validation policy ----------------------------------------------------------------------
def schema_breaking(text: str) -> str:
    """Give every variable an attribute the FMI 2.0 schema does not know (a problem each)."""
    return text.replace('<ScalarVariable ', '<ScalarVariable mshootUnknown="1" ')


def test_validation_is_one_policy_for_check_and_run(tmp_path, r1c1_fmu):
    copy_fmu(r1c1_fmu, tmp_path / 'r1c1.fmu', description=schema_breaking)
    strict = write_card(tmp_path, R1C1_CARD, 'strict.yaml')
    check = mshoot('card', 'check', str(strict))
    assert check.returncode == 2
    lines = error_lines(check.stderr)
    assert len(lines) == 2 and len(lines[1]) < 1500, lines  # summarised, not every problem
    assert 'breaks the FMI schema' in lines[1] and 'the first 3:' in lines[1]
    assert 'mshootUnknown' in lines[1] and 'more)' in lines[1]
    assert '`validate: false`' in lines[1]
    common = ['synthetic', '--hours', '2', '--horizon', '2', '--out', str(tmp_path / 'out')]
    run = mshoot('case', *common, '--control', str(strict))
    assert run.returncode == 2 and 'breaks the FMI schema' in run.stderr
    relaxed = write_card(tmp_path, {**R1C1_CARD, 'validate': False}, 'relaxed.yaml')
    check = mshoot('card', 'check', str(relaxed))
    assert check.returncode == 0, check.stderr
    assert 'modelDescription not validated (validate: false)' in check.stdout
    run = mshoot('case', *common, '--control', str(relaxed))
    assert run.returncode == 0, run.stderr


def test_summarise_keeps_the_count_and_the_first():
    assert summarise(['a']) == '1 problem: a'
    assert summarise(list('abcde')) == '5 problems, the first 3: a; b; c (and 2 more)'


def test_card_check_into_a_closed_pipe_ends_without_a_traceback():
    """`mshoot card check ... | head`: the reader is gone before the output is written."""
    read, write = os.pipe()
    os.close(read)
    try:
        done = mshoot('card', 'check', str(cards.builtin_card('r1c1_fmu')), stdout=write,
                      stderr=subprocess.PIPE)
    finally:
        os.close(write)
    assert 'Traceback' not in done.stderr and 'Exception ignored' not in done.stderr
    assert done.returncode == 141


def test_control_fmu_without_directional_derivatives_gets_an_accurate_tolerance(
        tmp_path, r1c1_fmu, caplog):
    copy_fmu(r1c1_fmu, tmp_path / 'r1c1.fmu', description=lambda text: text.replace(
        'providesDirectionalDerivative="true"', 'providesDirectionalDerivative="false"'))
    card = write_card(tmp_path, R1C1_CARD)
    caplog.set_level(logging.INFO, logger='mshoot_core.models.card')
    with cards.build_model(card, 'control') as model:
        assert model.tolerance == FINITE_DIFFERENCE_TOLERANCE
    assert 'finite-difference sensitivities (no directional derivatives)' in caplog.text
    with cards.build_model(card, 'emulator') as model:  # the emulator's own default
        assert model.tolerance == cards.role_tolerance('emulator')
    own = write_card(tmp_path, {**R1C1_CARD, 'tolerance': 1e-6}, 'own.yaml')
    caplog.clear()
    with cards.build_model(own, 'control') as model:
        assert model.tolerance == 1e-6
    assert [r.levelname for r in caplog.records if 'finite-difference' in r.message] == \
        ['WARNING']
    with cards.build_model(cards.builtin_card('r1c1_fmu'), 'control') as model:
        assert model.tolerance == cards.role_tolerance('control')  # sensitivities: untouched


# -- data files ---------------------------------------------------------------------------------
def test_a_data_file_with_a_time_twice_is_an_error_naming_its_lines(ou44_csv, tmp_path):
    raw = pd.read_csv(ou44_csv)
    row = int(np.flatnonzero(raw['datetime'].str.startswith('2018-04-05 10:00'))[0])
    repeated = raw.iloc[[row]].assign(Tout=raw['Tout'].iloc[row] + 8.0)
    data = pd.concat([raw.iloc[:row + 1], repeated, raw.iloc[row + 1:]])
    data.to_csv(tmp_path / 'dup.csv', index=False)
    run = mshoot('case', 'ou44', '--data', str(tmp_path / 'dup.csv'), '--hours', '2',
                 '--horizon', '2', '--out', str(tmp_path / 'out'))
    assert run.returncode == 2
    (error,) = [line for line in error_lines(run.stderr) if ' ERROR ' in line]
    assert f'lines {row + 2} and {row + 3} (2018-04-05 10:00:00)' in error
    assert not (tmp_path / 'out' / 'kpis.json').exists()


def test_unsorted_data_rows_are_a_warning(ou44_csv, tmp_path):
    raw = pd.read_csv(ou44_csv)
    row = int(np.flatnonzero(raw['datetime'].str.startswith('2018-04-05 10:00'))[0])
    order = np.arange(len(raw))
    order[[row, row + 1]] = order[[row + 1, row]]
    raw.iloc[order].to_csv(tmp_path / 'swapped.csv', index=False)
    common = ['ou44', '--hours', '2', '--horizon', '2']
    swapped = mshoot('case', *common, '--data', str(tmp_path / 'swapped.csv'), '--out',
                     str(tmp_path / 'swapped'))
    assert swapped.returncode == 0, swapped.stderr
    (warning,) = [line for line in error_lines(swapped.stderr) if ' WARNING ' in line]
    assert f'1 row out of time order (the first at line {row + 3}' in warning
    assert warning.endswith('sorted by time')
    reference = mshoot('case', *common, '--data', str(ou44_csv), '--out', str(tmp_path / 'ref'))
    assert reference.returncode == 0 and ' WARNING ' not in reference.stderr
    energy = [json.loads((tmp_path / name / 'kpis.json').read_text())['energy_kwh']
              for name in ('swapped', 'ref')]
    assert energy[0] == energy[1]


# -- exit codes ---------------------------------------------------------------------------------
def test_fallback_problem_counts_the_share():
    assert fallback_problem(0, 0, 0.5) is None
    assert fallback_problem(1, 2, 0.5) is None
    assert fallback_problem(2, 3, 0.5).startswith('2 of 3 steps fell back (67%')
    assert fallback_problem(4, 4, 0.9).startswith('every step fell back (100%')
    assert fallback_problem(4, 4, 1.0) is None


def test_a_run_that_never_controlled_exits_3(tmp_path):
    """A control model that fails on every step (its FMU refuses tmass = 0 at initialisation)."""
    failing = write_card(tmp_path, {**R1C1_CARD, 'fmu': None, 'builtin': 'r1c1-fmu',
                                    'parameters': {'tmass': 0.0}})
    failing.write_text(failing.read_text().replace('fmu: null\n', ''))
    common = ['synthetic', '--hours', '3', '--horizon', '3', '--control', str(failing)]
    run = mshoot('case', *common, '--out', str(tmp_path / 'out'))
    assert run.returncode == 3, run.stderr
    (warning,) = [line for line in error_lines(run.stderr) if ' WARNING ' in line]
    assert warning.endswith('every step fell back (100%, more than max_fallback_share 50%): '
                            'the MPC did not control this run (solve_failed x 3); exit code 3')
    steps = pd.read_csv(tmp_path / 'out' / 'steps.csv')
    assert steps['fallback'].all()
    assert 'every step fell back' in json.loads(
        (tmp_path / 'out' / 'kpis.json').read_text())['fallback_problem']
    allowed = mshoot('case', *common, '--max-fallback-share', '1', '--out',
                     str(tmp_path / 'allowed'))
    assert allowed.returncode == 0, allowed.stderr
    assert ' WARNING ' not in allowed.stderr
    # the demo's bring-up (over ROS, in one process) takes the same decision
    demo = subprocess.run([sys.executable, '-m', 'mshoot_nodes.bringup', '--scenario',
                           'synthetic', '--hours', '3', '--horizon', '3', '--control-model',
                           str(failing), '--no-bag', '--out', str(tmp_path / 'demo')],
                          capture_output=True, text=True, timeout=300)
    assert demo.returncode == 3, demo.stderr
    assert error_lines(demo.stderr)[-1] == (
        '[demo] WARNING: every step fell back (100%, more than max_fallback_share 50%): the MPC '
        'did not control this run; exit code 3')
    usage = ' '.join(mshoot('case', '--help').stdout.split())
    assert '--max-fallback-share' in usage and '3 the run ended but the MPC did not control it' \
        in usage
