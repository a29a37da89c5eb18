"""Lint: ament_pep257 over this package, as ``colcon test`` runs it."""
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1]


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257() -> None:
    """Check every docstring of the package with ament's pep257 configuration."""
    ament_pep257 = pytest.importorskip('ament_pep257.main')
    assert ament_pep257.main(argv=[str(PACKAGE)]) == 0, 'pep257 violations (listed above)'
