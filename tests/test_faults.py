"""
Fault injection in one process: every step gets a sane setpoint.

The fallback and the reason are in /mpc/status.

Faults go in at the real seams (:mod:`mshoot_testing.faults`: a solver that fails or
overruns, a model that raises), through the forecaster's ``enabled`` parameter
(the forecast stops) and by destroying and re-creating the MPC node (a restart).
Each test runs a short lockstep loop (:class:`mshoot_testing.harness.ClosedLoop`,
python R1C1 emulator) in a private context, with wall-clock guards.
"""
import re
import time

from mshoot_core.closed_loop import run_closed_loop
from mshoot_core.emulation import Emulator
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.safety import SetpointSupervisor
from mshoot_core.scenario import synthetic_scenario
from mshoot_core.solvers import make_solver
from mshoot_core.units import KELVIN, NS_PER_S
from mshoot_msgs.msg import Setpoint
from mshoot_nodes import contract
from mshoot_nodes.conversions import setpoint_msg, setpoint_plan, stamp_to_ns
from mshoot_nodes.emulator_node import EmulatorNode
from mshoot_testing.faults import FaultyModel, FaultySolver
from mshoot_testing.harness import ClosedLoop
import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

pytestmark = pytest.mark.ros
EPOCH_NS = 1522886400 * NS_PER_S  # the synthetic scenario's start
STEP_NS = 3600 * NS_PER_S


def make_loop(context, hours=6, mpc=None, emulator=None, **kwargs):
    params = {'emulator': {'hours': hours, 'model': 'python', **(emulator or {})},
              'forecaster': {'hours': hours},
              'mpc': {'model': 'python', 'horizon_steps': 6, **(mpc or {})}}
    return ClosedLoop(context, params, **kwargs)


def statuses(loop):
    return [status for _, status in loop.mpc_history()]


def step_stamps(loop):
    return [stamp_to_ns(setpoint.header.stamp) for setpoint, _ in loop.mpc_history()]


def assert_one_sane_setpoint_per_step(loop, hours):
    assert step_stamps(loop) == [EPOCH_NS + k * STEP_NS for k in range(hours)]
    for setpoint, status in loop.mpc_history():
        values = [*setpoint.control_values, *setpoint.temperature_setpoints_c, status.objective,
                  status.max_defect, status.solve_time_s, *setpoint.plan_controls,
                  *setpoint.plan_temperatures_c]
        assert np.all(np.isfinite(values))
        assert list(setpoint.control_names) == ['q']
        assert -2000.0 <= setpoint.control_values[0] <= 2000.0
        assert status.fallback == (status.source != 'optimum')
    applied = loop.emulator.applied_frame()['q'].to_numpy()
    np.testing.assert_array_equal(applied, [s.control_values[0] for s, _ in loop.mpc_history()])


def test_failing_solver_falls_back_on_the_last_good_plan(context):
    loop = make_loop(context, mpc={'on_failure': 'fallback'})
    try:
        solver = FaultySolver(make_solver('slsqp'))
        loop.mpc.mpc.set_solver(solver)
        loop.run_steps(2)
        solver.faults.arm('fail', times=1000)  # every solver call fails for two steps
        loop.run_steps(2)
        solver.faults.clear()
        loop.run_to_end(30.0)
        history = loop.mpc_history()
        sources = [status.source for _, status in history]
        assert sources == ['optimum', 'optimum', 'plan', 'plan', 'optimum', 'optimum']
        for k in (2, 3):
            status = history[k][1]
            assert status.fallback and not status.success
            assert status.fallback_reason == 'not_converged'
            assert 'solver did not converge' in status.message
            assert f'interval {k - 1} of the plan' in status.message
            assert status.consecutive_fallbacks == k - 1
            # The previous good plan (step 1), interval k - 1.
            plan = setpoint_plan(history[1][0])[0]['q']
            assert history[k][0].control_values[0] == pytest.approx(plan[k - 1], abs=1e-9)
            assert setpoint_plan(history[k][0])[0]['q'].tolist() == plan[k - 1:].tolist()
        assert solver.faults.injected['fail'] >= 2
        assert_one_sane_setpoint_per_step(loop, 6)
    finally:
        loop.close()


