"""
The one period loop (``mshoot_core.period_loop.run_steps``): its schedule, order and budget.

The loops that call it (``run_closed_loop``, ``run_span``, the excitations, the recorded
warm-up, the weather) are tested with their plants elsewhere; here the loop alone, with
callbacks that write down what they are given.
"""
from mshoot_core.period_loop import run_steps, step_count
import pytest


def test_steps_observe_decide_apply_in_order_the_last_one_ending_at_the_end():
    calls = []
    run = run_steps(100.0, 100.0 + 2.5 * 3600.0, 3600.0,
                    lambda t, end, d: calls.append(('apply', t, end, d)),
                    decide=lambda t: calls.append(('decide', t)) or f'u{t:g}',
                    observe=lambda t: calls.append(('observe', t)))
    assert calls == [('observe', 100.0), ('decide', 100.0), ('apply', 100.0, 3700.0, 'u100'),
                     ('observe', 3700.0), ('decide', 3700.0), ('apply', 3700.0, 7300.0, 'u3700'),
                     ('observe', 7300.0), ('decide', 7300.0), ('apply', 7300.0, 9100.0, 'u7300')]
    assert len(run.step_wall_s) == 3 and all(w >= 0.0 for w in run.step_wall_s)
    assert run.wall_s >= sum(run.step_wall_s)


def test_without_a_decision_the_plant_keeps_its_own_control_and_no_wall_time_is_kept():
    applied = []
    run = run_steps(0.0, 7200.0, 3600.0, lambda t, end, d: applied.append((t, end, d)))
    assert applied == [(0.0, 3600.0, None), (3600.0, 7200.0, None)]
    assert run.step_wall_s == []
    assert run_steps(5.0, 5.0, 60.0, lambda *a: applied.append(a)).step_wall_s == []
    assert len(applied) == 2  # an empty span: no step


def test_a_spent_budget_stops_before_the_next_step_but_never_before_the_first():
    applied = []
    run = run_steps(0.0, 10 * 60.0, 60.0, lambda t, end, d: applied.append(t),
                    decide=lambda t: None, budget_s=0.0)
    assert applied == [0.0] and len(run.step_wall_s) == 1


def test_step_count_and_bad_arguments():
    assert step_count(0.0, 86400.0, 3600.0) == 24
    assert step_count(0.0, 86400.0 + 1e-7, 3600.0) == 24  # within the time tolerance
    assert step_count(0.0, 86401.0, 3600.0) == 25
    assert step_count(10.0, 0.0, 3600.0) == 0
    with pytest.raises(ValueError, match='positive control step'):
        run_steps(0.0, 1.0, 0.0, lambda *a: None)
    with pytest.raises(ValueError, match='start <= end'):
        run_steps(1.0, 0.0, 1.0, lambda *a: None)


def test_the_closed_loop_result_is_a_loop_run_with_each_decision_timed():
    from mshoot_core.closed_loop import run_closed_loop
    from mshoot_core.emulation import Emulator
    from mshoot_core.models.r1c1 import R1C1Model
    from mshoot_core.mpc import MPC
    from mshoot_core.period_loop import LoopRun
    from mshoot_core.scenario import synthetic_scenario
    result = run_closed_loop(MPC(R1C1Model(), horizon_steps=3),
                             Emulator(R1C1Model(), synthetic_scenario(hours=4), [293.15]),
                             log_every=0)
    assert isinstance(result, LoopRun)
    assert len(result.step_wall_s) == len(result.steps) == 3  # 4 rows: 3 steps
    # a decision's wall time holds its solve
    for wall, solve in zip(result.step_wall_s, result.steps['solve_time_s']):
        assert wall >= solve - 1e-6
