"""Bags: sqlite3 storage, non-contract topics, QoS metadata and the message definitions."""
import sqlite3

from mshoot_msgs.msg import ZoneState
from mshoot_nodes import contract
from mshoot_nodes.bags import (bag_metadata, qos_from_rosbags, qos_to_rosbags, read_bag,
                               read_messages, typestore)
from mshoot_nodes.bringup import run_in_process
from mshoot_nodes.conversions import stamp_to_ns, zone_state_msg
from mshoot_nodes.recorder_node import RecorderNode
from mshoot_nodes.replayer_node import ReplayerNode
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from conftest import spin_until

pytestmark = pytest.mark.ros


def test_custom_types_come_from_the_installed_msg_files():
    store = typestore()
    for name in ('ZoneState', 'Disturbances', 'Forecast', 'Setpoint', 'MpcStatus'):
        assert f'mshoot_msgs/msg/{name}' in store.types
    # rosbags serialises like rclpy: the definitions match the generated classes.
    from rclpy.serialization import serialize_message
    msg = zone_state_msg(7 * 10 ** 9, {'T_0': 294.0, 'T_1': 295.5}, {'Tc_0': 20.85},
                         {'q_0': 12.5, 'q_1': -3.0}, 'zone_a')
    # a first state with its history (rclpy's serialize_message pads some layouts of empty
    # float64[] fields beyond the data, which rosbags refuses; messages on the wire and in
    # the recorded bags below have no such padding)
    msg.history_offsets_s = [-3600.0, 0.0]
    msg.history_state_values = [293.0, 294.0, 295.0, 295.5]
    msg.history_output_names = ['Tc_0']
    msg.history_output_values = [float('nan'), 20.8]
    decoded = store.deserialize_cdr(serialize_message(msg), 'mshoot_msgs/msg/ZoneState')
    assert decoded.header.frame_id == 'zone_a'
    assert list(decoded.state_names) == ['T_0', 'T_1']
    assert decoded.state_values.tolist() == [294.0, 295.5]
    assert list(decoded.control_names) == ['q_0', 'q_1']
    assert decoded.control_values.tolist() == [12.5, -3.0]
    assert list(decoded.output_names) == ['Tc_0'] and decoded.output_values.tolist() == [20.85]
    assert decoded.history_state_values.tolist() == [293.0, 294.0, 295.0, 295.5]


def test_qos_round_trip_through_the_metadata_form():
    for profile in contract.TOPIC_QOS.values():
        back = qos_from_rosbags(qos_to_rosbags(profile))
        assert back.reliability == profile.reliability
        assert back.durability == profile.durability
    latched = qos_from_rosbags(qos_to_rosbags(contract.LATCHED_QOS))
    assert latched.depth == 1 and latched.durability == DurabilityPolicy.TRANSIENT_LOCAL


def test_sqlite3_bag_of_a_short_run(context, tmp_path):
    bag = tmp_path / 'bag'
    run = run_in_process(context, {
        'emulator': {'hours': 4},
        'forecaster': {'hours': 4, 'use_sim_time': True},
        'mpc': {'use_sim_time': True},
        'recorder': {'bag_path': str(bag), 'storage': 'sqlite3'},
    }, timeout_s=30.0)
    assert bag_metadata(bag)['storage_identifier'] == 'sqlite3'
    assert bag_metadata(bag)['version'] == 9
    contents = read_bag(bag)
    assert contents.counts == run.recorder.counts
    assert contents.counts[contract.SETPOINT] >= 4
    # The message definitions travel with the bag (what `ros2 bag info/play` need).
    db = next(bag.glob('*.db3'))
    with sqlite3.connect(db) as con:
        definitions = dict(con.execute('SELECT topic_type, encoded_message_definition '
                                       'FROM message_definitions'))
    assert 'string[] state_names' in definitions['mshoot_msgs/msg/ZoneState']
    assert 'float64[] plan_controls' in definitions['mshoot_msgs/msg/Setpoint']
    states = read_messages(bag, contract.ZONE_STATE)
    assert [stamp_to_ns(s.header.stamp) for s in states][:5] == sorted(
        {stamp_to_ns(s.header.stamp) for s in states})


def test_recorder_discovers_other_topics_and_replayer_filters(context, tmp_path):
    bag = tmp_path / 'bag'
    talker = rclpy.create_node('talker', context=context)
    chatter = talker.create_publisher(String, '/chatter', QoSProfile(
        depth=5, reliability=ReliabilityPolicy.RELIABLE))
    state = talker.create_publisher(ZoneState, contract.ZONE_STATE, contract.DATA_QOS)
    recorder = RecorderNode(context=context, parameter_overrides=[
        Parameter('bag_path', value=str(bag)),
        Parameter('topics', value=['/chatter', contract.ZONE_STATE])])
    executor = SingleThreadedExecutor(context=context)
    for node in (talker, recorder):
        executor.add_node(node)
    spin_until(executor, lambda: recorder.counts.get('/chatter') is not None)
    spin_until(executor, lambda: talker.count_subscribers('/chatter') > 0)
    for k in range(3):
        chatter.publish(String(data=f'hello {k}'))
        state.publish(zone_state_msg(k * 10 ** 9 + 1, {'T': 293.15 + k}))
    spin_until(executor, lambda: recorder.counts['/chatter'] == 3
               and recorder.counts[contract.ZONE_STATE] == 3)
    recorder.destroy_node()
    contents = read_bag(bag)
    assert contents.topics['/chatter'][0] == 'std_msgs/msg/String'
    assert [m.data for m in read_messages(bag, '/chatter')] == [f'hello {k}' for k in range(3)]

    replayer = ReplayerNode(context=context, parameter_overrides=[
        Parameter('bag_path', value=str(bag)), Parameter('autostart', value=False),
        Parameter('topics', value=['/chatter'])])
    heard = []
    talker.create_subscription(String, '/chatter', lambda m: heard.append(m.data), 10)
    executor.add_node(replayer)
    spin_until(executor, lambda: replayer.count_subscribers('/chatter') > 0)
    assert len(replayer.messages) == 3  # /zone/state filtered out
    replayer.publish_until(2 ** 62)
    spin_until(executor, lambda: len(heard) == 3)
    assert heard == [f'hello {k}' for k in range(3)]
    executor.shutdown()
    for node in (talker, replayer):
        node.destroy_node()
