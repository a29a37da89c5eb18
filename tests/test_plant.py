"""
The emulated building as a plant, restarts, and FMUs that compute NaN.

The built-in R1C1 FMU's output ``Qr`` (the integral of q, a state the model
does not map) shows whether the plant keeps its internal states; the
time-dependent test FMU (``tests/fmus/timed_zone.c``, parameter ``nan_after``)
computes NaN from a given FMU time on.
"""
import json

from mshoot_core.closed_loop import EmulationStopped, run_closed_loop
from mshoot_core.controller import Controller
from mshoot_core.emulation import Emulator, Warmup
from mshoot_core.models import registry
from mshoot_core.models.base import ModelValueError
from mshoot_core.models.fmi import FmiModel, FmuValueError, r1c1_fmi_model
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.scenario import reference_scenario, synthetic_scenario
from mshoot_studies import case
import numpy as np
import pandas as pd
import pytest

from timed_fmu import VARIABLES

HOUR = 3600.0
FMI_TYPES = ['CoSimulation', 'ModelExchange']


def timed_model(path, fmi_type='CoSimulation', schedule=0, **parameters):
    return FmiModel(path, **VARIABLES, fmi_type=fmi_type, tolerance=1e-10,
                    parameters={'schedule': float(schedule), **parameters})


def run_steps(emulator, controls):
    records = [emulator.advance([q]) for q in controls]
    return pd.concat([r.fine if k == 0 else r.fine.iloc[1:] for k, r in enumerate(records)])


# -- one instance for the whole run ------------------------------------------------------------
@pytest.mark.parametrize('fmi_type', FMI_TYPES)
def test_plant_keeps_its_internal_states(fmi_type):
    """
    Qr (not mapped) keeps counting across steps instead of restarting at 0 every hour.

    The zone temperature is the exact R1C1's.
    """
    scenario = synthetic_scenario(hours=7)
    controls = [1000.0, 1000.0, -500.0, 0.0, 2000.0, 250.0]
    with r1c1_fmi_model(fmi_type=fmi_type, tolerance=1e-10) as model:
        emulator = Emulator(model, scenario, [293.15])
        assert emulator.plant
        fine = run_steps(emulator, controls)
    exact = run_steps(Emulator(R1C1Model(), scenario, [293.15]), controls)
    hourly = fine['y_Qr'].to_numpy()[::60]
    np.testing.assert_allclose(hourly, np.concatenate([[0.0], np.cumsum(controls) * HOUR]),
                               rtol=1e-9, atol=1e-3)
    np.testing.assert_allclose(fine['y_Qr'].to_numpy(), np.concatenate(
        [[0.0], np.cumsum(np.repeat(controls, 60)) * 60.0]), rtol=1e-9, atol=1e-3)
    tol = 1e-9 if fmi_type == 'CoSimulation' else 1e-6
    np.testing.assert_allclose(fine['x_T'].to_numpy(), exact['x_T'].to_numpy(), rtol=0,
                               atol=tol)


def test_case_with_the_fmu_plant_gives_the_exact_emulators_kpis(ou44_csv):
    """
    The 72 h OU44 case with the R1C1 FMU (Co-Simulation) as the plant.

    The KPIs of the exact Python emulator (to the rounding the MPC's solves amplify), and Qr meters
    the heat of the whole run.
    """
    scenario = reference_scenario('ou44', ou44_csv, 72)
    with r1c1_fmi_model(fmi_type='CoSimulation', tolerance=1e-10) as plant:
        result, kpis = case.run_case(scenario, R1C1Model(), plant, horizon=10, log_every=0)
    exact, exact_kpis = case.run_case(scenario, R1C1Model(), R1C1Model(), horizon=10,
                                      log_every=0)
    for name in ('energy_kwh', 'heating_kwh', 'cooling_kwh', 'discomfort_kh',
                 'discomfort_kh_hourly'):
        assert kpis[name] == pytest.approx(exact_kpis[name], rel=1e-6, abs=1e-6), name
    np.testing.assert_allclose(result.steps['T_end'], exact.steps['T_end'], rtol=0, atol=1e-5)
    assert result.fine['y_Qr'].iloc[-1] == pytest.approx(
        float((result.steps['q'] * HOUR).sum()), rel=1e-9)


