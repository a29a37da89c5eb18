"""
The reference study (mshoot_studies.study): every part on a shortened period.

KPIs are checked against an independent re-computation (the R1C1 closed-form
solution written out here from SPEC section 3, a trapezoidal discomfort
integral), tables against their ordering and contents, figures as real PNGs.
"""
import json
import math
import pathlib

import matplotlib.image
from mshoot_core.units import KELVIN
from mshoot_studies import study
from mshoot_studies.sweeps import RunSpec, SweepRunner
import numpy as np
import pytest

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'


# -- independent references -------------------------------------------------------------------
def r1c1_exact(t0_k: float, q_w: float, solrad: float, tout_c: float, occ: float,
               dt_s: float) -> float:
    """End temperature [K] of the R1C1 zone (SPEC section 3, dpos = 0) after ``dt_s`` [s]."""
    vi = 486.5
    capacity = 50.0 * 1.2 * 1005.0 * vi
    resistance = 4.0 / (3.0 * vi ** (2.0 / 3.0))
    occheff, shgc = 2.0836995296486704, 4.608961327935981
    # C dT/dt = a - b T
    a = (tout_c + KELVIN) / resistance + shgc * solrad + occheff * occ * 84.0 * 325.15 / 32.0 + q_w
    b = 1.0 / resistance + occheff * occ * 84.0 / 32.0
    t_inf = a / b
    return t_inf + (t0_k - t_inf) * math.exp(-b * dt_s / capacity)


