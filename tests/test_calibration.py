"""Calibration: known parameters recovered, the OU44 reference through the verb, bad options."""
import json
import pathlib
import subprocess
import sys

from mshoot_core import calibration
from mshoot_core.models import card as cards
from mshoot_studies import calibrate as verb
import numpy as np
import pandas as pd
import pytest

#: Parameters of the R1C1 that generate the data of the recovery tests (not the published ones).
TRUTH = {'tmass': 80.0, 'shgc': 3.0, 'occheff': 1.5, 'RExt': 6.0}


def synthetic_inputs(rows: int, seed: int = 3) -> pd.DataFrame:
    """Return 30-minute inputs of the R1C1 that excite every free parameter."""
    rng = np.random.default_rng(seed)
    t = np.arange(rows) * 1800.0
    hours = t / 3600.0
    day = (hours % 24 >= 8) & (hours % 24 < 17)
    return pd.DataFrame({
        'solrad': np.clip(400.0 * np.sin(2 * np.pi * (hours - 6) / 24), 0.0, None),
        'Tout': 5.0 + 4.0 * np.sin(2 * np.pi * (hours - 9) / 24) + rng.normal(0, 0.5, rows),
        'occ': np.where(day, 20.0, 0.0) * rng.uniform(0.5, 1.0, rows),
        'dpos': np.where(day, 30.0, 0.0),
        'q': rng.uniform(0.0, 2689.0, rows)}, index=pd.Index(t, name='time_s'))


def generated_period(build: calibration.Builder, rows: int) -> calibration.Period:
    """Return a period whose 'measurements' are the model's own output at :data:`TRUTH`."""
    inputs = synthetic_inputs(rows)
    start = calibration.Period('gen', inputs, np.array([293.15]), np.zeros(rows))
    measured = calibration.simulate_period(build(TRUTH), start)
    return calibration.Period('train', inputs, start.x0, measured)


def assert_recovered(result: calibration.CalibrationResult) -> None:
    for name, value in TRUTH.items():
        assert result.parameters[name] == pytest.approx(value, rel=1e-3), name
    assert result.metrics['train']['rmse_k'] < 1e-3


def test_recovers_python_r1c1_parameters() -> None:
    build = calibration.r1c1_builder(calibration.OU44_FIXED)
    period = generated_period(build, 4 * 48 + 1)
    result = calibration.calibrate(build, calibration.OU44_FREE, [period])
    # the fit starts at the published values, far from TRUTH
    assert abs(result.starts[0]['initial']['tmass'] - TRUTH['tmass']) > 20.0
    assert_recovered(result)
    assert not [w for w in result.warnings if 'bound' in w]


def test_multistart_and_prior() -> None:
    build = calibration.r1c1_builder(calibration.OU44_FIXED)
    period = generated_period(build, 2 * 48 + 1)
    result = calibration.calibrate(build, calibration.OU44_FREE, [period], starts=3, seed=1)
    assert len(result.starts) == 3
    assert len({round(s['initial']['tmass'], 6) for s in result.starts}) == 3
    assert_recovered(result)
    # a tight prior on shgc away from the truth pulls the fit towards the prior
    free = [p if p.name != 'shgc' else calibration.FreeParameter('shgc', 4.6, 0.0, 20.0, 5.0,
                                                                 1e-3)
            for p in calibration.OU44_FREE]
    pulled = calibration.calibrate(build, free, [period], noise=0.01)
    assert pulled.parameters['shgc'] == pytest.approx(5.0, abs=1e-2)
    assert pulled.metrics['train']['rmse_k'] > 1e-3


def test_bound_and_correlation_warnings() -> None:
    build = calibration.r1c1_builder(calibration.OU44_FIXED)
    period = generated_period(build, 2 * 48 + 1)
    free = [p if p.name != 'tmass' else calibration.FreeParameter('tmass', 50.0, 1.0, 60.0)
            for p in calibration.OU44_FREE]
    result = calibration.calibrate(build, free, [period])
    assert result.parameters['tmass'] == pytest.approx(60.0)
    assert any(w.startswith('tmass') and 'upper bound' in w for w in result.warnings)
    lo, hi = result.ci95['shgc']
    assert lo < result.parameters['shgc'] < hi
    assert np.allclose(np.diag(result.correlation), 1.0)


def test_recovers_fmu_parameters_through_card() -> None:
    build = calibration.card_builder(cards.builtin_card('r1c1_fmu'), tolerance=1e-10)
    period = generated_period(build, 48 + 1)
    reference = calibration.simulate_period(calibration.r1c1_builder()(TRUTH), period)
    assert np.max(np.abs(reference - period.measured)) < 1e-3  # the FMU is the same model
    result = calibration.calibrate(build, calibration.OU44_FREE, [period])
    assert_recovered(result)