def test_batch_calls_end_a_plant_run():
    with r1c1_fmi_model(fmi_type='CoSimulation') as model:
        model.plant_start([293.15], 0.0, [0.0, 5.0, 0.0, 0.0, 100.0])
        model.plant_step([0.0, 5.0, 0.0, 0.0, 100.0], 60.0)
        assert model.plant_time_s == 60.0
        model.simulate_intervals([[293.15]], [[0.0, 5.0, 0.0, 0.0, 100.0]], HOUR)
        with pytest.raises(RuntimeError, match='no plant run'):
            model.plant_step([0.0, 5.0, 0.0, 0.0, 100.0], 60.0)


# -- restarts --------------------------------------------------------------------------------
RESTART_CONTROLS = [800.0, -300.0, 1500.0, 0.0, -1200.0, 600.0, 100.0]


def _restart_models(timed_fmus, kind, fmi_type):
    if kind == 'r1c1':
        return lambda: r1c1_fmi_model(fmi_type=fmi_type, tolerance=1e-10)
    return lambda: timed_model(timed_fmus[kind], fmi_type, schedule=1)


@pytest.mark.parametrize('fmi_type', FMI_TYPES)
@pytest.mark.parametrize('kind', ['r1c1', 'state'])
def test_restart_from_a_saved_plant_state(timed_fmus, kind, fmi_type):
    """
    A run interrupted after 3 steps resumes from the saved FMU state.

    The same trajectory, every internal state included (Qr / Eint), as the uninterrupted run.
    """
    scenario = synthetic_scenario(hours=8)
    make = _restart_models(timed_fmus, kind, fmi_type)
    with make() as model:
        full = run_steps(Emulator(model, scenario, [292.0]), RESTART_CONTROLS)
    with make() as model:
        first = Emulator(model, scenario, [292.0])
        run_steps(first, RESTART_CONTROLS[:3])
        saved, x_saved = first.save_plant_state(), first.x
    with make() as model:
        resumed = Emulator(model, scenario, x_saved, start_index=3, plant_state=saved)
        rest = run_steps(resumed, RESTART_CONTROLS[3:])
    tail = full.loc[rest.index]
    values = [c for c in rest.columns if c[:2] in ('x_', 'y_')]  # (row 0: the step's control)
    np.testing.assert_allclose(rest[values].to_numpy(), tail[values].to_numpy(), rtol=1e-12,
                               atol=1e-9)
    np.testing.assert_array_equal(rest['q'].iloc[1:], tail['q'].iloc[1:])
    counter = 'y_Qr' if kind == 'r1c1' else 'y_Eint'
    assert rest[counter].iloc[0] == tail[counter].iloc[0] != 0.0


@pytest.mark.parametrize('fmi_type', FMI_TYPES)
def test_restart_with_a_warm_up_where_the_fmu_cannot_save_its_state(timed_fmus, fmi_type):
    scenario = synthetic_scenario(hours=8)
    make = _restart_models(timed_fmus, 'nostate', fmi_type)
    with make() as model:
        first = Emulator(model, scenario, [292.0])
        full = run_steps(first, RESTART_CONTROLS)
        with pytest.raises(ValueError, match='cannot save its state'):
            first.save_plant_state()
    with make() as model:
        x3 = full['x_T'].loc[3 * HOUR]
        with pytest.raises(ValueError, match='cannot restore a saved state'):
            Emulator(model, scenario, [x3], start_index=3, plant_state=b'MSHOOT-PLANT\x01')
        warm = Emulator(model, scenario, [x3], start_index=3,
                        warmup=Warmup([292.0], np.array(RESTART_CONTROLS[:3])[:, None]))
        assert warm.index == 3 and warm.t_s == 3 * HOUR
        rest = run_steps(warm, RESTART_CONTROLS[3:])
    values = [c for c in rest.columns if c[:2] in ('x_', 'y_')]
    np.testing.assert_allclose(rest[values].to_numpy(), full.loc[rest.index, values].to_numpy(),
                               rtol=0, atol=1e-12)
    assert rest['y_Eint'].iloc[0] > 0.0  # the gains of the warm-up hours are in the meter


