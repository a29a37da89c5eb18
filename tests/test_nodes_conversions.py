"""mshoot_nodes without spinning: message conversions, scenarios and parameter helpers."""
from mshoot_core.closed_loop import forecast_window
from mshoot_core.models.r1c1 import KELVIN, R1C1Model
from mshoot_core.mpc import MPC
from mshoot_core.scenario import reference_scenario, synthetic_scenario
from mshoot_nodes import conversions as cv
from mshoot_nodes import sources
from mshoot_nodes.forecaster_node import forecast_errors
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
        msg = cv.zone_state_msg(0, temperature_k, 10.0, 'zone_a')
        assert msg.header.frame_id == 'zone_a'
        assert abs(cv.zone_state_to_x(msg)[0] - temperature_k) < 1e-12


def test_forecast_round_trip_keeps_the_window():
    scenario = synthetic_scenario(hours=30)
    window = forecast_window(scenario, 5, 10)
    msg = cv.forecast_msg(7 * cv.NS_PER_S, 3600.0, window)
    assert cv.forecast_length(msg) == 11
    frame = cv.forecast_to_frame(msg, dpos=0.0)
    assert list(frame.columns) == ['solrad', 'Tout', 'occ', 'dpos', 'comfort_min',
                                   'comfort_max']
    np.testing.assert_array_equal(frame.to_numpy(), window[frame.columns].to_numpy())
    np.testing.assert_array_equal(frame.index.to_numpy(), 7.0 + 3600.0 * np.arange(11))
    msg.occupancy = msg.occupancy[:-1]
    with pytest.raises(ValueError, match='differ in length'):
        cv.forecast_length(msg)


def test_setpoint_and_status_from_an_mpc_result():
    scenario = synthetic_scenario(hours=20)
    mpc = MPC(R1C1Model(), horizon_steps=6)
    result = mpc.solve([293.15], 0.0, forecast_window(scenario, 0, 6))
    setpoint = cv.setpoint_msg(5, result, 3600.0)
    assert setpoint.heat_rate_w == result.controls[0, 0]
    assert setpoint.temperature_setpoint_c == result.states[1, 0] - KELVIN
    assert len(setpoint.plan_heat_rate_w) == len(setpoint.plan_temperature_c) == 6
    np.testing.assert_array_equal(cv.setpoint_to_controls(setpoint), result.controls[0])
    status = cv.status_msg(5, result)
    assert status.success == bool(result.success) and status.iterations == result.nit
    failed = cv.status_msg(5, None, fallback=True, message='time budget exceeded')
    assert failed.fallback and not failed.success and np.isnan(failed.objective)

    again = cv.fallback_setpoint_msg(5, 0.0, 20.0, 3600.0)
    records = cv.mpc_records_frame([setpoint, again], [status, failed], epoch_ns=5)
    assert len(records) == 1  # the first of each stamp: what a lockstep emulator applied
    assert records.index[0] == 0.0
    assert records['q_setpoint'].iloc[0] == setpoint.heat_rate_w
    assert bool(records['success'].iloc[0]) == bool(result.success)


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
    assert 'not found' in sources.check_model('/nowhere/x.fmu')
    assert 'must be one of' in sources.check_model('matlab')
    assert 'must be one of' in sources.check_scenario('winter', '')


def test_forecast_errors_are_seeded_and_grow_with_lead_time():
    tout, solrad = forecast_errors(3, 11, 0.5, 20.0, seed=1)
    assert tout[0] == solrad[0] == 0.0
    again = forecast_errors(3, 11, 0.5, 20.0, seed=1)
    np.testing.assert_array_equal(tout, again[0])
    other = forecast_errors(4, 11, 0.5, 20.0, seed=1)
    assert not np.array_equal(tout, other[0])
    many = np.array([forecast_errors(k, 11, 0.5, 20.0, seed=0)[0] for k in range(400)])
    spread = many.std(axis=0)
    assert spread[10] > 2 * spread[1] > 0
