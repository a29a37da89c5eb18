"""Lint: ament_flake8 over this package, as ``colcon test`` runs it."""
import configparser
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Check the package with ament's flake8 configuration; its modules form the last group."""
    ament_flake8 = pytest.importorskip('ament_flake8.main')
    config = configparser.ConfigParser()
    config.read(pathlib.Path(ament_flake8.__file__).parent / 'configuration' / 'ament_flake8.ini')
    config['flake8']['application-import-names'] = PACKAGE.name
    path = tmp_path / 'flake8.ini'
    with path.open('w') as stream:
        config.write(stream)
    monkeypatch.chdir(PACKAGE)
    rc, errors = ament_flake8.main_with_errors(argv=['--config', str(path), '.'])
    assert rc == 0, f'{len(errors)} flake8 violations:\n' + '\n'.join(errors)