def test_saved_plant_state_must_match(timed_fmus):
    scenario = synthetic_scenario(hours=8)
    with r1c1_fmi_model(fmi_type='CoSimulation') as model:
        emulator = Emulator(model, scenario, [292.0])
        run_steps(emulator, [0.0, 0.0])
        saved = emulator.save_plant_state()
    with r1c1_fmi_model(fmi_type='CoSimulation') as model:
        with pytest.raises(ValueError, match=r'saved plant state is at t = 7200.0 s, the restart '
                                             r'at row 3 \(t = 10800.0 s\)'):
            Emulator(model, scenario, [292.0], start_index=3, plant_state=saved)
    with timed_model(timed_fmus['state']) as other:
        with pytest.raises(ValueError, match='not one of this model'):
            Emulator(other, scenario, [292.0], start_index=2, plant_state=saved)
    with pytest.raises(ValueError, match='needs a model with a persistent plant'):
        Emulator(R1C1Model(), scenario, [292.0], start_index=2, plant_state=saved)


# -- non-finite values -----------------------------------------------------------------------
@pytest.mark.parametrize('fmi_type, schedule', [('CoSimulation', 0), ('ModelExchange', 0),
                                                ('ModelExchange', 1)])
def test_non_finite_intervals_name_the_variable_and_the_fmu_time(timed_fmus, fmi_type,
                                                                 schedule):
    """Values NaN from FMU time 10 h on: the batch raises FmuValueError (not a CVode message)."""
    x, u = np.full((4, 1), 293.0), np.tile([5.0, 0.0], (4, 1))
    with timed_model(timed_fmus['state'], fmi_type, schedule, nan_after=10 * HOUR) as model:
        ok, _ = model.simulate_intervals(
            x, u, HOUR, t_start_s=[0.0, 3 * HOUR, 6 * HOUR, 9 * HOUR - 1.0])
        assert np.all(np.isfinite(ok))
        with pytest.raises(FmuValueError) as info:
            model.simulate_intervals(x, u, HOUR, t_start_s=[0.0, 10 * HOUR, 11 * HOUR, 2.0])
        if fmi_type == 'ModelExchange':
            with pytest.raises(FmuValueError):
                model.interval_jacobians(x, u, HOUR, [1], t_start_s=[0.0, 10 * HOUR,
                                                                     11 * HOUR, 2.0])
            if schedule == 1:  # the compiled driver stays on after a non-finite interval
                assert model.me_batch_plan() is None and model._me_driver is not False
    error = info.value
    assert isinstance(error, ModelValueError) and isinstance(error, ValueError)
    assert 'zone.T' in error.variable and error.fmu == 'TimedZone.fmu'
    assert 10 * HOUR <= error.time_s <= 11 * HOUR
    assert 'non-finite' in str(error) and 'at FMU time' in str(error)


@pytest.mark.parametrize('fmi_type', FMI_TYPES)
def test_control_model_nan_is_a_solve_failed_fallback(timed_fmus, fmi_type):
    """
    Solves whose horizon reaches FMU time 10 h fail with the FmuValueError.

    The controller falls back ('solve_failed') and the loop goes on.
    """
    scenario = synthetic_scenario(hours=12)
    with timed_model(timed_fmus['state'], fmi_type, 1, nan_after=10 * HOUR) as control, \
            timed_model(timed_fmus['state'], 'CoSimulation', 1) as plant:
        result = run_closed_loop(Controller(mpc=MPC(control, horizon_steps=4)),
                                 Emulator(plant, scenario, [293.15]), steps=9, log_every=0)
    steps = result.steps
    broken = steps.index >= 6 * HOUR  # horizons ending past 10 h
    assert not steps['fallback'][~broken].any()
    assert steps['fallback'][broken].all()
    assert set(steps['fallback_code'][broken]) == {'solve_failed'}
    reason = steps['fallback_reason'][broken].iloc[0]
    assert 'solve failed: FmuValueError: TimedZone.fmu: non-finite' in reason
    assert ("'zone.T'" in reason or "output 'T'" in reason) and 'at FMU time 36000 s' in reason


