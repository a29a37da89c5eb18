"""
Recording survives SIGINT, SIGTERM and crashes.

The bag is valid and holds everything received before the signal; a bag cut short is read up to its
last complete chunk.

Four recorder processes (``lib/mshoot_nodes/recorder``, what ``ros2 run`` runs) record
the same topic from this process over DDS on this host; once every message is
acknowledged by all of them, one gets SIGINT, one SIGTERM and two (mcap, sqlite3) are
killed with SIGKILL after their periodic flush.
"""
import os
import pathlib
import shutil
import signal
import subprocess
import time

from mshoot_core.units import NS_PER_S
from mshoot_msgs.msg import ZoneState
from mshoot_nodes import bags, contract
from mshoot_nodes.bags import (IncompleteBagError, read_bag, read_messages, recover_bag,
                               salvage_bag)
from mshoot_nodes.conversions import stamp_to_ns, zone_state_msg
from mshoot_nodes.processes import executable
import pytest
import rclpy
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import Writer

pytestmark = [pytest.mark.ros, pytest.mark.host_discovery]
MESSAGES = 40
RECORDERS = {  # name: (storage, how it ends)
    'sigint': ('mcap', signal.SIGINT),
    'sigterm': ('sqlite3', signal.SIGTERM),
    'crash_mcap': ('mcap', signal.SIGKILL),
    'crash_sqlite3': ('sqlite3', signal.SIGKILL),
}


def _stamps(n):
    return [(1000 + k) * NS_PER_S + k for k in range(n)]


@pytest.fixture(scope='module')
def recordings(tmp_path_factory):
    """Run the four recorders, publish, end each its way; return bag paths and exit codes."""
    out = tmp_path_factory.mktemp('recordings')
    domain = 120 + os.getpid() % 90
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    command = executable('recorder', 'recorder_node')
    assert pathlib.Path(command[0]).name == 'recorder', 'not installed: make setup'
    procs, logs = {}, {}
    for name, (storage, _) in RECORDERS.items():
        logs[name] = out / f'{name}.log'
        procs[name] = subprocess.Popen(
            command + ['--ros-args', '-p', f'bag_path:={out / name}', '-p', f'storage:={storage}',
                       '-p', f'topics:=[{contract.ZONE_STATE}]', '-p', 'flush_period_s:=0.2'],
            env=env, stdout=open(logs[name], 'w'), stderr=subprocess.STDOUT)  # noqa: SIM115
    previous = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE')
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    talker = rclpy.create_node('talker', context=context)
    # Deep enough to keep the whole burst until every recorder has acknowledged it.
    publisher = talker.create_publisher(ZoneState, contract.ZONE_STATE, QoSProfile(
        depth=MESSAGES, reliability=ReliabilityPolicy.RELIABLE))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(talker)
    codes = {}
    try:
        deadline = time.monotonic() + 30.0
        while publisher.get_subscription_count() < len(RECORDERS):
            assert time.monotonic() < deadline, 'the recorders did not subscribe within 30 s'
            executor.spin_once(timeout_sec=0.05)
        for k, stamp in enumerate(_stamps(MESSAGES)):
            publisher.publish(zone_state_msg(stamp, {'T': 290.0 + k * 0.1}, {},
                                             {'q': float(k)}, 'zone'))
        assert publisher.wait_for_all_acked(Duration(seconds=10)), 'not acknowledged'
        # Everything is received (acknowledged) by every recorder: now end them.
        for name in ('crash_mcap', 'crash_sqlite3'):  # after their flush: all on disk
            deadline = time.monotonic() + 10.0
            while len(salvage_bag(out / name).messages) < MESSAGES:
                assert time.monotonic() < deadline, f'{name}: not flushed within 10 s'
                time.sleep(0.05)
        for name, (_, signum) in RECORDERS.items():
            procs[name].send_signal(signum)
        for name, proc in procs.items():
            codes[name] = proc.wait(timeout=15)
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        executor.shutdown()
        talker.destroy_node()
        rclpy.try_shutdown(context=context)
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = previous or 'OFF'
    return out, codes, {name: path.read_text() for name, path in logs.items()}


@pytest.mark.parametrize('name', ['sigint', 'sigterm'])
def test_signal_leaves_a_valid_bag_with_everything_received(recordings, name):
    out, codes, logs = recordings
    assert codes[name] == 0, logs[name]
    assert 'closing the bag' in logs[name]
    assert signal.Signals(RECORDERS[name][1]).name in logs[name]
    contents = read_bag(out / name)
    assert contents.storage == RECORDERS[name][0]
    assert contents.counts == {contract.ZONE_STATE: MESSAGES}
    states = read_messages(out / name, contract.ZONE_STATE)
    assert [stamp_to_ns(s.header.stamp) for s in states] == _stamps(MESSAGES)


@pytest.mark.parametrize('name', ['crash_mcap', 'crash_sqlite3'])
def test_crashed_recording_is_recovered_with_everything_flushed(recordings, name):
    out, codes, logs = recordings
    bag = out / name
    assert codes[name] == -signal.SIGKILL
    with pytest.raises(IncompleteBagError, match='python -m mshoot_nodes.bags recover'):
        read_bag(bag)
    assert bags.main(['recover', str(bag)]) == 0
    contents = read_bag(bag)
    assert contents.storage == RECORDERS[name][0]
    assert contents.counts == {contract.ZONE_STATE: MESSAGES}
    states = read_messages(bag, contract.ZONE_STATE)
    assert [stamp_to_ns(s.header.stamp) for s in states] == _stamps(MESSAGES)
    assert contents.topics[contract.ZONE_STATE][1][0].reliability.name == 'RELIABLE'
    assert list(bag.glob('*.damaged'))
    with pytest.raises(ValueError, match='nothing to recover'):
        recover_bag(bag)


def test_bag_cut_in_a_chunk_is_read_up_to_its_last_complete_chunk(tmp_path):
    """A crash in the middle of writing a chunk: the complete chunks are recovered."""
    bag = tmp_path / 'bag'
    store = bags.typestore()
    writer = Writer(bag, version=9, storage_plugin=bags.STORAGES['mcap'])
    writer.open()
    connection = writer.add_connection(contract.ZONE_STATE, contract.TOPIC_TYPES[
        contract.ZONE_STATE], typestore=store, offered_qos_profiles=[
            bags.qos_to_rosbags(contract.DATA_QOS)])
    from rclpy.serialization import serialize_message
    stamps = _stamps(30)
    sizes = []
    for batch in (stamps[:10], stamps[10:20], stamps[20:]):
        for stamp in batch:
            writer.write(connection, stamp, serialize_message(zone_state_msg(stamp, {'T': 293.0})))
        bags.flush_writer(writer)
        sizes.append((bag / 'bag.mcap').stat().st_size)
    data = (bag / 'bag.mcap').read_bytes()
    writer.storage.bio.close()  # the process dies: no summary, no metadata.yaml
    cut = (sizes[1] + sizes[2]) // 2  # in the middle of the third chunk
    (bag / 'bag.mcap').write_bytes(data[:cut])
    salvage = salvage_bag(bag)
    assert salvage.complete_chunks == 2 and salvage.lost_bytes > 0
    copy = tmp_path / 'copy'
    shutil.copytree(bag, copy)
    recovered = recover_bag(copy)
    assert len(recovered.messages) == 20
    states = read_messages(copy, contract.ZONE_STATE)
    assert [stamp_to_ns(s.header.stamp) for s in states] == stamps[:20]
