"""mshoot_nodes without spinning: message conversions, scenarios and parameter helpers."""
from mshoot_core.actuation import Schedule
from mshoot_core.controller import controller_for
from mshoot_core.models.multizone import MultiZoneModel
from mshoot_core.models.r1c1 import R1C1Model
from mshoot_core.models.registry import control_interface
from mshoot_core.safety import check_setpoint, Decision, reorder
from mshoot_core.scenario import forecast_window, reference_scenario, synthetic_scenario
from mshoot_core.settings import MpcSettings
from mshoot_core.units import KELVIN
from mshoot_nodes import conversions as cv
from mshoot_nodes import sources
import numpy as np
import pandas as pd
import pytest


def test_stamps_are_exact_integer_nanoseconds():
    ns = 1522886400 * cv.NS_PER_S + 3600 * cv.NS_PER_S * 71
    assert cv.stamp_to_ns(cv.ns_to_stamp(ns)) == ns
    assert cv.stamp_to_ns(cv.ns_to_stamp(123_456_789_012)) == 123_456_789_012
    assert cv.seconds_to_ns(3600.0) == 3600 * cv.NS_PER_S
    step = 3600 * cv.NS_PER_S
    assert cv.floor_to_step(ns + step - 1, step) == ns
    assert cv.stamp_to_ns(cv.clock_msg(ns).clock) == ns


def test_zone_state_round_trip():
    for temperature_k in np.linspace(250.0, 320.0, 71):
        msg = cv.zone_state_msg(0, {'T': temperature_k}, {'T': temperature_k - KELVIN},
                                {'q': 10.0}, 'zone_a')
        assert msg.header.frame_id == 'zone_a'
        assert cv.zone_state_states(msg) == {'T': temperature_k}
        assert cv.named(msg.control_names, msg.control_values) == {'q': 10.0}
    two = cv.zone_state_msg(0, {'T_1': 294.0, 'T_0': 293.0})
    assert list(two.state_names) == ['T_1', 'T_0'] and list(two.output_names) == []
    # In the model's order, whatever the message's order.
    np.testing.assert_array_equal(reorder(two.state_names, two.state_values, ('T_0', 'T_1')),
                                  [293.0, 294.0])


def test_named_series_flatten_name_major():
    names, values = cv.flatten({'a': [1.0, 2.0, 3.0], 'b': [4.0, 5.0, 6.0]})
    assert names == ['a', 'b'] and values == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    back = cv.unflatten_series(names, values)
    assert list(back) == ['a', 'b'] and back['b'].tolist() == [4.0, 5.0, 6.0]
    with pytest.raises(ValueError, match='do not split'):
        cv.unflatten_series(names, values[:-1])


def test_forecast_round_trip_keeps_the_window():
    scenario = synthetic_scenario(hours=30)
    window = forecast_window(scenario, 5, 10)
    msg = cv.forecast_msg(7 * cv.NS_PER_S, 3600.0, window)
    assert cv.forecast_length(msg) == 11
    assert list(msg.series_names) == ['Tout', 'solrad', 'occ'] and len(msg.price_per_kwh) == 0
    frame = cv.forecast_to_frame(msg, assumed={'dpos': 0.0})
    assert list(frame.columns) == ['Tout', 'solrad', 'occ', 'comfort_min', 'comfort_max',
                                   'dpos']
    np.testing.assert_array_equal(frame.to_numpy(), window[frame.columns].to_numpy())
    np.testing.assert_array_equal(frame.index.to_numpy(), 7.0 + 3600.0 * np.arange(11))
    # Any named series, and a price.
    window = window.assign(dpos=np.linspace(0.0, 50.0, 11), price=np.linspace(0.1, 0.3, 11))
    msg = cv.forecast_msg(7 * cv.NS_PER_S, 3600.0, window, ('solrad', 'dpos'))
    series, rejection = cv.forecast_series(msg)
    assert rejection is None
    assert list(series) == ['solrad', 'dpos', 'comfort_min', 'comfort_max', 'price']
    for name in series:
        np.testing.assert_array_equal(series[name], window[name].to_numpy())
    msg.series_values = msg.series_values[:-1]
    series, rejection = cv.forecast_series(msg)
    assert series == {} and rejection.kind == 'length'
    with pytest.raises(ValueError, match='2 series of 11 samples need 22 values, got 21'):
        cv.forecast_to_frame(msg)


