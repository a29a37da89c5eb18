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
