"""
The forecaster node: disturbance, comfort-band and price forecasts over the MPC horizon.

On every control step of simulated time (a sim-time timer) it publishes on
``/forecast`` (latched: reliable, transient local, depth 1) the scenario rows
of the step and the ``horizon_steps`` that follow, from
:func:`mshoot_core.scenario.forecast_window`, so a ROS run and the core-only
loop see the same forecasts: the scenario columns named by ``series`` (by
default Tout, solrad, occ: what the control model needs besides the
ventilation it assumes) as named series, the comfort band and, with
``send_price``, an energy price series (``price_per_kwh``: flat or by hour of
the day; a scenario with its own ``price`` column, e.g. a BOPTEST test period, sends that
one instead). By default the forecasts are perfect; ``temperature_uncertainty``,
``solar_uncertainty`` and ``seed`` give Tout and solrad BOPTEST's forecast errors
(:class:`mshoot_core.scenario_forecasts.ScenarioForecasts`: for a BOPTEST scenario, the test case's
``TDryBul`` and ``HGloHor`` at the step's FMU time, as BOPTEST serves them).
With ``model`` a control card that has a ``testcase_forecast`` section and a BOPTEST scenario,
every forecast is that card's :class:`mshoot_core.boptest.forecasts.TestCaseForecasts` frame
instead: interval means of the series the card names, the tightest comfort band per zone (the
first zone's as the band, every zone's as ``comfort_min_<zone>``/``comfort_max_<zone>`` when
there are several) and the price scenario's price, with the errors on the temperature and
solar points before the means.

Health on ``/diagnostics`` (``mshoot/forecaster``): forecasts published, the
last forecast's step, whether forecasts are paused (WARN); with use_sim_time the
clock as a peer (``mshoot/forecaster/peer/clock``: STALE, or ERROR for a second
writer of ``/clock``, :mod:`mshoot_nodes.peers`).
"""
from __future__ import annotations

import pathlib
from typing import Any

from mshoot_core.forecast import horizon_problem
from mshoot_core.peers import Peer
from mshoot_core.safety import COMFORT_SERIES, PRICE_SERIES
from mshoot_core.scenario_forecasts import ScenarioForecasts
from mshoot_core.settings import fields_of, ForecastErrorSettings
from mshoot_core.units import NS_PER_S
from mshoot_msgs.msg import Forecast
import numpy as np
import pandas as pd
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg

from mshoot_nodes import contract, sources
from mshoot_nodes.conversions import (floor_to_step, FORECAST_DISTURBANCES, forecast_msg,
                                      seconds_to_ns)
from mshoot_nodes.diagnostics import DiagnosticsPublisher, Level, Report
from mshoot_nodes.params import declare, ParamSpec, values
from mshoot_nodes.peers import PeerMonitor
from mshoot_nodes.startup import run_node

PARAMS = (
    ParamSpec('scenario', 'synthetic', "the scenario: 'synthetic', 'ou44', "
              "'boptest:<period>[:<price>]' or a path to a CSV in the OU44 format (the same as "
              'the emulator)', read_only=True),
    ParamSpec('data', '', "path of the OU44 measurements.csv for scenario 'ou44', of the "
              "test case folder for a BOPTEST scenario ('' = the default shared data folder)",
              read_only=True),
    ParamSpec('hours', 72, 'control steps of the scenario [-]', low=1, high=1_000_000,
              read_only=True),
    ParamSpec('start_time', '', 'ROS time of the first scenario row, ISO date-time read as UTC '
              "('' = the scenario's own start date)", read_only=True),
    ParamSpec('step_s', 3600.0, 'control step and forecast sample spacing [s]', low=1.0,
              high=86400.0, read_only=True),
    ParamSpec('horizon_steps', 10, 'forecast horizon N: every forecast holds N+1 samples [-]',
              low=1, high=10_000),
    *(ParamSpec.from_setting(f) for f in fields_of(ForecastErrorSettings)),
    ParamSpec('model', '', "the control model's card ('' = none): with a BOPTEST scenario and a "
              "card that has a testcase_forecast section, the forecasts are that section's "
              'interval means of the test case data (its series, the tightest band per zone, '
              "the scenario's price; series is then not used)", read_only=True),
    ParamSpec('history_steps', 0, "with model's test case source: the first forecast reaches "
              'back this many steps before its stamp (its history_steps: the inputs over a '
              "warm-up a first zone state's history is observed with) [-]", low=0,
              high=10_000, read_only=True),
    ParamSpec('series', list(FORECAST_DISTURBANCES), 'scenario columns sent as named '
              "disturbance series (the control model's disturbances; those it assumes may be "
              'left out)', read_only=True),
    ParamSpec('send_price', False, 'also send an energy price series (price_per_kwh)'),
    ParamSpec('price_per_kwh', [0.3], 'energy price [currency/kWh]: one value (flat) or 24 '
              '(by hour of the day, scenario time)'),
    ParamSpec('enabled', True, 'publish forecasts (false: pause them, e.g. to exercise the '
              "MPC's fallback when the forecast stops)"),
    ParamSpec('zone', 'zone', 'zone name (header.frame_id)', read_only=True),
    ParamSpec('clock_writer', 'emulator', 'with use_sim_time: name of the one node expected to '
              'publish /clock (any other is reported as an intruder on /diagnostics)',
              read_only=True),
    ParamSpec('peer_timeout_s', 30.0, 'with use_sim_time: wall time without /clock after which '
              'the clock is reported STALE on /diagnostics [s]', low=0.1, high=1e6,
              read_only=True),
)