def test_unconverged_solver_publishes_its_best_plan_by_default(context):
    loop = make_loop(context, hours=3)
    try:
        solver = FaultySolver(make_solver('slsqp'))
        loop.mpc.mpc.set_solver(solver)
        loop.run_steps(1)
        solver.faults.arm('fail', times=1000)
        loop.run_to_end(30.0)
        last = statuses(loop)[-1]
        # on_failure 'plan': the solver's sane best plan, reported as not converged.
        assert not last.success and not last.fallback and last.source == 'optimum'
        assert_one_sane_setpoint_per_step(loop, 3)
    finally:
        loop.close()


def test_model_error_falls_back_on_the_plan_then_on_the_safe_setpoint(context):
    model = FaultyModel(R1C1Model())
    loop = make_loop(context, hours=7, mpc_model=model, mpc={
        'max_plan_age_steps': 2, 'safe_value': 500.0, 'safe_temperature_c': 21.5})
    try:
        loop.run_steps(1)
        model.faults.arm('raise', times=100_000)  # an FMU that errors on every call
        loop.run_steps(4)
        model.faults.clear()
        loop.run_to_end(30.0)
        history = loop.mpc_history()
        assert [s.source for _, s in history] == ['optimum', 'plan', 'plan', 'safe', 'safe',
                                                  'optimum', 'optimum']
        for setpoint, status in history[1:5]:
            assert status.fallback_reason == 'solve_failed'
            assert 'InjectedModelError' in status.message
            assert status.objective == -1.0 and status.max_defect == -1.0
        for setpoint, status in history[3:5]:
            assert list(setpoint.control_values) == [500.0]
            assert list(setpoint.temperature_setpoints_c) == [21.5]
            assert list(setpoint.plan_controls) == []
            assert 'the safe values [500.0]' in status.message
        assert [s.consecutive_fallbacks for _, s in history] == [0, 1, 2, 3, 4, 0, 0]
        assert_one_sane_setpoint_per_step(loop, 7)
    finally:
        loop.close()


def test_solve_overrunning_its_budget_and_a_solver_still_busy(context):
    loop = make_loop(context, mpc={'time_budget_s': 0.3})
    try:
        solver = FaultySolver(make_solver('slsqp'))
        loop.mpc.mpc.set_solver(solver)
        loop.run_steps(2)
        solver.faults.arm('overrun', delay_s=0.9)  # the step-2 solve takes > 0.9 s
        loop.run_to_end(30.0)
        history = loop.mpc_history()
        assert [s.source for _, s in history][:2] == ['optimum', 'optimum']
        assert history[2][1].fallback_reason == 'budget'
        assert 'time budget exceeded (0.3 s)' in history[2][1].message
        assert history[2][1].source == 'plan'
        # The next step came while the worker was still busy: a fallback after the budget.
        assert history[3][1].fallback_reason == 'budget'
        assert 'is still running' in history[3][1].message
        assert [s.source for _, s in history][4:] == ['optimum', 'optimum']
        assert_one_sane_setpoint_per_step(loop, 6)
    finally:
        loop.close()


def test_unusable_plan_is_never_published(context):
    loop = make_loop(context, hours=3)
    try:
        loop.run_steps(1)
        core = loop.mpc.mpc
        real_solve = core.solve

        def non_finite_solve(x0, t_s, window, deadline=None):
            result = real_solve(x0, t_s, window, deadline)
            result.controls = np.full_like(result.controls, np.nan)
            return result

        core.solve = non_finite_solve
        loop.run_steps(1)
        core.solve = real_solve
        loop.run_to_end(30.0)
        status = statuses(loop)[1]
        assert status.fallback_reason == 'invalid_plan' and status.source == 'plan'
        assert 'non-finite controls' in status.message
        assert_one_sane_setpoint_per_step(loop, 3)
    finally:
        loop.close()


def test_forecast_that_stops(context):
    loop = make_loop(context, hours=8, mpc={'input_wait_s': 0.2, 'max_plan_age_steps': 2})
    try:
        loop.run_steps(2)
        loop.forecaster.set_parameters([Parameter('enabled', value=False)])
        loop.run_steps(4, timeout_s=10.0)
        loop.forecaster.set_parameters([Parameter('enabled', value=True)])
        loop.run_to_end(30.0)
        history = loop.mpc_history()
        assert [s.source for _, s in history] == ['optimum', 'optimum', 'plan', 'plan',
                                                  'safe', 'safe', 'optimum', 'optimum']
        for _, status in history[2:6]:
            assert status.fallback_reason == 'inputs_missing'
            assert 'the forecast is stale' in status.message
            # each step waited input_wait_s for the forecast before its fallback (the wait the
            # controller measured; no bound on how long the machine took)
            waited = re.search(r'after ([0-9.]+) s', status.message)
            assert waited is not None and float(waited.group(1)) >= 0.2, status.message
        assert_one_sane_setpoint_per_step(loop, 8)
    finally:
        loop.close()


