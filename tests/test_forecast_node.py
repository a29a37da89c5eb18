"""The forecaster node serves BOPTEST's forecast uncertainty: what it publishes is the core's."""
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.forecast import ForecastSource
from mshoot_core.settings import ForecastErrorSettings
from mshoot_core.units import KELVIN
import numpy as np
import pytest

from conftest import spin_until

pytestmark = pytest.mark.ros


def test_the_published_forecast_is_the_core_sources(boptest_case: TestCase, context,
                                                    tmp_path) -> None:
    """Over DDS and in the bag: Tout and solrad are the test case source's at that FMU time."""
    from mshoot_msgs.msg import Forecast
    from mshoot_nodes import contract
    from mshoot_nodes.bags import read_messages
    from mshoot_nodes.recorder_node import RecorderNode
    from mshoot_nodes.conversions import forecast_series
    from mshoot_nodes.forecaster_node import ForecasterNode
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    node = ForecasterNode(context=context, parameter_overrides=[
        Parameter('scenario', value='boptest:typical_heat_day:dynamic'),
        Parameter('hours', value=48), Parameter('horizon_steps', value=24),
        Parameter('temperature_uncertainty', value='high'),
        Parameter('solar_uncertainty', value='high'), Parameter('seed', value=7)])
    listener = Node('forecast_listener', context=context)
    received: list = []
    listener.create_subscription(Forecast, contract.FORECAST, received.append,
                                 contract.LATCHED_QOS)
    bag = tmp_path / 'bag'
    recorder = RecorderNode(context=context, parameter_overrides=[
        Parameter('bag_path', value=str(bag)), Parameter('topics', value=[contract.FORECAST])])
    executor = SingleThreadedExecutor(context=context)
    for each in (node, listener, recorder):
        executor.add_node(each)
    try:
        spin_until(executor, lambda: node.count_subscribers(contract.FORECAST) >= 2,
                   what='the listener and the recorder')
        step = 5 + 13  # a step in the day: the sun is up within the horizon
        node.publish_forecast(step)
        spin_until(executor, lambda: len(received) == 1
                   and recorder.counts.get(contract.FORECAST) == 1, what='the forecast')
    finally:
        executor.shutdown()
        recorder.destroy_node()  # closes the bag
        listener.destroy_node()
        node.destroy_node()
    series, rejection = forecast_series(received[0])
    assert rejection is None
    bagged = read_messages(bag, contract.FORECAST)
    assert len(bagged) == 1
    names = list(bagged[0].series_names)
    np.testing.assert_array_equal(np.asarray(bagged[0].series_values).reshape(len(names), -1),
                                  np.array([series[n] for n in names]))
    _, start, _ = boptest_case.test_period('typical_heat_day')
    errors = ForecastErrorSettings(temperature_uncertainty='high', solar_uncertainty='high',
                                   seed=7)
    core = ForecastSource.from_test_case(boptest_case, errors).forecast(
        start + step * 3600.0, 24 * 3600.0, 3600.0, ['TDryBul', 'HGloHor'])
    np.testing.assert_allclose(series['Tout'], core['TDryBul'] - KELVIN, rtol=0, atol=1e-9)
    np.testing.assert_allclose(series['solrad'], core['HGloHor'], rtol=0, atol=1e-9)
    truth = boptest_case.lookup_frame(['TDryBul', 'HGloHor', 'Occupancy[1]'], core['time'])
    assert np.abs(series['Tout'] - (truth['TDryBul'].to_numpy() - KELVIN)).max() > 0.1
    assert np.abs(series['solrad'] - truth['HGloHor'].to_numpy()).max() > 1.0
    np.testing.assert_array_equal(series['occ'], truth['Occupancy[1]'])  # exact, as before