def _check_sources(v: dict[str, Any]) -> str | None:
    if 'scenario' in v and (reason := sources.check_scenario(v['scenario'], v.get('data', ''))):
        return reason
    if 'start_time' in v and (reason := sources.check_start_time(v['start_time'])):
        return reason
    if 'series' in v:
        names = list(v['series'])
        if not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(names):
            return f'series must be distinct scenario column names, got {names}'
        clash = [n for n in names if n in (*COMFORT_SERIES, PRICE_SERIES)]
        if clash:
            return f'series must not name {clash}: the comfort band and the price are sent anyway'
    if v.get('history_steps') and not v.get('model'):
        return 'history_steps needs model (a card with a testcase_forecast section)'
    if 'model' in v and v['model'] and not pathlib.Path(v['model']).is_file():
        return f"model must be '' or the path of a card, got {v['model']!r} (no such file)"
    if 'horizon_steps' in v and (reason := horizon_problem(
            [v.get('temperature_uncertainty', 'none'), v.get('solar_uncertainty', 'none')],
            # a test case source's last row is a mean over one more step
            (v['horizon_steps'] + bool(v.get('model'))) * v.get('step_s', 3600.0))):
        return f'horizon_steps x step_s: {reason}'
    if 'price_per_kwh' in v:
        prices = list(v['price_per_kwh'])
        if len(prices) not in (1, 24) or not all(np.isfinite(prices)):
            return (f'price_per_kwh must be 1 or 24 finite prices [currency/kWh], got '
                    f'{prices}')
    return None