def test_an_older_forecast_is_shifted_while_it_is_recent_enough(context):
    loop = make_loop(context, hours=6, mpc={'input_wait_s': 0.2, 'max_forecast_age_s': 7200.0})
    try:
        loop.run_steps(2)
        loop.forecaster.set_parameters([Parameter('enabled', value=False)])
        loop.run_to_end(30.0)
        sources = [s.source for _, s in loop.mpc_history()]
        # Steps 2 and 3 plan on the step-1 forecast (1 and 2 h old), then it is too old.
        assert sources == ['optimum'] * 4 + ['plan', 'plan']
        assert_one_sane_setpoint_per_step(loop, 6)
    finally:
        loop.close()


def test_mpc_restarted_mid_run_picks_up_within_one_step(context):
    loop = make_loop(context, hours=6, emulator={'heartbeat_period_s': 0.2})
    try:
        loop.run_steps(3)
        first = loop.stop_mpc()
        loop.spin_for(0.5)  # lockstep: the emulator waits (heartbeats), nothing advances
        assert loop.steps_done == 3
        restarted = loop.start_mpc()
        # The latched forecast and the next heartbeat state suffice: the first setpoint is for
        # the step the emulator waits on (simulated time has not moved), no wall-time limit.
        loop.spin_until(lambda: len(restarted.history) > 0, 60.0, 'the first setpoint')
        assert loop.steps_done == 3
        loop.run_to_end(30.0)
        setpoint, status = restarted.history[0]
        assert stamp_to_ns(setpoint.header.stamp) == EPOCH_NS + 3 * STEP_NS
        assert status.success and not status.fallback
        assert len(first.history) == 3 and len(restarted.history) == 3
        assert loop.emulator.applied_sources == ['setpoint'] * 6
        assert_one_sane_setpoint_per_step(loop, 6)
    finally:
        loop.close()


def test_lockstep_without_mpc_times_out_with_a_clear_error(context):
    loop = make_loop(context, hours=4, emulator={'lockstep_timeout_s': 0.3,
                                                 'heartbeat_period_s': 0.1})
    try:
        loop.run_steps(1)
        loop.stop_mpc()
        loop.spin_until(lambda: loop.emulator.done, 5.0, 'the lockstep timeout')
        assert 'no setpoint for' in loop.emulator.failed
        assert 'lockstep_timeout_s = 0.3 s' in loop.emulator.failed
        assert loop.steps_done == 1
    finally:
        loop.close()


def test_lockstep_timeout_holds_the_last_setpoint_then_the_safe_default(context):
    loop = make_loop(context, hours=5, emulator={
        'lockstep_timeout_s': 0.2, 'on_lockstep_timeout': 'hold', 'hold_s': 3600.0,
        'safe_value': -100.0, 'heartbeat_period_s': 0.05})
    try:
        loop.run_steps(2)
        last = loop.stop_mpc().history[-1][0].control_values[0]
        loop.run_to_end(10.0)
        assert not loop.emulator.failed
        assert loop.emulator.applied_sources == ['setpoint', 'setpoint', 'held', 'safe', 'safe']
        applied = loop.emulator.applied_frame()['q'].tolist()
        assert applied[2] == pytest.approx(last) and applied[3:] == [-100.0, -100.0]
    finally:
        loop.close()


