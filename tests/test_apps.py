"""The applications (mshoot_studies): the case command, the ``mshoot`` command, Setup 2."""
import json
import os
import pathlib
import shutil
import subprocess
import sys

from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.scenario import PUBLISHED, reference_scenario
from mshoot_studies import case, cli, study
from mshoot_studies.setup2 import SETUP2_SPLIT, SETUP2_START, train_setup2
import numpy as np
import pandas as pd
import pytest

from conftest import ROOT

KPI_KEYS = ('energy_kwh', 'heating_kwh', 'cooling_kwh', 'discomfort_kh', 'discomfort_kh_hourly',
            'steps', 'horizon_h', 'wall_s', 'solve_s_median', 'solver_failures')


# -- the case ---------------------------------------------------------------------------------
@pytest.mark.parametrize('horizon', [2, 10])
def test_reference_case_against_published(ou44_csv, horizon):
    """Energy and hourly discomfort may not both be worse than published by more than 3 %."""
    scenario = reference_scenario('ou44', ou44_csv)
    result, kpis = case.run_case(scenario, R1C1Model(), R1C1Model(), horizon=horizon, log_every=0)
    published = PUBLISHED[horizon]
    worse_energy = kpis['energy_kwh'] > 1.03 * published['energy_kwh']
    worse_comfort = kpis['discomfort_kh_hourly'] > 1.03 * published['discomfort_kh_hourly']
    assert not (worse_energy and worse_comfort), kpis
    assert kpis['solver_failures'] == 0
    assert result.steps['max_defect'].max() <= 1e-6
    assert kpis['steps'] == 72


def test_case_command_writes_outputs(tmp_path):
    out = tmp_path / 'case'
    assert case.main(['synthetic', '--horizon', '3', '--hours', '6', '--out', str(out)]) == 0
    kpis = json.loads((out / 'kpis.json').read_text())
    for key in ('energy_kwh', 'heating_kwh', 'cooling_kwh', 'discomfort_kh',
                'discomfort_kh_hourly', 'steps', 'horizon_h', 'wall_s', 'solve_s_median',
                'solver_failures'):
        assert key in kpis
    assert kpis['steps'] == 6
    assert (out / 'plot.png').stat().st_size > 10_000
    traj = pd.read_csv(out / 'trajectories.csv')
    assert len(traj) == 6 * 60 + 1


def test_case_command_reports_bad_data_path(tmp_path, caplog):
    assert case.main(['ou44', '--data', str(tmp_path / 'nope.csv'), '--out',
                      str(tmp_path)]) == 2
    assert 'not found' in caplog.text


# -- the mshoot command -----------------------------------------------------------------------
def _case_kpis(out: pathlib.Path) -> dict:
    kpis = json.loads((out / 'kpis.json').read_text())
    return {k: v for k, v in kpis.items() if not (k.endswith('_s') or k.startswith('solve_s'))
            and k != 'solve_per_control_step'}  # wall and solve times differ run to run


def test_mshoot_case_equals_the_case_module(tmp_path):
    args = ['synthetic', '--horizon', '3', '--hours', '5']
    assert cli.main(['case', *args, '--out', str(tmp_path / 'verb')]) == 0
    assert case.main([*args, '--out', str(tmp_path / 'module')]) == 0
    verb, module = _case_kpis(tmp_path / 'verb'), _case_kpis(tmp_path / 'module')
    assert verb == module and verb['steps'] == 5 and verb['energy_kwh'] > 0.0


def test_mshoot_verbs_use_their_modules_parsers():
    parser = cli.build_parser()
    args = parser.parse_args(['study', '--hours', '3', '--dask', 'local', '--timeout', '9'])
    assert args.run is study.run
    module_args = study.build_parser().parse_args(['--hours', '3', '--dask', 'local',
                                                   '--timeout', '9'])
    assert {k: v for k, v in vars(args).items() if k not in ('verb', 'run')} == vars(module_args)
    assert parser.parse_args(['case', 'ou44', '--control', 'svr']).run is case.run
    with pytest.raises(SystemExit) as exc:
        parser.parse_args([])  # a verb is required
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        parser.parse_args(['case', 'ou44', '--control', 'nope'])
    assert exc.value.code == 2


@pytest.mark.parametrize('words', [[verb, '--no-such-option'] for verb in cli.VERBS]
                         + [['case', 'ou44', '--hours', 'x'], ['card', 'check'], ['nope']])