class ForecasterNode(Node):
    """Publishes the horizon forecast every control step (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('forecaster', **kwargs)
        declare(self, PARAMS, [_check_sources])
        self.params = values(self, PARAMS)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        p = self.params
        self.scenario = sources.load_scenario(p['scenario'], p['data'], p['hours'])
        #: The step forecasts, with the errors of ``temperature_uncertainty``,
        #: ``solar_uncertainty`` and ``seed`` (read-only: fixed for the run).
        self.forecasts = ScenarioForecasts(self.scenario, ForecastErrorSettings(
            **{f.name: p[f.name] for f in fields_of(ForecastErrorSettings)}), p['model'] or None)
        #: The disturbance series sent: the card section's, else ``series``.
        self.series = list(self.forecasts.series or p['series'])
        missing = [c for c in self.series if c not in self.scenario.columns]
        if self.forecasts.series is None and missing:
            raise ValueError(f'series {missing} are not columns of the {p["scenario"]} '
                             f'scenario {list(self.scenario.columns)}')
        self.forecasts.check_horizon(p['horizon_steps'])
        self.epoch_ns = sources.start_ns(self.scenario, p['start_time'])
        self.step_ns = seconds_to_ns(p['step_s'])
        self.last_index: int | None = None
        self.published = 0
        self._publisher = self.create_publisher(Forecast, contract.FORECAST, contract.LATCHED_QOS)
        # Fires on whole simulated steps when use_sim_time is true (never before a /clock).
        self._timer = self.create_timer(p['step_s'], self._on_step)
        self.peers = None
        if self.get_parameter('use_sim_time').value:
            self.peers = PeerMonitor(self, [Peer('clock', contract.CLOCK, p['clock_writer'],
                                                 p['peer_timeout_s'])])
            self.create_subscription(ClockMsg, contract.CLOCK,
                                     lambda _: self.peers.heard('clock'), contract.CLOCK_QOS)
        self.diagnostics = DiagnosticsPublisher(self, self.health, hardware_id=p['zone'],
                                                peers=self.peers)
        self.get_logger().info(
            f"{p['scenario']} scenario from {pd.Timestamp(self.epoch_ns, tz='UTC').isoformat()}: "
            f"{p['horizon_steps'] + 1}-sample forecasts of {self.series} every "
            f"{p['step_s']:.0f} s, errors: temperature {p['temperature_uncertainty']}, solar "
            f"{p['solar_uncertainty']} (seed {p['seed']})"
            + (f", interval means of {p['model']}'s test case section"
               if self.forecasts.testcase is not None else '')
            + (f", price {p['price_per_kwh']} per kWh" if p['send_price'] else ''))

    def _on_parameters_set(self, params: list) -> None:
        self.params = values(self, PARAMS)
        names = ', '.join(f'{p.name} = {p.value}' for p in params)
        self.get_logger().info(f'parameters changed: {names} (from the next step)')
        if any(p.name == 'enabled' and p.value for p in params):
            self._on_step()  # resumed: the current step's forecast at once

    def _on_step(self) -> None:
        now = self.get_clock().now().nanoseconds
        step = floor_to_step(now - self.epoch_ns, self.step_ns)
        index = step // self.step_ns
        last_step = len(self.scenario) - 2  # the last row only ends the last control step
        if index == self.last_index or (self.last_index is not None
                                        and self.last_index > last_step):
            return
        if 0 <= index <= last_step:
            if not self.params['enabled']:
                self.get_logger().warning(f'forecasts paused (enabled = false): none for step '
                                          f'{index}', throttle_duration_sec=30.0)
                return
            self.publish_forecast(int(index))
        elif index > last_step and self.last_index is not None:
            self.get_logger().info('scenario over: no more forecasts')
            self.last_index = int(index)
        elif now > 0:
            self.get_logger().warning(
                f'clock at {now / NS_PER_S:.0f} s is outside the scenario '
                f'({self.epoch_ns / NS_PER_S:.0f} s + {last_step + 1} steps); is use_sim_time '
                'set?', throttle_duration_sec=30.0)

    def health(self) -> Report:
        """Return the forecaster's status for /diagnostics."""
        p = self.params
        last = self.last_index
        values_ = {'forecasts_published': self.published, 'enabled': p['enabled'],
                   'temperature_uncertainty': p['temperature_uncertainty'],
                   'solar_uncertainty': p['solar_uncertainty'], 'seed': p['seed'],
                   'horizon_steps': p['horizon_steps'],
                   'last_step': last if last is not None else 'none',
                   'scenario_steps': len(self.scenario) - 1}
        if last is not None:
            values_['last_stamp'] = pd.Timestamp(self.epoch_ns + last * self.step_ns,
                                                 tz='UTC').isoformat()
        if not p['enabled']:
            return Report(Level.WARN, 'forecasts paused (enabled = false)', values_)
        if last is None:
            return Report(Level.OK, 'waiting for the first step of the scenario (/clock)',
                          values_)
        if last > len(self.scenario) - 2:
            return Report(Level.OK, f'scenario over: {self.published} forecasts', values_)
        return Report(Level.OK, f'{self.published} forecasts, the last for step {last}',
                      values_)

    def prices(self, times_s: np.ndarray) -> np.ndarray:
        """
        Return the energy price [currency/kWh] at scenario times [s].

        ``price_per_kwh``: flat, or by hour of the day from the scenario's start time.
        """
        prices = np.asarray(self.params['price_per_kwh'], dtype=float)
        if prices.size == 1:
            return np.full(len(times_s), prices[0])
        start = pd.Timestamp(self.scenario.attrs.get('start') or sources.DEFAULT_START)
        seconds = start.hour * 3600 + start.minute * 60 + start.second
        hours = ((seconds + np.asarray(times_s, dtype=float)) // 3600).astype(int) % 24
        return prices[hours]

    def publish_forecast(self, index: int) -> Forecast:
        """Publish the forecast starting at scenario row ``index``."""
        p = self.params
        window = self.forecasts.window(index, p['horizon_steps'])
        if p['send_price'] and PRICE_SERIES not in window.columns:
            window = window.copy()
            window[PRICE_SERIES] = self.prices(window.index.to_numpy(dtype=float))
        history = p['history_steps'] if self.last_index is None else 0
        if history:  # the first forecast: the warm-up's inputs before it
            window = pd.concat([self.forecasts.history(index, history), window])
        stamp = self.epoch_ns + index * self.step_ns
        msg = forecast_msg(stamp, p['step_s'], window, self.series, p['zone'])
        msg.history_steps = history
        self._publisher.publish(msg)
        self.last_index = index
        self.published += 1
        self.get_logger().debug(f'forecast for step {index} ({stamp / NS_PER_S:.0f} s)')
        return msg


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes forecaster`` (set use_sim_time:=true against the emulator)."""
    run_node(ForecasterNode, 'forecaster', args)


if __name__ == '__main__':
    main()