def test_free_running_emulator_holds_then_applies_the_safe_default(context):
    emulator = EmulatorNode(context=context, parameter_overrides=[
        Parameter('hours', value=4), Parameter('model', value='python'),
        Parameter('mode', value='free'), Parameter('speedup', value=3600.0 / 0.25),
        Parameter('clock_period_s', value=0.01), Parameter('ready_endpoints', value=['']),
        Parameter('hold_s', value=3600.0), Parameter('safe_value', value=250.0)])
    talker = rclpy.create_node('talker', context=context)
    publisher = talker.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)
    executor = SingleThreadedExecutor(context=context)
    for node in (emulator, talker):
        executor.add_node(node)
    try:
        deadline = time.monotonic() + 5.0
        while not emulator.started:
            assert time.monotonic() < deadline
            executor.spin_once(timeout_sec=0.01)
        publisher.publish(setpoint_msg(EPOCH_NS, 3600.0, {'q': 1234.0}, {'T': 21.0}))
        while not emulator.done:
            assert time.monotonic() < deadline + 5.0
            executor.spin_once(timeout_sec=0.01)
        assert emulator.applied_sources == ['setpoint', 'held', 'safe', 'safe']
        assert emulator.applied_frame()['q'].tolist() == [1234.0, 1234.0, 250.0, 250.0]
    finally:
        executor.shutdown()
        for node in (emulator, talker):
            node.destroy_node()


def test_emulator_starts_from_a_given_state_and_time(context):
    loop = make_loop(context, hours=8, emulator={'start_step': 5,
                                                 'initial_temperature_c': 23.0})
    try:
        loop.run_to_end(30.0)
        applied = loop.emulator.applied_frame()
        assert applied.index.tolist() == [5 * 3600.0, 6 * 3600.0, 7 * 3600.0]
        assert applied['T_start'].iloc[0] == pytest.approx(23.0 + KELVIN)
        assert step_stamps(loop)[0] == EPOCH_NS + 5 * STEP_NS
        core = run_closed_loop(MPC(R1C1Model(), horizon_steps=6),
                               Emulator(R1C1Model(), synthetic_scenario(hours=9),
                                        [23.0 + KELVIN], start_index=5), log_every=0)
        np.testing.assert_allclose(applied['T_end'], core.steps['T_end'], rtol=0, atol=1e-9)
    finally:
        loop.close()


def test_supervisor_never_plans_from_a_stale_plan():
    supervisor = SetpointSupervisor(((-2000.0, 2000.0),), 3600.0, (0.0,), max_plan_age_steps=3)

    class Result:
        success, message = True, 'ok'
        controls = np.array([[100.0], [200.0], [300.0]])
        states = np.array([[293.0], [294.0], [295.0], [296.0]])

    assert supervisor.review(0.0, Result()).source == 'optimum'
    # The plan has 3 intervals: step 3 is past its end even within max_plan_age_steps.
    assert [supervisor.fallback(k * 3600.0, 'budget', 'late').controls[0]
            for k in (1, 2, 3)] == [200.0, 300.0, 0.0]


def test_emulator_restart_resumes_the_fmu_plant_from_its_saved_state(context, tmp_path):
    """
    The emulator saves its FMU plant after every step; a restart at start_step resumes it.

    Every internal state, Qr included: the same trajectory as the uninterrupted run.
    """
    state_file = tmp_path / 'plant.bin'
    fmu = {'model': 'fmu-cs', 'plant_state_file': str(state_file)}
    whole = make_loop(context, hours=6, emulator=dict(fmu, plant_state_file=''))
    try:
        whole.run_to_end(60.0)
        reference = whole.emulator.fine_frame()
    finally:
        whole.close()
    first = make_loop(context, hours=6, emulator=fmu)
    try:
        first.run_steps(3)
        assert state_file.is_file()
        saved = state_file.read_bytes()
    finally:
        first.close()
    state_file.write_bytes(saved)  # the state after step 3, as a crash would leave it
    temperature = float(reference['x_T'].loc[3 * 3600.0]) - KELVIN
    second = make_loop(context, hours=6, emulator=dict(
        fmu, start_step=3, initial_temperature_c=temperature))
    try:
        second.run_to_end(60.0)
        resumed = second.emulator.fine_frame()
    finally:
        second.close()
    tail = reference.loc[3 * 3600.0:]
    # Qr (the integral of q, a state no message carries) goes on from where the plant was;
    # a plant started afresh from the temperature would restart it at 0.
    assert tail['y_Qr'].iloc[0] != 0.0
    assert resumed['y_Qr'].iloc[0] == pytest.approx(tail['y_Qr'].iloc[0], rel=1e-12)
    # (the restarted MPC solves from a cold start: its tiny night-time heat rates may differ
    # in the last digits, so the temperatures agree to well within the comfort scale)
    np.testing.assert_allclose(resumed['x_T'].to_numpy(), tail['x_T'].to_numpy(), atol=1e-4)
