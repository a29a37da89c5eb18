"""
Sweeps (mshoot_studies.sweeps): the same runs in process, in the local pool and on Dask.

Deadlines stop a run in the middle of a step while the sweep goes on.
"""
import math
import time

from mshoot_studies.sweeps import (Deadline, execute, RunSpec, RunStopped, StoppableModel,
                                   SweepRunner)
import numpy as np
import pytest

#: Short runs that differ in what the workers must build or receive: the exact model, the
#: FMU (control and emulator) at a tolerance, a trained scikit-learn model, another cost.
SPECS = (RunSpec('python', 4, 3), RunSpec('python', 2, 3, cost='energy'),
         RunSpec('fmu', 3, 3, tolerance=1e-6, emulator='fmu-cs'), RunSpec('linear', 3, 3))
#: A run whose first MPC step takes minutes: the naive algorithm with the FMU at H = 6 h
#: (over 90 s on an idle machine; a loaded one only makes it longer).
SLOW = RunSpec('fmu', 6, 2, tolerance=1e-6, mode='naive')
#: KPIs that depend on the run only (not on the machine's speed).
DETERMINISTIC = ('energy_kwh', 'heating_kwh', 'cooling_kwh', 'discomfort_kh',
                 'discomfort_kh_hourly', 'solver_failures', 'steps')


@pytest.fixture(scope='module')
def in_process(ou44_csv):
    """Return the reference: every run of SPECS in this process."""
    runner = SweepRunner(ou44_csv, jobs=0)
    return dict(zip(SPECS, runner.run(SPECS)))


def assert_same_runs(got, reference):
    assert [o.spec for o in got] == [o.spec for o in reference]
    for mine, theirs in zip(got, reference):
        assert mine.stop == 'completed' and mine.completed_steps == mine.spec.hours
        np.testing.assert_allclose(mine.steps['q'].to_numpy(), theirs.steps['q'].to_numpy(),
                                   rtol=0.0, atol=1e-9)
        np.testing.assert_allclose(mine.fine['y_T'].to_numpy(), theirs.fine['y_T'].to_numpy(),
                                   rtol=0.0, atol=1e-9)
        for key in DETERMINISTIC:
            assert mine.kpis[key] == pytest.approx(theirs.kpis[key], rel=1e-9, abs=1e-12), key


def test_local_pool_gives_the_in_process_runs(ou44_csv, in_process):
    with SweepRunner(ou44_csv, jobs=2) as runner:
        got = runner.run(SPECS)  # 4 runs on 2 workers: a fresh process for each
        assert runner.run(SPECS[:2]) == got[:2]  # cached, not run again
        assert runner.runs_done == len(SPECS)
    assert_same_runs(got, [in_process[s] for s in SPECS])
    assert runner.training_reports['linear']['rmse_free_run_k'] > 0.0


def test_dask_cluster_gives_the_in_process_runs(ou44_csv, in_process):
    distributed = pytest.importorskip('distributed')
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=':0') as cluster:
        with SweepRunner(ou44_csv, timeout_s=600.0, dask=cluster.scheduler_address) as runner:
            assert runner.parallel_runs == 2
            assert 'Dask cluster' in runner.description
            got = runner.run(SPECS)
    assert_same_runs(got, [in_process[s] for s in SPECS])


@pytest.mark.parametrize('where', ['in process', 'local pool', 'dask local'])
def test_a_run_over_its_timeout_is_stopped_mid_step_and_the_sweep_goes_on(ou44_csv, in_process,
                                                                          where):
    jobs, dask = {'in process': (0, None), 'local pool': (2, None),
                  'dask local': (1, 'local')}[where]
    with SweepRunner(ou44_csv, jobs, timeout_s=2.0, dask=dask) as runner:
        slow, quick = runner.run([SLOW, SPECS[0]])
    # the slow run never finished its first step: only a stop in the middle of it ends it
    assert slow.stop == 'timeout' and slow.timed_out and not slow.finished
    assert slow.completed_steps == 0 and slow.steps.empty
    assert math.isnan(slow.kpis['energy_kwh']) and slow.kpis['steps'] == 0
    # ... and the run after it in the same sweep is complete and unchanged
    assert_same_runs([quick], [in_process[SPECS[0]]])


def test_a_budget_stops_a_run_and_keeps_its_finished_steps(ou44_csv):
    spec = RunSpec('python', 10, 6, mode='naive', budget_s=1.5)  # about 1 s per step
    with SweepRunner(ou44_csv, jobs=1, timeout_s=600.0) as runner:
        (cut,) = runner.run([spec])
    assert cut.stop == 'budget' and not cut.timed_out
    assert cut.completed_steps < spec.hours
    assert len(cut.steps) == cut.completed_steps == cut.kpis.get('steps', cut.completed_steps)
    if cut.completed_steps:  # the kept steps are those of the uncut run
        # the same scenario (the same forecasts near its end), run for the kept steps only
        full = execute(RunSpec('python', 10, cut.completed_steps, mode='naive'),
                       runner.scenario(spec.hours))
        np.testing.assert_allclose(cut.steps['q'].to_numpy(), full.steps['q'].to_numpy(),
                                   atol=1e-9)
        assert cut.fine.index[-1] == pytest.approx(3600.0 * cut.completed_steps)


def test_a_stoppable_model_is_its_model_until_the_deadline():
    from mshoot_core.models.r1c1 import R1C1Model
    from mshoot_core.scenario import synthetic_scenario
    model = R1C1Model()
    udf = synthetic_scenario(hours=3)[['solrad', 'Tout', 'occ', 'dpos']].assign(q=500.0)
    udf = udf[list(model.input_names)]
    deadline = Deadline(0.3).start()
    wrapped = StoppableModel(model, deadline)
    assert (wrapped.input_names, wrapped.state_names, wrapped.output_names) == (
        model.input_names, model.state_names, model.output_names)
    y_wrapped, x_wrapped = wrapped.simulate(udf, [293.15])
    y, x = model.simulate(udf, [293.15])
    np.testing.assert_array_equal(x_wrapped.to_numpy(), x.to_numpy())
    np.testing.assert_array_equal(y_wrapped.to_numpy(), y.to_numpy())
    time.sleep(0.4)
    assert deadline.expired
    with pytest.raises(RunStopped):
        wrapped.simulate(udf, [293.15])
    with pytest.raises(RunStopped):
        wrapped.simulate_intervals(np.array([[293.15]]), udf.to_numpy()[:1], 3600.0)
    assert not Deadline(None).start().expired
    with pytest.raises(ValueError, match='deadline'):
        Deadline(0.0)
    with pytest.raises(TypeError, match='Model'):
        StoppableModel(object(), deadline)


def test_runner_rejects_bad_settings(ou44_csv, tmp_path):
    with pytest.raises(ValueError, match='jobs'):
        SweepRunner(ou44_csv, jobs=-1)
    with pytest.raises(ValueError, match='timeout_s'):
        SweepRunner(ou44_csv, timeout_s=0.0)
    with pytest.raises(ValueError, match='dask'):
        SweepRunner(ou44_csv, dask='')
    with pytest.raises(FileNotFoundError):
        SweepRunner(tmp_path / 'missing.csv')