def test_with_a_control_card_the_forecast_is_its_test_case_source(
        boptest_case: TestCase, context) -> None:
    """The card's interval means, band and price at the step's FMU time, with the errors."""
    from mshoot_core.boptest.forecasts import ForecastSpec, TestCaseForecasts
    from mshoot_core.models.card import builtin_card
    from mshoot_nodes.conversions import forecast_series
    from mshoot_nodes.forecaster_node import ForecasterNode
    from rclpy.parameter import Parameter
    card = builtin_card('boptest_house')
    node = ForecasterNode(context=context, parameter_overrides=[
        Parameter('scenario', value='boptest:peak_heat_day:dynamic'),
        Parameter('hours', value=48), Parameter('horizon_steps', value=36),
        Parameter('model', value=str(card)), Parameter('temperature_uncertainty', value='high'),
        Parameter('solar_uncertainty', value='medium'), Parameter('seed', value=5)])
    try:
        msg = node.publish_forecast(7)
    finally:
        node.destroy_node()
    series, rejection = forecast_series(msg)
    assert rejection is None
    assert list(msg.series_names) == ['Tout', 'solar', 'gains']
    _, start, _ = boptest_case.test_period('peak_heat_day')
    errors = ForecastErrorSettings(temperature_uncertainty='high', solar_uncertainty='medium',
                                   seed=5)
    core = TestCaseForecasts(boptest_case, ForecastSpec.from_card(card), 'dynamic',
                             errors).frame(start + 7 * 3600.0, 36, 3600.0)
    for name in ('Tout', 'solar', 'gains', 'price', 'comfort_min', 'comfort_max'):
        np.testing.assert_allclose(series[name], core[name], rtol=0, atol=1e-9)
    exact = TestCaseForecasts(boptest_case, ForecastSpec.from_card(card), 'dynamic').frame(
        start + 7 * 3600.0, 36, 3600.0)
    assert np.abs(series['Tout'] - exact['Tout']).max() > 0.1
    np.testing.assert_array_equal(series['gains'], exact['gains'])


def test_a_model_that_is_not_a_card_file_is_refused() -> None:
    from mshoot_nodes.forecaster_node import _check_sources
    assert 'no such file' in _check_sources({'model': '/nonexistent/card.yaml'})
    assert _check_sources({'model': ''}) is None
    # with a card the last row is a mean over one more step: 48 steps of 1 h exceed 48 h
    assert '48 h' in _check_sources({'model': __file__, 'horizon_steps': 48,
                                     'temperature_uncertainty': 'high'})
    assert _check_sources({'model': '', 'horizon_steps': 48,
                           'temperature_uncertainty': 'high'}) is None


def test_the_first_forecast_reaches_back_over_the_warm_up(boptest_case: TestCase,
                                                          context) -> None:
    """
    history_steps: the first forecast holds the warm-up's steps before its stamp, then no more.

    Each history row as the forecast of its own step has it first (the card's interval means);
    the rows from the stamp on are the step's forecast as without a history.
    """
    import pytest
    from mshoot_core.boptest.forecasts import ForecastSpec, TestCaseForecasts
    from mshoot_core.models.card import builtin_card
    from mshoot_nodes.conversions import forecast_series, stamp_to_ns
    from mshoot_nodes.forecaster_node import ForecasterNode
    from rclpy.parameter import Parameter
    card = builtin_card('boptest_house')
    common = [Parameter('scenario', value='boptest:peak_heat_day:dynamic'),
              Parameter('hours', value=24), Parameter('horizon_steps', value=6),
              Parameter('model', value=str(card))]
    node = ForecasterNode(context=context, parameter_overrides=[
        *common, Parameter('history_steps', value=5)])
    try:
        first, second = node.publish_forecast(0), node.publish_forecast(1)
    finally:
        node.destroy_node()
    assert (first.history_steps, second.history_steps) == (5, 0)
    assert stamp_to_ns(second.header.stamp) - stamp_to_ns(first.header.stamp) == 3600 * 10**9
    series, rejection = forecast_series(first)
    assert rejection is None and len(series['Tout']) == 5 + 7
    _, start, _ = boptest_case.test_period('peak_heat_day')
    source = TestCaseForecasts(boptest_case, ForecastSpec.from_card(card), 'dynamic')
    for k in range(5):
        row = source.frame(start - (5 - k) * 3600.0, 0, 3600.0)
        for name in ('Tout', 'solar', 'gains', 'price'):
            assert series[name][k] == pytest.approx(row[name].iloc[0], rel=0, abs=1e-12)
    now = source.frame(start, 6, 3600.0)
    for name in ('Tout', 'solar', 'gains', 'price', 'comfort_min', 'comfort_max'):
        np.testing.assert_allclose(series[name][5:], now[name], rtol=0, atol=1e-12)
    with pytest.raises(Exception, match='history_steps needs model'):
        ForecasterNode(context=context, parameter_overrides=[
            common[0], Parameter('history_steps', value=5)])