def test_emulator_nan_stops_the_run_with_the_steps_done(timed_fmus):
    scenario = synthetic_scenario(hours=12)
    with timed_model(timed_fmus['state'], nan_after=5.5 * HOUR) as plant:
        with pytest.raises(EmulationStopped) as info:
            run_closed_loop(MPC(R1C1Model(), horizon_steps=3),
                            _r1c1_inputs_emulator(plant, scenario), log_every=0)
    stop = info.value
    assert stop.step == 5 and stop.t_s == 5 * HOUR
    assert isinstance(stop.__cause__, FmuValueError)
    assert "'T'" in str(stop) and 'at FMU time 19800' in str(stop)
    assert len(stop.result.steps) == 5 and len(stop.result.fine) == 5 * 60 + 1
    assert np.all(np.isfinite(stop.result.fine.select_dtypes('number').to_numpy()))


def _r1c1_inputs_emulator(plant, scenario):
    return Emulator(plant, scenario, [293.15])


def test_case_command_exits_1_and_writes_the_steps_done(timed_fmus, tmp_path, monkeypatch,
                                                        caplog):
    """
    `mshoot case` with an emulator that computes NaN after 5.5 h: exit 1 with the message.

    kpis.json (with the reason under 'stopped'), steps.csv and trajectories.csv up to the last good
    step.
    """
    monkeypatch.setitem(registry._REGISTERED, 'timed-nan', (
        lambda tolerance: timed_model(timed_fmus['state'], nan_after=5.5 * HOUR), 'test FMU'))
    args = case.build_parser().parse_args(['synthetic', '--hours', '12', '--horizon', '3',
                                           '--out', str(tmp_path / 'out')])
    args.emulator = 'timed-nan'  # (the option offers the built-in models only)
    assert case.run(args) == 1
    kpis = json.loads((tmp_path / 'out' / 'kpis.json').read_text())
    assert 'emulation stopped at step 6/12' in kpis['stopped']
    assert 'TimedZone.fmu' in kpis['stopped'] and 'at FMU time 19800' in kpis['stopped']
    steps = pd.read_csv(tmp_path / 'out' / 'steps.csv')
    fine = pd.read_csv(tmp_path / 'out' / 'trajectories.csv')
    assert len(steps) == 5 and len(fine) == 5 * 60 + 1
    assert np.isfinite(fine['y_T']).all() and np.isfinite(kpis['discomfort_kh'])
    assert any('emulation stopped' in r.message and r.levelname == 'ERROR'
               for r in caplog.records)


def test_case_command_stopped_at_the_first_step_writes_the_reason(timed_fmus, tmp_path,
                                                                  monkeypatch):
    """Values NaN from FMU time 0: no step done; kpis.json holds the reason, no stale files."""
    monkeypatch.setitem(registry._REGISTERED, 'timed-nan-0', (
        lambda tolerance: timed_model(timed_fmus['state'], nan_after=0.0), 'test FMU'))
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'steps.csv').write_text('from an earlier run\n')
    args = case.build_parser().parse_args(['synthetic', '--hours', '4', '--horizon', '2',
                                           '--out', str(out)])
    args.emulator = 'timed-nan-0'
    assert case.run(args) == 1
    kpis = json.loads((out / 'kpis.json').read_text())
    assert kpis['stopped'].startswith('emulation stopped at step 1/4 (t = 0 s, 0 steps done)')
    assert "non-finite output 'T'" in kpis['stopped'] and kpis['emulator'] == 'timed-nan-0'
    assert sorted(p.name for p in out.iterdir()) == ['kpis.json']