def test_every_verb_reports_a_bad_command_line_in_one_line(words, capsys):
    """Whichever parser finds the error (mshoot's, the verb's, its action's): one line, exit 2."""
    with pytest.raises(SystemExit) as stop:
        cli.main(words)
    error = capsys.readouterr().err
    assert stop.value.code == 2
    assert error.startswith('mshoot') and ': error: ' in error and len(error.splitlines()) == 1


def test_mshoot_command_is_on_the_path_with_help_per_verb():
    """
    The command of the colcon install, as a shell that sourced env.sh finds it.

    A plain script (a symlink into the sources) in the install's ``bin``, not a generated
    console-script launcher: that one reads the installed packages' metadata at every command.
    """
    path = shutil.which('mshoot')
    assert path is not None, 'mshoot not on PATH: source env.sh'
    install = (ROOT / 'ros2_ws' / 'install').resolve()
    assert pathlib.Path(path).parent.resolve() == install / 'mshoot_studies' / 'bin'
    assert 'load_entry_point' not in pathlib.Path(path).read_text()
    expected = {(): ['case', 'study'], ('case',): ['--control', '--horizon', 'ou44'],
                ('study',): ['--jobs', '--dask', '--timeout', '--parts']}
    for verb, words in expected.items():
        done = subprocess.run([path, *verb, '--help'], capture_output=True, text=True,
                              timeout=60)
        assert done.returncode == 0, done.stderr
        assert done.stdout.startswith(f'usage: {" ".join(("mshoot",) + verb)} ')
        for word in words:
            assert word in done.stdout, (verb, word)
    bad = subprocess.run([path, 'case', 'ou44', '--hours', '0'], capture_output=True,
                         text=True, timeout=60)
    assert bad.returncode == 2


def test_python_m_modules_keep_working():
    for module in ('mshoot_studies', 'mshoot_studies.case', 'mshoot_studies.study'):
        done = subprocess.run([sys.executable, '-m', module, '--help'], capture_output=True,
                              text=True, timeout=60, env=dict(os.environ))
        assert done.returncode == 0, done.stderr
        assert done.stdout.startswith('usage: ')


@pytest.mark.parametrize('solver', ['slsqp', 'ipopt'])
def test_mshoot_case_loads_only_what_the_case_uses(tmp_path, solver):
    """
    ``mshoot case`` imports neither the study (nor its cluster client) nor matplotlib.

    Matplotlib is imported by its plot worker. Nor, with an FMU control model and SLSQP or
    IPOPT, the SciPy optimisers (SLSQP's core is loaded on its own; cyipopt without its SciPy
    interface), SciPy's sparse matrices, or the model cards' JSON Schema (the emulated R1C1 is
    the network of its card: YAML is read).
    """
    if solver == 'ipopt':
        pytest.importorskip('cyipopt', reason='the IPOPT case needs cyipopt-wheels')
    probe = ('import json, sys\n'
             'from mshoot_studies import cli\n'
             'code = cli.main(sys.argv[1:])\n'
             'print(json.dumps([code, sorted(sys.modules)]))\n')
    done = subprocess.run(
        [sys.executable, '-c', probe, 'case', 'synthetic', '--horizon', '3', '--hours', '4',
         '--control', 'fmu', '--solver', solver, '--out', str(tmp_path / 'case')],
        capture_output=True, text=True, timeout=120, env=dict(os.environ))
    assert done.returncode == 0, done.stderr
    code, modules = json.loads(done.stdout.splitlines()[-1])
    assert code == 0 and 'mshoot_studies.case' in modules and 'mshoot_core.mpc' in modules
    assert not [m for m in modules if m.split('.')[0] in ('matplotlib', 'dask', 'distributed',
                                                          'jsonschema')
                or m in ('mshoot_studies.study', 'scipy.optimize', 'scipy.sparse')]
    assert 'scipy.optimize._slsqplib' in modules
    assert (tmp_path / 'case' / 'plot.png').stat().st_size > 10_000


