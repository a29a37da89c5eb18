"""
The controller in core: every per-step decision, the same offline and over ROS.

Plain tests of :class:`mshoot_core.controller.Controller` (input validation and
gating, waiting, the fallback chain, the time budget that stops the solver
itself, settings updates), then the same faults injected into a core run and
into a ROS run (real nodes in one process, lockstep): the decisions must agree
step by step.
"""
import concurrent.futures
import threading
import time

from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.controller import Controller, controller_for
from mshoot_core.emulation import Emulator
from mshoot_core.kpis import closed_loop_kpis
from mshoot_core.models.multizone import MultiZoneModel
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.outputs import write_outputs
from mshoot_core.scenario import forecast_window, reference_scenario, synthetic_scenario
from mshoot_core.settings import MpcSettings
from mshoot_core.solvers import make_solver
from mshoot_core.units import KELVIN
from mshoot_testing.faults import FaultyModel, FaultySolver
import numpy as np
import pandas as pd
import pytest

NS = 1_000_000_000
STEP_NS = 3600 * NS


class SlowModel(R1C1Model):
    """
    The exact R1C1 whose every batched call sleeps ``delay_s`` while ``slow`` is set.

    A control model that cannot finish a solve within its budget.
    """

    def __init__(self, delay_s: float) -> None:
        super().__init__()
        self.delay_s = delay_s
        self.slow = threading.Event()
        self.calls = 0

    def _maybe_sleep(self) -> None:
        if self.slow.is_set():
            self.calls += 1
            time.sleep(self.delay_s)

    def simulate_intervals(self, x_start, u, dt_s):
        self._maybe_sleep()
        return super().simulate_intervals(x_start, u, dt_s)

    def interval_jacobians(self, x_start, u, dt_s, wrt_inputs):
        self._maybe_sleep()
        return super().interval_jacobians(x_start, u, dt_s, wrt_inputs)


def offer(controller, scenario, k, state_c=None, now_ns=None):
    """Offer the state and a perfect forecast of step ``k`` (scenario-relative time)."""
    now = k * STEP_NS if now_ns is None else now_ns
    window = forecast_window(scenario, k, controller.mpc.horizon_steps)
    x = [(20.0 if state_c is None else state_c) + KELVIN]
    return (controller.offer_state(k * STEP_NS, x, now),
            controller.offer_forecast(k * STEP_NS, 3600.0,
                                      {c: window[c].to_numpy() for c in window.columns}, now))


# -- the controller alone -----------------------------------------------------------------
def test_bad_inputs_are_rejected_counted_and_never_solved():
    scenario = synthetic_scenario(hours=6)
    controller = Controller(R1C1Model(), MpcSettings.from_flat(horizon_steps=3))
    assert controller.offer_state(0, [np.nan], 0).kind == 'non_finite'
    assert controller.offer_state(0, [900.0], 0).kind == 'out_of_range'
    assert controller.offer_state(0, [293.0, 1.0], 0).kind == 'length'
    window = forecast_window(scenario, 0, 3)
    series = {c: window[c].to_numpy() for c in window.columns}
    inverted = dict(series, comfort_min=series['comfort_max'] + 1.0)
    assert controller.offer_forecast(0, 3600.0, inverted, 0).kind == 'band'
    assert controller.offer_forecast(0, 60.0, series, 0).kind == 'step'
    assert controller.rejections.by_kind() == {'band': 1, 'length': 1, 'non_finite': 1,
                                               'out_of_range': 1, 'step': 1}
    # Nothing valid yet: the step waits, then falls back on the safe setpoint.
    assert controller.poll(1, steady_ns=0) == []
    [outcome] = controller.poll(1, steady_ns=int(5.1 * NS))
    assert outcome.decision.source == 'safe' and outcome.decision.code == 'inputs_missing'
    assert 'no zone state for the step and no forecast for the step' in outcome.decision.reason
    # Valid inputs for the next step: an optimum. Backwards stamps are rejected.
    assert offer(controller, scenario, 1) == (None, None)
    [outcome] = controller.poll(STEP_NS + 1)
    assert outcome.decision.source == 'optimum' and outcome.result.success
    assert controller.offer_state(0, [293.15], STEP_NS + 2).kind == 'backwards'