def _decision(controls, states, plan_controls, plan_states, source='optimum'):
    return Decision(0.0, np.asarray(controls, float), None if states is None
                    else np.asarray(states, float), np.asarray(plan_controls, float),
                    np.asarray(plan_states, float), source, source != 'optimum')


def test_setpoint_of_a_decision_names_every_control_and_zone():
    model = MultiZoneModel(2)
    interface = control_interface(model)
    assert interface.control_names == ('q_0', 'q_1')
    assert interface.temperature_names == ('T_0', 'T_1')
    plan_u = np.array([[100.0, -50.0], [110.0, -40.0], [120.0, -30.0]])
    plan_x = np.array([[294.0, 295.0], [294.5, 295.5], [295.0, 296.0]])
    setpoint = cv.decision_setpoint_msg(5, _decision(plan_u[0], plan_x[0], plan_u, plan_x),
                                        3600.0, interface, 21.0, 'house')
    assert setpoint.header.frame_id == 'house' and setpoint.step_s == 3600.0
    assert cv.setpoint_controls(setpoint) == {'q_0': 100.0, 'q_1': -50.0}
    assert list(setpoint.temperature_names) == ['T_0', 'T_1']
    np.testing.assert_allclose(setpoint.temperature_setpoints_c, plan_x[0] - KELVIN)
    # name-major: q_0 over the plan, then q_1
    assert list(setpoint.plan_controls) == [100.0, 110.0, 120.0, -50.0, -40.0, -30.0]
    controls, temperatures = cv.setpoint_plan(setpoint)
    np.testing.assert_array_equal(controls['q_1'], plan_u[:, 1])
    np.testing.assert_allclose(temperatures['T_1'], plan_x[:, 1] - KELVIN)
    assert check_setpoint(setpoint.step_s, setpoint.control_names, setpoint.control_values,
                          setpoint.temperature_names, setpoint.temperature_setpoints_c,
                          setpoint.plan_controls, setpoint.plan_temperatures_c,
                          expected_controls=('q_1', 'q_0')) is None
    safe = cv.decision_setpoint_msg(5, _decision([7.0, 8.0], None, np.empty((0, 2)),
                                                 np.empty((0, 2)), 'safe'),
                                    3600.0, interface, 21.5)
    assert list(safe.temperature_setpoints_c) == [21.5, 21.5]
    assert list(safe.plan_controls) == [] == list(safe.plan_temperatures_c)
    # bursts within the step: the schedule name-major, the first piece as the controls
    bursts = Schedule(np.array([0.0, 600.0, 2400.0]),
                      np.array([[0.0, -50.0], [300.0, -50.0], [300.0, 0.0]]))
    sent = cv.decision_setpoint_msg(5, _decision(plan_u[0], plan_x[0], plan_u, plan_x),
                                    3600.0, interface, 21.0, 'house', bursts)
    assert cv.setpoint_controls(sent) == {'q_0': 0.0, 'q_1': -50.0}
    assert list(sent.schedule_offsets_s) == [0.0, 600.0, 2400.0]
    assert list(sent.schedule_values) == [0.0, 300.0, 300.0, -50.0, -50.0, 0.0]
    assert list(sent.plan_controls) == list(setpoint.plan_controls)
    held = cv.decision_setpoint_msg(5, _decision(plan_u[0], plan_x[0], plan_u, plan_x),
                                    3600.0, interface, 21.0, 'house',
                                    Schedule(np.zeros(1), plan_u[:1]))
    assert list(held.schedule_offsets_s) == [] == list(held.schedule_values)