def resimulate(outcome, scenario, fine_step_s: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """Re-simulate the applied heat rates on a fine grid: (times [s], T [degC])."""
    t_k = 20.0 + KELVIN
    times, temps = [0.0], [t_k - KELVIN]
    q = outcome.steps['q'].to_numpy()
    for k, q_k in enumerate(q):
        row = scenario.iloc[k]
        for j in range(int(3600.0 / fine_step_s)):
            t_k = r1c1_exact(t_k, q_k, row['solrad'], row['Tout'], row['occ'], fine_step_s)
            times.append(k * 3600.0 + (j + 1) * fine_step_s)
            temps.append(t_k - KELVIN)
    return np.array(times), np.array(temps)


def discomfort_reference(times: np.ndarray, temps: np.ndarray, scenario) -> float:
    """Trapezoidal integral [K h] of the distance outside the band (band of each hour)."""
    hour = np.minimum((times // 3600.0).astype(int), len(scenario) - 1)
    # the sample closing an hour belongs to that hour's band (as the emulator records it)
    closing = (times % 3600.0 == 0.0) & (times > 0)
    hour[closing] -= 1
    lo = scenario['comfort_min'].to_numpy()[hour]
    hi = scenario['comfort_max'].to_numpy()[hour]
    dist = np.maximum(lo - temps, 0.0) + np.maximum(temps - hi, 0.0)
    return float(np.sum(0.5 * (dist[1:] + dist[:-1]) * np.diff(times)) / 3600.0)


def assert_png(path: pathlib.Path, min_width: int = 600) -> None:
    assert path.is_file(), path
    assert path.read_bytes()[:8] == PNG_MAGIC
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[1] >= min_width
    assert float(np.std(image[..., :3])) > 0.01  # not a blank canvas


@pytest.fixture(scope='module')
def runner(ou44_csv):
    return SweepRunner(ou44_csv, jobs=0)


@pytest.fixture(scope='module')
def out(tmp_path_factory):
    return tmp_path_factory.mktemp('study')


# -- pieces -----------------------------------------------------------------------------------
def test_markdown_table_formats_and_dashes():
    table = study.markdown_table(
        [{'h': 2, 'e': 41.93, 'p': None}, {'h': 10, 'e': float('nan'), 'p': 44.0}],
        [('h', 'H [h]', 'd'), ('e', 'energy [kWh]', '.1f'), ('p', 'published', '.1f')])
    lines = table.split('\n')
    assert lines[0] == '| H [h] | energy [kWh] | published |'
    assert lines[2] == '| 2 | 41.9 | – |'
    assert lines[3] == '| 10 | – | 44.0 |'


def test_run_spec_is_validated_and_canonical():
    with pytest.raises(ValueError, match='control'):
        RunSpec('fmu-cs', 10)
    with pytest.raises(ValueError, match='tolerance'):
        RunSpec('fmu', 10)
    with pytest.raises(ValueError, match='soft_penalty'):
        RunSpec('python', 10, comfort='soft')
    # irrelevant settings do not make runs differ
    assert RunSpec('python', 10, tolerance=1e-6) == RunSpec('python', 10)
    assert RunSpec('python', 10, soft_penalty=5.0) == RunSpec('python', 10)


def test_energy_at_equal_discomfort_interpolates_inside_the_curve_only():
    curve = [{'discomfort_kh': 20.0, 'energy_kwh': 30.0}, {'discomfort_kh': 10.0,
                                                           'energy_kwh': 40.0}]
    assert study.energy_at_equal_discomfort(curve, 15.0) == pytest.approx(35.0)
    assert math.isnan(study.energy_at_equal_discomfort(curve, 5.0))


# -- the parts --------------------------------------------------------------------------------
def test_part1_verification_matches_an_independent_simulation(runner, out, ou44_csv):
    hours = 10  # includes the 08:00 step to the 21-22 degC band
    result = study.solution_verification(runner, out, hours=hours, horizons=(2, 4),
                                         tolerance=1e-6)
    assert_png(result.figure)
    rows = json.loads(result.json_path.read_text())['tables']['horizons']
    assert [r['horizon_h'] for r in rows] == [2, 4]
    assert all(r['published_energy_kwh'] is None for r in rows)  # not the 72 h case
    scenario = study.reference_scenario('ou44', ou44_csv, hours=hours)
    for row, horizon in zip(rows, (2, 4)):
        outcome = runner.cache[RunSpec('fmu', horizon, hours, tolerance=1e-6,
                                       emulator='fmu-cs')]
        q = outcome.steps['q'].to_numpy()
        assert len(q) == hours and np.all(np.abs(q) <= 2000.0 + 1e-9)
        assert row['energy_kwh'] == pytest.approx(np.sum(np.abs(q)) / 1000.0, rel=1e-9)
        times, temps = resimulate(outcome, scenario)
        emulated = outcome.fine['y_T'].to_numpy()
        np.testing.assert_allclose(outcome.fine.index.to_numpy(), times)
        np.testing.assert_allclose(emulated, temps, atol=1e-6)
        assert row['discomfort_kh'] == pytest.approx(
            discomfort_reference(times, temps, scenario), abs=1e-6)
    # H = 2 starts heating for the 08:00 band barely in time; a longer horizon earlier
    assert rows[0]['discomfort_kh'] > 1e-4
    assert rows[1]['discomfort_kh'] < rows[0]['discomfort_kh']
    assert rows[1]['energy_kwh'] > rows[0]['energy_kwh']
    assert '| 2 |' in result.markdown and 'study_1_verification.png' in result.markdown


def test_part2_tolerance_ours_is_tolerance_free_and_gradients_follow_it(runner, out):
    result = study.integration_tolerance(
        runner, out, hours=10, tolerances=(1e-4, 1e-8), naive_tolerances=(1e-5,),
        naive_horizon=2, naive_hours=4, naive_budget_s=60.0, horizon=4, gradient_samples=4)
    assert_png(result.figure, min_width=1200)
    payload = json.loads(result.json_path.read_text())
    ours = payload['tables']['ours']
    assert [r['tolerance'] for r in ours] == [1e-4, 1e-8]
    assert ours[0]['energy_kwh'] > 1.0  # the heating for the 08:00 band is in the window
    assert ours[0]['energy_kwh'] == pytest.approx(ours[1]['energy_kwh'], rel=1e-3)
    assert payload['spread_energy'] < 1e-3
    window = payload['tables']['naive_window']
    assert [r['method'] for r in window] == ['ours', 'naive']
    assert all(r['steps'] == 4 for r in window)
    gradients = {r['tolerance']: r for r in payload['tables']['gradients']}
    assert set(gradients) == {1e-4, 1e-5, 1e-8}
    for tol, row in gradients.items():
        # our sensitivities follow the tolerance ...
        assert row['sens_max_rel_error'] < 100 * tol
    # ... SciPy's default difference step has a rounding floor (q moved by 3e-5 W moves T by
    # 4e-9 K, doubles resolve 6e-14 K at 294 K): far above tight-tolerance sensitivities
    assert gradients[1e-8]['fd_median_rel_error'] > 1e-6
    assert gradients[1e-8]['fd_median_rel_error'] > 10 * gradients[1e-8]['sens_max_rel_error']
    assert '2b. Naive reproduction' in result.markdown


def test_part3_data_driven_smooth_and_piecewise_constant_models(runner, out):
    result = study.data_driven(runner, out, hours=4, models=('linear', 'knn'), matrix_hours=3,
                               solvers=('slsqp', 'ipopt'))
    assert_png(result.figure, min_width=1200)
    rows = {r['model']: r for r in json.loads(result.json_path.read_text())['tables']['models']}
    assert list(rows) == ['python', 'linear', 'knn']
    assert rows['linear']['rmse_free_run_k'] == pytest.approx(
        runner.training('linear')[1]['rmse_free_run_k'])
    assert 0.0 < rows['linear']['rmse_free_run_k'] < 1.0
    # affine vs piecewise constant in q
    assert rows['python']['wrong_slope_share'] == 0.0
    assert rows['linear']['wrong_slope_share'] == 0.0
    assert rows['knn']['wrong_slope_share'] > 0.5
    # k-NN runs over the matrix window only
    assert [r['steps'] for r in rows.values()] == [4, 4, 3]
    assert rows['knn']['label'].endswith('(first 3 h)')
    assert all(r['energy_kwh'] >= 0.0 for r in rows.values())
    matrix = json.loads(result.json_path.read_text())['tables']['solver_matrix']
    assert [(r['model'], r['solver']) for r in matrix] == [
        (m, s) for m in ('python', 'linear', 'knn') for s in ('slsqp', 'ipopt')]
    assert all(r['steps'] == 3 for r in matrix)
    # the exact model's one-step response is affine in q
    q, t_end = study.learned_response(study.R1C1Model())
    assert np.max(np.abs(np.diff(t_end, 2))) < 1e-9
    assert np.all(np.diff(t_end) > 0)


def test_part4_time_rows_follow_the_horizons(runner, out):
    result = study.computation_time(runner, out, hours=3, horizons=(2, 6), tolerance=1e-6)
    assert_png(result.figure)
    rows = json.loads(result.json_path.read_text())['tables']['time']
    assert [r['horizon_h'] for r in rows] == [2, 6]
    for r in rows:
        for m in ('fmu', 'python', 'svr'):
            assert 0.0 < r[f'{m}_solve_s_total'] <= r[f'{m}_wall_s']
        assert r['published_wall_s'] is None


def test_part5_soft_penalty_trades_energy_for_comfort(runner, out, ou44_csv):
    hours = 10
    result = study.beyond_the_original(runner, out, hours=hours, penalties=(10.0, 1000.0))
    assert_png(result.figure, min_width=1200)
    payload = json.loads(result.json_path.read_text())
    runs = payload['tables']['runs']
    assert [(r['cost'], r['comfort'], r['soft_penalty']) for r in runs] == [
        ('quadratic', 'hard', None), ('quadratic', 'soft', 10.0), ('quadratic', 'soft', 1000.0),
        ('energy', 'hard', None), ('energy', 'soft', 10.0), ('energy', 'soft', 1000.0)]
    for cost in ('quadratic', 'energy'):
        hard, low, high = [r for r in runs if r['cost'] == cost]
        assert low['energy_kwh'] < high['energy_kwh']
        assert low['discomfort_kh'] > high['discomfort_kh']
        assert hard['discomfort_kh'] <= high['discomfort_kh'] + 0.05
    assert len(payload['tables']['equal_discomfort']) == 3
    # the discomfort of a soft run (the band is left on purpose) against a re-simulation
    scenario = study.reference_scenario('ou44', ou44_csv, hours=hours)
    outcome = runner.cache[RunSpec('python', 10, hours, comfort='soft', soft_penalty=10.0)]
    times, temps = resimulate(outcome, scenario)
    reference = discomfort_reference(times, temps, scenario)
    assert reference > 0.05
    assert runs[1]['discomfort_kh'] == pytest.approx(reference, rel=1e-6)
    assert runs[1]['energy_kwh'] == pytest.approx(
        np.sum(np.abs(outcome.steps['q'].to_numpy())) / 1000.0, rel=1e-9)


# -- the command ---------------------------------------------------------------------------------
def test_command_writes_study_markdown(ou44_csv, tmp_path):
    assert study.main(['--data', str(ou44_csv), '--out', str(tmp_path), '--hours', '3',
                       '--parts', '5', '--jobs', '0']) == 0
    text = (tmp_path / 'study.md').read_text()
    assert '## 5. Beyond the original' in text
    assert '(study_5_tradeoff.png)' in text and '| quadratic | hard |' in text
    assert_png(tmp_path / 'study_5_tradeoff.png')
    assert study.main(['--data', str(ou44_csv), '--out', str(tmp_path), '--parts', '9']) == 2
    assert study.main(['--data', str(tmp_path / 'missing.csv'), '--out', str(tmp_path)]) == 2
