"""
The rule node: BOPTEST's rule-based supervisory controller (and the baseline's clock) over ROS.

Answers every zone state on ``/zone/state`` with a setpoint on ``/mpc/setpoint`` stamped like
the state: the zone temperature setpoint of the pre-heating rule
(:class:`mshoot_core.boptest.rule.PreheatRule`: the comfort band's lower bound of zone
``band_zone`` over the coming step and ``lead_h`` after it, plus ``margin_k``) as the control
``control`` [degC] and as the zone's temperature setpoint; the emulator's card limits it. The
scenario parameters are the emulator's (a ``boptest:<period>[:<price>]`` scenario), so both
place the test period at the same ROS time.

``mode``: ``rule`` sends the rule's setpoint; ``baseline`` sends the band's lower bound (lead 0,
margin 0), which the baseline card (``boptest_baseline.yaml``: the setpoint without its
overwrite switch) never applies: in a baseline run the node only clocks the lockstep emulator,
the building's own controller is in charge. Every decision lives in core; the node converts.
"""
from __future__ import annotations

from typing import Any

from mshoot_core.boptest.rule import PreheatRule
from mshoot_core.boptest.testcase import TestCase
from mshoot_core.units import KELVIN, NS_PER_S
from mshoot_msgs.msg import Setpoint, ZoneState
from rclpy.node import Node

from mshoot_nodes import contract, sources
from mshoot_nodes.conversions import setpoint_msg, stamp_to_ns
from mshoot_nodes.params import declare, ParamSpec, values
from mshoot_nodes.startup import run_node

PARAMS = (
    ParamSpec('scenario', 'boptest:peak_heat_day', "the emulator's scenario: "
              "'boptest:<period>[:<price>]'", read_only=True),
    *sources.BOPTEST_SCENARIO_PARAMS,
    ParamSpec('step_s', 3600.0, 'control step [s]', low=1.0, high=86400.0, read_only=True),
    ParamSpec('mode', 'rule', "'rule': the pre-heating rule; 'baseline': the band's lower "
              'bound (the baseline card ignores it)', choices=('rule', 'baseline'),
              read_only=True),
    ParamSpec('lead_h', 0.0, 'rule: how far past the coming step the band is looked at [h]',
              low=0.0, high=48.0, read_only=True),
    ParamSpec('margin_k', 0.0, "rule: added to the band's lower bound [K]", low=0.0, high=5.0,
              read_only=True),
    ParamSpec('control', 'TSet', "the emulator card's setpoint control [degC]",
              read_only=True),
    ParamSpec('zone_temperature', 'T', 'name of the zone temperature setpoint sent',
              read_only=True),
    ParamSpec('zone', 'zone', 'zone name (header.frame_id)', read_only=True),
    ParamSpec('band_zone', '', "the test case's zone whose comfort band the rule follows "
              "(LowerSetp[<zone>]; '': the first zone of its kpis.json)", read_only=True),
)


class RuleNode(Node):
    """Answers zone states with the rule's setpoints (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('rule', **kwargs)
        declare(self, PARAMS, [sources.check_boptest_parameters])
        p = self.params = values(self, PARAMS)
        scenario = sources.load_scenario(p['scenario'], p['data'], p['hours'])
        self.epoch_ns = sources.start_ns(scenario, p['start_time'])
        self.start_fmu_s = float(scenario.attrs['boptest']['start_s'])
        case = TestCase.load(p['data'] or None)
        rule = p['mode'] == 'rule'
        self.band_zone = p['band_zone'] or case.zones[0]
        self.rule = PreheatRule(case, {}, p['lead_h'] if rule else 0.0,
                                p['margin_k'] if rule else 0.0, p['step_s'])
        self.answered = 0
        self._publisher = self.create_publisher(Setpoint, contract.SETPOINT, contract.DATA_QOS)
        self._subscription = self.create_subscription(ZoneState, contract.ZONE_STATE,
                                                      self._on_state, contract.DATA_QOS)
        self.get_logger().info(
            f"{p['mode']} on {p['scenario']}: setpoint = band lower bound over the step and "
            f'{self.rule.lead_h:g} h after + {self.rule.margin_k:g} K')

    def setpoint_c(self, stamp_ns: int) -> float:
        """Return the setpoint [degC] of the step starting at a ROS stamp [ns]."""
        fmu_s = self.start_fmu_s + (stamp_ns - self.epoch_ns) / NS_PER_S
        return self.rule.setpoint(fmu_s, self.band_zone) - KELVIN

    def _on_state(self, msg: ZoneState) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        value = self.setpoint_c(stamp)
        p = self.params
        self._publisher.publish(setpoint_msg(stamp, p['step_s'], {p['control']: value},
                                             {p['zone_temperature']: value}, zone=p['zone']))
        self.answered += 1


def main(args: list[str] | None = None) -> None:
    """``ros2 run mshoot_nodes rule``: answer zone states until Ctrl-C."""
    run_node(RuleNode, 'rule', args)


if __name__ == '__main__':
    main()