def test_named_inputs_are_checked_against_the_model():
    """
    Two zones: states by name in any order; bad names and values are rejected.

    Unknown, missing or repeated names, a series the model does not know, a bad price: rejected
    with kind 'names' (or the value's).
    """
    scenario = synthetic_scenario(hours=6)
    controller = controller_for(MultiZoneModel(2), MpcSettings.from_flat(horizon_steps=3),
                                assumed_inputs={'dpos': 0.0})
    assert controller.interface.control_names == ('q_0', 'q_1')
    assert controller.mpc.state_bounds == {'T_0': ('comfort_min', 'comfort_max', KELVIN),
                                           'T_1': ('comfort_min', 'comfort_max', KELVIN)}
    assert controller.forecast_required == ('solrad', 'Tout', 'occ', 'comfort_min',
                                            'comfort_max')
    offer_state = controller.offer_named_state
    rejected = [
        offer_state(0, ['T_0'], [293.0], 0),  # missing T_1
        offer_state(0, ['T_0', 'T_1', 'T_2'], [293.0, 294.0, 295.0], 0),
        offer_state(0, ['T_0', 'T_0'], [293.0, 293.0], 0),
        offer_state(0, ['T_0', 'T_1'], [293.0], 0),
        offer_state(0, ['T_0', 'T_1'], [293.0, 294.0], 0, control_names=['q'],
                    control_values=[10.0]),
        offer_state(0, ['T_0', 'T_1'], [293.0, 394.0], 0),
        offer_state(0, ['T_0', 'T_1'], [293.0, 294.0], 0, output_names=['Tc_0'],
                    output_values=[np.nan]),
    ]
    assert [r.kind for r in rejected] == ['names', 'length', 'names', 'length', 'names',
                                          'out_of_range', 'non_finite']
    assert "state lacks ['T_1']" in rejected[0].reason
    assert "control has unknown ['q']" in rejected[4].reason
    # Any order: put in the model's order.
    assert offer_state(0, ['T_1', 'T_0'], [294.0, 293.0], 0, control_names=['q_1'],
                       control_values=[5.0]) is None
    state = controller._states[controller._state_stamp(0)]  # noqa: SLF001
    np.testing.assert_array_equal(state, [293.0, 294.0])
    window = forecast_window(scenario, 0, 3)
    series = {c: window[c].to_numpy() for c in ('Tout', 'solrad', 'occ', 'comfort_min',
                                                'comfort_max')}
    assert controller.offer_forecast(0, 3600.0, dict(series, Tsky=series['Tout']),
                                     0).kind == 'names'
    missing = {k: v for k, v in series.items() if k != 'occ'}
    assert controller.offer_forecast(0, 3600.0, missing, 0).kind == 'length'
    assert controller.offer_forecast(0, 3600.0, dict(series, price=np.full(4, 1e6)),
                                     0).kind == 'out_of_range'
    assert controller.offer_forecast(0, 3600.0, dict(series, price=np.full(4, 0.3)), 0) is None
    [outcome] = controller.poll(0)
    assert outcome.decision.source == 'optimum'
    assert outcome.decision.controls.shape == (2,)


def _two_band_card(folder, zones=('0', '1')):
    """Write the card r1c1x2 with a test case forecast naming a band per zone of ``zones``."""
    import yaml
    from mshoot_core.models.card import builtin_card
    document = yaml.safe_load(builtin_card('r1c1x2').read_text())
    document['testcase_forecast'] = {
        'series': {'Tout': {'columns': ['TDryBul'], 'offset': -273.15}},
        'bands': {z: {'lower': f'LowerSetp[{z}]', 'upper': f'UpperSetp[{z}]'} for z in zones}}
    path = folder / 'two_bands.yaml'
    path.write_text(yaml.safe_dump(document))
    return path