def test_bad_parameters_raise() -> None:
    with pytest.raises(ValueError, match='lower'):
        calibration.FreeParameter('tmass', 5.0, 10.0, 1.0)
    with pytest.raises(ValueError, match='unknown R1C1 parameters'):
        calibration.r1c1_builder({'nope': 1.0})
    build = calibration.r1c1_builder()
    with pytest.raises(ValueError, match='starts'):
        calibration.calibrate(build, calibration.OU44_FREE, [generated_period(build, 5)],
                              starts=0)


def test_ou44_reference_calibration(ou44_csv: pathlib.Path, tmp_path: pathlib.Path) -> None:
    out = tmp_path / 'cal'
    assert verb.main(['ou44', '--data', str(ou44_csv), '--out', str(out)]) == 0
    report = json.loads((out / 'calibration.json').read_text())
    published = report['published']
    # the fit improves on the published parameters over the period it was fitted on
    assert report['rmse_train_k'] < published['rmse_train_k']
    for name, value in report['parameters'].items():
        lo, hi = verb.BOUNDS[name]
        assert lo < value < hi, name
        assert not any(w.startswith(name) and 'bound' in w for w in report['warnings'])
        ci_lo, ci_hi = report['ci95'][name]
        assert ci_lo < value < ci_hi
    assert set(report['parameters']) == set(verb.FREE)
    assert report['wall_s'] > 0 and (out / 'calibration.png').stat().st_size > 10_000
    # the calibrated card loads and reproduces the reported RMSEs
    model = cards.build_model(out / 'r1c1_calibrated.yaml')
    periods = calibration.ou44_periods(ou44_csv)
    for period in periods:
        scores = calibration.metrics(calibration.simulate_period(model, period),
                                     period.measured)
        assert scores['rmse_k'] == pytest.approx(report[f'rmse_{period.name}_k'], rel=1e-9)
    published_model = calibration.r1c1_builder()({})
    scores = calibration.metrics(calibration.simulate_period(published_model, periods[1]),
                                 periods[1].measured)
    assert scores['rmse_k'] == pytest.approx(published['rmse_validation_k'], rel=1e-12)


def test_ou44_calibration_of_an_fmu_card(ou44_csv: pathlib.Path,
                                         tmp_path: pathlib.Path) -> None:
    """The built-in Co-Simulation FMU (an exact solver) reaches the Python R1C1's optimum."""
    python, fmu = tmp_path / 'python', tmp_path / 'fmu'
    assert verb.main(['ou44', '--data', str(ou44_csv), '--out', str(python), '--no-figure']) == 0
    assert verb.main(['ou44', '--data', str(ou44_csv), '--out', str(fmu), '--no-figure',
                      '--model', str(cards.builtin_card('r1c1_fmu_cs'))]) == 0
    a, b = (json.loads((p / 'calibration.json').read_text()) for p in (python, fmu))
    for name, value in a['parameters'].items():
        assert b['parameters'][name] == pytest.approx(value, rel=1e-3), name
    card = cards.load_card(fmu / 'r1c1_calibrated.yaml')
    assert card.builtin == 'r1c1-fmu' and card.interface == 'CoSimulation'
    assert card.parameters['tmass'] == pytest.approx(b['parameters']['tmass'], rel=1e-12)


@pytest.mark.parametrize('extra', [['--starts', '0'], ['--free', 'tmass,nope'],
                                   ['--bound', 'tmass=5:1'], ['--prior', 'shgc=4'],
                                   ['--train', '2018-04-04 08:00', '2017-01-01 00:00'],
                                   ['--model', 'no_such_card.yaml']])
def test_bad_options_exit_2_one_line(ou44_csv: pathlib.Path, tmp_path: pathlib.Path,
                                     extra: list) -> None:
    run = subprocess.run([sys.executable, '-m', 'mshoot_studies.calibrate', 'ou44', '--data',
                          str(ou44_csv), '--out', str(tmp_path), *extra],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    assert len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert not (tmp_path / 'calibration.json').exists()


def test_missing_data_exits_2(tmp_path: pathlib.Path) -> None:
    run = subprocess.run([sys.executable, '-m', 'mshoot_studies.calibrate', 'ou44', '--data',
                          str(tmp_path / 'none.csv'), '--out', str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    assert 'not found' in run.stderr and len(run.stderr.strip().splitlines()) == 1
