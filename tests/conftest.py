"""Shared fixtures: paths to the project and to the OU44 reference data."""
import os
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
OU44_CSV = ROOT.parent / 'shared' / 'data' / 'ou44' / 'measurements.csv'


@pytest.fixture(scope='session')
def ou44_csv() -> pathlib.Path:
    """Path of the OU44 measurements; skip (fail under CI=true) when absent."""
    if not OU44_CSV.is_file():
        if os.environ.get('CI') == 'true':
            pytest.fail(f'OU44 data missing at {OU44_CSV} (required under CI)')
        pytest.skip(f'OU44 data not found at {OU44_CSV}')
    return OU44_CSV


@pytest.fixture(scope='session')
def timed_fmus(tmp_path_factory: pytest.TempPathFactory) -> dict[str, pathlib.Path]:
    """The time-dependent test FMU (tests/fmus/timed_zone.c), built with gcc: ``'state'``
    declares FMU-state get/set/serialise, ``'nostate'`` does not."""
    from timed_fmu import build_timed_fmu
    out = tmp_path_factory.mktemp('timed_fmu')
    return {'state': build_timed_fmu(out, True), 'nostate': build_timed_fmu(out, False)}