def test_each_zone_is_kept_in_its_own_band(tmp_path):
    """
    A card with a band per zone: each zone temperature is bounded by its own, both narrowed.

    Zone 1's band (22-26 degC) lies above zone 0's (20-24 degC): the plan (energy cost, band
    raised 0.5 K) holds each zone at its own raised lower edge from there, and the forecast
    must carry
    both bands. A card naming bands of several zones but not of every zone is refused.
    """
    from mshoot_core.models.card import build_model, CardError, load_card
    model = build_model(load_card(_two_band_card(tmp_path)))
    controller = controller_for(model, MpcSettings.from_flat(horizon_steps=6, cost='energy',
                                                             band_margin_k=0.5),
                                assumed_inputs={'dpos': 0.0})
    assert controller.mpc.state_bounds == {
        'T_0': ('comfort_min_0', 'comfort_max_0', KELVIN),
        'T_1': ('comfort_min_1', 'comfort_max_1', KELVIN)}
    assert sorted(controller.forecast_required) == ['Tout', 'comfort_max_0', 'comfort_max_1',
                                                    'comfort_min_0', 'comfort_min_1', 'occ',
                                                    'solrad']
    rows = 7
    series = {'solrad': np.zeros(rows), 'Tout': np.full(rows, 5.0), 'occ': np.zeros(rows),
              'comfort_min_0': np.full(rows, 20.0), 'comfort_max_0': np.full(rows, 24.0),
              'comfort_min_1': np.full(rows, 22.0), 'comfort_max_1': np.full(rows, 26.0)}
    assert controller.offer_named_state(0, ['T_0', 'T_1'], [20.5 + KELVIN, 22.5 + KELVIN],
                                        0) is None
    assert controller.offer_forecast(0, 3600.0, series, 0) is None
    [outcome] = controller.poll(0)
    assert outcome.decision.source == 'optimum'
    plan = outcome.result.plan
    # (the plan's states at the intervals' ends; one band would let zone 1 cool 0.5 K in 6 h)
    np.testing.assert_allclose(plan['T_0_end'].to_numpy() - KELVIN, 20.5, atol=0.02)
    np.testing.assert_allclose(plan['T_1_end'].to_numpy() - KELVIN, 22.5, atol=0.02)
    # the forecast margin (outdoor temperature errors) narrows each zone's own band
    uncertain = controller_for(model, controller.settings.replace(
        forecast_uncertainty='high', forecast_margin_std=1.0,
        forecast_error_inputs='Tout=temperature'), assumed_inputs={'dpos': 0.0})
    uncertain.offer_named_state(0, ['T_0', 'T_1'], [20.5 + KELVIN, 22.5 + KELVIN], 0)
    uncertain.offer_forecast(0, 3600.0, series, 0)
    [outcome] = uncertain.poll(0)
    ends = outcome.result.plan[['T_0_end', 'T_1_end']].to_numpy() - KELVIN
    assert (ends[-1] - [20.5, 22.5] > 0.03).all() and (ends >= [20.5, 22.5]).all()
    with pytest.raises(CardError, match=r"\['T_1'\] have no band of their own"):
        load_card(_two_band_card(tmp_path, zones=('0', '2')))


def test_stale_state_falls_back_on_the_last_good_plan():
    scenario = synthetic_scenario(hours=6)
    controller = Controller(R1C1Model(), MpcSettings.from_flat(horizon_steps=4,
                                                               input_deadline_s=600.0))
    offer(controller, scenario, 0)
    [first] = controller.poll(0)
    assert first.decision.source == 'optimum'
    # Step 1: only the forecast comes; after 600 s of controller clock the plan is used.
    window = forecast_window(scenario, 1, 4)
    controller.offer_forecast(STEP_NS, 3600.0, {c: window[c].to_numpy() for c in window},
                              STEP_NS)
    assert controller.poll(STEP_NS, steady_ns=0) == []
    [outcome] = controller.poll(STEP_NS + 600 * NS, steady_ns=1)
    d = outcome.decision
    assert d.source == 'plan' and d.code == 'inputs_missing'
    assert 'the zone state is stale (newest 3600 s before the step' in d.reason
    np.testing.assert_allclose(d.controls, first.decision.plan_controls[1])


@pytest.mark.parametrize('solver', ['slsqp', 'ipopt'])
def test_time_budget_stops_the_solver_itself(solver):
    scenario = synthetic_scenario(hours=12)
    model = SlowModel(delay_s=0.02)
    settings = MpcSettings.from_flat(horizon_steps=10, solver=solver)
    free = Controller(model, settings)
    offer(free, scenario, 8, state_c=17.0)
    model.slow.set()
    [unbudgeted] = free.poll(8 * STEP_NS)
    assert unbudgeted.decision.source == 'optimum' and unbudgeted.result.success
    calls_free = model.calls
    model.calls = 0
    budgeted = Controller(model, settings.replace(time_budget_s=0.2))
    offer(budgeted, scenario, 8, state_c=17.0)
    [outcome] = budgeted.poll(8 * STEP_NS)
    # The solver stopped itself: far fewer model calls than the full solve, no optimum.
    assert outcome.result.budget_exceeded and not outcome.result.success
    assert model.calls < calls_free / 2, (model.calls, calls_free)
    assert outcome.decision.code == 'budget' and outcome.decision.source == 'safe'
    assert 'time budget exceeded (0.2 s): solver stopped after' in outcome.decision.reason


