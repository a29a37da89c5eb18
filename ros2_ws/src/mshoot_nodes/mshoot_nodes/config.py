"""
Where the YAML parameter files of a run are (the package's ``config/`` folder).

Kept apart from the nodes so that light tools (the process bring-up) find the
files without importing numpy, pandas and scipy.
"""
from __future__ import annotations

import argparse
import pathlib
from typing import Sequence

from ament_index_python.packages import get_package_share_directory, PackageNotFoundError

#: Parameter files of a closed-loop run, in load order.
CONFIG_FILES = ('emulator.yaml', 'forecaster.yaml', 'mpc.yaml', 'recorder.yaml')


def config_dir() -> pathlib.Path:
    """Return the installed ``share/mshoot_nodes/config`` (else the source tree's ``config/``)."""
    try:
        installed = pathlib.Path(get_package_share_directory('mshoot_nodes')) / 'config'
        if (installed / CONFIG_FILES[0]).is_file():
            return installed
    except PackageNotFoundError:
        pass
    return pathlib.Path(__file__).resolve().parents[1] / 'config'


def default_params_files(scenario: str | None = None) -> list[pathlib.Path]:
    """Return the config files of a run, plus ``<scenario>.yaml`` if it exists (e.g. ou44.yaml)."""
    folder = config_dir()
    files = [folder / name for name in CONFIG_FILES]
    if scenario and (folder / f'{scenario}.yaml').is_file():
        files.append(folder / f'{scenario}.yaml')
    return files


def ros_args(params_files: Sequence[pathlib.Path]) -> list[str]:
    """Command-line arguments loading ``params_files`` (``--ros-args --params-file ...``)."""
    args = ['--ros-args']
    for path in params_files:
        args += ['--params-file', str(path)]
    return args


def add_model_options(parser: argparse.ArgumentParser) -> None:
    """
    Add ``--emulator-model`` and ``--control-model`` to a bring-up's command line.

    Both default to None: the model of ``emulator.yaml`` / ``mpc.yaml``.

    """
    models = ('python, fmu, fmu-cs, r1c1x2 (two zones), an .fmu path or a model card '
              '(.yaml)')
    parser.add_argument('--emulator-model', default=None,
                        help=f'emulation model (default: the emulator.yaml one): {models}')
    parser.add_argument('--control-model', default=None,
                        help=f'MPC model (default: the mpc.yaml one): {models}')