def test_setpoint_and_status_from_an_mpc_result():
    scenario = synthetic_scenario(hours=20)
    controller = controller_for(R1C1Model(), MpcSettings.from_flat(horizon_steps=6))
    result = controller.mpc.solve([293.15], 0.0, forecast_window(scenario, 0, 6))
    decision = controller.supervisor.review(0.0, result)
    setpoint = cv.decision_setpoint_msg(5, decision, 3600.0, controller.interface, 21.0)
    assert cv.setpoint_controls(setpoint) == {'q': result.controls[0, 0]}
    assert list(setpoint.temperature_setpoints_c) == [result.states[1, 0] - KELVIN]
    assert len(setpoint.plan_controls) == len(setpoint.plan_temperatures_c) == 6
    status = cv.status_msg(5, result)
    assert status.success == bool(result.success) and status.iterations == result.nit
    failed = cv.status_msg(5, None, fallback=True, message='time budget exceeded')
    assert failed.fallback and not failed.success and np.isnan(failed.objective)

    again = cv.setpoint_msg(5, 3600.0, {'q': 0.0}, {'T': 20.0})
    records = cv.mpc_records_frame([setpoint, again], [status, failed], epoch_ns=5)
    assert len(records) == 1  # the first of each stamp: what a lockstep emulator applied
    assert records.index[0] == 0.0
    assert records['q_setpoint'].iloc[0] == result.controls[0, 0]
    assert records['T_predicted_c'].iloc[0] == setpoint.temperature_setpoints_c[0]
    assert bool(records['success'].iloc[0]) == bool(result.success)
    assert not [c for c in records.columns if c.endswith(('_estimate', '_std'))]


def test_records_carry_the_estimated_state_like_the_core_steps():
    """A status with an estimated state: {state}_estimate and {state}_std columns [K]."""
    decision = _decision([100.0], [[294.0]], np.empty((0, 1)), np.empty((0, 1)))
    estimated = cv.decision_status_msg(5, decision, None, solve_time_s=0.1,
                                       state={'T': 294.2, 'Tw': 291.5},
                                       state_std=[0.05, np.nan])
    measured = cv.decision_status_msg(3600 * cv.NS_PER_S + 5, decision, None, solve_time_s=0.1,
                                      state={'T': 294.4, 'Tw': 291.6})
    assert list(estimated.state_std) == [0.05, -1.0] and list(measured.state_std) == []
    records = cv.mpc_records_frame([], [estimated, measured], epoch_ns=5)
    assert list(records.index) == [0.0, 3600.0]
    assert records['T_estimate'].iloc[0] == 294.2 and records['Tw_estimate'].iloc[0] == 291.5
    assert records['T_std'].iloc[0] == 0.05 and np.isnan(records['Tw_std'].iloc[0])
    # a state taken as measured is no estimate (as in the core's steps.csv)
    assert records[['T_estimate', 'Tw_estimate', 'T_std', 'Tw_std']].iloc[1].isna().all()
    # the steps.csv of a ROS run has them
    from mshoot_nodes.results import steps_frame
    applied = pd.DataFrame({'q': [100.0, 0.0], 'T_start': [294.0, 294.3],
                            'T_end': [294.3, 294.4]}, index=pd.Index([0.0, 3600.0],
                                                                     name='time_s'))
    steps = steps_frame(applied, records)
    assert steps['Tw_estimate'].iloc[0] == 291.5 and steps['T_std'].iloc[0] == 0.05


def test_scenarios_equal_the_core_reference_scenarios(ou44_csv):
    pd.testing.assert_frame_equal(sources.load_scenario('synthetic', '', 24),
                                  reference_scenario('synthetic', None, 24))
    pd.testing.assert_frame_equal(sources.load_scenario('ou44', str(ou44_csv), 72),
                                  reference_scenario('ou44', ou44_csv, 72))
    pd.testing.assert_frame_equal(sources.load_scenario(str(ou44_csv), '', 12),
                                  reference_scenario('ou44', ou44_csv, 12))


def test_simulated_time_starts_at_the_scenario_date():
    scenario = synthetic_scenario(hours=3)
    assert sources.start_ns(scenario) == 1522886400 * cv.NS_PER_S
    assert sources.start_ns(scenario, '2018-04-05T01:00:00+01:00') == 1522886400 * cv.NS_PER_S
    assert sources.check_start_time('yesterday-ish') is not None
    assert sources.check_model('python') is None
    assert sources.check_model('r1c1x2') is None
    assert 'not found' in sources.check_model('/nowhere/x.fmu')
    assert 'must be one of' in sources.check_model('matlab')
    assert 'must be one of' in sources.check_scenario('winter', '')