def test_update_is_a_setter_or_a_rebuild():
    scenario = synthetic_scenario(hours=6)
    controller = Controller(R1C1Model(), MpcSettings.from_flat(horizon_steps=4))
    offer(controller, scenario, 0)
    controller.poll(0)
    warm = controller.mpc._warm_start
    s = controller.settings
    assert controller.update(s) == 'unchanged'
    assert controller.update(s.replace(solver='ipopt', solver_max_iter=50)) == 'updated'
    assert controller.mpc.solver.name == 'ipopt' and controller.mpc.solver.max_iter == 50
    assert controller.mpc._warm_start is warm  # a solver change keeps the warm start
    assert controller.update(controller.settings.replace(soft_penalty=5.0)) == 'updated'
    assert controller.mpc.problem.soft_penalty == 5.0
    assert controller.update(controller.settings.replace(safe_value=100.0)) == \
        'updated+supervisor'
    assert controller.supervisor.safe_controls.tolist() == [100.0]
    assert controller.update(controller.settings.replace(horizon_steps=6)) == 'rebuilt'
    assert controller.mpc.horizon_steps == 6 and controller.mpc._warm_start is None
    with pytest.raises(ValueError, match=r"\['step_s'\] cannot change"):
        controller.update(controller.settings.replace(step_s=1800.0))


def test_solves_on_an_executor_decide_as_inline():
    scenario = synthetic_scenario(hours=8)
    inline = Controller(R1C1Model(), MpcSettings.from_flat(horizon_steps=4))
    done = threading.Event()
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        threaded = Controller(R1C1Model(), MpcSettings.from_flat(horizon_steps=4),
                              executor=pool, on_solve_done=done.set)
        for k in range(4):
            offer(inline, scenario, k)
            offer(threaded, scenario, k)
            [expected] = inline.poll(k * STEP_NS)
            done.clear()
            outcomes = threaded.poll(k * STEP_NS)  # dispatched to the worker
            if not outcomes:  # not finished yet: the owner polls again when told
                assert done.wait(30.0)
                outcomes = threaded.poll(k * STEP_NS)
            [outcome] = outcomes
            assert not threaded.busy
            assert outcome.decision.source == expected.decision.source
            np.testing.assert_allclose(outcome.decision.plan_controls,
                                       expected.decision.plan_controls, rtol=0, atol=1e-9)


# -- the same decisions in a core run and over ROS ------------------------------------------
HOURS = 8
FAULT_STEP = 3


def inject(fault, model, solver, on):
    """Switch a fault on (before step FAULT_STEP) or off (after it)."""
    if fault == 'raise':
        model.faults.arm('raise', times=100_000) if on else model.faults.clear()
    elif fault == 'nan':
        solver.faults.arm('nan', times=100_000) if on else solver.faults.clear()
    elif fault == 'fail':
        solver.faults.arm('fail', times=100_000) if on else solver.faults.clear()
    elif fault == 'late':
        model.inner.slow.set() if on else model.inner.slow.clear()


FAULT_MPC = {'horizon_steps': 4, 'on_failure': 'fallback', 'time_budget_s': 1.0,
             'max_plan_age_steps': 2}
#: A model call of the 'late' fault [s]. The solver looks at its deadline when an iteration
#: ends: the first ends after 6 model calls, here half a budget past the deadline, so the
#: solver stops itself at its first iteration however loaded the machine is (with 0.1 s, its
#: 4th and last iteration ended within ~1 % of the budget: stopped there or finished late, by
#: a few ms, each leaving another warm start, and the later steps 3e-4 W apart).
LATE_CALL_S = FAULT_MPC['time_budget_s'] / 4


def fault_setup(fault):
    inner = SlowModel(delay_s=LATE_CALL_S) if fault == 'late' else R1C1Model()
    return FaultyModel(inner), FaultySolver(make_solver('slsqp'))


def core_decisions(fault, hours=HOURS, fault_steps=(FAULT_STEP,), whole=False):
    model, solver = fault_setup(fault)
    mpc = MPC(model, MpcSettings.from_flat(FAULT_MPC))
    mpc.set_solver(solver)
    scenario = reference_scenario('synthetic', None, hours)  # as the emulator node's

    def progress(rows, fines):
        if len(rows) == fault_steps[0]:
            inject(fault, model, solver, True)
        if len(rows) == fault_steps[-1] + 1:
            inject(fault, model, solver, False)

    result = run_closed_loop(Controller(mpc=mpc), Emulator(R1C1Model(), scenario, [293.15]),
                             progress=progress, log_every=0)
    return result if whole else result.steps