def test_mshoot_command_exits_fast_and_clean(tmp_path):
    """
    The console script ends without the interpreter's teardown, after a normal exit's work.

    What a normal exit does is done: every file and log line out, no extracted FMU left behind.
    """
    out, scratch = tmp_path / 'case', tmp_path / 'tmp'
    scratch.mkdir()
    done = subprocess.run(
        [shutil.which('mshoot'), 'case', 'synthetic', '--horizon', '3', '--hours', '4',
         '--control', 'fmu', '--emulator', 'fmu-cs', '--out', str(out)],
        capture_output=True, text=True, timeout=120, env=dict(os.environ, TMPDIR=str(scratch)))
    assert done.returncode == 0, done.stderr
    assert done.stderr.rstrip().endswith(f'wrote {out / "kpis.json"}')  # the last log line
    assert sorted(p.name for p in out.iterdir()) == ['kpis.json', 'plot.png', 'steps.csv',
                                                     'trajectories.csv']
    assert json.loads((out / 'kpis.json').read_text())['steps'] == 4
    assert list(scratch.iterdir()) == []
    bad = subprocess.run([shutil.which('mshoot'), 'case', 'synthetic', '--hours', '0'],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and '--hours must be >= 1' in bad.stderr


@pytest.mark.parametrize('with_thread', [False, True])
def test_exit_now_does_what_a_normal_exit_does_for_the_outputs(tmp_path, with_thread):
    """
    Buffered output, atexit handlers and a running thread: done before the process ends.

    Atexit handlers: logging's, finalizers; the process ends with the code given.
    """
    probe = ('import atexit, logging, sys, threading, time\n'
             'from mshoot_studies.cli import exit_now\n'
             f'logging.basicConfig(filename={str(tmp_path / "log.txt")!r}, level=logging.INFO)\n'
             'logging.getLogger("probe").info("logged")\n'
             'atexit.register(lambda: print("atexit ran", file=sys.stderr))\n'
             'if sys.argv[1] == "thread":\n'
             '    late = lambda: (time.sleep(0.3), print("thread done"))\n'
             '    threading.Thread(target=late).start()\n'
             'print("buffered", end="")\n'
             'exit_now(3)\n')
    done = subprocess.run([sys.executable, '-c', probe, 'thread' if with_thread else 'none'],
                          capture_output=True, text=True, timeout=60,
                          env={k: v for k, v in os.environ.items() if k != 'PYTHONUNBUFFERED'})
    assert done.returncode == 3
    assert done.stdout == ('buffered' + ('thread done\n' if with_thread else ''))
    assert done.stderr == 'atexit ran\n'
    assert (tmp_path / 'log.txt').read_text() == 'INFO:probe:logged\n'


@pytest.mark.parametrize('collector', ['on', 'off'])
def test_import_verb_imports_without_collections_and_restores_the_collector(collector):
    """The verb's module is imported, no collection runs meanwhile, its objects are frozen."""
    probe = ('import gc, sys\n'
             'from mshoot_studies.cli import import_verb\n'
             'if sys.argv[1] == "off":\n'
             '    gc.disable()\n'
             'runs = []\n'
             'gc.callbacks.append(lambda phase, info: runs.append(phase))\n'
             'frozen = gc.get_freeze_count()\n'
             'import_verb("card")\n'
             'assert "mshoot_studies.card" in sys.modules\n'
             'assert runs == [], runs\n'
             'assert gc.get_freeze_count() > frozen\n'
             'assert gc.isenabled() == (sys.argv[1] == "on")\n')
    done = subprocess.run([sys.executable, '-c', probe, collector], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr


# -- Setup 2 ----------------------------------------------------------------------------------
@pytest.mark.parametrize('ventilation', ['measured', 'off'])
def test_setup2_svr_on_ou44(ou44_csv, ventilation):
    model, report = train_setup2(ou44_csv, 'svr', seed=0, ventilation=ventilation)
    assert model.is_fitted and report.estimator == 'svr'
    split_s = (pd.Timestamp(SETUP2_SPLIT) - pd.Timestamp(SETUP2_START)).total_seconds()
    assert report.validation.index[0] == split_s
    assert report.n_validation == len(report.validation) > 90  # 9-13 April, hourly
    assert report.n_train > 100  # 4 April 08:00 to 9 April, hourly
    assert report.rmse_free_run_k < 0.5
    assert report.rmse_one_step_k < 0.05
    assert report.rmse_one_step_k <= report.rmse_free_run_k
    table = report.validation
    np.testing.assert_allclose(table['T_free_run'].iloc[0], table['T_true'].iloc[0])
    assert 15.0 < table['T_true'].mean() < 35.0  # degC, not K
