"""
Lint as tests: ament_flake8 and ament_pep257 with ament's default configuration.

The configuration is the one ``colcon test`` applies to a ROS 2 package: 99 columns, google
import order, single quotes, the flake8 plugins ament_flake8 expects, and pep257 with ament's
ignore list. The only addition is what google import order cannot guess: the application
(``application-import-names``), which forms the last import group. For a package that is the
package itself; for tests/ and bench/ the local modules they import through ``sys.path``
(conftest, card_fmus, timed_fmu, bench's common and casadi_ref). Everything else, the
workspace's other packages included, is third party, sorted by module name.
``tools/ament_layout.py`` applies the mechanical part (docstring layout, import groups).

Both linters run as subprocesses from the folder they check, as ``colcon test`` runs them from
the package, so that their module-level state (flake8's worker pool, pep257's ``sys.argv``)
stays out of the test process.
"""
import configparser
import pathlib
import re
import subprocess
import sys

import ament_flake8
import pytest

from conftest import ROOT

# Folder checked -> its application modules (google import order's last group).
LINTED = {
    'ros2_ws/src/mshoot_core': ('mshoot_core',),
    'ros2_ws/src/mshoot_nodes': ('mshoot_nodes',),
    'ros2_ws/src/mshoot_studies': ('mshoot_studies',),
    'ros2_ws/src/mshoot_testing': ('mshoot_testing',),
    'tests': ('card_fmus', 'casadi_ref', 'conftest', 'timed_fmu'),
    'bench': ('casadi_ref', 'common'),
    'tools': (),
}
GUARD_S = 600.0
FLAKE8_VIOLATION = re.compile(r'^\S+\.py:\d+:\d+: [A-Z]+\d+ ')
PEP257_VIOLATION = re.compile(r'^\S+\.py:\d+ .*: D\d{3}: ')


def flake8_config(application: tuple[str, ...], directory: pathlib.Path) -> pathlib.Path:
    """
    Write ament_flake8's configuration with ``application-import-names`` set.

    Parameters
    ----------
    application : tuple of str
        Top-level modules forming the last import group.
    directory : pathlib.Path
        Where to write ``flake8.ini``.

    Returns
    -------
    pathlib.Path
        The configuration file.

    """
    config = configparser.ConfigParser()
    config.read(pathlib.Path(ament_flake8.__file__).parent / 'configuration' / 'ament_flake8.ini')
    if application:
        config['flake8']['application-import-names'] = ','.join(application)
    path = directory / 'flake8.ini'
    with path.open('w') as stream:
        config.write(stream)
    return path


def run_linter(module: str, args: list[str], cwd: pathlib.Path) -> tuple[int, str]:
    """
    Run ``python -m <module> <args>`` in ``cwd``.

    Parameters
    ----------
    module : str
        ``ament_flake8.main`` or ``ament_pep257.main``.
    args : list of str
        Command-line arguments.
    cwd : pathlib.Path
        Working directory: the folder checked.

    Returns
    -------
    tuple of (int, str)
        Exit code and the merged stdout and stderr.

    """
    done = subprocess.run([sys.executable, '-m', module, *args], cwd=cwd, text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=GUARD_S)
    return done.returncode, done.stdout


def python_files(folder: pathlib.Path) -> list[pathlib.Path]:
    """Return the ``.py`` files under ``folder`` that are not in a hidden or private folder."""
    return sorted(p for p in folder.rglob('*.py')
                  if not any(part[0] in '._' for part in p.relative_to(folder).parent.parts))


def violations(output: str, pattern: re.Pattern[str]) -> str:
    """Return the violation lines of a linter's output (all of it when none parses)."""
    found = [line for line in output.splitlines() if pattern.match(line)]
    return '\n'.join(found) if found else output[-4000:]


def flake8(folder: pathlib.Path, application: tuple[str, ...],
           config_dir: pathlib.Path) -> tuple[int, str, int]:
    """
    Run ament_flake8 over ``folder``.

    Parameters
    ----------
    folder : pathlib.Path
        The folder checked, also the working directory.
    application : tuple of str
        The folder's own top-level modules.
    config_dir : pathlib.Path
        Where to write the configuration.

    Returns
    -------
    tuple of (int, str, int)
        Exit code, output and the number of files flake8 reports as checked.

    """
    config = flake8_config(application, config_dir)
    code, output = run_linter('ament_flake8.main', ['--config', str(config), '.'], folder)
    checked = re.search(r'^(\d+) files checked$', output, re.MULTILINE)
    return code, output, int(checked.group(1)) if checked else -1


@pytest.mark.parametrize('folder', sorted(LINTED))
def test_flake8(folder: str, tmp_path: pathlib.Path) -> None:
    """Check every Python file of the folder with ament_flake8."""
    path = ROOT / folder
    code, output, checked = flake8(path, LINTED[folder], tmp_path)
    assert code == 0, f'ament_flake8 {folder}:\n{violations(output, FLAKE8_VIOLATION)}'
    assert checked == len(python_files(path)), output[-4000:]


@pytest.mark.parametrize('folder', sorted(LINTED))
def test_pep257(folder: str) -> None:
    """Check every docstring of the folder with ament_pep257."""
    path = ROOT / folder
    code, output = run_linter('ament_pep257.main', ['.'], path)
    assert code == 0, f'ament_pep257 {folder}:\n{violations(output, PEP257_VIOLATION)}'
    checked = [line for line in output.splitlines() if line.startswith('checking ')]
    assert len(checked) == len(python_files(path)), output[-4000:]


SAMPLE = '''\
"""Sample module."""
import os

from sample_own import helper
import numpy


def total(values):
    """Returns the sum."""
    return sum(values) + len("{}".format(os.sep)) + helper() + numpy.pi
''' + 'LONG = ' + repr('x' * 91) + '\n'  # 100 columns, one over ament's limit


def test_the_linters_report_what_ament_forbids(tmp_path: pathlib.Path) -> None:
    """The configuration in force flags import order, quotes, line length and mood."""
    (tmp_path / 'sample.py').write_text(SAMPLE)
    code, output, checked = flake8(tmp_path, ('sample_own',), tmp_path)
    found = {line.split()[1] for line in output.splitlines() if FLAKE8_VIOLATION.match(line)}
    assert code == 1 and checked == 1
    assert {'I100', 'I201', 'Q000', 'E501', 'D401'} <= found, output
    code, output = run_linter('ament_pep257.main', ['.'], tmp_path)
    assert code == 1
    assert 'D401' in violations(output, PEP257_VIOLATION), output