@pytest.mark.parametrize('fault', ['raise', 'nan', 'fail', 'late'])
def test_core_and_ros_make_the_same_decisions(fault, context):
    from mshoot_testing.harness import ClosedLoop
    steps = core_decisions(fault)
    model, solver = fault_setup(fault)
    params = {'emulator': {'hours': HOURS, 'model': 'python'},
              'forecaster': {'hours': HOURS},
              'mpc': {'model': 'python', **FAULT_MPC}}
    loop = ClosedLoop(context, params, mpc_model=model)
    try:
        loop.mpc.mpc.set_solver(solver)
        loop.run_steps(FAULT_STEP)
        inject(fault, model, solver, True)
        loop.run_steps(1)
        inject(fault, model, solver, False)
        loop.run_to_end(60.0)
        # (the MPC may also decide the step of the emulator's final state: not compared)
        statuses = [status for _, status in loop.mpc_history()][:HOURS]
        setpoints = [setpoint for setpoint, _ in loop.mpc_history()][:HOURS]
    finally:
        loop.close()
    assert [s.source for s in statuses] == steps['source'].tolist()
    assert [s.fallback_reason for s in statuses] == steps['fallback_code'].tolist()
    np.testing.assert_allclose([s.control_values[0] for s in setpoints], steps['q'], rtol=0,
                               atol=1e-9)
    expected = {'raise': 'solve_failed', 'nan': 'not_converged', 'fail': 'not_converged',
                'late': 'budget'}[fault]
    assert steps['fallback_code'].iloc[FAULT_STEP] == expected
    assert steps['source'].iloc[FAULT_STEP] == 'plan'
    assert (steps['source'].drop(steps.index[FAULT_STEP]) == 'optimum').all()
    if fault == 'late':  # stopped by its deadline at its first iteration (LATE_CALL_S)
        assert steps['iterations'].iloc[FAULT_STEP] == 1


def test_model_raising_from_hour_20_same_decisions_over_ros(context):
    """
    The 72 h run whose control model raises from hour 20 on, over ROS: the core run's decisions.

    Lockstep, real nodes in one process; the decisions of the core run, step by step.
    """
    from mshoot_testing.harness import ClosedLoop
    steps = core_decisions('raise', hours=72, fault_steps=(20, 72))
    model, solver = fault_setup('raise')
    loop = ClosedLoop(context, {'emulator': {'hours': 72, 'model': 'python'},
                                'forecaster': {'hours': 72},
                                'mpc': {'model': 'python', **FAULT_MPC}}, mpc_model=model)
    try:
        loop.mpc.mpc.set_solver(solver)
        loop.run_steps(20)
        inject('raise', model, solver, True)
        loop.run_to_end(120.0)
        history = list(loop.mpc_history())[:72]
    finally:
        loop.close()
    assert [s.source for _, s in history] == steps['source'].tolist()
    assert [s.fallback_reason for _, s in history] == steps['fallback_code'].tolist()
    np.testing.assert_allclose([sp.control_values[0] for sp, _ in history], steps['q'], rtol=0,
                               atol=1e-9)
    assert steps['source'].tolist() == ['optimum'] * 20 + ['plan'] * 2 + ['safe'] * 50


def test_core_run_whose_model_raises_from_hour_20_completes(tmp_path):
    """
    72 steps, the control model raising from hour 20 on: the fallbacks, recorded in steps.csv.

    The last good plan for max_plan_age_steps steps, then the safe setpoint, all recorded in
    steps.csv.
    """
    result = core_decisions('raise', hours=72, fault_steps=(20, 72), whole=True)
    kpis = closed_loop_kpis(result.steps, result.fine, 3600.0, result.wall_s)
    write_outputs(tmp_path, result, kpis, 'the model raises from hour 20')  # the case's writer
    read = pd.read_csv(tmp_path / 'steps.csv', index_col='time_s', keep_default_na=False)
    assert len(read) == 72
    assert read['source'].tolist() == ['optimum'] * 20 + ['plan'] * 2 + ['safe'] * 50
    assert set(read['fallback_code'].iloc[20:]) == {'solve_failed'}
    assert read['fallback'].tolist() == [False] * 20 + [True] * 52
    assert read['fallback_reason'].iloc[25].startswith(
        'solve failed: InjectedModelError: injected model error')
    assert (read['q'].iloc[22:] == 0.0).all()  # the safe setpoint
